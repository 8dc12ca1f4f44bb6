"""CapsuleCamera: depth of a known plane, markers where the lens puts them, the light's
fall-off in the colon, and the fixed and adaptive frame rates."""

import dataclasses
import math
import os
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from pydrake.common.yaml import yaml_load_typed
from pydrake.geometry import (Box, GeometryInstance, PerceptionProperties, Rgba, Role,
                              SceneGraph, Sphere)
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialVelocity
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.capsule.camera import capsule_camera_for_frame
from capsule_drake.capsule.camera_config import CameraConfig, check_camera_config
from capsule_drake.capsule.camera_renderer import LensRenderer, add_camera_renderer
from capsule_drake.capsule.model import capsule_model
from capsule_drake.models import configure_parser, model_url
from capsule_drake.perception import LensConfig
from capsule_drake.perception.views import camera_scene

# Images of the test scenes go here, to be looked at.
IMAGE_DIR = Path(os.environ.get("CAPSULE_CAMERA_TEST_IMAGES",
                               Path(tempfile.gettempdir()) / "capsule_camera_tests"))

FISHEYE = LensConfig(model="equidistant", fov_deg=172.0)
KB_FISHEYE = LensConfig(model="kannala_brandt", fov_deg=160.0, width=320, height=320,
                        kb_coefficients=[-0.02, 0.003, -0.0005, 0.0001])
PINHOLE = LensConfig(model="pinhole_radtan", fov_deg=120.0)
RADTAN = LensConfig(model="pinhole_radtan", fov_deg=120.0,
                    radtan_coefficients=[-0.28, 0.07, 1.0e-4, -2.0e-4, 0.0])


def _save(name, rgba=None, range_m=None, far=0.3):
    IMAGE_DIR.mkdir(parents=True, exist_ok=True)
    if rgba is not None:
        cv2.imwrite(str(IMAGE_DIR / f"{name}_rgb.png"), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGR))
    if range_m is not None:
        shown = np.where(np.isfinite(range_m), range_m, 0.0) / far
        cv2.imwrite(str(IMAGE_DIR / f"{name}_depth.png"),
                    np.clip(255.0 * shown, 0, 255).astype(np.uint8))


def _perceived(shape, X_WG, name, rgba=(0.9, 0.9, 0.9, 1.0)):
    instance = GeometryInstance(X_WG, shape, name)
    props = PerceptionProperties()
    props.AddProperty("phong", "diffuse", Rgba(*rgba))
    instance.set_perception_properties(props)
    return instance


def _anchored_scene(geometries, config):
    """A SceneGraph holding only anchored geometry, and its query object."""
    builder = DiagramBuilder()
    scene_graph = builder.AddSystem(SceneGraph())
    source = scene_graph.RegisterSource("test")
    for instance in geometries:
        scene_graph.RegisterAnchoredGeometry(source, instance)
    add_camera_renderer(scene_graph, config)
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    query_object = scene_graph.get_query_output_port().Eval(
        scene_graph.GetMyContextFromRoot(context))
    return scene_graph, query_object


def _ray(theta_deg, phi_deg):
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])


@pytest.mark.parametrize("lens", [FISHEYE, RADTAN], ids=["fisheye", "radtan"])
def test_depth_of_a_plane_at_a_known_distance(lens):
    # A 2 m square plate whose near face is 5 cm in front of the camera, seen by the camera
    # at the world origin looking along +z: every pixel's range times the cosine of its
    # ray's angle to +z is the plate's distance.
    distance = 0.05
    config = CameraConfig(lens=lens, near=0.001, far=2.0)
    plate = _perceived(Box(2.0, 2.0, 0.002), RigidTransform([0.0, 0.0, distance + 0.001]),
                       "plate")
    scene_graph, query_object = _anchored_scene([plate], config)
    renderer = LensRenderer(config)
    world = scene_graph.model_inspector().world_frame_id()
    range_m = renderer.render_range(query_object, world, RigidTransform())
    _save(f"plane_{lens.model}", renderer.render_rgba(query_object, world, RigidTransform()),
          range_m, far=0.2)
    rays, in_field = renderer.lens.pixel_rays()
    hit = in_field & np.isfinite(range_m)
    # The plate fills the field: it reaches atan(1 / 0.05) = 87 deg off axis.
    assert hit.sum() == in_field.sum()
    np.testing.assert_allclose(range_m[hit] * rays[hit][:, 2], distance, atol=1e-3)
    # Outside the image circle there is no measurement.
    assert np.all(np.isinf(range_m[~in_field]))


@pytest.mark.parametrize("lens, directions", [
    (FISHEYE, [(0, 0), (35, 30), (62, 200), (75, 120), (83, 290)]),
    (KB_FISHEYE, [(0, 0), (45, -60), (70, 160)]),
    (PINHOLE, [(0, 0), (30, 45), (50, 160)]),
    (RADTAN, [(0, 0), (30, 45), (50, 160), (45, -80)]),
], ids=["fisheye", "kannala_brandt", "pinhole", "radtan"])
def test_markers_land_where_the_lens_projects_them(lens, directions):
    # Small bright spheres 6 cm from the camera at known directions on a black background;
    # the centroid of each one's pixels must be the lens's projection of its centre.
    distance, radius = 0.06, 0.0015
    config = CameraConfig(lens=lens, light_attenuation=0.0, light_intensity=1.0)
    markers = [_perceived(Sphere(radius), RigidTransform(distance * _ray(*d)), f"marker{i}")
               for i, d in enumerate(directions)]
    scene_graph, query_object = _anchored_scene(markers, config)
    renderer = LensRenderer(config)
    world = scene_graph.model_inspector().world_frame_id()
    rgba = renderer.render_rgba(query_object, world, RigidTransform())
    _save(f"markers_{lens.model}_{lens.width}", rgba)
    expected, valid = renderer.lens.project(np.array([_ray(*d) for d in directions]))
    assert valid.all()
    gray = rgba[..., :3].max(axis=2)
    count, labels = cv2.connectedComponents((gray > 20).astype(np.uint8))
    assert count - 1 == len(directions)
    for pixel in expected:
        label = labels[int(round(pixel[1])), int(round(pixel[0]))]
        assert label > 0
        v, u = np.nonzero(labels == label)
        centroid = np.array([u.mean(), v.mean()])
        assert np.linalg.norm(centroid - pixel) < 1.0, (pixel, centroid)


@pytest.fixture(scope="module")
def colon_scene():
    diagram, _, plant, scene_graph, renderer_for = camera_scene(start_s=0.30)
    return diagram, plant, scene_graph, renderer_for


@pytest.mark.parametrize("lens", [FISHEYE, PINHOLE], ids=["fisheye", "pinhole"])
def test_lumen_is_dark_with_the_camera_light(colon_scene, lens):
    diagram, plant, scene_graph, renderer_for = colon_scene
    camera = capsule_camera_for_frame(plant, plant.GetFrameByName("camera"),
                                      CameraConfig(lens=lens), renderer_for)
    query_object = scene_graph.get_query_output_port().Eval(
        scene_graph.GetMyContextFromRoot(diagram.CreateDefaultContext()))
    renderer = camera.renderer
    parent, X_PC = camera._parent_frame, camera._X_PC
    name = camera.renderer_name(query_object)
    rgba = renderer.render_rgba(query_object, parent, X_PC, renderer=name)
    range_m = renderer.render_range(query_object, parent, X_PC, renderer=name)
    _save(f"colon_{lens.model}", rgba, range_m)
    gray = rgba[..., :3].astype(float).mean(axis=2)
    seen = renderer.in_field & (range_m > 0.0)
    depth = np.where(np.isfinite(range_m), range_m, np.inf)[seen]
    near, far = np.percentile(depth, [25.0, 75.0])
    # The light falls off as 1 / (1 + k d^2): the far quarter is much darker than the near.
    assert gray[seen][depth <= near].mean() > 3.0 * gray[seen][depth >= far].mean()
    # The darkest spot (blurred, so texture does not decide) lies near the deepest one.
    blurred = cv2.GaussianBlur(np.where(seen, gray, 255.0), (0, 0), 6.0)
    deep = cv2.GaussianBlur(np.where(seen, np.minimum(range_m, 0.3), 0.0), (0, 0), 6.0)
    darkest = np.unravel_index(np.argmin(blurred), gray.shape)
    deepest = np.unravel_index(np.argmax(deep), gray.shape)
    assert np.hypot(*np.subtract(darkest, deepest)) < 0.1 * renderer.width


def _moving_capsule_diagram(config, speed, static_scene=None):
    """A weightless capsule gliding along its axis at `speed` in front of a plate. Its own
    shell is invisible to cameras (the lens sits inside it, as in the station). With
    `static_scene` (True / False), the diagram holds two cameras, the given one last, the
    other first."""
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(MultibodyPlantConfig(time_step=0.0), builder)
    configure_parser(Parser(plant)).AddModels(url=model_url("capsule.sdf"))
    plant.RegisterVisualGeometry(plant.world_body(), RigidTransform([0.0, 0.0, 0.06]),
                                 Box(1.0, 1.0, 0.01), "plate", np.array([0.8, 0.4, 0.3, 1.0]))
    if static_scene is not None:
        plant.RegisterVisualGeometry(plant.world_body(), RigidTransform([0.02, 0.0, 0.04]),
                                     Sphere(0.008), "ball", np.array([0.3, 0.8, 0.3, 1.0]))
    plant.mutable_gravity_field().set_gravity_vector([0.0, 0.0, 0.0])
    plant.Finalize()
    add_camera_renderer(scene_graph, config)
    cameras = []
    for static in ([not static_scene, static_scene] if static_scene is not None else [False]):
        camera = builder.AddNamedSystem(f"camera_{len(cameras)}", capsule_camera_for_frame(
            plant, plant.GetFrameByName("camera"), config, static_scene=static))
        builder.Connect(scene_graph.get_query_output_port(),
                        camera.get_query_object_input_port())
        cameras.append(camera)
    source = plant.get_source_id()
    for geometry_id in plant.GetVisualGeometriesForBody(plant.GetBodyByName("capsule")):
        if scene_graph.model_inspector().GetPerceptionProperties(geometry_id):
            scene_graph.RemoveRole(source, geometry_id, Role.kPerception)
    camera = cameras[-1]
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyContextFromRoot(context)
    body = plant.GetBodyByName("capsule")
    plant.SetFreeBodyPose(plant_context, body, RigidTransform())
    plant.SetFreeBodySpatialVelocity(plant_context, body,
                                     SpatialVelocity(np.zeros(3), [0.0, 0.0, speed]))
    if static_scene is not None:
        return diagram, context, cameras
    return diagram, context, camera


def test_depth_drawn_on_demand_is_the_frames_own():
    """In a static scene the depth image is drawn when first read, from the pose its frame
    was taken at: the same image as drawing it with the frame, and never drawn unread."""
    config = CameraConfig(lens=LensConfig(width=96, height=96), fps=10.0)
    diagram, context, (eager, lazy) = _moving_capsule_diagram(config, 0.05, static_scene=True)
    drawn = []
    render_range = lazy.renderer.render_range
    lazy.renderer.render_range = lambda *a, **k: drawn.append(1) or render_range(*a, **k)
    simulator = Simulator(diagram, context)
    simulator.AdvanceTo(0.35)  # frames at 0, 0.1, 0.2, 0.3; the capsule 5 mm on since
    assert not drawn
    lazy_context = lazy.GetMyContextFromRoot(simulator.get_context())
    eager_context = eager.GetMyContextFromRoot(simulator.get_context())

    def depths():
        return (lazy.get_depth_image_output_port().Eval(lazy_context).data[..., 0].copy(),
                eager.get_depth_image_output_port().Eval(eager_context).data[..., 0])

    first, expected = depths()
    assert len(drawn) == 1
    assert np.isfinite(expected).sum() > 1000
    np.testing.assert_array_equal(np.isfinite(first), np.isfinite(expected))
    finite = np.isfinite(expected)
    np.testing.assert_allclose(first[finite], expected[finite], atol=1e-6)
    # Drawn from the frame's pose, not the capsule's current one (5 mm nearer the plate).
    now = lazy.renderer.render_range(
        lazy.get_query_object_input_port().Eval(lazy_context), lazy._parent_frame,
        lazy._X_PC)
    both = finite & np.isfinite(now)
    assert np.abs(now[both] - first[both]).max() > 0.003
    depths()
    assert len(drawn) == 2  # one more: the check just above; the cached image stands
    simulator.AdvanceTo(0.45)
    second, expected = depths()
    assert len(drawn) == 3
    finite = np.isfinite(expected)
    np.testing.assert_allclose(second[finite], expected[finite], atol=1e-6)
    assert np.abs(second[finite] - first[finite]).max() > 0.003  # a new frame


@pytest.mark.parametrize("mode, speed, duration, frames", [
    ("fixed", 0.0, 0.5, 6),        # 10 fps: t = 0, 0.1, ..., 0.5
    ("adaptive", 0.0, 1.0, 4),     # at rest 4 fps, quantised to the 35 Hz tick: 35 / 9
    ("adaptive", 0.02, 0.5, 18),   # 2 cm/s at 2 cm viewing distance is past full speed
], ids=["fixed", "adaptive_at_rest", "adaptive_moving"])
def test_frame_rate(mode, speed, duration, frames):
    config = CameraConfig(lens=LensConfig(model="pinhole_radtan", width=64, height=64),
                          fps_mode=mode, fps=10.0, render_depth=False)
    diagram, context, camera = _moving_capsule_diagram(config, speed)
    simulator = Simulator(diagram, context)
    simulator.AdvanceTo(duration + 1e-6)
    camera_context = camera.GetMyContextFromRoot(simulator.get_context())
    t_last, count, _, rate = camera.get_frame_info_output_port().Eval(camera_context)
    assert count == frames
    assert t_last <= duration + 1e-6 and t_last > duration - 1.0 / config.fps_min
    expected_rate = {"fixed": 10.0}.get(mode, 35.0 if speed > 0 else 4.0)
    assert rate == pytest.approx(expected_rate)
    # The held image is a real frame: the lit plate ~4 cm ahead fills the view.
    rgb = camera.get_rgb_image_output_port().Eval(camera_context).data
    assert rgb[..., 0].mean() > 5.0


def test_camera_system_outputs_after_initialisation():
    config = CameraConfig(lens=LensConfig(width=96, height=96), fps=5.0)
    diagram, context, camera = _moving_capsule_diagram(config, 0.0)
    diagram.ExecuteInitializationEvents(context)
    camera_context = camera.GetMyContextFromRoot(context)
    depth = camera.get_depth_image_output_port().Eval(camera_context).data[..., 0]
    rays, in_field = camera.lens.pixel_rays()
    # The plate's near face is at z = 0.055 m; the camera in the dome (models/capsule.sdf).
    # Within 75 degrees of the axis the plate is nearer than `far` (0.2 m of range); beyond
    # ~80 degrees it is farther, and reads +inf (a margin: at grazing incidence the pixels
    # next to the cut take their nearest rendered sample, whose range differs by ~5 %).
    z_plate = 0.055 - capsule_model().X_BC.translation()[2]
    within = in_field & (rays[..., 2] > math.cos(math.radians(75.0)))
    z = depth[within] * rays[within][:, 2]
    assert np.isfinite(z).all()
    np.testing.assert_allclose(z, z_plate, atol=1e-3)
    beyond = in_field & (rays[..., 2] < 0.9 * z_plate / config.far)
    assert beyond.any() and np.all(np.isinf(depth[beyond]))
    info = camera.get_frame_info_output_port().Eval(camera_context)
    np.testing.assert_array_equal(info, [0.0, 1.0, 1.0, 5.0])


def test_camera_config_yaml_and_checks():
    config = yaml_load_typed(schema=CameraConfig, data="""
lens: {model: kannala_brandt, width: 320, height: 320, fov_deg: 150}
fps_mode: adaptive
fps_min: 4
fps_max: 35
near: 0.002
far: 0.2
light_attenuation: 2000
""")
    check_camera_config(config)
    assert config.lens.width == 320 and config.fps_mode == "adaptive"
    for bad in [dict(fps_mode="sometimes"), dict(fps_min=40.0), dict(near=0.5, far=0.2)]:
        with pytest.raises(ValueError):
            check_camera_config(dataclasses.replace(CameraConfig(), **bad))
