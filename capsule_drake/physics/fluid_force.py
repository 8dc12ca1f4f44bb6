"""Buoyancy and drag on the capsule where it lies in residual fluid (`colon.lumen`).

The capsule (a cylinder of length `length` with hemispherical domes of its radius R, along
+z of its body B) is cut into slices across its axis. A slice at axial position x has the
radius rho(x) of the shape there; its disc is tilted as the axis is, so the level cuts it
along a chord, and the part below is a circular segment:

    A(x) = rho^2 [acos(-h) + h sqrt(1 - h^2)],  h = clip((level - z(x)) / (rho sin phi), -1, 1)

(phi the angle between the axis and the vertical; a horizontal disc is in or out whole).
The submerged volume V = sum A dx; the buoyancy rho_f g V acts upward at the submerged
segments' centroid. Drag (quadratic, C_d = 1 on the capsule's side area 2 R L, U) opposes the
capsule's velocity in proportion to the submerged share of its volume. The level is that of
the pool (anatomy/fluid.py) whose stretch of centreline passes nearest the capsule, within
the lumen's widest radius.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialForce, SpatialVelocity
from pydrake.multibody.plant import ExternallyAppliedSpatialForce
from pydrake.systems.framework import LeafSystem

from capsule_drake.anatomy.fluid import FLUID_DENSITY
from capsule_drake.lifetime import weak_method

SLICES = 24
"""Slices across the capsule's axis."""
DRAG_COEFFICIENT = 1.0
"""Quadratic drag coefficient of the capsule moving sideways through the fluid (U)."""


def capsule_slices(radius: float, length: float, slices: int = SLICES):
    """(x, rho, dx): the slices' axial positions (m, from the centre), their disc radii and
    thickness, for a capsule of `radius` with a cylinder `length` long (midpoint rule)."""
    half = 0.5 * length + radius
    dx = 2.0 * half / slices
    x = -half + dx * (np.arange(slices) + 0.5)
    beyond = np.maximum(np.abs(x) - 0.5 * length, 0.0)
    rho = np.sqrt(np.maximum(radius ** 2 - beyond ** 2, 0.0))
    return x, rho, dx


def submerged(p_WB: np.ndarray, axis_W: np.ndarray, level: float, x, rho, dx):
    """(volume below `level` [m^3], its centre [world, m]) of the capsule with centre p_WB
    and unit axis axis_W, cut into slices (capsule_slices)."""
    centres = p_WB[None, :] + x[:, None] * axis_W[None, :]
    tilt = np.sqrt(max(1.0 - axis_W[2] ** 2, 0.0))       # sin of the angle to the vertical
    reach = rho * tilt
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(reach > 1e-12, (level - centres[:, 2]) / reach,
                     np.where(level > centres[:, 2], 1.0, -1.0))
    h = np.clip(h, -1.0, 1.0)
    angle = np.arccos(-h) + h * np.sqrt(1.0 - h * h)
    area = rho ** 2 * angle
    volume = float(np.sum(area) * dx)
    if volume <= 0.0:
        return 0.0, p_WB.copy()
    # Each segment's centroid lies below its disc's centre, along the disc's steepest
    # ascent u, by 2/3 rho (1 - h^2)^(3/2) / angle (4 rho / 3 pi for a half disc).
    if tilt > 1e-12:
        u = (np.array([0.0, 0.0, 1.0]) - axis_W[2] * axis_W) / tilt
        drop = 2.0 / 3.0 * rho * (1.0 - h * h) ** 1.5 / np.maximum(angle, 1e-12)
        centres = centres - drop[:, None] * u[None, :]
    return volume, (area[:, None] * centres).sum(axis=0) / np.sum(area)


class FluidForce(LeafSystem):
    """Buoyancy and drag of the residual fluid's pools on the capsule (module docstring).

    Input ports: body_poses (list[RigidTransform]), body_spatial_velocities
    (list[SpatialVelocity]) of the plant. Output ports: applied_spatial_force
    (list[ExternallyAppliedSpatialForce], one on the capsule's body), submerged (1: the
    share of the capsule's volume in fluid).
    """

    def __init__(self, body, colon, pools, radius: float, length: float, gravity: float):
        super().__init__()
        self._index = body.index()
        self._pools = [(p.s_min, p.s_max, p.level) for p in pools]
        # Boxes around each pool's stretch of lumen (and the capsule's reach): outside all
        # of them, the capsule is dry without a search for its centreline station.
        reach = radius + 0.5 * length + 0.05
        self._boxes, self._stretches = [], []
        for pool in pools:
            s = np.linspace(pool.s_min, pool.s_max,
                            max(int((pool.s_max - pool.s_min) / 0.002), 2))
            centre = colon.centerline.point_at(s)
            self._boxes.append((centre.min(axis=0) - reach, centre.max(axis=0) + reach))
            self._stretches.append(centre)
        # A capsule nearer to a pool's centreline than the lumen is wide is in that pool.
        self._lumen_reach = float(colon.max_wall_radius(
            np.linspace(0.0, colon.centerline.length, 400)).max())
        self._slices = capsule_slices(radius, length)
        self._volume = float(np.pi * radius ** 2 * length + 4.0 / 3.0 * np.pi * radius ** 3)
        self._side_area = 2.0 * radius * (length + 2.0 * radius)
        self._gravity = gravity
        self._poses = self.DeclareAbstractInputPort(
            "body_poses", AbstractValue.Make([RigidTransform()]))
        self._velocities = self.DeclareAbstractInputPort(
            "body_spatial_velocities", AbstractValue.Make([SpatialVelocity()]))
        self.DeclareAbstractOutputPort(
            "applied_spatial_force", lambda: AbstractValue.Make([ExternallyAppliedSpatialForce()]),
            weak_method(self._calc_force))
        self.DeclareVectorOutputPort("submerged", 1, self._calc_submerged)

    def _state(self, context):
        """(share submerged, buoyancy centre, capsule pose)."""
        X_WB = self._poses.Eval(context)[self._index]
        p = X_WB.translation()
        level, nearest = None, self._lumen_reach
        for (low, high), stretch, (_, _, pool_level) in zip(self._boxes, self._stretches,
                                                           self._pools):
            if np.all(p >= low) and np.all(p <= high):
                d = float(np.sqrt(np.min(np.sum((stretch - p) ** 2, axis=1))))
                if d < nearest:
                    level, nearest = pool_level, d
        if level is None:
            return 0.0, p, X_WB
        axis = X_WB.rotation().matrix()[:, 2]
        volume, centre = submerged(p, axis, level, *self._slices)
        return volume / self._volume, centre, X_WB

    def _calc_submerged(self, context, output):
        output.SetAtIndex(0, self._state(context)[0])

    def _calc_force(self, context, output):
        share, centre, X_WB = self._state(context)
        force = ExternallyAppliedSpatialForce()
        force.body_index = self._index
        if share <= 0.0:
            force.F_Bq_W = SpatialForce(np.zeros(3), np.zeros(3))
            force.p_BoBq_B = np.zeros(3)
            output.set_value([force])
            return
        buoyancy = np.array([0.0, 0.0, FLUID_DENSITY * self._gravity * share * self._volume])
        v = self._velocities.Eval(context)[self._index].translational()
        drag = (-0.5 * FLUID_DENSITY * DRAG_COEFFICIENT * self._side_area * share
                * np.linalg.norm(v) * v)
        force.p_BoBq_B = X_WB.inverse().multiply(centre)
        force.F_Bq_W = SpatialForce(np.zeros(3), buoyancy + drag)
        output.set_value([force])
