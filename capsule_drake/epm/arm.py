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
import math

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.inverse_kinematics import (
    DifferentialInverseKinematicsParameters,
    DifferentialInverseKinematicsStatus,
    DoDifferentialInverseKinematics,
)
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem

from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import PdControllerGains
from pydrake.systems.primitives import TrajectorySource

from capsule_drake.epm.guard import EpmGuard
from capsule_drake.epm.poses import (extent_turn_slope, magnet_vertical_half_extent,
                                    pose_trajectory, vertical_half_extents)
from capsule_drake.epm.shaping import SAMPLE_TURN, MotionLimits, turn_toward_many
from capsule_drake.models import configure_parser, model_url
from capsule_drake.schema import ScenarioError, need_range

ARM_JOINTS = tuple(f"arm_joint_{i}" for i in range(1, 8))
ARM_BASE = "arm_link_0"
# Shoulder (joint 2) height above the base, from the model (m).
SHOULDER_HEIGHT = 0.36


@dataclasses.dataclass
class Arm:
    """The EPM on the 7-DoF arm (models/epm_arm.sdf) beside the table, placed by its
    controller (guard, differential IK) through the joints' PD servos. All fields default."""

    # Pose of the arm's base in the world (m, deg): beside the patient table (top at z = 0,
    # origin under the umbilicus, +y toward the head), facing the patient.
    base_xyz: list[float] = dataclasses.field(default_factory=lambda: [0.62, 0.0, 0.0])
    base_yaw_deg: float = 180.0
    # Joint servo gains (N m/rad, N m s/rad), per joint; the servos are the plant's implicit
    # PD actuators (an ideal torque-controlled arm with gravity compensation: the arm's own
    # weight is not simulated, the magnet's force on it is). Stiff enough that the largest
    # pull of the magnets (21.4 N at the default clearance) bends the arm by less than the
    # clearance's 2 mm tolerance (0.075 mm/N at the start posture); damped 2x the halved
    # gains' damping (ratios ~1.06 for ~0.75): at ~0.75 a joint stopped at its speed limit
    # rang the magnet +-3.5 mm (teleoperation, population patient 1001, 132 s).
    joint_stiffness: list[float] = dataclasses.field(
        default_factory=lambda: [16000.0, 16000.0, 10000.0, 10000.0, 4000.0, 2000.0, 1000.0])
    joint_damping: list[float] = dataclasses.field(
        default_factory=lambda: [600.0, 600.0, 300.0, 300.0, 80.0, 40.0, 16.0])
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
    # How fast the controller changes the magnet's velocity (m/s^2) and its turn rate
    # (rad/s^2). A joint servo lags a step in its velocity by ~w / (e wn): a stop from a
    # turn at the joints' speed limit would swing the magnet ~3 mm (measured), past the
    # clearance's 2 mm tolerance; a bounded change keeps the servos' lag well under it.
    max_acceleration: float = 1.0
    max_turn_acceleration: float = 4.0
    # Deceleration a joint is allowed toward its position limit (rad/s^2): it slows from
    # sqrt(2 a d) at a distance d from the limit (with its margin) instead of stopping there
    # within a period.
    joint_braking: float = 5.0
    # Largest change of a joint's commanded velocity (rad/s^2). The differential IK's
    # joint velocities jump when its active constraints switch (a joint reaching its speed
    # limit, a braking bound), even while the magnet's twist changes gradually; the servos
    # ring from a jump (+-3.5 mm at the magnet, teleoperation, population patient 1001,
    # 132 s). The step's joint velocities go from the last ones toward the IK's by at most
    # this times the period, all joints by the same share (the magnet's twist blends from
    # the last toward the new). Twice joint_braking, so the braking is followed.
    joint_acceleration: float = 10.0
    # Descent toward the skin: at most approach_speed (m/s) plus the height above the
    # clearance floor over approach_time (s), so the magnet arrives at the floor slowly.
    approach_speed: float = 0.005
    approach_time: float = 0.1
    # Largest distance from the shoulder to the magnet's centre the guard lets through (m).
    reach: float = 0.9
    # A command whose placement misses by more than this is reported unreachable (m).
    unreachable_tolerance: float = 0.002


def check_arm_config(config: Arm) -> None:
    """Raises ValueError naming the first impossible field."""
    if len(config.base_xyz) != 3:
        raise ValueError("epm.mount.base_xyz must have 3 values")
    for name in ("joint_stiffness", "joint_damping"):
        values = getattr(config, name)
        if len(values) != 7 or min(values) < 0.0:
            raise ValueError(f"epm.mount.{name} must be 7 values >= 0")
    if config.posture_deg and len(config.posture_deg) != 7:
        raise ValueError("epm.mount.posture_deg must be empty or 7 values")
    if not config.control_period > 0.0:
        raise ValueError("epm.mount.control_period must be > 0")
    if not 0.0 < config.velocity_scale <= 1.0:
        raise ValueError("epm.mount.velocity_scale must be in (0, 1]")
    if not config.limit_margin_deg >= 0.0 or not config.centering_gain >= 0.0:
        raise ValueError("epm.mount.limit_margin_deg and centering_gain must be >= 0")
    if not config.approach_speed > 0.0 or not config.approach_time > 0.0:
        raise ValueError("epm.mount.approach_speed and approach_time must be > 0")
    if not config.max_speed > 0.0 or not config.max_turn_rate > 0.0:
        raise ValueError("epm.mount.max_speed and max_turn_rate must be > 0")
    if not config.max_acceleration > 0.0 or not config.max_turn_acceleration > 0.0 \
            or not config.joint_braking > 0.0 or not config.joint_acceleration > 0.0:
        raise ValueError("epm.mount.max_acceleration, max_turn_acceleration, joint_braking "
                         "and joint_acceleration must be > 0")
    if not config.reach > 0.0 or not config.unreachable_tolerance > 0.0:
        raise ValueError("epm.mount.reach and unreachable_tolerance must be > 0")
    # Beyond the signs: what the arm (models/epm_arm.sdf, ~0.9 m from shoulder to flange)
    # and its controller can mean. A margin past the joints' ranges leaves no range at all
    # (Drake asserts), a period under 0.1 ms only adds events.
    need_range(config.base_xyz, "epm.mount.base_xyz", "[-2, 2]", "m",
               "beside the patient table")
    need_range(config.base_yaw_deg, "epm.mount.base_yaw_deg", "[-360, 360]", "deg")
    need_range(config.joint_stiffness, "epm.mount.joint_stiffness", "(0, 1e6]", "N m/rad",
               "a joint without stiffness does not hold the magnet")
    need_range(config.joint_damping, "epm.mount.joint_damping", "[0, 1e5]", "N m s/rad")
    need_range(config.control_period, "epm.mount.control_period", "[0.0001, 0.1]", "s")
    need_range(config.velocity_scale, "epm.mount.velocity_scale", "[0.01, 1]", "",
               "of the datasheet joint speeds")
    need_range(config.limit_margin_deg, "epm.mount.limit_margin_deg", "[0, 30]", "deg",
               "kept inside each joint's range; wider, some joints have none left")
    need_range(config.centering_gain, "epm.mount.centering_gain", "[0, 100]", "1/s")
    if config.posture_deg:
        need_range(config.posture_deg, "epm.mount.posture_deg", "[-360, 360]", "deg")
    need_range(config.max_speed, "epm.mount.max_speed", "[0.001, 2]", "m/s")
    need_range(config.max_turn_rate, "epm.mount.max_turn_rate", "[0.001, 10]", "rad/s")
    need_range(config.max_acceleration, "epm.mount.max_acceleration", "[0.001, 20]", "m/s^2")
    need_range(config.max_turn_acceleration, "epm.mount.max_turn_acceleration", "[0.001, 100]",
               "rad/s^2")
    need_range(config.joint_braking, "epm.mount.joint_braking", "[0.01, 100]", "rad/s^2")
    need_range(config.joint_acceleration, "epm.mount.joint_acceleration", "[0.01, 1000]",
               "rad/s^2")
    need_range(config.approach_speed, "epm.mount.approach_speed", "(0, 1]", "m/s")
    need_range(config.approach_time, "epm.mount.approach_time", "(0, 10]", "s")
    need_range(config.reach, "epm.mount.reach", "[0.1, 1.5]", "m",
               "the arm reaches ~0.9 m from its shoulder")
    need_range(config.unreachable_tolerance, "epm.mount.unreachable_tolerance", "(0, 0.1]", "m")


def arm_base_pose(config: Arm) -> RigidTransform:
    return RigidTransform(RotationMatrix.MakeZRotation(np.radians(config.base_yaw_deg)),
                          np.asarray(config.base_xyz, dtype=float))


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


def turn_vector(a, b, across) -> np.ndarray:
    """The rotation vector of the smallest turn taking unit axis a onto unit axis b; for
    opposite axes, a half turn about `across` (a unit vector across a)."""
    turn = np.cross(a, b)
    sin = np.linalg.norm(turn)
    angle = np.arctan2(sin, float(np.dot(a, b)))
    if sin > 1e-12:
        return turn / sin * angle
    if angle > 1.0:
        return np.asarray(across, dtype=float) * angle
    return np.zeros(3)


def pose_error(X_WE: RigidTransform, p_target, m_target) -> tuple[float, float]:
    """(position error (m), axis error (rad)) of the magnet at X_WE from a target."""
    axis = float(np.arccos(np.clip(X_WE.rotation().col(2) @ m_target, -1.0, 1.0)))
    return float(np.linalg.norm(X_WE.translation() - p_target)), axis


def clip_norm(x: np.ndarray, limit: float) -> np.ndarray:
    norm = np.linalg.norm(x)
    return x * (limit / norm) if norm > limit else x


def approach(gap: np.ndarray, acceleration: float, dt: float) -> np.ndarray:
    """The velocity toward a gap from which a stop at `acceleration` lands on it:
    sqrt(2 a |gap|), and no faster than closing it in one period dt."""
    distance = np.linalg.norm(gap)
    if distance < 1e-15:
        return np.zeros_like(gap)
    return gap / distance * min(distance / dt, math.sqrt(2.0 * acceleration * distance))


def blend(v_last: np.ndarray, v_new: np.ndarray, largest_change: float) -> np.ndarray:
    """From v_last toward v_new, every component by the same share, so that none changes
    by more than largest_change (the joints keep their coordination: the twist they give
    lies between the last one and the new one)."""
    change = np.max(np.abs(v_new - v_last))
    if change <= largest_change:
        return v_new
    return v_last + (largest_change / change) * (v_new - v_last)


# The controller's state: the joint command at the end of the current step and its
# velocity, the command at the step's start and the step's time (the servos' ramp between
# them), the last good EPM command, the status (see EpmArmController), the last guarded
# target [p, m_hat] and the magnet's last twist [w, v].
_Q, _V, _Q_START, _STEP_TIME = slice(0, 7), slice(7, 14), slice(14, 21), 21
_COMMAND, _STATUS, _TARGET, _TWIST = slice(22, 28), slice(28, 35), slice(35, 41), slice(41, 47)
_STATE_SIZE = 47


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
    error (rad), IK failures so far, non-finite commands so far]. In a station the EPM's
    guard (epm/guard.py) comes first: it raises the command and holds on a non-finite one
    itself (counted on epm.guard_counts), so the raised flag is 1 only after a pull within
    reach (onto a higher floor) and no non-finite command arrives.

    Args:
        arm_plant: a MultibodyPlant holding only the arm (base welded at the station's
            pose) and its EPM, finalised: the controller's kinematic model.
        config: Arm.
        guard: an EpmGuard.
        q0: initial joint command (7), e.g. `solve_posture`'s result.
    """

    def __init__(self, arm_plant, config: Arm, guard: EpmGuard, q0):
        super().__init__()
        check_arm_config(config)
        self._plant = arm_plant
        self._context = arm_plant.CreateDefaultContext()
        self._frame_E = arm_plant.GetBodyByName("epm").body_frame()
        self._config = config
        self._guard = guard
        self._dt = config.control_period
        self._params = ik_parameters(arm_plant, config, self._dt, q0)
        self._v_max = self._params.get_joint_velocity_limits()[1].copy()
        # The time (s) to turn a descent as fast as the floor falls under the turning magnet
        # into a climb as fast as it rises (its extent changes by at most its half diagonal
        # a radian of turn), at max_acceleration.
        self.turn_lookahead = (2.0 * extent_turn_slope(guard.geometry) * config.max_turn_rate
                               / config.max_acceleration)
        self._command_port = self.DeclareVectorInputPort("epm_command", 6)
        self._state_port = self.DeclareVectorInputPort("arm_state", 14)
        initial = np.zeros(_STATE_SIZE)
        initial[_Q] = initial[_Q_START] = q0
        initial[_COMMAND] = initial[_TARGET] = np.nan
        self._state = self.DeclareDiscreteState(BasicVector(initial))
        self.DeclareVectorOutputPort("arm_desired_state", 14, self._desired_state,
                                     {self.xd_ticket(), self.time_ticket()})
        self.DeclareVectorOutputPort(
            "status", 7,
            lambda context, out: out.SetFromVector(
                context.get_discrete_state(self._state).value()[_STATUS]),
            {self.xd_ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(self._dt, 0.0, self._update)

    def place(self, q: np.ndarray, p_target, m_target, previous=None):
        """One controller step from joint command q toward the (guarded) target, through
        the differential IK. Returns (q_next, v, solved).

        Offline (`previous` None: `solve_posture`), the twist closes the gap in one step,
        capped at the config's speeds (so the QP can follow its direction). In the loop,
        `previous` = (p, m_hat of the last target, the last step's twist [w, v], the last
        step's joint velocities): the twist is the target's own (its change over a period)
        plus an approach to the remaining gap that can stop within max_acceleration (speed
        sqrt(2 a gap)), capped at the speeds, and it changes from the last step's by at most
        the accelerations times the period; the IK's joint velocities are then reached from
        the last ones at most joint_acceleration times the period a step (`blend`). So the
        joint velocities the servos follow change gradually, and the magnet follows a
        moving target without lag."""
        X_WE = self._pose(q)
        axis = X_WE.rotation().col(2)
        gap_turn = turn_vector(axis, m_target, X_WE.rotation().col(0))
        # The target's height clears the skin for the target's moment; while the magnet
        # still turns toward it, it must clear it as it is turned now and as it will be on
        # the rest of its turn (a tilted magnet reaches lower): `lift` above the floor of
        # its present moment.
        lift = self.turn_lift(axis, m_target, None if previous is None else previous[2][:3])
        goal = np.array(p_target, dtype=float)
        goal[2] = max(goal[2], self._guard.lowest_centre_height(goal[0], goal[1], axis) + lift)
        gap = goal - X_WE.translation()
        c, dt = self._config, self._dt
        if previous is None:
            omega, velocity = gap_turn / dt, gap / dt
        else:
            p_last, m_last, twist, _ = previous
            omega = approach(gap_turn, c.max_turn_acceleration, dt)
            velocity = approach(gap, c.max_acceleration, dt)
            if np.all(np.isfinite(p_last)):
                omega = omega + turn_vector(m_last, m_target, X_WE.rotation().col(0)) / dt
                velocity = velocity + (np.asarray(p_target) - p_last) / dt
        omega = omega * min(1.0, c.max_turn_rate / max(np.linalg.norm(omega), 1e-12))
        velocity = velocity * min(1.0, c.max_speed / max(np.linalg.norm(velocity), 1e-12))
        if previous is not None:
            omega = twist[:3] + clip_norm(omega - twist[:3], c.max_turn_acceleration * dt)
            velocity = twist[3:] + clip_norm(velocity - twist[3:], c.max_acceleration * dt)
        # Slow down toward the skin: the servos would carry a fast descent past the floor,
        # the floor of the turn ahead too. Below the floor of its present moment (the floor
        # under a turning magnet rises), climb back within a period, whatever the
        # accelerations: the servos' lag on a climb is away from the skin.
        p = X_WE.translation()
        height = p[2] - self._guard.lowest_centre_height(p[0], p[1], axis)
        descent = c.approach_speed + max(height - lift, 0.0) / c.approach_time
        velocity[2] = min(max(velocity[2], -descent, -height / dt), c.max_speed)
        lower, upper = self._params.get_joint_position_limits()
        if previous is not None:
            # Toward a joint's limit no faster than it can stop at joint_braking on the way:
            # the QP's own bound stops it within a period, a jolt the servos ring from.
            brake = 2.0 * c.joint_braking
            self._params.set_joint_velocity_limits((
                np.maximum(-self._v_max, -np.sqrt(brake * np.maximum(q - lower, 0.0))),
                np.minimum(self._v_max, np.sqrt(brake * np.maximum(upper - q, 0.0)))))
        else:
            self._params.set_joint_velocity_limits((-self._v_max, self._v_max))
        result = DoDifferentialInverseKinematics(self._plant, self._context,
                                                 np.concatenate([omega, velocity]),
                                                 self._frame_E, self._params)
        if result.status != DifferentialInverseKinematicsStatus.kSolutionFound \
                or result.joint_velocities is None:
            return q.copy(), np.zeros(7), False
        v = np.asarray(result.joint_velocities).ravel()
        if previous is not None:
            v = blend(previous[3], v, c.joint_acceleration * dt)
        return np.clip(q + dt * v, lower, upper), v, True

    def turn_lift(self, axis, m_target, omega=None) -> float:
        """How much higher (m) than its present moment's floor the magnet must be to clear
        the skin on the turn ahead: the moments from its axis to the target's, and those of
        its present turn (rotation rate `omega`, rad/s) carried on for `turn_lookahead`,
        the time the controller needs to turn a descent into a climb as fast as the floor
        rises under the turn. Without it a magnet turning through the horizontal (where a
        cylinder's vertical extent is least) follows the floor down and is still
        descending when the turn needs height again (teleoperation, population patient
        1006, 70.5 s: 2.2 mm inside the clearance)."""
        angle = float(np.arccos(np.clip(axis @ m_target, -1.0, 1.0)))
        axes = [turn_toward_many(axis, m_target,
                                 np.linspace(0.0, 1.0, 2 + int(angle / SAMPLE_TURN)))]
        rate = 0.0 if omega is None else float(np.linalg.norm(omega))
        if rate > 1e-9:   # the axis's turn (`twist`) is across it: a great circle
            ahead = rate * self.turn_lookahead
            phi = np.linspace(0.0, ahead, 2 + int(ahead / SAMPLE_TURN))[:, None]
            axes.append(axis * np.cos(phi) + np.cross(omega / rate, axis) * np.sin(phi))
        extents = vertical_half_extents(np.concatenate(axes), self._guard.geometry)
        return max(0.0, float(extents.max())
                   - magnet_vertical_half_extent(axis, self._guard.geometry))

    def _pose(self, q) -> RigidTransform:
        self._plant.SetPositions(self._context, q)
        return self._plant.CalcRelativeTransform(self._context, self._plant.world_frame(),
                                                 self._frame_E)

    def twist(self, X_before: RigidTransform, X_after: RigidTransform) -> np.ndarray:
        """[w, v] of the magnet from pose X_before to X_after over one period (the turn of
        its moment's axis; the roll about it is free)."""
        turn = turn_vector(X_before.rotation().col(2), X_after.rotation().col(2),
                           X_before.rotation().col(0))
        return np.concatenate([turn, X_after.translation() - X_before.translation()]) / self._dt

    def placement_error(self, q, p_target, m_target):
        """(position error (m), axis error (rad)) of the EPM at joint positions q."""
        return pose_error(self._pose(q), p_target, m_target)

    def _desired_state(self, context, out):
        """The joint command between controller steps: from the last step's start toward
        its end, at its velocity (the servos follow a ramp, as an arm's interpolator gives
        them, not a staircase of 5 ms holds that would shake the magnet)."""
        values = context.get_discrete_state(self._state).value()
        share = np.clip((context.get_time() - values[_STEP_TIME]) / self._dt, 0.0, 1.0)
        q = values[_Q_START] + share * (values[_Q] - values[_Q_START])
        out.SetFromVector(np.concatenate([q, values[_V]]))

    def _update(self, context, discrete_state):
        values = context.get_discrete_state(self._state).value().copy()
        q = values[_Q].copy()
        values[_Q_START], values[_STEP_TIME] = q, context.get_time()
        command = np.asarray(self._command_port.Eval(context), dtype=float)
        norm = np.linalg.norm(command[3:]) if np.all(np.isfinite(command)) else 0.0
        status = values[_STATUS]
        if norm > 1e-9:
            values[_COMMAND] = command
        else:
            status[6] += 1.0
        if not np.all(np.isfinite(values[_COMMAND])):
            values[_V] = values[_TWIST] = 0.0  # nothing valid commanded yet: hold
            values[_STATUS] = status
            discrete_state.set_value(self._state, values)
            return EventStatus.Succeeded()
        p, m, raised, pulled = self._guard.apply(values[_COMMAND][:3], values[_COMMAND][3:])
        last = values[_TARGET]
        q_next, v, solved = self.place(q, p, m,
                                       (last[:3], last[3:], values[_TWIST], values[_V]))
        X_before, X_after = self._pose(q), self._pose(q_next)
        position_error, axis_error = pose_error(X_after, p, m)
        values[_TARGET] = np.concatenate([p, m])
        values[_TWIST] = self.twist(X_before, X_after)
        values[_Q], values[_V] = q_next, v
        status[0], status[1] = float(raised), float(pulled)
        status[2] = float(position_error > self._config.unreachable_tolerance)
        status[3], status[4] = position_error, axis_error
        status[5] += 0.0 if solved else 1.0
        values[_STATUS] = status
        discrete_state.set_value(self._state, values)
        return EventStatus.Succeeded()


def ik_parameters(arm_plant, config: Arm, dt: float, posture):
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


# Where the arm's start-posture solve begins (rad): shoulder forward, elbow bent, flange down.
ARM_START_GUESS = (0.0, 0.6, 0.0, -1.2, 0.0, 1.2, 0.0)


class ArmMount:
    """The arm in a station: the EPM command goes through the EpmArmController (guard,
    differential IK) to the joints' PD servos."""

    model_name = "epm_arm"

    def __init__(self, config: Arm):
        self.config = config

    def add_models(self, plant, parser):
        """Before Finalize: the arm welded at its base pose, its servo gains."""
        self.instance, = parser.AddModels(url=model_url("epm_arm.sdf"))
        plant.WeldFrames(plant.world_frame(), plant.GetFrameByName(ARM_BASE, self.instance),
                         arm_base_pose(self.config))
        # A torque-controlled arm compensates its own weight; the magnet's pull it must bear.
        plant.set_gravity_enabled(self.instance, False)
        for name, p, d in zip(ARM_JOINTS, self.config.joint_stiffness,
                              self.config.joint_damping):
            plant.GetJointActuatorByName(name, self.instance).set_controller_gains(
                PdControllerGains(p=p, d=d))
        return self.instance

    def motion_limits(self) -> MotionLimits:
        """The arm's controller moves the magnet toward its command at up to max_speed and
        max_acceleration and turns it at up to max_turn_rate: the path it is given goes no
        faster, so that it follows that path, not a line of its own."""
        c = self.config
        return MotionLimits(c.max_speed, c.max_acceleration, c.max_turn_rate)

    def controller_plant(self):
        """The controller's own model: the arm alone, welded at the same pose."""
        arm = MultibodyPlant(0.0)
        instance, = configure_parser(Parser(arm)).AddModels(url=model_url("epm_arm.sdf"))
        arm.WeldFrames(arm.world_frame(), arm.GetFrameByName(ARM_BASE, instance),
                       arm_base_pose(self.config))
        arm.Finalize()
        return arm

    def connect(self, builder, parts, q0):
        """After Finalize (`q0`, the stage joints of the EPM's start, is not used: the
        arm reaches the same pose): the controller and the arm's start posture (solved to reach the
        EPM's start pose, parts.epm.start_command); exports epm.state (arm [q, v]),
        epm.desired_state and epm.status (see EpmArmController)."""
        plant = parts.plant
        first = parts.epm.start_command
        shoulder = arm_base_pose(self.config).multiply([0.0, 0.0, SHOULDER_HEIGHT])
        epm = parts.epm
        guard = EpmGuard(parts.colon.abdomen, epm.magnet, epm.clearance, shoulder,
                         self.config.reach)
        arm = self.controller_plant()
        guess = (np.radians(self.config.posture_deg) if self.config.posture_deg
                 else np.array(ARM_START_GUESS))
        probe = EpmArmController(arm, self.config, guard, guess)
        q0, position_error, axis_error = solve_posture(probe, guess, first[:3], first[3:])
        if position_error > 1e-3 or axis_error > 1e-2:
            raise ScenarioError(
                f"scenario: epm.mount (the arm) cannot reach the EPM's first pose (misses by "
                f"{position_error * 1000:.1f} mm, {np.degrees(axis_error):.1f} deg): move "
                "epm.mount.base_xyz closer or give epm.mount.posture_deg")
        posture = np.radians(self.config.posture_deg) if self.config.posture_deg else q0
        self.controller = builder.AddNamedSystem("epm_arm_controller", EpmArmController(
            arm, dataclasses.replace(self.config, posture_deg=list(np.degrees(posture))),
            guard, q0))
        for name, value in zip(ARM_JOINTS, q0):
            plant.GetJointByName(name, self.instance).set_default_angle(value)
        builder.Connect(plant.get_state_output_port(self.instance),
                        self.controller.GetInputPort("arm_state"))
        builder.Connect(self.controller.GetOutputPort("arm_desired_state"),
                        plant.get_desired_state_input_port(self.instance))
        parts.export(plant.get_state_output_port(self.instance), "epm.state")
        parts.export(self.controller.GetOutputPort("arm_desired_state"), "epm.desired_state")
        parts.export(self.controller.GetOutputPort("status"), "epm.status")

    def follow(self, builder, parts, trajectory):
        """The controller follows the poses of the stage trajectory (`epm_path`); exports
        them as epm.command. Returns the path's system."""
        path = builder.AddNamedSystem("epm_path", TrajectorySource(pose_trajectory(trajectory)))
        builder.Connect(path.get_output_port(), self.controller.GetInputPort("epm_command"))
        parts.export(path.get_output_port(), "epm.command")
        return path

    def carrier_input(self, builder, parts):
        """The controller's pose command input [p_WE, m_hat_W], from the EPM's guard
        (drivers connect to `EpmParts.command_input`)."""
        return self.controller.GetInputPort("epm_command")
