"""`capsule-sim eval-lumen`: the lumen detectors scored on recorded datasets."""

from __future__ import annotations

import sys

from capsule_drake.app.eval_lumen import OUTPUTS as EVAL_OUTPUTS
from capsule_drake.app.eval_lumen import EvaluationStopped, evaluate_paths
from capsule_drake.perception.evaluation import IMAGE_CONDITIONS, LIGHT_CONDITIONS, RENDERERS
from capsule_drake.perception.lumen import load_detector
from capsule_drake.scenario import ScenarioError
from capsule_drake.app.commands.common import _output_folder


def _eval_lumen(args) -> int:
    # Bounds: a frame takes ~0.1 s to render and each colon ~5 s to build.
    if not (1 <= args.frames <= 100_000 and 1 <= args.colons <= 1000):
        raise ScenarioError(f"--frames must be 1-100000 and --colons 1-1000, got "
                            f"{args.frames} and {args.colons}")
    if not 0 <= args.seed < 2**32:
        raise ScenarioError(f"--seed must be in [0, 2^32), got {args.seed}")
    if not 0.0 <= args.wall_fraction <= 1.0:
        raise ScenarioError(f"--wall-fraction must be in [0, 1], got {args.wall_fraction}")

    names = args.detector or ["net", "core", "gaussian"]
    try:
        detectors = {name: load_detector(name) for name in names}
    except ValueError as e:
        raise ScenarioError(f"--detector: {e}") from None
    renderers = RENDERERS if args.renderer == "both" else (args.renderer,)
    lenses = ("fisheye", "pinhole") if args.lens == "both" else (args.lens,)
    wanted = None if args.conditions == "all" else [c.strip() for c in
                                                     args.conditions.split(",") if c.strip()]
    known = IMAGE_CONDITIONS + LIGHT_CONDITIONS
    if wanted is not None and (not wanted or any(c not in known for c in wanted)):
        raise ScenarioError(f"--conditions: expected 'all' or a comma-separated list of "
                            f"{', '.join(known)}; got {args.conditions!r}")
    light = [c for c in wanted or () if c in LIGHT_CONDITIONS]
    if light and args.renderer == "vtk":
        raise ScenarioError(f"--conditions {','.join(light)}: the light conditions are only "
                            "with the ray caster (--renderer raycast or both)")
    out_dir = _output_folder(args, "eval_lumen", "eval", outputs=EVAL_OUTPUTS)
    try:
        failing = evaluate_paths(detectors, renderers, lenses, wanted or known, out_dir,
                                 frames=args.frames, colons=args.colons, seed=args.seed,
                                 wall_fraction=args.wall_fraction, quiet=args.quiet)
    except EvaluationStopped as e:   # a detector failed: what was scored is on disk
        print(f"capsule-sim: error: {e}", file=sys.stderr)
        return 1
    print(f"{'every condition meets' if not failing else f'{len(failing)} condition(s) miss'}"
          f" the targets (against the far region: median <= 1.5 %, p90 <= 4 %, detected >= "
          f"95 %, false positives <= 10 %; against the point 5 cm ahead: median / p90 <= "
          f"1.5 / 5 % fisheye, 3 / 8 % pinhole); tables.md, results.json and contact sheets "
          f"in {out_dir}/")
    return 0
