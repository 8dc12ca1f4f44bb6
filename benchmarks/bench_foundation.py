"""What the compliant wall's foundation costs a step, timed per call in the simulation loop.

    .venv/bin/python benchmarks/bench_foundation.py [--scenario Default] [--sim-seconds 5]
        [--scenario-text YAML]

Builds the scenario on the compliant wall (`{contact: !CompliantWall {}}`, then the given
YAML), settles it for 1 s, then advances `sim-seconds` with the foundation's callbacks
wrapped in timers, and prints the wall time per plant step and each callback's share:
- `_update`: the foundation's discrete update (the bristles and stuck cells); the first
  call of a step computes the contact cells (`_geometry`), so it includes them;
- `_geometry`: the contact cells, their table lookup and their response (once per state;
  the other calls of the step find it memoised);
- `_solve`: the implicit step's force (per evaluation of the force port);
- `_calc_force`: the force port, which also evaluates the other applied forces (the
  magnet's), upstream of the foundation.
The foundation's own cost per step is about `_update` + `_solve`. The timers add ~1 us a
call. Median of `--repeats` runs.
"""

import argparse
import collections
import statistics
import time

from pydrake.systems.analysis import Simulator

from capsule_drake.physics.contact import foundation
from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station

TIMED = ("_update", "_geometry", "_solve", "_calc_force")


def timed_run(scenario_name: str, texts, sim_seconds: float):
    """(wall time per step, {callback: seconds per step}) for one run."""
    totals = collections.defaultdict(float)
    originals = {name: getattr(foundation.FoundationContact, name) for name in TIMED}

    def wrap(name, function):
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                totals[name] += time.perf_counter() - start
        return timed

    try:
        for name, function in originals.items():
            setattr(foundation.FoundationContact, name, wrap(name, function))
        scenario = load_scenario(name=scenario_name, override=texts)
        simulator = Simulator(make_station(scenario))
        simulator.Initialize()
        simulator.AdvanceTo(1.0)
        totals.clear()
        start = time.perf_counter()
        simulator.AdvanceTo(1.0 + sim_seconds)
        wall = time.perf_counter() - start
    finally:
        for name, function in originals.items():
            setattr(foundation.FoundationContact, name, function)
    steps = sim_seconds / scenario.plant.time_step
    return wall / steps, {name: totals[name] / steps for name in TIMED}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="Default")
    parser.add_argument("--scenario-text", default=None)
    parser.add_argument("--sim-seconds", type=float, default=5.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    texts = ["{contact: !CompliantWall {}}"] + ([args.scenario_text] if args.scenario_text else [])
    runs = [timed_run(args.scenario, texts, args.sim_seconds) for _ in range(args.repeats)]
    per_step = statistics.median(r[0] for r in runs)
    print(f"{args.scenario} on the compliant wall, {args.sim_seconds:g} s after 1 s, "
          f"median of {args.repeats}: {per_step * 1e3:.3f} ms a step")
    for name in TIMED:
        print(f"  {name:12s} {statistics.median(r[1][name] for r in runs) * 1e3:.3f} ms a step")
    own = statistics.median(r[1]["_update"] + r[1]["_solve"] for r in runs)
    print(f"  foundation's own (_update + _solve): {own * 1e3:.3f} ms a step")


if __name__ == "__main__":
    main()
