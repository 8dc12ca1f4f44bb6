"""Camera windows: a frame drawn from the colon window the camera is in is the frame the
whole wall gives, and the sight-line bound behind the windows holds."""

import dataclasses

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.anatomy import load_colon
from capsule_drake.anatomy.windows import CameraWindows, sight_reach
from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.capsule.camera_renderer import LensRenderer
from capsule_drake.capsule.camera_walls import add_camera_walls
from capsule_drake.capsule.model import CAPSULE_BODY, start_pose
from capsule_drake.models import configure_parser, model_url
from capsule_drake.scene_geometry import add_colon_visuals
from capsule_drake.scenario import Scenario


@pytest.fixture(scope="module")
def colon():
    colon, _ = load_colon(Scenario().colon)
    return colon


def test_sight_reach_is_the_range_on_straight_stretches_and_longer_in_bends(colon):
    length = colon.centerline.length
    s = np.linspace(0.3, length - 0.3, 200)
    lo, hi = sight_reach(colon, s, 0.2)
    # Never shorter than the range itself (1 - kappa r <= 1) ...
    assert np.all(hi - s >= 0.2 - 1e-6) and np.all(s - lo >= 0.2 - 1e-6)
    # ... and longer where the colon bends: the flexures stretch it.
    kappa_r = colon.centerline.curvature_at(s) * colon.max_wall_radius(s)
    assert np.max(hi - lo) > 0.44 and kappa_r.max() > 0.5
    # Clamped at the ends.
    lo, hi = sight_reach(colon, np.array([0.0, length]), 0.2)
    assert lo[0] == 0.0 and hi[1] == length


def test_window_index_serves_half_a_spacing_either_side():
    windows = CameraWindows(np.linspace(0.0, 1.0, 11), [], np.zeros(11), 0.2)
    assert windows.spacing == pytest.approx(0.1)
    assert [windows.index_at(s) for s in (-0.5, 0.0, 0.049, 0.051, 0.54, 0.56, 0.96, 3.0)] == \
        [0, 0, 0, 1, 5, 6, 10, 10]
    assert CameraWindows(np.array([0.7]), [], np.zeros(1), 0.2).index_at(0.1) == 0


@pytest.mark.slow
def test_windowed_frames_equal_whole_wall_frames(colon):
    """Random camera poses anywhere in the colon (turned up to ~70 degrees from the axis,
    up to 60 % of the radius off the centreline, at least 3 mm inside the wall): depth and
    colour from the window equal those from one renderer holding the whole wall."""
    scenario = Scenario()
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(MultibodyPlantConfig(time_step=0.001), builder)
    configure_parser(Parser(plant)).AddModels(url=model_url("capsule.sdf"))
    add_colon_visuals(plant, scenario.colon, colon, perception=False)
    config = CameraConfig()
    renderer_for = add_camera_walls(plant, scene_graph, scenario.colon, colon, config)
    add_camera_walls(plant, scene_graph, scenario.colon, colon,
                     dataclasses.replace(config, renderer_name="whole", window_spacing=0.0))
    plant.Finalize()
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyMutableContextFromRoot(context)
    body = plant.GetBodyByName(CAPSULE_BODY)
    frame_id = plant.GetBodyFrameIdOrThrow(body.index())
    X_BC = plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()
    lens = LensRenderer(config)
    rng = np.random.default_rng(7)
    length = colon.centerline.length
    used, windows_used = 0, set()
    while used < 40:
        s = rng.uniform(0.03, length - 0.03)
        X_WB = start_pose(colon, s)
        turn = RotationMatrix(RollPitchYaw(*rng.uniform(-1.2, 1.2, 3)))
        X_WB = RigidTransform(X_WB.rotation().multiply(turn), X_WB.translation())
        offset = rng.uniform(0.0, 0.6) * float(colon.max_wall_radius(s)[0])
        X_WB.set_translation(X_WB.translation() + offset * X_WB.rotation().col(0))
        p_WC = X_WB.multiply(X_BC.translation())
        if colon.excursion(p_WC)[0] > -0.003:
            continue
        used += 1
        plant.SetFreeBodyPose(plant_context, body, X_WB)
        query = scene_graph.get_query_output_port().Eval(
            scene_graph.GetMyContextFromRoot(context))
        window = renderer_for(p_WC)
        windows_used.add(window)
        windowed = lens.render_range(query, frame_id, X_BC, renderer=window)
        whole = lens.render_range(query, frame_id, X_BC, renderer="whole")
        seen = np.isfinite(windowed) | np.isfinite(whole)
        assert seen.any()
        difference = np.abs(np.nan_to_num(windowed, posinf=1.0) - np.nan_to_num(whole, posinf=1.0))
        assert np.count_nonzero(difference[seen] > 1e-3) == 0, (s, window)
        colour_difference = np.abs(
            lens.render_rgba(query, frame_id, X_BC, renderer=window).astype(int)
            - lens.render_rgba(query, frame_id, X_BC, renderer="whole").astype(int))
        assert colour_difference.max() <= 2, (s, window)
    assert len(windows_used) >= 10
