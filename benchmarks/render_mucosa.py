"""Render the textured colon wall with Drake's VTK engine: a check of the mucosa's look.

Usage: python benchmarks/render_mucosa.py [--seed 0] [--out-dir mucosa_renders] [--size 256]
       [--fov 100] [--meshcat-html mucosa.html]

A minimal scene: the colon's visual OBJ on the world body with empty illustration and
perception properties (so its MTL material and texture are used) and a RenderEngineVtk lit
only by a point light at the camera with distance falloff, as the capsule's own LEDs light
the real colon (the lumen far away stays dark). Pinhole views from the centreline looking
down the lumen, one per segment, plus close-ups from near the wall looking along it; each is
written as a PNG, and all of them as one contact sheet (`contact_sheet.png`, labelled).
Prints the asset build time (cold cache) and the milliseconds per colour frame.
With --meshcat-html the same mesh goes to Meshcat and the page is saved as static HTML.
"""

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from pydrake.geometry import (ClippingRange, ColorRenderCamera, GeometryInstance,
                              IllustrationProperties, LightParameter, MakeRenderEngineVtk,
                              Mesh, PerceptionProperties, RenderCameraCore,
                              RenderEngineVtkParams)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import CameraInfo

from capsule_drake.anatomy import ColonParams, build_colon, colon_assets

RENDERER = "vtk"


def make_scene(visual_obj: Path, meshcat=None):
    """Diagram with the colon mucosa as a visual on the world body and a VTK renderer whose
    only light is a point light at the camera. Returns (diagram, scene_graph)."""
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, 0.0)
    mucosa = GeometryInstance(RigidTransform(), Mesh(str(visual_obj)), "colon_mucosa")
    # Empty property sets: the look comes from the OBJ's own material (MTL + texture).
    mucosa.set_illustration_properties(IllustrationProperties())
    mucosa.set_perception_properties(PerceptionProperties())
    plant.RegisterVisualGeometry(plant.world_body(), mucosa)
    plant.Finalize()
    # A light at the camera with 1 / (1 + 100 d^2) falloff (half intensity at 10 cm): the
    # near wall is bright, the lumen ahead dark. Giving a light replaces the default ones.
    light = LightParameter(type="point", frame="camera", attenuation_values=[1.0, 0.0, 100.0],
                           intensity=1.0)
    scene_graph.AddRenderer(RENDERER, MakeRenderEngineVtk(RenderEngineVtkParams(
        lights=[light], default_clear_color=[0.0, 0.0, 0.0])))
    if meshcat is not None:
        from pydrake.geometry import MeshcatVisualizer
        MeshcatVisualizer.AddToBuilder(builder, scene_graph, meshcat)
    return builder.Build(), scene_graph


def camera_pose(eye, forward, up_hint) -> RigidTransform:
    """X_WC of a Drake camera (+z forward, +x right, +y down) at `eye` looking along
    `forward`, with `up_hint` as close to image-up as possible."""
    z = forward / np.linalg.norm(forward)
    y = -(up_hint - (up_hint @ z) * z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    return RigidTransform(RotationMatrix(np.column_stack([x, y, z])), eye)


def views(colon):
    """(label, X_WC) pairs: down the lumen mid-segment, and near-wall close-ups."""
    cl = colon.centerline
    out = []
    for name, (s0, s1) in cl.segment_ranges().items():
        s = 0.5 * (s0 + s1)
        t, n, b = (v[0] for v in cl.frame_at(np.array([s])))
        out.append((f"{name} s={s:.2f}", camera_pose(cl.point_at(s), t, b)))
    for name in ("descending", "transverse"):
        s0, s1 = cl.segment_ranges()[name]
        s = 0.5 * (s0 + s1)
        t, n, b = (v[0] for v in cl.frame_at(np.array([s])))
        # 70 % of the way to the wall, turned 35 degrees toward it: the wall fills the view.
        radius = colon.wall_radius(np.array([s]), np.array([0.0]))[0]
        eye = cl.point_at(s) + 0.7 * radius * n
        forward = np.cos(np.radians(35)) * t + np.sin(np.radians(35)) * n
        out.append((f"{name} wall", camera_pose(eye, forward, b)))
    # Looking straight across the lumen at theta = 0 (the texture seam, u = 0 = 1).
    s0, s1 = cl.segment_ranges()["transverse"]
    s = 0.5 * (s0 + s1)
    t, n, b = (v[0] for v in cl.frame_at(np.array([s])))
    out.append(("seam theta=0", camera_pose(cl.point_at(s) - 0.3 * colon.wall_radius(
        np.array([s]), np.array([0.0]))[0] * n, n, t)))
    return out


def render(diagram, scene_graph, poses, size: int, fov_deg: float, repeats: int = 5):
    """Colour images (RGB uint8) for `poses` and the median milliseconds per frame."""
    context = diagram.CreateDefaultContext()
    query = scene_graph.get_query_output_port().Eval(
        scene_graph.GetMyContextFromRoot(context))
    core = RenderCameraCore(RENDERER, CameraInfo(size, size, np.radians(fov_deg)),
                            ClippingRange(0.0005, 1.0), RigidTransform())
    camera = ColorRenderCamera(core, False)
    world = scene_graph.world_frame_id()
    images, times = [], []
    for X_WC in poses:
        query.RenderColorImage(camera, world, X_WC)  # warm-up (texture upload, first frame)
        for _ in range(repeats):
            start = time.perf_counter()
            image = query.RenderColorImage(camera, world, X_WC)
            times.append(time.perf_counter() - start)
        images.append(np.array(image.data, copy=True)[..., :3])
    return images, 1e3 * statistics.median(times)


def contact_sheet(images, labels, columns: int = 4) -> np.ndarray:
    """Images in a grid with their labels, RGB."""
    size = images[0].shape[0]
    rows = -(-len(images) // columns)
    sheet = np.zeros((rows * size, columns * size, 3), np.uint8)
    for k, (image, label) in enumerate(zip(images, labels)):
        r, c = divmod(k, columns)
        tile = np.ascontiguousarray(image)
        cv2.putText(tile, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1,
                    cv2.LINE_AA)
        sheet[r * size:(r + 1) * size, c * size:(c + 1) * size] = tile
    return sheet


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out-dir", default="mucosa_renders")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--fov", type=float, default=100.0, help="vertical field of view [deg]")
    parser.add_argument("--meshcat-html", default=None,
                        help="also draw the colon in Meshcat and save the page here")
    args = parser.parse_args()
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)

    params = ColonParams(seed=args.seed)
    with tempfile.TemporaryDirectory() as cache:
        start = time.perf_counter()
        colon_assets(params, cache_dir=cache)
        print(f"colon assets (cold cache, texture included): "
              f"{time.perf_counter() - start:.2f} s")
    assets = colon_assets(params)
    colon = build_colon(params)
    diagram, scene_graph = make_scene(assets.visual_obj)
    labelled = views(colon)
    images, ms = render(diagram, scene_graph, [pose for _, pose in labelled], args.size,
                        args.fov)
    print(f"colour frame {args.size} px, fov {args.fov:.0f} deg: {ms:.1f} ms (median)")
    labels = [label for label, _ in labelled]
    for label, image in zip(labels, images):
        name = label.split()[0] + ("_wall" if "wall" in label else "")
        cv2.imwrite(str(out / f"{name}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    sheet = contact_sheet(images, labels)
    cv2.imwrite(str(out / "contact_sheet.png"), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    print(f"wrote {len(images)} views and contact_sheet.png to {out}")

    if args.meshcat_html:
        from pydrake.geometry import Meshcat
        meshcat = Meshcat()
        diagram, _ = make_scene(assets.visual_obj, meshcat)
        diagram.ForcedPublish(diagram.CreateDefaultContext())
        cl = colon.centerline
        s = 0.5 * sum(cl.segment_ranges()["descending"])
        meshcat.SetCameraPose(camera_in_world=cl.point_at(s),
                              target_in_world=cl.point_at(s + 0.05))
        Path(args.meshcat_html).write_text(meshcat.StaticHtml())
        print(f"wrote {args.meshcat_html}")


if __name__ == "__main__":
    main()
