"""Teleoperation: the haptic device's dynamics and limits, the stylus-to-EPM mapping (the
three motions, clutch, lost link), the simulated operator's intent, and the loop in the
station with the simulated operator, a device over UDP and the browser."""


import numpy as np
import pytest
from pydrake.geometry import Meshcat, MeshcatParams
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from capsule_drake.anatomy import load_colon
from capsule_drake.capsule.model import start_pose
from capsule_drake.epm.guard import EpmGuard
from capsule_drake.epm.poses import field_aligning_moment_direction
from capsule_drake.scenario import Scenario, load_scenario
from capsule_drake.station import make_station
from capsule_drake.teleop.force_feedback import ForceFeedback
from capsule_drake.teleop.haptic_master import HapticDeviceConfig, HapticMaster
from capsule_drake.teleop.mapping import MappingConfig, TeleopMapping
from capsule_drake.perception.lumen_range import free_range
from capsule_drake.teleop.operator import (ForwardSpeed, OperatorConfig, SimulatedOperator,
                                           WayForward)
from pydrake.common.eigen_geometry import AngleAxis
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from capsule_drake.teleop.udp_client import StylusClient
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant

from capsule_drake.models import PACKAGE, configure_parser


def _device(hand, feedback, buttons=(0.0, 0.0), config=HapticDeviceConfig()):
    builder = DiagramBuilder()
    device = builder.AddSystem(HapticMaster(config))
    for name, value in (("hand_force", hand), ("feedback_force", feedback),
                        ("buttons", buttons)):
        source = builder.AddSystem(ConstantVectorSource(np.asarray(value, dtype=float)))
        builder.Connect(source.get_output_port(), device.GetInputPort(name))
    diagram = builder.Build()
    return diagram, device


def test_device_stylus_moves_as_a_mass_with_friction():
    config = HapticDeviceConfig()
    diagram, device = _device([0.2, 0.0, 0.0], [0.0, 0.0, 0.0])
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.1)
    context = device.GetMyContextFromRoot(simulator.get_context())
    v = device.GetOutputPort("stylus_velocity").Eval(context)
    m, b = config.stylus_mass, config.friction
    expected = 0.2 / b * (1.0 - np.exp(-b * 0.1 / m))  # closed form of m v' = F - b v
    assert v[0] == pytest.approx(expected, rel=0.02)
    assert abs(v[1]) < 1e-12 and abs(v[2]) < 1e-12


def test_device_saturates_the_rendered_force_and_has_stops():
    diagram, device = _device([0.0, 0.0, 0.0], [6.0, 8.0, 0.0])
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.01)
    context = device.GetMyContextFromRoot(simulator.get_context())
    motor = device.GetOutputPort("motor_force").Eval(context)
    np.testing.assert_allclose(motor[:3], [1.98, 2.64, 0.0], atol=1e-12)  # 3.3 N along it
    assert motor[3] == 1.0
    diagram, device = _device([0.0, 0.0, 0.0], [np.nan, 0.0, 0.0])
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.01)
    context = device.GetMyContextFromRoot(simulator.get_context())
    np.testing.assert_array_equal(device.GetOutputPort("motor_force").Eval(context)[:3], 0.0)
    # Pushed out of the workspace with 2 N, the stylus rests on the stop 2 N / k beyond it.
    config = HapticDeviceConfig()
    diagram, device = _device([0.0, 0.0, -2.0], [0.0, 0.0, 0.0])
    simulator = Simulator(diagram)
    simulator.AdvanceTo(3.0)
    context = device.GetMyContextFromRoot(simulator.get_context())
    z = device.GetOutputPort("stylus").Eval(context)[2]
    assert z == pytest.approx(-config.workspace_half_extents[2] - 2.0 / config.stop_stiffness,
                              abs=1e-4)


def test_force_feedback_is_the_pseudo_force_plus_the_contact_seen_from_the_camera():
    """F_D = pseudo + gain R_DC R_CW F_W, saturated by norm; non-finite inputs count as
    zero. R_CW is built here from roll-pitch-yaw, not the quaternion the system reads."""
    X_BC = RigidTransform(RollPitchYaw(0.3, -0.2, 0.1), [0.0, 0.0, 0.01])
    feedback = ForceFeedback(X_BC, contact_gain=2.0, force_limit=3.3)
    context = feedback.CreateDefaultContext()
    R_WB = RotationMatrix(RollPitchYaw(0.7, 0.4, -1.1))
    q = R_WB.ToQuaternion()
    state = np.concatenate([[q.w(), q.x(), q.y(), q.z()], np.zeros(9)])
    R_DC = np.diag([1.0, -1.0, -1.0])  # 180 deg about x, the default device_from_camera
    R_CW = (R_WB.matrix() @ X_BC.rotation().matrix()).T

    def output(pseudo, F_W, state=state):
        feedback.GetInputPort("pseudo_force_D").FixValue(context, pseudo)
        feedback.GetInputPort("capsule_force_W").FixValue(context, F_W)
        feedback.GetInputPort("capsule_state").FixValue(context, state)
        return feedback.GetOutputPort("F_D").Eval(context).copy()

    F_W, pseudo = np.array([0.2, -0.3, 0.5]), np.array([0.1, 0.2, -0.3])
    expected = pseudo + 2.0 * R_DC @ R_CW @ F_W
    np.testing.assert_allclose(output(pseudo, F_W), expected, atol=1e-12)
    np.testing.assert_allclose(output(pseudo, 10.0 * F_W),
                               3.3 * (u := pseudo + 20.0 * R_DC @ R_CW @ F_W)
                               / np.linalg.norm(u), atol=1e-12)
    np.testing.assert_allclose(output([np.nan, 0.0, 0.0], F_W), expected - pseudo, atol=1e-12)
    np.testing.assert_allclose(output(pseudo, [np.inf, 0.0, 0.0]), pseudo, atol=1e-12)
    np.testing.assert_allclose(output(pseudo, F_W, np.full(13, np.nan)), pseudo, atol=1e-12)


@pytest.fixture(scope="module")
def colon():
    return load_colon(Scenario().colon)[0]


class _Mapping:
    """A TeleopMapping on its own, the capsule held at a pose, the stylus set by hand."""

    def __init__(self, colon, config=MappingConfig()):
        scenario = Scenario()
        guard = EpmGuard(colon.abdomen, scenario.epm.magnet, 0.02, np.zeros(3), np.inf)
        plant = MultibodyPlant(0.0)
        configure_parser(Parser(plant)).AddModels(url=f"package://{PACKAGE}/capsule.sdf")
        plant.Finalize()
        X_BC = plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()
        self.X_WB = start_pose(colon, 0.45)
        self.p_WM = self.X_WB.translation()
        h0 = self.X_WB.rotation().col(2)
        p = self.p_WM + [0.0, 0.0, 0.12]
        u = (self.p_WM - p) / np.linalg.norm(self.p_WM - p)
        first = np.concatenate([p, field_aligning_moment_direction(u, h0)])
        self.system = TeleopMapping(config, X_BC, [0.0, 0.0, 0.0],
                                    guard.lowest_centre_height, first, h0)
        self.context = self.system.CreateDefaultContext()
        q = self.X_WB.rotation().ToQuaternion()
        state = np.concatenate([[q.w(), q.x(), q.y(), q.z()], self.p_WM, np.zeros(6)])
        self.system.GetInputPort("capsule_state").FixValue(self.context, state)
        self.R_WC = self.X_WB.rotation().matrix() @ X_BC.rotation().matrix()
        self.simulator = Simulator(self.system, self.context)
        self.set([0.0, 0.0, 0.0])

    def set(self, p, clutch=0.0, age=0.0):
        self.system.GetInputPort("stylus").FixValue(
            self.context, np.concatenate([p, [1.0, 0.0, 0.0, 0.0], [clutch, 0.0]]))
        self.system.GetInputPort("stylus_age").FixValue(self.context, [age])

    def step(self, seconds=0.02):
        self.simulator.AdvanceTo(self.context.get_time() + seconds)
        return (self.system.GetOutputPort("epm_command").Eval(self.context).copy(),
                self.system.GetOutputPort("heading").Eval(self.context).copy())


def test_mapping_the_three_motions(colon):
    m = _Mapping(colon)
    command0, h0 = m.step()
    m.set([0.0, 0.0, -0.01])  # push 1 cm away: forward
    command, h = m.step()
    travel = command[:2] - command0[:2]
    forward = h0[:2] / np.linalg.norm(h0[:2])
    assert travel @ forward == pytest.approx(0.02, abs=1e-9)  # 2:1 scale, along the heading
    assert abs(travel @ np.array([-forward[1], forward[0]])) < 1e-9
    np.testing.assert_allclose(h, h0, atol=1e-12)
    # The moment makes the field at the capsule point along the heading.
    u = (m.p_WM - command[:3]) / np.linalg.norm(m.p_WM - command[:3])
    field = 3 * u * (u @ command[3:]) - command[3:]
    assert np.degrees(np.arccos(np.clip(field @ h / np.linalg.norm(field), -1, 1))) < 1e-5
    m.set([0.01, 0.0, -0.01])  # 1 cm right: yaw right by 0.12 rad about the image's up
    _, h_yaw = m.step()
    right, up = m.R_WC[:, 0], -m.R_WC[:, 1]
    assert np.arccos(np.clip(h_yaw @ h0, -1, 1)) == pytest.approx(0.12, abs=1e-9)
    assert np.cross(h0, h_yaw) @ up < 0 and (h_yaw - h0) @ right > 0
    m.set([0.01, 0.01, -0.01])  # and 1 cm up: pitch up
    _, h_pitch = m.step()
    assert (h_pitch - h_yaw) @ up > 0


def test_lead_mapping_keeps_the_epm_over_the_capsule_ahead_by_the_lead(colon):
    m = _Mapping(colon, MappingConfig(mode="lead"))
    m.step()
    m.set([0.0, 0.0, -0.01])  # 1 cm away: a 2 cm lead along the heading
    command, h = m.step()
    lead = command[:2] - m.p_WM[:2]
    forward = h[:2] / np.linalg.norm(h[:2])
    assert lead @ forward == pytest.approx(0.02, abs=1e-9)
    assert abs(lead @ np.array([-forward[1], forward[0]])) < 1e-9
    m.set([0.0, 0.0, -0.2])  # far beyond the workspace: the lead stops at its limit
    command, h = m.step()
    assert np.linalg.norm(command[:2] - m.p_WM[:2]) == pytest.approx(0.05, abs=1e-9)


def test_assisted_lead_goes_toward_the_detected_lumen(colon):
    m = _Mapping(colon, MappingConfig(mode="lead", assist=True))
    ray_C = np.array([0.5, 0.0, 1.0]) / np.linalg.norm([0.5, 0.0, 1.0])  # right of centre
    m.system.GetInputPort("lumen_ray").FixValue(m.context, ray_C)
    m.system.GetInputPort("lumen_visible").FixValue(m.context, [1.0])
    m.step()
    m.set([0.0, 0.0, -0.01])
    command, _ = m.step()
    lead = command[:2] - m.p_WM[:2]
    toward = (m.R_WC @ ray_C)[:2]
    np.testing.assert_allclose(lead, 0.02 * toward / np.linalg.norm(toward), atol=1e-9)


def test_assisted_lead_stops_short_of_the_tissue_along_the_lumen_ray(colon):
    m = _Mapping(colon, MappingConfig(mode="lead", assist=True, assist_margin=0.01,
                                      max_lead_distance=0.1))
    ray_C = np.array([0.0, 0.3, 1.0]) / np.linalg.norm([0.0, 0.3, 1.0])
    m.system.GetInputPort("lumen_ray").FixValue(m.context, ray_C)
    m.system.GetInputPort("lumen_visible").FixValue(m.context, [1.0])
    m.system.GetInputPort("lumen_range").FixValue(m.context, [0.04])
    m.step()
    m.set([0.0, 0.0, -0.01])  # a 2 cm lead, inside the 4 cm of open lumen: 2 cm along it
    command, _ = m.step()
    ray_W = m.R_WC @ ray_C
    np.testing.assert_allclose(command[:2], m.p_WM[:2] + 0.02 * ray_W[:2], atol=1e-9)
    m.set([0.0, 0.0, -0.03])  # a 6 cm lead: the EPM stops over 3 cm along the ray
    command, _ = m.step()
    np.testing.assert_allclose(command[:2], m.p_WM[:2] + 0.03 * ray_W[:2], atol=1e-9)
    m.system.GetInputPort("lumen_range").FixValue(m.context, [np.nan])  # range unknown
    command, _ = m.step()
    toward = ray_W[:2] / np.linalg.norm(ray_W[:2])
    np.testing.assert_allclose(command[:2], m.p_WM[:2] + 0.06 * toward, atol=1e-9)


def test_lead_mapping_steers_from_the_cameras_current_axis(colon):
    m = _Mapping(colon, MappingConfig(mode="lead"))
    m.step()
    m.set([0.01, 0.0, 0.0])  # 1 cm right: 0.12 rad right of where the camera looks now
    _, h = m.step()
    forward, right = m.R_WC[:, 2], m.R_WC[:, 0]
    assert np.arccos(np.clip(h @ forward, -1, 1)) == pytest.approx(0.12, abs=1e-9)
    assert (h - forward) @ right > 0
    # The capsule turns (here: by hand, 0.3 rad about the image's up): the heading follows,
    # still 0.12 rad right of the new axis, with no clutching.
    up = -m.R_WC[:, 1]
    R_turn = RotationMatrix(AngleAxis(-0.3, up)).matrix()  # right turn about image up
    R_WB = R_turn @ m.X_WB.rotation().matrix()
    q = RotationMatrix(R_WB).ToQuaternion()
    m.system.GetInputPort("capsule_state").FixValue(
        m.context, np.concatenate([[q.w(), q.x(), q.y(), q.z()], m.p_WM, np.zeros(6)]))
    _, h2 = m.step()
    forward2 = R_turn @ forward
    assert np.arccos(np.clip(h2 @ forward2, -1, 1)) == pytest.approx(0.12, abs=1e-9)
    assert np.arccos(np.clip(h2 @ h, -1, 1)) == pytest.approx(0.3, abs=1e-9)


def test_mapping_limits_the_epm_speed(colon):
    m = _Mapping(colon, MappingConfig(mode="lead", max_speed=0.02, period=0.005))
    command0, _ = m.step()
    m.set([0.0, 0.0, -0.02])  # a 4 cm lead at once: the command moves 2 cm/s toward it
    command, _ = m.step(0.5)
    moved = np.linalg.norm(command[:2] - command0[:2])
    assert moved == pytest.approx(0.01, abs=1e-9)
    command, _ = m.step(2.0)
    assert np.linalg.norm(command[:2] - m.p_WM[:2]) == pytest.approx(0.04, abs=1e-9)


def test_free_range_reads_the_depth_at_the_lumen_pixel():
    depth = np.full((64, 64), 0.05, dtype=np.float32)
    depth[30:35, 40:45] = np.inf  # beyond the far clip
    assert free_range(depth, [10.2, 20.7], far=0.2) == pytest.approx(0.05)
    assert free_range(depth, [42, 32], far=0.2) == pytest.approx(0.2)
    assert np.isnan(free_range(depth, [70, 3], far=0.2))
    assert np.isnan(free_range(depth, [np.nan, 3], far=0.2))


def test_forward_speed_is_the_velocity_along_the_camera_axis():
    speed = ForwardSpeed([0.0, 0.0, 1.0])
    context = speed.CreateDefaultContext()
    rpy = RollPitchYaw(0.3, 1.1, -0.4)
    q, R = rpy.ToQuaternion(), rpy.ToRotationMatrix().matrix()
    v = np.array([0.3, -0.1, 0.2])
    speed.get_input_port().FixValue(
        context, np.concatenate([[q.w(), q.x(), q.y(), q.z()], np.zeros(3), np.zeros(3), v]))
    assert speed.get_output_port().Eval(context)[0] == pytest.approx(v @ R[:, 2], abs=1e-12)


def _operator_seeing(config, ray=(0.0, 0.0, 1.0)):
    """A SimulatedOperator with the stylus at rest at the centre and the lumen in view along
    `ray`; returns (operator, context)."""
    operator = SimulatedOperator(config, HapticDeviceConfig().workspace_half_extents)
    context = operator.CreateDefaultContext()
    operator.GetInputPort("stylus").FixValue(context, np.r_[np.zeros(3), 1, 0, 0, 0, 0, 0])
    operator.GetInputPort("stylus_velocity").FixValue(context, np.zeros(3))
    operator.GetInputPort("lumen_visible").FixValue(context, [1.0])
    operator.GetInputPort("lumen_ray").FixValue(context, np.asarray(ray, dtype=float))
    return operator, context


def test_simulated_operator_regulates_the_capsule_speed():
    config = OperatorConfig(reaction_time=0.02, period=0.01, cruise_offset=0.03,
                            target_speed=0.01, speed_gain=1.0, speed_time=0.05)
    operator, context = _operator_seeing(config)
    operator.GetInputPort("forward_speed").FixValue(context, [0.0])  # stuck: push on
    simulator = Simulator(operator, context)
    simulator.AdvanceTo(1.0)
    z_stuck = operator.GetOutputPort("intent").Eval(context)[2]
    assert z_stuck == pytest.approx(-0.01 * 1.0, abs=1.5e-3)  # 1 cm/s of stylus, forward
    operator.GetInputPort("forward_speed").FixValue(context, [0.2])  # shooting: draw back
    simulator.AdvanceTo(1.5)
    z_fast = operator.GetOutputPort("intent").Eval(context)[2]
    assert z_fast > z_stuck + 0.01
    assert z_fast <= 0.5 * config.cruise_offset + 1e-12  # at most a little behind centre


def test_way_forward_points_from_the_trail_to_the_capsule_in_the_camera_frame():
    rpy = RollPitchYaw(0.2, -0.4, 1.0)
    R_WB = rpy.ToRotationMatrix().matrix()
    R_BC = RollPitchYaw(np.pi, 0.0, 0.0).ToRotationMatrix().matrix()
    way = WayForward(R_BC, start=[0.0, 0.0, 0.0], trail_time=1.0, period=0.05)
    context = way.CreateDefaultContext()
    q = rpy.ToQuaternion()

    def at(p):
        way.get_input_port().FixValue(context, np.concatenate(
            [[q.w(), q.x(), q.y(), q.z()], p, np.zeros(6)]))
        return way.get_output_port().Eval(context)

    np.testing.assert_array_equal(at([0.01, 0.0, 0.0]), 0.0)  # within 2 cm of the trail
    p = np.array([0.1, 0.05, 0.0])
    np.testing.assert_allclose(at(p), (R_WB @ R_BC).T @ (p / np.linalg.norm(p)), atol=1e-12)
    simulator = Simulator(way, context)
    simulator.AdvanceTo(10.0)  # the trail catches up with a capsule that stays put
    np.testing.assert_array_equal(at(p), 0.0)


def test_operator_looking_back_the_way_it_came_searches_toward_the_way_forward():
    config = OperatorConfig(reaction_time=0.02, period=0.01, cruise_offset=0.03,
                            search_offset=0.02, turn_back_deg=30.0, steer_time=0.05)
    operator, context = _operator_seeing(config)  # the lumen centred
    way = np.array([0.6, 0.0, -0.8])  # the way forward is behind, to the right
    operator.GetInputPort("way_forward").FixValue(context, way)
    simulator = Simulator(operator, context)
    simulator.AdvanceTo(1.0)
    intent = operator.GetOutputPort("intent").Eval(context)
    assert intent[3] == 2.0  # not advancing toward the lumen in view: searching
    assert intent[0] > 0.015 and abs(intent[1]) < 1e-3  # turning right, toward the way
    operator.GetInputPort("way_forward").FixValue(context, [0.0, 0.0, 1.0])  # ahead again
    simulator.AdvanceTo(2.0)
    assert operator.GetOutputPort("intent").Eval(context)[3] == 0.0  # advancing


def test_mapping_clutch_and_lost_link_hold_the_command(colon):
    m = _Mapping(colon)
    m.step()
    m.set([0.0, 0.0, -0.01])
    engaged, _ = m.step()
    m.set([0.0, 0.0, 0.03], clutch=1.0)  # indexing back: nothing moves
    held, _ = m.step()
    np.testing.assert_array_equal(held, engaged)
    m.set([0.0, 0.0, 0.03])  # released: re-referenced there, no jump
    np.testing.assert_array_equal(m.step()[0], engaged)
    m.set([0.0, 0.0, 0.02])  # 1 cm further away from the new reference
    moved, _ = m.step()
    assert np.linalg.norm(moved[:2] - engaged[:2]) == pytest.approx(0.02, abs=1e-9)
    m.set([0.0, 0.0, -0.03], age=0.5)  # stale: hold
    np.testing.assert_array_equal(m.step()[0], moved)
    m.set([np.nan, 0.0, 0.0])  # garbage: hold
    np.testing.assert_array_equal(m.step()[0], moved)


def test_simulated_operator_advances_indexes_and_steers():
    config = OperatorConfig(reaction_time=0.02, period=0.01)
    half = HapticDeviceConfig().workspace_half_extents
    operator = SimulatedOperator(config, half)
    context = operator.CreateDefaultContext()
    operator.GetInputPort("stylus").FixValue(context, np.r_[np.zeros(3), 1, 0, 0, 0, 0, 0])
    operator.GetInputPort("stylus_velocity").FixValue(context, np.zeros(3))
    operator.GetInputPort("lumen_visible").FixValue(context, [1.0])
    ray = np.array([0.2, 0.0, 1.0]) / np.linalg.norm([0.2, 0.0, 1.0])  # right of centre
    operator.GetInputPort("lumen_ray").FixValue(context, ray)
    simulator = Simulator(operator, context)
    simulator.AdvanceTo(1.0)
    intent = operator.GetOutputPort("intent").Eval(context)
    start = half[2] * config.stroke_fraction
    assert intent[2] == pytest.approx(start - config.advance_speed * 0.98, abs=2e-4)
    assert intent[0] > 0  # steering right, toward the lumen
    # The hand's force is its impedance toward the target.
    force = operator.GetOutputPort("hand_force").Eval(context)
    np.testing.assert_allclose(force, config.hand_stiffness * intent[:3])
    simulator.AdvanceTo(20.0)  # long enough to reach the front: clutch and return
    phases = []
    for _ in range(400):
        simulator.AdvanceTo(context.get_time() + 0.05)
        phases.append(operator.GetOutputPort("intent").Eval(context)[3])
    assert 1.0 in phases and 0.0 in phases


@pytest.mark.slow
def test_teleop_in_the_station_with_the_simulated_operator():
    scenario = load_scenario(name="Teleop", override="{duration: 20.0, epm: {mount: !Stage {}}}")
    diagram = make_station(scenario)
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    command0 = diagram.GetOutputPort("epm.command").Eval(context).copy()
    commands, positions = [], []
    for t in np.arange(0.5, 20.01, 0.5):
        simulator.AdvanceTo(t)
        commands.append(diagram.GetOutputPort("epm.command").Eval(context)[:3].copy())
        positions.append(diagram.GetOutputPort("capsule.state").Eval(context)[4:7].copy())
    commands, positions = np.array(commands), np.array(positions)
    # The operator drove the EPM about (where the capsule goes from there is a matter of
    # stick-slip and the view: the teleoperation benchmark measures it) ...
    assert np.max(np.linalg.norm(commands[:, :2] - command0[:2], axis=1)) > 0.03
    assert np.sum(np.linalg.norm(np.diff(commands, axis=0), axis=1)) > 0.1
    # ... and the capsule moved with it.
    assert np.sum(np.linalg.norm(np.diff(positions, axis=0), axis=1)) > 0.02
    force = diagram.GetOutputPort("teleop.feedback_D").Eval(context)
    assert np.all(np.isfinite(force)) and np.linalg.norm(force) <= 3.3 + 1e-9


def test_teleop_over_udp_moves_the_epm_and_a_lost_link_holds_it():
    scenario = load_scenario(name="Teleop", override=(
        "{duration: 1.0, epm: {mount: !Stage {}, driver: !Teleop "
        "{operator: udp, mapping: {mode: position, translation_scale: 2.0}}}, "
        "capsule: {camera: null, lumen_tracker: null}, pseudo_force: {lumen_weight: 0}}"))
    diagram = make_station(scenario)
    device = diagram.GetSubsystemByName("teleop.device")
    client = StylusClient("127.0.0.1", device.port())
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    try:
        command0 = diagram.GetOutputPort("epm.command").Eval(context).copy()
        for k in range(300):  # the stylus pushed 15 mm away over 0.3 s
            client.send([0.0, 0.0, -0.05e-3 * k], [1.0, 0.0, 0.0, 0.0], 0)
            simulator.AdvanceTo((k + 1) * 0.001)
        simulator.AdvanceTo(0.35)
        command = diagram.GetOutputPort("epm.command").Eval(context).copy()
        assert np.linalg.norm(command[:2] - command0[:2]) > 0.02
        assert diagram.GetOutputPort("teleop.link_ok").Eval(context)[0] == 1.0
        assert client.receive(timeout=0.1)  # force replies came back
        simulator.AdvanceTo(0.45)  # no packets since 0.3 s: lost after the 0.1 s timeout
        assert diagram.GetOutputPort("teleop.link_ok").Eval(context)[0] == 0.0
        held = diagram.GetOutputPort("epm.command").Eval(context).copy()
        simulator.AdvanceTo(0.8)  # the EPM command holds while the link is down
        np.testing.assert_array_equal(diagram.GetOutputPort("epm.command").Eval(context),
                                      held)
        replies = client.receive(timeout=0.1)
        assert replies and np.all(np.asarray(replies[-1].force) == 0.0)
    finally:
        client.close()
        device.close()


@pytest.mark.slow
def test_teleop_from_the_browser_follows_the_sliders():
    meshcat = Meshcat(MeshcatParams(port=0))
    scenario = load_scenario(name="Teleop", override=(
        "{duration: 1.0, epm: {mount: !Stage {}, driver: !Teleop "
        "{operator: browser, mapping: {mode: position, translation_scale: 2.0}}}, "
        "capsule: {camera: {lens: {width: 64, height: 64}}}}"))
    diagram = make_station(scenario, meshcat)
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    simulator.AdvanceTo(0.1)
    command0 = diagram.GetOutputPort("epm.command").Eval(context).copy()
    meshcat.SetSliderValue("stylus z (m)", -0.01)
    simulator.AdvanceTo(0.3)
    stylus = diagram.GetOutputPort("teleop.stylus").Eval(context)
    assert stylus[2] == pytest.approx(-0.01)
    command = diagram.GetOutputPort("epm.command").Eval(context)
    assert np.linalg.norm(command[:2] - command0[:2]) == pytest.approx(0.02, abs=1e-6)
