"""Where the external magnet (EPM) goes: poses over the colon and the stage trajectory.

Pure functions of the colon's geometry. The EPM always hovers straight above the point it
acts on, outside the abdomen by at least the configured clearance, with its moment turned so
that its field at that point lies along the colon's tangent (docs/sources.md section 1): the dipole
field map B ~ (3 u u^T - I) m inverts as m ~ (3/2 u u^T - I) B, with u the unit vector from
the EPM to the point.

The stage (models/epm_stage.sdf) has joints x, y, z, yaw, pitch; its magnetisation axis is
E's +z, which the joints point along (cos yaw sin pitch, sin yaw sin pitch, cos pitch).
"""

from __future__ import annotations

import functools

import math

import numpy as np
from pydrake.trajectories import PiecewisePolynomial

from capsule_drake.physics.magnetics import MagnetGeometry


def field_aligning_moment_direction(u, h):
    """Unit EPM moment direction whose dipole field at distance u (unit, EPM -> target) is
    parallel to the unit vector h."""
    u = np.asarray(u, dtype=float)
    h = np.asarray(h, dtype=float)
    m = 1.5 * u * (u @ h) - h
    return m / np.linalg.norm(m)


def stage_joint_positions(p_WE, m_hat_W):
    """[x, y, z, yaw, pitch] of the stage that puts the EPM centre at p_WE with its moment
    along m_hat_W."""
    mx, my, mz = m_hat_W
    yaw = np.arctan2(my, mx)
    pitch = np.arctan2(np.hypot(mx, my), mz)
    return np.array([p_WE[0], p_WE[1], p_WE[2], yaw, pitch])


def magnet_vertical_half_extent(m_hat_W, geometry: MagnetGeometry) -> float:
    """Half of the vertical extent of the magnet body when its axis points along m_hat_W."""
    dims = geometry.dimensions
    if geometry.shape == "sphere":
        return 0.5 * dims[0]
    if geometry.shape == "cylinder":
        radius, half_length = 0.5 * dims[0], 0.5 * dims[1]
    else:  # cuboid, bounded by the cylinder around it
        radius, half_length = 0.5 * np.hypot(dims[0], dims[1]), 0.5 * dims[2]
    cos_tilt = abs(m_hat_W[2])
    return half_length * cos_tilt + radius * np.sqrt(max(0.0, 1.0 - cos_tilt**2))


def vertical_half_extents(m_hat_W, geometry: MagnetGeometry) -> np.ndarray:
    """`magnet_vertical_half_extent` of many unit moments (N, 3) at once."""
    m_hat_W = np.asarray(m_hat_W, dtype=float)
    dims = geometry.dimensions
    if geometry.shape == "sphere":
        return np.full(len(m_hat_W), 0.5 * dims[0])
    if geometry.shape == "cylinder":
        radius, half_length = 0.5 * dims[0], 0.5 * dims[1]
    else:
        radius, half_length = 0.5 * np.hypot(dims[0], dims[1]), 0.5 * dims[2]
    cos_tilt = np.abs(m_hat_W[:, 2])
    return half_length * cos_tilt + radius * np.sqrt(np.maximum(0.0, 1.0 - cos_tilt**2))


def extent_turn_slope(geometry: MagnetGeometry) -> float:
    """The most (m/rad) the magnet's vertical half extent changes per radian its moment
    turns: the half diagonal of its cylinder (`magnet_vertical_half_extent` is
    h cos(tilt) + r sin(tilt)); nothing for a sphere."""
    dims = geometry.dimensions
    if geometry.shape == "sphere":
        return 0.0
    if geometry.shape == "cylinder":
        return float(np.hypot(0.5 * dims[0], 0.5 * dims[1]))
    return float(np.hypot(0.5 * np.hypot(dims[0], dims[1]), 0.5 * dims[2]))


def magnet_footprint_radius(geometry: MagnetGeometry) -> float:
    """Radius of a disc that covers the magnet's shadow on the skin in any orientation."""
    dims = geometry.dimensions
    if geometry.shape == "sphere":
        return 0.5 * dims[0]
    if geometry.shape == "cylinder":
        return float(np.hypot(0.5 * dims[0], 0.5 * dims[1]))
    return 0.5 * float(np.linalg.norm(dims))


@functools.lru_cache(maxsize=16)
def disc_samples(radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Offsets of a 9 x 9 grid's points inside a disc of `radius` (cached: the guards call
    `highest_skin_under` hundreds of times a second with the magnet's one radius)."""
    offsets = np.linspace(-radius, radius, 9)
    dx, dy = np.meshgrid(offsets, offsets)
    inside = dx**2 + dy**2 <= radius**2 + 1e-12
    return dx[inside], dy[inside]


def highest_skin_under(abdomen, x: float, y: float, radius: float) -> float:
    """The highest skin point under a disc of `radius` centred at (x, y)."""
    return _highest_skin_under(abdomen, float(x), float(y), float(radius))


@functools.lru_cache(maxsize=64)
def _highest_skin_under(abdomen, x: float, y: float, radius: float) -> float:
    # Cached on the exact arguments: in a teleoperation step the mapping and the arm's
    # guard ask about the same EPM position several times.
    dx, dy = disc_samples(radius)
    return float(np.max(abdomen.skin_height(x + dx, y + dy)))


def epm_pose_over(colon, s: float, clearance: float, geometry: MagnetGeometry):
    """EPM centre and unit moment that act on the centerline point at arc length s.

    Returns (p_WE, m_hat_W, skin_gap) where skin_gap is the distance between the magnet's
    lowest point and the highest skin point under it (>= clearance by construction).
    """
    target = colon.centerline.point_at(s)
    tangent = colon.centerline.tangent_at(s)
    u = np.array([0.0, 0.0, -1.0])  # straight above the target
    m_hat = field_aligning_moment_direction(u, tangent)
    skin = highest_skin_under(colon.abdomen, target[0], target[1], magnet_footprint_radius(geometry))
    z = max(skin, target[2]) + clearance + magnet_vertical_half_extent(m_hat, geometry)
    p_WE = np.array([target[0], target[1], z])
    return p_WE, m_hat


def skin_gap(colon, p_WE, m_hat_W, geometry: MagnetGeometry) -> float:
    """Gap between the magnet's lowest point and the highest skin point under it (m)."""
    skin = highest_skin_under(colon.abdomen, p_WE[0], p_WE[1], magnet_footprint_radius(geometry))
    return float(p_WE[2] - magnet_vertical_half_extent(m_hat_W, geometry) - skin)


def along_colon_trajectory(colon, start_s: float, path, clearance: float,
                           geometry: MagnetGeometry, sample_period: float = 0.05):
    """Stage joint trajectory for an `AlongColon` path.

    The EPM waits over start_s + lead for `settle_time`, then moves along the centerline at
    `speed` until `end_s` (or the cecum), then holds. Returns (trajectory, s_of_t) where
    s_of_t(t) is the centerline arc length the EPM is over at time t.
    """
    s_max = float(colon.centerline.s[-1])
    s0 = float(np.clip(start_s + path.lead, 0.0, s_max))
    s_end = s_max if path.end_s <= 0.0 else float(np.clip(path.end_s, s0, s_max))
    travel_time = (s_end - s0) / path.speed if path.speed > 0 else 0.0
    t_end = path.settle_time + travel_time + 1.0

    def s_of_t(t):
        t = np.asarray(t, dtype=float)
        return np.clip(s0 + path.speed * np.maximum(0.0, t - path.settle_time), s0, s_end)

    times = np.arange(0.0, t_end + sample_period, sample_period)
    q = np.array([stage_joint_positions(*epm_pose_over(colon, s, clearance, geometry))
                  for s in s_of_t(times)])
    q[:, 3] = np.unwrap(q[:, 3])
    trajectory = PiecewisePolynomial.CubicShapePreserving(times, q.T, zero_end_point_derivatives=True)
    return trajectory, s_of_t


def hold_above_trajectory(colon, start_s: float, path, clearance: float,
                          geometry: MagnetGeometry):
    """Constant stage trajectory for a `HoldAbove` path; raises ValueError if the requested
    height would bring the magnet closer to the skin than the clearance."""
    target = colon.centerline.point_at(start_s)
    tangent = colon.centerline.tangent_at(start_s)
    m_hat = field_aligning_moment_direction([0.0, 0.0, -1.0], tangent)
    p_WE = target + np.array([0.0, 0.0, path.height])
    gap = skin_gap(colon, p_WE, m_hat, geometry)
    if gap < clearance:
        raise ValueError(f"epm.driver.height {path.height} m leaves {gap * 1000:.0f} mm between "
                         f"magnet and skin, less than the clearance {clearance * 1000:.0f} mm")
    q = stage_joint_positions(p_WE, m_hat)
    trajectory = PiecewisePolynomial.ZeroOrderHold([0.0, 1.0], np.column_stack([q, q]))
    return trajectory, (lambda t: np.full_like(np.asarray(t, dtype=float), start_s))


def stage_to_pose(q) -> np.ndarray:
    """[p_WE (3), m_hat_W (3)] of the stage's joint positions [x, y, z, yaw, pitch].
    Plain floats: the kinematic stage calls it at every plant step."""
    x, y, z, yaw, pitch = np.asarray(q, dtype=float)[:5].tolist()
    sin_pitch = math.sin(pitch)
    return np.array([x, y, z, math.cos(yaw) * sin_pitch, math.sin(yaw) * sin_pitch,
                     math.cos(pitch)])


def pose_trajectory(stage_trajectory, sample_period: float = 0.05):
    """The EPM pose [p_WE, m_hat_W] along a stage trajectory, as a trajectory (linear
    between samples `sample_period` apart; consumers renormalise the moment direction)."""
    start, end = stage_trajectory.start_time(), stage_trajectory.end_time()
    times = np.arange(start, end + 0.5 * sample_period, sample_period)
    if len(times) < 2:
        times = np.array([start, start + 1.0])
    poses = np.column_stack([stage_to_pose(stage_trajectory.value(t).ravel()) for t in times])
    return PiecewisePolynomial.FirstOrderHold(times, poses)
