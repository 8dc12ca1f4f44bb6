"""Cost of the wall's pressure map (physics/wall_pressure.py) in a Default run.

Prints:
  - the map's time per sample inside a simulation (its periodic update: reading the contact
    surfaces' faces, locating them on the wall, accumulating the patches), split into
    those parts; medians, means and 95th percentiles in milliseconds, and the faces a
    sample found;
  - the process's CPU seconds per simulated second with and without the map (median of
    interleaved runs; steadier than the wall clock on a shared machine), and the share of
    the run the samples took.

Run: python benchmarks/bench_wall_pressure.py [--seconds 10] [--repeats 3]
         [--scenario Default] [--scenario-text YAML]
"""

import argparse
import statistics
import time

import numpy as np

from capsule_drake.app import run as run_module
from capsule_drake.app.run import simulate
from capsule_drake.physics import wall_pressure
from capsule_drake.scenario import load_scenario


def one_run(scenario, with_map: bool, timings=None):
    """CPU seconds of a run (its build excluded), with or without the map; with
    `timings`, each sample's parts are timed into it."""
    cpu = {}

    def extend(builder, station):
        cpu["start"] = time.process_time()
        return lambda: cpu.setdefault("end", time.process_time())

    add = run_module.add_wall_pressure
    faces, sampled = wall_pressure.contact_faces, wall_pressure.WallPressureMap.sampled
    locate = wall_pressure.WallLocator.locate
    if not with_map:
        run_module.add_wall_pressure = lambda *args: None
    elif timings is not None:
        parts = {}

        def timed(function, key):
            def wrapper(*args):
                start = time.perf_counter()
                out = function(*args)
                parts[key] = parts.get(key, 0.0) + time.perf_counter() - start
                if key == "faces":
                    timings.setdefault("count", []).append(len(out[0]))
                return out
            return wrapper

        def timed_sample(self, context):
            parts.clear()
            out = timed(sampled, "sample")(self, context)
            for key in ("sample", "faces", "locate"):
                timings.setdefault(key, []).append(parts.get(key, 0.0))
            return out

        wall_pressure.contact_faces = timed(faces, "faces")
        wall_pressure.WallLocator.locate = timed(locate, "locate")
        wall_pressure.WallPressureMap.sampled = timed_sample
    try:
        result = simulate(scenario, progress=False, extend=extend)
    finally:
        run_module.add_wall_pressure = add
        wall_pressure.contact_faces = faces
        wall_pressure.WallPressureMap.sampled = sampled
        wall_pressure.WallLocator.locate = locate
    return result, cpu["end"] - cpu["start"]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scenario", default="Default")
    parser.add_argument("--scenario-text", default="")
    args = parser.parse_args()
    scenario = load_scenario(name=args.scenario,
                             override=[args.scenario_text, f"duration: {args.seconds}"])

    timings = {}
    result, _ = one_run(scenario, True, timings)
    sample = np.array(timings["sample"]) * 1e3
    faces, locate = np.array(timings["faces"]) * 1e3, np.array(timings["locate"]) * 1e3
    rest = sample - faces - locate
    print(f"{args.scenario}, {args.seconds:g} s: {len(sample)} samples, "
          f"{np.median(timings['count']):.0f} faces a sample (median; at most "
          f"{np.max(timings['count'])}); site peak "
          f"{result.metrics['site_peak_pressure_kPa']:.0f} kPa")
    print("ms per sample        median   mean    p95")
    for label, values in (("whole sample", sample), ("contact faces", faces),
                          ("locate on the wall", locate), ("patches, state", rest)):
        print(f"  {label:<18} {np.median(values):6.3f} {np.mean(values):6.3f} "
              f"{np.percentile(values, 95):6.3f}")

    cpu = {True: [], False: []}
    for _ in range(args.repeats):
        for with_map in (True, False):
            cpu[with_map].append(one_run(scenario, with_map)[1] / args.seconds)
    on, off = statistics.median(cpu[True]), statistics.median(cpu[False])
    print(f"CPU s per simulated s: {on:.3f} with the map, {off:.3f} without "
          f"({100 * (on - off) / off:+.1f} %); the samples' own time: "
          f"{sample.sum() / 1e3 / args.seconds:.3f} s per simulated s "
          f"({100 * sample.sum() / 1e3 / args.seconds / off:.1f} % of the run)")


if __name__ == "__main__":
    main()
