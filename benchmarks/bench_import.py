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

With --sweep N, instead: N tubes of random shape (tube_set.random_spec, seeds from
--first-seed, default 0: the set's features drawn together, deep folds, flares, oblique
cuts and sharp bends at the same end included; draws that bend tighter than their radius
allows, or whose oblique cut a bend before the end takes off a line of the wall, are
skipped) and the distribution of the largest distance, with each tube over 2 mm
named (--csv PATH: a row per tube).

With --sizes N,N,..., instead: for each size, a bent open tube of about N triangles (a
uniform grid of rings, 4 cm wide, 48 cm long) and a soup of N separate triangles, each
imported in a process of its own with the import's size limit lifted, and its wall time,
its peak memory and its outcome printed: what importer.MAX_IMPORT_FACES is set from.

Run: python benchmarks/bench_import.py [--repeats 3] [--sim 10] [--tubes] [--sweep N]
     [--first-seed S] [--csv PATH] [--sizes 300000,1200000,4800000]
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
from tube_set import (TUBES, CannotMake, centreline_errors, make_tube,  # noqa: E402
                      random_spec)


def sweep(count: int, first_seed: int = 0, csv_path: str | None = None) -> None:
    rows, seed = [], first_seed - 1
    skipped = {"bent": 0, "cut": 0, "other": 0}
    with tempfile.TemporaryDirectory() as folder:
        while len(rows) < count:
            seed += 1
            spec = random_spec(seed)
            try:
                tube = make_tube(spec)
            except CannotMake as e:
                skipped[e.reason] += 1
                continue
            except RuntimeError:   # no curve clear of itself
                skipped["other"] += 1
                continue
            path = tube.write(folder)
            start = time.perf_counter()
            try:
                wall = import_colon_mesh(path, tube.scale)
                to_truth, to_line = centreline_errors(tube.truth, wall.centerline.points)
                status = "ok"
            except ValueError as e:
                print(f"seed {seed}: refused ({str(e).splitlines()[0]})")
                to_truth = to_line = np.inf
                status = "refused"
            rows.append(dict(seed=seed, ends="/".join(spec.ends), to_truth_mm=1000 * to_truth,
                             to_line_mm=1000 * to_line,
                             error_mm=1000 * max(to_truth, to_line),
                             seconds=time.perf_counter() - start, status=status))
            if rows[-1]["error_mm"] >= 2.0:
                print(f"seed {seed}: {rows[-1]['error_mm']:.2f} mm  ends {'/'.join(spec.ends)}, "
                      f"flare {spec.flare}, oblique {spec.oblique}, bend {spec.end_bend}, folds "
                      f"{spec.haustra} (haustral) {spec.ripple} (ring), {spec.mesh}", flush=True)
    if csv_path:
        import csv

        with open(csv_path, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows({k: f"{v:.3f}" if isinstance(v, float) else v
                              for k, v in row.items()} for row in rows)
    e = np.array([row["error_mm"] for row in rows])
    print(f"{len(e)} tubes (seeds {first_seed}-{seed}; draws skipped: {skipped['bent']} bent "
          f"too tightly, {skipped['cut']} with an oblique cut a bend takes off the wall, "
          f"{skipped['other']} other): largest distance median {np.median(e):.2f} mm, "
          f"90th percentile {np.percentile(e, 90):.2f} mm, largest {e.max():.2f} mm; within 2 mm: "
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


def sized_mesh(kind: str, triangles: int, path: Path) -> int:
    """Writes a bent open tube ('tube') of about `triangles` faces, or a soup ('soup') of that
    many separate 2 mm triangles in a 30 x 30 x 9 cm box, as an OBJ; returns its faces."""
    rng = np.random.default_rng(0)
    if kind == "tube":
        around = max(32, 2 * int(np.sqrt(triangles / 20)))
        rings = triangles // (2 * around) + 1
        a = np.linspace(-0.8, 0.8, rings)  # an arc of 0.3 m radius, 4 cm wide
        centre = np.column_stack([0.3 * np.sin(a), np.zeros_like(a), 0.3 * (1 - np.cos(a))])
        normal = np.column_stack([-np.sin(a), np.zeros_like(a), np.cos(a)])
        theta = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
        vertices = (centre[:, None] + 0.02 * (np.cos(theta)[None, :, None] * normal[:, None]
                                              + np.sin(theta)[None, :, None] * [0, 1, 0])
                    ).reshape(-1, 3)
        i, j = np.meshgrid(np.arange(rings - 1), np.arange(around), indexing="ij")
        k, n = i * around + j, i * around + (j + 1) % around
        faces = np.concatenate([np.stack([k, n, k + around], -1).reshape(-1, 3),
                                np.stack([n, n + around, k + around], -1).reshape(-1, 3)])
    else:
        centres = rng.uniform(0.0, 0.3, (triangles, 1, 3)) * [1.0, 1.0, 0.3]
        vertices = (centres + rng.normal(0.0, 0.002, (triangles, 3, 3))).reshape(-1, 3)
        faces = np.arange(3 * triangles).reshape(-1, 3)
    with open(path, "w") as f:
        np.savetxt(f, vertices, fmt="v %.7f %.7f %.7f")
        np.savetxt(f, faces + 1, fmt="f %d %d %d")
    return len(faces)


def import_one(path: str) -> None:
    """(In a process of its own) imports `path` with the size limit lifted and prints its
    seconds, peak memory [GB] and outcome, tab-separated."""
    import resource

    from capsule_drake.anatomy import importer

    importer.MAX_IMPORT_FACES = 10**9
    start = time.perf_counter()
    try:
        wall = import_colon_mesh(path)
        outcome = f"imported ({len(wall.mesh.faces)} faces)"
    except ValueError as e:
        outcome = "refused: " + str(e).split(": ", 1)[1][:70]
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"{seconds:.1f}\t{peak:.2f}\t{outcome}")


def size_table(sizes: list[int]) -> None:
    import subprocess

    print(f"{'mesh':<6}{'triangles':>11}{'import [s]':>12}{'peak [GB]':>11}  outcome")
    with tempfile.TemporaryDirectory() as folder:
        for size in sizes:
            for kind in ("tube", "soup"):
                path = Path(folder) / f"{kind}_{size}.obj"
                faces = sized_mesh(kind, size, path)
                done = subprocess.run([sys.executable, __file__, "--one", str(path)],
                                      capture_output=True, text=True)
                path.unlink()
                if done.returncode != 0:
                    print(f"{kind:<6}{faces:>11,}  failed: {done.stderr.strip()[-200:]}")
                    continue
                seconds, peak, outcome = done.stdout.strip().splitlines()[-1].split("\t")
                print(f"{kind:<6}{faces:>11,}{float(seconds):>12.1f}{float(peak):>11.2f}  "
                      f"{outcome}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--sim", type=float, default=10.0, help="simulated seconds per run")
    parser.add_argument("--tubes", action="store_true",
                        help="time and check the import of the test tubes instead")
    parser.add_argument("--sweep", type=int, default=0, metavar="N",
                        help="import N tubes of random shape and print the errors instead")
    parser.add_argument("--first-seed", type=int, default=0,
                        help="the sweep's first seed (default 0)")
    parser.add_argument("--csv", metavar="PATH", help="the sweep's tubes, one row each")
    parser.add_argument("--sizes", metavar="N,N,...",
                        help="import tubes and triangle soups of these sizes instead, each "
                             "in a process of its own: seconds and peak memory")
    parser.add_argument("--one", metavar="MESH", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        import_one(args.one)
        return
    if args.sizes:
        size_table([int(float(n)) for n in args.sizes.split(",")])
        return
    if args.sweep:
        sweep(args.sweep, args.first_seed, args.csv)
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
