"""Camera views along the colon with their lumen ground truth (contact sheets, checks)."""

import dataclasses

import cv2
import numpy as np
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.anatomy import ColonParams, load_colon
from capsule_drake.capsule.camera import capsule_camera_for_frame
from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.capsule.camera_walls import add_camera_walls
from capsule_drake.capsule.model import CAPSULE_BODY, start_pose
from capsule_drake.models import configure_parser, model_url
from capsule_drake.scene_geometry import add_colon_visuals
from capsule_drake.perception.lumen import masked_blur
from capsule_drake.perception.lumen_truth import lumen_target, project_lumen


@dataclasses.dataclass
class View:
    """One rendered view: where it was taken and what the camera saw."""

    s: float                  # arc length of the capsule's centre (m)
    segment: str
    rgb: np.ndarray           # (H, W, 3) uint8
    depth: np.ndarray         # (H, W) float32, range along the ray (m)
    lumen_pixel: np.ndarray   # (2,) lumen truth (px)
    lumen_visible: bool
    mask: np.ndarray          # (H, W) bool, the pixels the lens sees


def camera_scene(start_s: float = 0.30, config: CameraConfig | None = None,
                 colon: ColonParams | None = None):
    """A minimal scene for camera checks and benchmarks: the capsule at `start_s` in the
    colon of `colon` (default: the default colon), whose wall the camera sees as in the
    station (windows and their renderers, from `config`), with no EPM, sensors or magnet.

    Returns (diagram, context, plant, scene_graph, renderer_for), renderer_for(p_WC) naming
    the renderer for a camera at p_WC.
    """
    colon_params = colon if colon is not None else ColonParams()
    colon, _ = load_colon(colon_params)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(MultibodyPlantConfig(time_step=0.001), builder)
    configure_parser(Parser(plant)).AddModels(url=model_url("capsule.sdf"))
    add_colon_visuals(plant, colon_params, colon, perception=False)
    renderer_for = add_camera_walls(plant, scene_graph, colon_params, colon,
                                    config or CameraConfig())
    plant.Finalize()
    plant.SetDefaultFloatingBaseBodyPose(plant.GetBodyByName(CAPSULE_BODY),
                                         start_pose(colon, start_s))
    diagram = builder.Build()
    return diagram, diagram.CreateDefaultContext(), plant, scene_graph, renderer_for


def darkest_spot(rgb: np.ndarray, mask: np.ndarray | None = None, blur_px: float = 8.0):
    """(u, v) of the darkest spot of a heavily blurred grey image: the simplest lumen cue
    with a light at the lens (docs/sources.md section 5). `mask` marks the pixels the lens sees;
    the blur is normalised by it, so the black surround of a fisheye's image circle does not
    darken the rim."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    if mask is None:
        mask = np.ones(grey.shape, dtype=bool)
    grey = masked_blur(grey, mask.astype(np.float32), blur_px)
    grey[~mask] = np.inf
    v, u = np.unravel_index(np.argmin(grey), grey.shape)
    return np.array([u, v], dtype=float)


def views_along_colon(scenario, s_values, tilt_deg: float = 0.0,
                      offset: float = 0.0) -> list[View]:
    """Renders the capsule camera at each arc length of the scenario's colon (its camera,
    or the default one), looking down the colon (tilted by `tilt_deg` about the camera's
    x axis, shifted `offset` metres off the centerline)."""
    config = scenario.capsule.camera or CameraConfig()
    colon, _ = load_colon(scenario.colon)
    diagram, context, plant, scene_graph, renderer_for = camera_scene(
        scenario.capsule.start_s, config, scenario.colon)
    camera = capsule_camera_for_frame(plant, plant.GetFrameByName("camera"), config,
                                      renderer_for, static_scene=True)
    plant_context = plant.GetMyMutableContextFromRoot(context)
    body = plant.GetBodyByName(CAPSULE_BODY)
    frame_id = plant.GetBodyFrameIdOrThrow(body.index())
    X_BC = plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()
    tilt = RigidTransform(RotationMatrix(RollPitchYaw(np.radians(tilt_deg), 0, 0)), [0, 0, 0])
    _, mask = camera.lens.pixel_rays()
    views = []
    for s in s_values:
        X_WB = start_pose(colon, s).multiply(tilt)
        X_WB.set_translation(X_WB.translation() + offset * X_WB.rotation().col(0))
        plant.SetFreeBodyPose(plant_context, body, X_WB)
        query = scene_graph.get_query_output_port().Eval(
            scene_graph.GetMyContextFromRoot(context))
        renderer = camera.renderer_name(query)
        rgb = camera.renderer.render_rgba(query, frame_id, X_BC,
                                          renderer=renderer)[:, :, :3].copy()
        depth = camera.renderer.render_range(query, frame_id, X_BC, renderer=renderer)
        X_WC = X_WB.multiply(X_BC)
        point, _ = lumen_target(colon, X_WC.translation(), X_WC.rotation().col(2),
                                scenario.capsule.lumen_lookahead)
        pixel, visible = project_lumen(camera.lens, X_WC, point, depth, depth_is_range=True)
        views.append(View(float(s), colon.centerline.segment_at(float(s)), rgb, depth,
                          pixel, bool(visible), mask))
    return views


def contact_sheet(views: list[View], columns: int = 4) -> np.ndarray:
    """The views tiled into one RGB image, each labelled with its segment and arc length,
    the lumen truth as a green cross and the darkest spot as a blue circle."""
    tiles = []
    for view in views:
        tile = view.rgb.copy()
        if view.lumen_visible:
            cv2.drawMarker(tile, tuple(int(round(x)) for x in view.lumen_pixel), (0, 255, 0),
                           cv2.MARKER_CROSS, 18, 2)
        u, v = darkest_spot(view.rgb, view.mask)
        cv2.circle(tile, (int(u), int(v)), 7, (60, 140, 255), 2)
        cv2.putText(tile, f"{view.segment} s={100 * view.s:.0f} cm", (6, 16),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)]
    return np.vstack(rows)
