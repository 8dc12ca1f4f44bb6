"""Time-step convergence study: a scenario at several plant steps against a fine reference.

    .venv/bin/python benchmarks/bench_step_convergence.py [--scenario Default]
        [--duration 20] [--steps 0.25,0.5,1,2,3,4] [--reference 0.25] [--scenario-text YAML]
        [--log-every-step]

Each step runs the same scenario (same seed) through the one run loop (app/run.py) with
`plant.time_step` set to it, bypassing the scenario's step bound (physics/step_bound.py), so
that the table also shows what happens beyond it. Printed per step, against the reference:
  - advance along the colon (m) and its difference from the reference's (%);
  - the capsule's position and axis along the run: median and largest distance (mm) and
    angle between the axes (deg), at the logged times;
  - the largest excursion beyond the wall (mm), over the whole run and after the first
    second (the capsule starts on the centreline and drops onto the wall);
  - the summed contact force after the first second: median and 95th percentile (N);
  - the real-time factor of that run (the run loop's, loggers and guard included).
A step whose run diverged or stopped early says so in its row. The runs log at the
scenario's log period (10 ms by default), which can miss a one-step excursion into the wall;
--log-every-step logs each run at its own step (slower).
"""

import argparse
import platform

import numpy as np

from capsule_drake.anatomy import load_colon
from capsule_drake.capsule.model import capsule_model
from capsule_drake.io.metrics import capsule_poses, capsule_surface_points_C, wall_excursion
from capsule_drake.app.run import simulate
from capsule_drake.scenario import load_scenario


def run(name, override, step, duration, every_step=False):
    scenario = load_scenario(name=name, override=override)
    scenario.plant.time_step = step
    scenario.duration = duration
    if every_step:
        scenario.outputs.log_period = step
    return simulate(scenario, progress=False)


def axes(capsule_state):
    """The capsule's long axis (+z of its body) in world at each log time (K, 3)."""
    w, x, y, z = capsule_state[:4]
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], -1)


def compare(result, reference, period=0.01):
    """Position (mm) and axis (deg) differences at common times every `period` s (the
    nearest logged sample of each run: their log periods may differ)."""
    end = min(result.times[-1], reference.times[-1])
    grid = np.arange(0.0, end + 1e-9, period)

    def at(run):
        k = np.clip(np.searchsorted(run.times, grid - 1e-9), 0, len(run.times) - 1)
        return run.capsule_state[:, k]

    a, b = at(result), at(reference)
    distance = 1000.0 * np.linalg.norm(a[4:7] - b[4:7], axis=0)
    cosine = np.clip(np.sum(axes(a) * axes(b), axis=1), -1.0, 1.0)
    angle = np.degrees(np.arccos(cosine))
    return distance, angle


def excursion_after(scenario, result, t0=1.0):
    """Largest excursion beyond the wall after t0 (mm), as the run's metrics measure it."""
    colon, _ = load_colon(scenario.colon)
    model = capsule_model()
    keep = result.times >= t0
    R, p = capsule_poses(result.capsule_state[:, keep])
    points = capsule_surface_points_C(model.radius, model.length)
    return 1000.0 * float(np.max(wall_excursion(colon, R, p, points)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="Default")
    parser.add_argument("--scenario-text", default=None)
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--steps", default="0.25,0.5,1,2,3,4", help="ms, comma separated")
    parser.add_argument("--reference", type=float, default=0.25, help="ms")
    parser.add_argument("--log-every-step", action="store_true",
                        help="log each run at its plant step (catches one-step excursions)")
    args = parser.parse_args()
    steps = sorted({float(s) for s in args.steps.split(",")} | {args.reference})

    scenario = load_scenario(name=args.scenario, override=args.scenario_text)
    results = {}
    for step in steps:
        results[step] = run(args.scenario, args.scenario_text, 1e-3 * step, args.duration,
                            args.log_every_step)
    reference = results[args.reference]
    ref_advance = reference.metrics["advance_m"]

    print(f"machine: {platform.machine()}, Python {platform.python_version()}; scenario "
          f"{args.scenario}, {args.duration:g} s, reference step {args.reference:g} ms")
    print("| step (ms) | advance (m) | vs reference | position diff median / max (mm) "
          "| axis diff median / max (deg) | excursion all / after 1 s (mm) "
          "| contact force median / p95 (N) | real-time factor |")
    print("|---|---|---|---|---|---|---|---|")
    for step in steps:
        result = results[step]
        m = result.metrics
        if m.get("advance_m") is None or m.get("stopped_early"):
            print(f"| {step:g} | {m.get('status')}: {m.get('stopped_early')} |||||||")
            continue
        distance, angle = compare(result, reference)
        load = np.asarray(result.contact_load)[result.times >= 1.0]
        print(f"| {step:g} | {m['advance_m']:.4f} | "
              f"{100.0 * (m['advance_m'] - ref_advance) / ref_advance:+.2f} % | "
              f"{np.median(distance):.2f} / {distance.max():.2f} | "
              f"{np.median(angle):.2f} / {angle.max():.2f} | "
              f"{1000.0 * m['max_wall_excursion_m']:.2f} / {excursion_after(scenario, result):.2f} | "
              f"{np.median(load):.3f} / {np.percentile(load, 95):.3f} | "
              f"{m['real_time_factor']:.2f} |")


if __name__ == "__main__":
    main()
