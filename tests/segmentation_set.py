"""Segmentation-like surfaces: the test tubes of tube_set.py seen the way a user's colon
arrives from CT colonography or photogrammetry, each with its true centreline.

`segmented_tube(spec)` takes a tube from `tube_set.make_tube` and remakes its surface the way
a segmentation pipeline would, from a voxel volume, not from the tube's parametrisation:

1. Its open ends are closed: each boundary loop is extruded `END_EXTENSION` outward along
   its plane's normal and capped there by a fan (the lumen becomes a closed solid, and the
   cap, with its staircase and blur, lies clear beyond the end's plane, where step 5
   cuts).
2. Voxelised: each grid point is inside the lumen if a line through it along the slice
   axis crosses the closed surface an odd number of times below it (ray parity, columns
   along z, the surface's actual triangles: nothing of the tube's generator is used). The
   grid is in the world's axes (the scanner's), not the tube's, its origin shifted by a
   random part of a voxel. Voxels are `voxel` in-plane and `slice_spacing` across slices.
3. Blurred: the binary volume convolved with a Gaussian of `blur` (m) standard deviation
   per axis: the partial-volume effect of the scanner's point-spread function; the
   surface is the level 0.5 of the blurred volume (half the voxel in the lumen).
4. Meshed: `tube_set.marching_tetrahedra` on the blurred volume, slab by slab along the
   longest horizontal axis (a 1.5 m tube's box holds up to ~10^9 voxels; a slab and each
   connected lumen piece in it is meshed on its own small box, shared planes carried over
   so the pieces weld exactly).
5. Opened again: the faces beyond each open end's plane that lie, seen along its normal,
   within its loop or 1.5 voxels of it (the extrusion and its cap) removed, and any crumb
   that leaves apart from the wall: the wall ends at the original end, ragged at the scale
   of the meshed faces; a wall reaching beyond its end's plane outside the loop (an oblique
   cut after a bend) keeps that part.
6. Noise: every vertex moved along its normal by Gaussian noise of `noise` (m) standard
   deviation, smoothed over `NOISE_SMOOTHING` rings of neighbours (segmentation and
   photogrammetry noise is correlated over about a voxel, not per vertex).
7. Decimated: quadric decimation (fast_simplification through trimesh, a dependency of the
   package) to `decimate_to` faces, as segmentation software exports (`aggression`
   DECIMATION_AGGRESSION; it still leaves a handful of doubled faces, which the import's
   repair removes).
8. Holes: `holes` discs of faces (radius `HOLE_RADIUS`: the faces wholly inside it, at
   least one) removed at random on the wall, at least `HOLE_CLEARANCE` from an open end
   and from one another: a segmentation's leaks and a photogrammetry reconstruction's
   unseen patches. Punched after the decimation: holes of a few millimetres punched
   before it are zipped shut by a 30-50-fold reduction (seen on some of these tubes), and
   the import's hole filling would go untested. Their boundary follows the decimated
   faces (2-10 mm long, the longer along the tube): ragged, 1-4 cm around.

Why these numbers (sources where found; the rest are assumptions, marked):
- Voxels: multislice CT gives contiguous 1 mm slices through the whole abdomen in one
  breath-hold (Colonography using multislice CT, Eur J Radiol 2000;36(2):81-5,
  doi:10.1016/s0720-048x(00)00267-9); the second ESGAR consensus statement on CT
  colonography (Neri et al., Eur Radiol 2013, doi:10.1007/s00330-012-2632-x) counts the
  scan parameters among its quality standards (its figures were not read for this). A
  published pelvic CT protocol, as an example of the usual grid: 512 x 512 matrix,
  1 mm slice thickness and interval (the Clinical-data-on-pelvic-fractures data set's
  description). In-plane 0.70-0.80 mm: a 512 x 512 matrix over a 360-410 mm abdominal
  field of view (assumption: the field of view). Slices 1.0 or 1.25 mm (assumption).
- Blur: 0.35 mm standard deviation (assumption: a point-spread function of ~0.8 mm full
  width at half maximum, the order of the in-plane voxel).
- Noise: 0.2-0.5 mm (assumption: a fraction of a voxel, as the level set of a noisy CT
  volume moves; photogrammetry of a specimen is noisier where texture is poor).
- Holes: 2-4 mm radius, a few (assumption). Such holes are 13-25 mm around, below the
  importer's hole filling limit (anatomy/importer.py MAX_HOLE_PERIMETER, 3 cm).
- Decimation: 20-40k faces (assumption: what 3-D Slicer-like tools export after reduction).

The truth is the tube's own (tube_set.Tube.truth): the surface is the same lumen, moved by
at most a fraction of a voxel plus the noise.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from tube_set import TubeSpec, Tube, make_tube, marching_tetrahedra

VOXEL = 0.75e-3
"""In-plane voxel [m] (512 x 512 over a 384 mm field of view)."""
SLICE = 1.0e-3
"""Slice spacing [m] (the reconstruction interval)."""
BLUR = 0.35e-3
"""Standard deviation [m] of the Gaussian point-spread function (partial volume)."""
NOISE = 0.3e-3
"""Standard deviation [m] of the vertices' displacement along their normals."""
NOISE_SMOOTHING = 2
"""Passes of neighbour averaging of the noise (its correlation over ~a voxel)."""
HOLES = 3
"""Holes punched in the wall."""
HOLE_RADIUS = (2e-3, 4e-3)
"""A hole's radius [m], drawn uniformly."""
HOLE_CLEARANCE = 0.015
"""A hole's centre at least this far [m] from an open end and from another hole's."""
DECIMATE_TO = 30_000
"""Faces after decimation."""
END_EXTENSION = 4e-3
"""How far [m] an open end is extruded before it is capped: the cap's staircase and blur
(about a slice) stay clear of the end's plane."""
DECIMATION_AGGRESSION = 3
"""fast_simplification's aggression: its default (7) leaves ~0.5 % of the faces doubled (a
face and its copy over a one-face hole: 164 of 30,000 on small_coarse), 3 a handful."""
SLAB = 32
"""Grid layers meshed at a time."""


def segmented_tube(spec: TubeSpec | Tube, voxel: float = VOXEL, noise: float = NOISE,
                   holes: int = HOLES, decimate_to: int | None = DECIMATE_TO, seed: int = 0,
                   slice_spacing: float = SLICE, blur: float = BLUR):
    """(mesh in metres, truth (K, 3) in metres): the tube of `spec` (or a made `Tube`)
    voxelised, blurred, meshed, its open ends opened, noised, decimated and holed (see the
    module's text). `noise` 0, `holes` 0, `blur` 0 or `decimate_to` None skip that step.
    The grid's offset, the noise and the holes are drawn from (`seed`, the tube's seed).
    mesh.metadata["segmentation"] says what was done (grid, faces at each step, holes,
    odd columns of the voxelisation, pieces and boundary loops of the result)."""
    tube = spec if isinstance(spec, Tube) else make_tube(spec)
    rng = np.random.default_rng([seed, tube.spec.seed])
    vertices = np.asarray(tube.mesh.vertices, dtype=float) * tube.scale
    faces = np.asarray(tube.mesh.faces, dtype=np.int64)
    ends = _open_ends(vertices, faces)
    closed_v, closed_f = _capped(vertices, faces, ends)
    spacing = np.array([voxel, voxel, slice_spacing])
    info = {"voxel_mm": 1000 * voxel, "slice_mm": 1000 * slice_spacing, "blur_mm": 1000 * blur,
            "noise_mm": 1000 * noise, "source_faces": len(faces)}
    mesh = _segment(closed_v, closed_f, spacing, blur, rng, info)
    info["closed_faces"] = len(mesh.faces)
    info["closed_watertight"] = bool(mesh.is_watertight)
    mesh = _open_again(mesh, vertices, ends, 1.5 * spacing.max())
    if noise > 0:
        mesh = _noised(mesh, noise, rng)
    info["faces_before_decimation"] = len(mesh.faces)
    if decimate_to is not None and len(mesh.faces) > decimate_to:
        small = mesh.simplify_quadric_decimation(face_count=decimate_to,
                                                 aggression=DECIMATION_AGGRESSION)
        mesh = trimesh.Trimesh(small.vertices, small.faces, process=False)
    if holes > 0:
        mesh, radii, perimeters = _holed(mesh, holes, rng)
        info["hole_radii_mm"] = [round(1000 * r, 2) for r in radii]
        info["hole_perimeters_mm"] = [round(1000 * p, 1) for p in perimeters]
    info["faces"] = len(mesh.faces)
    info["pieces"] = len(trimesh.graph.connected_components(
        mesh.face_adjacency, nodes=np.arange(len(mesh.faces)), min_len=1))
    info["boundary_loops"] = len(mesh.outline().entities) if len(mesh.faces) else 0
    mesh.metadata["segmentation"] = info
    return mesh, tube.truth


# --- 1. Closing the open ends -------------------------------------------------------------

def _open_ends(vertices, faces):
    """[(loop (n,) vertex indices in order, centre (3,), normal (3,), reach)] for each
    boundary loop: its plane's centre and normal (least squares), the normal away from the
    tube (from the mean of the vertices within two reaches), reach the loop's largest
    distance from its centre."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    out = []
    for entity in mesh.outline().entities:
        loop = np.asarray(entity.points)
        if loop[0] == loop[-1]:
            loop = loop[:-1]
        ring = vertices[loop]
        centre = ring.mean(axis=0)
        normal = np.linalg.svd(ring - centre)[2][-1]
        reach = float(np.linalg.norm(ring - centre, axis=1).max())
        near = vertices[np.linalg.norm(vertices - centre, axis=1) < 2.0 * reach]
        if (near.mean(axis=0) - centre) @ normal > 0:
            normal = -normal
        out.append((loop, centre, normal, reach))
    return out


def _capped(vertices, faces, ends, extension=END_EXTENSION):
    """The mesh closed: each loop joined to a copy of itself moved `extension` along its
    normal, that copy closed by a fan around its centre. (Winding is left as it falls: the
    voxelisation counts crossings, not orientation.)"""
    vertices, faces = [vertices], [faces]
    count = len(vertices[0])
    for loop, centre, normal, _ in ends:
        n = len(loop)
        moved = np.arange(count, count + n)
        apex = count + n
        vertices += [vertices[0][loop] + extension * normal, (centre + extension * normal)[None]]
        a, b = loop, np.roll(loop, -1)
        c, d = moved, np.roll(moved, -1)
        faces += [np.column_stack([a, b, d]), np.column_stack([a, d, c]),
                  np.column_stack([c, d, np.full(n, apex)])]
        count += n + 1
    return np.concatenate(vertices), np.concatenate(faces)


# --- 2-4. Voxelised, blurred and meshed slab by slab --------------------------------------

def _segment(vertices, faces, spacing, blur, rng, info):
    """The level 0.5 of the closed surface's blurred binary volume on a grid of `spacing`
    (x, y, z), as one welded mesh. Slabs run along the longer of x and y; columns for the
    parity test along z."""
    slab_axis = 0 if np.ptp(vertices[:, 0]) >= np.ptp(vertices[:, 1]) else 1
    perm = np.array([slab_axis, 1 - slab_axis, 2])
    v = vertices[:, perm]
    h = spacing[perm]
    sigma = blur / h if blur > 0 else np.zeros(3)
    halo = (np.ceil(4.0 * sigma) + 2).astype(int)
    origin = v.min(axis=0) - (halo + 2) * h - rng.uniform(0.0, 1.0, 3) * h
    shape = np.ceil((v.max(axis=0) - origin) / h).astype(int) + halo + 3
    info["grid"] = [int(n) for n in shape[np.argsort(perm)]]
    tri = v[faces]
    tri_lo = np.floor((tri.min(axis=1) - origin) / h).astype(int)
    tri_hi = np.ceil((tri.max(axis=1) - origin) / h).astype(int)
    pieces, carried, odd = [], None, 0
    for a in range(0, shape[0] - 1, SLAB):
        b = min(a + SLAB, shape[0] - 1)       # cubes a .. b-1, points a .. b
        x0, x1 = a - halo[0], b + halo[0]     # points voxelised (with the blur's halo)
        near = (tri_hi[:, 0] >= x0) & (tri_lo[:, 0] <= x1)
        if not near.any():
            carried = None
            continue
        lo = np.maximum(tri_lo[near].min(axis=0) - halo - 1, 0)
        hi = np.minimum(tri_hi[near].max(axis=0) + halo + 1, shape - 1)
        lo[0], hi[0] = x0, x1
        inside, n_odd = _voxelise(tri[near], origin, h, lo, hi)
        odd += n_odd
        field = inside.astype(np.float32)
        if blur > 0:
            field = ndimage.gaussian_filter(field, sigma, mode="constant", cval=0.0)
        values = 0.5 - field[halo[0]:halo[0] + (b - a) + 1]
        values[values == 0.0] = 1e-6           # no grid point exactly on the surface
        if carried is not None:                # the shared plane exactly as the last slab had it
            plane, plo = carried
            _paste(values[0], lo[1:], plane, plo)
        carried = (values[-1].copy(), lo[1:].copy())
        slab_origin = origin + np.array([a, lo[1], lo[2]]) * h
        pieces += _mesh_components(values, slab_origin, h)
    info["odd_columns"] = int(odd)
    if not pieces:
        raise ValueError("the volume holds no lumen")
    vertices = np.concatenate([p.vertices for p in pieces])
    offsets = np.cumsum([0] + [len(p.vertices) for p in pieces[:-1]])
    faces = np.concatenate([p.faces + o for p, o in zip(pieces, offsets)])
    if slab_axis == 1:   # x and y swapped back: a mirror, which turns the winding over
        faces = faces[:, ::-1]
    mesh = trimesh.Trimesh(vertices[:, np.argsort(perm)], faces, process=True)
    info["winding_consistent"] = bool(mesh.is_winding_consistent)
    return mesh


def _paste(target, target_lo, source, source_lo):
    """Copies the overlap of plane `source` (its first grid index `source_lo`) into plane
    `target` (first index `target_lo`)."""
    a = np.maximum(target_lo, source_lo)
    b = np.minimum(target_lo + target.shape, source_lo + source.shape)
    if np.any(b <= a):
        return
    target[a[0] - target_lo[0]:b[0] - target_lo[0], a[1] - target_lo[1]:b[1] - target_lo[1]] = \
        source[a[0] - source_lo[0]:b[0] - source_lo[0], a[1] - source_lo[1]:b[1] - source_lo[1]]


def _voxelise(tri, origin, h, lo, hi):
    """(inside (nx, ny, nz) bool, odd columns): the grid points lo..hi (inclusive indices)
    inside the closed surface `tri` (T, 3, 3), by the parity of its crossings along z below
    each point. A column crossed an odd number of times (grazing an edge) is left empty."""
    n = hi - lo + 1
    ilo = np.maximum(np.ceil((tri[:, :, 0].min(axis=1) - origin[0]) / h[0]).astype(int), lo[0])
    ihi = np.minimum(np.floor((tri[:, :, 0].max(axis=1) - origin[0]) / h[0]).astype(int), hi[0])
    jlo = np.maximum(np.ceil((tri[:, :, 1].min(axis=1) - origin[1]) / h[1]).astype(int), lo[1])
    jhi = np.minimum(np.floor((tri[:, :, 1].max(axis=1) - origin[1]) / h[1]).astype(int), hi[1])
    ni, nj = np.maximum(ihi - ilo + 1, 0), np.maximum(jhi - jlo + 1, 0)
    count = ni * nj
    which = np.repeat(np.arange(len(tri)), count)
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    i = ilo[which] + k // nj[which]
    j = jlo[which] + k % nj[which]
    x = origin[0] + i * h[0]
    y = origin[1] + j * h[1]
    p0, p1, p2 = tri[which, 0], tri[which, 1], tri[which, 2]
    # Barycentric coordinates of (x, y) in the triangle's projection on the xy plane.
    d1, d2 = p1[:, :2] - p0[:, :2], p2[:, :2] - p0[:, :2]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    rx, ry = x - p0[:, 0], y - p0[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (rx * d2[:, 1] - ry * d2[:, 0]) / det
        w = (d1[:, 0] * ry - d1[:, 1] * rx) / det
    hit = (det != 0) & (u >= 0) & (w >= 0) & (u + w <= 1)
    z = (p0[:, 2] + u * (p1[:, 2] - p0[:, 2]) + w * (p2[:, 2] - p0[:, 2]))[hit]
    column = ((i[hit] - lo[0]) * n[1] + (j[hit] - lo[1]))
    order = np.lexsort((z, column))
    column, z = column[order], z[order]
    starts = np.r_[0, np.flatnonzero(np.diff(column)) + 1]
    per = np.diff(np.r_[starts, len(column)])
    odd_columns = per % 2 == 1
    good = ~np.repeat(odd_columns, per)
    column, z = column[good], z[good]
    # Crossings in pairs along each column: inside from the first of a pair to the second.
    z_in, z_out, col = z[0::2], z[1::2], column[0::2]
    k_in = np.clip(np.ceil((z_in - origin[2]) / h[2]).astype(int) - lo[2], 0, n[2])
    k_out = np.clip(np.floor((z_out - origin[2]) / h[2]).astype(int) - lo[2] + 1, 0, n[2])
    steps = np.zeros((n[0] * n[1], n[2] + 1), dtype=np.int16)
    np.add.at(steps, (col, k_in), 1)
    np.add.at(steps, (col, k_out), -1)
    inside = np.cumsum(steps[:, :-1], axis=1) > 0
    return inside.reshape(n[0], n[1], n[2]), int(odd_columns.sum())


def _mesh_components(values, origin, h):
    """`marching_tetrahedra` on each connected piece of the slab's lumen (26-connected grid
    points: any two inside points a tetrahedron's edge joins belong to one piece), each on
    its own box; others' points set outside. (marching_tetrahedra keeps the largest surface
    piece of what it meshes: one piece at a time loses nothing but slivers.)"""
    label, count = ndimage.label(values < 0, structure=np.ones((3, 3, 3)))
    out = []
    for c, box in enumerate(ndimage.find_objects(label), start=1):
        if box is None:
            continue
        box = tuple(slice(max(s.start - 1, 0), min(s.stop + 1, n))
                    for s, n in zip(box, values.shape))
        part = values[box].copy()
        part[(label[box] != c) & (part < 0)] = 0.5
        if min(part.shape) < 2:
            continue
        start = np.array([s.start for s in box])
        out.append(_outward(marching_tetrahedra(part, origin + start * h, h), part,
                            origin + start * h, h))
    return out


def _outward(mesh, values, origin, h):
    """The mesh's faces wound with their normals out of the lumen: toward the side where
    the field (growing outward) is larger, sampled (trilinear) a third of a voxel either
    side of each face's centre."""
    faces = np.asarray(mesh.faces).copy()
    if len(faces) == 0:
        return mesh
    c, n = mesh.triangles_center, mesh.face_normals
    step = n * (h.min() / 3.0)
    ahead, behind = (ndimage.map_coordinates(values, ((p - origin) / h).T, order=1,
                                             mode="nearest") for p in (c + step, c - step))
    inward = ahead < behind
    faces[inward] = faces[inward][:, ::-1]
    return trimesh.Trimesh(mesh.vertices, faces, process=False)


# --- 5, 6, 8. Opened, noised, holed -----------------------------------------------------------

def _open_again(mesh, vertices, ends, margin):
    """The faces beyond an open end's plane (up to the extrusion's cap, + 3 mm) whose centres
    fall, seen along its normal, within its loop or `margin` of it, removed; then the
    largest connected piece kept (crumbs of a cap fall away). A wall reaching beyond the
    plane outside the loop (an oblique cut after a bend) stays."""
    c = mesh.triangles_center
    keep = np.ones(len(c), dtype=bool)
    for loop, centre, normal, reach in ends:
        d = (c - centre) @ normal
        candidates = np.flatnonzero((d > 0.0) & (d < END_EXTENSION + 3e-3)
                                    & (np.linalg.norm(c - centre, axis=1) < reach + 0.01))
        if len(candidates) == 0:
            continue
        u = np.linalg.svd(np.eye(3) - np.outer(normal, normal))[0][:, :2]  # the plane's axes
        polygon = (vertices[loop] - centre) @ u
        points = (c[candidates] - centre) @ u
        inside = _in_polygon(points, polygon)
        dense = _densified(polygon, 0.25 * margin)
        close = cKDTree(dense).query(points)[0] < margin
        keep[candidates[inside | close]] = False
    out = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    pieces = trimesh.graph.connected_components(out.face_adjacency, min_len=1,
                                                nodes=np.arange(len(out.faces)))
    out = trimesh.Trimesh(out.vertices, out.faces[np.sort(max(pieces, key=len))], process=False)
    out.remove_unreferenced_vertices()
    return out


def _in_polygon(points, polygon):
    """Whether each 2-D point lies inside the closed polygon (crossing count)."""
    a, b = polygon, np.roll(polygon, -1, axis=0)
    x, y = points[:, :1], points[:, 1:]
    spans = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        cross_x = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return np.sum(spans & (x < cross_x), axis=1) % 2 == 1


def _densified(polygon, step):
    """Points along the closed polygon's edges every ~`step`."""
    a, b = polygon, np.roll(polygon, -1, axis=0)
    out = [a]
    for k in range(1, int(np.ceil(np.linalg.norm(b - a, axis=1).max() / step))):
        t = k * step / np.maximum(np.linalg.norm(b - a, axis=1), 1e-12)
        ok = t < 1.0
        out.append((a + t[:, None] * (b - a))[ok])
    return np.concatenate(out)


def _neighbour_mean(mesh):
    """The (V, V) sparse matrix averaging each vertex's value with its neighbours'."""
    edges = mesh.edges_unique
    n = len(mesh.vertices)
    rows = np.r_[edges[:, 0], edges[:, 1], np.arange(n)]
    cols = np.r_[edges[:, 1], edges[:, 0], np.arange(n)]
    a = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)).tocsr()
    degree = np.asarray(a.sum(axis=1)).ravel()
    return coo_matrix((1.0 / degree[rows], (rows, cols)), shape=(n, n)).tocsr()


def _noised(mesh, sigma, rng):
    """Each vertex moved along its normal by smoothed Gaussian noise of standard deviation
    `sigma`."""
    noise = rng.normal(size=len(mesh.vertices))
    average = _neighbour_mean(mesh)
    for _ in range(NOISE_SMOOTHING):
        noise = average @ noise
    noise *= sigma / max(float(np.std(noise)), 1e-12)
    moved = mesh.vertices + noise[:, None] * mesh.vertex_normals
    return trimesh.Trimesh(moved, mesh.faces, process=False)


def _holed(mesh, count, rng):
    """(mesh, radii, perimeters): `count` discs of faces removed: the faces lying in a ball
    of the radius around a random face's centre (all three corners in it; at least that
    face) and joined to that face across edges (the wall's disc, not also the far side of a
    fold within reach), centred at least HOLE_CLEARANCE from the boundary (the open ends)
    and from one another. perimeters [m]: the holes' boundary loops', ragged at the faces'
    scale."""
    c = mesh.triangles_center
    loops = mesh.outline().entities
    boundary = np.unique(np.concatenate([e.points for e in loops])) if len(loops) \
        else np.array([], dtype=int)
    clear = np.ones(len(c), dtype=bool)
    if len(boundary):
        clear = cKDTree(mesh.vertices[boundary]).query(c)[0] > HOLE_CLEARANCE
    keep = np.ones(len(c), dtype=bool)
    tree = cKDTree(c)
    corners = mesh.vertices[mesh.faces]
    adjacency = mesh.face_adjacency
    radii = []
    for _ in range(count):
        candidates = np.flatnonzero(clear)
        if len(candidates) == 0:
            break
        first = int(rng.choice(candidates))
        r = float(rng.uniform(*HOLE_RADIUS))
        near = np.zeros(len(c), dtype=bool)
        ball = np.array(tree.query_ball_point(c[first], r), dtype=int)
        inside = np.linalg.norm(corners[ball] - c[first], axis=2).max(axis=1) <= r
        near[ball[inside]] = True
        near[first] = True
        pairs = adjacency[near[adjacency[:, 0]] & near[adjacency[:, 1]]]
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                           shape=(len(c), len(c)))
        label = connected_components(graph, directed=False)[1]
        keep[near & (label == label[first])] = False
        clear[tree.query_ball_point(c[first], HOLE_CLEARANCE + HOLE_RADIUS[1])] = False
        radii.append(r)
    out = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    was_boundary = np.zeros(len(mesh.vertices), dtype=bool)
    was_boundary[boundary] = True
    perimeters = []
    for loop in out.outline().entities:
        if not was_boundary[loop.points].any():
            ring = out.vertices[loop.points]
            perimeters.append(float(np.sum(np.linalg.norm(np.diff(ring, axis=0), axis=1))))
    out.remove_unreferenced_vertices()
    return out, radii, sorted(perimeters)
