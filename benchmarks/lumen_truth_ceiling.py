"""How close the seed's idea can come to the lumen truth at best: the centre of the
farthest part of the view, taken from the range image itself (no shading, no detector).

    .venv/bin/python benchmarks/lumen_truth_ceiling.py [--frames 200] [--seed 100]
        [--lens fisheye|pinhole]

With the light at the camera, the darkest region is the farthest one. This script takes that
principle at its ideal: for each of the evaluation's seeded poses (`evaluation.seeded_poses`,
the frames `capsule-sim eval-lumen` scores), the range-weighted centroid of the farthest
`q` of the field (q = 2, 5, 10, 20 %; `lumen_truth.far_region`, the image-side truth, which
takes the tenth), from the ray caster's exact range image, against the
lumen truth (the centreline point `lookahead` ahead, through the lens) at several lookaheads.
Any detector that finds the darkest region, however well, inherits these errors; what it
adds comes from the shading. Prints median, 90th percentile and the share within 4 % of the
image diagonal, over the frames with the truth in view.
"""

import argparse

import numpy as np

from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.perception.evaluation import seeded_poses
from capsule_drake.perception.lens import LensConfig
from capsule_drake.perception.lumen_truth import far_region, lumen_target, project_lumen
from capsule_drake.perception.raycast import RayCaster

QUANTILES = (0.02, 0.05, 0.10, 0.20)
LOOKAHEADS = (0.03, 0.05, 0.08)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--lens", choices=("fisheye", "pinhole"), default="fisheye")
    args = parser.parse_args()
    lens = LensConfig(model="pinhole_radtan") if args.lens == "pinhole" else LensConfig()
    config = CameraConfig(lens=lens)
    errors = {(la, q): [] for la in LOOKAHEADS for q in QUANTILES}
    diagonal = None
    for _, colon, poses in seeded_poses(args.frames, 5, args.seed):
        caster = RayCaster(colon.visual_mesh(), config.lens, far=config.far)
        diagonal = float(np.hypot(*caster.field.shape))
        for _, X_WC, _ in poses:
            range_image = caster.range_image(caster.cast(X_WC))
            for la in LOOKAHEADS:
                point, _ = lumen_target(colon, X_WC.translation(), X_WC.rotation().col(2), la)
                pixel, visible = project_lumen(caster.lens, X_WC, point, range_image)
                if not visible:
                    continue
                for q in QUANTILES:
                    centre = far_region(range_image, caster.field, config.far, q,
                                        lens=caster.lens).pixel
                    errors[la, q].append(np.linalg.norm(centre - pixel) / diagonal)
    print(f"The farthest part of the view against the lumen truth: colon seeds {args.seed}-"
          f"{args.seed + 4}, {args.frames} poses, {args.lens} lens "
          "(% of the image diagonal, over the frames with the truth in view)")
    print(f"{'lookahead':>9s} {'farthest':>8s} {'frames':>6s} {'median':>6s} {'p90':>6s} "
          f"{'<= 4 %':>6s}")
    for (la, q), e in errors.items():
        e = np.array(e)
        print(f"{100 * la:7.0f}cm {100 * q:7.0f}% {len(e):6d} {100 * np.median(e):5.1f}% "
              f"{100 * np.percentile(e, 90):5.1f}% {100 * np.mean(e <= 0.04):5.0f}%")


if __name__ == "__main__":
    main()
