"""The EPM on a 7-DoF arm: a controller that places the magnet, and the magnet's pose.

    EPM command [p_WE, m_hat_W] --> EpmArmController --> arm desired state (joint PD servos)
                                      ^ arm state (initialisation, tracking report)

The command is a position for the magnet's centre and a direction for its moment (the roll
about the moment is free). The controller guards it (clearance above the skin, reach),
then runs Drake's differential inverse kinematics (a QP: the command's velocity in least
squares, joint position and velocity limits as constraints, a joint-centering cost toward
a posture in the null space) on an integrated joint command, which the arm's joint servos
track in the plant. The magnet's reaction wrench loads the arm through those servos.
"""

import dataclasses

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.inverse_kinematics import (
    DifferentialInverseKinematicsParameters,
    DifferentialInverseKinematicsStatus,
    DoDifferentialInverseKinematics,
)
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem

from capsule_drake.epm.poses import (highest_skin_under, magnet_footprint_radius,
                                    magnet_vertical_half_extent)

ARM_JOINTS = tuple(f"arm_joint_{i}" for i in range(1, 8))
ARM_BASE = "arm_link_0"
# Shoulder (joint 2) height above the base, from the model (m).
SHOULDER_HEIGHT = 0.36


@dataclasses.dataclass
class ArmConfig:
    """The arm that carries the EPM (models/epm_arm.sdf) and its controller.
    YAML-loadable; all fields default."""

    # Pose of the arm's base in the world (m, deg): beside the patient table (top at z = 0,
    # origin under the umbilicus, +y toward the head), facing the patient.
    base_xyz: list[float] = dataclasses.field(default_factory=lambda: [0.62, 0.0, 0.0])
    base_yaw_deg: float = 180.0
    # Joint servo gains (N m/rad, N m s/rad), per joint; the servos are the plant's implicit
    # PD actuators (an ideal torque-controlled arm with gravity compensation: the arm's own
    # weight is not simulated, the magnet's force on it is).
    joint_stiffness: list[float] = dataclasses.field(
        default_factory=lambda: [8000.0, 8000.0, 5000.0, 5000.0, 2000.0, 1000.0, 500.0])
    joint_damping: list[float] = dataclasses.field(
        default_factory=lambda: [300.0, 300.0, 150.0, 150.0, 40.0, 20.0, 8.0])
    # Controller period (s).
    control_period: float = 0.005
    # Fraction of the datasheet joint speeds the controller may command.
    velocity_scale: float = 0.5
    # Margin kept from each joint's position limits (deg).
    limit_margin_deg: float = 3.0
    # Joint-centering gain toward the posture (1/s), in the task's null space.
    centering_gain: float = 1.0
    # Posture the null space is drawn to (deg); empty: the posture that reaches the first
    # command, solved when the station is built.
    posture_deg: list[float] = dataclasses.field(default_factory=list)
    # Fastest the controller moves the magnet toward a command: speed (m/s) and turn rate
    # of its moment (rad/s). Commands that move slower are followed exactly.
    max_speed: float = 0.2
    max_turn_rate: float = 1.0
    # Descent toward the skin: at most approach_speed (m/s) plus the height above the
    # clearance floor over approach_time (s), so the magnet arrives at the floor slowly.
    approach_speed: float = 0.005
    approach_time: float = 0.1
    # Largest distance from the shoulder to the magnet's centre the guard lets through (m).
    reach: float = 0.9
    # A command whose placement misses by more than this is reported unreachable (m).
    unreachable_tolerance: float = 0.002


def check_arm_config(config: ArmConfig) -> None:
    """Raises ValueError naming the first impossible field."""
    if len(config.base_xyz) != 3:
        raise ValueError("epm.arm.base_xyz must have 3 values")
    for name in ("joint_stiffness", "joint_damping"):
        values = getattr(config, name)
        if len(values) != 7 or min(values) < 0.0:
            raise ValueError(f"epm.arm.{name} must be 7 values >= 0")
    if config.posture_deg and len(config.posture_deg) != 7:
        raise ValueError("epm.arm.posture_deg must be empty or 7 values")
    if not config.control_period > 0.0:
        raise ValueError("epm.arm.control_period must be > 0")
    if not 0.0 < config.velocity_scale <= 1.0:
        raise ValueError("epm.arm.velocity_scale must be in (0, 1]")
    if not config.limit_margin_deg >= 0.0 or not config.centering_gain >= 0.0:
        raise ValueError("epm.arm.limit_margin_deg and centering_gain must be >= 0")
    if not config.approach_speed > 0.0 or not config.approach_time > 0.0:
        raise ValueError("epm.arm.approach_speed and approach_time must be > 0")
    if not config.max_speed > 0.0 or not config.max_turn_rate > 0.0:
        raise ValueError("epm.arm.max_speed and max_turn_rate must be > 0")
    if not config.reach > 0.0 or not config.unreachable_tolerance > 0.0:
        raise ValueError("epm.arm.reach and unreachable_tolerance must be > 0")


def arm_base_pose(config: ArmConfig) -> RigidTransform:
    return RigidTransform(RotationMatrix.MakeZRotation(np.radians(config.base_yaw_deg)),
                          np.asarray(config.base_xyz, dtype=float))


class EpmGuard:
    """Keeps an EPM command safe and within reach: the magnet's lowest point at least
    `clearance` above the highest skin under it, its centre within `reach` of the shoulder.
    `apply(p, m)` returns (p_safe, m_hat, raised (bool), pulled_in (bool))."""

    def __init__(self, abdomen, geometry, clearance: float, shoulder_W: np.ndarray,
                 reach: float):
        self.abdomen = abdomen
        self.geometry = geometry
        self.clearance = clearance
        self.shoulder_W = np.asarray(shoulder_W, dtype=float)
        self.reach = reach
        self._footprint = magnet_footprint_radius(geometry)

    def lowest_centre_height(self, x: float, y: float, m_hat: np.ndarray) -> float:
        skin = highest_skin_under(self.abdomen, x, y, self._footprint)
        return skin + self.clearance + magnet_vertical_half_extent(m_hat, self.geometry)

    def apply(self, p_WE, m_hat_W):
        p = np.array(p_WE, dtype=float)
        m = np.asarray(m_hat_W, dtype=float)
        m = m / np.linalg.norm(m)
        pulled_in = False
        offset = p - self.shoulder_W
        distance = np.linalg.norm(offset)
        if distance > self.reach:
            p = self.shoulder_W + offset * (self.reach / distance)
            pulled_in = True
        floor = self.lowest_centre_height(p[0], p[1], m)
        raised = bool(p[2] < floor)
        if raised:
            p[2] = floor
        return p, m, raised, pulled_in


def rotate_axis_onto(R_WE: RotationMatrix, target_W: np.ndarray) -> RotationMatrix:
    """The rotation nearest R_WE whose z axis is `target_W`: R_WE turned by the smallest
    rotation that takes its z axis onto the target (roll about the axis unchanged)."""
    z = R_WE.col(2)
    target = np.asarray(target_W, dtype=float) / np.linalg.norm(target_W)
    axis = np.cross(z, target)
    sin, cos = np.linalg.norm(axis), float(np.clip(z @ target, -1.0, 1.0))
    if sin < 1e-12:
        if cos > 0.0:
            return R_WE
        axis = R_WE.col(0)  # half turn about x
    else:
        axis = axis / sin
    angle = np.arctan2(sin, cos)
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]],
                  [-axis[1], axis[0], 0.0]])
    R = np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K
    return RotationMatrix(R @ R_WE.matrix())


class EpmArmController(LeafSystem):
    """Places the EPM with the arm: guard, differential IK, integrated joint command.

    .. pydrake_system::

        name: EpmArmController
        input_ports:
        - epm_command
        - arm_state
        output_ports:
        - arm_desired_state
        - status

    epm_command: [p_WE (3), m_hat_W (3)], the magnet's centre and moment direction; a
    non-finite command holds the last one (a lost or corrupt link keeps the EPM where it
    is). arm_state: the arm's [q (7), v (7)] in the plant (read at initialisation and for
    the tracking report). arm_desired_state: [q_cmd, v_cmd] for the joint servos.
    status: [command raised to the clearance (0/1), command pulled within reach (0/1),
    unreachable (0/1: the IK placement misses the guarded command by more than
    `unreachable_tolerance`), placement error of the joint command (m), its moment-axis
    error (rad), IK failures so far, non-finite commands so far].

    Args:
        arm_plant: a MultibodyPlant holding only the arm (base welded at the station's
            pose) and its EPM, finalised: the controller's kinematic model.
        config: ArmConfig.
        guard: an EpmGuard.
        q0: initial joint command (7), e.g. `solve_posture`'s result.
    """

    def __init__(self, arm_plant, config: ArmConfig, guard: EpmGuard, q0):
        super().__init__()
        check_arm_config(config)
        self._plant = arm_plant
        self._context = arm_plant.CreateDefaultContext()
        self._frame_E = arm_plant.GetBodyByName("epm").body_frame()
        self._config = config
        self._guard = guard
        self._dt = config.control_period
        self._params = ik_parameters(arm_plant, config, self._dt, q0)
        self._command_port = self.DeclareVectorInputPort("epm_command", 6)
        self._state_port = self.DeclareVectorInputPort("arm_state", 14)
        # [q_cmd (7), v_cmd (7), last good command (6), raised, pulled, unreachable,
        #  position error, axis error, ik failures, bad commands]
        initial = np.concatenate([q0, np.zeros(7), np.full(6, np.nan), np.zeros(7)])
        self._state = self.DeclareDiscreteState(BasicVector(initial))
        self.DeclareVectorOutputPort(
            "arm_desired_state", 14,
            lambda context, out: out.SetFromVector(
                context.get_discrete_state(self._state).value()[:14]),
            {self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "status", 7,
            lambda context, out: out.SetFromVector(
                context.get_discrete_state(self._state).value()[20:27]),
            {self.xd_ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(self._dt, 0.0, self._update)

    def place(self, q: np.ndarray, p_target, m_target):
        """One controller step from joint command q toward the (guarded) target: the
        velocity that closes the gap in one step, capped at the config's speeds (so the QP
        can follow its direction), through the differential IK. Returns (q_next, v,
        solved)."""
        self._plant.SetPositions(self._context, q)
        X_WE = self._plant.CalcRelativeTransform(self._context, self._plant.world_frame(),
                                                 self._frame_E)
        axis = X_WE.rotation().col(2)
        turn = np.cross(axis, m_target)
        sin = np.linalg.norm(turn)
        angle = np.arctan2(sin, float(axis @ m_target))
        if sin > 1e-12:
            omega = turn / sin * angle / self._dt
        elif angle > 1.0:  # opposite: turn about any axis across the moment
            omega = X_WE.rotation().col(0) * angle / self._dt
        else:
            omega = np.zeros(3)
        velocity = (np.asarray(p_target) - X_WE.translation()) / self._dt
        c = self._config
        omega *= min(1.0, c.max_turn_rate / max(np.linalg.norm(omega), 1e-12))
        velocity *= min(1.0, c.max_speed / max(np.linalg.norm(velocity), 1e-12))
        # Slow down toward the skin: the servos would carry a fast descent past the floor.
        p = X_WE.translation()
        height = p[2] - self._guard.lowest_centre_height(p[0], p[1], axis)
        descent = c.approach_speed + max(height, 0.0) / c.approach_time
        velocity[2] = max(velocity[2], -descent)
        result = DoDifferentialInverseKinematics(self._plant, self._context,
                                                 np.concatenate([omega, velocity]),
                                                 self._frame_E, self._params)
        if result.status != DifferentialInverseKinematicsStatus.kSolutionFound \
                or result.joint_velocities is None:
            return q.copy(), np.zeros(7), False
        v = np.asarray(result.joint_velocities).ravel()
        lower, upper = self._params.get_joint_position_limits()
        return np.clip(q + self._dt * v, lower, upper), v, True

    def placement_error(self, q, p_target, m_target):
        """(position error (m), axis error (rad)) of the EPM at joint positions q."""
        self._plant.SetPositions(self._context, q)
        X_WE = self._plant.CalcRelativeTransform(self._context, self._plant.world_frame(),
                                                 self._frame_E)
        axis = float(np.arccos(np.clip(X_WE.rotation().col(2) @ m_target, -1.0, 1.0)))
        return float(np.linalg.norm(X_WE.translation() - p_target)), axis

    def _update(self, context, discrete_state):
        values = context.get_discrete_state(self._state).value().copy()
        q = values[:7]
        command = np.asarray(self._command_port.Eval(context), dtype=float)
        norm = np.linalg.norm(command[3:]) if np.all(np.isfinite(command)) else 0.0
        if norm > 1e-9:
            values[14:20] = command
        else:
            values[26] += 1.0
        if not np.all(np.isfinite(values[14:20])):
            values[7:14] = 0.0  # nothing valid commanded yet: hold
            discrete_state.set_value(self._state, values)
            return EventStatus.Succeeded()
        p, m, raised, pulled = self._guard.apply(values[14:17], values[17:20])
        q_next, v, solved = self.place(q, p, m)
        position_error, axis_error = self.placement_error(q_next, p, m)
        values[:7], values[7:14] = q_next, v
        values[20], values[21] = float(raised), float(pulled)
        values[22] = float(position_error > self._config.unreachable_tolerance)
        values[23], values[24] = position_error, axis_error
        values[25] += 0.0 if solved else 1.0
        discrete_state.set_value(self._state, values)
        return EventStatus.Succeeded()


def ik_parameters(arm_plant, config: ArmConfig, dt: float, posture):
    """Drake's DifferentialInverseKinematicsParameters for the arm: joint limits (with the
    margin), scaled velocity limits, the posture's centering in the null space, and the
    roll about the magnet's axis (E's z) left free."""
    params = DifferentialInverseKinematicsParameters(arm_plant.num_positions(),
                                                     arm_plant.num_velocities())
    params.set_time_step(dt)
    margin = np.radians(config.limit_margin_deg)
    params.set_joint_position_limits((arm_plant.GetPositionLowerLimits() + margin,
                                      arm_plant.GetPositionUpperLimits() - margin))
    v_max = config.velocity_scale * arm_plant.GetVelocityUpperLimits()
    params.set_joint_velocity_limits((-v_max, v_max))
    params.set_nominal_joint_position(np.asarray(posture, dtype=float))
    params.set_joint_centering_gain(config.centering_gain * np.eye(7))
    params.set_end_effector_velocity_flag([True, True, False, True, True, True])
    return params


def solve_posture(controller: EpmArmController, q_start, p_target, m_target,
                  iterations: int = 2000, tolerance: float = 1e-6):
    """Joint positions that place the EPM at (p_target, m_target), by iterating the
    controller's own steps (offline, at build time) from q_start and from q_start with the
    flange turned (joint 7) by -145, -70, 70 and 145 degrees: the moment's heading is mostly
    joint 7's business, and its limits can trap a single start. Returns the best
    (q, position error, axis error)."""
    p, m, _, _ = controller._guard.apply(p_target, m_target)
    best = None
    for turn in (0.0, -2.5, -1.2, 1.2, 2.5):
        q = np.asarray(q_start, dtype=float).copy()
        q[6] += turn
        for _ in range(iterations):
            q, _, _ = controller.place(q, p, m)
            position_error, axis_error = controller.placement_error(q, p, m)
            if position_error < tolerance and axis_error < tolerance:
                break
        if best is None or position_error + axis_error < best[1] + best[2]:
            best = (q, position_error, axis_error)
        if position_error < tolerance and axis_error < tolerance:
            break
    return best


class MagnetPose(LeafSystem):
    """[p_WM (3), m_hat_W (3)]: a magnet body's centre and moment direction, from the
    plant's body poses (the moment along the body's `axis_B`)."""

    def __init__(self, plant, body, axis_B=(0.0, 0.0, 1.0)):
        super().__init__()
        self._index = int(body.index())
        self._axis_B = np.asarray(axis_B, dtype=float)
        self._poses = self.DeclareAbstractInputPort(
            "body_poses", AbstractValue.Make([RigidTransform()] * plant.num_bodies()))
        self.DeclareVectorOutputPort("pose", 6, self._calc)

    def _calc(self, context, output):
        X_WB = self._poses.Eval(context)[self._index]
        output.SetFromVector(np.concatenate([X_WB.translation(),
                                             X_WB.rotation().matrix() @ self._axis_B]))


class CommandMarker(LeafSystem):
    """Shows an EPM pose command in Meshcat: a translucent copy of the magnet (moment along
    its axis) at [p_WE, m_hat_W], published every `period` (and into a recording)."""

    def __init__(self, meshcat, geometry, period: float, path: str = "/epm_command"):
        super().__init__()
        from pydrake.geometry import Cylinder, Rgba, Sphere
        self._meshcat = meshcat
        self._path = path
        dims = geometry.dimensions
        shape = (Sphere(0.5 * dims[0]) if geometry.shape == "sphere" else
                 Cylinder(0.5 * dims[0], dims[1]) if geometry.shape == "cylinder" else
                 Cylinder(0.5 * float(np.hypot(dims[0], dims[1])), dims[2]))
        meshcat.SetObject(path, shape, Rgba(0.2, 0.6, 1.0, 0.3))
        self._command = self.DeclareVectorInputPort("epm_command", 6)
        self.DeclarePeriodicPublishEvent(period, 0.0, self._publish)

    def _publish(self, context):
        command = self._command.Eval(context)
        if not np.all(np.isfinite(command)) or np.linalg.norm(command[3:]) < 1e-9:
            return EventStatus.DidNothing()
        R = RotationMatrix.MakeFromOneVector(command[3:], 2)
        self._meshcat.SetTransform(self._path, RigidTransform(R, command[:3]),
                                   context.get_time())
        return EventStatus.Succeeded()
