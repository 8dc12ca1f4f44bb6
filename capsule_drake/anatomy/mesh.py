"""Triangle meshes of the colon wall and plain OBJ/MTL writers.

The colon tissue is the solid and the lumen is outside it, so face normals point INTO the
lumen (toward the centreline). Rings of vertices lie exactly on `wall_radius`.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

def mucosa_mtl(texture_file: str, specular: float, shininess: float) -> str:
    """Material of the mucosa: the texture as diffuse map (Kd = 1 leaves its colours as
    they are) and a moderate specular term for the wet sheen."""
    return f"""# Colonic mucosa: procedural texture, moist surface with a soft specular highlight.
newmtl mucosa
Ka 0.20 0.08 0.07
Kd 1.00 1.00 1.00
Ks {specular:.3f} {specular:.3f} {specular:.3f}
Ns {shininess:.1f}
d 1.0
illum 2
map_Kd {texture_file}
"""

SKIN_MTL = """# Abdominal skin, meant to be drawn semi-transparent.
newmtl skin
Ka 0.20 0.16 0.14
Kd 0.88 0.72 0.62
Ks 0.05 0.05 0.05
Ns 10.0
d 0.3
illum 2
"""


def ring_stations(colon, max_step: float, tolerance: float | None = None,
                  min_step: float = 0.001) -> np.ndarray:
    """Arc lengths of the wall's rings, from 0 to L.

    Uniform at `max_step` when `tolerance` is None. Otherwise the spacing adapts to the
    wall's axial curvature so that the straight edges between rings stay within `tolerance`
    of the analytic wall: a chord of length h across a curve with second derivative k sags
    by k h^2 / 8, so h = sqrt(8 tolerance / k), clipped to [min_step, max_step]. Folds get
    dense rings and the smooth stretches between them sparse ones.
    """
    length = colon.centerline.length
    if tolerance is None:
        return np.linspace(0.0, length, int(np.ceil(length / max_step)) + 1)
    fine = np.arange(0.0, length + 2.5e-4, 2.5e-4)
    theta = np.linspace(0.0, 2.0 * np.pi, 48, endpoint=False)
    r = colon.wall_radius(fine[:, None], theta[None, :])
    k = np.zeros(len(fine))
    k[1:-1] = np.max(np.abs(r[2:] - 2.0 * r[1:-1] + r[:-2]), axis=1) / 2.5e-4**2
    k = np.maximum.reduce([k, np.roll(k, 1), np.roll(k, -1)])
    step = np.clip(np.sqrt(8.0 * tolerance / np.maximum(k, 1e-9)), min_step, max_step)
    stations = [0.0]
    while stations[-1] < length:
        here = stations[-1]
        window = (fine >= here) & (fine <= here + max_step)
        # The smallest spacing wanted anywhere the next edge will span.
        stations.append(min(length, here + float(np.min(step[window]))))
    return np.array(stations)


def tube_rings(colon, stations: np.ndarray, points_around: int):
    """Ring vertices of the wall at the given arc lengths.

    Returns:
        (s, theta, rings): s (R,) the stations, theta (M,), rings (R, M, 3).
    """
    cl = colon.centerline
    s = np.asarray(stations, dtype=float)
    theta = np.linspace(0.0, 2.0 * np.pi, points_around, endpoint=False)
    _, n, b = cl.frame_at(s)
    w = colon.wall_radius(s[:, None], theta[None, :])
    c = cl.point_at(s)
    rings = (c[:, None, :] + w[..., None] * (np.cos(theta)[None, :, None] * n[:, None, :]
                                            + np.sin(theta)[None, :, None] * b[:, None, :]))
    return s, theta, rings


def tube_faces(n_rings: int, m: int, first_ring: int = 0) -> np.ndarray:
    """Triangles between consecutive rings, wound so normals face the centreline."""
    i = np.arange(first_ring, first_ring + n_rings - 1)[:, None]
    j = np.arange(m)[None, :]
    a = i * m + j
    b = i * m + (j + 1) % m
    c = (i + 1) * m + j
    d = (i + 1) * m + (j + 1) % m
    # With theta turning from the normal to the binormal (normal x binormal = tangent),
    # (a, c, b) has normal along -radial, i.e. toward the centreline.
    tri1 = np.stack([a, c, b], axis=-1).reshape(-1, 3)
    tri2 = np.stack([b, c, d], axis=-1).reshape(-1, 3)
    return np.concatenate([tri1, tri2])


def cap_faces(ring_start: int, m: int, center: int, at_start: bool) -> np.ndarray:
    """Fan closing a ring; normals point into the lumen (+tangent at the start)."""
    j = np.arange(m)
    a = ring_start + j
    b = ring_start + (j + 1) % m
    cen = np.full(m, center)
    return np.stack([cen, a, b] if at_start else [cen, b, a], axis=-1)


def closed_tube(colon, stations: np.ndarray, points_around: int) -> trimesh.Trimesh:
    """The whole wall with both end caps, as one mesh."""
    s, _, rings = tube_rings(colon, stations, points_around)
    r, m, _ = rings.shape
    cl = colon.centerline
    verts = np.concatenate([rings.reshape(-1, 3), cl.point_at(np.array([0.0, cl.length]))])
    faces = np.concatenate([tube_faces(r, m), cap_faces(0, m, r * m, True),
                            cap_faces((r - 1) * m, m, r * m + 1, False)])
    return trimesh.Trimesh(verts, faces, process=False)


@dataclass
class TexturedMesh:
    """A mesh with per-vertex normals and texture coordinates, ready for an OBJ.

    Attributes:
        vertices: (V, 3) positions [m].
        normals: (V, 3) unit vertex normals.
        uv: (V, 2) texture coordinates (u around the lumen, v along it).
        faces: (F, 3) vertex indices, wound so normals face the centreline.
        s: (V,) arc length [m] of each vertex's ring (0 and L on the end caps).
    """

    vertices: np.ndarray
    normals: np.ndarray
    uv: np.ndarray
    faces: np.ndarray
    s: np.ndarray

    def subset(self, keep_faces: np.ndarray) -> "TexturedMesh":
        """The faces where `keep_faces` (F,) is true, with only the vertices they use."""
        faces = self.faces[np.asarray(keep_faces, dtype=bool)]
        used, inverse = np.unique(faces, return_inverse=True)
        return TexturedMesh(self.vertices[used], self.normals[used], self.uv[used],
                            inverse.reshape(-1, 3), self.s[used])


def textured_tube(colon, stations: np.ndarray, points_around: int, v_per_metre: float,
                  cap_u_per_metre: float) -> TexturedMesh:
    """The closed wall of `closed_tube` with texture coordinates for a tileable texture.

    Texture coordinates stay within [0, 1], so no renderer has to repeat the texture (Drake's
    VTK engine clamps it): u = theta / 2 pi runs 0..1 once around the lumen, the ring's first
    vertex being repeated at theta = 2 pi with u = 1, so no triangle interpolates u across
    the seam. v = s * `v_per_metre` modulo 1: a ring is inserted at every whole period of v
    and doubled there (v = 1 below, v = 0 above), which the tileable texture hides. The end
    caps get their own vertices, with flat normals and a planar projection of the texture
    (`cap_u_per_metre` across, `v_per_metre` along) centred on (0.5, 0.5). Positions and wall
    normals are those of the watertight tube: the duplicates are invisible.
    """
    length = colon.centerline.length
    period = 1.0 / v_per_metre
    wraps = np.arange(period, length - 1e-6, period)
    stations = np.asarray(stations, dtype=float)
    # Stations very close to a wrap would only make sliver triangles.
    near = np.min(np.abs(stations[:, None] - wraps[None, :]), axis=1,
                  initial=np.inf) < 1e-4
    stations = np.concatenate([stations[~near | (stations == 0) | (stations == length)],
                               wraps])
    order = np.argsort(stations, kind="stable")
    stations = stations[order]
    is_wrap = (np.arange(len(order)) >= len(order) - len(wraps))[order]

    s, theta, rings = tube_rings(colon, stations, points_around)
    r, m, _ = rings.shape
    # Normals from the wall alone, closed around the seam.
    wall = trimesh.Trimesh(rings.reshape(-1, 3), tube_faces(r, m), process=False)
    normals = np.asarray(wall.vertex_normals).reshape(r, m, 3)
    # Rows of vertices: every ring once, wrap rings twice (first closing a period at v = 1).
    ring_of_row = np.repeat(np.arange(r), np.where(is_wrap, 2, 1))
    phase = s * v_per_metre
    v_row = (phase - np.floor(phase))[ring_of_row]
    first_copy = np.r_[True, ring_of_row[1:] != ring_of_row[:-1]]
    v_row[is_wrap[ring_of_row] & first_copy] = 1.0
    v_row[is_wrap[ring_of_row] & ~first_copy] = 0.0
    rows = len(ring_of_row)
    seam = np.r_[np.arange(m), 0]
    vertices = [rings[ring_of_row][:, seam].reshape(-1, 3)]
    vertex_normals = [normals[ring_of_row][:, seam].reshape(-1, 3)]
    vertex_s = [np.repeat(s[ring_of_row], m + 1)]
    u = np.arange(m + 1) / m
    uv = [np.stack(np.broadcast_arrays(u[None, :], v_row[:, None]), axis=-1).reshape(-1, 2)]
    # Quads between consecutive rows of different rings, same winding as `tube_faces`.
    lower = np.flatnonzero(ring_of_row[1:] != ring_of_row[:-1])
    i = lower[:, None] * (m + 1)
    j = np.arange(m)[None, :]
    a, b = i + j, i + j + 1
    c, d = a + m + 1, b + m + 1
    faces = [np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)]

    cl = colon.centerline
    count = rows * (m + 1)
    for ring, at_start in ((0, True), (r - 1, False)):
        t, n, bn = (x[0] for x in cl.frame_at(np.array([s[ring]])))
        centre = cl.point_at(s[ring])
        points = np.concatenate([rings[ring], centre[None, :]])
        local = points - centre
        vertices.append(points)
        vertex_normals.append(np.tile(t if at_start else -t, (m + 1, 1)))
        uv.append(np.column_stack([0.5 + cap_u_per_metre * (local @ n),
                                   0.5 + v_per_metre * (local @ bn)]))
        faces.append(cap_faces(count, m, count + m, at_start))
        vertex_s.append(np.full(m + 1, s[ring]))
        count += m + 1
    return TexturedMesh(np.concatenate(vertices), np.concatenate(vertex_normals),
                        np.concatenate(uv), np.concatenate(faces), np.concatenate(vertex_s))


def tube_chunks(colon, stations: np.ndarray, points_around: int, chunks: int):
    """The wall split along its length; consecutive chunks share their boundary ring."""
    s, _, rings = tube_rings(colon, stations, points_around)
    r, m, _ = rings.shape
    cl = colon.centerline
    chunks = max(1, min(chunks, r - 1))
    cuts = np.round(np.linspace(0, r - 1, chunks + 1)).astype(int)
    out = []
    for k in range(chunks):
        r0, r1 = cuts[k], cuts[k + 1]
        verts = rings[r0:r1 + 1].reshape(-1, 3)
        faces = [tube_faces(r1 - r0 + 1, m)]
        extra = []
        if k == 0:
            extra.append(cl.point_at(0.0))
            faces.append(cap_faces(0, m, len(verts), True))
        if k == chunks - 1:
            extra.append(cl.point_at(cl.length))
            faces.append(cap_faces((r1 - r0) * m, m, len(verts) + len(extra) - 1, False))
        if extra:
            verts = np.concatenate([verts, np.array(extra)])
        out.append(trimesh.Trimesh(verts, np.concatenate(faces), process=False))
    return out


def write_obj(path, mesh: trimesh.Trimesh, normals: bool = False,
              material: tuple[str, str] | None = None) -> None:
    """Plain OBJ writer (1-based indices); `material` = (mtl file name, material name)."""
    path = Path(path)
    lines = ["# generated by capsule_drake.anatomy"]
    if material is not None:
        lines.append(f"mtllib {material[0]}")
    body = [_rows("v", mesh.vertices, "%.6f")]
    if normals:
        body.append(_rows("vn", mesh.vertex_normals, "%.5f"))
    if material is not None:
        body.append(f"usemtl {material[1]}\n")
    f = np.asarray(mesh.faces) + 1
    if normals:
        ff = np.repeat(f, 2, axis=1)
        body.append(_rows("f", ff, "%d//%d %d//%d %d//%d", row_fmt=True))
    else:
        body.append(_rows("f", f, "%d"))
    path.write_text("\n".join(lines) + "\n" + "".join(body))


def write_textured_obj(path, mesh: TexturedMesh, material: tuple[str, str]) -> None:
    """OBJ with `v`, `vt`, `vn` and `f v/vt/vn` faces (one index shared by all three);
    `material` = (mtl file name, material name)."""
    f = np.repeat(np.asarray(mesh.faces) + 1, 3, axis=1)
    body = [_rows("v", mesh.vertices, "%.6f"), _rows("vt", mesh.uv, "%.5f"),
            _rows("vn", mesh.normals, "%.5f"), f"usemtl {material[1]}\n",
            _rows("f", f, "%d/%d/%d %d/%d/%d %d/%d/%d", row_fmt=True)]
    Path(path).write_text(f"# generated by capsule_drake.anatomy\nmtllib {material[0]}\n"
                          + "".join(body))


def _rows(tag: str, array, fmt: str, row_fmt: bool = False) -> str:
    array = np.asarray(array)
    if row_fmt:
        template = f"{tag} {fmt}\n"
    else:
        template = f"{tag} " + " ".join([fmt] * array.shape[1]) + "\n"
    return (template * len(array)) % tuple(array.ravel())
