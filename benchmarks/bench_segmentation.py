"""The colon import on segmentation-like surfaces (tests/segmentation_set.py): the test tubes
voxelised as a CT colonography scan would (0.70-0.80 mm in-plane, 1.0 or 1.25 mm slices,
partial-volume blur), meshed from the volume, their open ends cut open again, noised along
the normals (0.2-0.5 mm), holed (2-4 holes of 2-4 mm radius) and decimated (20-40k faces).

Each surface is written as an OBJ in millimetres (as segmentation tools export) to a
temporary folder and imported (capsule_drake.anatomy.imported.import_colon_mesh, scale
0.001). Printed per surface: its faces, the seconds to make it and to import it, the
outcome (imported, or the refusal's one line), and the recovered centreline's largest
distance to the true one both ways [mm] (tube_set.centreline_errors), with where along the
truth the worst point lies (0 its start, 1 its end). Then a summary: within 2 mm, refused,
worse than 2 mm; median and worst error of the imported ones.

Surfaces: the 18 tubes of tube_set.TUBES (--tubes, the default) and/or N random shapes
(--random N) from tube_set.random_spec seeds starting at --first-seed (default 30000: seeds
used nowhere else; draws that bend tighter than their radius allows are skipped). Each
surface's segmentation parameters are drawn from its own seed, so a row is reproducible.
--raw skips the decimation (the surface as meshed, 0.2-3 M faces: the importer's own
decimation then runs). --baseline also imports each tube's own clean mesh (tube_set) and
prints its error beside: what the segmentation costs, apart from what the shape costs.
--only NAME,NAME keeps those surfaces. --csv PATH writes a row each.

Run: python benchmarks/bench_segmentation.py [--tubes] [--random N] [--first-seed S]
     [--only NAMES] [--raw] [--baseline] [--csv PATH]
"""

import argparse
import csv
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from segmentation_set import segmented_tube  # noqa: E402
from tube_set import TUBES, centreline_errors, densify, make_tube, random_spec  # noqa: E402

from capsule_drake.anatomy.imported import import_colon_mesh  # noqa: E402

LIMIT_MM = 2.0


def parameters(seed: int) -> dict:
    """A surface's segmentation parameters, drawn from its seed (see segmentation_set.py for
    why these ranges)."""
    rng = np.random.default_rng([seed, 31])
    return dict(voxel=float(rng.uniform(0.70e-3, 0.80e-3)),
                slice_spacing=float(rng.choice([1.0e-3, 1.25e-3])),
                noise=float(rng.uniform(0.2e-3, 0.5e-3)), holes=int(rng.integers(2, 5)),
                decimate_to=int(rng.integers(20_000, 40_001)), seed=seed)


def surfaces(tubes: bool, random: int, first_seed: int, only):
    """(name, spec, seed) of each surface to make."""
    out = []
    if tubes:
        out += [(spec.name, spec, spec.seed) for spec in TUBES]
    seed, found = first_seed - 1, 0
    while found < random:
        seed += 1
        spec = random_spec(seed)
        try:
            make_tube(spec)
        except (RuntimeError, ValueError):
            continue   # bent tighter than its radius allows
        out.append((spec.name, spec, seed))
        found += 1
    if only:
        out = [row for row in out if row[0] in only]
    return out


def worst_at(truth, points) -> float:
    """Where along the truth (0 its start, 1 its end) the recovered line is farthest."""
    d = cKDTree(densify(points)).query(truth)[0]
    return float(np.argmax(d) / max(len(truth) - 1, 1))


def clean_error(spec, folder: Path) -> float:
    """The largest distance [mm] of the centreline imported from the tube's own clean mesh
    (nan if refused)."""
    tube = make_tube(spec)
    path = tube.write(folder)
    try:
        wall = import_colon_mesh(path, tube.scale)
        return 1000 * max(centreline_errors(tube.truth, wall.centerline.points))
    except ValueError:
        return float("nan")
    finally:
        path.unlink()


def run(rows_in, raw: bool, folder: Path, baseline: bool = False) -> list[dict]:
    print(f"{'surface':<22}{'ends':<22}{'faces':>9}{'make [s]':>10}{'import [s]':>11}"
          f"{'to truth':>10}{'to line':>9}{'at':>6}" + (f"{'clean':>7}" if baseline else "")
          + "  outcome", flush=True)
    rows = []
    for name, spec, seed in rows_in:
        p = parameters(seed)
        if raw:
            p["decimate_to"] = None
        start = time.perf_counter()
        mesh, truth = segmented_tube(spec, **p)
        made = time.perf_counter() - start
        info = mesh.metadata["segmentation"]
        path = folder / f"{name}.obj"
        trimesh.Trimesh(mesh.vertices * 1000.0, mesh.faces, process=False).export(path)
        start = time.perf_counter()
        to_truth = to_line = at = float("nan")
        try:
            wall = import_colon_mesh(path, 0.001)
            to_truth, to_line = (1000 * e for e in centreline_errors(truth, wall.centerline.points))
            at = worst_at(truth, wall.centerline.points)
            outcome = "imported"
            message = ""
        except ValueError as e:
            outcome = "refused"
            message = str(e).replace(str(folder) + "/", "")
        except Exception as e:  # noqa: BLE001 - a crash is a finding, not the end of the run
            outcome = "crashed"
            text = str(e).strip().splitlines()[0] if str(e).strip() else ""
            message = f"{type(e).__name__}: {text}"
        seconds = time.perf_counter() - start
        path.unlink()
        row = dict(surface=name, ends="/".join(spec.ends), source_mesh=spec.mesh,
                   voxel_mm=1000 * p["voxel"], slice_mm=1000 * p["slice_spacing"],
                   noise_mm=1000 * p["noise"], holes=len(info.get("hole_radii_mm", [])),
                   hole_radii_mm=" ".join(f"{r:.1f}" for r in info.get("hole_radii_mm", [])),
                   hole_perimeters_mm=" ".join(f"{r:.0f}"
                                               for r in info.get("hole_perimeters_mm", [])),
                   faces_meshed=info["faces_before_decimation"], faces=info["faces"],
                   pieces=info["pieces"], boundary_loops=info["boundary_loops"],
                   make_s=made, import_s=seconds, outcome=outcome,
                   to_truth_mm=to_truth, to_line_mm=to_line,
                   error_mm=max(to_truth, to_line), worst_at=at, message=message)
        if baseline:
            row["clean_error_mm"] = clean_error(spec, folder)
        rows.append(row)
        shown = message if outcome != "imported" else ""
        clean = f"{row['clean_error_mm']:>7.2f}" if baseline else ""
        print(f"{name:<22}{row['ends']:<22}{info['faces']:>9}{made:>10.1f}{seconds:>11.1f}"
              f"{to_truth:>10.2f}{to_line:>9.2f}{at:>6.2f}{clean}  {outcome} {shown}",
              flush=True)
    return rows


def summary(rows: list[dict]) -> None:
    imported = [r for r in rows if r["outcome"] == "imported"]
    e = np.array([r["error_mm"] for r in imported])
    within = int(np.sum(e < LIMIT_MM))
    refused = sum(r["outcome"] == "refused" for r in rows)
    crashed = sum(r["outcome"] == "crashed" for r in rows)
    print(f"\n{len(rows)} surfaces: within {LIMIT_MM:g} mm {within}, refused {refused}, "
          f"worse than {LIMIT_MM:g} mm {len(e) - within}"
          + (f", crashed {crashed}" if crashed else ""))
    if "clean_error_mm" in rows[0]:
        clean = np.array([r["clean_error_mm"] for r in rows])
        print(f"the same tubes' clean meshes (tube_set): within {LIMIT_MM:g} mm "
              f"{int(np.sum(clean < LIMIT_MM))}, refused {int(np.sum(np.isnan(clean)))}, "
              f"median {np.nanmedian(clean):.2f} mm, worst {np.nanmax(clean):.2f} mm")
    if len(e):
        print(f"imported: largest distance median {np.median(e):.2f} mm, worst {e.max():.2f} mm "
              f"({imported[int(np.argmax(e))]['surface']})")
    for r in rows:
        if r["outcome"] != "imported":
            print(f"  {r['surface']}: {r['outcome']}: {r['message']}")


def write_csv(rows: list[dict], path: str) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows({k: f"{v:.3f}" if isinstance(v, float) else v for k, v in row.items()}
                         for row in rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tubes", action="store_true", help="the 18 test tubes (default)")
    parser.add_argument("--random", type=int, default=0, metavar="N",
                        help="N random shapes from --first-seed on")
    parser.add_argument("--first-seed", type=int, default=30000)
    parser.add_argument("--only", metavar="NAMES", help="comma-separated surface names")
    parser.add_argument("--raw", action="store_true", help="skip the decimation")
    parser.add_argument("--baseline", action="store_true",
                        help="also import each tube's clean mesh and print its error")
    parser.add_argument("--csv", metavar="PATH", help="one row per surface")
    args = parser.parse_args()
    tubes = args.tubes or not args.random
    only = set(args.only.split(",")) if args.only else None
    chosen = surfaces(tubes, args.random, args.first_seed, only)
    with tempfile.TemporaryDirectory() as folder:
        rows = run(chosen, args.raw, Path(folder), args.baseline)
    summary(rows)
    if args.csv and rows:
        write_csv(rows, args.csv)


if __name__ == "__main__":
    main()
