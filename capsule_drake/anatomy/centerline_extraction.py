"""The centreline of a tubular mesh: arc length and local radius, for imported colons.

1. Rings. Geodesic distance over the mesh's edge graph from one end (a tube's open boundary
   loop, or for a closed mesh the vertex farthest from another far vertex) grows along the
   tube; vertices binned by it form rings around the lumen, and the rings' centroids are a
   first centreline. It follows any bend, but its rings tilt where the inner wall is
   shorter than the outer.
2. Sections. The mesh is cut by the plane through each centreline point normal to the
   centreline's tangent; the cut's loop around that point (the smallest containing it: in
   a bend the plane may cut the tube twice, and a wall with thickness gives an inner and an
   outer loop) gives the new point, the centre of a circle fitted to the loop's outer
   envelope (folds stand inward and would pull an area centroid off the axis), and an
   area, the local radius sqrt(A / pi). Repeated, the points settle on the lumen's centre.
3. Ends. The rings are unreliable near the ends, so the line is cut back there and grown
   again by marching sections to where the tube ends (an open end's loop) or closes (a cap,
   found by a ray); then sections and a light smoothing spline once more.

Round trip of the procedural colon (exported, imported, extracted), seeds 0-9: within
0.5-1.3 mm of the original centreline everywhere.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.interpolate import make_smoothing_spline
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from .importer import _boundary_loops, geometry_of


def _edge_graph(mesh: trimesh.Trimesh):
    edges = mesh.edges_unique
    lengths = mesh.edges_unique_length
    n = len(mesh.vertices)
    return coo_matrix((np.concatenate([lengths, lengths]),
                       (np.concatenate([edges[:, 0], edges[:, 1]]),
                        np.concatenate([edges[:, 1], edges[:, 0]]))), shape=(n, n)).tocsr()


def _start_vertices(mesh: trimesh.Trimesh, graph) -> np.ndarray:
    """One end of the tube: the boundary loop nearest the vertex geodesically farthest from
    vertex 0, or that vertex alone for a closed mesh."""
    far = int(np.argmax(dijkstra(graph, indices=0)))
    loops = _boundary_loops(mesh)
    if loops:
        distance = dijkstra(graph, indices=far)
        return min(loops, key=lambda loop: float(np.min(distance[loop])))
    return np.array([far])


def ring_centreline(mesh: trimesh.Trimesh, step: float):
    """Step 1: ring centroids every `step` (m) of geodesic distance from one end."""
    graph = _edge_graph(mesh)
    start = _start_vertices(mesh, graph)
    distance = np.min(dijkstra(graph, indices=start), axis=0) if len(start) > 1 else \
        dijkstra(graph, indices=int(start[0]))
    finite = np.isfinite(distance)
    vertices = np.asarray(mesh.vertices)[finite]
    distance = distance[finite]
    bins = np.floor(distance / step).astype(int)
    points = []
    for k in range(bins.max() + 1):
        ring = vertices[bins == k]
        if len(ring) >= 3:
            points.append(ring.mean(axis=0))
    return np.array(points)


def _resample(points: np.ndarray, step: float, smoothing: float | None = None) -> np.ndarray:
    """Points every `step` of arc length along a smoothed polyline through `points`."""
    d = np.linalg.norm(np.diff(points, axis=0), axis=1)
    keep = np.concatenate([[True], d > 1e-9])
    points = points[keep]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    if len(points) < 5:
        return points
    spline = [make_smoothing_spline(s, points[:, k], lam=smoothing) for k in range(3)]
    fine = np.linspace(0.0, s[-1], max(int(s[-1] / (0.2 * step)), 10))
    dense = np.column_stack([f(fine) for f in spline])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    count = max(int(np.ceil(arc[-1] / step)), 1)
    stations = np.linspace(0.0, arc[-1], count + 1)  # both ends kept
    return np.column_stack([np.interp(stations, arc, dense[:, k]) for k in range(3)])


def _polygon(loop: np.ndarray):
    """(area, centroid) of a closed 2-D polyline by the shoelace formula."""
    x, y = loop[:, 0], loop[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cross = x * y1 - x1 * y
    area = 0.5 * cross.sum()
    if abs(area) < 1e-14:
        return 0.0, loop.mean(axis=0)
    cx = ((x + x1) * cross).sum() / (6.0 * area)
    cy = ((y + y1) * cross).sum() / (6.0 * area)
    return abs(area), np.array([cx, cy])


def section_loop(mesh: trimesh.Trimesh, origin: np.ndarray, normal: np.ndarray):
    """The plane section's closed loop around `origin` (the smallest containing it), or the
    nearest one if none does: (loop (K, 3) world points, area centroid (3,), area), or None.
    In a bend the plane may cut the tube twice; a wall with thickness gives an inner and an
    outer loop (the inner one, the lumen, is the smaller)."""
    from matplotlib.path import Path as PlanePath

    section = mesh.section(plane_origin=origin, plane_normal=normal)
    if section is None:
        return None
    planar, to_3d = section.to_2D()
    local_origin = trimesh.transform_points([origin], np.linalg.inv(to_3d))[0, :2]
    best = None
    for loop in planar.discrete:
        if len(loop) < 4 or np.linalg.norm(loop[0] - loop[-1]) > 1e-6:
            continue  # open: the mesh's end, not a loop around the lumen
        area, centre = _polygon(loop[:-1])
        if area <= 0.0:
            continue
        inside = PlanePath(loop).contains_point(local_origin)
        distance = 0.0 if inside else float(np.linalg.norm(centre - local_origin))
        if best is None or distance < best[0] or (distance == best[0] == 0.0 and area < best[2]):
            best = (distance, centre, area, loop[:-1])
    if best is None:
        return None
    centre3 = trimesh.transform_points([[best[1][0], best[1][1], 0.0]], to_3d)[0]
    loop3 = trimesh.transform_points(np.column_stack([best[3], np.zeros(len(best[3]))]), to_3d)
    return loop3, centre3, best[2]


def _section_centre(mesh: trimesh.Trimesh, origin: np.ndarray, normal: np.ndarray):
    """(centre, area) of `section_loop`, or None: the centre of the circle fitted to the
    loop's outer envelope (`envelope_centre`), or its area centroid if the fit fails."""
    cut = section_loop(mesh, origin, normal)
    if cut is None:
        return None
    loop, centroid, area = cut
    centre = envelope_centre(loop, centroid, normal)
    return (centroid if centre is None else centre), area


MARCH_BASELINE = 0.01
"""The march's direction is that of the chord over this much centreline [m]."""


def envelope_centre(loop: np.ndarray, start: np.ndarray, normal: np.ndarray,
                    inside: float = 0.0005, iterations: int = 12):
    """Centre of the circle fitted to a section loop's outer envelope, or None.

    Haustral folds, valves and taeniae stand inward from the colon's wall: a one-sided
    perturbation that pulls the area centroid away from them by millimetres where they sit
    on one side only. Points more than `inside` (m) within the fitted circle count 2 % as
    much as those on or outside it (iteratively reweighted algebraic circle fit, each point
    weighted by the length of loop it stands for), so the circle settles on the wall between
    the folds."""
    n = normal / np.linalg.norm(normal)
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    d = loop - start
    xy = np.column_stack([d @ a, d @ b])
    seg = np.linalg.norm(np.roll(xy, -1, axis=0) - xy, axis=1)
    length = 0.5 * (seg + np.roll(seg, 1))
    weights = length.copy()
    centre = np.zeros(2)
    for _ in range(iterations):
        design = np.column_stack([xy, np.ones(len(xy))])
        target = -np.sum(xy ** 2, axis=1)
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
        weights = length * np.where(r < radius - inside, 0.02, 1.0)
    if np.linalg.norm(centre) > 0.5 * radius:
        return None  # not a round lumen around the start: keep the centroid
    return start + centre[0] * a + centre[1] * b


def _end_loop_centres(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    return [np.asarray(mesh.vertices)[loop].mean(axis=0) for loop in _boundary_loops(mesh)
            if len(loop) >= 3]


def _march(mesh: trimesh.Trimesh, points: list, step: float, fine: float):
    """Extends `points` (the last ones inside the tube) past their end, a section every
    `step` and then every `fine` (m), each centred on its loop, until the plane leaves the
    tube (an open end) or the tube closes (a cap).

    A cap shows as the section's area falling: below a third of the last section's, or,
    in the fine steps, below 90 % of the lumen's area before the end (the median of the
    coarse sections'), where a plane not quite parallel to a flat cap starts cutting it and
    the loop's centroid slides sideways; and in the coarse steps below 80 % of the last
    four's median. There the march stops, and the end is where a ray along the march from
    the last centre meets the cap."""
    points = list(points)
    area = None
    areas = []
    t = None
    for size in (step, fine):
        reference = float(np.median(areas)) if areas else None
        for _ in range(2000):
            back = next((q for q in reversed(points[:-1])
                         if np.linalg.norm(points[-1] - q) >= MARCH_BASELINE), points[0])
            t = points[-1] - back
            t = t / np.linalg.norm(t)
            guess = points[-1] + size * t
            cut = _section_centre(mesh, guess, t)
            if cut is None:
                break
            centre, new_area = cut
            # A loop far off the march (another part of the tube).
            if np.linalg.norm(centre - guess) > 0.3 * np.sqrt(new_area / np.pi):
                break
            recent = float(np.median(areas[-4:])) if len(areas) >= 3 else None
            if (area is not None and new_area < area / 3.0) or (
                    size == fine and reference is not None and new_area < 0.9 * reference) or (
                    size == step and recent is not None and new_area < 0.8 * recent):
                break
            points.append(centre)
            area = new_area
            if size == step:
                areas.append(new_area)
    # The end: where a ray along the march meets a cap (after an open end, or far off, it
    # meets nothing near).
    if t is not None and area is not None:
        hit = _ray_hit(mesh, points[-1], t)
        if hit is not None and hit <= 1.5 * np.sqrt(area / np.pi):
            points.append(points[-1] + hit * t)
    return points


def _ray_hit(mesh: trimesh.Trimesh, origin: np.ndarray, direction: np.ndarray):
    """Distance along the ray to the nearest face it meets (Moller-Trumbore over every
    face), or None."""
    triangles = np.asarray(mesh.triangles)
    v0 = triangles[:, 0]
    e1, e2 = triangles[:, 1] - v0, triangles[:, 2] - v0
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-15
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = origin - v0
    u = np.einsum("ij,ij->i", tvec, p) * inv
    q = np.cross(tvec, e1)
    v = (q @ direction) * inv
    dist = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (dist > 1e-9)
    return float(dist[hit].min()) if hit.any() else None


def extract_centerline(mesh: trimesh.Trimesh, step: float = 0.005, iterations: int = 3,
                       progress=None):
    """(s, points, radius): the centreline of a tubular mesh every `step` (m), from the end
    found first (geodesically farthest), with the local radius sqrt(section area / pi).

    Near the ends the rings are unreliable (a closed tube's cap, the geodesic source), so
    1.5 radii of centreline are cut from each end and grown back by marching: a section
    every `step`, then every millimetre, each centred on its loop, to where the tube ends
    (an open end's loop centroid is added) or closes (a cap: the loop collapses).
    `progress`, if given, is called with (iteration, iterations)."""
    mesh = geometry_of(mesh)
    points = _resample(ring_centreline(mesh, step), step)
    for iteration in range(iterations):
        if progress is not None:
            progress(iteration, iterations)
        points = _refine(mesh, points, step)[0]
        if len(points) > 10:
            points = _resample(points, step)
    # Cut the ends back to where the tube is whole: at least 1.5 radii, and past where the
    # sections still grow inward (a cap cut obliquely), then grow them back. (The radii of
    # the evenly resampled points: the cut counts points.)
    radii = _refine(mesh, points, step, keep_ends=True)[1]
    base = int(np.ceil(1.5 * float(np.median(radii)) / step))

    def cut_from(r):
        window = r[:min(len(r), 4 * base)]
        grown = np.flatnonzero(window >= 0.9 * window.max())
        return max(base, int(grown[0]) + 1 if len(grown) else base)

    head, tail = cut_from(radii), cut_from(radii[::-1])
    if len(points) > head + tail + 6:
        points = points[head:len(points) - tail]
    points = _march(mesh, points, step, 0.001)
    points = _march(mesh, list(points[::-1]), step, 0.001)[::-1]
    points = np.array(points)
    ends = _end_loop_centres(mesh)
    if len(ends) >= 2:
        ends = np.array(ends)
        head = ends[np.argmin(np.linalg.norm(ends - points[0], axis=1))]
        tail = ends[np.argmin(np.linalg.norm(ends - points[-1], axis=1))]
        points = np.vstack([head, points, tail])
    points = _resample(points, step, smoothing=1e-12) if len(points) > 10 else points
    for _ in range(FINAL_PASSES):
        points, radius = _refine(mesh, points, step, keep_ends=True, max_move=0.5 * step)
        points = _smooth_inside(points)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    return s, points, radius


FINAL_PASSES = 2
"""Section-and-smooth passes after the ends are grown back."""
SMOOTHING_LAMBDA = 1e-7
"""Weight [m^3] of the curvature penalty in the final smoothing spline: it smooths over
~lambda^(1/4) ~ 2 cm. (Generalised cross-validation chose far stronger smoothing, which
cut the corners of the rectum's bends by up to 2.4 mm on the round trip.)"""


def _smooth_inside(points):
    """The section centres smoothed (see below), their ends kept."""
    # The section centres scatter by a fraction of a millimetre; the lumen's centre line
    # does not: a smoothing spline. Its natural end conditions straighten the ends, though,
    # where the centres are right to within ~0.4 mm (the round trip): they are blended
    # back in over the last 2 cm.
    if len(points) > 10:
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
        smooth = np.column_stack([make_smoothing_spline(s, points[:, k], lam=SMOOTHING_LAMBDA)(s)
                                  for k in range(3)])
        to_end = np.minimum(s, s[-1] - s)
        keep = np.clip(1.0 - to_end / 0.02, 0.0, 1.0) ** 2
        points = smooth + keep[:, None] * (points - smooth)
        # Each end point on the line through its two neighbours, at its distance along it:
        # a sideways step there would be a curvature spike.
        for end, a, b in ((0, 1, 2), (-1, -2, -3)):
            t = points[a] - points[b]
            t /= np.linalg.norm(t)
            points[end] = points[a] + max(float((points[end] - points[a]) @ t), 1e-4) * t
    return points


def _refine(mesh, points, step, keep_ends=False, max_move=None):
    """Each point moved to the centre of its section normal to the centreline
    (`_section_centre`); returns
    (points, radii). With keep_ends, the end points stay (their sections are the tube's
    ends) and take their neighbours' radii."""
    tangents = np.gradient(points, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    new, radius = [], []
    for k, (p, t) in enumerate(zip(points, tangents)):
        if keep_ends and k in (0, len(points) - 1):
            new.append(p)
            radius.append(np.nan)
            continue
        cut = _section_centre(mesh, p, t)
        if cut is None:
            if keep_ends:
                new.append(p)
                radius.append(np.nan)
            continue
        centre, area = cut
        if np.linalg.norm(centre - p) > (4.0 * step if max_move is None else max_move):
            centre = p  # a stray loop: keep the point
        new.append(centre)
        radius.append(np.sqrt(area / np.pi))
    radius = np.array(radius)
    if np.isnan(radius).any() and not np.isnan(radius).all():
        good = np.flatnonzero(~np.isnan(radius))
        radius = np.interp(np.arange(len(radius)), good, radius[good])
    return np.array(new), radius
