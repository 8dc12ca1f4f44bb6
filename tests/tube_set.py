"""Tubes made without the package's code, each with its true centreline, for testing the
colon import on geometry it did not generate.

A tube is a sweep of a (slightly elliptic) section along a random smooth curve in 3-D:
- the curve is integrated from its curvature (a parallel-transport frame turned by a
  curvature vector whose two components are smooth random sums of sines), so it is
  parametrised by arc length and its bends are never tighter than a chosen radius of
  curvature (at least 3 times the tube's largest radius); curves whose tube would come
  within 15 mm of itself are drawn again;
- the radius varies smoothly between 12 and 35 mm, and may carry fold-like ripples (narrow
  circular constrictions every few centimetres) or haustral folds (crescents between three
  longitudinal bands, deepest midway between them, none at the bands);
- each end is open (the mesh's boundary, a section normal to the curve), a hemispherical
  cap or a flat cap; an open end may flare (the radius growing over its last 4 cm) and be
  cut obliquely (its boundary in a plane through the curve's end, tilted from the normal
  section; where a bend before the end takes a line of the wall wholly ahead of that plane
  the draw is refused, and where a bend brings a line back across it the rim is the
  crossing nearest the end); the curve may turn sharply (up to 80 degrees) over its last
  centimetres before an end; haustral crescents fade over a hemispherical cap (its pole is
  a point);
- the triangulation is a uniform grid of rings, jittered rings (uneven spacing, a varying
  count of vertices per ring, vertices moved along and around the surface, zipped ring to
  ring), or a Delaunay triangulation of jittered points in the surface's parameter plane
  (periodic around), from 5k to 200k faces;
- in metres or in millimetres (import with scale 0.001), as OBJ, STL or PLY.

The true centreline is the curve, continued straight along its end tangent into a cap up
to the cap's wall: to the apex of a hemispherical cap (one end radius beyond the curve's
end), to the disc of a flat cap (the curve's end itself). That is where the lumen closes;
the procedural colon's centreline likewise ends on its caps. At an open end the true
centreline ends at the end section's centre (an oblique end's too: its plane passes
through the curve's end). The haustral crescents are alike in the three sectors, so the
section's centroid stays on the curve.
"""

import dataclasses

import numpy as np
import trimesh
from scipy.spatial import Delaunay, cKDTree

ENDS = ("open", "hemisphere", "flat")
MESHES = ("rings", "jittered", "delaunay")


def straight_tube(length=0.3, radius=0.02, rings=60, around=32, start=0.0):
    """An open straight tube along +z from `start` to `start + length` (a uniform grid of
    rings), its vertices exactly on the circle of `radius`."""
    z = np.linspace(start, start + length, rings)
    a = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
    vertices = np.array([[radius * np.cos(t), radius * np.sin(t), zz] for zz in z for t in a])
    return trimesh.Trimesh(vertices, ring_faces(rings, around), process=False)


def ring_faces(rings: int, around: int) -> list:
    """The triangles of a grid of `rings` rings of `around` vertices each (ring after ring,
    closed round each ring): two per quad."""
    faces = []
    for i in range(rings - 1):
        for j in range(around):
            k, n = i * around + j, i * around + (j + 1) % around
            faces += [[k, n, k + around], [n, n + around, k + around]]
    return faces


def arc_tube(bend_radius=0.3, angle=0.8, radius=0.02, step=0.004, around=32):
    """An open tube along a circular arc in the vertical x-z plane, lowest at its middle (a
    valley): its centreline at angle a (from -`angle` to +`angle`, rad) is
    (R sin a, 0, R (1 - cos a)), R = `bend_radius`, so it slopes by |a| and its arc length
    from the first end is R (a + `angle`)."""
    a = np.linspace(-angle, angle, int(np.ceil(2 * angle * bend_radius / step)) + 1)
    centre = np.column_stack([bend_radius * np.sin(a), np.zeros_like(a),
                              bend_radius * (1.0 - np.cos(a))])
    normal = np.column_stack([-np.sin(a), np.zeros_like(a), np.cos(a)])  # toward the bend's axis
    binormal = np.tile([0.0, 1.0, 0.0], (len(a), 1))
    theta = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
    vertices = (centre[:, None, :] + radius * (np.cos(theta)[None, :, None] * normal[:, None, :]
                                               + np.sin(theta)[None, :, None]
                                               * binormal[:, None, :])).reshape(-1, 3)
    return trimesh.Trimesh(vertices, ring_faces(len(a), around), process=False)


def lying_cylinder(length=300.0, diameter=40.0, sections=64):
    """trimesh's capped cylinder (its ends closed by discs), turned from standing along z to
    lying along y (the patient's head-foot axis), in millimetres: a segmentation of a
    straight colon 30 cm long and 4 cm wide as a scan's STL would hold it."""
    mesh = trimesh.creation.cylinder(radius=0.5 * diameter, height=length, sections=sections)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1.0, 0.0, 0.0]))
    return mesh


@dataclasses.dataclass(frozen=True)
class TubeSpec:
    """How to make one tube (lengths in metres)."""

    name: str
    seed: int
    length: float                       # of the swept part
    radius: tuple = (0.015, 0.03)       # the smooth radius's range
    ripple: float = 0.0                 # depth of the folds, a share of the radius
    haustra: float = 0.0                # depth of the crescent folds, a share of the radius
    flare: tuple = (0.0, 0.0)           # an open end's radius grows by this share
    oblique: tuple = (0.0, 0.0)         # an open end's cut, degrees from the normal section
    end_bend: tuple = (0.0, 0.0)        # degrees the curve turns over its last cm, per end
    ellipticity: float = 0.0            # semi-axes (1 + e) r and (1 - e) r
    tightest_bend: float = 3.0          # smallest radius of curvature / largest radius
    ends: tuple = ("open", "open")
    mesh: str = "rings"
    faces: int = 20000                  # roughly
    unit: str = "m"                     # "m" or "mm"
    fmt: str = "obj"
    outward: bool = False               # normals out of the lumen (else into it)


@dataclasses.dataclass
class Tube:
    spec: TubeSpec
    mesh: trimesh.Trimesh               # in the file's unit
    truth: np.ndarray                   # (K, 3) the true centreline, dense, in metres
    truth_radius: np.ndarray            # (K,) the section's equal-area radius there [m]
    truth_length: float                 # [m], caps' straight continuations included

    @property
    def scale(self) -> float:
        """What the mesh's coordinates are multiplied by to be in metres."""
        return 0.001 if self.spec.unit == "mm" else 1.0

    def write(self, folder) -> "Path":
        from pathlib import Path

        path = Path(folder) / f"{self.spec.name}.{self.spec.fmt}"
        self.mesh.export(path)
        return path


# --- The curve ----------------------------------------------------------------------------

def _smooth(rng, s, wavelengths, count=4):
    """A smooth random function of s: a sum of sines, amplitude ~1."""
    out = np.zeros_like(s)
    for _ in range(count):
        lam = rng.uniform(*wavelengths)
        out += rng.normal() * np.sin(2 * np.pi * s / lam + rng.uniform(0, 2 * np.pi))
    return out / np.sqrt(count / 2)


def _rotate(v, axis, angle):
    """Rodrigues: each row of v turned about the unit axis by angle."""
    c, s = np.cos(angle), np.sin(angle)
    return v * c + np.cross(axis, v) * s + np.outer(v @ axis, axis) * (1 - c)


END_BEND_SPAN = (0.01, 0.05)
"""Where an end bend turns: from 5 cm to 1 cm before the end (m)."""


def _bump(x, a, b, edge=0.005):
    """1 on [a, b], falling smoothly to 0 over `edge` outside it."""
    def step(t):
        t = np.clip(t, 0.0, 1.0)
        return t * t * (3.0 - 2.0 * t)
    return step((x - a + edge) / edge) * step((b + edge - x) / edge)


def _curve(rng, length, max_curvature, ds=2e-4, end_bend=(0.0, 0.0)):
    """(s, points, tangent, m1, m2): an arc-length curve and its parallel-transport frame,
    its curvature vector a m1 + b m2 with |(a, b)| <= max_curvature, plus, near each end
    with an `end_bend` (degrees), a turn by that angle about m2 over END_BEND_SPAN."""
    s = np.arange(0.0, length + 0.5 * ds, ds)
    s[-1] = length
    a = _smooth(rng, s, (0.15, 0.6))
    b = _smooth(rng, s, (0.15, 0.6))
    k = np.hypot(a, b)
    scale = max_curvature * rng.uniform(0.6, 1.0) / k.max()
    a, b = a * scale, b * scale
    near, far = END_BEND_SPAN
    for end, degrees in enumerate(end_bend):
        if degrees:
            span = (near, far) if end == 0 else (length - far, length - near)
            bump = _bump(s, *span)
            a = a + np.radians(degrees) * bump / (np.sum(bump) * ds)
    frame = np.eye(3)[rng.permutation(3)] * rng.choice([-1, 1], size=(3, 1))
    if np.linalg.det(frame) < 0:
        frame[2] *= -1
    t, m1, m2 = frame
    out = np.empty((len(s), 3, 3))
    out[0] = frame
    for i in range(len(s) - 1):
        h = s[i + 1] - s[i]
        kv = 0.5 * (a[i] + a[i + 1]) * m1 + 0.5 * (b[i] + b[i + 1]) * m2
        kn = np.linalg.norm(kv)
        if kn > 0:
            axis = np.cross(t, kv) / kn
            t, m1, m2 = _rotate(np.array([t, m1, m2]), axis, kn * h)
        out[i + 1] = (t, m1, m2)
    tangent, m1, m2 = out[:, 0], out[:, 1], out[:, 2]
    steps = 0.5 * (tangent[1:] + tangent[:-1]) * np.diff(s)[:, None]
    points = np.concatenate([[np.zeros(3)], np.cumsum(steps, axis=0)])
    return s, points, tangent, m1, m2


def _radius_function(rng, spec):
    lo, hi = spec.radius
    phases = rng.uniform(0, 2 * np.pi, 3)
    lams = rng.uniform(0.12, 0.5, 3)
    fold_period = rng.uniform(0.03, 0.05)
    fold_phase = rng.uniform(0, 2 * np.pi)

    def radius(s):
        s = np.asarray(s, dtype=float)
        wave = sum(np.sin(2 * np.pi * s / lam + ph) for lam, ph in zip(lams, phases)) / 3.0
        r = lo + (hi - lo) * (0.5 + 0.5 * np.clip(wave * 1.3, -1, 1))
        if spec.ripple:
            fold = (0.5 + 0.5 * np.cos(2 * np.pi * s / fold_period + fold_phase)) ** 6
            r = r * (1.0 - spec.ripple * fold)
        for end, share in enumerate(spec.flare):
            if share:
                from_end = s if end == 0 else spec.length - s
                t = np.clip(1.0 - from_end / FLARE_LENGTH, 0.0, 1.0)
                r = r * (1.0 + share * t * t * (3.0 - 2.0 * t))
        return r

    radius.fold = lambda s: (0.5 + 0.5 * np.cos(2 * np.pi * np.asarray(s) / fold_period
                                                + fold_phase + 1.0)) ** 6
    return radius


MAX_BEND_SHARE = 0.7
"""Largest radius * curvature a tube may have (1: its inner wall meets the bend's axis)."""
FLARE_LENGTH = 0.04
"""How far from an open end its flare begins (m)."""
OBLIQUE_RAMP = 0.06
"""Over how much of the tube an oblique end's tilt fades in (m): the rings stay apart."""


class CannotMake(ValueError):
    """A draw the set cannot make as specified; `reason` says why ("bent": tighter than its
    radius allows, "cut": an oblique cut a bend before the end takes off a line of the
    wall)."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


def _crescent(theta):
    """How deep a haustral fold is around the section: 0 at the three bands (theta = 0,
    2 pi / 3, 4 pi / 3), 1 midway between them."""
    return np.abs(np.sin(1.5 * np.asarray(theta)))


# --- The surface --------------------------------------------------------------------------

class _Surface:
    """The tube's surface as a function of (u, theta): u is arc length along the curve on
    the swept part, [0, L], and runs on over the caps to their poles."""

    def __init__(self, spec, s, points, tangent, m1, m2, radius):
        self.spec = spec
        self.s, self.points, self.tangent, self.m1, self.m2 = s, points, tangent, m1, m2
        self.radius = radius
        self.L = float(s[-1])
        r0, r1 = float(radius(0.0)), float(radius(self.L))
        self.cap_length = [self._cap_length(spec.ends[0], r0), self._cap_length(spec.ends[1], r1)]
        self.u0 = -self.cap_length[0]
        self.u1 = self.L + self.cap_length[1]

    @staticmethod
    def _cap_length(kind, r):
        return {"open": 0.0, "hemisphere": 0.5 * np.pi * r, "flat": r}[kind]

    def _frame(self, s):
        s = np.clip(s, 0.0, self.L)
        pick = lambda v: np.column_stack([np.interp(s, self.s, v[:, k]) for k in range(3)])
        c, t, m1, m2 = (pick(v) for v in (self.points, self.tangent, self.m1, self.m2))
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        m1 -= np.sum(m1 * t, axis=1, keepdims=True) * t
        m1 /= np.linalg.norm(m1, axis=1, keepdims=True)
        return c, t, m1, np.cross(t, m1)

    def _cut(self, end, theta):
        """Where, along the surface's line at angle theta, an oblique open end's plane
        cuts it: u (per theta) with the point on the plane through the curve's end tilted by
        `oblique` degrees about m2 there. A line a bend brings back across the plane crosses
        it more than once: the crossing nearest the curve's end is the rim (found on a grid
        of u, then by bisection). A line that does not cross it within reach has no rim:
        the tube cannot be cut so (ValueError)."""
        L_end = 0.0 if end == 0 else self.L
        c, t, m1, m2 = (v[0] for v in self._frame(np.array([L_end])))
        angle = np.radians(self.spec.oblique[end])
        normal = np.cos(angle) * t + np.sin(angle) * np.cross(m2, t)
        reach = 3.0 * float(self.radius(L_end)) * max(1.0, np.tan(angle))
        grid = L_end + np.linspace(-reach, reach, 257)
        uu, tt = np.meshgrid(grid, theta, indexing="ij")
        ahead = ((self._plain_point(uu.ravel(), tt.ravel()) - c) @ normal > 0.0).reshape(uu.shape)
        change = ahead[1:] != ahead[:-1]                     # (grid - 1, theta)
        if not change.any(axis=0).all():
            missed = float(np.degrees(theta[~change.any(axis=0)][0]))
            raise CannotMake("cut", f"{self.spec.name}: its {self.spec.oblique[end]:.0f} "
                             f"degree cut at end {end} misses the wall's line at "
                             f"{missed:.0f} degrees (a bend before the end takes it ahead "
                             f"of the plane)")
        middle = 0.5 * (grid[1:] + grid[:-1])
        nearest = np.argmin(np.where(change, np.abs(middle - L_end)[:, None], np.inf), axis=0)
        lo, hi = grid[nearest], grid[nearest + 1]
        lo_ahead = ahead[nearest, np.arange(len(theta))]
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            same = ((self._plain_point(mid, theta) - c) @ normal > 0.0) == lo_ahead
            lo, hi = np.where(same, mid, lo), np.where(same, hi, mid)
        return 0.5 * (lo + hi)

    def _tilt(self, u, theta):
        """How far along the curve an oblique open end moves the point (u, theta): the end's
        ring lies in its cut's plane (`_cut`); the shift fades in over OBLIQUE_RAMP."""
        shift = np.zeros_like(u)
        for end, degrees in enumerate(self.spec.oblique):
            if not degrees or self.spec.ends[end] != "open":
                continue
            from_end = u if end == 0 else self.L - u
            near = from_end < OBLIQUE_RAMP
            if not near.any():
                continue
            w = np.clip(1.0 - from_end[near] / OBLIQUE_RAMP, 0.0, 1.0)
            cut = self._cut(end, theta[near]) - (0.0 if end == 0 else self.L)
            shift[near] += w * w * (3.0 - 2.0 * w) * cut
        return shift

    def point(self, u, theta):
        u, theta = np.broadcast_arrays(np.asarray(u, float), np.asarray(theta, float))
        u, theta = u.ravel(), theta.ravel()
        if any(self.spec.oblique):
            u = u + self._tilt(u, theta)
        return self._plain_point(u, theta)

    def _plain_point(self, u, theta):
        e = self.spec.ellipticity
        c, t, m1, m2 = self._frame(u)
        # Beyond an open end (an oblique cut's far side): straight on along the end tangent.
        for end, kind in enumerate(self.spec.ends):
            beyond = (u < 0.0) if end == 0 else (u > self.L)
            if kind == "open" and beyond.any():
                c[beyond] += (u[beyond] - (0.0 if end == 0 else self.L))[:, None] * t[beyond]
        section = ((1 + e) * np.cos(theta))[:, None] * m1 + ((1 - e) * np.sin(theta))[:, None] * m2
        r = self.radius(np.clip(u, 0.0, self.L))
        crescent = np.zeros_like(r)
        if self.spec.haustra:
            crescent = (self.spec.haustra * self.radius.fold(np.clip(u, 0.0, self.L))
                        * _crescent(theta))
        out = c + (r * (1.0 - crescent))[:, None] * section
        for end, kind in enumerate(self.spec.ends):
            cap = (u < 0.0) if end == 0 else (u > self.L)
            if kind == "open" or not cap.any():
                continue
            depth = -u[cap] if end == 0 else u[cap] - self.L
            sign = -1.0 if end == 0 else 1.0
            rr = r[cap]
            if kind == "hemisphere":
                # The crescents fade over the cap (as cos phi: smooth at its base), so that
                # its pole is a point one unfolded radius beyond the curve's end, not a
                # ridge along the axis.
                phi = np.minimum(depth / rr, 0.5 * np.pi)
                rr = rr * (1.0 - crescent[cap] * np.cos(phi))
                out[cap] = c[cap] + rr[:, None] * (sign * np.sin(phi)[:, None] * t[cap]
                                                   + np.cos(phi)[:, None] * section[cap])
            else:
                rr = rr * (1.0 - crescent[cap])
                rho = np.clip(1.0 - depth / rr, 0.0, 1.0)
                out[cap] = c[cap] + (rr * rho)[:, None] * section[cap]
        return out

    def truth(self, step=1e-4):
        s = np.arange(0.0, self.L, step)
        s = np.append(s, self.L)
        c, t, _, _ = self._frame(s)
        points, radius = [c], [self._equal_area(self.radius(s))]
        if self.spec.haustra:   # the section's area with its crescents, as a circle's
            theta = np.linspace(0.0, 2 * np.pi, 96, endpoint=False)
            depth = self.spec.haustra * self.radius.fold(s)[:, None] * _crescent(theta)[None, :]
            radius[0] = radius[0] * np.sqrt(np.mean((1.0 - depth) ** 2, axis=1))
        for end, kind in enumerate(self.spec.ends):
            if kind != "hemisphere":
                continue
            r = float(self.radius(0.0 if end == 0 else self.L))
            z = np.arange(step, r + 0.5 * step, step)
            z[-1] = r
            p = c[0] - z[:, None] * t[0] if end == 0 else c[-1] + z[:, None] * t[-1]
            rz = self._equal_area(np.sqrt(np.maximum(r * r - z * z, 0.0)))
            if end == 0:
                points.insert(0, p[::-1])
                radius.insert(0, rz[::-1])
            else:
                points.append(p)
                radius.append(rz)
        return np.concatenate(points), np.concatenate(radius)

    def _equal_area(self, r):
        e = self.spec.ellipticity
        return r * np.sqrt((1 + e) * (1 - e))


# --- Triangulations -----------------------------------------------------------------------

def _zip(ring_a, theta_a, ring_b, theta_b):
    """Triangles joining two rings of vertex indices sorted by angle (theta in [0, 2 pi)),
    walking around both, always advancing the ring whose next vertex comes first."""
    na, nb = len(ring_a), len(ring_b)
    if na == 1 or nb == 1:  # a pole
        if na == 1:
            return [[ring_a[0], ring_b[(j + 1) % nb], ring_b[j]] for j in range(nb)]
        return [[ring_a[j], ring_a[(j + 1) % na], ring_b[0]] for j in range(na)]
    # Start both at the vertex nearest angle 0 (theta sorted, so index 0) and unwrap.
    ta = np.append(theta_a, theta_a[0] + 2 * np.pi)
    tb = np.append(theta_b, theta_b[0] + 2 * np.pi)
    i = j = 0
    faces = []
    while i < na or j < nb:
        advance_a = j >= nb or (i < na and ta[i + 1] <= tb[j + 1])
        if advance_a:
            faces.append([ring_a[i % na], ring_a[(i + 1) % na], ring_b[j % nb]])
            i += 1
        else:
            faces.append([ring_a[i % na], ring_b[(j + 1) % nb], ring_b[j % nb]])
            j += 1
    return faces


def _ring_positions(rng, surface, spec, h):
    """u of the rings (caps included, each pole a ring of one) and vertices per ring."""
    def spaced(a, b, jitter):
        n = max(1, int(round((b - a) / h)))
        if not jitter:
            return np.linspace(a, b, n + 1)
        gaps = rng.uniform(0.4, 1.6, n)
        return a + (b - a) * np.concatenate([[0.0], np.cumsum(gaps) / gaps.sum()])

    jitter = spec.mesh != "rings"
    body = spaced(0.0, surface.L, jitter)
    u = [body]
    if spec.ends[0] != "open":
        u.insert(0, spaced(surface.u0, 0.0, jitter)[:-1])
    if spec.ends[1] != "open":
        u.append(spaced(surface.L, surface.u1, jitter)[1:])
    u = np.concatenate(u)
    return u


def _around(surface, u, h, jitter, rng):
    """Vertices around the ring at u: one at a pole, else about circumference / h."""
    if np.isclose(u, surface.u0) and surface.spec.ends[0] != "open" or \
            np.isclose(u, surface.u1) and surface.spec.ends[1] != "open":
        return 1
    p = surface.point(np.full(64, u), np.linspace(0, 2 * np.pi, 64, endpoint=False))
    circumference = np.sum(np.linalg.norm(p - np.roll(p, 1, axis=0), axis=1))
    n = circumference / h * (rng.uniform(0.7, 1.3) if jitter else 1.0)
    return max(6, int(round(n)))


def _rings_mesh(rng, surface, spec, h):
    jitter = spec.mesh == "jittered"
    u_rings = _ring_positions(rng, surface, spec, h)
    vertices, rings, thetas = [], [], []
    n_used = 0
    fixed_m = None
    for k, u in enumerate(u_rings):
        m = _around(surface, u, h, jitter, rng)
        if not jitter and m > 1:  # the same count on every ring: the body's middle one's
            fixed_m = fixed_m or _around(surface, 0.5 * surface.L, h, False, rng)
            m = fixed_m
        if m == 1:
            theta = np.zeros(1)
            uu = np.array([u])
        else:
            theta = 2 * np.pi * np.arange(m) / m
            if jitter:
                theta = theta + rng.uniform(0, 2 * np.pi) + rng.uniform(-0.3, 0.3, m) * 2 * np.pi / m
                theta = np.sort(np.mod(theta, 2 * np.pi))
            uu = np.full(m, u)
            open_end = (k == 0 and spec.ends[0] == "open") or \
                (k == len(u_rings) - 1 and spec.ends[1] == "open")
            if jitter and not open_end and 0 < k < len(u_rings) - 1:
                gap = min(u - u_rings[k - 1], u_rings[k + 1] - u)
                uu = uu + rng.uniform(-0.3, 0.3, m) * gap
        vertices.append(surface.point(uu, theta))
        rings.append(np.arange(n_used, n_used + m))
        thetas.append(theta)
        n_used += m
    faces = []
    for k in range(len(rings) - 1):
        faces += _zip(rings[k], thetas[k], rings[k + 1], thetas[k + 1])
    return np.concatenate(vertices), np.array(faces)


def _delaunay_mesh(rng, surface, spec, h):
    """Jittered points over the swept part triangulated by Delaunay in (u, R theta)
    (periodic around), its end rings zipped to ring-meshed caps."""
    L = surface.L
    r_mean = float(np.mean(surface.radius(np.linspace(0, L, 200))))
    m_end = [_around(surface, 0.0, h, False, rng), _around(surface, L, h, False, rng)]
    # Rows of jittered points, spacing varying smoothly by a factor of ~2 along the tube.
    rows = []
    u = 0.0
    density = lambda x: 1.0 + 0.45 * np.sin(2 * np.pi * x / max(L / 2.5, 0.05) + 1.0)
    while True:
        u += h * density(u) * rng.uniform(0.8, 1.2)
        if u > L - 0.6 * h:
            break
        rows.append(u)
    points_u, points_t = [], []
    for u in rows:
        m = _around(surface, u, h * density(u), False, rng)
        theta = (np.arange(m) + rng.uniform(-0.4, 0.4, m)) * 2 * np.pi / m + rng.uniform(0, 7)
        uu = np.clip(u + rng.uniform(-0.25, 0.25, m) * h * density(u), 0.2 * h, L - 0.2 * h)
        points_u.append(uu)
        points_t.append(np.mod(theta, 2 * np.pi))
    end_theta = [2 * np.pi * np.arange(m) / m for m in m_end]
    all_u = np.concatenate([np.zeros(m_end[0]), *points_u, np.full(m_end[1], L)])
    all_t = np.concatenate([end_theta[0], *points_t, end_theta[1]])
    n = len(all_u)
    # Periodic: three copies around, keep triangles whose centroid is in the middle one.
    U = np.concatenate([all_u] * 3)
    T = np.concatenate([all_t - 2 * np.pi, all_t, all_t + 2 * np.pi])
    tri = Delaunay(np.column_stack([U, r_mean * T]))
    simplices = tri.simplices
    centroid = T[simplices].mean(axis=1)
    keep = (centroid >= 0.0) & (centroid < 2 * np.pi)
    body = simplices[keep] % n
    # Orientation: counter-clockwise in (u, theta) like the rings' faces.
    a, b, c = (np.column_stack([U[simplices[keep][:, k]], T[simplices[keep][:, k]]])
               for k in range(3))
    cross = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]
    body = np.where((cross > 0)[:, None], body[:, [0, 2, 1]], body)
    vertices = [surface.point(all_u, all_t)]
    faces = [body]
    count = n
    ring_first = np.arange(m_end[0])
    ring_last = np.arange(n - m_end[1], n)
    for end in (0, 1):
        if spec.ends[end] == "open":
            continue
        edge = ring_first if end == 0 else ring_last
        a_u, b_u = (surface.u0, 0.0) if end == 0 else (L, surface.u1)
        cap_u = np.linspace(a_u, b_u, max(2, int(round((b_u - a_u) / h)) + 1))
        cap_u = cap_u[:-1] if end == 0 else cap_u[1:]
        rings, thetas = [], []
        for u in cap_u:
            m = _around(surface, u, h, False, rng)
            theta = np.zeros(1) if m == 1 else 2 * np.pi * np.arange(m) / m
            vertices.append(surface.point(np.full(m, u), theta))
            rings.append(np.arange(count, count + m))
            thetas.append(theta)
            count += m
        if end == 0:
            rings.append(edge)
            thetas.append(end_theta[0])
        else:
            rings.insert(0, edge)
            thetas.insert(0, end_theta[1])
        cap = []
        for k in range(len(rings) - 1):
            cap += _zip(rings[k], thetas[k], rings[k + 1], thetas[k + 1])
        faces.append(np.array(cap))
    return np.concatenate(vertices), np.concatenate(faces)


# --- The tube -----------------------------------------------------------------------------

def _clear_of_itself(points, radii, s, margin=0.015):
    """Whether the tube around `points` keeps `margin` from itself (arc-distant parts)."""
    tree = cKDTree(points)
    reach = 2 * radii.max() + margin
    for i, j in tree.query_pairs(reach, output_type="ndarray"):
        if abs(s[i] - s[j]) > 2.5 * reach and \
                np.linalg.norm(points[i] - points[j]) < radii[i] + radii[j] + margin:
            return False
    return True


def make_tube(spec: TubeSpec) -> Tube:
    rng = np.random.default_rng(spec.seed)
    radius = _radius_function(rng, spec)
    r_max = spec.radius[1] * (1 + spec.ellipticity)
    for _ in range(50):
        s, points, tangent, m1, m2 = _curve(rng, spec.length, 1.0 / (spec.tightest_bend * r_max),
                                            end_bend=spec.end_bend)
        coarse = slice(None, None, 25)
        extended = np.concatenate([points[coarse], [points[0] - r_max * tangent[0],
                                                    points[-1] + r_max * tangent[-1]]])
        ss = np.concatenate([s[coarse], [-r_max, s[-1] + r_max]])
        if _clear_of_itself(extended, np.full(len(extended), r_max), ss):
            break
    else:
        raise RuntimeError(f"{spec.name}: no curve clear of itself")
    # A tube bends no tighter than its radius allows: where r * curvature nears 1 its inner
    # wall folds over itself (an end bend with a flare can ask for that).
    curvature = np.linalg.norm(np.gradient(tangent, s, axis=0), axis=1)
    worst = float(np.max(curvature * radius(s) * (1 + spec.ellipticity)))
    if worst > MAX_BEND_SHARE:
        raise CannotMake("bent", f"{spec.name}: bends to {worst:.2f} of its radius of "
                         f"curvature (at most {MAX_BEND_SHARE})")
    surface = _Surface(spec, s, points, tangent, m1, m2, radius)
    for end, degrees in enumerate(spec.oblique):    # a cut the tube can have, or CannotMake
        if degrees and spec.ends[end] == "open":
            surface._cut(end, np.linspace(0.0, 2.0 * np.pi, 360, endpoint=False))
    area = 2 * np.pi * float(np.mean(radius(s))) * (surface.u1 - surface.u0)
    h = np.sqrt(area / (0.5 * spec.faces) * 2 / np.sqrt(3))  # equilateral-ish faces
    if spec.mesh == "delaunay":
        vertices, faces = _delaunay_mesh(rng, surface, spec, h)
    else:
        vertices, faces = _rings_mesh(rng, surface, spec, h)
    # Each face's normal into the lumen, or out of it: made consistent from one face's
    # test against the curve.
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    c = mesh.triangles_center
    nearest = cKDTree(points).query(c)[1]
    inward = np.einsum("ij,ij->i", mesh.face_normals, points[nearest] - c)
    if (np.median(inward) > 0) == spec.outward:
        faces = faces[:, ::-1]
    # Random offset and rotation in space: the curve does not start at the origin.
    rotation = trimesh.transformations.random_rotation_matrix(rng.random(3))
    rotation[:3, 3] = rng.uniform(-0.5, 0.5, 3)
    truth, truth_radius = surface.truth()
    vertices = trimesh.transform_points(vertices, rotation)
    truth = trimesh.transform_points(truth, rotation)
    unit = 1000.0 if spec.unit == "mm" else 1.0
    mesh = trimesh.Trimesh(vertices * unit, faces, process=False)
    length = float(np.sum(np.linalg.norm(np.diff(truth, axis=0), axis=1)))
    return Tube(spec, mesh, truth, truth_radius, length)


# --- Comparing a recovered centreline with the truth --------------------------------------

def densify(points, step=1e-4):
    """The polyline through `points` sampled every ~`step`."""
    out = [points[:1]]
    for a, b in zip(points[:-1], points[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)


def centreline_errors(truth, points):
    """(largest distance [m] from a recovered point to the true curve, largest distance
    from a true point to the recovered polyline)."""
    to_truth = cKDTree(densify(truth)).query(points)[0].max()
    to_recovered = cKDTree(densify(points)).query(truth)[0].max()
    return float(to_truth), float(to_recovered)


def perturbed(mesh: trimesh.Trimesh, share=1e-6, seed=0) -> trimesh.Trimesh:
    """The mesh with every vertex moved at random by ~`share` of its size (bounding box
    diagonal), per coordinate."""
    rng = np.random.default_rng(seed)
    size = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    return trimesh.Trimesh(mesh.vertices + rng.normal(scale=share * size, size=mesh.vertices.shape),
                           mesh.faces, process=False)


# --- The set ------------------------------------------------------------------------------

TUBES = (
    TubeSpec("plain_open", 1, 0.45, (0.018, 0.028), faces=8000),
    TubeSpec("ripple_hemi_mm", 2, 0.6, (0.015, 0.03), ripple=0.15, ends=("hemisphere", "open"),
             mesh="jittered", faces=20000, unit="mm", fmt="stl"),
    TubeSpec("flat_caps", 3, 0.5, (0.02, 0.035), ends=("flat", "flat"), faces=15000, fmt="ply"),
    TubeSpec("delaunay_open", 4, 0.7, (0.012, 0.025), mesh="delaunay", faces=25000,
             outward=True),
    TubeSpec("tight_hemi", 5, 0.4, (0.025, 0.035), tightest_bend=3.0,
             ends=("hemisphere", "hemisphere"), mesh="jittered", faces=12000),
    TubeSpec("elliptic_flat_mm", 6, 0.55, (0.015, 0.025), ellipticity=0.08,
             ends=("open", "flat"), mesh="delaunay", faces=18000, unit="mm"),
    TubeSpec("small_coarse", 7, 0.3, (0.012, 0.02), ends=("hemisphere", "flat"), faces=5000,
             mesh="jittered"),
    TubeSpec("long_ripple", 8, 1.2, (0.015, 0.03), ripple=0.2, ends=("flat", "hemisphere"),
             mesh="jittered", faces=60000, outward=True),
    TubeSpec("long_delaunay_mm", 9, 1.0, (0.02, 0.035), ripple=0.1, ends=("open", "open"),
             mesh="delaunay", faces=50000, unit="mm", fmt="stl"),
    TubeSpec("wide_hemi", 10, 0.5, (0.03, 0.035), ends=("hemisphere", "hemisphere"),
             faces=20000, fmt="ply"),
    TubeSpec("narrow_long", 11, 1.5, (0.012, 0.018), ripple=0.12, ends=("flat", "open"),
             mesh="rings", faces=100000),
    TubeSpec("huge_mm", 12, 1.5, (0.015, 0.035), ripple=0.15, ends=("hemisphere", "flat"),
             mesh="delaunay", faces=200000, unit="mm"),
    TubeSpec("mid_jitter_flat", 13, 0.8, (0.014, 0.03), ends=("flat", "open"),
             mesh="jittered", faces=35000, ellipticity=0.05),
    # Shapes of tubes made elsewhere (issue: the importer right to the ends): haustral
    # crescents, flared and oblique open ends, sharp bends just before a cap.
    TubeSpec("haustral_open_mm", 14, 0.7, (0.018, 0.03), haustra=0.3, ends=("open", "open"),
             mesh="jittered", faces=30000, unit="mm", fmt="stl"),
    TubeSpec("flared_oblique", 15, 0.6, (0.015, 0.025), flare=(0.5, 0.3), oblique=(40.0, 25.0),
             faces=20000),
    TubeSpec("capped_bend_hemi", 16, 0.5, (0.015, 0.022), end_bend=(0.0, 80.0),
             ends=("open", "hemisphere"), faces=20000),
    TubeSpec("capped_bend_flat_mm", 17, 0.5, (0.015, 0.022), end_bend=(70.0, 80.0),
             ends=("flat", "flat"), mesh="jittered", faces=20000, unit="mm"),
    TubeSpec("haustral_oblique_mm", 18, 0.8, (0.02, 0.03), haustra=0.25, flare=(0.0, 0.3),
             oblique=(30.0, 0.0), mesh="delaunay", faces=40000, unit="mm", fmt="ply"),
)


# --- Shapes that are not tubes --------------------------------------------------------------

def marching_tetrahedra(values, origin, spacing):
    """The surface values = 0 of a sampled field (nx, ny, nz) as a triangle mesh: each grid
    cube split into six tetrahedra around its diagonal, each cut by a triangle or a quad;
    vertices shared through the grid edges they lie on (winding left to the import's
    repair)."""
    nx, ny, nz = values.shape
    index = np.arange(nx * ny * nz).reshape(nx, ny, nz)
    corner = [index[i:nx - 1 + i, j:ny - 1 + j, k:nz - 1 + k].ravel()
              for k in (0, 1) for j in (0, 1) for i in (0, 1)]  # bit 1 x, 2 y, 4 z
    flat = values.ravel()
    grid = np.stack(np.meshgrid(*(np.arange(n) for n in values.shape), indexing="ij"),
                    axis=-1).reshape(-1, 3) * spacing + origin
    triangles = []
    for tet in ((0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7)):
        g = np.column_stack([corner[c] for c in tet])
        inside = flat[g] < 0.0
        count = inside.sum(axis=1)
        order = np.argsort(~inside, axis=1, kind="stable")  # inside corners first
        g = np.take_along_axis(g, order, axis=1)
        one = count == 1  # the lone inside corner against the other three
        three = count == 3  # the lone outside corner (last) against the other three
        for mask, lone, rest in ((one, 0, (1, 2, 3)), (three, 3, (0, 1, 2))):
            h = g[mask]
            triangles.append(np.stack([np.stack([h[:, lone], h[:, r]], axis=1) for r in rest],
                                      axis=1))
        h = g[count == 2]  # inside a, b; outside c, d: a quad
        a, b, c, d = h.T
        quad = [np.stack([a, c], 1), np.stack([a, d], 1), np.stack([b, d], 1), np.stack([b, c], 1)]
        triangles.append(np.stack([quad[0], quad[1], quad[2]], axis=1))
        triangles.append(np.stack([quad[0], quad[2], quad[3]], axis=1))
    edges = np.concatenate(triangles)  # (T, 3, 2) grid-vertex pairs
    keys, inverse = np.unique(np.sort(edges.reshape(-1, 2), axis=1), axis=0, return_inverse=True)
    fa, fb = flat[keys[:, 0]], flat[keys[:, 1]]
    w = fa / (fa - fb)
    vertices = grid[keys[:, 0]] + w[:, None] * (grid[keys[:, 1]] - grid[keys[:, 0]])
    faces = inverse.reshape(-1, 3)
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                  & (faces[:, 0] != faces[:, 2])]
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    # Slivers where the surface passes through a grid point collapse into stray faces:
    # the largest piece is the surface.
    return max(mesh.split(only_watertight=False), key=lambda piece: len(piece.faces))


def y_branch(radius=0.018, arms=(0.16, 0.16, 0.16), spacing=0.003, open_ends=False):
    """A Y: three arms of a tube (`arms` long) from one junction, 120 degrees apart in a
    plane, closed at their ends (round), or cut open there (`open_ends`)."""
    directions = [np.array([np.cos(a), np.sin(a), 0.0]) for a in (0.0, 2.1, 4.2)]
    reach = max(arms) + radius + 2 * spacing
    axes = [np.arange(-reach, reach + spacing, spacing)] * 2 + \
        [np.arange(-radius - 3 * spacing, radius + 3 * spacing + 1e-9, spacing)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    p = np.stack([X, Y, Z], axis=-1)
    field = np.full(X.shape, np.inf)
    for d, arm in zip(directions, arms):
        t = np.clip(p @ d, 0.0, arm)
        field = np.minimum(field, np.linalg.norm(p - t[..., None] * d, axis=-1) - radius)
    mesh = marching_tetrahedra(field, np.array([a[0] for a in axes]), spacing)
    if open_ends:  # cut each arm a radius before its round end
        c = mesh.triangles_center
        keep = np.all([c @ d < arm - radius for d, arm in zip(directions, arms)], axis=0)
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
        mesh.remove_unreferenced_vertices()
    return mesh


def random_spec(seed: int) -> TubeSpec:
    """A tube of random shape (benchmarks/bench_import.py --sweep): the set's features
    drawn together, each end open or capped, flared, cut obliquely and bent before it at
    random. Some draws bend tighter than their radius allows (`make_tube` refuses them)."""
    rng = np.random.default_rng(seed)
    ends = tuple(str(e) for e in rng.choice(ENDS, 2, p=[0.5, 0.25, 0.25]))
    return TubeSpec(
        f"random_{seed}", 10_000 + seed, float(rng.uniform(0.4, 0.8)),
        (float(rng.uniform(0.012, 0.02)), float(rng.uniform(0.022, 0.032))),
        ripple=float(rng.choice([0.0, 0.15])), haustra=float(rng.choice([0.0, 0.25, 0.4])),
        flare=tuple(float(x) for x in rng.choice([0.0, 0.3, 0.5], 2)),
        oblique=tuple(float(x) if e == "open" else 0.0
                      for x, e in zip(rng.choice([0.0, 20.0, 35.0, 45.0], 2), ends)),
        end_bend=tuple(float(x) for x in rng.choice([0.0, 40.0, 70.0, -60.0], 2)),
        ends=ends, mesh=str(rng.choice(MESHES)), faces=int(rng.choice([10000, 25000])),
        unit=str(rng.choice(["m", "mm"])))

