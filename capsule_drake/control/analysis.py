"""Magnetic control analysis: the EPM pose for a wanted force, the actuation matrix,
magnetic stiffness, equilibria and controllability of a capsule held by the EPM
(point-dipole model). The lumen follower drives with `epm_pose_for_force`.

Derivatives come from automatic differentiation (`AutoDiffXd`) through the same dipole
functions the simulation uses (`capsule_drake.physics.magnetics`); the tests check them against
central differences and physical identities (a symmetric, traceless stiffness).

Frames and units: world frame, SI. p_E, p_C: the EPM's and the capsule magnet's centres (m);
m_E, m_C: their moments (A m^2, vectors).
"""

from __future__ import annotations

import numpy as np
from pydrake.autodiffutils import ExtractGradient, InitializeAutoDiff
from pydrake.systems.primitives import ControllabilityMatrix, IsControllable, LinearSystem

from capsule_drake.epm.poses import field_aligning_moment_direction
from capsule_drake.physics.magnetics import MU0, dipole_force, dipole_torque


# Directions from the capsule's magnet to the EPM searched by `epm_pose_for_force`: the
# upper hemisphere (elevation 2-90 deg) on a 2-degree grid, refined around the best.
_GRID_STEP = np.radians(2.0)


def _directions(elevation, azimuth):
    elevation, azimuth = np.meshgrid(elevation, azimuth)
    return np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                     np.sin(elevation)], axis=-1).reshape(-1, 3)


_HEMISPHERE = _directions(np.arange(1, 46) * _GRID_STEP, np.arange(0, 180) * _GRID_STEP)


def aligned_unit_forces(u, h, epm_moment, ipm_moment):
    """Forces (N) on a capsule magnet of moment `ipm_moment` along the unit vector h, from an
    EPM of moment `epm_moment` one metre away in each unit direction u (rows; capsule ->
    EPM), the EPM's moment turned so that its field at the capsule is along h. Forces scale
    as 1 / distance^4."""
    n = -np.asarray(u, dtype=float)  # EPM -> capsule
    m = 1.5 * n * (n @ h)[:, None] - h
    m = epm_moment * m / np.linalg.norm(m, axis=1, keepdims=True)
    mt = ipm_moment * np.asarray(h, dtype=float)
    ms_n = np.sum(m * n, axis=1)
    mt_n = n @ mt
    ms_mt = m @ mt
    return 3.0 * MU0 / (4.0 * np.pi) * (m * mt_n[:, None] + mt[None, :] * ms_n[:, None]
                              + n * (ms_mt - 5.0 * ms_n * mt_n)[:, None])


def epm_pose_for_force(p_WM, h, force, epm_moment, ipm_moment):
    """The EPM's centre p_WE above the capsule's magnet at p_WM, and its unit moment, such
    that the dipole force on the capsule's magnet (aligned with h, the EPM's field at it
    along h) is `force` (N, world). The force's direction fixes the direction from the
    magnet to the EPM (searched over the upper hemisphere), its size the distance (forces
    fall as 1 / distance^4). A force no EPM above can give (downward) gets the nearest
    direction. Returns (p_WE, m_hat_W, distance)."""
    h = np.asarray(h, dtype=float)
    force = np.asarray(force, dtype=float)
    size = float(np.linalg.norm(force))
    if size < 1e-12:
        raise ValueError("epm_pose_for_force needs a non-zero force")

    def best(directions):
        G = aligned_unit_forces(directions, h, epm_moment, ipm_moment)
        g = np.linalg.norm(G, axis=1)
        i = int(np.argmax((G @ force) / g))
        return directions[i], g[i]

    u, _ = best(_HEMISPHERE)
    # Refine: a finer grid around the coarse best, twice.
    step = _GRID_STEP
    for _ in range(2):
        elevation = np.arcsin(np.clip(u[2], -1.0, 1.0))
        azimuth = np.arctan2(u[1], u[0])
        offsets = np.linspace(-step, step, 9)
        u, g = best(_directions(np.clip(elevation + offsets, 0.0, np.pi / 2),
                                azimuth + offsets))
        step /= 4.0
    distance = (g / size) ** 0.25
    p_WE = np.asarray(p_WM, dtype=float) + distance * u
    m_hat = field_aligning_moment_direction(-u, h)
    return p_WE, m_hat, distance


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], dtype=object)


def capsule_wrench(p_E, m_E, p_C, m_C):
    """(force, torque) on the capsule's magnet from the EPM (torque about its centre)."""
    p = np.asarray(p_C) - np.asarray(p_E)
    return dipole_force(m_E, m_C, p), dipole_torque(m_E, m_C, p)


def actuation_matrix(p_E, m_E, p_C, m_C) -> np.ndarray:
    """6 x 6 Jacobian of the capsule's wrench [F; T] with respect to the EPM's pose
    [p_E; theta_E]: its position (m) and a small rotation theta_E (rad, world frame) of its
    moment, m_E -> m_E + theta_E x m_E. The rotation about m_E itself does nothing (the
    column along it is zero): rank at most 5. For the capsule's magnet held (not turning
    with the field)."""
    p_E = np.asarray(p_E, dtype=float)
    m_E = np.asarray(m_E, dtype=float)
    x = InitializeAutoDiff(np.zeros(6)).reshape(-1)
    pE = p_E + x[:3]
    mE = m_E + _skew(x[3:]) @ m_E
    F, T = capsule_wrench(pE, mE, np.asarray(p_C, dtype=object), np.asarray(m_C, dtype=object))
    return ExtractGradient(np.concatenate([F, T]))


def magnetic_stiffness(p_E, m_E, p_C, m_C) -> np.ndarray:
    """3 x 3 gradient of the force on the capsule's magnet with respect to its position,
    K = dF/dp_C, its moment held. F = grad(m_C . B), so K is the Hessian of m_C . B:
    symmetric, and traceless because the field is harmonic in free space (Earnshaw: some
    direction is always unstable)."""
    p_C = np.asarray(p_C, dtype=float)
    x = InitializeAutoDiff(np.zeros(3)).reshape(-1)
    F, _ = capsule_wrench(np.asarray(p_E, dtype=object), np.asarray(m_E, dtype=object),
                          p_C + x, np.asarray(m_C, dtype=object))
    return ExtractGradient(F)


def hold_against_gravity(p_C, heading, weight: float, epm_moment: float,
                         ipm_moment: float):
    """The EPM pose that holds the capsule's magnet at p_C (aligned with `heading`, the field
    there along it) against its weight (N): the magnet's pull is `weight` straight up.
    Returns (p_E, m_E_hat). The equilibrium is unstable (`magnetic_stiffness` has a
    positive eigenvalue): it needs feedback, or a wall."""
    p_E, m_hat, _ = epm_pose_for_force(p_C, heading, np.array([0.0, 0.0, weight]),
                                       epm_moment, ipm_moment)
    return p_E, m_hat


def translational_model(p_E, m_E, p_C, m_C, mass: float, damping: float = 0.0):
    """The capsule's translation about (p_C, v = 0), linearised, with the EPM's position as
    the input: x = [dp_C, dv], u = dp_E,
        d(dp_C)/dt = dv,  m d(dv)/dt = K dp_C - c dv + J_p dp_E,
    K the magnetic stiffness, J_p = dF/dp_E (= -K for a dipole pair: only the offset
    counts), c the colon's speed-proportional resistance (N s/m). A continuous-time
    `LinearSystem` (the capsule's magnet held in its orientation)."""
    K = magnetic_stiffness(p_E, m_E, p_C, m_C)
    J_p = actuation_matrix(p_E, m_E, p_C, m_C)[:3, :3]
    A = np.block([[np.zeros((3, 3)), np.eye(3)], [K / mass, -damping / mass * np.eye(3)]])
    B = np.vstack([np.zeros((3, 3)), J_p / mass])
    return LinearSystem(A, B, np.eye(6), np.zeros((6, 3)))


def controllability(system: LinearSystem) -> tuple[bool, int]:
    """(controllable, rank of the controllability matrix) of a linear system."""
    matrix = ControllabilityMatrix(system)
    return bool(IsControllable(system)), int(np.linalg.matrix_rank(matrix))
