"""Diverticula: pouches of the wall (anatomy/lesions.py draws them; sources in
docs/sources.md section 3.4).

A diverticulum is a hole in the wall, its neck, and a sac behind it. Its place is found as a
polyp's is (its segment, its place along it, its angle from the floor); its neck is a circle
of the drawn diameter draped on the mucosa, and its sac a cylinder of the neck's radius that
ends in a hemisphere, as deep as the neck is wide (U: published sizes are the neck's or the
sac's width, not their depth; a sac wider than its neck is not modelled).

The colon's meshes (camera, visual, collision) are cut by the same rule (`cut`): every
triangle whose centroid lies, seen along the wall's normal, within the neck's radius plus the
mesh's longest edge there is removed, and the hole's rim is joined to the neck by a collar of
triangles (a zip of the two loops by their angle around the neck). The mesh stays closed where
it was closed: wall, collar and sac meet vertex for vertex. The mucosa's texture needs the
collar's vertices away from its seams (theta = 0 and every period along the colon), so a
diverticulum whose cut would reach one is moved just clear of it (at most the cut's reach;
U: the seam's place has no anatomical meaning, so this only shifts a few pouches by up to
~2 cm).

The convex-pieces contact model (anatomy/pieces.py) wraps the analytic wall, which has no
pouches: there the capsule rides over a neck as over level mucosa.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import trimesh

from .lesion_geometry import drape, floor_angle, segment_s, site_frame, wall_site
from .lesions import DrawnLesion
from .mesh import TexturedMesh

_log = logging.getLogger("capsule_drake.anatomy")

NECK_POINTS = 24
"""Vertices around a neck (and each ring of its sac)."""
SAC_DEPTH_PER_DIAMETER = 1.0
"""A sac's depth below its neck, per neck diameter (U)."""
CUT_REACH = 0.016
"""How far beyond the neck's radius a cut may reach (m): the longest edge of the coarsest
wall mesh (the camera's, 32 vertices around a 35 mm cecal radius: 6.9 mm) from a removed
triangle's centroid, plus its two thirds, rounded up."""
SPACING_CELL = 0.008
"""The coarsest wall mesh's largest cell diagonal (m): two necks' cuts stay apart by both
radii and three of these (`place_diverticula`)."""
MAX_NECK_MM = 20.0
"""The widest neck the meshes are cut for (a giant diverticulum is wider, and rare)."""


@dataclasses.dataclass(frozen=True)
class PlacedDiverticulum:
    """A diverticulum in the wall: its neck and sac in the world frame."""

    index: int                 # its place in the patient's list of lesions
    lesion: DrawnLesion
    s: float                   # arc length of its neck's centre (m)
    theta: float               # angle around the centreline (rad, the centreline's frame)
    base_W: np.ndarray         # the neck's centre on the wall (m)
    axis_W: np.ndarray         # the wall's unit inward normal there (the sac lies along -axis)
    frame_W: np.ndarray        # 3x3: columns x, y across the neck, z = axis_W
    neck_radius: float         # m
    depth: float               # from the neck's centre to the sac's bottom (m)
    rim_W: np.ndarray          # (NECK_POINTS, 3) the neck, draped on the mucosa
    sac_vertices_W: np.ndarray  # (S, 3) the sac's other vertices
    sac_faces: np.ndarray      # (F, 3) into [rim_W, sac_vertices_W], normals into the pouch

    @property
    def top_W(self) -> np.ndarray:
        """The point of the lesion nearest the lumen's axis: the neck's centre."""
        return self.base_W

    @property
    def sac(self) -> trimesh.Trimesh:
        """The pouch's inside, open at the neck; normals face into the pouch."""
        return trimesh.Trimesh(np.vstack([self.rim_W, self.sac_vertices_W]), self.sac_faces,
                               process=False)


def _off_seams(colon, s: float, theta: float, reach: float) -> tuple[float, float]:
    """(s, theta) moved so that nothing within `reach` of the wall point crosses the mucosa
    texture's seams: theta = 0 (its u seam) and every texture period along the colon."""
    mucosa = colon.params.mucosa
    period = mucosa.texels_along / mucosa.texels_per_metre
    wrap = round(s / period) * period
    if wrap > 0.0 and abs(s - wrap) < reach:
        s = wrap + (reach if s >= wrap else -reach)
    length = colon.centerline.length
    s = float(np.clip(s, reach, length - reach))
    r = float(colon.wall_radius(np.array([s]), np.array([theta]))[0])
    margin = min(reach / r, 0.5 * np.pi)
    t = float(np.mod(theta, 2 * np.pi))
    t = margin if t < margin else (2 * np.pi - margin if t > 2 * np.pi - margin else t)
    return s, t


def _sac_profile(radius: float, depth: float) -> tuple[np.ndarray, np.ndarray]:
    """(radius, depth below the neck) of the sac's rings under the neck, then its bottom:
    a cylinder down to depth - radius, then a hemisphere."""
    straight = max(depth - radius, 0.0)
    beta = np.radians([20.0, 40.0, 60.0, 80.0])
    r = np.concatenate([[radius, radius], radius * np.cos(beta), [0.0]])
    d = np.concatenate([[0.5 * straight, straight], straight + radius * np.sin(beta),
                        [straight + radius]])
    return r, d


def drawn_site(colon, lesion: DrawnLesion) -> tuple[float, float]:
    """(s, theta) where `lesion` asks to be: its segment, place along it, angle from the
    floor."""
    s = segment_s(colon, lesion)
    return s, floor_angle(colon, s) + np.radians(lesion.around_deg)


def place_diverticulum(colon, lesion: DrawnLesion, index: int = 0,
                       where: tuple[float, float] | None = None) -> PlacedDiverticulum:
    """`lesion` (a diverticulum) in the wall of a procedural `colon`, at its drawn site or
    at (s, theta) `where`, moved off the texture's seams."""
    if lesion.polyp:
        raise ValueError("a polyp is placed by anatomy/lesion_geometry.py")
    if lesion.size_mm > MAX_NECK_MM:
        raise ValueError(f"a diverticulum's neck of {lesion.size_mm:g} mm is wider than "
                         f"the {MAX_NECK_MM:g} mm the wall is cut for")
    radius = 0.5e-3 * lesion.size_mm
    s, theta = drawn_site(colon, lesion) if where is None else where
    s, theta = _off_seams(colon, s, theta, radius + CUT_REACH)
    site = wall_site(colon, s, theta)
    frame = site_frame(site)[:3, :3]
    x, y, axis = frame.T
    phi = 2 * np.pi * np.arange(NECK_POINTS) / NECK_POINTS
    around = np.outer(np.cos(phi), x) + np.outer(np.sin(phi), y)
    rim = drape(colon, site.base_W + radius * around, site.base_W, axis)
    depth = SAC_DEPTH_PER_DIAMETER * 2.0 * radius
    ring_r, ring_d = _sac_profile(radius, depth)
    lift = (rim - site.base_W) @ axis     # each rim point's height on the plane
    rings = (site.base_W + ring_r[:-1, None, None] * around[None]
             + (lift[None, :] - ring_d[:-1, None])[..., None] * axis)
    bottom = site.base_W + (float(np.mean(lift)) - ring_d[-1]) * axis
    vertices = np.vstack([rings.reshape(-1, 3), bottom[None]])
    m, k = NECK_POINTS, len(ring_r) - 1          # rings under the rim (the rim is ring 0)
    faces = []
    for i in range(k):                           # ring i (0: the rim) to ring i + 1
        j = np.arange(m)
        a, b = i * m + j, i * m + (j + 1) % m
        c, d = a + m, b + m
        faces += [np.stack([a, b, c], -1), np.stack([b, d, c], -1)]
    j = np.arange(m)
    tip = (k + 1) * m
    faces.append(np.stack([k * m + j, k * m + (j + 1) % m, np.full(m, tip)], -1))
    faces = np.concatenate(faces)
    # Normals into the pouch: the first wall triangle's normal against its way to the axis.
    p = np.vstack([rim, vertices])
    f0 = p[faces[0]]
    normal = np.cross(f0[1] - f0[0], f0[2] - f0[0])
    if normal @ (site.base_W - axis * 0.5 * depth - f0.mean(axis=0)) < 0.0:
        faces = faces[:, ::-1]
    return PlacedDiverticulum(index, lesion, site.s, site.theta, site.base_W, axis, frame,
                              radius, depth, rim, vertices, np.ascontiguousarray(faces))


def _apart(a_s, a_theta, a_radius, b: PlacedDiverticulum, r: float) -> bool:
    """True when two necks' cuts cannot meet: apart by more than both radii and three of
    the coarsest mesh's cells (SPACING_CELL) along the lumen or around it."""
    reach = a_radius + b.neck_radius + 3 * SPACING_CELL
    return (abs(a_s - b.s) >= reach
            or r * abs(np.angle(np.exp(1j * (a_theta - b.theta)))) >= reach)


def place_diverticula(colon, lesions: list[DrawnLesion]) -> list[PlacedDiverticulum]:
    """The diverticula of `lesions` in the wall of `colon`, indexed by their place in the
    list. Each is placed where it was drawn unless an earlier one's cut lies there; then
    it goes to the nearest clear place found turning around the lumen in steps of 30
    degrees and moving along it in steps of its own reach (U: diverticula crowd less than
    a patient's may; a patient with more than the wall has room for loses the rest, with a
    warning)."""
    placed = []
    for k, lesion in enumerate(lesions):
        if lesion.polyp:
            continue
        s0, theta0 = drawn_site(colon, lesion)
        radius = 0.5e-3 * lesion.size_mm
        step = 2 * radius + 3 * SPACING_CELL
        length = colon.centerline.length
        for along in (0, 1, -1, 2, -2, 3, -3, 4, -4, 5, -5, 6, -6):
            s = s0 + along * step
            if not 0.05 < s < length - 0.05:
                continue
            for turn in range(12):
                where = _off_seams(colon, s, theta0 + np.radians(30.0 * turn),
                                   radius + CUT_REACH)
                r = float(colon.wall_radius(np.array([where[0]]), np.array([where[1]]))[0])
                if all(_apart(*where, radius, other, r) for other in placed):
                    placed.append(place_diverticulum(colon, lesion, k, where))
                    break
            else:
                continue
            break
        else:
            _log.warning(f"diverticulum {k}: no room left in the wall near its place "
                         f"(s = {s0:.3f} m); not placed")
    return placed


class CollarFoldsOver(ValueError):
    """A cut's collar would fold over (its triangles turn their backs to the lumen)."""


@dataclasses.dataclass
class Cut:
    """A mesh's triangles around one neck removed and the hole joined to the neck.

    Attributes:
        keep: (F,) the mesh's triangles that stay.
        loop: (K,) the hole's rim: indices of the mesh's vertices, in order around the neck.
        collar: (K + N, 3) triangles into [loop vertices, neck vertices], facing the lumen.
        removed: (R,) indices of the removed triangles.
    """

    keep: np.ndarray
    loop: np.ndarray
    collar: np.ndarray
    removed: np.ndarray


def cut(vertices: np.ndarray, faces: np.ndarray, pouch: PlacedDiverticulum,
        centerline) -> Cut:
    """Where a mesh of the wall is cut for `pouch` (`cut_once`): with a margin of one cell
    around the neck, or of two or three where the collar would fold over with one (a fold's
    flank or a steep flexure within the first: one of 200 drawn necks on seeds 0-39, in
    two of its three meshes)."""
    for cells in (1, 2):
        try:
            return cut_once(vertices, faces, pouch, centerline, cells)
        except CollarFoldsOver:
            pass
    return cut_once(vertices, faces, pouch, centerline, 3)


def cut_once(vertices: np.ndarray, faces: np.ndarray, pouch: PlacedDiverticulum,
             centerline, cells: int = 1) -> Cut:
    """Where a mesh of the wall (normals into the lumen; vertices shared by position may be
    repeated, as at a texture's seam or between collision chunks) is cut for `pouch`.

    The triangles removed are those whose three vertices lie, in tube coordinates (arc
    length s and angle theta about `centerline`), within the neck's span widened by the
    longest edge around it: the wall's rings and columns are lines of constant s and theta,
    so the hole is a block of whole cells, its rim goes once around the neck, and every
    triangle that meets the neck is in it. `cells` widens the margin to that many of the
    longest edges."""
    c, frame = pouch.base_W, pouch.frame_W
    local = (vertices - c) @ frame               # (x, y, height above the neck's plane)
    ring = float(np.max(np.linalg.norm(pouch.rim_W - c, axis=1)))
    centroid = local[faces].mean(axis=1)
    planar = np.hypot(centroid[:, 0], centroid[:, 1])
    near = ((planar < ring + (cells + 1) * CUT_REACH)
            & np.all(np.abs(local[faces, 2]) < 0.012, axis=1))
    tri = vertices[faces[near]]
    longest = float(np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)))
    used = np.unique(faces[near])
    s_v, rho_v, theta_v = centerline.closest(vertices[used])
    s_r, _, theta_r = centerline.closest(pouch.rim_W)
    turn = lambda t: np.angle(np.exp(1j * (t - pouch.theta)))   # noqa: E731
    ds, dt = s_v - pouch.s, turn(theta_v)
    ds_r, dt_r = s_r - pouch.s, turn(theta_r)
    slack = (cells + 0.05) * longest
    spread = slack / float(np.min(rho_v))
    inside = np.zeros(len(vertices), bool)
    inside[used] = ((ds > ds_r.min() - slack) & (ds < ds_r.max() + slack)
                    & (dt > dt_r.min() - spread) & (dt < dt_r.max() + spread))
    removed = np.flatnonzero(near & np.all(inside[faces], axis=1))
    if len(removed) == 0:
        raise ValueError(f"diverticulum {pouch.index}: no wall triangles at its neck")
    # Topology by position: vertices repeated at seams or chunk borders are one.
    _, first, canon_used = np.unique(np.round(vertices[used] / 1e-8).astype(np.int64),
                                     axis=0, return_index=True, return_inverse=True)
    canon = np.full(len(vertices), -1)
    canon[used] = canon_used.ravel()
    tri_canon = canon[faces[removed]]
    pairs = np.sort(np.concatenate([tri_canon[:, [0, 1]], tri_canon[:, [1, 2]],
                                    tri_canon[:, [2, 0]]]), axis=1)
    edges_u, counts = np.unique(pairs, axis=0, return_counts=True)
    boundary = edges_u[counts == 1]
    neighbours: dict[int, list[int]] = {}
    for a, b in boundary:
        neighbours.setdefault(int(a), []).append(int(b))
        neighbours.setdefault(int(b), []).append(int(a))
    if any(len(v) != 2 for v in neighbours.values()):
        raise ValueError(f"diverticulum {pouch.index}: the hole in the wall is not a disc")
    start = int(boundary[0, 0])
    order, previous = [start], -1
    while True:
        here = order[-1]
        a, b = neighbours[here]
        nxt = a if a != previous else b
        if nxt == start:
            break
        order.append(nxt)
        previous = here
    if len(order) != len(neighbours):
        raise ValueError(f"diverticulum {pouch.index}: the hole's rim is not one loop")
    at = first[np.array(order)]                  # the loop's places in `used`
    loop = used[at]
    # The collar is laid out where the hole is a block of whole cells: in tube coordinates
    # (s, r theta), where its rim goes around the neck's image like a star around its
    # centre; counter-clockwise there is a triangle facing the lumen (as the wall's own).
    r0 = float(np.median(rho_v))
    plane_loop = np.column_stack([ds[at], r0 * dt[at]])
    plane_rim = np.column_stack([ds_r, r0 * dt_r])
    angle = np.unwrap(np.arctan2(plane_loop[:, 1], plane_loop[:, 0]))
    turn = angle[-1] - angle[0] + np.angle(np.exp(1j * (angle[0] - angle[-1])))
    if abs(abs(turn) - 2 * np.pi) > 0.5:
        raise ValueError(f"diverticulum {pouch.index}: the hole's rim does not go once "
                         "around the neck")
    if turn < 0.0:
        loop, plane_loop = loop[::-1], plane_loop[::-1]
    rim_angle = np.arctan2(plane_rim[:, 1], plane_rim[:, 0])
    rim_turn = np.sum(np.angle(np.exp(1j * (np.roll(rim_angle, -1) - rim_angle))))
    rim_order = np.arange(NECK_POINTS) if rim_turn > 0.0 else np.arange(NECK_POINTS)[::-1]
    collar = _zip(np.arctan2(plane_loop[:, 1], plane_loop[:, 0]), rim_angle[rim_order])
    # Neck vertices back to their own order.
    k = len(loop)
    collar = np.where(collar >= k, k + rim_order[np.clip(collar - k, 0, None)], collar)
    keep = np.ones(len(faces), bool)
    keep[removed] = False
    flat = np.vstack([plane_loop, plane_rim])[collar]
    e1, e2 = flat[:, 1] - flat[:, 0], flat[:, 2] - flat[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    if np.any(area <= 0.0):
        raise CollarFoldsOver(f"diverticulum {pouch.index}: the collar folds over")
    return Cut(keep, loop, collar, removed)


def _zip(outer_angle: np.ndarray, inner_angle: np.ndarray) -> np.ndarray:
    """Triangles between two loops around a centre, each given by its vertices' angles in
    counter-clockwise order: into [outer (K), inner (N)], counter-clockwise."""
    k, n = len(outer_angle), len(inner_angle)

    def walk(angle):
        a = np.mod(angle, 2 * np.pi)
        first = int(np.argmin(a))
        order = np.roll(np.arange(len(a)), -first)
        a = np.unwrap(a[order])
        return order, np.append(a, a[0] + 2 * np.pi)

    outer, a = walk(outer_angle)
    inner, b = walk(inner_angle)
    # Both walks start at their smallest angle in [0, 2 pi); the later start waits.
    i = j = 0
    faces = []
    while i < k or j < n:
        if j == n or (i < k and a[i + 1] < b[j + 1]):
            faces.append((outer[i], outer[(i + 1) % k], k + inner[j % n]))
            i += 1
        else:
            faces.append((outer[i % k], k + inner[(j + 1) % n], k + inner[j % n]))
            j += 1
    return np.asarray(faces, dtype=np.int64)


def pouched_mesh(mesh: trimesh.Trimesh, pouches, centerline) -> trimesh.Trimesh:
    """`mesh` (the wall, normals into the lumen) cut for every pouch, each hole joined to its
    neck and closed by its sac: closed where `mesh` was."""
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    keep = np.ones(len(faces), bool)
    extra_v, extra_f = [], []
    count = len(vertices)
    for pouch in pouches:
        c = cut(vertices, faces, pouch, centerline)
        keep &= c.keep
        rim = count + np.arange(NECK_POINTS)
        index = np.concatenate([c.loop, rim])
        extra_v.append(pouch.rim_W)
        extra_f.append(index[c.collar])
        inner = count + NECK_POINTS + np.arange(len(pouch.sac_vertices_W))
        extra_v.append(pouch.sac_vertices_W)
        extra_f.append(np.concatenate([rim, inner])[pouch.sac_faces])
        count += NECK_POINTS + len(inner)
    if not pouches:
        return mesh
    out = trimesh.Trimesh(np.vstack([vertices] + extra_v),
                          np.vstack([faces[keep]] + extra_f), process=False)
    out.remove_unreferenced_vertices()
    return out


def pouched_textured(mesh: TexturedMesh, pouches, centerline) -> TexturedMesh:
    """`mesh` cut for every pouch and each hole joined to its neck (the sacs are geometry of
    their own). The neck's texture coordinates, normals and arc lengths are the removed
    vertices' fitted linearly across the neck's plane (the seams are kept clear of it)."""
    if not pouches:
        return mesh
    vertices, faces = mesh.vertices, mesh.faces
    keep = np.ones(len(faces), bool)
    parts = [[vertices], [mesh.normals], [mesh.uv], [mesh.s]]
    extra_f = []
    count = len(vertices)
    for pouch in pouches:
        c = cut(vertices, faces, pouch, centerline)
        keep &= c.keep
        around = np.unique(np.concatenate([faces[c.removed].ravel(), c.loop]))
        design = np.column_stack([(vertices[around] - pouch.base_W) @ pouch.frame_W[:, :2],
                                  np.ones(len(around))])
        target = np.column_stack([mesh.uv[around], mesh.normals[around], mesh.s[around]])
        coef, *_ = np.linalg.lstsq(design, target, rcond=None)
        neck = np.column_stack([(pouch.rim_W - pouch.base_W) @ pouch.frame_W[:, :2],
                                np.ones(NECK_POINTS)]) @ coef
        normals = neck[:, 2:5] / np.linalg.norm(neck[:, 2:5], axis=1, keepdims=True)
        parts[0].append(pouch.rim_W)
        parts[1].append(normals)
        parts[2].append(np.clip(neck[:, :2], 0.0, 1.0))
        parts[3].append(neck[:, 5])
        extra_f.append(np.concatenate([c.loop, count + np.arange(NECK_POINTS)])[c.collar])
        count += NECK_POINTS
    vertices, normals, uv, s = (np.concatenate(p) for p in parts)
    out = TexturedMesh(vertices, normals, uv, np.vstack([faces[keep]] + extra_f), s)
    return out.subset(np.ones(len(out.faces), bool))


def pouched_chunks(chunks: list[trimesh.Trimesh], pouches, centerline) -> list[trimesh.Trimesh]:
    """Collision chunks of the wall cut for every pouch, and one more chunk holding every
    collar and sac (rigid geometry need not be closed, so the chunks stay apart)."""
    if not pouches:
        return chunks
    merged = trimesh.util.concatenate(chunks)
    vertices, faces = np.asarray(merged.vertices), np.asarray(merged.faces)
    keep = np.ones(len(faces), bool)
    pieces = []
    for pouch in pouches:
        c = cut(vertices, faces, pouch, centerline)
        keep &= c.keep
        points = np.vstack([vertices[c.loop], pouch.rim_W, pouch.sac_vertices_W])
        k = len(c.loop)
        pieces.append(trimesh.Trimesh(points, np.vstack([c.collar, k + pouch.sac_faces]),
                                      process=False))
    out, start = [], 0
    for chunk in chunks:
        n = len(chunk.faces)
        kept = trimesh.Trimesh(chunk.vertices, np.asarray(chunk.faces)[keep[start:start + n]],
                               process=False)
        kept.remove_unreferenced_vertices()
        out.append(kept)
        start += n
    return out + [trimesh.util.concatenate(pieces)]
