"""The centreline of a tubular mesh: arc length and local radius, for imported colons.

Two steps:
1. Rings. Geodesic distance over the mesh's edge graph from one end (a tube's open boundary
   loop, or for a closed mesh the vertex farthest from another far vertex) grows along the
   tube; vertices binned by it form rings around the lumen, and the rings' centroids are a
   first centreline. It follows any bend, but its rings tilt where the inner wall is
   shorter than the outer.
2. Sections. The mesh is cut by the plane through each centreline point normal to the
   centreline's tangent; the cut's loop around that point (the one nearest it, in a bend
   the plane may cut the tube twice) has an area centroid, the new point, and an area, the
   local radius sqrt(A / pi). Repeated, the points settle on the lumen's centre.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.interpolate import make_smoothing_spline
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra


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
    from capsule_drake.anatomy.importer import _boundary_loops

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
    """(centroid, area) of `section_loop`, or None."""
    cut = section_loop(mesh, origin, normal)
    return None if cut is None else (cut[1], cut[2])


def _end_loop_centres(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    from capsule_drake.anatomy.importer import _boundary_loops

    return [np.asarray(mesh.vertices)[loop].mean(axis=0) for loop in _boundary_loops(mesh)
            if len(loop) >= 3]


def _march(mesh: trimesh.Trimesh, points: list, step: float, fine: float):
    """Extends `points` (the last ones inside the tube) past their end, a section every
    `step` and then every `fine` (m), each centred on its loop, until the plane leaves the
    tube (an open end) or its loop shrinks to less than a third of the last (a cap)."""
    points = list(points)
    area = None
    for size in (step, fine):
        for _ in range(2000):
            # The direction over the last ~2 cm: section centroids scatter by millimetres
            # in a wide, uneven lumen, too much for a short baseline.
            back = next((q for q in reversed(points[:-1])
                         if np.linalg.norm(points[-1] - q) >= 0.02), points[0])
            t = points[-1] - back
            t = t / np.linalg.norm(t)
            guess = points[-1] + size * t
            cut = _section_centre(mesh, guess, t)
            if cut is None:
                break
            centre, new_area = cut
            # A loop far off the march (another part of the tube) or collapsing (a cap).
            if np.linalg.norm(centre - guess) > 0.3 * np.sqrt(new_area / np.pi) or (
                    area is not None and new_area < area / 3.0):
                break
            points.append(centre)
            area = new_area
    return points


def extract_centerline(mesh: trimesh.Trimesh, step: float = 0.005, iterations: int = 3,
                       progress=None):
    """(s, points, radius): the centreline of a tubular mesh every `step` (m), from the end
    found first (geodesically farthest), with the local radius sqrt(section area / pi).

    Near the ends the rings are unreliable (a closed tube's cap, the geodesic source), so
    1.5 radii of centreline are cut from each end and grown back by marching: a section
    every `step`, then every millimetre, each centred on its loop, to where the tube ends
    (an open end's loop centroid is added) or closes (a cap: the loop collapses).
    `progress`, if given, is called with (iteration, iterations)."""
    from capsule_drake.anatomy.importer import geometry_of

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
    points, radius = _refine(mesh, points, step, keep_ends=True, max_move=0.5 * step)
    # The section centroids follow the folds by a millimetre or two; the lumen's centre
    # line does not: a smoothing spline (its weight by generalised cross-validation).
    if len(points) > 10:
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
        ends = points[0].copy(), points[-1].copy()
        points = _resample(points, step)
        # Where the tube ends, not where the spline does: the end points go out to the
        # tube's ends along the spline's end tangents (moved sideways onto the end
        # section's centre they would kink the line, and the kink is a curvature spike).
        for index, inner, end in ((0, 1, ends[0]), (-1, -2, ends[1])):
            tangent = points[index] - points[inner]
            tangent /= np.linalg.norm(tangent)
            points[index] = points[inner] + max(float((end - points[inner]) @ tangent),
                                                1e-4) * tangent
        radius = np.interp(np.linspace(0.0, s[-1], len(points)), s, radius)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    return s, points, radius


def _refine(mesh, points, step, keep_ends=False, max_move=None):
    """Each point moved to the centroid of its section normal to the centreline; returns
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
