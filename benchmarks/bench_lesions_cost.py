"""What lesions cost the simulation: the same scenario without and with lesions, run side by
side in one process, in alternating slices of simulated time, so that whatever else the
machine does falls on both alike.

    .venv/bin/python benchmarks/bench_lesions_cost.py [--scenarios Default,Navigation]
        [--sim-seconds 6] [--slice 0.25] [--lesions YAML]

Prints, per scenario, each side's real-time factor over its slices and the median of the
slices' paired ratios (with lesions / without): the cost, robust to a noisy machine.
Both are let settle for 1 s first. The default lesions: three polyps (8 mm 0-Is and 12 mm
0-Ip in the rectum, 10 mm 0-IIa in the sigmoid) and an 8 mm diverticulum in the sigmoid.
"""

import argparse
import platform
import time

import numpy as np
from pydrake.systems.analysis import Simulator

from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station

LESIONS = ("{drawn: false, placed: [{kind: 0-Is, size_mm: 8, segment: rectum, along: 0.5}, "
           "{kind: 0-Ip, size_mm: 12, segment: rectum, along: 0.8}, {kind: 0-IIa, size_mm: "
           "10, segment: sigmoid, along: 0.2}, {kind: diverticulum, size_mm: 8, segment: "
           "sigmoid, along: 0.1, around_deg: 200}]}")


def paired(name: str, lesions: str, sim_seconds: float, slice_s: float) -> dict:
    simulators = []
    for text in ("{}", f"{{colon: {{lesions: {lesions}}}}}"):
        simulator = Simulator(make_station(load_scenario(name=name, override=text)))
        simulator.Initialize()
        simulator.AdvanceTo(1.0)
        simulators.append(simulator)
    walls = [[], []]
    t = 1.0
    while t < 1.0 + sim_seconds - 1e-9:
        t += slice_s
        order = (0, 1) if len(walls[0]) % 2 == 0 else (1, 0)   # who goes first alternates
        for k in order:
            start = time.perf_counter()
            simulators[k].AdvanceTo(t)
            walls[k].append(time.perf_counter() - start)
    off, on = (np.asarray(w) for w in walls)
    return {"off": sim_seconds / off.sum(), "on": sim_seconds / on.sum(),
            "ratio": float(np.median(off / on)), "slices": len(off)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", default="Default,Navigation")
    parser.add_argument("--sim-seconds", type=float, default=6.0)
    parser.add_argument("--slice", type=float, default=0.25)
    parser.add_argument("--lesions", default=LESIONS)
    args = parser.parse_args(argv)
    print(f"machine: {platform.machine()}, {platform.processor() or platform.platform()}, "
          f"Python {platform.python_version()}; {args.sim_seconds:g} s in slices of "
          f"{args.slice:g} s after 1 s")
    print("| scenario | real-time factor without lesions | with | with / without "
          "(median of paired slices) |")
    print("|---|---|---|---|")
    for name in args.scenarios.split(","):
        r = paired(name, args.lesions, args.sim_seconds, args.slice)
        print(f"| `{name}` | {r['off']:.2f} | {r['on']:.2f} | **{r['ratio']:.3f}** "
              f"({r['slices']} slices) |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
