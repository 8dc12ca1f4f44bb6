"""The README's population-tier tables from benchmark runs, finished or still going.

    .venv/bin/python benchmarks/population_tables.py RUNS.csv [RUNS.csv ...]

Reads each `runs.csv` or `runs-as-finished.csv` that `capsule-sim benchmark` wrote (the
latter is appended run by run, so a suite still going can be tabled) and prints, as
Markdown, per navigator: the cecal intubation rate with its 95 % Wilson interval, the mean
time to the cecum, the mean speed to it (the centreline's length over the time, runs that
reached it), wall contact, peak contact force and pressure, the wall's per-site figures
(the highest pressure one patch of mucosa felt, the longest one patch spent above 4 kPa and
above 330 kPa; runs whose contact model has them), and coverage; then the
breakdown by sigmoid variant, sex and tercile of the colon's length (app/benchmark/tables.py
`breakdown`), and the runs that did not reach the cecum with where they stopped.
"""

import argparse
import csv
from pathlib import Path

import numpy as np

from capsule_drake.app.benchmark import breakdown, wilson_interval

NUMBERS = ("colon_cm", "time_to_cecum_s", "progress", "progress_cm", "wall_contact_s",
           "peak_contact_force_N", "peak_contact_pressure_kPa", "coverage", "sim_time_s",
           "site_peak_pressure_kPa", "site_injury_s", "site_ischaemia_s")


def read_rows(paths):
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


def markdown(rows, columns) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(str(row[c]) for c in columns) + " |" for row in rows]
    return "\n".join(lines)


def speed(rows) -> str:
    """Mean speed (mm/s) to the cecum of the runs that reached it: the way along the
    centreline over the time it took."""
    values = [10.0 * row["progress_cm"] / row["time_to_cecum_s"] for row in rows
              if row["reached_cecum"] and row["time_to_cecum_s"] > 0]
    return f"{np.mean(values):.1f}" if values else "-"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    rows = read_rows(parser.parse_args().runs)
    table = []
    for navigator in dict.fromkeys(row["navigator"] for row in rows):
        mine = [row for row in rows if row["navigator"] == navigator]
        reached = sum(row["reached_cecum"] for row in mine)
        low, high = wilson_interval(reached, len(mine))

        def mean(key, rows_=mine):
            values = np.array([row[key] for row in rows_], dtype=float)
            values = values[np.isfinite(values)]
            return f"{values.mean():.1f}" if len(values) else "-"

        table.append({"navigator": navigator, "runs": len(mine),
                      "cecum": f"{reached}/{len(mine)}", "95 % interval": f"{low:.2f}-{high:.2f}",
                      "time to cecum (s)": mean("time_to_cecum_s"),
                      "speed (mm/s)": speed(mine),
                      "wall contact (s)": mean("wall_contact_s"),
                      "peak force (N)": f"{np.nanmean([r['peak_contact_force_N'] for r in mine]):.3f}",
                      "peak pressure (kPa)": mean("peak_contact_pressure_kPa"),
                      "site peak (kPa)": mean("site_peak_pressure_kPa"),
                      "site > 4 kPa (s)": mean("site_ischaemia_s"),
                      "site > 330 kPa (s)": mean("site_injury_s"),
                      "coverage": f"{np.nanmean([r['coverage'] for r in mine]):.2f}"})
    print(markdown(table, list(table[0])))
    print()
    groups = breakdown([{"row": row} for row in rows])
    print(markdown(groups, list(groups[0])) if groups else "(no population patients)")
    print()
    for row in rows:
        if not row["reached_cecum"]:
            print(f"- {row['navigator']} seed {row['seed']} ({row['colon_cm']:.0f} cm, "
                  f"{row['patient']}): {row['progress_cm']:.0f} cm in, {row['stuck_in']}")


if __name__ == "__main__":
    main()
