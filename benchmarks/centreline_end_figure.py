"""A figure of one tube's end: the wall cut through its true centre line, the true line, and
the importer's line with and without one of its end steps (settled open ends, or the
capsule-end fit of round caps), to look at what a change did.

Run: python benchmarks/centreline_end_figure.py SEED head|tail [--step settle|capsule]
     [--out docs/images/open_end_settled.png]
The tube is tube_set.random_spec(SEED) (tests/tube_set.py), imported twice."""

import argparse
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from capsule_drake.anatomy import centerline_extraction as ce  # noqa: E402
from capsule_drake.anatomy.imported import import_colon_mesh  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from tube_set import densify, make_tube, random_spec  # noqa: E402

FLAGS = {"settle": "SETTLE_OPEN_ENDS", "capsule": "FIT_ROUND_CAPS"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seed", type=int)
    parser.add_argument("end", choices=["head", "tail"])
    parser.add_argument("--step", choices=sorted(FLAGS), default="settle")
    parser.add_argument("--out", default="open_end.png")
    parser.add_argument("--reach", type=float, default=0.08, help="[m] shown before the end")
    args = parser.parse_args()
    spec = random_spec(args.seed)
    tube = make_tube(spec)
    lines = {}
    with tempfile.TemporaryDirectory() as folder:
        path = tube.write(folder)
        for on in (False, True):
            setattr(ce, FLAGS[args.step], on)
            lines[on] = import_colon_mesh(path, tube.scale).centerline.points
    truth = tube.truth if args.end == "tail" else tube.truth[::-1]
    end, t = truth[-1], truth[-1] - truth[-4]
    t /= np.linalg.norm(t)
    for on, line in lines.items():   # each line from the other end to this one
        lines[on] = line if np.linalg.norm(line[-1] - end) < np.linalg.norm(line[0] - end) \
            else line[::-1]
    # The plane through the true end holding its tangent and the worse line's largest
    # departure from the truth near the end.
    before = lines[False]
    near = before[np.linalg.norm(before - end, axis=1) < args.reach]
    gap = near - densify(truth)[cKDTree(densify(truth)).query(near)[1]]
    side = gap[np.argmax(np.linalg.norm(gap, axis=1))]
    side = side - (side @ t) * t
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-9 else np.cross(t, [0, 0, 1])
    normal = np.cross(t, side)
    mesh = trimesh.Trimesh(tube.mesh.vertices * tube.scale, tube.mesh.faces, process=False)
    cut = mesh.section(plane_origin=end, plane_normal=normal)
    to2d = lambda p: np.column_stack([(p - end) @ t, (p - end) @ side]) * 1000.0  # noqa: E731
    fig, ax = plt.subplots(figsize=(7, 4.5))
    if cut is not None:
        for entity in cut.entities:
            q = to2d(cut.vertices[entity.points])
            keep = q[:, 0] > -1000 * args.reach - 10
            ax.plot(q[keep, 0], q[keep, 1], color="0.6", lw=1.0)
    show = lambda p: p[np.linalg.norm(p - end, axis=1) < args.reach + 0.01]  # noqa: E731
    for points, style, label in ((truth, "k-", "true centre line"),
                                 (lines[False], "C3--", f"without {FLAGS[args.step]}"),
                                 (lines[True], "C0-", f"with {FLAGS[args.step]}")):
        q = to2d(show(points))
        ax.plot(q[:, 0], q[:, 1], style, lw=1.6, label=label)
    ax.set_xlabel("along the true end's tangent [mm]")
    ax.set_ylabel("across it [mm]")
    ax.set_xlim(-1000 * args.reach, 15)
    ax.set_aspect("equal")
    ax.legend(loc="lower left", fontsize=8)
    ax.set_title(f"seed {args.seed}, {args.end} ({spec.ends[0 if args.end == 'head' else 1]} end; "
                 f"flare {spec.flare}, bend {spec.end_bend})", fontsize=9)
    fig.tight_layout()
    fig.savefig(args.out, dpi=130)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
