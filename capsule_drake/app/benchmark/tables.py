"""The suite's tables: completion with its Wilson interval, the breakdown by patient group,
the segments, and the files a suite writes."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from capsule_drake.anatomy.lesions import SIZE_CLASSES
from capsule_drake.app.benchmark.task import COLUMN_DOCS, COLUMNS, Task, failed_result


def _json_default(value):
    """numpy scalars and arrays in results as plain JSON."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


def wilson_interval(successes: int, runs: int, z: float = 1.959964) -> tuple[float, float]:
    """The Wilson score interval (95 % by default) of a rate of successes in runs: unlike
    the normal approximation it stays inside [0, 1] and is not empty at 0/n or n/n."""
    if runs == 0:
        return 0.0, 1.0
    p = successes / runs
    centre = (p + z * z / (2 * runs)) / (1 + z * z / runs)
    half = z / (1 + z * z / runs) * np.sqrt(p * (1 - p) / runs + z * z / (4 * runs * runs))
    return max(0.0, centre - half), min(1.0, centre + half)


def summary(results: list[dict], by: str = "navigator") -> list[dict]:
    """Per navigator (or per value of another column `by`, as the results pages group a
    sweep): runs, cecal intubation rate with its 95 % Wilson interval, mean time to cecum
    (of those that reached it), mean progress, and the means of the other columns; for the
    localisation errors, the worst run's too."""
    out = []
    for navigator in dict.fromkeys(r["row"][by] for r in results):
        rows = [r["row"] for r in results if r["row"][by] == navigator]

        def finite(key):
            values = np.array([row.get(key, np.nan) for row in rows], dtype=float)
            return values[np.isfinite(values)]

        def mean(key):
            values = finite(key)
            return round(float(values.mean()), 3) if len(values) else np.nan

        def worst(key):
            values = finite(key)
            return round(float(values.max()), 3) if len(values) else np.nan

        out.append({by: navigator, "runs": len(rows),
                    "reached_cecum": f"{sum(row['reached_cecum'] for row in rows)}/{len(rows)}",
                    "cecum_95ci": "[{:.2f}, {:.2f}]".format(*wilson_interval(
                        sum(bool(row["reached_cecum"]) for row in rows), len(rows))),
                    "colon_cm": mean("colon_cm"),
                    "time_to_cecum_s": mean("time_to_cecum_s"), "progress": mean("progress"),
                    "wall_contact_s": mean("wall_contact_s"),
                    "peak_contact_force_N": mean("peak_contact_force_N"),
                    "peak_contact_pressure_kPa": mean("peak_contact_pressure_kPa"),
                    "injury_pressure_s": mean("injury_pressure_s"),
                    "site_peak_pressure_kPa": mean("site_peak_pressure_kPa"),
                    "site_injury_s": mean("site_injury_s"),
                    "site_ischaemia_s": mean("site_ischaemia_s"),
                    "centring_error_deg": mean("centring_error_deg"),
                    "detection_error_pct": mean("detection_error_pct"),
                    "detection_rate": mean("detection_rate"),
                    "detection_fp_rate": mean("detection_fp_rate"),
                    **{f"{key}{suffix}": how(key)
                       for key in ("loc_pos_err_median_mm", "loc_pos_err_p95_mm",
                                   "loc_rot_err_median_deg")
                       for suffix, how in (("", mean), ("_worst", worst))},
                    "epm_path_m": mean("epm_path_m"), "coverage": mean("coverage"),
                    **{f"seen_{size_class}": _seen(rows, size_class)
                       for size_class in SIZE_CLASSES},
                    "seen_diverticula": _seen(rows, "diverticula"),
                    "polyp_sensitivity": _sensitivity(rows),
                    "polyp_fp_per_min": mean("polyp_fp_per_min")})
    return out


def _mean_doc(key: str, how: str = "mean") -> str:
    return f"{how}, over the navigator's runs with a value (NaN left out), of {key}: " + (
        COLUMN_DOCS[key])


SUMMARY_COLUMN_DOCS = {
    "navigator": COLUMN_DOCS["navigator"],
    "runs": "the navigator's runs, failed ones included (count)",
    "reached_cecum": "\"reached/runs\": the runs that reached the cecum (text)",
    "cecum_95ci": "the 95 % Wilson score interval of the cecal intubation rate "
                  "(`wilson_interval`), \"[low, high]\" (1)",
    **{key: _mean_doc(key) for key in (
        "colon_cm", "time_to_cecum_s", "progress", "wall_contact_s", "peak_contact_force_N",
        "peak_contact_pressure_kPa", "injury_pressure_s", "site_peak_pressure_kPa",
        "site_injury_s", "site_ischaemia_s", "centring_error_deg", "detection_error_pct",
        "detection_rate", "detection_fp_rate")},
    **{key + suffix: _mean_doc(key, how)
       for key in ("loc_pos_err_median_mm", "loc_pos_err_p95_mm", "loc_rot_err_median_deg")
       for suffix, how in (("", "mean"), ("_worst", "largest"))},
    "epm_path_m": _mean_doc("epm_path_m"),
    "coverage": _mean_doc("coverage"),
    **{f"seen_{size_class}": f"\"seen/present\" {size_class} polyps over the runs that "
       "counted them (a camera); \"-\" if none had one (text)" for size_class in SIZE_CLASSES},
    "seen_diverticula": "\"seen/present\" diverticula over the runs that counted them; "
                        "\"-\" if none had one (text)",
    "polyp_sensitivity": "\"detected/seen\" polyps over the runs that scored a polyp "
                         "detector; \"-\" without one (text)",
    "polyp_fp_per_min": _mean_doc("polyp_fp_per_min"),
}
"""What each column of summary.csv (`summary`) is, ending in its unit in parentheses."""


def _sensitivity(rows) -> str:
    """"detected/seen" polyps over the runs that scored a polyp detector ("-": none)."""
    scored = [row for row in rows if np.isfinite(float(row.get("polyps_detected", np.nan)))]
    seen = sum(int(row[f"seen_{c}"]) for row in scored for c in SIZE_CLASSES
               if np.isfinite(float(row[f"seen_{c}"])))
    if not scored:
        return "-"
    return f"{sum(int(row['polyps_detected']) for row in scored)}/{seen}"


def _seen(rows, size_class: str) -> str:
    """"seen/present" polyps of a size class (or "diverticula") over the runs that counted
    them ("-": none)."""
    counted = [row for row in rows
               if np.isfinite(float(row.get(f"seen_{size_class}", np.nan)))]
    present = sum(int(row[f"polyps_{size_class}" if size_class in SIZE_CLASSES
                          else size_class]) for row in counted)
    if not present:
        return "-"
    return f"{sum(int(row[f'seen_{size_class}']) for row in counted)}/{present}"


_summary_columns = set(summary([failed_result(Task("check", 0), "")])[0])
if _summary_columns != set(SUMMARY_COLUMN_DOCS):
    raise RuntimeError("summary columns without a SUMMARY_COLUMN_DOCS entry, or entries "
                       f"without a column: {sorted(_summary_columns ^ set(SUMMARY_COLUMN_DOCS))}")


def breakdown(results: list[dict]) -> list[dict]:
    """Per navigator, the cecal intubation rate (with its Wilson interval) and the mean time
    to the cecum of each group of the population's patients: by sigmoid variant, by sex and
    by tercile of the colon's length (the terciles of the runs' own colons). Empty when no
    run's colon was drawn from the population (its `patient` is "")."""
    rows = [r["row"] for r in results]

    def patient(row) -> str:   # a failed run's row has no patient (NaN)
        value = row.get("patient")
        return value if isinstance(value, str) else ""

    if not any(patient(row) for row in rows):
        return []
    lengths = np.array([row.get("colon_cm", np.nan) for row in rows], dtype=float)
    cuts = np.nanquantile(lengths, [1 / 3, 2 / 3])
    groups = {
        "all": lambda row: True,
        "normal sigmoid": lambda row: "normal sigmoid" in patient(row),
        "redundant sigmoid": lambda row: "redundant sigmoid" in patient(row),
        "female": lambda row: patient(row).startswith("female"),
        "male": lambda row: patient(row).startswith("male"),
        f"length < {cuts[0]:.0f} cm": lambda row: row.get("colon_cm", np.nan) < cuts[0],
        f"length {cuts[0]:.0f}-{cuts[1]:.0f} cm":
            lambda row: cuts[0] <= row.get("colon_cm", np.nan) < cuts[1],
        f"length >= {cuts[1]:.0f} cm": lambda row: row.get("colon_cm", np.nan) >= cuts[1],
    }
    out = []
    for navigator in dict.fromkeys(row["navigator"] for row in rows):
        mine = [row for row in rows if row["navigator"] == navigator]
        for group, member in groups.items():
            chosen = [row for row in mine if member(row)]
            if not chosen:
                continue
            reached = sum(bool(row["reached_cecum"]) for row in chosen)
            times = np.array([row.get("time_to_cecum_s", np.nan) for row in chosen],
                             dtype=float)
            times = times[np.isfinite(times)]
            out.append({"navigator": navigator, "group": group,
                        "reached_cecum": f"{reached}/{len(chosen)}",
                        "cecum_95ci": "[{:.2f}, {:.2f}]".format(
                            *wilson_interval(reached, len(chosen))),
                        "time_to_cecum_s": round(float(times.mean()), 1) if len(times)
                        else np.nan})
    return out


def segment_table(results: list[dict]) -> list[dict]:
    """Per navigator, the share of runs that got through each colon segment."""
    names = _segment_names(results)
    out = []
    for navigator in dict.fromkeys(r["row"]["navigator"] for r in results):
        rows = [r["row"] for r in results if r["row"]["navigator"] == navigator]
        out.append({"navigator": navigator, **{
            name: f"{sum(name in row['segments_passed'] for row in rows)}/{len(rows)}"
            for name in names}})
    return out


def _segment_names(results: list[dict]) -> list[str]:
    """The colon's segments, from the first run that finished (a failed run has none)."""
    return next((list(r["segments"]) for r in results if r.get("segments")), [])


def format_table(rows: list[dict], columns) -> str:
    cells = [[str(row.get(c, "")) for c in columns] for row in rows]
    widths = [max(len(c), *(len(r[k]) for r in cells)) for k, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths))]
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths)) for r in cells]
    return "\n".join(lines)


def write_outputs(results: list[dict], out_dir: Path) -> dict[str, Path]:
    """runs.csv (one row per run), summary.csv, progress.png (progress against time) and
    segments.png (share of runs through each colon segment, per navigator)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"runs": out_dir / "runs.csv", "summary": out_dir / "summary.csv",
             "progress": out_dir / "progress.png", "segments": out_dir / "segments.png",
             "results": out_dir / "results.json"}
    # Everything the table and plots are made from (rows, progress curves, segments), so
    # they can be redrawn or analysed further without rerunning the suite.
    with open(paths["results"], "w") as f:
        json.dump(results, f, default=_json_default)
    with open(paths["runs"], "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for r in results:
            writer.writerow(r["row"])
    rows = summary(results)
    with open(paths["summary"], "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    groups = breakdown(results)
    if groups:
        paths["breakdown"] = out_dir / "breakdown.csv"
        with open(paths["breakdown"], "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(groups[0]))
            writer.writeheader()
            writer.writerows(groups)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    navigators = list(dict.fromkeys(r["row"]["navigator"] for r in results))
    colours = {n: plt.cm.tab10(k % 10) for k, n in enumerate(navigators)}
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for r in results:
        t, s = r["curve"]
        navigator = r["row"]["navigator"]
        ax.plot(t, 100.0 * np.asarray(s), color=colours[navigator], lw=1.0, alpha=0.8)
    for n in navigators:
        ax.plot([], [], color=colours[n], label=n)
    ax.set_xlabel("simulated time (s)")
    ax.set_ylabel("centreline station of the capsule (cm)")
    ax.set_title("progress toward the cecum, one line per run")
    ax.legend(loc="upper left", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(paths["progress"], dpi=120)
    plt.close(fig)
    names = _segment_names(results)
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / max(len(navigators), 1)
    for k, n in enumerate(navigators):
        rows = [r["row"] for r in results if r["row"]["navigator"] == n]
        share = [np.mean([name in row["segments_passed"] for row in rows]) for name in names]
        ax.bar(np.arange(len(names)) + k * width, share, width, color=colours[n], label=n)
    ax.set_xticks(np.arange(len(names)) + 0.4 - width / 2, names, rotation=20, fontsize=8)
    ax.set_ylabel("share of runs through the segment")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(paths["segments"], dpi=120)
    plt.close(fig)
    return paths


def report(results, out_dir) -> None:
    """The benchmark's tables on stdout and its files in `out_dir` (`write_outputs`)."""
    if not results:
        print(f"no run finished; wrote {out_dir / 'runs-as-finished.csv'}")
        return
    print(format_table([r["row"] for r in results], [c for c in COLUMNS]))
    print()
    rows = summary(results)
    print(format_table(rows, list(rows[0])))
    print()
    rows = segment_table(results)
    print("runs through each segment:")
    print(format_table(rows, list(rows[0])))
    rows = breakdown(results)
    if rows:
        print("\nby the population's patients (sigmoid variant, sex, tercile of length):")
        print(format_table(rows, list(rows[0])))
    paths = write_outputs(results, out_dir)
    print(f"\nwrote {', '.join(str(p) for p in paths.values())}")
