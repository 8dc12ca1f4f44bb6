"""Contact sheet of polyps of each Paris type and size class, and of diverticula, in the capsule camera's frames.

    .venv/bin/python benchmarks/lesion_sheet.py [--out docs/lesions_contact_sheet.jpg]
        [--seed 0] [--segment descending] [--back 0.04]

Each row a Paris type (0-Is, 0-IIa, 0-Ip), each column a size (4, 8 and 15 mm: diminutive,
small, large), then a row of diverticula (necks of 5, 7.5 and 10 mm), each lesion placed alone on the wall of the colon of `--seed` and seen from
the centreline `--back` metres before it, looking down the lumen, through the default
fisheye. Left of each pair the colour frame, right the same frame with the polyp's pixels
of the label image outlined (the instance mask a dataset records).
"""

import argparse
from pathlib import Path

import cv2
import numpy as np

from capsule_drake.anatomy import load_colon
from capsule_drake.anatomy.params import ColonParams, Lesions, PlacedLesion
from capsule_drake.anatomy.source import lesion_scene
from capsule_drake.capsule.camera import capsule_camera_for_frame
from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.capsule.camera_walls import lesion_labels
from capsule_drake.capsule.model import CAPSULE_BODY, start_pose
from capsule_drake.perception.views import camera_scene

KINDS = ("0-Is", "0-IIa", "0-Ip", "diverticulum")
SIZES_MM = (4.0, 8.0, 15.0)
NECKS_MM = (5.0, 7.5, 10.0)


def frame(seed: int, segment: str, kind: str, size: float, back: float, around: float):
    params = ColonParams(seed=seed, lesions=Lesions(drawn=False, placed=[PlacedLesion(
        kind=kind, size_mm=size, segment=segment, along=0.5, around_deg=around)]))
    colon, _ = load_colon(params)
    polyp = lesion_scene(params).lesions[0]
    config = CameraConfig()
    diagram, context, plant, scene_graph, renderer_for = camera_scene(0.3, config, params)
    camera = capsule_camera_for_frame(plant, plant.GetFrameByName("camera"), config,
                                      renderer_for, static_scene=True)
    body = plant.GetBodyByName(CAPSULE_BODY)
    plant.SetFreeBodyPose(plant.GetMyMutableContextFromRoot(context), body,
                          start_pose(colon, polyp.s - back))
    query = scene_graph.get_query_output_port().Eval(scene_graph.GetMyContextFromRoot(context))
    renderer = camera.renderer_name(query)
    frame_id = plant.GetBodyFrameIdOrThrow(body.index())
    X_BC = plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()
    rgb = camera.renderer.render_rgba(query, frame_id, X_BC, renderer=renderer)[..., :3].copy()
    label = camera.renderer.render_label(query, frame_id, X_BC, renderer=renderer)
    mask = label == next(iter(lesion_labels([polyp])))
    return rgb, mask


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/lesions_contact_sheet.jpg"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--segment", default="descending")
    parser.add_argument("--back", type=float, default=0.04)
    parser.add_argument("--around", type=float, default=150.0,
                        help="degrees from the floor around the lumen")
    args = parser.parse_args(argv)
    rows = []
    for kind in KINDS:
        tiles = []
        for size in NECKS_MM if kind == "diverticulum" else SIZES_MM:
            rgb, mask = frame(args.seed, args.segment, kind, size, args.back, args.around)
            outlined = rgb.copy()
            contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL,
                                           cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(outlined, contours, -1, (0, 255, 0), 1)
            for image in (rgb, outlined):
                cv2.putText(image, f"{kind} {size:g} mm", (6, 16), cv2.FONT_HERSHEY_SIMPLEX,
                            0.45, (255, 255, 255), 1, cv2.LINE_AA)
            cv2.putText(outlined, f"mask {int(mask.sum())} px", (6, 248),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
            tiles += [rgb, outlined]
            print(f"{kind:12s} {size:4g} mm: {int(mask.sum()):5d} mask px")
        rows.append(np.hstack(tiles))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), cv2.cvtColor(np.vstack(rows), cv2.COLOR_RGB2BGR))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
