"""Milliseconds per camera frame, rendered from inside the default colon.

    python benchmarks/bench_camera.py [--positions 8] [--frames 9] [--save DIR]

Scene: the capsule (models/capsule.sdf) looking down the lumen of the default colon at
`--positions` places spread along it; the camera wall as the station builds it (windows, one
VTK renderer each, with the point light), each frame drawn with the window the camera is
in. For each lens (120-degree pinhole, 172-degree fisheye, at 256 px) it prints the pinhole
views a frame needs and the pixels they render, then the median time of colour + depth, of
colour alone and of depth alone over all places, and the worst place's median. --save
writes the images of the first place as PNGs.
"""

import argparse
import dataclasses
import os
import time
from pathlib import Path

import cv2
import numpy as np

from capsule_drake.anatomy import ColonParams, load_colon
from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.capsule.camera_renderer import LensRenderer
from capsule_drake.capsule.model import CAPSULE_BODY, start_pose
from capsule_drake.perception import LensConfig
from capsule_drake.perception.views import camera_scene

# name: (lens, face_resolution_scale)
LENSES = {
    "pinhole 120 deg": (LensConfig(model="pinhole_radtan", fov_deg=120.0), 1.0),
    "pinhole 120 deg radtan": (LensConfig(model="pinhole_radtan", fov_deg=120.0,
                                          radtan_coefficients=[-0.28, 0.07, 0.0, 0.0, 0.0]),
                               1.0),
    "fisheye 172 deg": (LensConfig(model="equidistant", fov_deg=172.0), 1.0),
    "fisheye 172 deg, faces x0.7": (LensConfig(model="equidistant", fov_deg=172.0), 0.7),
}


def time_frames(function, frames: int) -> float:
    """Median wall time of `function()` in ms, after two warm-up calls."""
    function()
    function()
    times = []
    for _ in range(frames):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--positions", type=int, default=8)
    parser.add_argument("--frames", type=int, default=9, help="per place and measurement")
    parser.add_argument("--save", type=Path, default=None, help="directory for PNGs")
    args = parser.parse_args()

    config = CameraConfig()
    diagram, context, plant, scene_graph, walls = camera_scene(config=config)
    colon, _ = load_colon(ColonParams())
    body = plant.GetBodyByName(CAPSULE_BODY)
    plant_context = plant.GetMyMutableContextFromRoot(context)
    body_frame = plant.GetBodyFrameIdOrThrow(body.index())
    X_BC = plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()
    places = np.linspace(0.1, colon.centerline.length - 0.1, args.positions)

    print(f"load average before: {os.getloadavg()[0]:.2f} (2 cores; others' work inflates these)")
    triangles = walls.windows.triangles
    print(f"camera wall: {len(triangles)} windows of {triangles.min()}-{triangles.max()} "
          f"triangles (median {int(np.median(triangles))}); {args.positions} places")
    print(f"{'lens':28s} {'views':>5s} {'view px':>8s} {'rgb+depth ms':>13s} "
          f"{'rgb ms':>7s} {'depth ms':>9s}   worst place: rgb, depth ms")
    for name, (lens, scale) in LENSES.items():
        renderer = LensRenderer(dataclasses.replace(config, lens=lens,
                                                    face_resolution_scale=scale))
        both_ms, rgb_ms, depth_ms = [], [], []
        for place, s in enumerate(places):
            X_WB = start_pose(colon, s)
            plant.SetFreeBodyPose(plant_context, body, X_WB)
            query_object = scene_graph.get_query_output_port().Eval(
                scene_graph.GetMyContextFromRoot(context))
            window = walls(X_WB.multiply(X_BC.translation()))
            rgb = lambda: renderer.render_rgba(query_object, body_frame, X_BC,  # noqa: E731
                                               renderer=window)
            depth = lambda: renderer.render_range(query_object, body_frame,  # noqa: E731
                                                  X_BC, renderer=window)
            # Interleaved, so a busy machine biases the three alike.
            both_ms.append(time_frames(lambda: (rgb(), depth()), args.frames))
            rgb_ms.append(time_frames(rgb, args.frames))
            depth_ms.append(time_frames(depth, args.frames))
            if args.save is not None and place == 0:
                args.save.mkdir(parents=True, exist_ok=True)
                stem = name.replace(" ", "_").replace(",", "")
                cv2.imwrite(str(args.save / f"{stem}_rgb.png"),
                            cv2.cvtColor(rgb(), cv2.COLOR_RGBA2BGR))
                shown = np.where(np.isfinite(depth()), depth(), 0.0)
                cv2.imwrite(str(args.save / f"{stem}_depth.png"),
                            np.clip(shown / config.far * 255.0, 0, 255).astype(np.uint8))
        pixels = sum(view.width * view.height for view in renderer.views)
        print(f"{name:28s} {len(renderer.views):5d} {pixels:8d} {np.median(both_ms):13.1f} "
              f"{np.median(rgb_ms):7.1f} {np.median(depth_ms):9.1f}   "
              f"{np.max(rgb_ms):.1f}, {np.max(depth_ms):.1f}")


if __name__ == "__main__":
    main()
