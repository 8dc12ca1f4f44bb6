"""Magnetic localisation: the capsule's 6-DoF pose from its Hall sensors, its IMU and the EPM.

The EPM's pose is known (the robot places it) and so is its field, from a model: here the
point dipole, while the simulation's magnets may be finite cylinders, so the estimator meets
the model error a real one does. The capsule's Hall sensors (capsule/magnetic_array.py)
read that field at several points around its magnet, in the capsule's frame; the IMU's
gyroscope turns the capsule's orientation from one sample to the next and its accelerometer
gives the direction of gravity while the capsule does not accelerate much.

Method: an error-state extended Kalman filter, iterated (Gauss-Newton) in its update, run
at the sensors' rate.
- State: the body origin's position p_WB, its orientation R_WB, the gyroscope's bias b
  (in the body frame) and the share d by which the IPM's field has changed since the
  sensors were calibrated (its temperature: each sensor then reads d times its calibrated
  self-field c_i on top of the EPM's field, a pattern of 3n numbers the filter knows).
  Error state [dp, dtheta, db, dd] (10), dtheta a rotation vector on the body side:
  R = R_hat Exp(dtheta).
- Predict: R <- R Exp((omega - b) dt) with the gyroscope's omega; p and b random walks.
- Update: every unsaturated sensor's field, h_i = R^T B(p + R p_BSi - p_E; m_E) + d c_i, and the
  accelerometer's specific force, h_a = R^T g_up (its noise grows with | |a| - g |, so a
  capsule being shaken trusts it less). The Jacobians are analytic (the dipole's field
  gradient is a closed form, checked against finite differences in the tests).
  Iterating the update re-linearises the field about the updated estimate: the field is
  far from linear over a prior of several millimetres (it falls off as 1/r^3).
- Observability: position from the field's strength and its change across the array;
  the orientation's tilt from gravity and the field; the heading from the field's
  direction, which is known in the world. Where the field is weak (the EPM far, or lost),
  the measurements stop informing and the covariance grows instead of the estimate
  running off; where the field is parallel to gravity (a vertical moment straight above)
  the heading about that axis is unobserved and held by the gyroscope, which the
  covariance also shows.

Why an iterated EKF rather than least squares on each sample (Di Natali et al., T-RO 2016):
each sample alone has 3n + 3 equations for 6 unknowns and is well posed with the default
four sensors, but the filter carries what it knew through moments when it is not (a
saturated sensor excluded, the field weak or vertical) and gives a covariance the follower
can read; iterating its update gives the least-squares solution with the prior as one more
term. The cost is one 10-state filter with 15 measurements iterated twice, ~0.4-0.5 ms an update
(benchmarks/bench_localization.py).
"""

import dataclasses

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.systems.framework import BasicVector, LeafSystem

from capsule_drake.physics.magnetics import MU0
from capsule_drake.blocks import block, checked, need
from capsule_drake.schema import need_range

_K = MU0 / (4.0 * np.pi)
# Size of the error state: position, orientation, gyroscope bias, self-field drift.
N = 10


@dataclasses.dataclass
class LocalizerConfig:
    """The pose estimator (module docstring). YAML-loadable; all fields default."""

    # Update period (s): the Hall sensors' sample period.
    period: float = 0.01
    # Iterations of the update (1: the plain EKF; a third changes nothing measurable).
    iterations: int = 2
    # Standard deviation of a field reading's error (T, per axis): what the estimator
    # assumes of the sensors, from their datasheet (noise, offset drift, gain residual).
    field_noise: float = 100e-6
    # The self-field's change since calibration: its prior (a share of it, 1 sigma) and
    # random walk (1/sqrt(s)).
    self_field_drift: float = 0.003
    self_field_drift_walk: float = 1e-5
    # The field model's error as a share of the field (per axis): the point dipole against
    # a finite magnet is 1-3 % off at 15-25 cm (sources.md s. 1). It is smooth: the
    # same at every sensor of the array (fully correlated between them), with a smaller
    # part that differs from sensor to sensor (model_error_local).
    model_error: float = 0.02
    model_error_local: float = 0.003
    # The accelerometer as a gravity reference: noise (m/s^2) plus this factor times how
    # far |a| is from g.
    accel_noise: float = 0.3
    accel_motion_factor: float = 3.0
    # Random walks of the state: position (m/sqrt(s)), orientation beyond the gyroscope's
    # noise (rad/sqrt(s)), gyroscope bias (rad/s/sqrt(s)). They also stand for the sensors'
    # errors that are constant over a run (gains, offsets) and the field model's, which a
    # filter that takes every sample as independent would average as if they were noise:
    # with smaller walks its covariance claims more than it knows (its NEES rises above
    # the state's dimension; tests/test_localization.py).
    position_walk: float = 0.015
    orientation_walk: float = 0.015
    gyro_bias_walk: float = 1e-4
    # A gyroscope sample within 1 % of its range (the IMU's `gyro_range`) counts as
    # saturated (a tumble): the orientation's uncertainty then grows by saturated_turn (rad
    # per update).
    saturated_turn: float = 0.2
    # The start's uncertainty: position (m), orientation (deg), gyroscope bias (deg/s).
    initial_position_sigma: float = 0.005
    initial_rotation_sigma_deg: float = 5.0
    initial_gyro_bias_sigma_deg: float = 0.3


def check_localizer_config(config: LocalizerConfig) -> None:
    """Raises ValueError naming the first impossible field."""
    need_range(config.period, "period", "[0.0001, 1]", "s")
    need_range(config.iterations, "iterations", "[1, 20]")
    need_range(config.field_noise, "field_noise", "(0, 1]", "T", "a standard deviation")
    for name in ("self_field_drift", "self_field_drift_walk", "model_error",
                 "model_error_local"):
        need_range(getattr(config, name), name, "[0, 1]", "", "a fraction")
    need_range(config.accel_noise, "accel_noise", "(0, 100]", "m/s^2")
    need_range(config.accel_motion_factor, "accel_motion_factor", "[0, 100]")
    need_range(config.position_walk, "position_walk", "(0, 10]", "m/sqrt(s)")
    need_range(config.saturated_turn, "saturated_turn", "[0, 3.2]", "rad")
    need_range(config.orientation_walk, "orientation_walk", "(0, 10]", "rad/sqrt(s)")
    need_range(config.gyro_bias_walk, "gyro_bias_walk", "[0, 1]", "rad/s/sqrt(s)")
    need_range(config.initial_position_sigma, "initial_position_sigma", "(0, 1]", "m")
    need_range(config.initial_rotation_sigma_deg, "initial_rotation_sigma_deg", "(0, 180]",
               "deg")
    need_range(config.initial_gyro_bias_sigma_deg, "initial_gyro_bias_sigma_deg", "[0, 100]",
               "deg/s")


def skew(v) -> np.ndarray:
    """[v]x: skew(v) @ w = v x w."""
    return _skews(np.reshape(v, (1, 3)))[0]


def _skews(v) -> np.ndarray:
    """[v_k]x for each row v_k of v (n x 3) -> (n x 3 x 3)."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def exp_so3(w) -> np.ndarray:
    """The rotation matrix of rotation vector w (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    W = skew(w)
    if angle < 1e-8:
        return np.eye(3) + W + 0.5 * W @ W
    return (np.eye(3) + (np.sin(angle) / angle) * W
            + ((1.0 - np.cos(angle)) / angle**2) * W @ W)


def log_so3(R) -> np.ndarray:
    """The rotation vector of rotation matrix R."""
    cos = np.clip(0.5 * (np.trace(R) - 1.0), -1.0, 1.0)
    angle = float(np.arccos(cos))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-6:
        return 0.5 * v
    if angle > np.pi - 1e-4:  # near a half turn: from the symmetric part
        axis = np.sqrt(np.clip((np.diag(R) + 1.0) / 2.0, 0.0, None))
        k = int(np.argmax(axis))
        axis = (R[:, k] + R[k, :]) / (4.0 * axis[k]) if axis[k] > 0 else axis
        axis[k] = np.sqrt(max((R[k, k] + 1.0) / 2.0, 0.0))
        axis = axis / np.linalg.norm(axis)
        if axis @ v < 0.0:
            axis = -axis
        return angle * axis
    return angle / (2.0 * np.sin(angle)) * v


def dipole_fields(m, r):
    """Fields (n x 3, T) and their gradients (n x 3 x 3, T/m) of dipole m (A m^2) at
    offsets r (n x 3, m): B = K/r^3 (3 u (u.m) - m), dB/dr = 3K/r^4 ((u.m) I + u m^T +
    m u^T - 5 (u.m) u u^T)."""
    r = np.atleast_2d(r)
    d = np.linalg.norm(r, axis=1)
    u = r / d[:, None]
    um = u @ m
    B = (_K / d**3)[:, None] * (3.0 * um[:, None] * u - m)
    outer_um = u[:, :, None] * m[None, None, :]
    G = (3.0 * _K / d**4)[:, None, None] * (
        um[:, None, None] * np.eye(3) + outer_um + np.transpose(outer_um, (0, 2, 1))
        - 5.0 * um[:, None, None] * u[:, :, None] * u[:, None, :])
    return B, G


class PoseEstimate:
    """The filter's arithmetic, without Drake: state (p, R, b, d) and covariance P (10 x 10).

    Args:
        config: LocalizerConfig.
        p_BS: the Hall sensors' positions in the body (n x 3); their axes are the body's.
        self_field: each sensor's calibrated self-field c_i (n x 3, T, sensor frame).
        epm_moment: the EPM's moment magnitude (A m^2).
        R_BI: the IMU's frame in the body (3 x 3).
        gravity: |g| (m/s^2).
    """

    def __init__(self, config: LocalizerConfig, p_BS, self_field, epm_moment: float,
                 R_BI=np.eye(3), gravity: float = 9.81, gyro_range: float = np.radians(250.0)):
        check_localizer_config(config)
        self.config = config
        self.gyro_range = float(gyro_range)   # the IMU's (rad/s): beyond, a sample saturates
        self.p_BS = np.atleast_2d(np.asarray(p_BS, dtype=float))
        self.n = len(self.p_BS)
        self._self_field = np.asarray(self_field, dtype=float).reshape(self.n, 3)
        self.epm_moment = float(epm_moment)
        self._skew_p = _skews(self.p_BS)
        self.R_BI = np.asarray(R_BI, dtype=float)
        self.g_up = np.array([0.0, 0.0, float(gravity)])
        self.p = np.zeros(3)
        self.R = np.eye(3)
        self.b = np.zeros(3)
        self.d = 0.0
        self.P = np.eye(N)
        self.used = 0
        self.nis = 0.0

    def reset(self, p, R, b=np.zeros(3)):
        """Starts from pose (p, R) with the configured initial uncertainty."""
        c = self.config
        self.p, self.R, self.b = (np.array(p, dtype=float), np.array(R, dtype=float),
                                  np.array(b, dtype=float))
        self.d = 0.0
        self.P = np.diag(np.concatenate([
            np.full(3, c.initial_position_sigma**2),
            np.full(3, np.radians(c.initial_rotation_sigma_deg)**2),
            np.full(3, np.radians(c.initial_gyro_bias_sigma_deg)**2),
            [c.self_field_drift**2]]))

    def predict(self, gyro_I, dt: float):
        """Turns the orientation by the gyroscope's rate (IMU frame; NaN: held) over dt."""
        c = self.config
        gyro_I = np.asarray(gyro_I, dtype=float)
        w = self.R_BI @ gyro_I
        turn = 0.0
        if not np.all(np.isfinite(w)):
            w, turn = self.b.copy(), c.saturated_turn
        elif np.max(np.abs(gyro_I)) >= 0.99 * self.gyro_range:
            turn = c.saturated_turn
        step = exp_so3((w - self.b) * dt)
        self.R = self.R @ step
        F = np.eye(N)
        F[3:6, 3:6] = step.T
        F[3:6, 6:9] = -dt * np.eye(3)
        Q = np.diag(np.concatenate([np.full(3, c.position_walk**2 * dt),
                                    np.full(3, c.orientation_walk**2 * dt + turn**2),
                                    np.full(3, c.gyro_bias_walk**2 * dt),
                                    [c.self_field_drift_walk**2 * dt]]))
        self.P = F @ self.P @ F.T + Q

    def _model(self, p, R, d, p_E, m_E, sensors, accel_B):
        """Predicted measurements, their Jacobian (m x 10) at (p, R, d), and their noise's
        covariance (m x m)."""
        c = self.config
        p_S = p + self.p_BS[sensors] @ R.T
        B_W, G_W = dipole_fields(m_E, p_S - p_E)
        B_B = B_W @ R   # R^T B per sensor
        h = (B_B + d * self._self_field[sensors]).ravel()
        RtG = np.matmul(R.T, G_W)   # R^T G per sensor
        H = np.zeros((len(sensors), 3, N))
        H[:, :, 0:3] = RtG
        H[:, :, 3:6] = _skews(B_B) - np.matmul(np.matmul(RtG, R), self._skew_p[sensors])
        H[:, :, 9] = self._self_field[sensors]
        rows = [H.reshape(-1, N)]
        magnitude = np.linalg.norm(B_W, axis=1)
        sigma = np.sqrt(c.field_noise**2 + (c.model_error_local * magnitude)**2)
        shared = c.model_error * magnitude
        noise = np.diag(np.repeat(sigma**2, 3)) + np.kron(np.outer(shared, shared), np.eye(3))
        if accel_B is not None:
            g_B = R.T @ self.g_up
            h = np.concatenate([h, g_B])
            H = np.zeros((3, N))
            H[:, 3:6] = skew(g_B)
            rows.append(H)
            s = c.accel_noise + c.accel_motion_factor * abs(np.linalg.norm(accel_B)
                                                            - self.g_up[2])
            m = len(noise)
            noise = np.pad(noise, ((0, 3), (0, 3)))
            noise[m:, m:] = s**2 * np.eye(3)
        return h, np.vstack(rows), noise

    def update(self, B, saturated, accel_I, epm_pose):
        """One measurement update: B (3n, calibrated readings), saturated (n), accel_I (3,
        IMU frame; NaN: none), epm_pose [p_WE, m_hat_W] (NaN or zero moment: no field).
        Returns the number of sensors used."""
        B = np.asarray(B, dtype=float).reshape(self.n, 3)
        saturated = np.asarray(saturated, dtype=float).reshape(self.n)
        epm_pose = np.asarray(epm_pose, dtype=float)
        sensors = []
        if np.all(np.isfinite(epm_pose)) and np.linalg.norm(epm_pose[3:]) > 0.5:
            sensors = [i for i in range(self.n)
                       if saturated[i] < 0.5 and np.all(np.isfinite(B[i]))]
        accel_B = self.R_BI @ np.asarray(accel_I, dtype=float)
        if not np.all(np.isfinite(accel_B)):
            accel_B = None
        self.used = len(sensors)
        if not sensors and accel_B is None:
            return 0
        p_E = epm_pose[:3]
        m_E = (self.epm_moment * epm_pose[3:] / np.linalg.norm(epm_pose[3:]) if sensors
               else np.zeros(3))   # no field used: the accelerometer alone
        z = B[sensors].ravel()
        if accel_B is not None:
            z = np.concatenate([z, accel_B])
        p0, R0, b0, d0 = self.p, self.R, self.b, self.d
        p, R, b, d = p0, R0, b0, d0
        for _ in range(self.config.iterations):
            h, H, noise = self._model(p, R, d, p_E, m_E, sensors, accel_B)
            delta = np.concatenate([p - p0, log_so3(R0.T @ R), b - b0, [d - d0]])
            S = H @ self.P @ H.T + noise
            K = np.linalg.solve(S, H @ self.P).T
            innovation = z - h
            dx = K @ (innovation + H @ delta)
            p, R, b, d = p0 + dx[0:3], R0 @ exp_so3(dx[3:6]), b0 + dx[6:9], d0 + dx[9]
        self.nis = float(innovation @ np.linalg.solve(S, innovation))
        IKH = np.eye(N) - K @ H
        self.P = IKH @ self.P @ IKH.T + K @ noise @ K.T
        self.P = 0.5 * (self.P + self.P.T)
        self.p, self.R, self.b, self.d = p, R, b, d
        return len(sensors)

    def quaternion(self) -> np.ndarray:
        """The orientation as [w, x, y, z]."""
        return _quaternion_wxyz(self.R)

    def pose_covariance(self) -> np.ndarray:
        """The covariance (6 x 6) of [position, orientation (rotation vector, body side)]."""
        return self.P[:6, :6].copy()


def _quaternion_wxyz(R) -> np.ndarray:
    """[w, x, y, z] of a rotation matrix (orthonormalised first)."""
    U, _, Vt = np.linalg.svd(R)
    q = Quaternion(U @ Vt)
    return np.array([q.w(), q.x(), q.y(), q.z()])


class MagneticLocalizer(LeafSystem):
    """The capsule's pose estimate from its Hall sensors, IMU and the EPM's pose.

    .. pydrake_system::

        name: MagneticLocalizer
        input_ports:
        - B
        - saturated
        - accel
        - gyro
        - epm_pose
        output_ports:
        - pose
        - covariance
        - std
        - sensors_used

    B (3n, T): the array's calibrated readings; saturated (n); accel, gyro (3 each): the
    IMU's samples in its frame; epm_pose: [p_WE, m_hat_W]. pose: [q_WB (wxyz), p_WB];
    covariance (36): of [p_WB, rotation vector], row-major; std (6): the square roots of its
    diagonal (m, rad); sensors_used (1): Hall sensors in the last update.

    Args:
        estimate: a PoseEstimate (its configuration, sensors and models).
        X_WB0: the start pose the estimate begins at (RigidTransform).
    """

    def __init__(self, estimate: PoseEstimate, X_WB0):
        super().__init__()
        self._estimate = estimate
        n = estimate.n
        self._R0 = np.asarray(X_WB0.rotation().matrix())
        self._p0 = np.asarray(X_WB0.translation())
        self._B = self.DeclareVectorInputPort("B", 3 * n)
        self._saturated = self.DeclareVectorInputPort("saturated", n)
        self._accel = self.DeclareVectorInputPort("accel", 3)
        self._gyro = self.DeclareVectorInputPort("gyro", 3)
        self._epm = self.DeclareVectorInputPort("epm_pose", 6)
        # [p (3), R (9, row-major), b (3), d, P (N x N), used]
        estimate.reset(self._p0, self._R0)
        self._state = self.DeclareDiscreteState(BasicVector(self._pack(estimate)))
        self.DeclareVectorOutputPort("pose", 7, self._calc_pose, {self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "covariance", 36,
            lambda c, out: out.SetFromVector(self._P(c)[:6, :6].ravel()), {self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "std", 6, lambda c, out: out.SetFromVector(np.sqrt(np.diag(self._P(c))[:6])),
            {self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "sensors_used", 1,
            lambda c, out: out.SetAtIndex(0, c.get_discrete_state(self._state).value()[-1]),
            {self.xd_ticket()})
        # Half a period after the sensors sample (they do at 0, T, 2T, ...): each update
        # reads the samples just taken, never the zeros the sensors hold before their first.
        self.DeclarePeriodicDiscreteUpdateEvent(estimate.config.period,
                                                0.5 * estimate.config.period, self._update)

    @staticmethod
    def _pack(e: PoseEstimate) -> np.ndarray:
        return np.concatenate([e.p, e.R.ravel(), e.b, [e.d], e.P.ravel(), [e.used]])

    def _unpack(self, x):
        e = self._estimate
        e.p, e.R, e.b, e.d = x[0:3].copy(), x[3:12].reshape(3, 3).copy(), x[12:15].copy(), x[15]
        e.P = x[16:16 + N * N].reshape(N, N).copy()
        return e

    def _P(self, context):
        return context.get_discrete_state(self._state).value()[16:16 + N * N].reshape(N, N)

    def _calc_pose(self, context, output):
        x = context.get_discrete_state(self._state).value()
        output.SetFromVector(np.concatenate([_quaternion_wxyz(x[3:12].reshape(3, 3)), x[0:3]]))

    def _update(self, context, discrete_state):
        e = self._unpack(context.get_discrete_state(self._state).value())
        e.predict(self._gyro.Eval(context), e.config.period)
        e.update(self._B.Eval(context), self._saturated.Eval(context),
                 self._accel.Eval(context), self._epm.Eval(context))
        discrete_state.set_value(self._state, self._pack(e))


def check_localizer(config: LocalizerConfig, scenario) -> None:
    checked("capsule.localizer.", check_localizer_config, config)
    need(scenario.capsule.imu is not None and scenario.capsule.magnetic_array is not None,
         "capsule.localizer needs capsule.imu and capsule.magnetic_array")


@block("capsule.localizer", LocalizerConfig, check=check_localizer)
def add_localizer(builder, parts, config: LocalizerConfig):
    """`capsule.localizer`: the pose estimate from capsule.magnetic_array, capsule.imu and
    epm.pose, started at the capsule's start pose; exports capsule.localizer.{pose,
    covariance, std, sensors_used}."""
    imu = parts.shared("capsule.imu.config")
    estimate = PoseEstimate(
        config, parts.shared("capsule.magnetic_array.positions"),
        parts.shared("capsule.magnetic_array.self_field"), parts.epm.magnet.moment(),
        imu.X_BS().rotation().matrix(), parts.gravity, imu.gyro_range)
    localizer = builder.AddNamedSystem("capsule.localizer", MagneticLocalizer(
        estimate, parts.X_WB0))
    builder.Connect(parts.output("capsule.magnetic_array.B"), localizer.GetInputPort("B"))
    builder.Connect(parts.output("capsule.magnetic_array.saturated"),
                    localizer.GetInputPort("saturated"))
    builder.Connect(parts.output("capsule.imu.accel"), localizer.GetInputPort("accel"))
    builder.Connect(parts.output("capsule.imu.gyro"), localizer.GetInputPort("gyro"))
    builder.Connect(parts.output("epm.pose"), localizer.GetInputPort("epm_pose"))
    parts.export_outputs(localizer, "capsule.localizer")
    return localizer
