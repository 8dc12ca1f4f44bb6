"""The EPM's path: its field at the target lies along the colon, and it keeps its clearance."""

import numpy as np
import pytest

from capsule_drake.epm.poses import (
    along_colon_trajectory,
    epm_pose_over,
    field_aligning_moment_direction,
    hold_above_trajectory,
    magnet_vertical_half_extent,
    skin_gap,
    stage_joint_positions,
)
from capsule_drake.physics.magnetics import MagnetGeometry, dipole_field
from capsule_drake.scenario import AlongColon, HoldAbove


class _Abdomen:
    """A skin dome: 0.22 m at the origin, falling off quadratically."""

    def skin_height(self, x, y):
        return 0.22 - 1.5 * np.asarray(x) ** 2 - 0.5 * np.asarray(y) ** 2


class _Centerline:
    """A helix-like course 10-12 cm under the skin, for testing without a colon mesh."""

    def __init__(self):
        self.s = np.linspace(0.0, 0.6, 601)

    def point_at(self, s):
        return np.array([0.1 * np.sin(3 * s), s - 0.3, 0.10 + 0.02 * np.cos(5 * s)])

    def tangent_at(self, s):
        d = np.array([0.3 * np.cos(3 * s), 1.0, -0.1 * np.sin(5 * s)])
        return d / np.linalg.norm(d)


class _Colon:
    centerline = _Centerline()
    abdomen = _Abdomen()


def test_field_aligning_moment_points_field_along_heading():
    rng = np.random.default_rng(1)
    for _ in range(50):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        h = rng.normal(size=3)
        h /= np.linalg.norm(h)
        m = field_aligning_moment_direction(u, h)
        B = dipole_field(970.0 * m, 0.15 * u)  # independent route: the dipole field itself
        np.testing.assert_allclose(B / np.linalg.norm(B), h, atol=1e-9)


def test_stage_joints_reproduce_moment_direction():
    rng = np.random.default_rng(2)
    for _ in range(20):
        m = rng.normal(size=3)
        m /= np.linalg.norm(m)
        _, _, _, yaw, pitch = stage_joint_positions([0, 0, 0], m)
        # Rz(yaw) Ry(pitch) e_z, the stage's kinematics.
        direction = [np.cos(yaw) * np.sin(pitch), np.sin(yaw) * np.sin(pitch), np.cos(pitch)]
        np.testing.assert_allclose(direction, m, atol=1e-12)


def test_vertical_half_extent_of_cylinder():
    geometry = MagnetGeometry(dimensions=[0.1, 0.06])
    assert magnet_vertical_half_extent([0, 0, 1], geometry) == pytest.approx(0.03)
    assert magnet_vertical_half_extent([1, 0, 0], geometry) == pytest.approx(0.05)


def test_pose_over_centerline_keeps_clearance_and_aligns_field():
    colon = _Colon()
    geometry = MagnetGeometry()
    for s in np.linspace(0.0, 0.6, 13):
        p_WE, m_hat = epm_pose_over(colon, s, 0.02, geometry)
        assert skin_gap(colon, p_WE, m_hat, geometry) >= 0.02 - 1e-9
        target = colon.centerline.point_at(s)
        B = dipole_field(970.0 * m_hat, target - p_WE)
        np.testing.assert_allclose(B / np.linalg.norm(B), colon.centerline.tangent_at(s), atol=1e-9)


def test_along_colon_trajectory_moves_at_speed_and_keeps_clearance():
    colon = _Colon()
    geometry = MagnetGeometry()
    path = AlongColon(settle_time=1.0, speed=0.02, lead=0.0, end_s=0.4)
    trajectory, s_of_t = along_colon_trajectory(colon, 0.05, path, 0.02, geometry)
    assert s_of_t(0.5) == pytest.approx(0.05)
    assert s_of_t(3.0) == pytest.approx(0.05 + 0.04)
    assert s_of_t(1000.0) == pytest.approx(0.4)
    for t in np.linspace(0.0, trajectory.end_time(), 200):
        q = trajectory.value(t).ravel()
        m = [np.cos(q[3]) * np.sin(q[4]), np.sin(q[3]) * np.sin(q[4]), np.cos(q[4])]
        # The spline between samples must not dip below the clearance by more than 1 mm.
        assert skin_gap(colon, q[:3], m, geometry) > 0.02 - 1e-3


def test_hold_above_refuses_to_breach_clearance():
    colon = _Colon()
    with pytest.raises(ValueError, match="clearance"):
        hold_above_trajectory(colon, 0.1, HoldAbove(height=0.1), 0.02, MagnetGeometry())
    trajectory, _ = hold_above_trajectory(colon, 0.1, HoldAbove(height=0.5), 0.02, MagnetGeometry())
    np.testing.assert_allclose(trajectory.value(0.0)[:3].ravel(),
                               colon.centerline.point_at(0.1) + [0, 0, 0.5])
