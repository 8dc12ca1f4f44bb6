"""Where the plant's time step (and the magnet force's update period) stops giving a run that
means anything: the measurement behind capsule_drake/physics/step_bound.py.

    .venv/bin/python benchmarks/bench_time_step.py [--cases Default Close ...]
        [--steps 0.25 0.5 1 2 4 8 16] [--periods 2 4 8 16] [--duration 4] [--json out.json]
    .venv/bin/python benchmarks/bench_time_step.py --from-json out.json [more.json ...]

Cases: the scenarios Default, FarMagnet, WithArm, FastContact and ExVivoSegment of
diagrams/default.yaml; Close, Default with the capsule started where the procedural patient
is shallowest (the transverse colon's roof: the EPM then hovers 10.4 cm from the capsule, the
stiffest magnet coupling any case here reaches; the magnet flings the capsule across the
lumen at 2.3 m/s); and CloseDrag, Close with a translational drag of 20 N s/m (no fling, the
rotation undamped: the magnet's own stability limit). Each runs for `--duration` simulated
seconds (the scenario's own duration if shorter) at every plant step of `--steps` (ms; the
Close cases at 1.5, 3, 5, 6 and 7 ms too), the magnet force recomputed every step
(FastContact keeps its own 2 ms hold below a 2 ms step), and, for Default and the Close
cases, at a 1 ms step with the force held (magnet_force.update_period) for each of
`--periods` (ms). Each run is its own process (a diverging run cannot take the next one
with it), one at a time; `--json` keeps the rows and `--from-json` prints them again.

The scenario is loaded, then its step set on the loaded object (validation would refuse the
long steps), and logged every step (every 1 ms below that); the run guard's limits are
raised to 50 m/s and 50 mm, so that it stops only a diverging run, before its numbers
overflow. A run FAILS at the first of:
  - a run that diverged (stopped by the guard, or its state went NaN);
  - any point of the capsule farther than 1 mm beyond the colon wall (the contact itself lets
    it 0.1-0.9 mm in at 0.25 ms);
  - a peak speed over 1 m/s that is also 25 % over the 0.25 ms reference's (the magnet's
    fling in Close reaches 2.3 m/s at 0.25 ms: physical);
  - an advance along the colon (metrics advance_m) off the 0.25 ms reference's by more than
    15 % of it plus 2 mm (the plus: FarMagnet's capsule barely moves).
Printed: one row per run (build + simulation wall time, real-time factor, largest wall
excursion, peak speed and angular speed, advance, its difference from the reference, closest
EPM-capsule distance, verdict), then per case the longest step that passed with every
shorter one passing too and the first that failed, beside the bound step_bound.py derives
for the case's scenario. A full run takes ~35 min on two cores.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

CASES = ("Default", "FarMagnet", "WithArm", "FastContact", "ExVivoSegment", "Close",
         "CloseDrag")
# Steps (ms) added to --steps for the cases where the magnet's instability is looked for.
EXTRA_STEPS = {"Close": (1.5, 3.0, 5.0, 6.0, 7.0), "CloseDrag": (1.5, 3.0, 5.0, 6.0, 7.0)}
HELD = ("Default", "Close", "CloseDrag")   # cases also run with the force held
REFERENCE_STEP = 0.25e-3
MAX_EXCURSION = 1.0e-3     # m
MAX_SPEED = 1.0            # m/s
SPEED_OVER_REFERENCE = 1.25
ADVANCE_RELATIVE = 0.15
ADVANCE_ABSOLUTE = 2.0e-3  # m
TIMEOUT = 900.0            # s of wall time per run
GUARD_SPEED = 50.0         # m/s: the run guard's limits while measuring
GUARD_EXCURSION = 0.05     # m


def shallowest_start_s(colon_params) -> float:
    """Arc length where the capsule's centre can come nearest the skin (the top of the lumen)."""
    from capsule_drake.anatomy import build_colon
    from capsule_drake.capsule.model import capsule_model

    colon = build_colon(colon_params)
    s = np.arange(0.02, colon.centerline.length - 0.02, 0.002)
    top = colon.depth_below_skin(s) - (colon.max_wall_radius(s) - capsule_model().radius)
    return float(s[int(np.argmin(top))])


def load_case(case: str, duration: float, step: float, period: float):
    """The case's scenario with its plant step and force update period set (not validated)."""
    from capsule_drake.scenario import load_scenario

    if case in ("Close", "CloseDrag"):
        scenario = load_scenario(name="Default")
        scenario.capsule.start_s = shallowest_start_s(scenario.colon)
        if case == "CloseDrag":   # no snap across the lumen: terminal speed ~0.15 m/s
            scenario.contact.drag_translational = 20.0
    else:
        scenario = load_scenario(name=case)
    scenario.duration = min(duration, scenario.duration)
    scenario.plant.time_step = step
    scenario.magnet_force.update_period = period
    # Logged every step (at most every 1 ms): an overshoot into the wall lasts a few steps.
    scenario.outputs.log_period = max(step, 1e-3)
    # The run guard stops a diverging run before its numbers overflow, but lets a run that
    # merely overshoots show how far it goes.
    scenario.guard.max_speed = GUARD_SPEED
    scenario.guard.max_wall_excursion = GUARD_EXCURSION
    return scenario


def run_one(case: str, duration: float, step: float, period: float) -> dict:
    """Runs one configuration in this process; returns its numbers."""
    from capsule_drake.app.run import simulate

    start = time.perf_counter()
    scenario = load_case(case, duration, step, period)
    result = simulate(scenario, out_dir=None, progress=False)
    metrics = result.metrics
    state = result.capsule_state
    finite = bool(np.all(np.isfinite(state)))
    speed = np.linalg.norm(state[10:13], axis=0) if state.size else np.zeros(1)
    spin = np.linalg.norm(state[7:10], axis=0) if state.size else np.zeros(1)
    return {
        "case": case, "step": step, "period": period,
        "wall_s": time.perf_counter() - start,
        "rtf": metrics.get("real_time_factor"),
        "sim_time": metrics.get("sim_time_s"),
        "duration": scenario.duration,
        "excursion": metrics.get("max_wall_excursion_m"),
        "advance": metrics.get("advance_m"),
        "closest": metrics.get("min_epm_capsule_distance_m"),
        "speed": float(np.nanmax(speed)) if finite else float("nan"),
        "spin": float(np.nanmax(spin)) if finite else float("nan"),
        "finite": finite,
        "stopped": metrics.get("stopped_early"),
    }


def run_isolated(case: str, duration: float, step: float, period: float) -> dict:
    """run_one in a child process (with a wall-clock limit)."""
    spec = json.dumps({"case": case, "duration": duration, "step": step, "period": period})
    try:
        done = subprocess.run([sys.executable, __file__, "--one", spec], capture_output=True,
                              text=True, timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        return {"case": case, "step": step, "period": period, "stopped": "timed out",
                "finite": True}
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if done.returncode != 0 or not lines:
        tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
        return {"case": case, "step": step, "period": period, "stopped": f"crashed: {tail}",
                "finite": True}
    return json.loads(lines[-1])


def verdict(row: dict, reference: dict | None) -> str:
    """'ok' or why the run failed (see the module docstring)."""
    if row.get("stopped"):
        text = str(row["stopped"])
        if "run guard at t = " in text:   # "stopped by the run guard at t = 0.250 s: why"
            when, _, why = text.split("run guard at t = ", 1)[1].partition(": ")
            return f"diverged, stopped at {when.replace(' ', '')}: {why[:44]}"
        if "Quaternion is not normalized" in text:
            # The state went NaN: the run's metrics cannot be computed (io/metrics.py).
            return "diverged: state not finite"
        return text[:70]
    if not row.get("finite", True) or row.get("excursion") is None:
        return "not finite"
    if row["excursion"] > MAX_EXCURSION:
        return f"wall {row['excursion'] * 1e3:.1f} mm"
    ref_speed = reference["speed"] if reference else 0.0
    if row["speed"] > MAX_SPEED and row["speed"] > SPEED_OVER_REFERENCE * ref_speed:
        return f"speed {row['speed']:.2f} m/s"
    if reference is not None and reference.get("advance") is not None:
        off = abs(row["advance"] - reference["advance"])
        if off > ADVANCE_RELATIVE * abs(reference["advance"]) + ADVANCE_ABSOLUTE:
            return f"advance off {off * 1e3:.1f} mm"
    return "ok"


def fmt(value, scale=1.0, spec=".2f"):
    return "-" if value is None or (isinstance(value, float) and np.isnan(value)) \
        else format(value * scale, spec)


HEADER = (f"{'case':<13} {'step':>5} {'force':>5} {'wall s':>6} {'RTF':>5} {'exc mm':>6} "
          f"{'v m/s':>6} {'w rad/s':>7} {'adv mm':>7} {'d adv':>6} {'EPM cm':>6}  verdict")


def configs_of(case: str, steps, periods) -> list[tuple[float, float]]:
    """(plant step, force update period) in s of the runs of one case."""
    steps = sorted(set(steps) | set(EXTRA_STEPS.get(case, ())))
    configs = [(step * 1e-3, 0.0) for step in steps]
    if case in HELD:
        configs += [(1e-3, period * 1e-3) for period in sorted(periods)]
    if case == "FastContact":  # its own 2 ms hold, at every step that is shorter
        configs = [(step, max(2e-3, step)) for step, _ in configs]
    return configs


def judged(rows: list[dict]) -> list[dict]:
    """The rows with their verdicts, each against its case's 0.25 ms reference."""
    references = {r["case"]: r for r in rows
                  if r["step"] == REFERENCE_STEP and not r.get("stopped")}
    for row in rows:
        reference = references.get(row["case"])
        row["verdict"] = verdict(row, reference)
        row["advance_off"] = (None if reference is None or row.get("advance") is None
                              else row["advance"] - reference["advance"])
    return rows


def row_text(row: dict) -> str:
    step, period = row["step"], row["period"]
    return (f"{row['case']:<13} {step * 1e3:>5g} {max(period, step) * 1e3:>5g} "
            f"{fmt(row.get('wall_s'), 1, '.0f'):>6} {fmt(row.get('rtf'), 1, '.1f'):>5} "
            f"{fmt(row.get('excursion'), 1e3):>6} {fmt(row.get('speed')):>6} "
            f"{fmt(row.get('spin'), 1, '.0f'):>7} {fmt(row.get('advance'), 1e3, '.1f'):>7} "
            f"{fmt(row.get('advance_off'), 1e3, '.1f'):>6} "
            f"{fmt(row.get('closest'), 1e2, '.1f'):>6}  {row['verdict']}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    parser.add_argument("--steps", nargs="+", type=float,
                        default=[0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0], help="ms")
    parser.add_argument("--periods", nargs="+", type=float, default=[2.0, 4.0, 8.0, 16.0],
                        help="ms, force update periods at a 1 ms step (Default, Close*)")
    parser.add_argument("--duration", type=float, default=4.0)
    parser.add_argument("--json", type=Path, help="also write the rows here")
    parser.add_argument("--from-json", nargs="+", type=Path, metavar="FILE",
                        help="print the table of saved rows instead of running (a later "
                             "file's row replaces an earlier one of the same run)")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        spec = json.loads(args.one)
        print(json.dumps(run_one(spec["case"], spec["duration"], spec["step"],
                                 spec["period"])))
        return

    if args.from_json:
        saved = {}
        for path in args.from_json:
            for row in json.loads(path.read_text()):
                saved[row["case"], row["step"], row["period"]] = row
        rows = judged([row for row in saved.values() if row["case"] in args.cases])
        rows.sort(key=lambda r: (CASES.index(r["case"]), r["period"] > r["step"]
                                 and r["case"] != "FastContact", r["step"], r["period"]))
        print(HEADER)
        for row in rows:
            print(row_text(row))
    else:
        rows = []
        print(HEADER)
        for case in args.cases:
            for step, period in configs_of(case, args.steps, args.periods):
                rows.append(run_isolated(case, args.duration, step, period))
                print(row_text(judged(rows)[-1]), flush=True)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1) + "\n")
    summary(args.cases, judged(rows), args.duration)


def summary(cases, rows, duration):
    """Per case: the longest step that passed, every shorter one passing too, and the first
    failure; the same for the force held at a 1 ms step; beside the bounds step_bound.py
    derives for the case's scenario."""
    from capsule_drake.physics.step_bound import step_bounds

    def longest(candidates, key):
        passed, failed = None, None
        for row in sorted(candidates, key=key):
            if row["verdict"] != "ok":
                failed = row
                break
            passed = row
        return passed, failed

    print()
    print("longest passing step (every shorter one passing too), first failure, bound:")
    for case in cases:
        case_rows = [r for r in rows if r["case"] == case]
        if not case_rows:
            continue
        bounds = step_bounds(load_case(case, duration, 1e-3, 0.0))
        per_step = [r for r in case_rows if r["period"] == (
            max(2e-3, r["step"]) if case == "FastContact" else 0.0)]
        passed, failed = longest(per_step, lambda r: r["step"])
        text = (f"  {case:<13} step: {fmt(passed and passed['step'], 1e3, 'g')} ms passes, "
                f"{fmt(failed and failed['step'], 1e3, 'g')} ms fails "
                f"({failed['verdict'] if failed else '-'}); bound "
                f"{bounds.plant_step * 1e3:.3g} ms")
        held = [r for r in case_rows if r["step"] == 1e-3 and r["period"] > 1e-3
                and case != "FastContact"]
        if held:
            passed, failed = longest(held, lambda r: r["period"])
            text += (f"; force held {fmt(passed and passed['period'], 1e3, 'g')} ms passes, "
                     f"{fmt(failed and failed['period'], 1e3, 'g')} ms fails; bound "
                     f"{bounds.force_period * 1e3:.3g} ms")
        print(text)


if __name__ == "__main__":
    main()
