"""The compliant wall's consequences for navigation in one table (the README's, and the
summary of docs/results/navigation.md, "On the compliant wall"), from the benchmark's result
files.

    .venv/bin/python benchmarks/compliant_summary.py

Per tier, tissue and navigator: the cecal intubation rate with its 95 % Wilson interval, the
mean time to the cecum and speed to it over the runs that arrive, the mean wall-contact time,
the wall's per-site peak pressure (mean over the runs, and the highest of any run), the
longest any run kept one patch of mucosa above 4 kPa, and the rigid stand-in's rate on the
same seeds (typed: those runs were not kept as result files; docs/results/navigation.md
gives their dates and tables). Runs that did not finish (crashed, timed out) are left out.
The standard tier ran before the followers' lift was fixed at 0.9 (on those seeds, with
autonomy-truth, in 300 s runs); the population tier and the corners ran with it.
"""

from pathlib import Path

import numpy as np

from capsule_drake.app.benchmark.result_tables import read_rows
from capsule_drake.app.benchmark.tables import wilson_interval

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


def figure(value: float, digits: int = 1) -> str:
    return "-" if not np.isfinite(value) else f"{value:.{digits}f}"


def row(tier: str, navigator: str, name: str, kept, rigid: str) -> str:
    rows = [r for r in read_rows([RESULTS / name]) if r["navigator"] == navigator
            and (kept is None or r[kept[0]] == kept[1])]
    arrived = [r for r in rows if r["reached_cecum"]]
    low, high = wilson_interval(len(arrived), len(rows))
    time = np.mean([r["time_to_cecum_s"] for r in arrived]) if arrived else np.nan
    speed = (np.mean([10.0 * r["progress_cm"] / r["time_to_cecum_s"] for r in arrived])
             if arrived else np.nan)
    contact = np.nanmean([r["wall_contact_s"] for r in rows])
    peaks = [r["site_peak_pressure_kPa"] for r in rows]
    longest = np.nanmax([r["site_ischaemia_s"] for r in rows])
    return (f"| {tier} | {navigator} | {len(arrived)}/{len(rows)} | {low:.2f}-{high:.2f} | "
            f"{figure(time)} | {figure(speed)} | {figure(contact)} | "
            f"{figure(np.nanmean(peaks), 0)} / {figure(np.nanmax(peaks), 0)} | "
            f"{figure(longest, 0)} | {rigid} |")


def main():
    print("| tier and tissue | navigator | cecum | 95 % interval | time to cecum (s) | "
          "speed (mm/s) | wall contact (s) | site peak, mean / highest (kPa) | longest on "
          "one patch > 4 kPa, most of any run (s) | rigid stand-in's cecum |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for group in GROUPS:
        print(row(*group))


if __name__ == "__main__":
    main()
