"""The compliant wall as an elastic foundation under the capsule, computed here
(`FoundationContact`): the default realisation of the compliant wall (compliant.py, its
`realisation` "foundation"; "hydroelastic" gives the same wall to Drake's hydroelastic
contact instead).

Why not Drake's hydroelastic contact. A wall that yields by millimetres wraps a large patch
of the capsule: Drake cuts it into 100-500 polygons (the wall's triangles against the
capsule field's tetrahedra), each a contact of its own for the solver, and the Default run
goes at 0.65x real time where the rigid stand-in goes at 2.15x (benchmarks/bench_realtime.py).
Coarser meshes are cheaper but miss the foundation's closed form by 10-25 % at the shallow
indentations runs reach. Here the same mechanics are integrated directly, at a cost that does
not grow with the patch: the per-cell arithmetic is compiled (foundation_kernels.py, Numba),
and the compliant wall runs faster than the rigid stand-in (docs/results/performance.md, "The
compliant wall's cost").

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

Adhesion. Mucosa sticks to capsule materials (Terry et al. 2012: 0.55 J/m^2 in peel, 1.98
in tack; compliant.adhesion_energy). A cell that has touched the wall stays stuck to it: it
pulls back with the same spring, k times how far it is beyond the mucosa, until it is pulled
the release distance sqrt(2 W / k) off, where it lets go (the springs' energy at release is W
per area: an adhesive Winkler foundation). A stuck cell in tension carries no friction.

The force is linearly implicit in the wall's own stiffness, damping and friction (the
velocity change over the step taken with the cells' response at its end, the other applied
forces passing through this system), so the wall's stiffness sets no step bound; a capsule at
rest sits where its weight needs.

The tube's two ends are closed by flat caps across the centreline's end tangents, as its
collision mesh is. What it leaves out: the diverticula (pouches cut into the wall mesh: the
foundation sees the wall without them); polyps and the boxes around the tube keep Drake's
hydroelastic contact with the capsule's field mesh (compliant.py). The wall is taken as undeformed
elsewhere: a capsule's dent does not move the wall beside it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import ExternallyAppliedSpatialForce
from pydrake.systems.framework import LeafSystem
from scipy.ndimage import maximum_filter1d, minimum_filter1d
from scipy.spatial import cKDTree

from capsule_drake.anatomy.centerline import Centerline
from capsule_drake.lifetime import weak_method
from capsule_drake.physics.contact import foundation_kernels as kernels

TABLE_STEP = 0.5e-3
"""Spacing (m) of the wall's table along the centreline: a haustral fold (a few mm wide, up
to ~5 mm high) is read within ~20 micrometres by bilinear interpolation."""
TABLE_AROUND = 128
"""Angles of the wall's table around the centreline (2.8 degrees: 1.2 mm at a 25 mm radius)."""
PROBES_AROUND = 40
PROBES_ALONG = 6
PROBES_CAP_RINGS = 5
"""The capsule's surface cells (`capsule_probes`)."""
CAP_REACH = 0.05
"""How near (m, along the centreline) a tube's end a capsule's station must be for its
points to be checked against that end's cap (its farthest point is 16 mm from its centre)."""
FOLLOW_REACH = 0.06
"""How far (m) a capsule's centre may lie from its tube's centreline before its station is
looked up afresh: beyond the widest lumen (a caecum of 45 mm) and a capsule pressed 15 mm
into its wall."""
REFINEMENTS = 1
"""Steps of each point's station from the capsule's (module docstring): one, then its own."""
NEAR_SLACK = 0.3e-3
"""How far (m) a capsule's surface may move, on the same station, before the cells that may
touch the wall are picked afresh (`FoundationContact._near`: they are picked with this
slack, so the pick holds for any pose within it; the result does not depend on it)."""
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
        self.curvature = np.linalg.norm(self.bends, axis=1)
        self.radii = radius                       # (S, K)
        # (S, 3, 3): each station's point P, tangent over the table's step T' and dT/ds B',
        # gathered once per Newton step: a point p's step in stations from there is
        # (d . T') / (1 - d . B'), d = p - P.
        self._steps = np.stack([self.points, self.tangents / step, self.bends], axis=1)
        self._tree = cKDTree(self.points)
        self._filters = {}

    def nearest(self, p) -> int:
        """The table's station nearest the point p (3,)."""
        return int(self._tree.query(p)[1])

    def follow(self, p, station: int) -> int:
        """The station of the point p (3,) on the stretch of tube around `station`: Newton
        steps along the centreline from it (so that a capsule pressed through its wall stays
        in its own tube rather than being handed to a neighbouring loop that lies nearer),
        or the nearest station when that does not settle or ends farther from p than
        FOLLOW_REACH (a capsule placed anew)."""
        j = kernels.follow_station(self._steps, np.asarray(p, dtype=float), int(station),
                                   FOLLOW_REACH)
        return j if j >= 0 else self.nearest(p)

    def near_wall(self, points, station: int, reach: float, slack: float = 0.0) -> np.ndarray:
        """Indices of the points (N, 3), all within `reach` (m) of the station `station`'s
        point, that may lie beyond the mucosa: their distance from the centreline, measured
        in that station's plane, exceeds the narrowest radius of the stations within reach,
        less what a bend can change that distance by over their offset u along the
        centreline (kappa u^2 / 2 for the sharpest curvature kappa there) and 1 mm. With a
        `slack` (m), every point that may lie beyond it after moving by up to that much."""
        lowest, bend = self._filter(reach)
        last = self.count - 1
        return kernels.near_wall(
            np.ascontiguousarray(points, dtype=float), self.frames[station], lowest[station],
            float(bend[station]), float(slack), self.dtheta, self.around,
            station * self.step <= CAP_REACH, (last - station) * self.step <= CAP_REACH,
            self.frames[0], self.frames[last])

    def _filter(self, reach: float):
        """near_wall's thresholds for points within `reach` of a station, per station
        (computed once per reach): the narrowest radius over the stations within reach, per
        sector of angle and its two neighbours (a point's angle seen from this station's
        frame differs from its own station's by a little in a bend), less 1 mm (S, K); and
        half the sharpest curvature there (S,)."""
        cached = self._filters.get(reach)
        if cached is None:
            size = 2 * (int(reach / self.step) + 1) + 1
            lowest = minimum_filter1d(self.radii, size, axis=0, mode="nearest")
            lowest = minimum_filter1d(lowest, 3, axis=1, mode="wrap") - 1e-3
            bend = 0.5 * maximum_filter1d(self.curvature, size, mode="nearest")
            cached = self._filters[reach] = (lowest, bend)
        return cached

    def depth(self, points, station: int):
        """For world points (N, 3) near the station `station` (a table index near them):
        (depth along the wall's normal beyond the mucosa (N,; negative inside the lumen),
        the wall's inward unit normal (N, 3)), in m. Each point's station: one Newton step
        from `station`'s frame, then REFINEMENTS from its own; the radius and its slopes
        bilinear in (s, theta); the tube's end caps (a point whose station is an end and
        that lies past the end's plane is that far into it)."""
        points = np.ascontiguousarray(points, dtype=float)
        depth, inward = np.empty(len(points)), np.empty((len(points), 3))
        kernels.wall_depth(points, int(station), REFINEMENTS, self._steps, self.frames,
                           self.flat, self.step, self.dtheta, self.around, depth, inward)
        return depth, inward


class StraightTube:
    """The simplest colon the wall's table takes: a straight tube along +x of constant
    radius, its angle measured from +z (for checks and benchmarks of the contact alone)."""

    def __init__(self, radius: float, length: float = 0.4):
        s = np.arange(0.0, length + 1e-9, 0.001)
        self.centerline = Centerline(s, np.stack([s, 0 * s, 0 * s], 1),
                                     np.tile([0.0, 0.0, 1.0], (len(s), 1)),
                                     np.full(len(s), radius), np.zeros(len(s), int), ["tube"])
        self.radius = radius

    def wall_radius(self, s, theta):
        return np.full(np.broadcast(np.asarray(s), np.asarray(theta)).shape, self.radius)


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


def no_forces() -> AbstractValue:
    """An empty list of applied forces, as a value of the plant's applied-force port type."""
    value = AbstractValue.Make([ExternallyAppliedSpatialForce()])
    value.set_value([])
    return value


def empty_wall_contact() -> WallContact:
    """A WallContact with no contact (a port's model value)."""
    return WallContact(np.zeros(3), np.zeros(3), np.zeros((0, 3)), np.zeros(0), np.zeros(0),
                       np.zeros((0, 3)))


class FoundationContact(LeafSystem):
    """The compliant wall's force on the capsule (module docstring).

    Input ports: capsule_state ([q_WB (wxyz), p_WB, w_WB, v_WB], 13), other_forces (the
    other applied forces, list[ExternallyAppliedSpatialForce]). Output ports:
    applied_spatial_force (the other forces and the wall's, on the capsule's body at its
    origin: what the plant is given), wall_contact (WallContact). State: each surface cell's bristle deflection
    (world, m), updated every plant step.
    """

    def __init__(self, body_index, table: WallTable, X_BG, radius: float, length: float,
                 foundation_modulus: float, friction: float, dissipation: float,
                 time_step: float, mass: float, axial_inertia: float,
                 spatial_inertia=None, p_BoBcm=(0.0, 0.0, 0.0),
                 gravity_W=(0.0, 0.0, -9.81), start_station: int = 0,
                 adhesion_energy: float = 0.0, knee_depth: float = math.inf,
                 stiffened_modulus: float | None = None):
        super().__init__()
        self._index = body_index
        self._table = table
        centres, normals, areas = capsule_probes(radius, length)
        R_BG, p_BG = X_BG.rotation().matrix(), X_BG.translation()
        self._p_B = centres @ R_BG.T + p_BG
        self._n_B = normals @ R_BG.T
        self._areas = areas
        self._count = len(areas)
        self._reach = float(np.linalg.norm(self._p_B, axis=1).max())
        self._k = foundation_modulus
        # Past `knee_depth` (m) beyond the mucosa the wall presses with `stiffened_modulus`
        # (Pa/m) more per metre: its stretch past the knee of its stress-strain curve.
        self._knee = float(knee_depth)
        self._k_stiff = float(foundation_modulus if stiffened_modulus is None
                              else stiffened_modulus)
        self._mu = friction
        self._dissipation = dissipation
        self._dt = time_step
        # Adhesion: a cell that has touched the wall stays stuck to it until pulled a
        # release distance delta beyond the mucosa, with k delta^2 / 2 = the adhesion
        # energy (module docstring); 0: no adhesion.
        self._release = (math.sqrt(2.0 * adhesion_energy / foundation_modulus)
                         if adhesion_energy > 0.0 else 0.0)
        m_t = tangential_mass(mass, radius, axial_inertia)
        # The capsule's spatial inertia about its body origin in its frame (6x6, [w; v]).
        if spatial_inertia is None:
            spatial_inertia = np.diag([axial_inertia] * 3 + [mass] * 3)
        self._inertia_B = np.asarray(spatial_inertia, dtype=float)
        self._p_BoBcm = np.asarray(p_BoBcm, dtype=float)
        self._centred = not self._p_BoBcm.any()
        self._weight = mass * np.asarray(gravity_W, dtype=float)
        omega = TANGENTIAL_TURN / time_step
        self._tangential_stiffness = omega**2 * m_t                         # N/m, whole patch
        self._tangential_damping = 2.0 * TANGENTIAL_DAMPING_RATIO * omega * m_t  # N s/m
        self._state_port = self.DeclareVectorInputPort("capsule_state", 13)
        self._others = self.DeclareAbstractInputPort(
            "other_forces", AbstractValue.Make([ExternallyAppliedSpatialForce()]))
        self._bristles = self.DeclareDiscreteState(3 * self._count)
        # The capsule's station on the centreline, followed from step to step (WallTable.follow).
        self._station = self.DeclareDiscreteState(np.array([float(start_station)]))
        # Each cell: 1 while stuck to the wall (adhesion), else 0.
        self._stuck = self.DeclareDiscreteState(self._count)
        self._no_stuck = np.zeros(self._count)   # (without adhesion: no cell is stuck)
        self.DeclarePeriodicDiscreteUpdateEvent(time_step, 0.0, weak_method(self._update))
        ticket = {self.input_port_ticket(self._state_port.get_index()),
                  self.input_port_ticket(self._others.get_index()),
                  self.discrete_state_ticket(self._bristles),
                  self.discrete_state_ticket(self._station),
                  self.discrete_state_ticket(self._stuck)}
        self._force_port = self.DeclareAbstractOutputPort(
            "applied_spatial_force", lambda: AbstractValue.Make([ExternallyAppliedSpatialForce()]),
            weak_method(self._calc_force), prerequisites_of_calc=ticket)
        self._contact_port = self.DeclareAbstractOutputPort(
            "wall_contact", lambda: AbstractValue.Make(empty_wall_contact()),
            weak_method(self._calc_wall_contact), prerequisites_of_calc=ticket)
        self._memo = (None, None)
        self._near_memo = None   # (station, p_WB, R, the cells picked with NEAR_SLACK)

    def _geometry(self, x, hint: int, stuck=None):
        """The pressed cells at the capsule state x (and, with adhesion, the cells stuck to
        the wall, `stuck` (N,) 1 or 0): a dict of their indices, centres' offsets from the
        body origin (world), depths, wall normals, wall areas and velocities (computed once
        per state: the plant's step and this system's update read it)."""
        release = self._release
        key = x.tobytes() if not release else x.tobytes() + stuck.tobytes()
        if self._memo[0] == key:
            return self._memo[1]
        # The plant's quaternion drifts off unit length between its own normalisations:
        # its rotation is that of the unit quaternion along it.
        # (one sum: a NaN or an infinity anywhere in x makes it NaN or infinite)
        if not math.isfinite(x.sum()):   # diverged: the run guard says so and stops the run
            return self._no_contact(key, hint, np.zeros(0, dtype=np.intp), np.eye(3))
        w, i, j, k = x[0:4].tolist()
        scale = 1.0 / math.sqrt(w * w + i * i + j * j + k * k)
        R = _rotation(w * scale, i * scale, j * scale, k * scale)
        p_WB = x[4:7]
        table = self._table
        offsets, points = kernels.place_cells(self._p_B, R, p_WB)
        station = table.follow(p_WB, hint)
        near = self._near(points, station, p_WB, R)
        if near.size == 0:                    # clear of the wall: nothing to look up
            return self._no_contact(key, station, near, R)
        # The cells in contact and each one's response (foundation_kernels.contact_cells):
        # its pressure k d (1 + c d') (with adhesion, a stuck cell beyond the mucosa: k d, in
        # tension), its normal force's stiffness over a step and its damping (N s/m),
        # d f / d v = -k d c A and d f / d x = -k (1 + c d') A, and its bristle's, mapped by
        # its Jacobian J = [-[r]x, I] onto the capsule's spatial velocity [w; v] (6x6 gain).
        # Linearly implicit in the wall's own response: the velocity change over the step
        # with every cell's force taken at the step's end is dt (M + dt gain)^-1 (F + F_other)
        # (`system`: M + dt gain, M the capsule's spatial inertia in world).
        (pressed, r, nu, area, pressure, normal_gain, beta, share, slip, limit, floor,
         system) = kernels.contact_cells(
            points, offsets, self._n_B, R, near, self._no_stuck if stuck is None else stuck,
            release, x[10:13], x[7:10], self._areas, self._k, self._knee, self._k_stiff,
            self._dissipation, self._dt,
            self._mu, self._tangential_damping + self._dt * self._tangential_stiffness,
            station, REFINEMENTS, table._steps, table.frames, table.flat, table.step,
            table.dtheta, table.around, self._inertia_B)
        geometry = {"station": station, "pressed": pressed, "offsets": r, "points": points[pressed],
                    "normals": nu, "areas": area, "pressures": pressure,
                    "normal_force": pressure * area, "normal_gain": normal_gain,
                    "bristle_gain": beta, "R": R, "share": share,
                    "slip": slip,                  # the cells' velocity's tangential part
                    "limit": limit,                # mu times the pressing force
                    # The least normal force a cell can carry: 0, or with adhesion the
                    # tension at which it lets go.
                    "floor": floor,
                    "system": system}
        self._memo = (key, geometry)
        return geometry

    def _no_contact(self, key, station: int, pressed, R) -> dict:
        """The geometry of a capsule clear of the wall (kept for its state `key`)."""
        geometry = {"station": station, "pressed": pressed, "points": np.zeros((0, 3)),
                    "normals": np.zeros((0, 3)), "areas": np.zeros(0),
                    "pressures": np.zeros(0), "R": R}
        self._memo = (key, geometry)
        return geometry

    def _near(self, points, station: int, p_WB, R) -> np.ndarray:
        """The cells that may touch the wall (WallTable.near_wall), picked with NEAR_SLACK and
        kept while the capsule stays on its station and no cell has moved farther than that
        since (|dp| + |dR|_F times the farthest cell's distance bounds every cell's move)."""
        memo = self._near_memo
        if memo is not None and memo[0] == station:
            dp = p_WB - memo[1]
            dR = R - memo[2]
            if (math.sqrt(float(dp @ dp)) + self._reach * math.sqrt(float(np.vdot(dR, dR)))
                    <= NEAR_SLACK):
                return memo[3]
        # (a stuck cell pulls from up to its release distance beyond the mucosa)
        near = self._table.near_wall(points, station, self._reach, NEAR_SLACK + self._release)
        self._near_memo = (station, np.array(p_WB), R, near)
        return near

    def _geometry_of(self, context):
        """`_geometry` at this context's capsule state, followed from its stored station."""
        return self._geometry(
            self._state_port.Eval(context),
            int(context.get_discrete_state(self._station).GetAtIndex(0)),
            context.get_discrete_state(self._stuck).value() if self._release else None)

    def _solve(self, context, others=None):
        """(the wall's geometry at this state, the net force and torque about the body
        origin, world); `others`: the other_forces input's value, if evaluated already."""
        g = self._geometry_of(context)
        if len(g["pressed"]) == 0:
            self._explicit = np.zeros(6)
            return g, np.zeros(3), np.zeros(3)
        # The velocity change over the step with every cell's force taken at the step's end
        # (dt (M + dt A)^-1 (F + F_other), the geometry's `system` M + dt A), then each
        # cell's force there: its normal force at least 0 (with adhesion, at least the
        # tension at which it lets go), its friction within mu times its pressing force (a
        # cell that would need more slips: Coulomb's cone).
        self._explicit, applied = kernels.implicit_wrench(
            g["pressed"], g["offsets"], g["normals"], g["normal_force"], g["normal_gain"],
            g["bristle_gain"], g["share"], g["slip"], g["floor"],
            context.get_discrete_state(self._bristles).value(), g["system"],
            self._other_wrench(g["R"], self._others.Eval(context) if others is None else others),
            self._dt, self._mu, self._tangential_stiffness, self._tangential_damping)
        return g, applied[3:], applied[:3]

    def wall_wrench(self, context) -> np.ndarray:
        """The wall's force at this context's state as its pressures and bristles give it
        ([torque about the body origin; force], world), before the implicit correction
        (what the closed form describes)."""
        g = self._geometry_of(context)
        if len(g["pressed"]) == 0:
            return np.zeros(6)
        self._solve(context)
        return self._explicit.copy()

    def _other_wrench(self, R, others):
        """The other forces on the capsule this step ([torque about the body origin; force],
        world): gravity and the applied forces `others` given to this system (the magnet's,
        the fluid's)."""
        fx, fy, fz = self._weight.tolist()
        if self._centred:          # the centre of mass at the body origin: weight, no torque
            tx = ty = tz = 0.0
        else:
            tx, ty, tz = (_skew(R @ self._p_BoBcm) @ self._weight).tolist()
        for force in others:
            if force.body_index != self._index:
                continue
            ax, ay, az, bx, by, bz = force.F_Bq_W.get_coeffs().tolist()
            rx, ry, rz = (R @ force.p_BoBq_B).tolist()
            tx += ax + ry * bz - rz * by
            ty += ay + rz * bx - rx * bz
            tz += az + rx * by - ry * bx
            fx += bx
            fy += by
            fz += bz
        return np.array([tx, ty, tz, fx, fy, fz])

    def _calc_force(self, context, output):
        others = self._others.Eval(context)
        _, f, tau = self._solve(context, others)
        force = ExternallyAppliedSpatialForce()
        force.body_index = self._index
        force.p_BoBq_B = np.zeros(3)
        force.F_Bq_W = SpatialForce(tau, f)
        output.set_value(others + [force])

    def _calc_wall_contact(self, context, output):
        g, f, tau = self._solve(context)
        output.set_value(WallContact(f, tau, g["points"], g["areas"], g["pressures"],
                                     g["normals"]))

    def _update(self, context, discrete_state):
        """Each pressed cell's bristle follows its slip over the step, up to mu times its
        normal force; a cell out of contact lets go. With adhesion, every cell in contact
        (pressed, or stuck and within its release distance) is stuck for the next step."""
        g = self._geometry_of(context)
        pressed = g["pressed"]
        if self._release:
            stuck = np.zeros(self._count)
            stuck[pressed] = 1.0
            discrete_state.set_value(self._stuck, stuck)
        discrete_state.set_value(self._bristles, kernels.next_bristles(
            self._count, pressed, g["normals"], g["slip"], g["share"], g["limit"],
            context.get_discrete_state(self._bristles).value(), self._dt,
            self._tangential_stiffness) if len(pressed) else np.zeros(3 * self._count))
        discrete_state.set_value(self._station, np.array([float(g["station"])]))


def _skew(v) -> np.ndarray:
    """[v]x: the matrix of v x (3,)."""
    x, y, z = v.tolist()
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _rotation(w, x, y, z) -> np.ndarray:
    """The rotation matrix of a unit quaternion (w, x, y, z)."""
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
