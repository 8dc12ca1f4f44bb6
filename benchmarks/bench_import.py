"""Cost of importing a colon mesh, stage by stage, and of simulating on the result.

Imports (capsule_drake.anatomy.imported.import_colon_mesh) two meshes `--repeats` times and
prints the median wall time of each stage (reading and checking, repairing, centreline,
wall table) and the total:
  - the procedural colon (seed 0, the Default scenario's) exported as an OBJ, as a user
    would bring a segmentation (closed, ~100k faces, 1.46 m);
  - the shipped ex vivo segment's reconstruction (a textured thick wall, 77k faces).
Then simulates the Default drag for `--sim` seconds on the procedural colon and on its
import, and the ExVivoSegment scenario, and prints each real-time factor (simulated over
wall time, build excluded).

With --tubes, instead: imports the test tubes of tests/tube_set.py (made independently of
the package, 4k-220k faces) once each and prints each one's faces, import time, and the
recovered centreline's largest distance from the true one (both ways) [mm].

With --sweep N, instead: N tubes of random shape (tube_set.random_spec, seeds from 0: the
set's features drawn together, deep folds, flares, oblique cuts and sharp bends at the
same end included; draws that bend tighter than their radius allows are skipped) and the
distribution of the largest distance, with each tube over 2 mm named.

Run: python benchmarks/bench_import.py [--repeats 3] [--sim 10] [--tubes] [--sweep N]
"""

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from pydrake.systems.analysis import Simulator

from capsule_drake.anatomy import load_colon
from capsule_drake.anatomy.ex_vivo import write_segment
from capsule_drake.anatomy.imported import import_colon_mesh
from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station

STAGES = ("reading", "repairing", "centreline", "wall table")


def timed_import(path: Path) -> dict[str, float]:
    """Seconds spent in each stage of one import."""
    marks = []

    def progress(text):
        stage = next(name for name in STAGES if text.startswith(name))
        if not marks or marks[-1][0] != stage:
            marks.append((stage, time.perf_counter()))

    import_colon_mesh(path, progress=progress)
    end = time.perf_counter()
    return {stage: (marks[k + 1][1] if k + 1 < len(marks) else end) - start
            for k, (stage, start) in enumerate(marks)}


def real_time_factor(scenario, seconds: float) -> float:
    diagram = make_station(dataclasses.replace(scenario, duration=seconds))
    simulator = Simulator(diagram)
    simulator.Initialize()
    start = time.perf_counter()
    simulator.AdvanceTo(seconds)
    return seconds / (time.perf_counter() - start)


sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from tube_set import TUBES, centreline_errors, make_tube, random_spec  # noqa: E402


def sweep(count: int) -> None:
    errors, skipped, seed = [], 0, -1
    with tempfile.TemporaryDirectory() as folder:
        while len(errors) < count:
            seed += 1
            spec = random_spec(seed)
            try:
                tube = make_tube(spec)
            except (RuntimeError, ValueError):
                skipped += 1   # bent tighter than its radius allows
                continue
            path = tube.write(folder)
            try:
                wall = import_colon_mesh(path, tube.scale)
                error = max(centreline_errors(tube.truth, wall.centerline.points))
            except ValueError as e:
                print(f"seed {seed}: refused ({str(e).splitlines()[0]})")
                error = np.inf
            errors.append(error)
            if error >= 0.002:
                print(f"seed {seed}: {1000 * error:.2f} mm  ends {'/'.join(spec.ends)}, flare "
                      f"{spec.flare}, oblique {spec.oblique}, bend {spec.end_bend}, folds "
                      f"{spec.haustra} (haustral) {spec.ripple} (ring), {spec.mesh}", flush=True)
    e = 1000 * np.array(errors)
    print(f"{len(e)} tubes (seeds 0-{seed}; {skipped} draws bent too tightly, skipped): "
          f"largest distance median {np.median(e):.2f} mm, 90th percentile "
          f"{np.percentile(e, 90):.2f} mm, largest {e.max():.2f} mm; within 2 mm: "
          f"{np.sum(e < 2.0)} of {len(e)}")


def tube_table() -> None:
    print(f"{'tube':<18}{'ends':<22}{'mesh':<10}{'faces':>8}{'import [s]':>12}"
          f"{'error [mm]':>12}")
    with tempfile.TemporaryDirectory() as folder:
        for spec in sorted(TUBES, key=lambda spec: spec.faces):
            tube = make_tube(spec)
            path = tube.write(folder)
            start = time.perf_counter()
            wall = import_colon_mesh(path, tube.scale)
            seconds = time.perf_counter() - start
            error = max(centreline_errors(tube.truth, wall.centerline.points))
            print(f"{spec.name:<18}{'/'.join(spec.ends):<22}{spec.mesh:<10}"
                  f"{len(tube.mesh.faces):>8}{seconds:>12.1f}{1000 * error:>12.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--sim", type=float, default=10.0, help="simulated seconds per run")
    parser.add_argument("--tubes", action="store_true",
                        help="time and check the import of the test tubes instead")
    parser.add_argument("--sweep", type=int, default=0, metavar="N",
                        help="import N tubes of random shape and print the errors instead")
    args = parser.parse_args()
    if args.sweep:
        sweep(args.sweep)
        return
    if args.tubes:
        tube_table()
        return
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        procedural = folder / "procedural_colon.obj"
        colon, _ = load_colon(load_scenario(name="Default").colon)
        colon.visual_mesh().export(procedural)
        segment = write_segment(folder / "ex_vivo")
        print(f"{'mesh':<18}" + "".join(f"{s:>12}" for s in STAGES) + f"{'total':>10}  [s]")
        for name, path in (("procedural (OBJ)", procedural), ("ex vivo segment", segment)):
            runs = [timed_import(path) for _ in range(args.repeats)]
            medians = {s: float(np.median([r.get(s, 0.0) for r in runs])) for s in STAGES}
            total = float(np.median([sum(r.values()) for r in runs]))
            print(f"{name:<18}" + "".join(f"{medians[s]:>12.2f}" for s in STAGES)
                  + f"{total:>10.2f}")
        print(f"\nreal-time factor over {args.sim:g} s (build excluded):")
        for name, scenario in (
                ("Default, procedural", load_scenario(name="Default")),
                ("Default, imported", load_scenario(
                    name="Default", override=f"{{colon: {{source: !Imported {{path: {procedural}}}}}}}")),
                ("ExVivoSegment", load_scenario(name="ExVivoSegment"))):
            print(f"  {name:<22} {real_time_factor(scenario, args.sim):.2f}")


if __name__ == "__main__":
    main()
