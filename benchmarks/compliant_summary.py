"""The compliant wall's consequences for navigation in one table (the README's, and the
summary of docs/results/navigation.md, "On the compliant wall"), from the benchmark's result
files.

    .venv/bin/python benchmarks/compliant_summary.py

Per tier, tissue and navigator, the results pages' summary (result_tables.summary: the cecal
intubation rate with its 95 % Wilson interval, the mean time to the cecum and speed to it
over the runs that arrive, the mean wall-contact time and per-site peak pressure), then the
highest per-site peak of any run, the longest any run kept one patch of mucosa above 4 kPa, and the rigid stand-in's rate on the
same seeds (typed: those runs were not kept as result files; docs/results/navigation.md
gives their dates and tables). Runs that did not finish (crashed, timed out) are left out.
The standard tier ran before the followers' lift was fixed at 0.9 (on those seeds, with
autonomy-truth, in 300 s runs); the population tier and the corners ran with it.
"""

from pathlib import Path

import numpy as np

from capsule_drake.app.benchmark.result_tables import markdown, read_rows, summary

RESULTS = Path(__file__).resolve().parent / "results"
STANDARD = "compliant_standard_2026-11-29.csv"
POPULATION = "population (30 patients), nominal"
TEAM = "population's first 8, nominal"
BEFORE = "standard (seeds 0-9), nominal, lift 1.0 (before the lift)"
# (tier and tissue, navigator, result file, (column, value) the rows kept (None: all), the
# rigid stand-in's rate)
GROUPS = (
    (BEFORE, "autonomy-truth", STANDARD, None, "10/10"),
    (BEFORE, "autonomy-detected", STANDARD, None, "10/10"),
    (BEFORE, "autonomy-sensors", STANDARD, None, "10/10"),
    ("standard, nominal, lift 0.9 (chosen here; 300 s runs)", "autonomy-truth",
     "compliant_lift_sweep_2026-11-29.csv", ("lift", "0.9"), "10/10"),
    (POPULATION, "autonomy-truth", "compliant_population_truth_lift09_2026-11-29.csv", None,
     "27/30"),
    (POPULATION, "autonomy-detected", "compliant_population_detected_lift09_2026-11-29.csv",
     None, "30/30"),
    (POPULATION, "autonomy-sensors", "compliant_population_sensors_lift09_2026-11-30.csv",
     None, "-"),
    ("population, soft and slippery corner", "autonomy-sensors",
     "compliant_population_sensors_soft_stiffened_partial_2026-11-30.csv",
     ("tissue", "soft_slippery"), "-"),
    ("population, stiff and sticky corner", "autonomy-sensors",
     "compliant_population_sensors_corners_partial_2026-11-30.csv", ("tissue", "stiff_sticky"),
     "-"),
    (TEAM, "teleop-guided", "compliant_population_teleop_2026-11-30.csv", None, "0/8"),
    (TEAM, "teleop-unguided", "compliant_population_teleop_2026-11-30.csv", None, "0/8"),
)


# The results pages' summary columns (result_tables.summary) shown here, then this table's own.
SHOWN = ("cecum", "95 % interval", "time to cecum (s)", "speed (mm/s)", "wall contact (s)",
         "site peak (kPa)")
COLUMNS = ("tier and tissue", "navigator") + SHOWN + (
    "highest site peak (kPa)", "longest on one patch > 4 kPa, most of any run (s)",
    "rigid stand-in's cecum")


def row(tier: str, navigator: str, name: str, kept, rigid: str) -> dict:
    rows = [r for r in read_rows([RESULTS / name]) if r["navigator"] == navigator
            and (kept is None or r[kept[0]] == kept[1])]
    shown, = summary(rows)
    return {"tier and tissue": tier, "navigator": navigator,
            **{column: shown[column] for column in SHOWN},
            "highest site peak (kPa)": f"{np.nanmax([r['site_peak_pressure_kPa'] for r in rows]):.0f}",
            "longest on one patch > 4 kPa, most of any run (s)":
                f"{np.nanmax([r['site_ischaemia_s'] for r in rows]):.0f}",
            "rigid stand-in's cecum": rigid}


def main():
    print(markdown([row(*group) for group in GROUPS], COLUMNS))


if __name__ == "__main__":
    main()
