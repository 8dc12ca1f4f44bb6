"""The capsule as every block sees it: its body, frames, size and mass, read once from
models/capsule.sdf, and the frame convention of the whole package.

Frames (one letter each, everywhere: code, ports, SDF comments, docs/diagram.md):
    W  world: x to the patient's left, y to the head, z anterior (up; the patient lies
       supine on the table, whose top is z = 0)
    B  the capsule body: origin at its geometric centre, +z along its axis toward the dome
    C  the capsule camera: its lens inside the front dome, 3.25 mm behind the apex (so tissue
       on the dome stays beyond the renderer's near plane), Drake's camera convention
       (+z forward along
       the optical axis, +x right, +y down in the image)
    M  the capsule's internal permanent magnet (IPM): its centre, magnetised along +z
    S  a sensor on the capsule's board (IMU, magnetometer), its pose X_BS in its config
    E  the external permanent magnet (EPM): its centre, magnetised along +z
    D  the haptic device: x right, y up, z toward the operator
Monogram notation as Drake's: X_AB is frame B's pose in A, p_AB the position of B's origin
from A's, R_AB the rotation, F_W a force expressed in W. A capsule state is
[q_WB (w, x, y, z), p_WB, w_WB, v_WB] (13).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.geometry import Capsule
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.blocks import checked, need
from capsule_drake.models import configure_parser, model_url

CAPSULE_BODY = "capsule"
"""Name of the capsule's body (and model instance) in the plant."""


@dataclasses.dataclass(frozen=True)
class CapsuleModel:
    """What models/capsule.sdf says of the capsule, read once (`capsule_model()`)."""

    X_BC: RigidTransform   # the camera in the body
    X_BM: RigidTransform   # the internal magnet in the body (its axis: +z of M)
    radius: float          # of the collision capsule (m)
    length: float          # of its cylinder, along +z of B (m)
    mass: float            # kg

    @property
    def half_length(self) -> float:
        """From the centre to the tip of either dome (m)."""
        return 0.5 * self.length + self.radius


@functools.cache
def capsule_model() -> CapsuleModel:
    """The capsule's frames, size and mass from models/capsule.sdf (parsed once)."""
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(MultibodyPlantConfig(time_step=0.0), builder)
    instance, = configure_parser(Parser(plant)).AddModels(url=model_url("capsule.sdf"))
    body = plant.GetBodyByName(CAPSULE_BODY, instance)
    inspector = scene_graph.model_inspector()
    shapes = [inspector.GetShape(g) for g in plant.GetCollisionGeometriesForBody(body)]
    shell = next((s for s in shapes if isinstance(s, Capsule)), None)
    if shell is None:
        raise RuntimeError("models/capsule.sdf has no capsule collision shape")
    return CapsuleModel(
        X_BC=plant.GetFrameByName("camera", instance).GetFixedPoseInBodyFrame(),
        X_BM=plant.GetFrameByName("ipm", instance).GetFixedPoseInBodyFrame(),
        radius=shell.radius(), length=shell.length(), mass=body.default_mass())


def start_pose(colon, s: float) -> RigidTransform:
    """X_WB of a capsule on the centreline at arc length s, its axis (camera forward) down
    the lumen."""
    p = colon.centerline.point_at(s)
    z = colon.centerline.tangent_at(s)
    x = np.cross([0.0, 0.0, 1.0], z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return RigidTransform(RotationMatrix(np.column_stack([x, y, z])), p)


def rotation_from_quaternion(q_wxyz) -> np.ndarray:
    """R (3 x 3) of a quaternion [w, x, y, z], normalised first (a logged or estimated one
    drifts off the unit sphere)."""
    q = np.asarray(q_wxyz, dtype=float)
    return Quaternion(q / np.linalg.norm(q)).rotation()


def check_board_sensor(config, key: str, check_config) -> None:
    """The check of a sampled sensor on the capsule's board (`key`, e.g. capsule.imu): a
    rate above 0 (said so first), its own fields (`check_config`), its frame inside the
    capsule. Raises ScenarioError (one line)."""
    need(config.sample_rate > 0, f"{key}.sample_rate must be > 0, got {config.sample_rate}")
    checked(f"{key}.", check_config, config)
    checked("", check_inside_capsule, config.p_BS, f"{key}.p_BS")


def check_inside_capsule(p_BS, key: str) -> None:
    """Raises ValueError unless the point p_BS (capsule frame B, m) lies inside the capsule:
    where a sensor's `key` puts it."""
    model = capsule_model()
    if not (math.hypot(p_BS[0], p_BS[1]) <= model.radius and abs(p_BS[2]) <= model.half_length):
        raise ValueError(f"{key} must lie inside the capsule (radius "
                         f"{1000 * model.radius:.1f} mm, |z| <= "
                         f"{1000 * model.half_length:.2f} mm), got {p_BS}")
