"""Magnetic localisation: the capsule's position from its magnetometer and the known EPM.

The EPM's pose is known (the robot places it); its point-dipole field at the sensor,
turned into the world frame with the AHRS's orientation, is what the magnetometer reads.
Three equations, three unknowns: the sensor's position solves B(p_S - p_E; m_E) = R_WS B_S
by Levenberg-Marquardt from the previous estimate. A dipole's field is the same at p and at
its mirror image through the magnet's centre (B(r) = B(-r)), so the estimate is kept on
the patient's side: below the EPM. Closed-loop magnetic capsule systems localise this way
(the actuating magnet's known field read by the capsule's own sensors); here the field model
is the point dipole this simulator's physics uses.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from capsule_drake.capsule.model import rotation_from_quaternion
from capsule_drake.physics.magnetics import dipole_field


def locate_sensor(B_W, p_E, m_E, p_guess, iterations: int = 30,
                  tolerance: float = 1e-9) -> tuple[np.ndarray, float]:
    """The sensor position p_S (m) whose dipole field from the EPM (centre p_E, moment m_E,
    A m^2) equals B_W (T, world frame), starting from p_guess; kept below the EPM.

    Returns (p_S, residual (T)): the residual |B(p_S) - B_W| tells a solution from a
    failure (a field the dipole cannot produce, e.g. a saturated sensor).
    """
    B_W = np.asarray(B_W, dtype=float)
    p_E = np.asarray(p_E, dtype=float)
    m_E = np.asarray(m_E, dtype=float)
    r = np.asarray(p_guess, dtype=float) - p_E
    if r[2] > 0.0:  # start on the patient's side of the magnet
        r = -r
    scale = max(np.linalg.norm(B_W), 1e-12)
    damping = 1e-3

    def residual(r):
        return (dipole_field(m_E, r) - B_W) / scale

    f = residual(r)
    cost = f @ f
    for _ in range(iterations):
        h = 1e-6 * max(np.linalg.norm(r), 1e-3)
        J = np.column_stack([(residual(r + h * e) - f) / h for e in np.eye(3)])
        step = np.linalg.solve(J.T @ J + damping * np.diag(np.diag(J.T @ J) + 1e-12),
                               -J.T @ f)
        r_new = r + step
        if r_new[2] > 0.0:  # the mirror image above the EPM: the same field, not the patient
            r_new = -r_new
        f_new = residual(r_new)
        cost_new = f_new @ f_new
        if cost_new < cost:
            r, f, cost = r_new, f_new, cost_new
            damping = max(damping / 3.0, 1e-9)
            if np.linalg.norm(step) < tolerance:
                break
        else:
            damping *= 5.0
    return p_E + r, float(np.sqrt(cost) * scale)


@dataclasses.dataclass
class LocalizerConfig:
    """Magnetic localisation. YAML-loadable; all fields default."""

    # A field the dipole model misses by more than this share of its magnitude is not used
    # (the estimate holds): a saturated or disturbed reading.
    max_relative_residual: float = 0.05
    # Update period (s); the magnetometer's sample period is the natural choice.
    period: float = 0.01


class MagneticLocalizer(LeafSystem):
    """The capsule's pose estimate: orientation from the AHRS, position from the field.

    .. pydrake_system::

        name: MagneticLocalizer
        input_ports:
        - B_S
        - q_WB
        - epm_pose
        output_ports:
        - capsule_pose
        - valid

    B_S: the magnetometer's reading (T, sensor frame). q_WB: the AHRS's orientation of the
    capsule body (wxyz). epm_pose: [p_WE, m_hat_W] (the EPM's centre and moment direction).
    capsule_pose: [q_WB (4), p_WB (3)], the body origin's estimated position.
    valid: 1 when the last reading located the capsule, 0 when it held the estimate.

    Args:
        X_BS: the magnetometer's pose in the capsule body.
        epm_moment: the EPM's moment magnitude (A m^2).
        p_WB0: the capsule's starting position (the first guess).
        config: LocalizerConfig.
        q_WB0: the capsule's starting orientation (wxyz), the estimate until the first
            update (default identity).
    """

    def __init__(self, X_BS, epm_moment: float, p_WB0, config: LocalizerConfig | None = None,
                 q_WB0=(1.0, 0.0, 0.0, 0.0)):
        super().__init__()
        self._config = config or LocalizerConfig()
        self._R_BS = np.asarray(X_BS.rotation().matrix())
        self._p_BS = np.asarray(X_BS.translation())
        self._moment = float(epm_moment)
        self._B = self.DeclareVectorInputPort("B_S", 3)
        self._q = self.DeclareVectorInputPort("q_WB", 4)
        self._epm = self.DeclareVectorInputPort("epm_pose", 6)
        # [q_WB (4), p_WB (3), valid]
        q_WB0 = np.asarray(q_WB0, dtype=float)
        initial = np.concatenate([q_WB0 / np.linalg.norm(q_WB0), np.asarray(p_WB0, dtype=float),
                                  [0.0]])
        self._state = self.DeclareDiscreteState(BasicVector(initial))
        self.DeclareVectorOutputPort(
            "capsule_pose", 7,
            lambda c, out: out.SetFromVector(c.get_discrete_state(self._state).value()[:7]),
            {self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "valid", 1,
            lambda c, out: out.SetAtIndex(0, c.get_discrete_state(self._state).value()[7]),
            {self.xd_ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(self._config.period, 0.0, self._update)

    def _update(self, context, discrete_state):
        x = context.get_discrete_state(self._state).value().copy()
        B_S = np.asarray(self._B.Eval(context), dtype=float)
        q = np.asarray(self._q.Eval(context), dtype=float)
        epm = np.asarray(self._epm.Eval(context), dtype=float)
        x[7] = 0.0
        if not (np.all(np.isfinite(B_S)) and np.all(np.isfinite(q)) and np.all(np.isfinite(epm))
                and np.linalg.norm(q) > 0.5 and np.linalg.norm(epm[3:]) > 0.5):
            discrete_state.set_value(self._state, x)
            return
        R_WB = rotation_from_quaternion(q)
        x[:4] = q / np.linalg.norm(q)
        B_W = R_WB @ (self._R_BS @ B_S)
        m_E = self._moment * epm[3:] / np.linalg.norm(epm[3:])
        p_S_guess = x[4:7] + R_WB @ self._p_BS
        p_S, residual = locate_sensor(B_W, epm[:3], m_E, p_S_guess)
        if residual <= self._config.max_relative_residual * np.linalg.norm(B_W):
            x[4:7] = p_S - R_WB @ self._p_BS
            x[7] = 1.0
        discrete_state.set_value(self._state, x)
