"""Contact sheet of capsule camera views along the default colon (for docs/models/sensors.md,
"Views along the colon").

    .venv/bin/python benchmarks/contact_sheet.py [--out docs/contact_sheet.png] [--seed 0]

Green cross: the lumen ground truth (the centerline point 5 cm ahead, projected through the
lens). Blue circle: the darkest spot of the blurred image. Prints their distance per view.
"""

import argparse
import dataclasses
from pathlib import Path

import cv2
import numpy as np

from capsule_drake.anatomy import load_colon
from capsule_drake.perception.views import contact_sheet, darkest_spot, views_along_colon
from capsule_drake.scenario import load_scenario


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/contact_sheet.png"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    scenario = load_scenario()
    scenario = dataclasses.replace(scenario, colon=dataclasses.replace(scenario.colon,
                                                                       seed=args.seed))
    colon, _ = load_colon(scenario.colon)
    length = colon.centerline.length
    s_values = np.linspace(0.08, length - 0.08, 12)
    views = views_along_colon(scenario, s_values)
    for view in views:
        gap = np.linalg.norm(darkest_spot(view.rgb, view.mask) - view.lumen_pixel)
        print(f"{view.segment:11s} s = {100 * view.s:5.1f} cm  lumen visible: "
              f"{view.lumen_visible!s:5s}  darkest spot to lumen truth: {gap:5.1f} px")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), cv2.cvtColor(contact_sheet(views), cv2.COLOR_RGB2BGR))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
