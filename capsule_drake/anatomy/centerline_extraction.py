"""The centreline of a tubular mesh: arc length and local radius, for imported colons.

1. Rings. Geodesic distance over the mesh's edge graph from one end (a tube's open boundary
   loop, or for a closed mesh the vertex farthest from another far vertex) grows along the
   tube; vertices binned by it form rings around the lumen, and the rings' centroids are a
   first centreline. It follows any bend, but its rings tilt where the inner wall is
   shorter than the outer. The rings are joined by a smoothing spline whose smoothing
   cross-validation chooses; where that straightens a bend off the lumen (step 2 finds too
   few closed sections round it), the rings are joined with the later passes' light
   smoothing instead, and failing that the rings of the other end are tried, before the
   mesh is refused.
2. Sections. The mesh is cut by the plane through each centreline point normal to the
   centreline's tangent (`MeshSections`: every face the plane crosses gives a segment; the
   segments join, through the edges they end on, into loops); the cut's closed loop around
   that point (the smallest containing it: in a bend the plane may cut the tube twice, and
   a wall with thickness gives an inner and an outer loop) gives the new point, the centre
   of a circle fitted to the loop's outer envelope (folds stand inward and would pull an
   area centroid off the axis), and an area, the local radius sqrt(A / pi). Repeated until
   the points move less than 0.02 mm (at most `iterations` times), they settle on the
   lumen's centre: for a tube swept by circles along a curve, the curve itself.
3. Ends. The line is cut back a radius from each end and grown again by marching: a step
   along the end's tangent (a quadratic fitted to the last 3 cm, each point weighted by the
   line it stands for), a section there, its centre again from a section normal to the
   tangent through it: the next point. Before each step a ray along the tangent looks for
   the wall ahead: within `CAP_AHEAD` of the radius it is a flat cap; as near as the tube
   is wide, with rays beside the axis meeting it nearer still, it is a round cap's base.
   Either way the line goes on along the ray to the wall (no section is cut across a cap:
   a plane not quite parallel to a flat cap cuts it and slides the centre sideways, and a
   round cap's sections are centred on any line through its centre). Near an open end the
   end's rim cuts the sections open; while most of the circle is left (210 degrees) the
   arc's fitted circle gives the centre (`MeshSections.arc_around`). An open end is passed
   when there is neither; the boundary loop ahead (within 3 radii, a bend may turn it
   aside) is the end. Where the ray meets the wall within the cap's reach, the wall's own
   shape tells a flat cap from a round one (`_flat_disc`: a plane piece at least a third of
   the circle), not how near it is (a round cap met off its axis is as near as a flat one).
4. Sections and a light smoothing spline once more, the ends held; then each end's last
   stretch is made again from the refined line (`_recast_caps`): a cubic fitted to section
   centres (arcs too, near an open end) every millimetre over the last 2 cm, followed to a
   flat cap; to the centre of the sphere fitted to a round cap and then straight along its
   tangent to the wall; to where it crosses the plane of an open end's loop (an oblique
   cut's centre: the loop's own centroid is off the axis where the tube flares or bends),
   or straight along the end's tangent there if the cubic wanders.
5. A recast can wander (a cubic carried past the sections it was fitted to, refined, then
   recast from its own wandering end), so each end is taken from the pass whose last 4 cm
   are nearest their own sections' centres (`end_residual`: the true centre line is a fixed
   point of "each section normal to the line is centred on it"). A flat cap's end is then
   made from the cap itself (`_finish_cap`): the area centroid of its disc (the flat faces
   joined to the one the line's ray meets, however wide a flared end makes it), reached
   along the disc's normal; where a line astray meets the disc near its rim, the disc is
   found among the faces that face the line, by their own normals (`_facing_disc`). An
   open end's last stretch is made again from the wall's normals (`_open_axis_end`):
   each normal of a tube swept by circles meets its axis, flared or not, where the
   sections are cut open by an oblique rim; the straight line they meet nearest, within
   0.3 radii of the end, is followed to the loop's plane, if its end is nearer its
   sections' centres than the line's (`end_residual`).
6. A round cap's end (and an end the march left with no loop or cap: a closed end, flared
   past what its sections allow) is fitted to the wall as a capsule's end (`_fit_round_cap`): a
   hemisphere and, behind it, a tube whose radius changes linearly, by a robust least
   squares on the faces near the end in which the wall inside the fit (folds) weighs a
   tenth, from several starting axes, kept only if rays from its centre meet the wall all
   round; fitted with 4, 8 and 12 mm of tube, the fit whose made end is nearest its own
   sections' centres is kept (`_capsule_end`; `end_residual`). Where the line's end is
   1.5 mm or more from its pole (a march that left a flared or bent cap astray: inside a
   bulb any line through its middle is a line of section centres), the line is taken to
   where the fitted tube begins, joined to it by a cubic over 3 cm, and along the fitted
   axis to the pole, unless that end leaves its own sections' centres by a tenth of the
   radius more than the line's did (`end_residual`; a voxelised flat cap, blunt enough to
   be called round, is fitted as a larger sphere whose pole sits in the corner).
7. An open end's last 5 cm are settled on their own sections (`_settle_open_end`): each
   point to the centre of its section (a closed loop, or an arc of at least 180 degrees
   where the rim cuts it), a cubic through those centres leaving the line behind along
   it, cut at the plane of the end's loop, twelve times; kept if its end is nearer its
   sections' centres than the line's (`end_residual`). A flare or a bend before the rim
   leaves the passes' sections there cut open, and the line they leave can bulge by
   millimetres while its end is right.
   Then the same stretch is made from the wall itself (`_fitted_open_end`): the faces of
   the last 5 cm, the far side of an oblique cut included, fitted by a robust least squares
   as a tube of circles whose axis's offsets from the stretch's chord and whose radius are
   cubics along it (the offsets quadratics at an oblique cut, whose far side alone cannot
   tell a cubic offset from the radius; folds inside the fit weigh a tenth); the line
   follows that axis from a third of the stretch in to the loop's plane, again only if its
   end is nearer its sections' centres (at an oblique cut, not farther by more than half
   again: its arcs are biased). Arcs cut open by a rim, with a fold across them, pull their
   circles aside; the fit uses the whole wall and no rim. Not where the line turns by more
   than 40 degrees over the stretch (a cubic across the chord does not follow it). A flat cap's
   last stretch is made the same way from the wall before its disc (`_fitted_cap_end`),
   where the line turns by up to 60 degrees and the fitted axis meets the disc within a
   tenth of the radius of its centroid.
8. An end the march left with no loop or cap met but with a boundary loop within two radii
   (a flared end cut obliquely after a bend, whose sections widen and tilt past what the
   march allows) is an open end, and finishes on the plane of its loop
   (`_reach_loop_plane`; the true centre line of a cut tube ends where it meets the cut):
   taken there along its end's tangent if it stopped more than 1 mm short (cut there if it
   passed it), if the crossing is well inside the loop.

The true centreline of a capped tube, as measured in the tests, is the curve continued
straight into the cap to its wall: to a hemisphere's apex, to a flat cap's disc.

Accuracy (tests/test_import_tubes.py, tests/tube_set.py): on 18 tubes made independently
(random smooth curves with bends down to 3 radii, radius 11-35 mm with ring folds or
haustral crescents, open, hemispherical and flat ends, open ends flared by 30-50 % and cut
25-40 degrees obliquely, bends of 70-80 degrees over the last 5 cm before a cap, uniform,
jittered and Delaunay triangulations of 4k-220k faces, metres and millimetres) within
0.05-0.47 mm of the true centreline everywhere, ends included (both ways); lengths within
0.7 mm; equal-area radii within 0.6 % (median); the same mesh with its vertices moved by
1e-6 of its size gives a centreline within 0.05 mm of the first. Tubes of random shape,
every feature drawn together (`benchmarks/bench_import.py --sweep`), show where it fails:
see docs/models/imported-colon.md, "The centreline".
Round trip of the procedural colon (exported, imported, extracted), seeds 0-9: within
0.35-0.95 mm of the original centreline everywhere, both ways (seeds 0, 3, 4: 0.64, 0.90,
0.50 mm).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh
from scipy.interpolate import make_smoothing_spline
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from .importer import geometry_of, open_end_loops
from .tube_check import MIN_CLOSED_SHARE, NotATubeError


# --- Plane sections -----------------------------------------------------------------------

@dataclasses.dataclass
class Section:
    """One closed loop of a plane section: its segments' end points `a`, `b` (K, 3), each
    segment running the same way round; the loop's enclosed `area` [m^2] and area
    `centroid` (3,)."""

    a: np.ndarray
    b: np.ndarray
    area: float
    centroid: np.ndarray

    @property
    def points(self) -> np.ndarray:
        """The segments' midpoints (not in order around the loop)."""
        return 0.5 * (self.a + self.b)

    @property
    def lengths(self) -> np.ndarray:
        return np.linalg.norm(self.b - self.a, axis=1)

    @property
    def radius(self) -> float:
        """Of the circle with the loop's area."""
        return float(np.sqrt(self.area / np.pi))


def _plane_basis(normal):
    n = normal / np.linalg.norm(normal)
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return n, a, np.cross(n, a)


class MeshSections:
    """Plane sections of one mesh, vectorised: the plane's signed distance at every vertex,
    a segment in every face it crosses (a vertex on the plane counts as in front of it), the
    segments joined into loops by the edges they end on (an edge is shared by two faces).
    Each segment runs along normal x face normal, so the loops of a consistently wound mesh
    run one way round and their areas and centroids follow from the shoelace sums without
    ordering the segments."""

    def __init__(self, mesh: trimesh.Trimesh):
        self.vertices = np.asarray(mesh.vertices, dtype=float)
        self.faces = np.asarray(mesh.faces, dtype=np.int64)
        edges = np.sort(self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        self.edges, inverse = np.unique(edges, axis=0, return_inverse=True)
        self.face_edges = inverse.reshape(-1, 3)
        self.face_normals = np.asarray(mesh.face_normals, dtype=float)
        triangles = self.vertices[self.faces]
        self._v0 = triangles[:, 0]
        self._e1 = triangles[:, 1] - self._v0
        self._e2 = triangles[:, 2] - self._v0
        self.face_centres = triangles.mean(axis=1)
        self.face_areas = 0.5 * np.linalg.norm(np.cross(self._e1, self._e2), axis=1)

    def loops(self, origin, normal):
        """(sections, contains, closed): every loop of the plane section through `origin`
        normal to `normal`; per loop whether it encloses `origin` (an odd number of its
        segments cross a ray from it in the plane) and whether it is closed (no segment
        ends on a boundary edge)."""
        origin = np.asarray(origin, dtype=float)
        n, ax, bx = _plane_basis(np.asarray(normal, dtype=float))
        d = (self.vertices - origin) @ n
        front = d >= 0.0
        fp = front[self.faces]
        count = fp.sum(axis=1)
        crossing = np.flatnonzero((count == 1) | (count == 2))
        if len(crossing) == 0:
            return [], np.zeros(0, bool), np.zeros(0, bool)
        fc = fp[crossing]
        cut = fc != np.roll(fc, -1, axis=1)  # edge k (k, k+1) crosses: exactly two per face
        which = np.argsort(~cut, axis=1, kind="stable")[:, :2]
        face_edge = self.face_edges[crossing[:, None], which]  # (C, 2)
        used, node = np.unique(face_edge, return_inverse=True)
        node = node.reshape(-1, 2)
        va, vb = self.edges[used, 0], self.edges[used, 1]
        t = d[va] / (d[va] - d[vb])
        p = self.vertices[va] + t[:, None] * (self.vertices[vb] - self.vertices[va])
        a, b = p[node[:, 0]], p[node[:, 1]]
        along = np.cross(n, self.face_normals[crossing])
        flip = np.einsum("ij,ij->i", b - a, along) < 0.0
        a[flip], b[flip] = b[flip].copy(), a[flip].copy()
        m = len(used)
        graph = coo_matrix((np.ones(len(node)), (node[:, 0], node[:, 1])), shape=(m, m))
        ncomp, label = connected_components(graph, directed=False)
        seg_label = label[node[:, 0]]
        degree = np.bincount(node.reshape(-1), minlength=m)
        open_comp = np.zeros(ncomp, bool)
        open_comp[label[degree == 1]] = True
        # In-plane coordinates from the origin.
        xa, ya = (a - origin) @ ax, (a - origin) @ bx
        xb, yb = (b - origin) @ ax, (b - origin) @ bx
        cross = xa * yb - xb * ya
        area = 0.5 * np.bincount(seg_label, cross, ncomp)
        cx = np.bincount(seg_label, (xa + xb) * cross, ncomp)
        cy = np.bincount(seg_label, (ya + yb) * cross, ncomp)
        # Parity of the crossings of the ray from the origin along +x.
        straddle = (ya > 0.0) != (yb > 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_at = xa + (xb - xa) * (0.0 - ya) / (yb - ya)
        hits = np.bincount(seg_label, (straddle & (x_at > 0.0)).astype(float), ncomp)
        contains = (hits.astype(int) % 2) == 1
        order = np.argsort(seg_label, kind="stable")
        bounds = np.searchsorted(seg_label[order], np.arange(ncomp + 1))
        sections = []
        for k in range(ncomp):
            pick = order[bounds[k]:bounds[k + 1]]
            ar = float(area[k])
            if abs(ar) > 1e-16:
                c2 = np.array([cx[k], cy[k]]) / (6.0 * ar)
            else:
                c2 = np.array([np.mean(xa[pick]), np.mean(ya[pick])])
            sections.append(Section(a[pick], b[pick], abs(ar), origin + c2[0] * ax + c2[1] * bx))
        return sections, contains, ~open_comp

    def around(self, origin, normal):
        """The smallest closed loop of the section that encloses `origin`, or None."""
        sections, contains, closed = self.loops(origin, normal)
        best = None
        for section, inside, whole in zip(sections, contains, closed):
            if inside and whole and section.area > 0.0 and (
                    best is None or section.area < best.area):
                best = section
        return best

    def arc_around(self, origin, normal, reach: float, min_span: float = np.radians(210.0)):
        """Where the plane cuts an open end's rim: the open part of the section (its chains
        that end on the mesh's boundary) within `reach` of `origin`, as a Section whose
        area is that of the circle fitted to it (`envelope_centre`), if it goes at least
        `min_span` round `origin`; else None. Its centre is the fitted circle's."""
        sections, _, closed = self.loops(origin, normal)
        chains = [sec for sec, whole in zip(sections, closed) if not whole]
        if not chains:
            return None
        a = np.concatenate([c.a for c in chains])
        b = np.concatenate([c.b for c in chains])
        near = np.linalg.norm(0.5 * (a + b) - origin, axis=1) <= reach
        if near.sum() < 8:
            return None
        a, b = a[near], b[near]
        _, ax, bx = _plane_basis(np.asarray(normal, dtype=float))
        mid = 0.5 * (a + b) - origin
        angle = np.sort(np.arctan2(mid @ bx, mid @ ax))
        gaps = np.diff(np.concatenate([angle, [angle[0] + 2 * np.pi]]))
        if 2 * np.pi - gaps.max() < min_span:
            return None
        lengths = np.linalg.norm(b - a, axis=1)
        centre = envelope_centre(0.5 * (a + b), lengths, origin, normal)
        if centre is None:
            return None
        radius = float(np.average(np.linalg.norm(0.5 * (a + b) - centre, axis=1),
                                  weights=lengths))
        return Section(a, b, np.pi * radius * radius, centre)

    def ray(self, origin, direction, reach=np.inf):
        """Distance along the ray to the nearest face it meets within `reach`
        (Moller-Trumbore), or inf."""
        return _ray(self._v0, self._e1, self._e2, origin, direction, reach)

    def near(self, centre, reach):
        """The faces with a corner within `reach` of `centre`, as (first corners, edges,
        edges) for `_ray`: rays from near `centre` tested against them alone."""
        near = np.linalg.norm(self._v0 - centre, axis=1) <= reach
        return self._v0[near], self._e1[near], self._e2[near]


def _ray(v0_all, e1_all, e2_all, origin, direction, reach=np.inf):
    """Distance along the ray to the nearest of the triangles (first corners, two edges)
    it meets within `reach` (Moller-Trumbore), or inf."""
    direction = np.asarray(direction, dtype=float)
    direction = direction / np.linalg.norm(direction)
    rel = v0_all - origin
    if np.isfinite(reach):  # faces whose first corner is near the ray's reach
        size = np.linalg.norm(e1_all, axis=1) + np.linalg.norm(e2_all, axis=1)
        near = np.linalg.norm(rel, axis=1) <= reach + size
        if not near.any():
            return np.inf
        e1, e2, v0 = e1_all[near], e2_all[near], v0_all[near]
    else:
        e1, e2, v0 = e1_all, e2_all, v0_all
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-18
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = origin - v0
    u = np.einsum("ij,ij->i", tvec, p) * inv
    q = np.cross(tvec, e1)
    v = (q @ direction) * inv
    dist = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (dist > 1e-9) & (dist <= reach)
    return float(dist[hit].min()) if hit.any() else np.inf


def section_loop(mesh, origin: np.ndarray, normal: np.ndarray, sections=None):
    """The plane section's closed loop around `origin` (the smallest containing it), or the
    nearest closed one if none does: (points (K, 3) on the loop (segment midpoints, not in
    order), area centroid (3,), area), or None. In a bend the plane may cut the tube twice;
    a wall with thickness gives an inner and an outer loop (the inner one, the lumen, is the
    smaller). `sections`: a `MeshSections` of `mesh` to reuse."""
    sections = sections or MeshSections(mesh)
    found, contains, closed = sections.loops(origin, normal)
    best = None
    for section, inside, whole in zip(found, contains, closed):
        if not whole or section.area <= 0.0:
            continue
        distance = 0.0 if inside else float(np.linalg.norm(section.centroid - origin))
        if best is None or distance < best[0] or (distance == best[0] == 0.0
                                                   and section.area < best[1].area):
            best = (distance, section)
    if best is None:
        return None
    return best[1].points, best[1].centroid, best[1].area


# --- Section centres ----------------------------------------------------------------------

def envelope_centre(points: np.ndarray, lengths: np.ndarray, start: np.ndarray,
                    normal: np.ndarray, inside: float = 0.0005, iterations: int = 12):
    """Centre of the circle fitted to a section loop's outer envelope, or None.

    Haustral folds, valves and taeniae stand inward from the colon's wall: a one-sided
    perturbation that pulls the area centroid away from them by millimetres where they sit
    on one side only. Points more than `inside` (m) within the fitted circle count 2 % as
    much as those on or outside it (iteratively reweighted algebraic circle fit, each point
    weighted by the length of loop it stands for; the weight falls smoothly over 0.25 mm, so
    the centre moves smoothly with the mesh), and the circle settles on the wall between
    the folds."""
    _, a, b = _plane_basis(normal)
    d = points - start
    xy = np.column_stack([d @ a, d @ b])
    weights = lengths.copy()
    design = np.column_stack([xy, np.ones(len(xy))])
    target = -np.sum(xy ** 2, axis=1)
    centre = np.zeros(2)
    radius = 0.0
    for _ in range(iterations):
        w = np.sqrt(weights)
        try:
            sol = np.linalg.lstsq(design * w[:, None], target * w, rcond=None)[0]
        except np.linalg.LinAlgError:
            return None
        centre = -0.5 * sol[:2]
        radius_sq = centre @ centre - sol[2]
        if not np.isfinite(radius_sq) or radius_sq <= 0.0:
            return None
        radius = np.sqrt(radius_sq)
        r = np.linalg.norm(xy - centre, axis=1)
        depth = (radius - inside - r) / 0.00025  # > 0: inside the band
        weights = lengths * (0.02 + 0.98 / (1.0 + np.exp(np.clip(4.0 * depth, -50, 50))))
    if np.linalg.norm(centre) > 0.5 * radius:
        return None  # not a round lumen around the start: keep the centroid
    return start + centre[0] * a + centre[1] * b


def _centre(section: Section, origin, normal):
    centre = envelope_centre(section.points, section.lengths, origin, normal)
    return section.centroid if centre is None else centre


# --- Helpers ------------------------------------------------------------------------------

def _edge_graph(mesh: trimesh.Trimesh):
    edges = mesh.edges_unique
    lengths = mesh.edges_unique_length
    n = len(mesh.vertices)
    return coo_matrix((np.concatenate([lengths, lengths]),
                       (np.concatenate([edges[:, 0], edges[:, 1]]),
                        np.concatenate([edges[:, 1], edges[:, 0]]))), shape=(n, n)).tocsr()


def _start_vertices(mesh: trimesh.Trimesh, graph, loops) -> np.ndarray:
    """One end of the tube: the open end's loop (`loops`, vertex indices) nearest the vertex
    geodesically farthest from vertex 0, or that vertex alone for a closed mesh."""
    first = dijkstra(graph, indices=0)
    first[~np.isfinite(first)] = -1.0
    far = int(np.argmax(first))
    if loops:
        distance = dijkstra(graph, indices=far)
        return min(loops, key=lambda loop: float(np.min(distance[loop])))
    return np.array([far])


def ring_centreline(mesh: trimesh.Trimesh, step: float, loops=None, other_end=False):
    """Step 1: ring centroids every `step` (m) of geodesic distance from one end.
    `loops`: the mesh's open ends (`open_end_loops`), if already found. `other_end`: from
    the end geodesically farthest from that one instead (its open loop, if it has one)."""
    graph = _edge_graph(mesh)
    loops = open_end_loops(mesh) if loops is None else loops
    start = _start_vertices(mesh, graph, loops)
    distance = _geodesic_from(graph, start)
    if other_end:
        far = int(np.argmax(np.where(np.isfinite(distance), distance, -1.0)))
        to_far = dijkstra(graph, indices=far)
        others = [loop for loop in loops if not np.array_equal(loop, start)]
        nearest = min(others, key=lambda loop: float(np.min(to_far[loop])), default=None)
        # The other open end's loop if it is at that end, else the farthest vertex (a cap).
        start = nearest if nearest is not None and \
            float(np.min(to_far[nearest])) < 0.5 * distance[far] else np.array([far])
        distance = _geodesic_from(graph, start)
    finite = np.isfinite(distance)
    vertices = np.asarray(mesh.vertices)[finite]
    distance = distance[finite]
    bins = np.floor(distance / step).astype(int)
    points = []
    for k in range(bins.max() + 1):
        ring = vertices[bins == k]
        if len(ring) >= 3:
            points.append(ring.mean(axis=0))
    return np.array(points).reshape(-1, 3)


def _geodesic_from(graph, start) -> np.ndarray:
    """Edge-graph distance of every vertex from the nearest of the vertices `start`."""
    return np.min(dijkstra(graph, indices=start), axis=0) if len(start) > 1 else \
        dijkstra(graph, indices=int(start[0]))


def _arc(points):
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _resample(points: np.ndarray, step: float, smoothing: float | None = None) -> np.ndarray:
    """Points every `step` of arc length along a smoothed polyline through `points`."""
    d = np.linalg.norm(np.diff(points, axis=0), axis=1)
    keep = np.concatenate([[True], d > 1e-9])
    points = points[keep]
    if len(points) < 5:
        return points
    s = _arc(points)
    spline = [make_smoothing_spline(s, points[:, k], lam=smoothing) for k in range(3)]
    fine = np.linspace(0.0, s[-1], max(int(s[-1] / (0.2 * step)), 10))
    dense = np.column_stack([f(fine) for f in spline])
    arc = _arc(dense)
    count = max(int(np.ceil(arc[-1] / step)), 1)
    stations = np.linspace(0.0, arc[-1], count + 1)  # both ends kept
    return np.column_stack([np.interp(stations, arc, dense[:, k]) for k in range(3)])


def _tangents(points):
    tangents = np.gradient(points, axis=0)
    return tangents / np.linalg.norm(tangents, axis=1, keepdims=True)


# --- The centreline -----------------------------------------------------------------------

INTERIOR_TOLERANCE = 2e-5
"""The interior's sections are repeated until no point moves more than this [m]."""
MARCH_BASELINE = 0.03
"""The march's direction is the tangent of a quadratic fitted to this much centreline [m]."""
CAP_AHEAD = 0.35
"""A cap: the wall straight ahead within this share of the tube's radius."""


def extract_centerline(mesh: trimesh.Trimesh, step: float = 0.005, iterations: int = 8,
                       progress=None, details: dict | None = None):
    """(s, points, radius): the centreline of a tubular mesh every `step` (m), from the end
    found first (geodesically farthest), with the local radius sqrt(section area / pi).

    Raises NotATubeError (one line) if no tube can be followed: the plane sections are not
    closed loops around a line (an open sheet; anatomy/tube_check.py). `progress`, if
    given, is called with (iteration, iterations). `details`, if given, is filled with
    "closed_share" (of the middle 80 % of the first line's stations, the share whose
    section is a closed loop around it) and "ends" (per end, "open", "flat cap", "round
    cap" or "none": a mesh whose end is open but has no boundary, a thick wall's)."""
    mesh = geometry_of(mesh)
    sections = MeshSections(mesh)
    end_loops = open_end_loops(mesh)
    # The first line: the rings of one end, through a smoothing spline whose smoothing is
    # chosen by cross-validation. That choice can straighten a bend centimetres off the
    # rings (it turned on 5e-9 m of rounding in one tube), so if the line's sections do not
    # close round it, the rings are followed with the light smoothing of the later passes;
    # failing that, the rings of the other end.
    rings = {}
    for other_end, smoothing in ((False, None), (False, SMOOTHING_LAMBDA),
                                 (True, SMOOTHING_LAMBDA)):
        if other_end not in rings:
            rings[other_end] = ring_centreline(mesh, step, end_loops, other_end=other_end)
        if len(rings[other_end]) < 5:
            raise NotATubeError("not a tube: its vertices make fewer than 5 rings along it "
                                "(too small, or too coarse a mesh?)")
        points, radius, closed_share, closed_count = _first_line(
            sections, _resample(rings[other_end], step, smoothing=smoothing), step,
            iterations, progress)
        if smoothing is None:
            first = closed_count   # what the refusal reports, as before the retries
        if closed_share >= MIN_CLOSED_SHARE and radius is not None:
            break
    else:
        raise NotATubeError(
            f"not a tube: only {first[0]} of the {first[1]} plane sections across "
            "the middle of its middle line are closed loops around it (at least "
            f"{MIN_CLOSED_SHARE:.0%} of a tube's are): an open sheet, or a branching mesh?")
    # Cut each end back by a radius (the sections there may still lean on the end) and
    # grow it again.
    radius_now = np.asarray(radius)
    cut = int(np.ceil(1.0 * float(np.median(radius_now)) / step))
    if len(points) > 2 * cut + 6:
        points = points[cut:len(points) - cut]
    reference = float(np.median(radius_now))
    # The open ends' boundary loops (vertices, (K, 3)), found once for both marches and the
    # recast of their last stretches.
    loops = [np.asarray(mesh.vertices)[loop] for loop in end_loops]
    tail, tail_end, tail_jump = _march(sections, loops, list(points), step, 0.001, reference)
    head, head_end, head_jump = _march(sections, loops, list(points[::-1]), step, 0.001,
                                       reference)
    # A march that stopped with a boundary loop near (a flared end cut obliquely after a
    # bend widens, and tilts its sections, past what the march allows before the loop is
    # ahead of it) ended at an open end all the same.
    stopped = tuple(kind == "none" and any(
        np.linalg.norm(ring.mean(axis=0) - line[-1]) <= 2.0 * reference for ring in loops)
        for kind, line in ((head_end, head), (tail_end, tail)))
    head_end, tail_end = ("open" if short else kind
                          for kind, short in zip((head_end, tail_end), stopped))
    # An open end cut square to the tube (`_square_cut`): its loop's centroid is the lumen's
    # centre, flared or not, and the smoothing leaves it there (the recast and the wall's
    # axis still compete for the end, as at any open end: the test can take a folded tube's
    # tilted cut for a square one); the march's points just before it whose sections the rim
    # cut open (their centres are circles fitted to arcs, off where a fold crosses the rim)
    # are left out.
    fixed = tuple(kind == "open" and _square_cut(line[-1], loops)
                  for kind, line in ((head_end, head), (tail_end, tail)))
    if fixed[0]:
        head = _closed_before(sections, head, len(points))
    if fixed[1]:
        tail = _closed_before(sections, tail, len(points))
    points = np.array(head[::-1][:-len(points)] + tail)
    points = _resample(points, step, smoothing=1e-12) if len(points) > 10 else points
    # A cap's last stretch is the ray's: its sections (across a round cap, any line through
    # its centre is a line of section centres) are not refined; once the line behind it is,
    # its tangent there is more accurate than the march's, and the ray is cast again.
    jumps = [head_jump, tail_jump]
    candidates = []
    for final in range(FINAL_PASSES):
        hold = tuple(j + 0.5 * step if j > 0 else 0.0 for j in jumps)
        points, radius, _ = _refine(sections, points, step, keep_ends=True,
                                    max_move=0.5 * step, hold=hold)
        points = _smooth_inside(points, fixed)
        if final == 0:
            marched = (points, radius)
        else:   # recast ends
            candidates.append((points, radius))
        if final < FINAL_PASSES - 1:
            points, jumps = _recast_caps(sections, points, step, (head_end, tail_end), jumps,
                                         reference, loops)
    # The march's own end is a candidate at a round cap (a recast from a flared or bent
    # tube's last sections can carry the line centimetres astray), not at an open end (its
    # loop's centroid is off the axis where the tube flares or the cut is oblique).
    points, radius = _best_ends(sections, candidates, reference, marched,
                                (head_end == "round cap", tail_end == "round cap"))
    for side, kind in ((0, head_end), (1, tail_end)):
        if kind == "flat cap":
            line = points[::-1] if side == 0 else points
            line = _finish_cap(sections, line, reference, step)
            points = line[::-1] if side == 0 else line
    changed = False
    # The radius 25-75 mm before each end, taken before either end is made again.
    end_radii = [float(np.median(r[-15:-5] if len(r) > 20 else r))
                 for r in (radius[::-1], radius)]
    for side, kind in ((0, head_end), (1, tail_end)):
        # An end the march left as "none" (no loop, no cap met: it stopped where a flared
        # end widened past it) is closed all the same: fitted as a round cap.
        if kind not in ("round cap", "none") or not FIT_ROUND_CAPS:
            continue
        line = points[::-1] if side == 0 else points
        # (the end's own sections, which a flare widens, bound the fitted cap's size too)
        widest = float(np.max(radius[:3] if side == 0 else radius[-3:]))
        made = _round_cap_end(sections, line, end_radii[side], step, widest=widest)
        if made is not line:
            changed = True
            points = made[::-1] if side == 0 else made
    # Each open end made again from the wall's normals, then settled on its own sections,
    # then from its wall fitted as a tube; each taken only if its end is nearer its own
    # sections' centres than the line's (`end_residual`, as the recast passes are chosen):
    # a fold across the window can turn the wall's normals astray.
    remakes = (_open_axis_end,) + ((_settle_open_end,) if SETTLE_OPEN_ENDS else ()) + \
        ((_fitted_open_end,) if FIT_OPEN_ENDS else ())
    for remake in remakes:
        for side, kind in ((0, head_end), (1, tail_end)):
            if kind != "open":
                continue
            line = points[::-1] if side == 0 else points
            made = remake(sections, line, reference, step, loops)
            # (_fitted_open_end judges its own fit)
            if made is not line and (remake is _fitted_open_end or end_residual(
                    sections, made, reference) < end_residual(sections, line, reference)):
                changed = True
                points = made[::-1] if side == 0 else made
    # A flat cap's last stretch made again from the wall before it fitted as a tube, on the
    # same terms (its end, the disc's centroid, is already right; the line before it can
    # bulge where a flare and a bend meet the cap).
    for side, kind in ((0, head_end), (1, tail_end)):
        if kind != "flat cap" or not FIT_OPEN_ENDS:
            continue
        line = points[::-1] if side == 0 else points
        made = _fitted_cap_end(sections, line, reference, step)
        if made is not line and end_residual(sections, made, reference) < \
                end_residual(sections, line, reference):
            changed = True
            points = made[::-1] if side == 0 else made
    # An open end the march stopped short of ends on its loop's plane, wherever the remakes
    # left it. (Not judged by `end_residual`: near an oblique rim the sections are arcs, and
    # the right extension raised it, 0.13 -> 0.27 and 0.36 -> 1.46 mm on the two tubes it
    # was made for. Not at every open end: there it took two fresh tubes farther, none
    # nearer.)
    for side, short in enumerate(stopped):
        if not short:
            continue
        line = points[::-1] if side == 0 else points
        made = _reach_loop_plane(line, reference, step, loops)
        if made is not line:
            changed = True
            points = made[::-1] if side == 0 else made
    if changed or len(radius) != len(points):
        radius = _refine(sections, points, step, keep_ends=True, max_move=0.0)[1]
    if details is not None:
        details.update(closed_share=closed_share, ends=(head_end, tail_end))
    return _arc(points), points, radius


def _first_line(sections: MeshSections, points, step, iterations, progress=None):
    """Step 2 from a first line: (points, radius, closed_share, (closed, stations)), the
    line refined on its sections until it moves less than INTERIOR_TOLERANCE, with the
    share of its middle 80 % of stations whose section is a closed loop round it (the best
    of the passes: a long tortuous tube's first line may leave a bend's sections open; a
    sheet's are never closed). radius is None if a pass kept fewer than 5 points."""
    radius = None
    closed_share, closed_count = 0.0, (0, 0)
    for iteration in range(iterations):
        if progress is not None:
            progress(iteration, iterations)
        new, radius, found = _refine(sections, points, step)
        middle = found[len(found) // 10:len(found) - len(found) // 10]
        share = float(np.mean(middle)) if len(middle) else 0.0
        if iteration == 0 or share > closed_share:
            closed_share, closed_count = share, (int(middle.sum()), len(middle))
        if len(new) < 5:
            return points, None, closed_share, closed_count
        moved = _distance_between(points, new)
        points = _resample(new, step, smoothing=SMOOTHING_LAMBDA)
        if moved < INTERIOR_TOLERANCE:
            break
    return points, radius, closed_share, closed_count


END_CHECK_LENGTH = 0.04
"""The stretch of line at each end over which candidate lines are compared [m]."""
END_CHECK_SPACING = 0.002


def end_residual(sections: MeshSections, line, radius: float) -> float:
    """How far the last END_CHECK_LENGTH of `line` is from being its own sections' centres:
    the rms distance from stations every END_CHECK_SPACING to the centre of the section
    normal to the line there (a closed loop, or where an open end's rim cuts it an arc of at
    least 180 degrees; `MeshSections.arc_around`). The true centre line is a fixed point of
    this (each section normal to it is centred on it); a line that leaves it tilts its
    sections and they pull away. inf if fewer than 5 stations have a section."""
    line = np.asarray(line)
    s = _arc(line)
    tangents = _tangents(line)
    gaps = []
    for x in np.arange(max(0.0, s[-1] - END_CHECK_LENGTH), s[-1] - 1e-4, END_CHECK_SPACING):
        p = np.array([np.interp(x, s, line[:, k]) for k in range(3)])
        t = np.array([np.interp(x, s, tangents[:, k]) for k in range(3)])
        t /= np.linalg.norm(t)
        section = sections.around(p, t) or sections.arc_around(p, t, 2.0 * radius,
                                                                 min_span=np.pi)
        if section is not None:
            gaps.append(np.linalg.norm(_centre(section, p, t) - p))
    return float(np.sqrt(np.mean(np.square(gaps)))) if len(gaps) >= 5 else np.inf


def _best_ends(sections: MeshSections, candidates, radius: float, marched=None,
               marched_at=(False, False)):
    """Of the lines the final passes made after their ends were recast ((points, radii)
    each), each end taken from the line whose end is nearest its own sections' centres
    (`end_residual`), the two halves joined half-way along. (A recast can wander: a cubic
    carried past the sections it was fitted to, then refined, then recast from its own
    wandering end.) `marched`, the line with the march's own ends, competes at the ends
    `marched_at` (head, tail) says."""
    allowed = [list(range(len(candidates)))] * 2
    if marched is not None and any(marched_at):
        allowed = [keys + [len(candidates)] if here else keys
                   for keys, here in zip(allowed, marched_at)]
        candidates = list(candidates) + [marched]
    if len(candidates) == 1:
        return candidates[0]
    head = min(allowed[0],
               key=lambda k: end_residual(sections, candidates[k][0][::-1], radius))
    tail = min(allowed[1],
               key=lambda k: end_residual(sections, candidates[k][0], radius))
    if head == tail:
        return candidates[head]
    (a, ra), (b, rb) = candidates[head], candidates[tail]
    sa, sb = _arc(a), _arc(b)
    first = sa < 0.5 * sa[-1]
    join = a[first][-1]
    second = np.flatnonzero(sb > sb[np.argmin(np.linalg.norm(b - join, axis=1))])
    return np.vstack([a[first], b[second]]), np.concatenate([ra[first], rb[second]])


def _distance_between(a, b):
    """Largest distance from a point of `b` to the polyline `a` (approximately: to its
    nearest vertex, the polylines being ~`step` apart at most)."""
    from scipy.spatial import cKDTree

    return float(cKDTree(a).query(b)[0].max()) if len(a) and len(b) else np.inf


FINAL_PASSES = 3
"""Section-and-smooth passes after the ends are grown back."""
SMOOTHING_LAMBDA = 1e-7
"""Weight [m^3] of the curvature penalty in the final smoothing spline: it smooths over
~lambda^(1/4) ~ 2 cm. (Generalised cross-validation chose far stronger smoothing, which
cut the corners of the rectum's bends by up to 2.4 mm on the round trip.)"""


def _end_tangent(points):
    """The unit tangent at the last point: a quadratic in arc length fitted to the last
    `MARCH_BASELINE` of centreline (at least 4 points), each point weighted by the length of
    line it stands for (the march's 1 mm steps would otherwise outweigh the 5 mm ones, and
    their scatter tilt the tangent)."""
    pts = np.asarray(points[-200:])[::-1]  # from the end backwards
    s = _arc(pts)
    use = min(len(pts), max(4, int(np.searchsorted(s, MARCH_BASELINE)) + 1))
    s, q = s[:use], pts[:use]
    if use >= 5:
        gaps = np.diff(s)
        w = np.sqrt(0.5 * (np.concatenate([[0.0], gaps]) + np.concatenate([gaps, [0.0]])))
        design = np.column_stack([np.ones(use), s, s ** 2])
        coef = np.linalg.lstsq(design * w[:, None], q * w[:, None], rcond=None)[0]
        t = -coef[1]
    else:
        t = q[0] - q[-1]
    return t / np.linalg.norm(t)


def _march(sections: MeshSections, loops, points: list, step: float, fine: float,
           reference: float):
    """Extends `points` past their last one until the tube ends or closes: returns (points,
    "flat cap" | "round cap" | "open" | "none", the length of the last stretch [m]: the
    ray's at a cap, the step to the end loop's centre at an open end).

    Each step: a ray along the end's tangent (`_end_tangent`) looks for the wall ahead;
    within `CAP_AHEAD` of the local radius it is a flat cap, within 1.1 radii and curving
    back toward the rays beside it (`_round_ahead`) a round cap's base: the line ends where
    the ray meets the wall. Otherwise a section `step` ahead (at most half-way to the wall
    ahead; 1 mm after a failed step), and its centre, corrected by a second section normal
    to the tangent through it, is the next point; a section that is no loop around the
    point, or whose centre is off by a quarter of the radius, or that is far wider than the
    last, ends the march: past an open end. The end is then the centre of a boundary loop
    (`loops`: the mesh's, vertices (K, 3)) ahead, within OPEN_END_AHEAD radii, else the last
    point, or a flat cap's disc the march stopped short of (`_flat_cap_ahead`). `reference`:
    the tube's typical radius, if the local one cannot be measured."""
    points = list(points)
    given = len(points)
    start = sections.around(points[-1], _end_tangent(points))
    last_radius = start.radius if start is not None else reference  # the local radius
    reference = last_radius
    size = step
    t = _end_tangent(points)
    for _ in range(5000):
        t = _end_tangent(points)
        p = points[-1]
        ahead = sections.ray(p, t, reach=3.0 * reference)
        # The wall straight ahead: near, a flat cap; as near as the tube is wide and
        # curving back toward the rays beside this one, a round cap whose base this is.
        if ahead <= CAP_AHEAD * max(reference, last_radius):
            points.append(p + ahead * t)
            # Near the wall: a flat cap, or a round one met off its axis (a bend or a flare
            # before it tilts the line), by the wall's own shape.
            flat = _wall_is_flat(sections, p + ahead * t, last_radius)
            return points, "flat cap" if flat else "round cap", ahead
        if ahead <= 1.1 * last_radius and _round_ahead(sections, p, t, last_radius, ahead):
            points.append(p + ahead * t)
            return points, "round cap", ahead
        size = min(size, max(fine, 0.5 * ahead))
        guess = p + size * t
        section = sections.around(guess, t)
        if section is None:   # an open end's rim may cut it: the arc left, if most of it
            section = sections.arc_around(guess, t, 2.0 * last_radius)
        good = section is not None
        if good:
            centre = _centre(section, guess, t)
            good = (np.linalg.norm(centre - guess) <= 0.25 * section.radius
                    and section.radius <= 1.5 * last_radius)
        if good:
            # Corrector: the section again, normal to the tangent through the new centre.
            t2 = _end_tangent(points + [centre])
            again = sections.around(centre, t2) or sections.arc_around(centre, t2,
                                                                       2.0 * last_radius)
            if again is not None:
                centre2 = _centre(again, centre, t2)
                if np.linalg.norm(centre2 - centre) <= 0.25 * again.radius:
                    centre, section = centre2, again
        if not good:
            if size > fine:
                size = fine
                continue
            break
        points.append(centre)
        last_radius = section.radius
    # An open end: its loop's centre, if one lies just ahead (measured in the tube's radius
    # where the march began, or the last one if wider: the last may be a fold's crest).
    p = points[-1]
    wide = max(last_radius, reference)
    best = None
    for ring in loops:
        centre = _loop_centroid(ring)
        along = float((centre - p) @ t)
        side = float(np.linalg.norm(centre - p - along * t))
        # Near, not off to the side more than it is ahead (a bend turns it), and ahead or
        # at most a radius behind (arcs of an oblique rim carry the march past its centre).
        if -wide <= along and np.linalg.norm(centre - p) <= OPEN_END_AHEAD * wide \
                and side <= max(0.5 * wide, along) and (best is None or along < best[0]):
            best = (along, centre)
    if best is not None:
        centre = best[1]
        # Marched past the end's centre: its own points, and the given line's within a
        # radius of the centre (a march whose last tangent turned aside once took the
        # given line back 8 cm, seed 270030).
        while len(points) > 5 and float((points[-1] - centre) @ t) > -1e-4 and \
                (len(points) > given or np.linalg.norm(points[-1] - centre) <= wide):
            points.pop()
        points.append(centre)
        return points, "open", float(np.linalg.norm(centre - points[-2]))
    rescued = _flat_cap_ahead(sections, points, step, last_radius)
    return rescued if rescued is not None else (points, "none", 0.0)


SQUARE_CUT = np.radians(10.0)
"""An open end's loop is a cut square to the tube if it is stretched along one direction
of its plane by less than a cut tilted this far from square would be (1 / cos). Measured on
the 20 open ends of seeds 40000-40094: cut square, 0-6 degrees (the loop's centroid within
0.1 mm of the true end); cut 20-45 degrees, 21-61 degrees (0.7-14 mm off: flared, bent).
Not always: haustral_oblique_mm's 30 degree cut through folds reads 5.8 degrees."""


def _loop_segments(ring):
    """(midpoints (K, 3), lengths (K,)) of a closed loop's segments (vertices (K, 3))."""
    previous = np.roll(ring, 1, axis=0)
    return 0.5 * (ring + previous), np.linalg.norm(ring - previous, axis=1)


def _loop_centroid(ring):
    """A closed loop's centroid as a curve (its segments' midpoints, length-weighted)."""
    mid, lengths = _loop_segments(ring)
    return np.sum(mid * lengths[:, None], axis=0) / lengths.sum()


def _square_cut(end, loops) -> bool:
    """Whether the boundary loop (vertices, (K, 3)) nearest `end` is a cut square to the
    tube. A section of a tube whose wall is alike all round its axis (round, or with folds
    alike in its sectors) has the same second moment about every line through its centroid
    in its plane; a cut tilted by a from square is stretched by 1 / cos(a) along the tilt,
    its largest moment 1 / cos(a)^2 times its second. Its centroid is then the lumen's centre
    whether the tube flares or not; a tilted cut's is off it where the tube flares or
    bends."""
    if not loops:
        return False
    ring = min(loops, key=lambda ring: float(np.linalg.norm(ring.mean(axis=0) - end)))
    mid, lengths = _loop_segments(ring)
    d = mid - _loop_centroid(ring)
    moments = np.linalg.eigvalsh((d * lengths[:, None]).T @ d)   # ascending
    return bool(moments[2] * np.cos(SQUARE_CUT) ** 2 <= moments[1])


def _closed_before(sections: MeshSections, line: list, body: int) -> list:
    """A march's `line` (its end an open end's loop centroid) without the points just before
    its end whose section normal to the line is not a closed loop around them; the first
    `body` points (the line the march started from) are kept."""
    keep = len(line) - 1
    while keep > max(body, 5):
        if sections.around(line[keep - 1], _end_tangent(line[:keep])) is not None:
            break
        keep -= 1
    return list(line[:keep]) + [line[-1]]


FLAT_CAP_REACH = 3.0
"""How far ahead of where the march stopped (in radii) a flat cap is looked for."""
FLAT_CAP_HOLD = 0.5
"""The last stretch of a line joined to a flat cap that the final passes leave as it is (in
radii): the rest of the join is refined by its sections like the line behind it."""


def _flat_cap_ahead(sections: MeshSections, points, step, radius):
    """Where the march stopped short of a flat cap (in a flare before it the sections tilt,
    their centres pull to the wide side and the march stops): the cap's disc where the ray
    ahead meets it within FLAT_CAP_REACH radii (`_flat_disc`), and the line on to the disc's
    area centroid along a cubic (Hermite) that leaves the march's end along its tangent and
    meets the disc square, as a tube's axis meets its flat end. Returns (points, "flat cap",
    the stretch held at the end: at most FLAT_CAP_HOLD radii) or None (no flat disc ahead,
    or one turned more than 60 degrees from the line or behind it)."""
    p, t = points[-1], _end_tangent(points)
    ahead = sections.ray(p, t, reach=FLAT_CAP_REACH * radius)
    if not np.isfinite(ahead):
        return None
    disc = _flat_disc(sections, p + ahead * t, radius)
    if disc is None:
        return None
    areas = sections.face_areas[disc]
    centre = np.average(sections.face_centres[disc], axis=0, weights=areas)
    normal = np.average(sections.face_normals[disc], axis=0, weights=areas)
    normal /= np.linalg.norm(normal)
    if normal @ t < 0.0:
        normal = -normal
    if normal @ t < np.cos(np.radians(60.0)) or (centre - p) @ t <= 0.0:
        return None
    chord = float(np.linalg.norm(centre - p))
    u = np.linspace(0.0, 1.0, max(2, int(np.ceil(chord / step))) + 1)[1:, None]
    join = ((2 * u**3 - 3 * u**2 + 1) * p + (u**3 - 2 * u**2 + u) * chord * t
            + (3 * u**2 - 2 * u**3) * centre + (u**3 - u**2) * chord * normal)
    length = float(_arc(np.vstack([p, join]))[-1])
    return list(points) + list(join), "flat cap", min(length, FLAT_CAP_HOLD * radius)


def _piece(sections: MeshSections, mask, seed: int):
    """The faces of `mask` joined to face `seed` through edges shared by two faces of it."""
    edge_of = sections.face_edges.reshape(-1)
    face_of = np.repeat(np.arange(len(sections.faces)), 3)
    order = np.argsort(edge_of, kind="stable")
    e, f = edge_of[order], face_of[order]
    pair = np.flatnonzero(e[1:] == e[:-1])
    a, b = f[pair], f[pair + 1]
    keep = mask[a] & mask[b]
    n = len(sections.faces)
    graph = coo_matrix((np.ones(int(keep.sum())), (a[keep], b[keep])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    return mask & (label == label[seed])


def _flat_disc(sections: MeshSections, wall, radius):
    """The faces of a flat cap's disc where a ray meets the wall at `wall`, or None: the faces
    joined by edges to the one met that lie in its plane (within 2 % of `radius`) and turn
    from it by less than FLAT_CAP_ANGLE, if they cover at least FLAT_CAP_SHARE of the circle
    of `radius` (a disc is at least as wide as the tube, all of it counts however far it
    reaches where the end flares; on a sphere only a patch of ~7 % of the circle turns by
    less than FLAT_CAP_ANGLE, on a wall a strip)."""
    centres = sections.face_centres
    hit = int(np.argmin(np.linalg.norm(centres - wall, axis=1)))
    normal = sections.face_normals[hit]
    flat = (np.abs((centres - centres[hit]) @ normal) < 0.02 * radius) \
        & (sections.face_normals @ normal > np.cos(FLAT_CAP_ANGLE))
    disc = _piece(sections, flat, hit)
    if sections.face_areas[disc].sum() < FLAT_CAP_SHARE * np.pi * radius ** 2:
        return None
    return disc


def _wall_is_flat(sections: MeshSections, wall, radius) -> bool:
    """Whether the wall where a ray meets it (`wall`) is a flat cap's disc (`_flat_disc`)."""
    return _flat_disc(sections, wall, radius) is not None


FLAT_CAP_ANGLE = np.radians(15.0)
"""Faces of a flat cap's disc turn from one another by less than this (mesh noise only)."""
FLAT_CAP_SHARE = 0.3
"""A flat cap's disc covers at least this share of the circle of the tube's radius where
the march stops (all of it, or more where the end flares; a tilt of the disc against the
section, or a radius taken from a fold's crest, leave well over a third)."""


OPEN_END_AHEAD = 3.0
"""How far ahead of where the march stops (in radii) an open end's boundary loop may lie:
the sections before an oblique or ragged end are cut open by it, and one across a deep
fold is far narrower than the next (the march stops at either)."""


def _first_crossing(curve, q, normal, u):
    """The first u at which `curve` (u -> (point, tangent)) crosses the plane through `q`
    normal to `normal`: the first sign change over the samples `u`, bisected; None if none."""
    side = lambda x: float((curve(x)[0] - q) @ normal)
    values = np.array([side(x) for x in u])
    change = np.flatnonzero(np.sign(values[1:]) != np.sign(values[:-1]))
    if len(change) == 0:
        return None
    lo, hi = u[change[0]], u[change[0] + 1]
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.sign(side(mid)) == np.sign(values[change[0]]) else (lo, mid)
    return 0.5 * (lo + hi)


def _plane_crossing(curve, loops, near, reach):
    """u at which `curve` (u -> (point, tangent)) crosses the least-squares plane of the
    boundary loop (vertices, (K, 3)) whose centroid lies nearest `near`, searched over
    (0, 1.5 `reach`]; None if there is no loop within `reach` of `near`, no crossing, or
    the crossing is not well inside the loop (within a third of its mean radius of its
    centroid: a cubic carried past the sections it was fitted to may wander)."""
    best = None
    for ring in loops:
        d = float(np.linalg.norm(ring.mean(axis=0) - near))
        if d <= reach and (best is None or d < best[0]):
            best = (d, ring)
    if best is None:
        return None
    ring = best[1]
    q = ring.mean(axis=0)
    normal = np.linalg.svd(ring - q)[2][2]
    u_cut = _first_crossing(curve, q, normal, np.linspace(0.0, 1.5 * reach, 61))
    if u_cut is None:
        return None
    loop_radius = float(np.mean(np.linalg.norm(ring - q, axis=1)))
    if np.linalg.norm(curve(u_cut)[0] - q) > loop_radius / 3.0:
        return None
    return u_cut


def _recast_caps(sections: MeshSections, points, step, ends, jumps, reference, loops=()):
    """The round caps' last stretches (`jumps`, [m]) made again from the line behind them,
    now that it is refined: a cubic fitted to dense section centres over its last
    `RECAST_BASELINE` (`_end_fit`) is followed to the cap's base, the centre of the sphere
    fitted to the cap's far part (`_cap_sphere`), and the line goes on straight along its
    tangent there to the wall (a round cap's sections are centred on any line through its
    centre: the tube's direction where it closes is all there is to follow). A flat cap's
    stretch, the march's, is kept (its ray is short: a third of a radius). Returns (points,
    jumps)."""
    jumps = list(jumps)
    for side in (0, 1):
        if jumps[side] <= 0.0 or ends[side] not in ("round cap", "open"):
            continue
        line = points[::-1] if side == 0 else points
        s = _arc(line)
        body = line[s <= s[-1] - jumps[side] + 1e-9]
        if len(body) < 5:
            continue
        local = sections.around(body[-1], _end_tangent(body))
        radius = local.radius if local is not None else reference
        if ends[side] == "open":
            # The stretch to the end, whose sections the end cuts open: the cubic of the
            # section centres behind it, to where it crosses the plane of the end's loop
            # (an oblique cut's centre; its loop's centroid is off the axis where the tube
            # flares or bends), or through the loop's centre.
            end = line[-1]
            u_end = float(np.linalg.norm(end - body[-1]))
            if u_end <= step:
                continue
            curve = _end_fit(sections, body, arcs=radius)
            u_cut = _plane_crossing(curve, loops, end, u_end) if curve is not None else None
            if u_cut is None:   # the cubic wanders: straight on along the body's end tangent
                p_end, t_end = body[-1], _end_tangent(body)
                curve = lambda u, p_end=p_end, t_end=t_end: (p_end + u * t_end, t_end)
                u_cut = _plane_crossing(curve, loops, end, u_end)
            if u_cut is None:
                curve = _end_fit(sections, body, through=(u_end, end), arcs=radius)
                if curve is None:
                    continue
                u_cut = u_end
            else:
                end = curve(u_cut)[0]
            count = int(np.ceil(u_cut / step))
            extension = [curve(u)[0] for u in np.linspace(0.0, u_cut, count + 1)[1:-1]]
            points = np.vstack([body] + ([np.asarray(extension)] if extension else [])
                               + [end[None, :]])
            points = points[::-1] if side == 0 else points
            jumps[side] = u_cut
            continue
        # The sections within a quarter radius of the cap's base reach into it (a plane
        # tilted by 0.02 rad does, 0.5 mm off the base) and are left out.
        curve = _end_fit(sections, body, stop=-ROUND_CAP_CLEAR * radius)
        if curve is None:
            continue
        reach = 2.0 * jumps[side] + radius
        p0, t0 = curve(0.0)
        ahead = sections.ray(p0, t0, reach=reach)
        sphere = _cap_sphere(sections, p0, t0, ahead) if np.isfinite(ahead) else None
        extension, u_base = [], 0.0
        if sphere is not None:
            u_base = float(np.clip((sphere[0] - p0) @ t0, 0.0, 0.5 * sphere[1]))
            curve = _end_fit(sections, body, stop=u_base - ROUND_CAP_CLEAR * sphere[1],
                             through=(u_base, sphere[0])) or curve
            count = int(np.ceil(u_base / step))
            extension = [curve(u)[0] for u in np.linspace(0.0, u_base, count + 1)[1:]]
            p0, t0 = curve(u_base)
            ahead = sections.ray(p0, t0, reach=reach)
        if not np.isfinite(ahead):
            continue
        count = max(1, int(np.ceil(ahead / step)))
        extension += list(p0 + np.outer(np.arange(1, count + 1) / count * ahead, t0))
        points = np.vstack([body, np.asarray(extension)])
        points = points[::-1] if side == 0 else points
        jumps[side] = u_base + ahead
    return points, jumps


ROUND_CAP_CLEAR = 0.25
"""Section centres are fitted up to this share of the radius before a round cap's base."""
RECAST_BASELINE = 0.02
"""A cap's last stretch follows a cubic fitted to this much line before it [m], ...
(4 cm cut the corner of a bend of 80 degrees ending 1 cm before a round cap: the cubic's
tangent there 7 degrees astray, 2.1 mm at the apex; 2 cm: 0.4 mm, the other tubes alike)"""
RECAST_SPACING = 0.001
"""... of section centres this far apart [m] (the line's own points, 5 mm apart, left the
tangent ~0.015 rad astray: 0.5 mm at a round cap's apex)."""


def _cubic(u, points, weights=None):
    """The cubic in u fitted to `points` (least squares): u -> (point, unit tangent)."""
    w = np.ones(len(u)) if weights is None else weights
    design = np.column_stack([np.ones(len(u)), u, u ** 2, u ** 3])
    coef = np.linalg.lstsq(design * w[:, None], points * w[:, None], rcond=None)[0]

    def curve(x):
        point = coef[0] + x * coef[1] + x ** 2 * coef[2] + x ** 3 * coef[3]
        tangent = coef[1] + 2 * x * coef[2] + 3 * x ** 2 * coef[3]
        return point, tangent / np.linalg.norm(tangent)

    return curve


def _end_fit(sections: MeshSections, body, stop: float = 0.0, through=None,
             arcs: float = 0.0):
    """The cubic in arc length fitted to section centres every `RECAST_SPACING` over
    `RECAST_BASELINE` of line up to `stop` [m] past the end of `body` (< 0: before it; > 0:
    on along the cubic through the body's points): a function u -> (point, unit tangent), u
    [m] past the body's end. The sections are cut normal to a cubic fitted to the body's
    own points (its polyline's tangents kink by ~0.02 rad at its points in a tight bend;
    cutting them normal to the centres' own cubic, again and again, drifts at the end).
    `through`: (u, point) the cubic is to pass through (a round cap's centre). `arcs`: the
    tube's radius near an open end, whose rim cuts the last sections open: their arcs are
    used (`MeshSections.arc_around`). None if fewer than 10 sections are found."""
    s = _arc(body) - _arc(body)[-1]  # <= 0, the body's end at 0
    u = np.arange(max(s[0], stop - RECAST_BASELINE), stop + 1e-9, RECAST_SPACING)
    window = s >= u[0] - 0.01
    if len(u) < 10 or window.sum() < 5:
        return None
    guide = _cubic(s[window], body[window])
    centres, at = [], []
    for x in u:
        q, tq = guide(x)
        section = sections.around(q, tq)
        if section is None and arcs:
            section = sections.arc_around(q, tq, 2.0 * arcs)
        if section is None:
            continue
        c = _centre(section, q, tq)
        if np.linalg.norm(c - q) <= 0.1 * section.radius:
            centres.append(c)
            at.append(x)
    if len(centres) < 10:
        return None
    at, centres = np.asarray(at), np.asarray(centres)
    weights = np.ones(len(at))
    if through is not None:
        at = np.append(at, through[0])
        centres = np.vstack([centres, through[1]])
        weights = np.append(weights, np.sqrt(len(weights)))
    return _cubic(at, centres, weights)


def _cap_sphere(sections: MeshSections, p, t, ahead):
    """(centre, radius) of the sphere fitted (algebraically) to the mesh's vertices in a
    round cap's far part, those beyond 60 % of the way from `p` to where the ray along `t`
    meets the cap (`ahead` [m]) and within `ahead` of that line; None if fewer than 20, or
    if they are not near a sphere (rms misfit over 5 % of its radius), or the sphere is not
    about as wide as the cap is deep from `p` (0.6-1.5 times)."""
    vertices = sections.vertices
    d = vertices - p
    along = d @ t
    side = np.linalg.norm(d - np.outer(along, t), axis=1)
    pick = (along > 0.6 * ahead) & (along < 1.2 * ahead) & (side < ahead)
    if pick.sum() < 20:
        return None
    x = vertices[pick] - p
    design = np.column_stack([2 * x, np.ones(len(x))])
    sol = np.linalg.lstsq(design, np.sum(x ** 2, axis=1), rcond=None)[0]
    centre = sol[:3]
    radius_sq = sol[3] + centre @ centre
    if radius_sq <= 0.0:
        return None
    radius = float(np.sqrt(radius_sq))
    misfit = np.sqrt(np.mean((np.linalg.norm(x - centre, axis=1) - radius) ** 2))
    if misfit > 0.05 * radius or not 0.6 * ahead <= radius <= 1.5 * ahead:
        return None
    return p + centre, radius


def _before(line, keep):
    """`line` without the stretch at its end whose points are not to be kept (only that
    stretch: a tortuous tube's far parts may fail the same test)."""
    kept = np.flatnonzero(keep[::-1])
    return line[:len(line) - kept[0]] if len(kept) else line[:0]


def _finish_cap(sections: MeshSections, line, reference, step):
    """A flat cap's last stretch made from the cap itself.

    The wall ahead of the line's last radius is fitted with a plane (the faces within 0.7
    radii of where the line's ray meets it). If it fits (rms within FLAT_CAP_RMS of the
    radius), the line ends at the area centroid of the disc (the faces about as flat as that
    plane joined to the one the ray meets: all of the disc however wide, a flared end's up
    to half as wide again as the tube before it), reached straight along the disc's normal
    over the last half radius: the line's own direction there (a bend just before the cap
    tilts it; a section near the disc cuts it) is not used. A round wall is left as the
    march made it."""
    s = _arc(line)
    t = _end_tangent(line)
    local = sections.around(line[-1], t)
    radius = local.radius if local is not None else reference
    back = np.array([np.interp(s[-1] - radius, s, line[:, k]) for k in range(3)])
    ahead = sections.ray(back, t, reach=4.0 * radius)
    if not np.isfinite(ahead):
        return line
    wall = back + ahead * t
    centres = sections.face_centres
    areas = sections.face_areas
    near = np.linalg.norm(centres - wall, axis=1) < 0.7 * radius
    if near.sum() < 20:
        return line
    x = centres[near]
    q = x.mean(axis=0)
    normal = np.linalg.svd(x - q)[2][2]
    if normal @ t < 0.0:
        normal = -normal
    if np.sqrt(np.mean(((x - q) @ normal) ** 2)) > FLAT_CAP_RMS * radius:
        # A line astray (a flare and a bend just before the cap) meets the disc near its
        # rim, and the wall beside it spoils the plane: the disc is looked for again among
        # the faces that face the line, by their own normals.
        found = _facing_disc(sections, wall, t, radius)
        if found is None:
            return line   # not flat: a round cap the march took for a flat one is left
        q, normal = found
    flat = ((np.abs((centres - q) @ normal) < 0.03 * radius)
            & (np.abs(sections.face_normals @ normal) > np.cos(np.radians(15.0))))
    hit = int(np.argmin(np.where(flat, np.linalg.norm(centres - wall, axis=1), np.inf)))
    disc = _piece(sections, flat, hit)
    if disc.sum() < 10:
        return line
    end = np.average(centres[disc], axis=0, weights=areas[disc])
    start = end - 0.5 * radius * normal
    body = _before(line, (line - end) @ normal < -0.5 * radius - 0.5 * step)
    count = max(1, int(np.ceil(0.5 * radius / step)))
    tail = start + np.outer(np.arange(0, count + 1) / count * 0.5 * radius, normal)
    return np.vstack([body, tail])


def _facing_disc(sections: MeshSections, wall, t, radius):
    """(point, normal) of the plane of a flat cap's disc near `wall` (where the line's ray
    along `t` meets it), from the faces within 1.5 radii of it that face the line (normals
    within FACING_ANGLE of `t`): their area-weighted mean normal, then the faces within 15
    degrees of it joined to the one nearest `wall` (`_piece`), their area centroid and mean
    normal; if those fit the plane within FLAT_CAP_RMS of the radius and cover at least a
    third of the circle of `radius`. Else None."""
    centres, areas, normals = sections.face_centres, sections.face_areas, sections.face_normals
    big = np.linalg.norm(centres - wall, axis=1) < 1.5 * radius
    facing = big & (np.abs(normals @ t) > np.cos(FACING_ANGLE))
    if facing.sum() < 20:
        return None
    signed = normals[facing] * np.sign(normals[facing] @ t)[:, None]
    normal = np.average(signed, axis=0, weights=areas[facing])
    normal /= np.linalg.norm(normal)
    flat = big & (np.abs(normals @ normal) > np.cos(np.radians(15.0)))
    if flat.sum() < 20:
        return None
    # The piece of those joined to the one nearest the ray's hit (ring folds near the cap
    # face the line too, but stand apart from the disc).
    hit = int(np.argmin(np.where(flat, np.linalg.norm(centres - wall, axis=1), np.inf)))
    disc = _piece(sections, flat, hit)
    if areas[disc].sum() < np.pi * radius ** 2 / 3.0:
        return None
    q = np.average(centres[disc], axis=0, weights=areas[disc])
    normal = np.average(normals[disc] * np.sign(normals[disc] @ normal)[:, None], axis=0,
                        weights=areas[disc])
    normal /= np.linalg.norm(normal)
    if np.sqrt(np.average(((centres[disc] - q) @ normal) ** 2, weights=areas[disc])) > \
            FLAT_CAP_RMS * radius:
        return None
    return q, normal


FACING_ANGLE = np.radians(50.0)
"""How far a face's normal may turn from the line's direction and still count as facing it
(`_facing_disc`): a bend of 60-70 degrees over the last 5 cm before a cap tilts the line's
end by up to about 40 degrees to its disc."""


FLAT_CAP_RMS = 0.03
"""A cap is flat if the plane fitted to its faces near the line's end fits them within this
share of the radius (a hemisphere's: ~0.08)."""


AXIS_WINDOW = 0.3
"""An open end's axis is fitted to the wall within this many radii of the end (behind it, and
ahead of it on an oblique cut's far side) as a straight line: a tube bends no tighter than
its radius (r * curvature < 1, or its inner wall folds over), and over 0.3 radii the
tightest such bend leaves a straight line by at most 0.011 radii (0.2 mm in a 2 cm tube)."""
AXIS_ITERATIONS = 6
"""Passes of the axis's fit: where each normal line passes the axis, and which faces' normals
miss it (their Cauchy weights), settle as the axis does."""
AXIS_MAX_TILT = np.cos(np.radians(45.0))
"""Faces whose normal turns more than 45 degrees toward the axis are left out of its fit:
the rim's chamfer, a fold's steep flank; a flared wall turns by at most ~25 degrees."""
AXIS_MIN_FACES = 30
"""Fewer faces than this in the window leave the end as the sections made it (the line has
four unknowns; a coarse mesh's 0.3-radius band holds 40 faces and more)."""


def _wall_axis(sections: MeshSections, end, t, radius, back, ahead):
    """The axis of the tube's last stretch from its wall's normals: for a section that is a
    circle round the axis, flared or not, every normal of the wall meets the axis; a haustral
    fold's normals turn aside alike in the three sectors. The faces within 2 radii of the
    line through `end` along `t`, from `back` [m] behind `end` to `ahead` [m] ahead, their
    normals facing it and within 45 degrees of square to it (AXIS_MAX_TILT): the axis, a
    straight line, is the least-squares fit to their normal lines (each face's distance
    from it where its normal line passes it, area-weighted, with a Cauchy weight for the
    faces whose normal misses it), AXIS_ITERATIONS times from the line through `end` along
    `t`. Returns a function a -> (point, unit tangent) (a [m] along `t` from
    `end`), or None if fewer than AXIS_MIN_FACES faces are used."""
    _, e1, e2 = _plane_basis(t)
    centres = sections.face_centres
    normals = sections.face_normals
    areas = sections.face_areas
    rel = centres - end
    a0 = rel @ t
    side = rel - np.outer(a0, t)
    near = (a0 >= -back - radius) & (a0 <= ahead + radius) \
        & (np.linalg.norm(side, axis=1) < 2.0 * radius) \
        & (np.abs(normals @ t) < AXIS_MAX_TILT) & (np.einsum("ij,ij->i", -side, normals) > 0.0)
    if near.sum() < AXIS_MIN_FACES:
        return None
    p, n, w_area = rel[near], normals[near], areas[near]
    inside = (a0[near] >= -back) & (a0[near] <= ahead)
    coef = np.zeros(4)   # offsets along e1 and e2: c0 + c1 a each

    def proj(v):   # the part of each row of v across its face's normal
        return v - np.einsum("ij,ij->i", v, n)[:, None] * n

    pe1, pe2 = proj(np.tile(e1, (len(p), 1))), proj(np.tile(e2, (len(p), 1)))
    for _ in range(AXIS_ITERATIONS):
        # Where each normal line passes the current axis: a there (from the point of the
        # normal line nearest the axis point at the face's own a).
        a = p @ t
        q = np.outer(a, t) + np.outer(coef[0] + coef[1] * a, e1) \
            + np.outer(coef[2] + coef[3] * a, e2)
        lam = np.einsum("ij,ij->i", q - p, n)
        a = (p + lam[:, None] * n) @ t
        # The axis point at a from the normal line: (I - n n^T)(axis(a) - p), linear in the
        # coefficients.
        base = proj(np.outer(a, t) - p)
        design = np.stack([pe1, pe1 * a[:, None], pe2, pe2 * a[:, None]], axis=2)  # (K, 3, 4)
        resid = np.linalg.norm(base + design @ coef, axis=1)
        # Faces in the window (their normals may pass the axis outside it: a fold's flanks
        # turn along the tube), facing the axis from about the tube's distance.
        use = inside & (lam > 0.3 * radius) & (lam < 3.0 * radius) \
            & (a >= -back - radius) & (a <= ahead + radius)
        if use.sum() < AXIS_MIN_FACES:
            return None
        scale = max(2.0 * float(np.median(resid[use])), 0.01 * radius)
        w = np.sqrt(w_area * use / (1.0 + (resid / scale) ** 2))[:, None]
        coef = np.linalg.lstsq((design * w[:, :, None]).reshape(-1, 4), (-base * w).reshape(-1),
                               rcond=None)[0]
    tangent = t + coef[1] * e1 + coef[3] * e2
    tangent /= np.linalg.norm(tangent)
    return lambda x: (end + x * t + (coef[0] + coef[1] * x) * e1 + (coef[2] + coef[3] * x) * e2,
                      tangent)


def _open_axis_end(sections: MeshSections, line, reference, step, loops):
    """An open end's last stretch made again on its wall's axis (`_wall_axis`, fitted within
    AXIS_WINDOW radii of the end): to where the axis crosses the plane of the end's loop (an
    oblique cut's centre, on the axis; the true centre line ends there, the loop's own
    centroid is off it where the tube flares). The line's points within AXIS_WINDOW radii
    of the new end are the axis's, those up to twice that blended into it. The line is
    returned as it is if there is no such axis (too few faces) or no crossing near the
    loop's centre (`_plane_crossing`)."""
    t = _end_tangent(line)
    end = line[-1]
    local = sections.around(end - reference * t, t)
    radius = local.radius if local is not None else reference
    window = AXIS_WINDOW * radius
    rings = [ring for ring in loops
             if np.linalg.norm(ring.mean(axis=0) - end) <= 2.0 * radius]
    if not rings:
        return line
    ring = min(rings, key=lambda ring: np.linalg.norm(ring.mean(axis=0) - end))
    # The first window about the loop's centre (within a quarter radius of the axis's
    # crossing even where the tube flares; the sections' end may be past an oblique cut's
    # centre, or short of it), the next about the crossing found.
    a_end = float((ring.mean(axis=0) - end) @ t)
    for _ in range(3):
        curve = _wall_axis(sections, end, t, radius, window - a_end, window + a_end)
        if curve is None:
            return line
        u_end = _plane_crossing(lambda u: curve(u - radius), loops, end, 2.0 * radius)
        if u_end is None:
            return line
        moved = u_end - radius - a_end
        a_end = u_end - radius
        if abs(moved) < 0.1 * window:
            break
    a_line = (line - end) @ t
    s = _arc(line)
    tail = s > s[-1] - 4.0 * radius - abs(a_end)   # only the end's stretch is compared along t
    body = _before(line, ~tail | (a_line < a_end - 2.0 * window))
    if len(body) < 3:
        return line
    blend = line[len(body):]
    blend = blend[(blend - end) @ t < a_end - window]
    out = [body]
    for p in blend:
        a = float((p - end) @ t)
        w = np.clip((a - (a_end - 2.0 * window)) / window, 0.0, 1.0)
        out.append((p + w * (curve(a)[0] - p))[None, :])
    a_from = float((out[-1][-1] - end) @ t)
    if a_end <= a_from:
        return line
    count = max(1, int(np.ceil((a_end - a_from) / step)))
    out.append(np.array([curve(x)[0] for x in np.linspace(a_from, a_end, count + 1)[1:]]))
    return np.vstack(out)


SETTLE_OPEN_ENDS = True
"""Whether `extract_centerline` settles each open end's last stretch on its own sections
(`_settle_open_end`, step 7 of the module's docstring)."""
FIT_OPEN_ENDS = True
"""Whether `extract_centerline` makes each open end and flat cap's last stretch again from
its wall fitted as a tube (`_fitted_open_end`, `_fitted_cap_end`, step 7 of the module's
docstring), where that end is nearer its sections' centres."""
SETTLE_LENGTH = 0.05
"""The stretch [m] before an open end that `_settle_open_end` makes again."""
SETTLE_PASSES = 12
"""Passes of `_settle_open_end` (each: centre, fit the cubic, cut at the loop's plane)."""
SETTLE_ANCHOR = 20.0
"""Weight of the line's last 8 points behind the settled stretch in its cubic (against 1
for each section centre): the stretch leaves the line along it."""


def _settle_open_end(sections: MeshSections, line, radius, step, loops):
    """An open end's last SETTLE_LENGTH made again as a fixed point of "each section
    normal to the line is centred on it" (`end_residual`'s test), which the passes behind
    the end do not reach where a flare or a bend before the rim leaves the sections cut
    open: repeatedly, each point of the stretch goes to the centre of its section (a closed
    loop, or an arc of at least 180 degrees), a cubic in arc length is fitted to those
    centres and to the line's last 8 points behind the stretch (weighted SETTLE_ANCHOR),
    and the stretch is that cubic up to the plane of the end's loop (`_plane_crossing`).
    The line is returned as it is if it is shorter than three stretches, if fewer than
    four sections are found, or if the cubic does not cross the loop near its centre."""
    line = np.asarray(line)
    s = _arc(line)
    if s[-1] < 3.0 * SETTLE_LENGTH:
        return line
    base = line[s <= s[-1] - SETTLE_LENGTH]
    s_base = _arc(base)
    anchor, u_anchor = base[-8:], s_base[-8:] - s_base[-1]
    current = line
    for _ in range(SETTLE_PASSES):
        s_now = _arc(current)
        tangents = _tangents(current)
        centres, u = [], []
        for k in np.flatnonzero(s_now > s_base[-1]):
            p, t = current[k], tangents[k]
            section = sections.around(p, t) or sections.arc_around(p, t, 2.0 * radius,
                                                                     min_span=np.pi)
            if section is None:
                continue
            centre = _centre(section, p, t)
            if np.linalg.norm(centre - p) <= 0.5 * radius:
                centres.append(centre)
                u.append(s_now[k] - s_base[-1])
        if len(centres) < 4:
            return line
        weights = np.r_[[SETTLE_ANCHOR] * len(anchor), np.ones(len(centres))]
        x = np.vstack([anchor, centres])
        coef = np.linalg.lstsq(np.vander(np.r_[u_anchor, u], 4) * weights[:, None],
                               x * weights[:, None], rcond=None)[0]

        def curve(v, coef=coef):
            d = np.array([3.0 * v * v, 2.0 * v, 1.0]) @ coef[:3]
            return np.vander([v], 4)[0] @ coef, d / np.linalg.norm(d)

        # The crossing is looked for from 1.5 radii before the stretch's length to as far
        # beyond it (`_plane_crossing` searches 1.5 times its reach from where it starts).
        u_from = max(0.0, SETTLE_LENGTH - 1.5 * radius)
        u_end = _plane_crossing(lambda v: curve(u_from + v), loops, current[-1], 2.0 * radius)
        if u_end is None:
            return line
        u_end += u_from
        v = np.linspace(0.0, u_end, max(3, int(np.ceil(u_end / step)) + 1))[1:]
        current = np.vstack([base, [curve(x)[0] for x in v]])
    return current


LOOP_PLANE_TOLERANCE = 0.001
"""How far [m] along its tangent an open end may stop short of, or pass, the plane of its
loop before `_reach_loop_plane` takes it there (a rim's loop is flat to about 1 mm where
the mesh cuts it)."""


def _reach_loop_plane(line, radius, step, loops):
    """An open end taken to the plane of its boundary loop (the true centre line of a cut
    tube ends where it meets the cut, obliquely or not): along the end's tangent
    (`_end_tangent`) if it stopped short, cut there if it passed it. The crossing is
    `_plane_crossing`'s, on the straight line through the end along its tangent, searched
    from a radius behind the end; the line is returned as it is if its end is within
    LOOP_PLANE_TOLERANCE of the crossing, if there is none (no loop's centroid within two
    radii of the end, or the crossing not well inside the loop), or if it is more than a
    radius ahead of the end."""
    line = np.asarray(line)
    end = line[-1]
    t = _end_tangent(line)
    u = _plane_crossing(lambda x: (end + (x - radius) * t, t), loops, end, 2.0 * radius)
    if u is None or abs(u - radius) <= LOOP_PLANE_TOLERANCE or u > 2.0 * radius:
        return line
    u -= radius
    crossing = end + u * t
    if u > 0.0:
        count = max(1, int(np.ceil(u / step)))
        return np.vstack([line, end + np.outer(np.arange(1, count + 1) / count * u, t)])
    a = _arc(line)
    keep = a < a[-1] + u - 1e-9
    return np.vstack([line[keep], crossing])


OPEN_FIT_LENGTH = 0.05
"""The stretch [m] before an open end whose wall `_fitted_open_end` fits as a tube."""
OPEN_FIT_TURN = 40.0
"""Largest turn [degrees] of the line over that stretch for which an open end's fit is
tried: its axis is a cubic across the stretch's chord, which follows a bend of 40 degrees
before the end (the line turning by 11-39 degrees over the stretch, seeds 260000-260089)
but not always one of 60 or 70 (seen on seeds 240002, 260050 and 260056, turning by 45, 55
and 56 degrees: 0.5 -> 4.9, 1.2 -> 2.1 and 0.2 -> 1.4 mm)."""
OBLIQUE_FIT_SLACK = 1.5
"""At an oblique open end, the end the wall's fit makes (its axis's offsets quadratics there:
where only the far side of the cut is left, a cubic trades its offset for the radius) is
kept unless its `end_residual` exceeds the line's by more than this factor: the sections
there are open arcs that a fold pulls aside, so the residual is biased. Chosen on the open
ends of seeds 260000 and 270000 (any factor from 1.1 to 2 gave the same: 7 ends over 2 mm
-> 5), scored on fresh seeds."""
CAP_FIT_TURN = 60.0
"""The same for a flat cap's fit, which is checked against the disc's centroid as well
(CAP_FIT_AGREE): a bend of 40 degrees before the cap turned seed 260024's line by 54."""
CAP_FIT_AGREE = 0.1
"""How near [radii] the disc's centroid (the end `_finish_cap` makes) a flat cap's fitted
axis must meet the disc's plane."""
OPEN_FIT_FACES = 4000
"""Most faces the open end's fit uses (a fixed random sample of a finer mesh's)."""
FLAT_FIT_CLEAR = 0.0015
"""How far [m] before a flat cap's disc the wall fitted by `_fitted_cap_end` begins (the
disc's own faces lie in its plane)."""


def _open_tube_parts(x, faces):
    """The tube of `_fitted_open_end` with parameters x (three cubics in zeta: the axis's
    offsets along e1 and e2 [m], its radius [m]) at the faces (rows: along e1, along e2 [m],
    zeta): each face's zeta projected on the axis (three Newton steps) and its distance
    from the tube [m] (negative inside)."""
    poly = np.polynomial.polynomial
    cx, cy, cr = x[0:4], x[4:8], x[8:12]
    dcx, dcy = poly.polyder(cx), poly.polyder(cy)
    zeta = faces[:, 2].copy()
    for _ in range(3):
        ax, ay = poly.polyval(zeta, cx), poly.polyval(zeta, cy)
        gx, gy = poly.polyval(zeta, dcx), poly.polyval(zeta, dcy)
        d = np.column_stack([faces[:, 0] - ax, faces[:, 1] - ay,
                             (faces[:, 2] - zeta) * OPEN_FIT_LENGTH])
        g = np.column_stack([gx, gy, np.full_like(gx, OPEN_FIT_LENGTH)])
        zeta = zeta + np.sum(d * g, axis=1) / np.sum(g * g, axis=1)
    d = np.column_stack([faces[:, 0] - poly.polyval(zeta, cx),
                         faces[:, 1] - poly.polyval(zeta, cy),
                         (faces[:, 2] - zeta) * OPEN_FIT_LENGTH])
    return np.linalg.norm(d, axis=1) - poly.polyval(zeta, cr)


def _open_tube_residuals(x, faces, weights, inside):
    gap = _open_tube_parts(x, faces)
    return weights * np.where(gap < 0.0, inside * gap, gap)


def _fitted_axis(sections: MeshSections, line, radius, q, normal, clear: float = -1e-4,
                 max_turn: float = OPEN_FIT_TURN, degree: int = 3):
    """The axis of the wall over the line's last OPEN_FIT_LENGTH fitted as a tube (see
    `_fitted_open_end`), as a function u -> (point, unit tangent) of length along the
    stretch's chord from a third of the way in, or None. Only faces on the line's side of the
    plane through `q` normal to `normal`, and at least `clear` [m] from it, are fitted; None
    if the line turns by more than `max_turn` degrees over the stretch. The axis's offsets
    from the chord are polynomials of `degree` (2 or 3); the radius is a cubic."""
    from scipy.optimize import least_squares

    s = _arc(line)
    if s[-1] < 3.0 * OPEN_FIT_LENGTH:
        return None
    stretch = line[s >= s[-1] - OPEN_FIT_LENGTH]
    turn = _tangents(stretch)[[0, -1]]
    if np.degrees(np.arccos(np.clip(turn[0] @ turn[1], -1.0, 1.0))) > max_turn:
        return None
    end = line[-1]
    a = end - stretch[0]
    a /= np.linalg.norm(a)
    _, e1, e2 = _plane_basis(a)
    normal = normal if (stretch[0] - q) @ normal > 0.0 else -normal
    centres, areas = sections.face_centres, sections.face_areas
    rel = centres - end
    z = rel @ a
    lateral = np.linalg.norm(rel - np.outer(z, a), axis=1)
    # Faces beside the stretch and beyond its end (an oblique cut's far side), on the
    # line's side of the plane; the radius started from their median distance.
    pick = (z > -OPEN_FIT_LENGTH) & (z < 3.0 * radius) & (lateral < 3.0 * radius) & \
        ((centres - q) @ normal > clear)
    dense = _resample(stretch, 0.5e-3)
    near = np.flatnonzero(pick)
    gap = np.min(np.linalg.norm(centres[near, None] - dense[None, ::4], axis=2), axis=1)
    r0 = float(np.median(gap[gap < 2.0 * radius])) if np.any(gap < 2.0 * radius) else radius
    near = near[gap < 2.0 * r0]
    if len(near) < 200:
        return None
    if len(near) > OPEN_FIT_FACES:
        near = np.sort(np.random.default_rng(0).choice(near, OPEN_FIT_FACES, replace=False))
    faces = np.column_stack([rel[near] @ e1, rel[near] @ e2, z[near] / OPEN_FIT_LENGTH])
    weights = np.sqrt(areas[near] / np.mean(areas[near]))
    free = np.r_[0:degree + 1, 4:5 + degree, 8:12]   # the coefficients fitted

    def full(y):
        x = np.zeros(12)
        x[free] = y
        return x

    y0 = np.zeros(len(free))
    y0[-4] = r0
    y = least_squares(lambda y: _open_tube_residuals(full(y), faces, weights, ROUND_CAP_INSIDE),
                      y0, loss="soft_l1", f_scale=5e-4).x
    x = full(y)
    poly = np.polynomial.polynomial

    def axis(zeta):
        return (end + poly.polyval(zeta, x[0:4]) * e1 + poly.polyval(zeta, x[4:8]) * e2
                + zeta * OPEN_FIT_LENGTH * a)

    def curve(u, h=1e-4):
        zeta = -2.0 / 3.0 + u / OPEN_FIT_LENGTH
        d = axis(zeta + h) - axis(zeta - h)
        return axis(zeta), d / np.linalg.norm(d)

    return curve


def _along_axis(line, curve, u_end, step):
    """The line up to a third of OPEN_FIT_LENGTH into its last stretch, then `curve` (of
    `_fitted_axis`) to u_end, every `step`."""
    s = _arc(line)
    keep = line[s < s[-1] - 2.0 * OPEN_FIT_LENGTH / 3.0]
    u = np.arange(step, u_end, step)
    made = np.vstack([keep, [curve(v)[0] for v in u], curve(u_end)[0]])
    return _resample(made, step, smoothing=1e-12)


def _fitted_open_end(sections: MeshSections, line, radius, step, loops):
    """An open end's last OPEN_FIT_LENGTH made again from the wall there fitted as a tube:
    circles normal to an axis whose offsets from the stretch's chord are cubics along it
    (quadratics where the cut is oblique, `_square_cut`), with a radius that is a cubic (a
    flare by half over the last 4 cm is one), by a robust least squares on the faces within
    two radii of the line and short of the loop's plane, the wall inside the fit (folds)
    weighing ROUND_CAP_INSIDE as at a round cap. The rim does not enter the fit: where an
    oblique cut leaves the sections near it open arcs (a fold across an arc pulls its
    circle aside), the wall on the far side of the cut still bounds the tube. The line is
    kept up to a third of the stretch in, then follows the fitted axis to the plane of the
    end's loop (`_plane_crossing`).

    The made line is returned if its end is nearer its own sections' centres than the
    line's (`end_residual`); at an oblique cut, if it is not farther by more than
    OBLIQUE_FIT_SLACK. Otherwise the line is returned as it is, and so if it is shorter
    than three stretches, if it turns by more than OPEN_FIT_TURN over the stretch, if
    fewer than 200 faces are near, or if the axis does not cross the loop near its
    centre."""
    line = np.asarray(line)
    end = line[-1]
    ring = min(loops, key=lambda r: np.linalg.norm(r.mean(axis=0) - end), default=None)
    if ring is None or np.linalg.norm(ring.mean(axis=0) - end) > 2.0 * radius:
        return line
    q = ring.mean(axis=0)
    square = _square_cut(end, loops)
    curve = _fitted_axis(sections, line, radius, q, np.linalg.svd(ring - q)[2][2],
                         degree=3 if square else 2)
    if curve is None:
        return line
    u_end = _plane_crossing(curve, loops, end, 2.0 * radius)
    if u_end is None:
        return line
    made = _along_axis(line, curve, u_end, step)
    slack = 1.0 if square else OBLIQUE_FIT_SLACK
    if end_residual(sections, made, radius) < slack * end_residual(sections, line, radius):
        return made
    return line


def _fitted_cap_end(sections: MeshSections, line, radius, step):
    """A flat cap's last OPEN_FIT_LENGTH made again from the wall before the cap fitted as
    a tube (`_fitted_axis`; the disc's faces, within FLAT_FIT_CLEAR of its plane, left
    out), followed to the disc's plane: where a flare and a bend just before the cap leave
    the sections there tilted, the line between them can bulge by millimetres while its end,
    the disc's centroid (`_finish_cap`), is right. The line is returned as it is if the
    wall its end's tangent meets is not a disc (`_flat_disc`), if there is no fit (or the
    line turns by more than CAP_FIT_TURN over the stretch), or if the axis meets the plane
    farther than CAP_FIT_AGREE radii from the disc's centroid."""
    line = np.asarray(line)
    end = line[-1]
    t = _end_tangent(line)
    ahead = sections.ray(end - radius * t, t, reach=2.0 * radius)
    if not np.isfinite(ahead):
        return line
    disc = _flat_disc(sections, end - radius * t + ahead * t, radius)
    if disc is None:
        return line
    q = np.average(sections.face_centres[disc], axis=0, weights=sections.face_areas[disc])
    normal = np.average(sections.face_normals[disc], axis=0, weights=sections.face_areas[disc])
    normal /= np.linalg.norm(normal)
    curve = _fitted_axis(sections, line, radius, q, normal, clear=FLAT_FIT_CLEAR,
                         max_turn=CAP_FIT_TURN)
    if curve is None:
        return line
    u_end = _first_crossing(curve, q, normal, np.linspace(0.0, OPEN_FIT_LENGTH, 51))
    if u_end is None or np.linalg.norm(curve(u_end)[0] - q) > CAP_FIT_AGREE * radius:
        return line
    return _along_axis(line, curve, u_end, step)


def _round_ahead(sections: MeshSections, p, t, radius, ahead) -> bool:
    """Whether the wall ahead curves back toward the march: rays parallel to `t` from six
    points half a radius around `p` all meet it 5 % nearer than the ray from `p` or more (a
    hemisphere's base: 13 % nearer); not a flat cap (as far), nor a bend's outer wall (the
    rays on its inner side go farther)."""
    _, u, v = _plane_basis(t)
    hits = []
    for phi in np.linspace(0.0, 2 * np.pi, 6, endpoint=False):
        start = p + 0.5 * radius * (np.cos(phi) * u + np.sin(phi) * v)
        hits.append(sections.ray(start, t, reach=2.0 * ahead))
    return bool(np.max(hits) < 0.95 * ahead)


def _smooth_inside(points, fixed=(False, False)):
    """The section centres smoothed (see below), their ends kept; an end that is not
    `fixed` (head, tail) is put on the line through its two neighbours."""
    # The section centres scatter by a fraction of a millimetre; the lumen's centre line
    # does not: a smoothing spline. Its natural end conditions straighten the ends, though,
    # where the centres are right to within ~0.4 mm (the round trip): they are blended
    # back in over the last 2 cm.
    if len(points) > 10:
        s = _arc(points)
        smooth = np.column_stack([make_smoothing_spline(s, points[:, k], lam=SMOOTHING_LAMBDA)(s)
                                  for k in range(3)])
        to_end = np.minimum(s, s[-1] - s)
        keep = np.clip(1.0 - to_end / 0.02, 0.0, 1.0) ** 2
        points = smooth + keep[:, None] * (points - smooth)
        # Each end point on the line through its two neighbours, at its distance along it:
        # a sideways step there would be a curvature spike.
        for end, a, b in ((0, 1, 2), (-1, -2, -3)):
            if fixed[end]:
                continue
            t = points[a] - points[b]
            t /= np.linalg.norm(t)
            points[end] = points[a] + max(float((points[end] - points[a]) @ t), 1e-4) * t
    return points


def _refine(sections: MeshSections, points, step, keep_ends=False, max_move=None,
            hold=(0.0, 0.0)):
    """Each point moved to the centre of its section normal to the centreline (`_centre`);
    returns (points, radii, whether each point's section was found). Points without a
    closed loop around them are dropped (kept, with keep_ends). With keep_ends, the end
    points stay (their sections are the tube's ends) and take their neighbours' radii, and
    so do the points within hold[0] of the first end and hold[1] of the last (in a cap)."""
    points = np.asarray(points)
    tangents = _tangents(points)
    s = _arc(points)
    new, radius = [], []
    found = np.zeros(len(points), bool)
    for k, (p, t) in enumerate(zip(points, tangents)):
        end = keep_ends and k in (0, len(points) - 1)
        held = keep_ends and (s[k] < hold[0] or s[-1] - s[k] < hold[1])
        section = None if end else sections.around(p, t)
        if section is None or held:
            if keep_ends:  # held: it stays, its section gives its radius
                new.append(p)
                radius.append(np.nan if section is None else section.radius)
            continue
        found[k] = True
        centre = _centre(section, p, t)
        limit = 4.0 * step if max_move is None else max_move
        if np.linalg.norm(centre - p) > min(limit, 0.5 * section.radius):
            if not keep_ends:
                continue  # a stray loop
            centre = p
        new.append(centre)
        radius.append(section.radius)
    radius = np.array(radius)
    if np.isnan(radius).any() and not np.isnan(radius).all():
        good = np.flatnonzero(~np.isnan(radius))
        radius = np.interp(np.arange(len(radius)), good, radius[good])
    return np.array(new).reshape(-1, 3), radius, found


FIT_ROUND_CAPS = True
"""Whether `extract_centerline` ends a round cap at its fitted capsule end (step 6 of the
module's docstring; off, the march's end is kept)."""
ROUND_CAP_BODIES = (0.004, 0.008, 0.012)
"""Lengths [m] of tube behind a round cap's hemisphere fitted with it (`_fit_round_cap`),
one fit each; the fit whose made end is nearest its sections' centres is kept
(`_capsule_end`). Against the fit whose pole was nearest the others', on the round-cap
passes of seeds 260000, 270000 and 290000: 8 ends over 2 mm -> 4 (260034 6.1 -> 0.25,
270036 4.5 -> 1.7, 290053 9.9 -> 0.2, 290056 5.4 -> 0.5 mm; the wrong way 270084 0.3 ->
9.0, 260062 2.2 -> 2.9); scored on fresh seeds."""
ROUND_CAP_INSIDE = 0.1
"""Weight of the wall standing inside the fitted capsule end (folds) against the wall on
or outside it: the fit follows the wall's outer envelope, as the sections' centres do."""
ROUND_CAP_AGREE = 0.0015
"""A line whose end is this near [m] the fitted pole is kept as it is (`_round_cap_end`):
the sections' line is the more accurate where it found the cap (a tube curving within the
fitted body tilts the fit's axis by a fraction of a degree)."""
ROUND_CAP_SECTIONS = 0.1
"""A capsule end is taken only if its last 4 cm are at most this share of the radius
further from their own sections' centres than the line's (`end_residual`): a round cap's
true line is centred by its sections as well as any other (measured on seeds 110000 and
120000: the fitted ends taken were at most 1.2 mm worse, r/10 = 1.2-3 mm; the segmented
capped tube's blunt cap fitted as a larger sphere, 2.6-3.6 mm worse, r/10 = 1.6 mm)."""
ROUND_CAP_FACES = 4000
"""Most faces near a round cap its fit uses (a fixed random sample of a finer mesh's)."""
ROUND_CAP_TILTS = (0.0, 15.0, 30.0)
"""Starting tilts [degrees] of the capsule end's axis from the line's end tangent (each
but 0 at six azimuths): the fit's cost has more than one minimum where folds cross it."""


def _capsule_end_parts(x, a0, e1, e2, faces):
    c, r, taper = x[:3], x[5], x[6]
    n = a0 + x[3] * e1 + x[4] * e2
    a = n / np.linalg.norm(n)
    d = faces - c
    z = d @ a
    q = d - np.outer(z, a)
    rho = np.linalg.norm(q, axis=1)
    dist = np.linalg.norm(d, axis=1)
    cap = z >= 0.0
    gap = np.where(cap, dist - r, rho - (r + taper * z))
    return n, a, d, z, q, rho, dist, cap, gap


def _capsule_end_residuals(x, a0, e1, e2, faces, weights, inside):
    """Each face's distance from the capsule end x = (centre, axis tilts along e1 and e2
    from a0, r, taper): from the sphere where it is ahead of the centre, else from the
    body's axis less the body's radius; times `weights`, and `inside` where negative."""
    gap = _capsule_end_parts(x, a0, e1, e2, faces)[-1]
    return weights * np.where(gap < 0.0, inside * gap, gap)


def _capsule_end_jacobian(x, a0, e1, e2, faces, weights, inside):
    """The derivative of `_capsule_end_residuals` by x, in closed form."""
    n, a, d, z, q, rho, dist, cap, gap = _capsule_end_parts(x, a0, e1, e2, faces)
    taper = x[6]
    jac = np.zeros((len(faces), 7))
    q_hat = q / np.maximum(rho, 1e-12)[:, None]
    jac[:, :3] = np.where(cap[:, None], -d / np.maximum(dist, 1e-12)[:, None],
                          -q_hat + taper * a)
    by_axis = -z[:, None] * q_hat - taper * d   # by a unit change of the axis
    project = (np.eye(3) - np.outer(a, a)) / np.linalg.norm(n)
    jac[:, 3] = np.where(cap, 0.0, by_axis @ (project @ e1))
    jac[:, 4] = np.where(cap, 0.0, by_axis @ (project @ e2))
    jac[:, 5] = -1.0
    jac[:, 6] = np.where(cap, 0.0, -z)
    scale = weights * np.where(gap < 0.0, inside, 1.0)
    return scale[:, None] * jac


def _fit_round_cap(sections: MeshSections, line, radius: float, body: float,
                   tilts=ROUND_CAP_TILTS, widest: float = 0.0):
    """The end of a tube closed by a round cap, fitted to the wall as a capsule's end: a
    hemisphere of radius r about a centre c on an axis a (its pole c + r a), and behind
    it, for `body` [m], a tube whose radius changes linearly along a (a flared end's last
    centimetre). Faces (by their centres, weighted by their areas) near the cap; a robust
    loss (soft L1, 0.5 mm) and the wall inside the fit down-weighted (`ROUND_CAP_INSIDE`);
    the faces chosen again about each fit (four times). Started from the line's end
    (radius `radius`, its centre a radius back along the end tangent) with the axis tilted
    by `tilts`; the start with the smallest robust cost is kept. A fit's r is at least
    0.3 `radius` and less than twice the larger of `radius` and `widest` (the radius of
    the line's last sections: a flare by half ahead of ring folds took one cap to 2.3
    times the radius 2.5-7.5 cm before the end).

    Returns (centre, axis, r, cost) or None if too few faces are near the end."""
    line = np.asarray(line)
    end = line[-1]
    t = _end_tangent(line)
    _, u, v = _plane_basis(t)
    starts = [t]
    for tilt in tilts:
        if tilt == 0.0:
            continue
        for phi in np.linspace(0.0, 2 * np.pi, 6, endpoint=False):
            starts.append(np.cos(np.radians(tilt)) * t + np.sin(np.radians(tilt)) *
                          (np.cos(phi) * u + np.sin(phi) * v))
    centres, areas = sections.face_centres, sections.face_areas
    near = np.linalg.norm(centres - end, axis=1) < 3.0 * radius + body
    centres, areas = centres[near], areas[near]
    if len(centres) < 50:
        return None
    if len(centres) > ROUND_CAP_FACES:  # a fine mesh: a fixed sample of its faces
        keep = np.random.default_rng(0).choice(len(centres), ROUND_CAP_FACES, replace=False)
        centres, areas = centres[keep], areas[keep]
    walls = sections.near(end, 6.0 * radius + body)   # for the rays of `_closed_around`
    best = None
    for a0 in starts:
        fit = _capsule_fit(centres, areas, (end - radius * t, a0, radius, 0.0), body,
                           ROUND_CAP_INSIDE)
        if fit is not None and 0.3 * radius < fit[2] < 2.0 * max(radius, widest) and \
                (best is None or fit[4] < best[4]) and _closed_around(walls, *fit[:3]):
            best = fit
    if best is None:
        return None
    c, a, r, _, cost = best
    return c, a, float(r), cost


def _capsule_fit(centres, areas, start, body, inside, iterations=4):
    """(centre, axis, r, taper, cost) of the capsule end (`_fit_round_cap`) fitted to the
    faces (`centres`, `areas`) from `start` (centre, axis, r, taper), the faces within
    reach of it chosen again about each fit, `iterations` times. None if fewer than 50."""
    from scipy.optimize import least_squares

    c, a, r, taper = start
    for _ in range(iterations):
        d = centres - c
        z = d @ a
        side = np.linalg.norm(d - np.outer(z, a), axis=1)
        pick = (z > -body) & (z < 1.6 * r) & (side < 1.6 * r)
        if pick.sum() < 50:
            return None
        _, e1, e2 = _plane_basis(a)
        weights = np.sqrt(areas[pick] / np.mean(areas[pick]))
        fit = least_squares(
            _capsule_end_residuals, np.r_[c, 0.0, 0.0, r, taper], jac=_capsule_end_jacobian,
            args=(a, e1, e2, centres[pick], weights, inside),
            loss="soft_l1", f_scale=5e-4, x_scale=np.r_[[1e-3] * 3, 0.1, 0.1, 1e-3, 0.1])
        c, r, taper = fit.x[:3], fit.x[5], fit.x[6]
        a = a + fit.x[3] * e1 + fit.x[4] * e2
        a = a / np.linalg.norm(a)
    return c, a, r, taper, 2.0 * fit.cost / pick.sum()


def _closed_around(faces, c, a, r) -> bool:
    """Whether a fitted cap is the wall's: rays from its centre `c` along its axis `a` and
    at 45 degrees to it (six) all meet the wall within 1.3 r, the axial one beyond 0.7 r (a
    fit slid along the tube, or turned across it, looks down the lumen). `faces`: the
    faces near c, as `MeshSections.near` gives them (reaching beyond 1.3 r)."""
    _, u, v = _plane_basis(a)
    axial = _ray(*faces, c, a, reach=1.3 * r)
    if not 0.7 * r <= axial <= 1.3 * r:
        return False
    for phi in np.linspace(0.0, 2 * np.pi, 6, endpoint=False):
        d = a + np.cos(phi) * u + np.sin(phi) * v
        if _ray(*faces, c, d, reach=1.3 * r) > 1.3 * r:
            return False
    return True


def _capsule_end(sections: MeshSections, line, radius: float, widest: float = 0.0,
                 step: float = 0.005):
    """The round cap's end fitted with each body length of ROUND_CAP_BODIES
    (`_fit_round_cap`): (centre, axis, r, body) of the fit whose made end (`_along_cap`)
    is nearest its own sections' centres (`end_residual`), or None if no fit. (A flare's
    cone, a bend or folds behind a bulb leave its axis loosely held: one fit of the three
    is often right and the other two tilt alike, so the fit whose pole is nearest the
    others' was often a wrong one.)"""
    best = _best_cap(sections, line, radius, widest, step)
    return None if best is None else best[0]


def _best_cap(sections: MeshSections, line, radius, widest, step, blend: float = 0.03):
    """((centre, axis, r, body), made line, its `end_residual`) of `_capsule_end`'s
    choice, or None."""
    line = np.asarray(line)
    made = []
    for body in ROUND_CAP_BODIES:
        fit = _fit_round_cap(sections, line, radius, body, widest=widest)
        if fit is None:
            continue
        c, a, r, _ = fit
        end = _along_cap(line, c, a, r, body, step, blend)
        if end is not None:
            made.append(((c, a, r, body), end, end_residual(sections, end, radius)))
    if not made:
        return None
    return min(made, key=lambda m: m[2])


def _along_cap(line, c, a, r, body, step, blend):
    """The line up to where a fitted cap's body begins, then along its axis to the pole;
    the last `blend` [m] before the body made again as the cubic Hermite curve from the
    line's point and tangent there to the body's start along the axis (the line behind a
    cap found astray leans toward it), resampled every `step`. None if fewer than 5 points
    of the line lie behind the body."""
    z = (line - c) @ a
    keep = _before(line, z < -body)
    if len(keep) < 5:
        return None
    start = c - body * a
    s = _arc(keep)
    head = keep[s <= s[-1] - blend] if s[-1] > blend + 5 * step else keep[:2]
    p0 = head[-1]
    t0 = _end_tangent(head) if len(head) >= 5 else a
    gap = float(np.linalg.norm(start - p0))
    h = np.linspace(0.0, 1.0, max(3, int(np.ceil(gap / step)) + 1))[1:-1, None]
    hermite = ((2 * h ** 3 - 3 * h ** 2 + 1) * p0 + (h ** 3 - 2 * h ** 2 + h) * gap * t0 +
               (-2 * h ** 3 + 3 * h ** 2) * start + (h ** 3 - h ** 2) * gap * a)
    ray = c + np.arange(-body, r + 1e-9, step)[:, None] * a
    ray = np.vstack([ray, c + r * a]) if np.linalg.norm(ray[-1] - (c + r * a)) > 1e-6 else ray
    return _resample(np.vstack([head, hermite, ray]), step, smoothing=1e-12)


def _round_cap_end(sections: MeshSections, line, radius, step, blend: float = 0.03,
                   widest: float = 0.0):
    """A round cap's end made from its fitted capsule end (`_capsule_end`, `_along_cap`).
    `line` unchanged if no fit, if the line's end is within ROUND_CAP_AGREE of the fitted
    pole, or if the made end is ROUND_CAP_SECTIONS radii or more further from its own
    sections' centres than the line's (`end_residual`)."""
    line = np.asarray(line)
    best = _best_cap(sections, line, radius, widest, step, blend)
    if best is None:
        return line
    (c, a, r, _), made, residual = best
    if np.linalg.norm(line[-1] - (c + r * a)) < ROUND_CAP_AGREE:
        return line
    # Kept only if its sections still centre it (`end_residual`): a blunt cap fitted as a
    # larger sphere puts the pole in the corner, where the sections tilt away by millimetres.
    if residual > end_residual(sections, line, radius) + ROUND_CAP_SECTIONS * radius:
        return line
    return made
