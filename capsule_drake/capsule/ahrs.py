"""Attitude from gyroscope and accelerometer: Mahony's explicit complementary filter.

Mahony, Hamel and Pflimlin, "Nonlinear complementary filters on the special orthogonal
group", IEEE Trans. Automatic Control 53(5), 2008, section V ("explicit complementary filter
with bias correction"), with a single vector measurement: the accelerometer's direction,
which at rest (or at constant velocity) is the world's up direction expressed in the sensor
frame S. With R the estimate of R_WS and v_hat = R^T e_z the predicted up direction,

    omega_mes = v x v_hat                    (v = a / |a|, the measured up direction)
    b_dot     = -k_I omega_mes               (gyro bias estimate)
    R_dot     = R [omega_y - b + k_P omega_mes]_x

integrated once per IMU sample with the exact exponential of a constant rate over the period.
The correction is skipped (gyro integration only) while |a| differs from g by more than a
set fraction: then the accelerometer reads motion, not the vertical.

Observability: the accelerometer fixes roll and pitch (tilt) only. Heading (yaw about the
world vertical) is never corrected: it drifts as the integral of the gyro error about the
vertical. At rest that error is the component of the gyro bias along the up direction (the
filter cannot estimate it, since a rotation about the vertical leaves v unchanged), so yaw
drifts at that rate (0.2 deg/s of turn-on bias is 12 deg per minute) plus a random walk from
the white rate noise. When the capsule turns so that the up direction moves in the sensor
frame, every bias component becomes observable (Mahony et al. 2008, Theorem 5.1, persistent
excitation) and the yaw drift slows to the residual bias error. A magnetometer would fix
heading in open space, but next to the external permanent magnet the earth's field is
swamped, so this filter deliberately has none.
"""


import copy
import dataclasses
import math

import numpy as np
from pydrake.math import RotationMatrix
from pydrake.systems.framework import LeafSystem

from capsule_drake.blocks import block, checked, need
from capsule_drake.capsule.imu import STANDARD_GRAVITY
from capsule_drake.schema import need_range


@dataclasses.dataclass
class AhrsConfig:
    """The Mahony filter's settings; YAML-loadable."""

    # Proportional gain (rad/s): the tilt correction's bandwidth. Larger follows the
    # accelerometer faster and lets more of its noise and of the capsule's own acceleration
    # through. U.
    kp: float = 1.0
    # Integral gain (rad/s^2) of the gyro-bias estimate; kp^2 / 4 makes the linearised tilt
    # and bias loop critically damped (time constant 2 / kp = 2 s) for the bias components
    # across the vertical. While the capsule turns, the others converge more slowly (about
    # 20 s at 20 deg/s about an axis 30 deg off the vertical, tests/test_ahrs.py). U.
    ki: float = 0.25
    # The accelerometer correction is skipped while ||a| - g| > accel_rejection * g
    # (capsule accelerating); 0 or less disables the check. U.
    accel_rejection: float = 0.1
    # Initial orientation of the capsule body in world (quaternion w, x, y, z). Empty: from
    # the first accelerometer sample, tilt only, with the heading of the smallest rotation
    # that takes the measured up direction to world +z.
    initial_q_WB: list[float] = dataclasses.field(default_factory=list)


def check_ahrs_config(config: AhrsConfig) -> None:
    """Raises ValueError naming the first impossible field (relative to the AHRS)."""
    need_range(config.kp, "kp", ">= 0", "rad/s", "a negative gain drives the estimate away")
    need_range(config.ki, "ki", ">= 0", "rad/s^2", "a negative gain drives the estimate away")
    q = config.initial_q_WB
    if len(q) not in (0, 4):
        raise ValueError("initial_q_WB must be empty (the true start) or a quaternion "
                         f"[w, x, y, z], got {q}")
    need_range(q, "initial_q_WB", "[-1.1, 1.1]")
    if q and not 0.9 <= math.sqrt(sum(c * c for c in q)) <= 1.1:
        raise ValueError(f"initial_q_WB must be a unit quaternion [w, x, y, z] (norm within "
                         f"10 % of 1; it is normalised), got {q}")


def _quat_multiply(p, q):
    """Hamilton product of wxyz quaternions (plain floats)."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw)


def _quat_normalize(q):
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def _quat_exp(rx, ry, rz):
    """Unit quaternion of the rotation vector (rx, ry, rz) (rad)."""
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-12:
        return _quat_normalize((1.0, 0.5 * rx, 0.5 * ry, 0.5 * rz))
    s = math.sin(0.5 * angle) / angle
    return (math.cos(0.5 * angle), s * rx, s * ry, s * rz)


def tilt_quaternion(accel) -> tuple:
    """q_WS (wxyz) of the smallest rotation that takes the measured up direction
    ``accel / |accel|`` (sensor frame) to world +z: roll and pitch from gravity, no heading."""
    ax, ay, az = (float(x) for x in accel)
    n = math.sqrt(ax * ax + ay * ay + az * az)
    if n == 0.0:
        raise ValueError("cannot initialise the attitude from a zero acceleration")
    vx, vy, vz = ax / n, ay / n, az / n
    # Rotation taking v to e_z: axis v x e_z = (vy, -vx, 0), cos = vz. The half-angle form
    # q = (1 + vz, v x e_z) / norm is exact and stable except at vz = -1 (upside down).
    if vz < -1.0 + 1e-12:
        return (0.0, 1.0, 0.0, 0.0)
    return _quat_normalize((1.0 + vz, vy, -vx, 0.0))


def mahony_update(q, bias, accel, gyro, dt, kp, ki, accel_rejection=0.0,
                  gravity=STANDARD_GRAVITY):
    """One step of the explicit complementary filter (module docstring).

    Args:
        q: estimate of q_WS (wxyz, 4 floats).
        bias: gyro-bias estimate (rad/s, 3 floats).
        accel: measured specific force in S (m/s^2); gyro: measured rate in S (rad/s).
        dt: sample period (s).

    Returns:
        (q, bias) after the step, as tuples of floats.
    """
    qw, qx, qy, qz = q
    bx, by, bz = bias
    ex = ey = ez = 0.0
    ax, ay, az = (float(x) for x in accel)
    n = math.sqrt(ax * ax + ay * ay + az * az)
    if n > 0.0 and (accel_rejection <= 0.0 or abs(n - gravity) <= accel_rejection * gravity):
        vx, vy, vz = ax / n, ay / n, az / n
        # v_hat = R^T e_z: third row of R(q).
        hx = 2.0 * (qx * qz - qw * qy)
        hy = 2.0 * (qy * qz + qw * qx)
        hz = qw * qw - qx * qx - qy * qy + qz * qz
        ex, ey, ez = vy * hz - vz * hy, vz * hx - vx * hz, vx * hy - vy * hx
        bx, by, bz = bx - ki * ex * dt, by - ki * ey * dt, bz - ki * ez * dt
    wx, wy, wz = (float(x) for x in gyro)
    rate = (wx - bx + kp * ex, wy - by + kp * ey, wz - bz + kp * ez)
    q = _quat_normalize(_quat_multiply(q, _quat_exp(rate[0] * dt, rate[1] * dt, rate[2] * dt)))
    return q, (bx, by, bz)


def tilt_and_heading_error(R_WB_estimate, R_WB_true):
    """(tilt, heading) errors (rad) of an attitude estimate.

    Tilt: the angle between the estimated and the true up direction in the body frame (roll
    and pitch error together). Heading: the angle of the remaining rotation about the world
    vertical, from the error rotation R_est R_true^T.
    """
    R_est = np.asarray(R_WB_estimate.matrix() if hasattr(R_WB_estimate, "matrix")
                       else R_WB_estimate)
    R_true = np.asarray(R_WB_true.matrix() if hasattr(R_WB_true, "matrix") else R_WB_true)
    up_est, up_true = R_est[2], R_true[2]
    tilt = math.atan2(np.linalg.norm(np.cross(up_est, up_true)), float(up_est @ up_true))
    R_err = R_est @ R_true.T
    heading = math.atan2(R_err[1, 0] - R_err[0, 1], R_err[0, 0] + R_err[1, 1])
    return tilt, heading


class MahonyAhrs(LeafSystem):
    """Attitude and heading reference: Mahony's complementary filter on gyro and accelerometer.

    Runs every ``1 / sample_rate`` s, half a period after the IMU samples, so it reads the
    sample the IMU has just taken. Each update applies ``mahony_update`` to the held sample
    k (taken at t_k): the output then estimates the orientation at t_{k+1}, half a period
    ahead of the update, so at any time it is at most half a period off. The first update
    with a nonzero accelerometer sample starts from ``config.initial_q_WB`` or from the
    accelerometer's tilt (``AhrsConfig``). Outputs are discrete state (sample-and-hold);
    before the first update the orientation is the identity and the bias zero.

    .. pydrake_system::

        name: MahonyAhrs
        input_ports:
        - accel
        - gyro
        output_ports:
        - q_WB
        - gyro_bias

    - ``accel`` (3, m/s^2): measured specific force in the IMU frame S (``Imu`` ``accel``).
    - ``gyro`` (3, rad/s): measured angular velocity in S (``Imu`` ``gyro``).
    - ``q_WB`` (4): estimated orientation of the body (capsule) frame in world, unit quaternion
      w, x, y, z (body-to-world: ``R_WB = RotationMatrix(Quaternion(q_WB))``).
    - ``gyro_bias`` (3, rad/s): estimated gyro bias, in S.

    Args:
        sample_rate: the IMU's sample rate (Hz).
        config: an ``AhrsConfig`` (copied).
        R_BS: the IMU frame's orientation in the body (``ImuConfig.X_BS().rotation()``);
            default identity.
        gravity: magnitude of gravity (m/s^2) for the acceleration check.
    """

    def __init__(self, sample_rate: float, config: AhrsConfig | None = None, R_BS=None,
                 gravity: float = STANDARD_GRAVITY):
        LeafSystem.__init__(self)
        self._config = copy.deepcopy(config) if config is not None else AhrsConfig()
        if sample_rate <= 0:
            raise ValueError(f"sample_rate must be positive, got {sample_rate}")
        self._period = 1.0 / sample_rate
        self._gravity = float(gravity)
        R_BS = RotationMatrix() if R_BS is None else RotationMatrix(R_BS)
        q_BS = R_BS.ToQuaternion()
        self._q_BS = (q_BS.w(), q_BS.x(), q_BS.y(), q_BS.z())
        self._q_SB = (q_BS.w(), -q_BS.x(), -q_BS.y(), -q_BS.z())
        self._q_WS0 = None
        if self._config.initial_q_WB:
            if len(self._config.initial_q_WB) != 4:
                raise ValueError("initial_q_WB must have 4 entries (w, x, y, z)")
            q_WB0 = _quat_normalize(tuple(float(x) for x in self._config.initial_q_WB))
            self._q_WS0 = _quat_multiply(q_WB0, self._q_BS)
        self._accel_port = self.DeclareVectorInputPort("accel", 3)
        self._gyro_port = self.DeclareVectorInputPort("gyro", 3)
        # q_WS is the filter's state; q_WB its output (q_WB = q_WS q_SB), held alongside.
        self._q_WS_state = self.DeclareDiscreteState(np.array([1.0, 0.0, 0.0, 0.0]))
        self._q_WB_state = self.DeclareDiscreteState(np.array([1.0, 0.0, 0.0, 0.0]))
        self._bias_state = self.DeclareDiscreteState(3)
        self._started = self.DeclareDiscreteState(1)
        self._q_WB_port = self.DeclareStateOutputPort("q_WB", self._q_WB_state)
        self._bias_port = self.DeclareStateOutputPort("gyro_bias", self._bias_state)
        self.DeclarePeriodicDiscreteUpdateEvent(self._period, 0.5 * self._period, self._update)

    def config(self) -> AhrsConfig:
        return copy.deepcopy(self._config)

    def get_accel_input_port(self):
        return self._accel_port

    def get_gyro_input_port(self):
        return self._gyro_port

    def get_q_WB_output_port(self):
        return self._q_WB_port

    def get_gyro_bias_output_port(self):
        return self._bias_port

    def _update(self, context, discrete_state):
        accel = self._accel_port.Eval(context)
        if context.get_discrete_state(self._started).get_value()[0] == 0.0:
            if not np.any(accel):
                return  # the IMU has not sampled yet
            # The orientation at this sample; the step below carries it to the next one.
            q = self._q_WS0 if self._q_WS0 is not None else tilt_quaternion(accel)
            bias = (0.0, 0.0, 0.0)
            discrete_state.get_mutable_vector(self._started).SetAtIndex(0, 1.0)
        else:
            q = tuple(context.get_discrete_state(self._q_WS_state).get_value())
            bias = tuple(context.get_discrete_state(self._bias_state).get_value())
        c = self._config
        q, bias = mahony_update(q, bias, accel, self._gyro_port.Eval(context), self._period,
                                c.kp, c.ki, c.accel_rejection, self._gravity)
        discrete_state.get_mutable_vector(self._q_WS_state).SetFromVector(q)
        discrete_state.get_mutable_vector(self._q_WB_state).SetFromVector(
            _quat_multiply(q, self._q_SB))
        discrete_state.get_mutable_vector(self._bias_state).SetFromVector(bias)


def check_ahrs(config: AhrsConfig, scenario) -> None:
    checked("capsule.ahrs.", check_ahrs_config, config)
    need(scenario.capsule.imu is not None,
         "capsule.ahrs needs capsule.imu (set ahrs: null too, or give an imu)")


@block("capsule.ahrs", AhrsConfig, check=check_ahrs)
def add_ahrs(builder, parts, config: AhrsConfig):
    """`capsule.ahrs` on the IMU's samples (its check makes sure there is an IMU), starting
    from the capsule's true start attitude unless `initial_q_WB` is given; exports
    capsule.ahrs.q_WB and capsule.ahrs.gyro_bias."""
    imu = parts.shared("capsule.imu.config")
    if not config.initial_q_WB:
        q = parts.X_WB0.rotation().ToQuaternion()
        config = dataclasses.replace(config, initial_q_WB=[q.w(), q.x(), q.y(), q.z()])
    ahrs = builder.AddNamedSystem("capsule.ahrs", MahonyAhrs(
        imu.sample_rate, config, R_BS=imu.X_BS().rotation(),
        gravity=parts.gravity))
    builder.Connect(parts.output("capsule.imu.accel"), ahrs.get_accel_input_port())
    builder.Connect(parts.output("capsule.imu.gyro"), ahrs.get_gyro_input_port())
    parts.export(ahrs.get_q_WB_output_port(), "capsule.ahrs.q_WB")
    parts.export(ahrs.get_gyro_bias_output_port(), "capsule.ahrs.gyro_bias")
    return ahrs
