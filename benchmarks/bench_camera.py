"""Milliseconds per camera frame, rendered from inside the default colon.

    python benchmarks/bench_camera.py [--frames 30] [--save DIR]

Scene: the capsule (models/capsule.sdf) on the centreline of the default colon, looking down
the lumen, and the colon's visual mesh as one visual on the world body; the camera's VTK
renderer with its point light. For each lens (120-degree pinhole, 172-degree fisheye, at
256 px) it prints the median time of colour + depth and of colour alone, the pinhole views
each frame needs and the pixels they render, and, with --save, writes the images as PNGs.
"""

import argparse
import dataclasses
import os
import time
from pathlib import Path

import cv2
import numpy as np

from capsule_drake.systems.camera import CameraConfig, LensRenderer
from capsule_drake.views import camera_scene
from capsule_drake.vision import LensConfig

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
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--save", type=Path, default=None, help="directory for PNGs")
    args = parser.parse_args()

    config = CameraConfig()
    diagram, context, plant, scene_graph = camera_scene(config=config)
    query_object = scene_graph.get_query_output_port().Eval(
        scene_graph.GetMyContextFromRoot(context))
    body_frame = plant.GetBodyFrameIdOrThrow(plant.GetBodyByName("capsule").index())
    X_BC = plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()

    print(f"load average before: {os.getloadavg()[0]:.2f} (2 cores; others' work inflates these)")
    print(f"{'lens':28s} {'views':>5s} {'view px':>8s} {'rgb+depth ms':>13s} "
          f"{'rgb ms':>7s} {'depth ms':>9s}")
    for name, (lens, scale) in LENSES.items():
        renderer = LensRenderer(dataclasses.replace(config, lens=lens,
                                                    face_resolution_scale=scale))
        rgb = lambda: renderer.render_rgba(query_object, body_frame, X_BC)  # noqa: E731
        depth = lambda: renderer.render_range(query_object, body_frame, X_BC)  # noqa: E731
        # Interleave the three measurements so a busy machine biases them alike.
        both_ms, rgb_ms, depth_ms = [], [], []
        for _ in range(3):
            both_ms.append(time_frames(lambda: (rgb(), depth()), args.frames // 3 + 1))
            rgb_ms.append(time_frames(rgb, args.frames // 3 + 1))
            depth_ms.append(time_frames(depth, args.frames // 3 + 1))
        pixels = sum(view.width * view.height for view in renderer.views)
        print(f"{name:28s} {len(renderer.views):5d} {pixels:8d} {np.median(both_ms):13.1f} "
              f"{np.median(rgb_ms):7.1f} {np.median(depth_ms):9.1f}")
        if args.save is not None:
            args.save.mkdir(parents=True, exist_ok=True)
            stem = name.replace(" ", "_")
            cv2.imwrite(str(args.save / f"{stem}_rgb.png"),
                        cv2.cvtColor(rgb(), cv2.COLOR_RGBA2BGR))
            rng = depth()
            shown = np.where(np.isfinite(rng), rng, 0.0)
            cv2.imwrite(str(args.save / f"{stem}_depth.png"),
                        np.clip(shown / config.far * 255.0, 0, 255).astype(np.uint8))


if __name__ == "__main__":
    main()
