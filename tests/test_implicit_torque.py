"""The implicit magnet torque's plain-float algebra (physics/implicit_torque.py) against
numpy, and its step against the formula it implements, written with numpy."""

import numpy as np

from capsule_drake.physics.implicit_torque import (cholesky3, cross3, implicit_torque,
                                                   mat_vec, minus_scaled, rotate_symmetric,
                                                   rotational_stiffness, solve_spd3)
from capsule_drake.physics.magnetics import dipole_pair_interaction_float

RNG = np.random.default_rng(7)


def _rows(M):
    """A matrix as the compiled algebra takes it: a tuple of its rows."""
    return tuple(tuple(row) for row in np.asarray(M, dtype=float).tolist())


def _vec(v):
    return tuple(np.asarray(v, dtype=float).tolist())


def _rotation():
    q, _ = np.linalg.qr(RNG.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _spd():
    a = RNG.normal(size=(3, 3))
    return a @ a.T + 3.0 * np.eye(3)


def test_the_float_algebra_is_numpys():
    for _ in range(20):
        a, b = _vec(RNG.normal(size=3)), _vec(RNG.normal(size=3))
        np.testing.assert_allclose(cross3(a, b), np.cross(a, b), atol=1e-14)
        M, R, I, S = RNG.normal(size=(3, 3)), _rotation(), _spd(), _spd()
        np.testing.assert_allclose(mat_vec(_rows(M), a), M @ a, atol=1e-14)
        np.testing.assert_allclose(rotate_symmetric(_rows(R), _rows(I)), R @ I @ R.T,
                                   atol=1e-13)
        np.testing.assert_allclose(minus_scaled(_rows(I), 0.3, _rows(S)), I - 0.3 * S,
                                   atol=1e-14)
        np.testing.assert_allclose(solve_spd3(cholesky3(_rows(I)), b),
                                   np.linalg.solve(I, b), rtol=1e-12)
    assert cholesky3(_rows(-np.eye(3))) is None   # not positive definite


def test_the_stiffness_is_the_torques_derivative_as_the_body_turns():
    """Turning the body by a small angle about each axis changes the torque about its
    centre of mass by K times that angle (central differences, an independent route)."""
    m, p, r = (0.0, 0.2, 1.2), (0.01, 0.0, 0.12), (0.0, 0.0, 0.004)
    others = (((0.0, 0.0, 970.0), (0.0, 0.0, 0.0)),)
    K = np.array(rotational_stiffness(m, p, r, others, 1e-3))

    def torque(angle_vector):
        R = _rodrigues(angle_vector)
        m_i, r_i = R @ m, R @ r
        p_i = np.array(p) - np.array(r) + r_i
        out = np.zeros(3)
        for m_j, p_j in others:
            result = dipole_pair_interaction_float(m_j, tuple(m_i), tuple(p_i - p_j), 1e-3)
            out += np.array(result.torque_target) + np.cross(r_i, result.force_target)
        return out

    h = 1e-6
    numeric = np.column_stack([(torque(h * e) - torque(-h * e)) / (2 * h) for e in np.eye(3)])
    np.testing.assert_allclose(K, numeric, rtol=1e-4, atol=1e-6 * np.abs(numeric).max())


def _rodrigues(w):
    angle = np.linalg.norm(w)
    if angle == 0.0:
        return np.eye(3)
    k = w / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def test_the_step_is_the_linearly_implicit_formula():
    """tau = tau0 + h S w_hat, w_hat = w + (I - h^2 S)^-1 h (tau0 + h S w + tau_other),
    tau_other = I (w - w_prev) / h - tau_prev: written again with numpy (a stiffness whose
    symmetric part keeps I - 2 h^2 S positive definite, so it is taken whole)."""
    h = 1e-3
    R, I_B = _rotation(), np.diag([1.1e-6, 1.1e-6, 0.4e-6])
    K = -0.02 * _spd()
    tau_M, f_W, r = RNG.normal(size=3) * 1e-3, RNG.normal(size=3) * 0.1, RNG.normal(size=3) * 1e-3
    w, previous = RNG.normal(size=3), _vec(RNG.normal(size=6) * 1e-3)
    tau, tau_cm, w_out = implicit_torque(_vec(tau_M), _vec(f_W), _vec(r), _rows(K),
                                         _rows(R), _rows(I_B), _vec(w), previous, h)
    S = 0.5 * (K + K.T)
    I_W = R @ I_B @ R.T
    tau0 = tau_M + np.cross(r, f_W)
    other = I_W @ (w - previous[:3]) / h - np.array(previous[3:])
    w_hat = w + np.linalg.solve(I_W - h * h * S, h * (tau0 + h * S @ w + other))
    np.testing.assert_allclose(tau, tau_M + h * S @ w_hat, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(tau_cm, tau0 + h * S @ w_hat, rtol=1e-10, atol=1e-15)
    assert list(w_out) == list(w)
