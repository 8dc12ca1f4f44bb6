"""The compliant wall as an elastic foundation under the capsule, computed here
(`FoundationContact`): the default realisation of `CompliantWall` (its `realisation`
"foundation"; "hydroelastic" gives the same wall to Drake's hydroelastic contact instead).

Why not Drake's hydroelastic contact. A wall that yields by millimetres wraps a large patch
of the capsule: Drake cuts it into 100-500 polygons (the wall's triangles against the
capsule field's tetrahedra), each a contact of its own for the solver, and the Default run
goes at 0.65x real time where the rigid stand-in goes at 2.15x (benchmarks/bench_realtime.py).
Coarser meshes are cheaper but miss the foundation's closed form by 10-25 % at the shallow
indentations runs reach. Here the same mechanics are integrated directly, at a cost that does
not grow with the patch.

The wall. The colon is a tube around its centreline: at arc length s and angle theta its
mucosa lies `colon.wall_radius(s, theta)` from the centreline (the haustral folds and taenia
in it; an imported colon's table). That radius is tabulated once per colon
(`WallTable`: every 0.5 mm along, 128 angles, with its two slopes), and a point's depth
beyond the mucosa is read from it: the point's station on the centreline, its distance rho
from it, and e = rho - R(s, theta) along the radius, converted to the depth along the wall's
normal (the surface rho = R(s, theta) has normal e_rho - R_s e_s - R_theta / R e_theta).

The force. The wall is a Winkler foundation of modulus k (Pa/m, compliant.foundation_modulus):
where the capsule's surface lies a depth d beyond the mucosa, the wall pushes on it with the
pressure k d along the wall's normal, over the wall's area under that patch of capsule. The
force is k times the volume of capsule beyond the undeformed mucosa; for a flat wall it has
the closed form `compliant.indentation_force` (the volume of a cylinder's segment and a
sphere's cap), which the quadrature here matches within 2 % from 0.2 mm of indentation
(tests/test_contact_models.py). The capsule's surface is cut into cells (`capsule_probes`:
64 around, 12 along the cylinder, 8 rings on each dome), each pressing with its depth at its
centre on its area projected onto the wall. Only the cells that face the wall push (a deeper
capsule displaces the volume between the mucosa and its near surface). Hunt and Crossley's
dissipation scales the pressure by (1 + c d') as in Drake's contact.

Friction: a brush. Each cell in contact carries a bristle: its deflection z grows with the
cell's slip over the wall, the wall pulls it back with k_t z per area, and where that would
exceed mu times the cell's pressure the bristle slips (z held at the limit). This is
Coulomb's law with stiction (the brush model of rolling tyres), and rolling resistance and
spin about the normal come with it. The bristles' stiffness is the stiction's
regularisation, as Drake's solver regularises its own: the patch's total tangential
stiffness is set so that the capsule's lightest tangential mode (its mass with its roll
about its axis, `tangential_mass`) turns by half a radian per step, and damped at 0.7 of
critical. At the default 2 ms step a capsule pressed with 1 N creeps 0.36 mm before it
slides.

Forces are explicit: computed at the start of each plant step from the capsule's state, as
the magnet's. physics/step_bound.py keeps the wall's stiffest normal mode (the capsule half
buried, `contact_stiffness_bound`) within omega dt <= 1.

What it leaves out: the diverticula (pouches cut into the wall mesh: the foundation sees the
wall without them); polyps and the boxes closing the tube's ends keep Drake's hydroelastic
contact with the capsule's field mesh (compliant.py). The wall is taken as undeformed
elsewhere: a capsule's dent does not move the wall beside it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from pydrake.common.value import AbstractValue
from scipy.spatial import cKDTree
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import ExternallyAppliedSpatialForce
from pydrake.systems.framework import LeafSystem

from capsule_drake.lifetime import weak_method

TABLE_STEP = 0.5e-3
"""Spacing (m) of the wall's table along the centreline: a haustral fold (a few mm wide, up
to ~5 mm high) is read within ~20 micrometres by bilinear interpolation."""
TABLE_AROUND = 128
"""Angles of the wall's table around the centreline (2.8 degrees: 1.2 mm at a 25 mm radius)."""
PROBES_AROUND = 40
PROBES_ALONG = 6
PROBES_CAP_RINGS = 5
"""The capsule's surface cells (`capsule_probes`)."""
REFINEMENTS = 1
"""Steps of each point's station from the capsule's (module docstring): one, then its own."""
TANGENTIAL_TURN = 0.5
"""The bristles' stiffness: the capsule's lightest tangential mode turns by this many radians
per step (omega dt)."""
TANGENTIAL_DAMPING_RATIO = 0.7


class WallTable:
    """The colon's wall radius around its centreline, tabulated (module docstring), and the
    depth of points beyond it (`depth`)."""

    def __init__(self, colon, step: float = TABLE_STEP, around: int = TABLE_AROUND):
        centerline = colon.centerline
        length = float(centerline.length)
        self.step = step
        self.count = int(math.floor(length / step)) + 1
        self.s = np.arange(self.count) * step
        self.points = centerline.point_at(self.s)
        self.tangents, self.normals, self.binormals = centerline.frame_at(self.s)
        self.around = around
        self.dtheta = 2.0 * math.pi / around
        theta = np.arange(around) * self.dtheta
        radius = colon.wall_radius(self.s[:, None], theta[None, :])
        slope_s = np.gradient(radius, step, axis=0)
        slope_theta = (np.roll(radius, -1, axis=1) - np.roll(radius, 1, axis=1)) / (
            2.0 * self.dtheta)
        table = np.stack([radius, slope_s, slope_theta], axis=-1)
        # Flattened (S (K + 1), 3): the angle wraps, so each row's last entry repeats its first.
        self.flat = np.concatenate([table, table[:, :1]], axis=1).reshape(-1, 3)
        # (S, 4, 3): each station's point, tangent, normal and binormal.
        self.frames = np.stack([self.points, self.tangents, self.normals, self.binormals],
                               axis=1)
        # The tangent's rate of turn dT/ds (1/m): a Newton step to a point's foot divides its
        # offset along the tangent by 1 - (offset . dT/ds).
        self.bends = np.gradient(self.tangents, step, axis=0)
        self._tree = cKDTree(self.points)
        self._corners = np.array([0, 1, around + 1, around + 2])

    def nearest(self, p) -> int:
        """The table's station nearest the point p (3,)."""
        return int(self._tree.query(p)[1])

    def depth(self, points, station: int):
        """For world points (N, 3) near the station `station` (a table index near them):
        (depth along the wall's normal beyond the mucosa (N,; negative inside the lumen),
        the wall's inward unit normal (N, 3)), in m."""
        frames, step = self.frames, self.step
        last = self.count - 1
        # The station of each point: from the nearest station's frame, then once from its own.
        offset = points - frames[station, 0]
        along = (offset @ frames[station, 1]) / (1.0 - offset @ self.bends[station])
        j = np.clip(station + np.rint(along / step).astype(np.intp), 0, last)
        for _ in range(REFINEMENTS):
            frame = frames[j]
            offset = points - frame[:, 0]
            along = (np.einsum("ij,ij->i", offset, frame[:, 1])
                     / (1.0 - np.einsum("ij,ij->i", offset, self.bends[j])))
            j = np.clip(j + np.rint(along / step).astype(np.intp), 0, last)
        frame = frames[j]
        local = np.einsum("nij,nj->ni", frame[:, 1:], points - frame[:, 0])
        along, x, y = local[:, 0], local[:, 1], local[:, 2]
        rho = np.hypot(x, y)
        # Bilinear in (s, theta) over the flattened table.
        u = np.clip(j + along / step, 0.0, last - 1e-6)
        ju = u.astype(np.intp)
        fu = u - ju
        v = (np.arctan2(y, x) % (2.0 * math.pi)) / self.dtheta
        kv = np.minimum(v.astype(np.intp), self.around - 1)
        fv = v - kv
        i00 = ju * (self.around + 1) + kv
        gu, gv = 1.0 - fu, 1.0 - fv
        weights = np.stack([gu * gv, gu * fv, fu * gv, fu * fv])
        corners = self.flat[i00[None, :] + self._corners[:, None]]
        radius, slope_s, slope_theta = np.einsum("cn,cnk->kn", weights, corners)
        # The outward normal e_rho - R_s e_s - R_theta / R e_theta, in the frame (T, N, B).
        inv = 1.0 / np.maximum(rho, 1e-9)
        cx, cy = x * inv, y * inv
        tilt = slope_theta / np.maximum(radius, 1e-9)
        norm = np.sqrt(1.0 + slope_s * slope_s + tilt * tilt)
        outward = np.stack([-slope_s, cx + tilt * cy, cy - tilt * cx], axis=1)
        inward = -np.einsum("nji,nj->ni", frame[:, 1:], outward) / norm[:, None]
        return (rho - radius) / norm, inward


def capsule_probes(radius: float, length: float, around: int = PROBES_AROUND,
                   along: int = PROBES_ALONG, cap_rings: int = PROBES_CAP_RINGS):
    """The capsule's surface cut into cells (midpoint rule): (centres (N, 3), outward unit
    normals (N, 3), areas (N,)) in the frame of a capsule along z centred at the origin,
    its cylinder from -length/2 to +length/2. The domes' rings have fewer cells toward the
    poles (in proportion to their circumference)."""
    def ring(count, beta_lo, beta_hi, side, offset):
        dphi = 2.0 * math.pi / count
        phi = (np.arange(count) + 0.5) * dphi
        beta = 0.5 * (beta_lo + beta_hi)
        normal = np.stack([math.cos(beta) * np.cos(phi), math.cos(beta) * np.sin(phi),
                           np.full(count, side * math.sin(beta))], axis=1)
        area = radius**2 * (math.sin(beta_hi) - math.sin(beta_lo)) * dphi
        return radius * normal + np.array([0.0, 0.0, offset]), normal, np.full(count, area)

    dphi = 2.0 * math.pi / around
    phi = (np.arange(around) + 0.5) * dphi
    dz = length / along
    z = -0.5 * length + (np.arange(along) + 0.5) * dz
    normal = np.stack([np.tile(np.cos(phi), along), np.tile(np.sin(phi), along),
                       np.zeros(along * around)], axis=1)
    centres = [radius * normal + np.stack([np.zeros_like(normal[:, 0]),
                                           np.zeros_like(normal[:, 0]),
                                           np.repeat(z, around)], axis=1)]
    normals, areas = [normal], [np.full(along * around, radius * dphi * dz)]
    dbeta = 0.5 * math.pi / cap_rings
    for side in (1.0, -1.0):
        for n in range(cap_rings):
            lo, hi = n * dbeta, (n + 1) * dbeta
            count = max(6, int(round(around * math.cos(0.5 * (lo + hi)))))
            c, nn, a = ring(count, lo, hi, side, side * 0.5 * length)
            centres.append(c)
            normals.append(nn)
            areas.append(a)
    return np.concatenate(centres), np.concatenate(normals), np.concatenate(areas)


def tangential_mass(mass: float, radius: float, axial_inertia: float) -> float:
    """The capsule's lightest effective mass (kg) at its surface for a tangential push:
    across its axis, where the push also rolls it, 1 / (1 / m + r^2 / I_axial)."""
    return 1.0 / (1.0 / mass + radius**2 / axial_inertia)


def contact_stiffness_bound(k: float, radius: float, length: float) -> float:
    """The wall's normal stiffness (N/m) against a capsule half buried (its axis on the
    mucosa), the stiffest the foundation is over the indentations it takes:
    d/d depth of k (volume beyond the wall) = k (2 r L + pi r^2)."""
    return k * (2.0 * radius * length + math.pi * radius**2)


@dataclasses.dataclass
class WallContact:
    """The foundation's contact at one instant, for the monitors and logs: the net force and
    torque on the capsule (world; torque about its body origin), and each pressed cell's
    centre (world), wall area (m^2), pressure (Pa) and the wall's inward normal."""

    force_W: np.ndarray
    torque_W: np.ndarray
    points_W: np.ndarray
    areas: np.ndarray
    pressures: np.ndarray
    normals_W: np.ndarray


def _empty_contact() -> WallContact:
    return WallContact(np.zeros(3), np.zeros(3), np.zeros((0, 3)), np.zeros(0), np.zeros(0),
                       np.zeros((0, 3)))


class FoundationContact(LeafSystem):
    """The compliant wall's force on the capsule (module docstring).

    Input port: capsule_state ([q_WB (wxyz), p_WB, w_WB, v_WB], 13). Output ports:
    applied_spatial_force (list[ExternallyAppliedSpatialForce], on the capsule's body at
    its origin), wall_contact (WallContact). State: each surface cell's bristle deflection
    (world, m), updated every plant step.
    """

    def __init__(self, body_index, table: WallTable, X_BG, radius: float, length: float,
                 foundation_modulus: float, friction: float, dissipation: float,
                 time_step: float, mass: float, axial_inertia: float):
        super().__init__()
        self._index = body_index
        self._table = table
        centres, normals, areas = capsule_probes(radius, length)
        R_BG, p_BG = X_BG.rotation().matrix(), X_BG.translation()
        self._p_B = centres @ R_BG.T + p_BG
        self._n_B = normals @ R_BG.T
        self._areas = areas
        self._count = len(areas)
        self._k = foundation_modulus
        self._mu = friction
        self._dissipation = dissipation
        self._dt = time_step
        m_t = tangential_mass(mass, radius, axial_inertia)
        omega = TANGENTIAL_TURN / time_step
        self._tangential_stiffness = omega**2 * m_t                         # N/m, whole patch
        self._tangential_damping = 2.0 * TANGENTIAL_DAMPING_RATIO * omega * m_t  # N s/m
        self._state_port = self.DeclareVectorInputPort("capsule_state", 13)
        self._bristles = self.DeclareDiscreteState(3 * self._count)
        self.DeclarePeriodicDiscreteUpdateEvent(time_step, 0.0, weak_method(self._update))
        ticket = {self.input_port_ticket(self._state_port.get_index()),
                  self.discrete_state_ticket(self._bristles)}
        self._force_port = self.DeclareAbstractOutputPort(
            "applied_spatial_force", lambda: AbstractValue.Make([ExternallyAppliedSpatialForce()]),
            weak_method(self._calc_force), prerequisites_of_calc=ticket)
        self._contact_port = self.DeclareAbstractOutputPort(
            "wall_contact", lambda: AbstractValue.Make(_empty_contact()),
            weak_method(self._calc_wall_contact), prerequisites_of_calc=ticket)
        self._memo = (None, None)

    def _geometry(self, x):
        """The pressed cells at the capsule state x: a dict of their indices, centres'
        offsets from the body origin (world), depths, wall normals, wall areas and velocities
        (computed once per state: the plant's step and this system's update read it)."""
        key = x.tobytes()
        if self._memo[0] == key:
            return self._memo[1]
        R = _rotation(*x[0:4])
        p_WB, w_W, v_W = x[4:7], x[7:10], x[10:13]
        table = self._table
        offsets = self._p_B @ R.T
        points = offsets + p_WB
        depth, inward = table.depth(points, table.nearest(p_WB))
        facing = -np.einsum("ij,ij->i", self._n_B @ R.T, inward)
        pressed = np.flatnonzero((depth > 0.0) & (facing > 0.0))
        r = offsets[pressed]
        nu = inward[pressed]
        w = w_W
        velocity = v_W + np.stack([w[1] * r[:, 2] - w[2] * r[:, 1],
                                   w[2] * r[:, 0] - w[0] * r[:, 2],
                                   w[0] * r[:, 1] - w[1] * r[:, 0]], axis=1)
        into = -np.einsum("ij,ij->i", velocity, nu)
        area = self._areas[pressed] * facing[pressed]
        pressure = self._k * depth[pressed] * np.maximum(1.0 + self._dissipation * into, 0.0)
        geometry = {"pressed": pressed, "offsets": r, "points": points[pressed],
                    "normals": nu, "areas": area, "pressures": pressure,
                    "slip": velocity + into[:, None] * nu,      # the tangential part
                    "share": area / max(float(np.sum(area)), 1e-300),
                    "limit": self._mu * pressure * area}
        self._memo = (key, geometry)
        return geometry

    def _bristles_of(self, context, g):
        """The pressed cells' bristles, in their wall's tangent plane."""
        z = context.get_discrete_state(self._bristles).value().reshape(-1, 3)[g["pressed"]]
        return z - np.einsum("ij,ij->i", z, g["normals"])[:, None] * g["normals"]

    def _solve(self, context):
        """(the wall's geometry at this state, the net force and torque about the body
        origin, world)."""
        g = self._geometry(self._state_port.Eval(context))
        if len(g["pressed"]) == 0:
            return g, np.zeros(3), np.zeros(3)
        tangential = -(self._tangential_stiffness * self._bristles_of(context, g)
                       + self._tangential_damping * g["slip"]) * g["share"][:, None]
        size = np.linalg.norm(tangential, axis=1)
        over = size > g["limit"]
        if np.any(over):
            tangential[over] *= (g["limit"][over] / size[over])[:, None]
        forces = (g["pressures"] * g["areas"])[:, None] * g["normals"] + tangential
        r = g["offsets"]
        torque = np.stack([r[:, 1] * forces[:, 2] - r[:, 2] * forces[:, 1],
                           r[:, 2] * forces[:, 0] - r[:, 0] * forces[:, 2],
                           r[:, 0] * forces[:, 1] - r[:, 1] * forces[:, 0]], axis=1)
        return g, forces.sum(axis=0), torque.sum(axis=0)

    def _calc_force(self, context, output):
        _, f, tau = self._solve(context)
        force = ExternallyAppliedSpatialForce()
        force.body_index = self._index
        force.p_BoBq_B = np.zeros(3)
        force.F_Bq_W = SpatialForce(tau, f)
        output.set_value([force])

    def _calc_wall_contact(self, context, output):
        g, f, tau = self._solve(context)
        output.set_value(WallContact(f, tau, g["points"], g["areas"], g["pressures"],
                                     g["normals"]))

    def _update(self, context, discrete_state):
        """Each pressed cell's bristle follows its slip over the step, up to mu times its
        normal force; a cell out of contact lets go."""
        g = self._geometry(self._state_port.Eval(context))
        z = np.zeros((self._count, 3))
        pressed = g["pressed"]
        if len(pressed):
            bristles = self._bristles_of(context, g) + self._dt * g["slip"]
            size = np.linalg.norm(bristles, axis=1) * self._tangential_stiffness * g["share"]
            over = size > g["limit"]
            if np.any(over):
                bristles[over] *= (g["limit"][over] / size[over])[:, None]
            z[pressed] = bristles
        discrete_state.set_value(self._bristles, z.ravel())


def _rotation(w, x, y, z) -> np.ndarray:
    """The rotation matrix of a unit quaternion (w, x, y, z)."""
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
