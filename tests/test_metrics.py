"""Run metrics against geometry whose answer is known in closed form."""

import numpy as np
import pytest
from pydrake.math import RollPitchYaw, RotationMatrix

from capsule_drake.anatomy import load_colon
from capsule_drake.capsule.model import start_pose
from capsule_drake.io.metrics import capsule_surface_points_C, wall_excursion
from capsule_drake.scenario import Scenario

RADIUS, LENGTH = 0.0058, 0.0199


class _StraightTube:
    """A straight lumen of radius 15 mm along world y: excursion = distance from axis - 15 mm."""

    @staticmethod
    def excursion(points):
        return np.hypot(points[:, 0], points[:, 2]) - 0.015


def test_surface_points_lie_on_the_capsule():
    points = capsule_surface_points_C(RADIUS, LENGTH)
    z = np.clip(points[:, 2], -LENGTH / 2, LENGTH / 2)
    # Distance from the capsule's axis segment is the radius for every point.
    distance = np.linalg.norm(points - np.column_stack([0 * z, 0 * z, z]), axis=1)
    np.testing.assert_allclose(distance, RADIUS, atol=1e-12)
    assert points[:, 2].max() == pytest.approx(LENGTH / 2 + RADIUS)


def test_excursion_of_a_capsule_pushed_into_a_straight_tube():
    points = capsule_surface_points_C(RADIUS, LENGTH)
    R = RotationMatrix(RollPitchYaw(-np.pi / 2, 0, 0)).matrix()  # capsule axis along +y
    tube = _StraightTube()
    for depth in (-0.004, 0.0, 0.002):
        p = np.array([0.015 - RADIUS + depth, 0.3, 0.0])
        assert wall_excursion(tube, R[None], p[None], points)[0] == pytest.approx(depth, abs=1e-9)
    # Tilted by 10 degrees about x, a cap end reaches further: the closed form is
    # (L/2) sin(10 deg) + r - (15 mm - offset) along z.
    R_tilt = RotationMatrix(RollPitchYaw(-np.pi / 2 + np.radians(10), 0, 0)).matrix()
    expected = LENGTH / 2 * np.sin(np.radians(10)) + RADIUS - 0.015
    got = wall_excursion(tube, R_tilt[None], np.zeros((1, 3)), points)[0]
    assert got == pytest.approx(expected, abs=1e-4)  # the ring sampling costs < 0.1 mm


def test_sampled_excursion_matches_a_dense_surface_sampling():
    # In the real colon, the sampled surface points find the capsule's largest excursion
    # as well as 20,000 random points on its surface do, within 0.3 mm.
    colon, _ = load_colon(Scenario().colon)
    rng = np.random.default_rng(3)
    angle = rng.uniform(0, 2 * np.pi, 10000)
    cylinder = np.column_stack([RADIUS * np.cos(angle), RADIUS * np.sin(angle),
                                rng.uniform(-LENGTH / 2, LENGTH / 2, 10000)])
    caps = rng.normal(size=(10000, 3))
    caps = RADIUS * caps / np.linalg.norm(caps, axis=1, keepdims=True)
    caps[:, 2] += np.sign(caps[:, 2]) * LENGTH / 2
    dense = np.vstack([cylinder, caps])
    for s in (0.3, 0.8, 1.2):
        X = start_pose(colon, s)
        R = X.rotation().matrix()
        side = R[:, 0]
        p = X.translation() + side * 0.01  # pressed toward the wall
        coarse = wall_excursion(colon, R[None], p[None], capsule_surface_points_C(RADIUS, LENGTH))
        fine = wall_excursion(colon, R[None], p[None], dense)
        assert coarse[0] == pytest.approx(fine[0], abs=1.5e-4)
