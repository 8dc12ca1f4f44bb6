"""Lumen ground truth: the centerline point ahead, projected through a lens."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix

from capsule_drake.anatomy import load_colon
from capsule_drake.capsule.model import start_pose
from capsule_drake.perception.lumen_truth import LumenTruth, lumen_target
from capsule_drake.scenario import Scenario


class IdealPinhole:
    """A distortion-free pinhole, 256 px, 90 degrees: an independent, closed-form lens."""

    width = height = 256
    f = 128.0

    def project(self, rays):
        rays = np.asarray(rays, dtype=float)
        z = rays[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = np.column_stack([self.f * rays[:, 0] / z + 127.5,
                                      self.f * rays[:, 1] / z + 127.5])
        inside = (pixels >= -0.5).all(axis=1) & (pixels <= 255.5).all(axis=1)
        return pixels, (z > 1e-9) & inside


def state_of(X_WB: RigidTransform) -> np.ndarray:
    q = X_WB.rotation().ToQuaternion()
    return np.concatenate([[q.w(), q.x(), q.y(), q.z()], X_WB.translation(), np.zeros(6)])


@pytest.fixture(scope="module")
def colon():
    colon, _ = load_colon(Scenario().colon)
    return colon


def truth_for(colon, X_WB, lookahead=0.03):
    system = LumenTruth(colon, IdealPinhole(), RigidTransform(), lookahead=lookahead)
    context = system.CreateDefaultContext()
    system.get_input_port(0).FixValue(context, state_of(X_WB))
    return (system.GetOutputPort("lumen_pixel").Eval(context),
            system.GetOutputPort("lumen_visible").Eval(context)[0],
            system.GetOutputPort("lumen_point_W").Eval(context))


def test_target_is_ahead_in_the_direction_the_camera_looks(colon):
    X = start_pose(colon, 0.4)
    z = X.rotation().col(2)
    point, s = lumen_target(colon, X.translation(), z, 0.05)
    assert s == pytest.approx(0.45, abs=2e-3)
    point, s = lumen_target(colon, X.translation(), -z, 0.05)
    assert s == pytest.approx(0.35, abs=2e-3)


def test_lumen_projects_where_a_pinhole_puts_it(colon):
    X_WB = start_pose(colon, 0.4)
    pixel, visible, point = truth_for(colon, X_WB)
    # Closed form: the target in the camera frame, through f x / z + c.
    p_C = X_WB.inverse().multiply(point[:3])
    expected = 128.0 * p_C[:2] / p_C[2] + 127.5
    np.testing.assert_allclose(pixel, expected, atol=1e-6)
    assert visible == 1.0
    # Down a colon that bends gently over 3 cm, the lumen is near the image centre.
    assert np.linalg.norm(pixel - 127.5) < 100


def test_lumen_behind_the_camera_or_outside_the_view_is_not_visible(colon):
    X_WB = start_pose(colon, 0.4)
    # Turned to look at the wall (90 degrees about its x axis), the 90-degree pinhole
    # cannot see a point that lies along the colon.
    side = X_WB.multiply(RigidTransform(RotationMatrix(RollPitchYaw(np.pi / 2, 0, 0)), [0, 0, 0]))
    _, visible, _ = truth_for(colon, side)
    assert visible == 0.0
