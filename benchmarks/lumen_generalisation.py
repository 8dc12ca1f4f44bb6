"""Lumen detectors on optics nobody tuned or trained them on, against the image-side truth.

`capsule-sim eval-lumen` scores the detectors through the two lenses the project uses (the
172-degree fisheye and the 120-degree pinhole, both 256 px), and the learned detector
(`net`, perception/lumen_net.py) was trained through exactly those. This script renders the
same kind of frames through other optics: a narrower fisheye (140 degrees), a wider and a
narrower pinhole (140 and 90 degrees), and the default fisheye at 400 px (another
resolution), on colon seeds 100-104 (the reported seeds, which no detector was tuned or
trained on), under the ray caster's nominal light, its random light (every shading group at
once) and the simulator's renderer with every image condition at once.

    python benchmarks/lumen_generalisation.py [--frames 100] [--detector net --detector core]

Prints per optics, image path and detector: median / p90 error (% of the diagonal, against
the far region), detection (% of frames with a lumen in view) and false positives (% of
frames without one).
"""

import argparse
import sys

from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.perception.evaluation import condition_frames, evaluate
from capsule_drake.perception.lens import LensConfig
from capsule_drake.perception.lumen import load_detector

OPTICS = {
    "fisheye 140 deg": LensConfig(fov_deg=140.0),
    "fisheye 172 deg, 400 px": LensConfig(width=400, height=400),
    "pinhole 90 deg": LensConfig(model="pinhole_radtan", fov_deg=90.0),
    "pinhole 140 deg": LensConfig(model="pinhole_radtan", fov_deg=140.0),
}
PATHS = {"raycast": ("nominal", "light_all"), "vtk": ("everything",)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--detector", action="append")
    args = parser.parse_args(argv)
    names = args.detector or ["net", "core", "gaussian"]
    detectors = {name: load_detector(name) for name in names}
    print("| optics | image path, condition | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for optics, lens in OPTICS.items():
        config = CameraConfig(lens=lens)
        for renderer, conditions in PATHS.items():
            frames = condition_frames(args.frames, 5, args.seed, renderer, conditions, config)
            for condition, shown in frames.items():
                cells = []
                for detector in detectors.values():
                    s = evaluate(shown, detector).summary()
                    cells.append(f"{100 * s['median_error']:.1f} / {100 * s['p90_error']:.1f} / "
                                 f"{100 * s['detection_rate']:.0f} / "
                                 f"{100 * s['false_positive_rate']:.0f}")
                print(f"| {optics} | {renderer} {condition} | " + " | ".join(cells) + " |",
                      flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
