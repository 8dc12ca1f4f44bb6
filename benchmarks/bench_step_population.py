"""The plant step over a population: a navigation scenario on several colons at several steps.

    .venv/bin/python benchmarks/bench_step_population.py [--scenario Navigation]
        [--seeds 0-9] [--steps 1,2,5] [--duration 120] [--csv PATH] [--summary CSV ...]

A navigation run is chaotic: a millimetre or a millisecond changes where the capsule lands
after it breaks free, so two steps are not compared run by run (bench_step_convergence.py
does that for the Default drag, which is not) but as populations: each colon seed at each
plant step (ms), the scenario's step bound bypassed as bench_step_convergence.py does. One
row per run (printed as it ends, and to --csv): status, advance along the colon (cm), the
highest pressure on one site of the wall (kPa, the compliant wall's `site_peak_pressure`),
the largest excursion beyond the undeformed wall (mm), CPU seconds. Then per step: runs
completed, the medians of the completed runs' advance and site peak, the largest
excursion, and the median CPU seconds. `--summary A.csv B.csv ...` prints that table
from rows written before (runs made in several processes), running nothing.

`--bristles-at MS` holds the friction's bristles at the stiffness they have at a step of MS
ms whatever the step (foundation.TANGENTIAL_TURN scaled by step / MS in this process): the
bristles' stiffness is a regularisation set per step, and this tells its share of the
step's effect from the rest.
"""

import argparse
import csv
import json
import math
import platform
import statistics
import sys
import time

from population_flexures import seeds_of   # (this folder: "0-9" or "0,2,4")

FIELDS = ["seed", "step_ms", "status", "advance_cm", "site_peak_kPa", "excursion_mm",
          "cpu_s", "stopped"]


def run(scenario_name: str, seed: int, step_ms: float, duration: float,
        turn: float | None = None) -> dict:
    """One run; `turn`: foundation.TANGENTIAL_TURN for it (None: as shipped)."""
    from capsule_drake.app.run import simulate
    from capsule_drake.physics.contact import foundation
    from capsule_drake.scenario import load_scenario

    if turn is not None:
        foundation.TANGENTIAL_TURN = turn

    scenario = load_scenario(name=scenario_name,
                             override=f"{{colon: {{seed: {seed}}}, duration: {duration!r}}}")
    scenario.plant.time_step = 1e-3 * step_ms   # past the step bound, as intended here
    cpu = time.process_time()
    result = simulate(scenario, progress=False)
    m = result.metrics

    def number(key, scale):
        value = m.get(key)
        return round(scale * value, 2) if value is not None else math.nan

    return {"seed": seed, "step_ms": step_ms, "status": result.status,
            "advance_cm": number("advance_m", 100.0),
            "site_peak_kPa": number("site_peak_pressure_kPa", 1.0),
            "excursion_mm": number("max_wall_excursion_m", 1000.0),
            "cpu_s": round(time.process_time() - cpu, 1),
            "stopped": m.get("stopped_early") or ""}


def summary(rows: list[dict]) -> str:
    lines = ["| step (ms) | completed | advance median (cm) | site peak median (kPa) "
             "| largest excursion (mm) | CPU s per run (median) |",
             "|---|---|---|---|---|---|"]
    for step in sorted({float(r["step_ms"]) for r in rows}):
        these = [r for r in rows if float(r["step_ms"]) == step]
        done = [r for r in these if r["status"] == "completed"]

        def median(key):
            values = [float(r[key]) for r in done if not math.isnan(float(r[key]))]
            return f"{statistics.median(values):.1f}" if values else "-"

        excursion = max((float(r["excursion_mm"]) for r in done), default=None)
        cpu = statistics.median(float(r["cpu_s"]) for r in these)
        lines.append(f"| {step:g} | {len(done)} of {len(these)} | {median('advance_cm')} | "
                     f"{median('site_peak_kPa')} | "
                     f"{'-' if excursion is None else f'{excursion:.2f}'} | {cpu:.0f} |")
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="Navigation")
    parser.add_argument("--seeds", default="0-9", help="colon seeds: 0-9 or 0,2,4")
    parser.add_argument("--steps", default="1,2,5", help="plant steps (ms), comma separated")
    parser.add_argument("--duration", type=float, default=120.0)
    parser.add_argument("--csv", help="write the rows here")
    parser.add_argument("--bristles-at", type=float, metavar="MS",
                        help="the bristles' stiffness of an MS ms step at every step")
    parser.add_argument("--summary", nargs="+", metavar="CSV",
                        help="print the table of rows written before; run nothing")
    args = parser.parse_args()
    if args.summary:
        rows = []
        for path in args.summary:
            with open(path, newline="") as f:
                rows += list(csv.DictReader(f))
        print(summary(rows))
        return
    from capsule_drake.physics.contact import foundation
    shipped = foundation.TANGENTIAL_TURN   # omega = turn / step: the same omega at every step
    rows = []
    for seed in seeds_of(args.seeds):
        for step in (float(s) for s in args.steps.split(",")):
            turn = shipped * step / args.bristles_at if args.bristles_at else None
            rows.append(run(args.scenario, seed, step, args.duration, turn))
            print(json.dumps(rows[-1]), flush=True)
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=FIELDS)
            writer.writeheader()
            writer.writerows(rows)
    print(f"machine: {platform.machine()}, Python {platform.python_version()}; "
          f"{args.scenario}, {args.duration:g} s per run", file=sys.stderr)
    print(summary(rows))


if __name__ == "__main__":
    main()
