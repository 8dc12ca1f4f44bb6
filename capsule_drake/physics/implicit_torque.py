"""The linearly implicit magnetic torque, in plain floats: what `MagneticForce` applies to a
free magnet body when its torque is integrated implicitly in its stiff part (the system's
`implicit_step`; physics/magnet_force.py keeps the state and calls these).

The magnet's torque m x B has a rotational stiffness K (N m/rad, about the body's centre of
mass), so stiff on a 12 g capsule that an explicit step is stable only while omega h < 2
(physics/step_bound.py). Applied instead of tau0:

    tau = tau0 + h K w_hat,
    w_hat = w_n + (I - h^2 K)^-1 h (tau0 + h K w_n + tau_other),

w_hat being the body's angular velocity after the step as predicted with the torque
linearised at the end of the step (backward Euler), I its central inertia in world, and
tau_other everything else that turned it during the last step (contact, gyroscopic), read
off its change of angular velocity: I (w_n - w_{n-1}) / h - tau(n-1).

Plain floats and tuples throughout, compiled with Numba (`implicit_torque` and what it calls
run in machine code; a 3x3 matrix is a tuple of its rows): this runs at every plant step, and
numpy's per-call overhead on 3x3 matrices, or Python's on the arithmetic, would cost several
times the arithmetic. Each function's first call in a process loads its machine code from the
cache beside this file (compiled once, a few seconds).
"""

import math

import numpy as np
from numba import njit

from capsule_drake.physics.magnetics import dipole_pair_interaction_float


@njit(cache=True)
def cross3(a, b):
    """a x b of two 3-sequences of floats, as a tuple (numpy's cross costs ~30 us)."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@njit(cache=True)
def mat_vec(M, v):
    """M v for a 3x3 matrix given as rows and a 3-sequence, as a tuple."""
    return (M[0][0] * v[0] + M[0][1] * v[1] + M[0][2] * v[2],
            M[1][0] * v[0] + M[1][1] * v[1] + M[1][2] * v[2],
            M[2][0] * v[0] + M[2][1] * v[1] + M[2][2] * v[2])


@njit(cache=True)
def rotate_symmetric(R, I):
    """R I R^T for a rotation R and a symmetric I, both as rows."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R
    (i00, i01, i02), (_, i11, i12), (_, _, i22) = I
    # Rows of R I.
    a00 = r00 * i00 + r01 * i01 + r02 * i02
    a01 = r00 * i01 + r01 * i11 + r02 * i12
    a02 = r00 * i02 + r01 * i12 + r02 * i22
    a10 = r10 * i00 + r11 * i01 + r12 * i02
    a11 = r10 * i01 + r11 * i11 + r12 * i12
    a12 = r10 * i02 + r11 * i12 + r12 * i22
    a20 = r20 * i00 + r21 * i01 + r22 * i02
    a21 = r20 * i01 + r21 * i11 + r22 * i12
    a22 = r20 * i02 + r21 * i12 + r22 * i22
    w00 = a00 * r00 + a01 * r01 + a02 * r02
    w01 = a00 * r10 + a01 * r11 + a02 * r12
    w02 = a00 * r20 + a01 * r21 + a02 * r22
    w11 = a10 * r10 + a11 * r11 + a12 * r12
    w12 = a10 * r20 + a11 * r21 + a12 * r22
    w22 = a20 * r20 + a21 * r21 + a22 * r22
    return ((w00, w01, w02), (w01, w11, w12), (w02, w12, w22))


@njit(cache=True)
def minus_scaled(A, c, B):
    """A - c B for symmetric 3x3 A and B (rows)."""
    return ((A[0][0] - c * B[0][0], A[0][1] - c * B[0][1], A[0][2] - c * B[0][2]),
            (A[1][0] - c * B[1][0], A[1][1] - c * B[1][1], A[1][2] - c * B[1][2]),
            (A[2][0] - c * B[2][0], A[2][1] - c * B[2][1], A[2][2] - c * B[2][2]))


@njit(cache=True)
def cholesky3(A):
    """The lower Cholesky factor of a symmetric 3x3 matrix (rows), or None if it is not
    positive definite."""
    a = A[0][0]
    if not a > 0.0:
        return None
    l00 = math.sqrt(a)
    l10, l20 = A[1][0] / l00, A[2][0] / l00
    a = A[1][1] - l10 * l10
    if not a > 0.0:
        return None
    l11 = math.sqrt(a)
    l21 = (A[2][1] - l20 * l10) / l11
    a = A[2][2] - l20 * l20 - l21 * l21
    if not a > 0.0:
        return None
    return l00, l10, l20, l11, l21, math.sqrt(a)


@njit(cache=True)
def solve_spd3(L, b):
    """x with L L^T x = b, L from cholesky3."""
    l00, l10, l20, l11, l21, l22 = L
    y0 = b[0] / l00
    y1 = (b[1] - l10 * y0) / l11
    y2 = (b[2] - l20 * y0 - l21 * y1) / l22
    x2 = y2 / l22
    x1 = (y1 - l21 * x2) / l11
    x0 = (y0 - l10 * x1 - l20 * x2) / l00
    return (x0, x1, x2)


@njit(cache=True)
def _array3(A):
    """A 3x3 matrix given as rows, as an array."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i][j]
    return out


@njit(cache=True)
def restoring_part(S, I_W):
    """The restoring part of a symmetric stiffness S (torque per radian) on a body of
    inertia I_W: in mass-weighted coordinates (I^-1/2 S I^-1/2, whose eigenvalues are
    -omega^2 of the turning modes) the positive eigenvalues, modes that the torque turns
    further away, set to zero. Those grow in the physics too; left to the explicit torque,
    they keep I - h^2 S positive definite."""
    values, vectors = np.linalg.eigh(_array3(I_W))
    root = vectors @ np.diag(values ** 0.5) @ vectors.T
    inverse_root = vectors @ np.diag(values ** -0.5) @ vectors.T
    modes, Q = np.linalg.eigh(inverse_root @ _array3(S) @ inverse_root)
    A = root @ Q
    P = A @ np.diag(np.minimum(modes, 0.0)) @ A.T
    return ((P[0, 0], P[0, 1], P[0, 2]), (P[1, 0], P[1, 1], P[1, 2]),
            (P[2, 0], P[2, 1], P[2, 2]))


@njit(cache=True)
def _torque_about_cm(m_i, p_i, r_i, others, min_distance):
    """The point-dipole torque of the `others` [(m_j, p_j)] on a magnet of moment m_i at
    p_i, about its body's centre of mass r_i behind it."""
    tx = ty = tz = 0.0
    for m_j, p_j in others:
        result = dipole_pair_interaction_float(
            m_j, m_i, (p_i[0] - p_j[0], p_i[1] - p_j[1], p_i[2] - p_j[2]), min_distance)
        lever = cross3(r_i, result.force_target)
        torque = result.torque_target
        tx += torque[0] + lever[0]
        ty += torque[1] + lever[1]
        tz += torque[2] + lever[2]
    return tx, ty, tz


@njit(cache=True)
def rotational_stiffness(m, p, r, others, min_distance: float, eps: float = 1e-6):
    """K (3 rows, N m/rad): how the point-dipole torque about a magnet's body's centre of
    mass changes as the body turns about it, the moment `m` turning and the magnet's centre
    `p` swinging on its lever arm `r` (from the centre of mass) through the field and
    gradient of the `others` (a tuple of (m_j, p_j)). By forward differences of `eps` rad
    (the stiffness need only be close: the torque applied is the field model's own, plus
    h K w_hat)."""
    base = _torque_about_cm(m, p, r, others, min_distance)
    columns = []
    for axis in range(3):
        turn = (eps if axis == 0 else 0.0, eps if axis == 1 else 0.0,
                eps if axis == 2 else 0.0)
        dm, dr = cross3(turn, m), cross3(turn, r)
        turned = _torque_about_cm(
            (m[0] + dm[0], m[1] + dm[1], m[2] + dm[2]),
            (p[0] + dr[0], p[1] + dr[1], p[2] + dr[2]),
            (r[0] + dr[0], r[1] + dr[1], r[2] + dr[2]), others, min_distance)
        columns.append(((turned[0] - base[0]) / eps, (turned[1] - base[1]) / eps,
                        (turned[2] - base[2]) / eps))
    return ((columns[0][0], columns[1][0], columns[2][0]),
            (columns[0][1], columns[1][1], columns[2][1]),
            (columns[0][2], columns[1][2], columns[2][2]))


@njit(cache=True)
def implicit_torque(tau_M, f_W, r, K, R_WB, I_B, w, previous, h: float):
    """One step's torque on a free magnet body (module docstring).

    Args:
        tau_M, f_W: the field model's torque on the magnet (about its centre) and force.
        r: the lever arm from the body's centre of mass to the magnet's centre (world).
        K: the rotational stiffness (`rotational_stiffness`), rows.
        R_WB, I_B: the body's orientation (rows) and central inertia in its frame (rows).
        w: its angular velocity now, w_n (world).
        previous: [w_{n-1} (3), tau(n-1) about the centre of mass (3)], or None at the
            first step (no tau_other then).
        h: the step (s).
    Every vector a 3-tuple (previous a 6-tuple), every matrix a tuple of rows.
    Returns:
        (tau applied about the magnet's centre, the same about the centre of mass, w_n):
        the last two are the next step's `previous`.
    """
    lever = cross3(r, f_W)
    tau0 = (tau_M[0] + lever[0], tau_M[1] + lever[1], tau_M[2] + lever[2])
    # Its symmetric part, taken implicitly in full while its modes turn the body away
    # slower than 1 / (h sqrt 2) (the mass-weighted eigenvalues below 1 / (2 h^2): backward
    # Euler is accurate on them and I - h^2 S positive definite); else only its restoring
    # part (the body turned against the field: `restoring_part`).
    s01, s02, s12 = (0.5 * (K[0][1] + K[1][0]), 0.5 * (K[0][2] + K[2][0]),
                     0.5 * (K[1][2] + K[2][1]))
    S = ((K[0][0], s01, s02), (s01, K[1][1], s12), (s02, s12, K[2][2]))
    I_W = rotate_symmetric(R_WB, I_B)
    hh2 = 2.0 * h * h
    if cholesky3(minus_scaled(I_W, hh2, S)) is None:
        S = restoring_part(S, I_W)
    other = (0.0, 0.0, 0.0)
    if previous is not None:
        I_dw = mat_vec(I_W, ((w[0] - previous[0]) / h, (w[1] - previous[1]) / h,
                             (w[2] - previous[2]) / h))
        other = (I_dw[0] - previous[3], I_dw[1] - previous[4], I_dw[2] - previous[5])
    S_w = mat_vec(S, w)
    rhs = (h * (tau0[0] + h * S_w[0] + other[0]), h * (tau0[1] + h * S_w[1] + other[1]),
           h * (tau0[2] + h * S_w[2] + other[2]))
    L = cholesky3(minus_scaled(I_W, h * h, S))
    if L is None:   # (not reached: S as chosen above keeps I - h^2 S positive definite)
        return tau_M, tau0, w
    dw_hat = solve_spd3(L, rhs)
    S_w_hat = mat_vec(S, (w[0] + dw_hat[0], w[1] + dw_hat[1], w[2] + dw_hat[2]))
    c = (h * S_w_hat[0], h * S_w_hat[1], h * S_w_hat[2])
    return ((tau_M[0] + c[0], tau_M[1] + c[1], tau_M[2] + c[2]),
            (tau0[0] + c[0], tau0[1] + c[1], tau0[2] + c[2]), w)
