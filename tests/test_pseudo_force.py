"""The pseudo-force on the haptic stylus: its three terms, the frames, saturation, the system."""

import dataclasses
import math

import numpy as np
import pytest
import trimesh
from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed
from pydrake.geometry import Role, SceneGraph
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from capsule_drake.anatomy import load_colon
from capsule_drake.capsule.model import capsule_model as sdf_capsule_model
from capsule_drake.capsule.model import start_pose
from capsule_drake.guidance import terms as guidance
from capsule_drake.guidance.pseudo_force import PseudoForceField
from capsule_drake.guidance.terms import (PseudoForceConfig, capsule_axis_points,
                                          check_pseudo_force_config, colon_potential,
                                          colon_potential_force, lumen_attraction,
                                          pseudo_force, wall_avoidance, wall_clearance)
from capsule_drake.models import configure_parser
from capsule_drake.scenario import Scenario, ScenarioError, load_scenario

# The device frame of the default config, written out: x_D = x_C (image right), y_D = -y_C
# (image up), z_D = -z_C (toward the operator, so camera forward is pushing the stylus away).
R_DC = np.diag([1.0, -1.0, -1.0])

# The capsule's collision shape (radius, cylinder length), as the package reads it from
# models/capsule.sdf; test_capsule_shape_matches_the_model checks it against the SDF.
RADIUS, LENGTH = sdf_capsule_model().radius, sdf_capsule_model().length


@pytest.fixture(scope="module")
def colon():
    colon, _ = load_colon(Scenario().colon)
    return colon


@pytest.fixture(scope="module")
def capsule_model():
    """(X_BC of the `camera` frame, collision Capsule shape) read from models/capsule.sdf."""
    plant = MultibodyPlant(0.0)
    scene_graph = SceneGraph()
    plant.RegisterAsSourceForSceneGraph(scene_graph)
    instance, = configure_parser(Parser(plant)).AddModels(url="package://capsule_drake/capsule.sdf")
    plant.Finalize()
    X_BC = plant.GetFrameByName("camera", instance).GetFixedPoseInBodyFrame()
    body = plant.GetBodyByName("capsule", instance)
    inspector = scene_graph.model_inspector()
    geometry, = plant.GetCollisionGeometriesForBody(body)
    assert inspector.GetProperties(geometry, Role.kProximity) is not None
    return X_BC, inspector.GetShape(geometry)


def state_of(X_WB: RigidTransform, w_WB=(0.0, 0.0, 0.0), v_WB=(0.0, 0.0, 0.0)) -> np.ndarray:
    q = X_WB.rotation().ToQuaternion()
    return np.concatenate([[q.w(), q.x(), q.y(), q.z()], X_WB.translation(), w_WB, v_WB])


def segment_middle(colon, name: str) -> float:
    start, end = colon.centerline.segment_ranges()[name]
    return 0.5 * (start + end)


def near_wall(colon, s: float, direction_B, clearance: float):
    """The capsule at arc length s, body z down the lumen, moved along a body direction in its
    cross-section until its wall distance first drops below `clearance`; (X_WB, e_W)."""
    X = start_pose(colon, s)
    R = X.rotation().matrix()
    e_W = R @ np.asarray(direction_B, dtype=float)
    for offset in np.arange(0.0, 0.04, 2e-4):
        p = X.translation() + offset * e_W
        if wall_clearance(colon, R, p, np.zeros(3), np.zeros(3), RADIUS,
                          LENGTH).distance < clearance:
            return RigidTransform(X.rotation(), p), e_W
    raise AssertionError("never reached the wall")


# --- (a) lumen attraction ---------------------------------------------------------------------

def ray(offset_deg, azimuth_deg=0.0):
    """A unit ray `offset_deg` off the optical axis, toward `azimuth_deg` in the image
    (0 = right, 90 = down)."""
    a, b = math.radians(offset_deg), math.radians(azimuth_deg)
    return np.array([math.sin(a) * math.cos(b), math.sin(a) * math.sin(b), math.cos(a)])


def test_lumen_pull_points_where_the_lumen_is_in_the_image():
    for offset in (5.0, 30.0, 60.0, 85.0):
        for azimuth in (0.0, 40.0, 135.0, 250.0):
            r = ray(offset, azimuth)
            F = lumen_attraction(r, True, 1.0, 2.0, 1.0)
            # Independent route: where a pinhole puts the lumen, relative to the image centre.
            pixel_offset = 300.0 * r[:2] / r[2]
            np.testing.assert_allclose(F[:2] / np.linalg.norm(F[:2]),
                                       pixel_offset / np.linalg.norm(pixel_offset), atol=1e-12)
            # The lateral part is k_lateral sin(offset), whatever the azimuth.
            assert np.linalg.norm(F[:2]) == pytest.approx(2.0 * math.sin(math.radians(offset)))


def test_lumen_pull_grows_with_the_offset_and_is_forward_when_centred():
    lateral = [np.linalg.norm(lumen_attraction(ray(a, 30.0), True, 1.0, 2.0, 1.0)[:2])
               for a in np.linspace(0.0, 86.0, 44)]
    assert lateral[0] == 0.0
    assert np.all(np.diff(lateral) > 0.0)
    centred = lumen_attraction([0.0, 0.0, 1.0], True, 1.0, 2.0, 1.0)
    np.testing.assert_array_equal(centred, [0.0, 0.0, 1.0])
    # A lumen behind the camera (a 172-deg fisheye sees a little past 90 deg) never pulls back.
    assert lumen_attraction(ray(95.0), True, 1.0, 2.0, 1.0)[2] == 0.0


def test_lumen_pull_vanishes_when_unseen_and_scales_with_confidence():
    r = ray(40.0, 200.0)
    np.testing.assert_array_equal(lumen_attraction(r, False, 1.0, 2.0, 1.0), np.zeros(3))
    full = lumen_attraction(r, True, 1.0, 2.0, 1.0)
    np.testing.assert_allclose(lumen_attraction(r, True, 0.25, 2.0, 1.0), 0.25 * full)
    np.testing.assert_array_equal(lumen_attraction(r, True, 0.0, 2.0, 1.0), np.zeros(3))
    # A ray that is not unit is a direction all the same.
    np.testing.assert_allclose(lumen_attraction(3.0 * r, True, 1.0, 2.0, 1.0), full)


# --- device frame -------------------------------------------------------------------------------

def lumen_only_force(colon, r, X_BC, visible=1.0):
    """F_D of the lumen term alone: the capsule on the centreline, far from the wall."""
    config = PseudoForceConfig(wall_weight=0.0)
    state = state_of(start_pose(colon, segment_middle(colon, "transverse")))
    return pseudo_force(colon, config, X_BC.rotation().matrix(), r, visible, 1.0, state,
                        RADIUS, LENGTH).F_D


def test_default_device_frame_is_diag_1_minus1_minus1():
    R = guidance.rotation_from_rpy_deg(PseudoForceConfig().device_from_camera_rpy_deg)
    np.testing.assert_allclose(R, R_DC, atol=1e-15)
    # Same convention as Drake's RollPitchYaw (the one every *_rpy_deg in the repo uses).
    rpy = [10.0, -25.0, 70.0]
    np.testing.assert_allclose(guidance.rotation_from_rpy_deg(rpy),
                               RotationMatrix(RollPitchYaw(np.deg2rad(rpy))).matrix(),
                               atol=1e-15)


def test_lumen_directions_in_the_device_frame(colon, capsule_model):
    X_BC, _ = capsule_model
    ahead = lumen_only_force(colon, [0.0, 0.0, 1.0], X_BC)
    np.testing.assert_allclose(ahead, [0.0, 0.0, -1.0], atol=1e-12)  # pushed away from you
    right = lumen_only_force(colon, ray(30.0, 0.0), X_BC)
    assert right[0] > 0.9 and abs(right[1]) < 1e-12                  # image right: stylus right
    below = lumen_only_force(colon, ray(30.0, 90.0), X_BC)
    assert below[1] < -0.9 and abs(below[0]) < 1e-12                 # image down: stylus down
    assert np.all(lumen_only_force(colon, ray(30.0, 0.0), X_BC, visible=0.0) == 0.0)


def test_wall_push_in_the_device_frame(colon, capsule_model):
    """A wall on the image's right pushes the stylus left; a wall below pushes it up."""
    X_BC, _ = capsule_model
    config = PseudoForceConfig(lumen_weight=0.0)
    s = segment_middle(colon, "descending")
    for direction_B, axis, sign in (([1.0, 0.0, 0.0], 0, -1.0), ([0.0, 1.0, 0.0], 1, 1.0)):
        X_WB, _ = near_wall(colon, s, direction_B, 0.002)
        F_D = pseudo_force(colon, config, X_BC.rotation().matrix(), np.zeros(3), 0.0, 1.0,
                           state_of(X_WB), RADIUS, LENGTH).F_D
        assert sign * F_D[axis] > 0.95 * np.linalg.norm(F_D) > 0.0


# --- (b) wall avoidance ---------------------------------------------------------------------------

def test_capsule_shape_matches_the_model(capsule_model):
    _, shape = capsule_model
    assert shape.radius() == RADIUS
    assert shape.length() == LENGTH


@pytest.mark.parametrize("segment, direction_B", [
    ("sigmoid", [1.0, 0.0, 0.0]), ("descending", [0.0, -1.0, 0.0]),
    ("transverse", [0.6, 0.8, 0.0])])
def test_wall_push_grows_toward_the_wall_and_points_back(colon, segment, direction_B):
    config = PseudoForceConfig()
    X = start_pose(colon, segment_middle(colon, segment))
    R = X.rotation().matrix()
    e_W = R @ direction_B
    magnitudes, distances = [], []
    for offset in np.arange(0.0, 0.04, 5e-4):
        p = X.translation() + offset * e_W
        clearance = wall_clearance(colon, R, p, np.zeros(3), np.zeros(3), RADIUS, LENGTH)
        F = wall_avoidance(clearance.distance, clearance.rate, clearance.normal_W,
                           config.k_wall, config.c_wall, config.wall_distance)
        magnitudes.append(np.linalg.norm(F))
        distances.append(clearance.distance)
        if np.linalg.norm(F) > 0.0:
            # Back toward the centreline (the capsule's ends see the wall's normal a little
            # tilted in a bend).
            assert F @ -e_W > 0.95 * np.linalg.norm(F)
        if clearance.distance < -0.001:
            break
    magnitudes, distances = np.array(magnitudes), np.array(distances)
    assert distances[0] > config.wall_distance and magnitudes[0] == 0.0  # centred: nothing
    inside = distances < config.wall_distance
    assert np.all(magnitudes[~inside] == 0.0)
    # Once within d0 of the wall, every step closer pushes harder. (Farther out, d from
    # `Colon.excursion` is measured radially, so between folds it need not fall steadily.)
    entered = int(np.argmax(inside))
    assert np.all(inside[entered:]) and len(inside) - entered >= 8
    assert np.all(np.diff(magnitudes[entered:]) > 0.0)
    # At contact it reaches the spring's k_wall d0 (1.6 N by default).
    assert magnitudes[-1] > config.k_wall * config.wall_distance


def test_wall_distance_agrees_with_the_wall_mesh(colon):
    """Independent route: the distance from the capsule's axis to the triangle mesh of the
    wall, minus the capsule's radius, at 10 random places within 4 mm of the wall in the
    sigmoid (folds 5 mm high, 5-8 cm apart). `Colon.excursion` is a first-order distance
    along the radial direction, so near a fold's crest it is off by up to ~1 mm there (up to
    ~2 mm too far and ~10 mm too near by the ascending colon's and cecum's 15 mm folds)."""
    mesh = colon.visual_mesh()
    query = trimesh.proximity.ProximityQuery(mesh)
    rng = np.random.default_rng(5)
    start, end = colon.centerline.segment_ranges()["sigmoid"]
    errors = []
    for s in rng.uniform(start + 0.02, end - 0.02, 10):
        angle = rng.uniform(0.0, 2.0 * np.pi)
        X_WB, _ = near_wall(colon, s, [math.cos(angle), math.sin(angle), 0.0], 0.004)
        R, p = X_WB.rotation().matrix(), X_WB.translation()
        d = wall_clearance(colon, R, p, np.zeros(3), np.zeros(3), RADIUS, LENGTH).distance
        _, to_mesh, _ = query.on_surface(capsule_axis_points(R, p, LENGTH, samples=41))
        errors.append(d - (to_mesh.min() - RADIUS))
    assert np.max(np.abs(errors)) < 1e-3
    assert np.median(np.abs(errors)) < 3e-4


def test_approaching_the_wall_pushes_harder(colon):
    config = PseudoForceConfig()
    X_WB, e_W = near_wall(colon, segment_middle(colon, "descending"), [0.0, 1.0, 0.0], 0.002)
    R, p = X_WB.rotation().matrix(), X_WB.translation()
    speed = 0.01
    pushes = {}
    for label, v in (("toward", speed * e_W), ("still", np.zeros(3)), ("away", -speed * e_W)):
        c = wall_clearance(colon, R, p, np.zeros(3), v, RADIUS, LENGTH)
        pushes[label] = np.linalg.norm(wall_avoidance(
            c.distance, c.rate, c.normal_W, config.k_wall, config.c_wall, config.wall_distance))
        # Independent route for d_dot: the distance a moment later, minus now.
        h = 1e-4
        later = wall_clearance(colon, R, p + h * v, np.zeros(3), v, RADIUS, LENGTH).distance
        assert c.rate == pytest.approx((later - c.distance) / h, abs=0.05 * speed)
    assert pushes["toward"] > pushes["still"] > pushes["away"] > 0.0
    assert pushes["toward"] - pushes["still"] == pytest.approx(config.c_wall * speed, rel=0.05)
    # Leaving fast enough cancels the spring, but never pulls toward the wall.
    c = wall_clearance(colon, R, p, np.zeros(3), -1.0 * e_W, RADIUS, LENGTH)
    F = wall_avoidance(c.distance, c.rate, c.normal_W, config.k_wall, config.c_wall,
                       config.wall_distance)
    np.testing.assert_array_equal(F, np.zeros(3))


def test_rotation_moves_the_capsule_ends(colon):
    """The critical point's velocity includes w x r: spinning the capsule about an axis across
    it moves its ends toward or away from the wall, checked against the distance after a
    small rotation."""
    X_WB, e_W = near_wall(colon, segment_middle(colon, "descending"), [1.0, 0.0, 0.0], 0.002)
    R, p = X_WB.rotation().matrix(), X_WB.translation()
    w_W = 0.5 * R[:, 1]  # about body y: the ends swing along body x
    c = wall_clearance(colon, R, p, w_W, np.zeros(3), RADIUS, LENGTH)
    assert abs(c.rate) > 0.001  # an end, not the middle, is nearest (the colon bends)
    h = 1e-4
    R_later = RotationMatrix(RollPitchYaw(0.0, 0.5 * h, 0.0)).matrix()
    later = wall_clearance(colon, R @ R_later, p, w_W, np.zeros(3), RADIUS, LENGTH).distance
    assert c.rate == pytest.approx((later - c.distance) / h, rel=0.1)


# --- (c) potential field --------------------------------------------------------------------------

def test_potential_force_is_minus_its_gradient(colon):
    """-grad U by central differences of U (h = 10 um) at points up to 60 % of the lumen radius
    off the centreline: within 1e-3 N (the field is ~1-3 N). The spline centreline is C2, so
    U is smooth wherever a point has one closest station (inside the lumen)."""
    cl = colon.centerline
    rng = np.random.default_rng(3)
    h = 1e-5
    largest_bend_effect = 0.0
    for s in np.linspace(0.03, cl.length - 0.03, 12):
        t, n, b = cl.frame_at(s)
        for fraction in (0.0, 0.3, 0.6):
            angle = rng.uniform(0.0, 2.0 * np.pi)
            p = cl.point_at(s) + fraction * cl.radius_at(s) * (np.cos(angle) * n
                                                                + np.sin(angle) * b)
            F = colon_potential_force(cl, p, 1.0, 100.0)
            steps = np.concatenate([np.eye(3), -np.eye(3)]) * h
            U = colon_potential(cl, p + steps, 1.0, 100.0)
            gradient = (U[:3] - U[3:]) / (2.0 * h)
            np.testing.assert_allclose(F, -gradient, atol=1e-3)
            e, rho, s_p = guidance.toward_centerline(cl, p)
            flat = cl.tangent_at(s_p) + 100.0 * rho * e
            largest_bend_effect = max(largest_bend_effect, np.linalg.norm(F - flat))
    # The test can tell the exact gradient from its straight-tube limit.
    assert largest_bend_effect > 0.05


def test_potential_pulls_toward_the_cecum_on_the_centreline(colon):
    cl = colon.centerline
    for s in (0.2, 0.7, 1.2):
        F = colon_potential_force(cl, cl.point_at(s), 1.5, 100.0)
        np.testing.assert_allclose(F, 1.5 * cl.tangent_at(s), atol=1e-6)


# --- the sum and its saturation -------------------------------------------------------------------

def busy_inputs(colon):
    """A capsule near the wall, moving toward it, with the lumen off-centre: all terms act."""
    X_WB, e_W = near_wall(colon, segment_middle(colon, "descending"), [1.0, 0.0, 0.0], 0.002)
    state = state_of(X_WB, w_WB=[0.1, -0.2, 0.3], v_WB=0.005 * e_W)
    return X_WB, ray(35.0, 120.0), state


def test_saturation_keeps_the_direction(colon, capsule_model):
    X_BC, _ = capsule_model
    _, r, state = busy_inputs(colon)
    huge = PseudoForceConfig(potential_weight=1.0, k_lateral=1e4, k_forward=1e4, k_wall=1e6,
                             c_wall=1e4, k_along=1e4, k_radial=1e6)
    result = pseudo_force(colon, huge, X_BC.rotation().matrix(), r, 1.0, 1.0, state, RADIUS,
                          LENGTH)
    total = result.terms_D.sum(axis=0)
    assert np.linalg.norm(total) > 100.0 * huge.force_limit
    assert np.linalg.norm(result.F_D) == pytest.approx(huge.force_limit, abs=1e-9)
    np.testing.assert_allclose(result.F_D / np.linalg.norm(result.F_D),
                               total / np.linalg.norm(total), atol=1e-12)
    # Below the limit the sum passes unchanged.
    gentle = PseudoForceConfig(potential_weight=0.2, k_lateral=0.5, k_forward=0.2, k_wall=50.0,
                               c_wall=5.0, k_along=0.2, k_radial=10.0)
    result = pseudo_force(colon, gentle, X_BC.rotation().matrix(), r, 1.0, 1.0, state, RADIUS,
                          LENGTH)
    assert 0.0 < np.linalg.norm(result.F_D) < gentle.force_limit
    np.testing.assert_array_equal(result.F_D, result.terms_D.sum(axis=0))


# --- the system -----------------------------------------------------------------------------------

def expected_terms_D(colon, config, X_BC, X_WB, r, confidence, state):
    """Each weighted term in D, composed here from the term functions and Drake's poses."""
    R_CW = X_WB.rotation().multiply(X_BC.rotation()).inverse().matrix()
    lumen = lumen_attraction(r, True, confidence, config.k_lateral, config.k_forward)
    c = wall_clearance(colon, X_WB.rotation().matrix(), X_WB.translation(), state[7:10],
                       state[10:13], RADIUS, LENGTH)
    wall = wall_avoidance(c.distance, c.rate, c.normal_W, config.k_wall, config.c_wall,
                          config.wall_distance)
    potential = colon_potential_force(colon.centerline, X_WB.translation(), config.k_along,
                                      config.k_radial)
    terms = np.array([config.lumen_weight * R_DC @ lumen,
                      config.wall_weight * R_DC @ R_CW @ wall,
                      config.potential_weight * R_DC @ R_CW @ potential])
    return terms, c.distance


def test_system_samples_and_holds_the_pure_functions(colon, capsule_model):
    X_BC, _ = capsule_model
    X_WB, r, state = busy_inputs(colon)
    config = PseudoForceConfig(lumen_weight=1.5, wall_weight=2.0, potential_weight=0.5,
                               update_period=0.001)
    builder = DiagramBuilder()
    dut = builder.AddNamedSystem("pseudo_force",
                                 PseudoForceField(colon, config, X_BC, RADIUS, LENGTH))
    for port, value in ((dut.get_lumen_ray_input_port(), r),
                        (dut.get_lumen_visible_input_port(), [1.0]),
                        (dut.get_lumen_confidence_input_port(), [0.7]),
                        (dut.get_capsule_state_input_port(), state)):
        source = builder.AddSystem(ConstantVectorSource(np.asarray(value, dtype=float)))
        builder.Connect(source.get_output_port(), port)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = dut.GetMyContextFromRoot(simulator.get_context())
    assert math.isnan(dut.get_wall_distance_output_port().Eval(context)[0])  # not sampled yet
    simulator.AdvanceTo(0.0025)

    terms, distance = expected_terms_D(colon, config, X_BC, X_WB, r, 0.7, state)
    np.testing.assert_allclose(dut.get_terms_D_output_port().Eval(context),
                               terms.reshape(-1), atol=1e-12)
    total = terms.sum(axis=0)
    assert np.linalg.norm(total) > config.force_limit  # so the saturation is exercised
    np.testing.assert_allclose(dut.get_F_D_output_port().Eval(context),
                               total * config.force_limit / np.linalg.norm(total), atol=1e-12)
    assert dut.get_wall_distance_output_port().Eval(context)[0] == pytest.approx(distance)
    np.testing.assert_array_equal(dut.get_invalid_inputs_output_port().Eval(context), 0.0)
    # Sample-and-hold: no output depends on an input within the same instant.
    for i in range(dut.num_input_ports()):
        for j in range(dut.num_output_ports()):
            assert not dut.HasDirectFeedthrough(i, j)


def run_fixed(dut, values, duration=0.0025):
    """Simulates `dut` alone with fixed inputs ({port: value}); returns its context."""
    simulator = Simulator(dut)
    context = simulator.get_mutable_context()
    for port, value in values.items():
        port.FixValue(context, np.asarray(value, dtype=float))
    simulator.AdvanceTo(duration)
    return context


def test_non_finite_inputs_give_a_finite_force_and_are_counted(colon, capsule_model):
    X_BC, _ = capsule_model
    dut = PseudoForceField(colon, PseudoForceConfig(potential_weight=1.0, update_period=0.001),
                           X_BC, RADIUS, LENGTH)
    X_WB, r, state = busy_inputs(colon)
    nan_velocity = state.copy()
    nan_velocity[10] = np.nan
    context = run_fixed(dut, {dut.get_lumen_ray_input_port(): [np.nan, 0.0, np.inf],
                              dut.get_lumen_visible_input_port(): [1.0],
                              dut.get_lumen_confidence_input_port(): [0.9],
                              dut.get_capsule_state_input_port(): nan_velocity})
    # Three samples (t = 0, 1, 2 ms); the lumen and wall terms had no information in each.
    np.testing.assert_array_equal(dut.get_invalid_inputs_output_port().Eval(context), [3, 3, 0])
    terms = dut.get_terms_D_output_port().Eval(context).reshape(3, 3)
    np.testing.assert_array_equal(terms[:2], 0.0)
    assert np.linalg.norm(terms[2]) > 0.5  # the pose alone still gives the potential
    assert np.all(np.isfinite(dut.get_F_D_output_port().Eval(context)))
    assert dut.get_wall_distance_output_port().Eval(context)[0] < 0.004

    context = run_fixed(dut, {dut.get_lumen_ray_input_port(): r,
                              dut.get_lumen_visible_input_port(): [np.nan],
                              dut.get_lumen_confidence_input_port(): [0.9],
                              dut.get_capsule_state_input_port(): np.full(13, np.inf)})
    np.testing.assert_array_equal(dut.get_invalid_inputs_output_port().Eval(context), [3, 3, 3])
    np.testing.assert_array_equal(dut.get_F_D_output_port().Eval(context), 0.0)
    assert math.isnan(dut.get_wall_distance_output_port().Eval(context)[0])

    # An unseen lumen may come with any ray: that is not an error.
    context = run_fixed(dut, {dut.get_lumen_ray_input_port(): [np.nan] * 3,
                              dut.get_lumen_visible_input_port(): [0.0],
                              dut.get_lumen_confidence_input_port(): [np.nan],
                              dut.get_capsule_state_input_port(): state})
    np.testing.assert_array_equal(dut.get_invalid_inputs_output_port().Eval(context), 0.0)
    assert np.all(np.isfinite(dut.get_F_D_output_port().Eval(context)))


def test_unconnected_inputs_mean_no_information(colon, capsule_model):
    X_BC, _ = capsule_model
    dut = PseudoForceField(colon, PseudoForceConfig(), X_BC, RADIUS, LENGTH)
    X_WB, r, state = busy_inputs(colon)
    context = run_fixed(dut, {dut.get_capsule_state_input_port(): state})
    terms = dut.get_terms_D_output_port().Eval(context).reshape(3, 3)
    np.testing.assert_array_equal(terms[0], 0.0)  # no tracker: no lumen term
    assert np.linalg.norm(terms[1]) > 0.5         # the wall is 2 mm away
    np.testing.assert_array_equal(dut.get_invalid_inputs_output_port().Eval(context), 0.0)
    context = run_fixed(dut, {dut.get_lumen_ray_input_port(): [0.0, 0.0, 1.0],
                              dut.get_lumen_visible_input_port(): [1.0]})
    np.testing.assert_allclose(dut.get_F_D_output_port().Eval(context), [0.0, 0.0, -1.0],
                               atol=1e-12)
    np.testing.assert_array_equal(dut.get_invalid_inputs_output_port().Eval(context), 0.0)


# --- configuration --------------------------------------------------------------------------------

def test_config_yaml_round_trip_and_unknown_keys():
    config = PseudoForceConfig(potential_weight=0.5, k_wall=250.0,
                               device_from_camera_rpy_deg=[180.0, 0.0, 90.0])
    assert yaml_load_typed(schema=PseudoForceConfig, data=yaml_dump_typed(config)) == config
    partial = yaml_load_typed(schema=PseudoForceConfig, data="{force_limit: 2.0}")
    assert partial == dataclasses.replace(PseudoForceConfig(), force_limit=2.0)
    check_pseudo_force_config(PseudoForceConfig())
    with pytest.raises(RuntimeError, match="unknown"):
        yaml_load_typed(schema=PseudoForceConfig, data="{no_such_gain: 1.0}")


@pytest.mark.parametrize("field, value", [
    ("k_wall", -1.0), ("lumen_weight", math.inf), ("c_wall", math.nan), ("force_limit", 0.0),
    ("wall_distance", -0.001), ("update_period", 0.0), ("k_radial", -5.0),
    ("device_from_camera_rpy_deg", [180.0, 0.0]),
    ("device_from_camera_rpy_deg", [180.0, math.nan, 0.0])])
def test_bad_config_values_name_the_field(field, value):
    config = dataclasses.replace(PseudoForceConfig(), **{field: value})
    with pytest.raises(ValueError, match=field) as error:
        check_pseudo_force_config(config)
    assert "\n" not in str(error.value)
    # The system trusts its config; a scenario is checked when it is loaded.
    with pytest.raises(ScenarioError,
                       match=rf"^scenario: pseudo_force\.{field} must be") as error:
        load_scenario(override=f"pseudo_force: {{{field}: {_yaml(value)}}}")
    assert "\n" not in str(error.value)


def _yaml(value) -> str:
    """A number or a list of numbers as YAML (.inf, .nan for the non-finite)."""
    if isinstance(value, list):
        return "[" + ", ".join(_yaml(v) for v in value) + "]"
    return {math.inf: ".inf", -math.inf: "-.inf"}.get(value, ".nan" if math.isnan(value)
                                                       else repr(value))
