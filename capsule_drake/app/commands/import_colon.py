"""`capsule-sim import-colon`: a user's colon mesh into the cache."""

from __future__ import annotations

import sys

import numpy as np

from capsule_drake.anatomy.imported import import_colon_mesh, write_import
from capsule_drake.app.outputs import plan_outputs
from capsule_drake.app.run import StepBar
from capsule_drake.scenario import ScenarioError
from capsule_drake.app.commands.common import IMPORT_OUTPUTS, _claim


def _import_colon(args) -> int:
    stages = ["reading", "repairing", "centreline", "wall table"]
    bar = StepBar(len(stages), enabled=not args.quiet, unit="stages")

    def say(text):  # the stages before this one are done
        bar.show(next((k for k, name in enumerate(stages) if text.startswith(name)), 0), text)

    if not (args.scale > 0.0 and np.isfinite(args.scale)):
        raise ScenarioError(f"--scale must be > 0, got {args.scale}")
    if not 1000 <= args.max_faces <= 10_000_000:
        raise ScenarioError(f"--max-faces must be 1000-10000000, got {args.max_faces}")
    _claim(plan_outputs(args.out, args.force, outputs=IMPORT_OUTPUTS, inputs=[args.mesh]))
    try:
        wall = import_colon_mesh(args.mesh, args.scale, args.max_faces, args.reverse,
                                 progress=say)
    except ValueError as e:  # MeshImportError, or a mesh with no tube to follow
        if not args.quiet:
            print(file=sys.stderr)
        raise ScenarioError(str(e).splitlines()[0]) from None
    summary = write_import(wall, args.out)
    bar.show(len(stages), "done")
    radius = summary["radius_m"]
    print(f"imported {args.mesh}: {summary['faces']} faces"
          f"{' (textured)' if summary['textured'] else ''}; centreline "
          f"{100 * summary['centreline_length_m']:.1f} cm, radius {1000 * radius['min']:.1f}-"
          f"{1000 * radius['max']:.1f} mm (median {1000 * radius['median']:.1f})")
    for line in wall.report.lines():
        print(f"  repaired: {line}")
    print(f"wrote {args.out}/: wall.obj, centerline.npz, wall_radius.npz, import.json; "
          f"use it with colon: {{source: !Imported {{path: {args.out}}}}}")
    return 0
