"""The results pages' navigation tables, made from the benchmark's result files.

A results page names the files a table comes from, and the documentation build
(scripts/docs_hooks.py) puts the table there, so no figure of these tables is typed:

    <!-- results-table: benchmarks/results/compliant_standard_2026-11-29.csv -->
    <!-- results-stops: benchmarks/results/compliant_standard_2026-11-29.csv -->

Options after the files: `by=COLUMN` groups the rows by another column of the files than
the navigator (`by=lift`, `by=tissue`); `where=COLUMN:VALUE` keeps the rows whose column
holds that value; `label="TEXT"` adds a first column saying what the runs were (a wall, a
setting), for a table set beside another.

`results-table` is the summary per navigator (the cecal intubation rate with its 95 % Wilson
interval, the mean time to the cecum and speed to it, wall contact, peak force and pressure,
the wall's per-site figures, coverage); `results-stops` the runs that did not reach the
cecum and where they stopped; `results-breakdown` the population's groups (sigmoid variant,
sex, tercile of the colon's length). The files are `runs.csv` or `runs-as-finished.csv` of
`capsule-sim benchmark` (the latter is appended run by run, so a suite still going can be
tabled); rows whose run did not finish are left out. `benchmarks/population_tables.py`
prints the same from the command line.
"""

from __future__ import annotations

import csv
import re
import shlex
from pathlib import Path

import numpy as np

from capsule_drake.app.benchmark.tables import breakdown, wilson_interval
from capsule_drake.app.benchmark.tables import summary as tables_summary

NUMBERS = ("colon_cm", "time_to_cecum_s", "progress", "progress_cm", "wall_contact_s",
           "peak_contact_force_N", "peak_contact_pressure_kPa", "coverage", "sim_time_s",
           "site_peak_pressure_kPa", "site_injury_s", "site_ischaemia_s")

MARKER = re.compile(r"^<!-- results-(table|stops|breakdown): (.+?) -->$")
"""A results page's line naming the result files a table is made from."""


def read_rows(paths) -> list[dict]:
    """The finished runs of benchmark result files, numbers as floats (blank: NaN)."""
    rows = []
    for path in paths:
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                if row.get("status") != "finished":
                    continue
                for key in NUMBERS:
                    row[key] = float(row[key]) if row.get(key) not in (None, "") else np.nan
                row["reached_cecum"] = row["reached_cecum"] == "True"
                row["seed"] = int(row["seed"])
                rows.append(row)
    return rows


def markdown(rows: list[dict], columns) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(str(row.get(c, "")) for c in columns) + " |" for row in rows]
    return "\n".join(lines)


def _speed(rows) -> str:
    """Mean speed (mm/s) to the cecum of the runs that reached it: the way along the
    centreline over the time it took."""
    values = [10.0 * row["progress_cm"] / row["time_to_cecum_s"] for row in rows
              if row["reached_cecum"] and row["time_to_cecum_s"] > 0]
    return f"{np.mean(values):.1f}" if values else "-"


# The page's columns: its heading, the benchmark summary's column, the digits shown.
SHOWN = (("time to cecum (s)", "time_to_cecum_s", 1), ("wall contact (s)", "wall_contact_s", 1),
         ("peak force (N)", "peak_contact_force_N", 3),
         ("peak pressure (kPa)", "peak_contact_pressure_kPa", 1),
         ("site peak (kPa)", "site_peak_pressure_kPa", 1),
         ("site > 4 kPa (s)", "site_ischaemia_s", 1), ("site > 330 kPa (s)", "site_injury_s", 1),
         ("coverage", "coverage", 2))


def summary(rows: list[dict], by: str = "navigator", label: str | None = None) -> list[dict]:
    """The benchmark's summary (tables.summary), one row per value of the column `by` (the
    navigator), shown as the results pages show it; `label`: a first column saying what the
    runs were."""
    table = []
    for group in tables_summary([{"row": row} for row in rows], by):
        mine = [row for row in rows if row[by] == group[by]]
        low, high = wilson_interval(sum(row["reached_cecum"] for row in mine), len(mine))
        shown = {"runs of": label} if label is not None else {}
        shown.update({by: group[by], "runs": group["runs"], "cecum": group["reached_cecum"],
                      "95 % interval": f"{low:.2f}-{high:.2f}"})
        for heading, key, digits in SHOWN:
            value = group[key]
            shown[heading] = "-" if np.isnan(value) else f"{value:.{digits}f}"
            if key == "time_to_cecum_s":
                shown["speed (mm/s)"] = _speed(mine)
        if np.isfinite(group["loc_pos_err_p95_mm"]):   # a navigator localising the capsule
            shown["localiser p95 (mm)"] = f"{group['loc_pos_err_p95_mm']:.1f}"
        table.append(shown)
    return table


def stops(rows: list[dict], by: str = "navigator") -> list[str]:
    """A line per run that did not reach the cecum: where it stopped."""
    lines = []
    for row in rows:
        if row["reached_cecum"]:
            continue
        patient = f", {row['patient']}" if row.get("patient") else ""
        patient += f", {by} {row[by]}" if by != "navigator" else ""
        where = (f"{row['progress_cm']:.0f} cm in, {row['stuck_in']}"
                 if np.isfinite(row["progress_cm"]) else row["stuck_in"])
        lines.append(f"- {row['navigator']} seed {row['seed']} ({row['colon_cm']:.0f} cm"
                     f"{patient}): {where}")
    return lines


def parse(arguments: str) -> tuple[list[str], dict[str, str]]:
    """A marker's files and options (`by=lift label="soft wall"`)."""
    files, options = [], {}
    for token in shlex.split(arguments):
        key, equals, value = token.partition("=")
        if equals:
            if key not in ("by", "label", "where"):
                raise ValueError(f"results marker: unknown option {key!r} (by, label, where)")
            options[key] = value
        else:
            files.append(token)
    return files, options


def block(kind: str, arguments: str, root: Path = Path(".")) -> str:
    """The Markdown of a marker: `kind` is table, stops or breakdown; `arguments` its files
    and options."""
    paths, options = parse(arguments)
    rows = read_rows([root / p for p in paths])
    if not rows:
        raise ValueError(f"no finished runs in {' '.join(map(str, paths))}")
    by = options.get("by", "navigator")
    column, _, value = options.get("where", "").partition(":")
    for name in (by, column) if column else (by,):
        if any(name not in row for row in rows):
            raise ValueError(f"results marker: no column {name!r} in {' '.join(paths)}")
    if column:
        rows = [row for row in rows if row[column] == value]
        if not rows:
            raise ValueError(f"results marker: no finished run with {column} {value!r}")
    if kind == "table":
        table = summary(rows, by, options.get("label"))
        return markdown(table, list(dict.fromkeys(k for row in table for k in row)))
    if kind == "stops":
        return "\n".join(stops(rows, by)) or "(every run reached the cecum)"
    groups = breakdown([{"row": row} for row in rows])
    return markdown(groups, list(groups[0])) if groups else "(no population patients)"


def expand(text: str, root: Path = Path(".")) -> str:
    """`text` with the table, list or breakdown made from its files after each marker (a
    block already there, typed or made before, is replaced)."""
    lines, out, k = text.splitlines(), [], 0
    while k < len(lines):
        match = MARKER.match(lines[k].strip())
        out.append(lines[k])
        k += 1
        if not match:
            continue
        while k < len(lines) and lines[k].startswith(("|", "- ")):
            k += 1
        out += ["", block(match.group(1), match.group(2), root), ""]
    return "\n".join(out) + ("\n" if text.endswith("\n") else "")
