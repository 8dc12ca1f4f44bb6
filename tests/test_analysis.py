"""Magnetic control analysis: the actuation matrix and stiffness against central differences
and physical identities, the gravity-holding EPM pose against the dipole force, and the
controllability of the linearised capsule."""

import numpy as np
import pytest

from capsule_drake.control.analysis import (actuation_matrix, capsule_wrench, controllability,
                                    hold_against_gravity, magnetic_stiffness,
                                    translational_model)
from capsule_drake.physics.magnetics import cylinder_moment, dipole_force

M_EPM = cylinder_moment(0.1016, 0.1016, 1.48)
M_IPM = cylinder_moment(0.0111, 0.0111, 1.48)


def _pose(seed):
    rng = np.random.default_rng(seed)

    def unit():
        v = rng.normal(size=3)
        return v / np.linalg.norm(v)

    p_C = rng.normal(size=3) * 0.05
    p_E = p_C + rng.uniform(0.1, 0.25) * unit()
    return p_E, M_EPM * unit(), p_C, M_IPM * unit()


def _rotate(v, axis_angle):
    angle = np.linalg.norm(axis_angle)
    if angle == 0.0:
        return v
    k = axis_angle / angle
    return (v * np.cos(angle) + np.cross(k, v) * np.sin(angle)
            + k * (k @ v) * (1.0 - np.cos(angle)))


@pytest.mark.parametrize("seed", range(5))
def test_actuation_matrix_matches_central_differences(seed):
    p_E, m_E, p_C, m_C = _pose(seed)
    J = actuation_matrix(p_E, m_E, p_C, m_C)
    h = 1e-6
    numeric = np.zeros((6, 6))
    for k in range(6):
        step = np.zeros(6)
        step[k] = h

        def wrench(s):
            F, T = capsule_wrench(p_E + s[:3], _rotate(m_E, s[3:]), p_C, m_C)
            return np.concatenate([F, T])

        numeric[:, k] = (wrench(step) - wrench(-step)) / (2.0 * h)
    np.testing.assert_allclose(J, numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max())
    # Turning the EPM about its own moment does nothing.
    np.testing.assert_allclose(J[:, 3:] @ (m_E / np.linalg.norm(m_E)), 0.0,
                               atol=1e-9 * np.abs(J).max())
    assert np.linalg.matrix_rank(J, tol=1e-9 * np.abs(J).max()) == 5


@pytest.mark.parametrize("seed", range(5))
def test_stiffness_is_symmetric_traceless_and_the_force_gradient(seed):
    p_E, m_E, p_C, m_C = _pose(seed)
    K = magnetic_stiffness(p_E, m_E, p_C, m_C)
    scale = np.abs(K).max()
    np.testing.assert_allclose(K, K.T, atol=1e-10 * scale)
    assert abs(np.trace(K)) < 1e-10 * scale  # Laplace: the field is harmonic
    h = 1e-6
    numeric = np.column_stack([
        (dipole_force(m_E, m_C, p_C + h * e - p_E) - dipole_force(m_E, m_C, p_C - h * e - p_E))
        / (2.0 * h) for e in np.eye(3)])
    np.testing.assert_allclose(K, numeric, rtol=1e-5, atol=1e-7 * scale)
    # Moving the EPM is moving the capsule the other way: dF/dp_E = -K.
    np.testing.assert_allclose(actuation_matrix(p_E, m_E, p_C, m_C)[:3, :3], -K,
                               atol=1e-9 * scale)


def test_hold_against_gravity_pulls_the_weight_straight_up():
    weight = 0.012 * 9.81
    p_C = np.array([0.02, -0.01, 0.08])
    heading = np.array([0.6, 0.8, 0.0])
    p_E, m_hat = hold_against_gravity(p_C, heading, weight, M_EPM, M_IPM)
    F = dipole_force(M_EPM * m_hat, M_IPM * heading, p_C - p_E)
    np.testing.assert_allclose(F, [0.0, 0.0, weight], atol=0.01 * weight)
    assert p_E[2] > p_C[2] + 0.2  # 0.12 N needs the EPM ~25 cm away
    # Unstable, as Earnshaw says: the stiffness has a positive eigenvalue.
    K = magnetic_stiffness(p_E, M_EPM * m_hat, p_C, M_IPM * heading)
    assert np.linalg.eigvalsh(0.5 * (K + K.T)).max() > 0.0


def test_the_linearised_capsule_is_controllable_by_the_epm_position():
    weight = 0.012 * 9.81
    p_C = np.zeros(3)
    heading = np.array([1.0, 0.0, 0.0])
    p_E, m_hat = hold_against_gravity(p_C, heading, weight, M_EPM, M_IPM)
    system = translational_model(p_E, M_EPM * m_hat, p_C, M_IPM * heading, mass=0.012,
                                 damping=2.0)
    assert controllability(system) == (True, 6)
    # Open loop it is unstable (a positive real eigenvalue from the stiffness).
    assert np.linalg.eigvals(system.A()).real.max() > 0.0
    # An input that cannot move the capsule (no EPM): not controllable.
    from pydrake.systems.primitives import LinearSystem
    blind = LinearSystem(system.A(), np.zeros_like(system.B()), system.C(), system.D())
    assert controllability(blind) == (False, 0)
