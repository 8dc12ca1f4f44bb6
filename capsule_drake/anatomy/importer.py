"""Importing a user's colon mesh: load, check, repair.

Researchers bring meshes from CT segmentations, photogrammetry or a phantom's CAD, as OBJ,
STL, PLY or GLB. `load_colon_mesh` reads one with trimesh and `check_colon_mesh` refuses,
with one line naming the file and the problem, what cannot become a colon: a missing or
unreadable file, a file with no triangles, a point cloud, a mesh whose size is plainly in
the wrong unit, a flat sheet with no lumen. `repair_colon_mesh` fixes what can be fixed and
says what it did: duplicate and degenerate faces, inconsistent winding, small holes, and
normals pointing into the tissue instead of toward the lumen.
"""

from __future__ import annotations

import dataclasses
import io
from pathlib import Path

import numpy as np
import trimesh

FORMATS = (".obj", ".stl", ".ply", ".glb", ".gltf")

# A colon or a segment of one, in metres: its largest extent between these.
MIN_EXTENT = 0.01
MAX_EXTENT = 3.0
# A lumen needs depth: the smallest principal extent at least this share of the largest.
MIN_THICKNESS_RATIO = 0.02
# A boundary loop this short [m] is a hole to fill; a colon's open end is at least ~6 cm
# around (1 cm radius).
MAX_HOLE_PERIMETER = 0.03
# A longer loop is a hole too when it lies in the wall: the surface within 1.5 R of its
# centre (R its perimeter / 2 pi) keeps within HOLE_DEPTH R of its plane (90th percentile),
# where an open end's wall runs away from its plane along the lumen. Measured on the
# segmentation-like surfaces (tests/segmentation_set.py): holes of 2-4 mm radius 0.17-0.26,
# open ends 0.92-1.20; a hole on a curved wall passes 0.5 only when it is wider than about
# half the lumen across (a tear, which the tube check then refuses as a third end).
HOLE_DEPTH = 0.5


class MeshImportError(ValueError):
    """A mesh that cannot become a colon; the message is one line naming file and problem."""


# The most triangles an import takes. Measured on a 2-core machine (benchmarks/
# bench_import.py --sizes: a bent open tube, imported in a process of its own), quiet: 0.3 M
# triangles 20 s and 0.7 GB at its peak, 1.2 M 44 s and 1.35 GB, 2.4 M 76 s and 2.2 GB,
# 4.8 M 179 s and 4.1 GB; shared with other work, 66, 154, 163 and 288 s. The repairs and
# the decimation grow with the triangles (the centreline is found on the decimated wall),
# the memory by 0.8 GB a million. At 4 M an import takes 2-4 minutes and 3.5 GB. A mesh that
# large is a scan at a resolution the simulation does not use (the wall is decimated to
# --max-faces, 150,000 by default).
MAX_IMPORT_FACES = 4_000_000


# What a file given for a mesh holds, by its first bytes (offset, bytes, kind): a picture, a
# scan or a document is named for what it is, whatever its file name says.
_NOT_MESHES = (
    (0, b"\x89PNG\r\n\x1a\n", "a PNG image"), (0, b"\xff\xd8\xff", "a JPEG image"),
    (0, b"GIF87a", "a GIF image"), (0, b"GIF89a", "a GIF image"),
    (0, b"II*\x00", "a TIFF image"), (0, b"MM\x00*", "a TIFF image"),
    (0, b"%PDF-", "a PDF document"), (0, b"PK\x03\x04", "a ZIP archive"),
    (0, b"\x1f\x8b", "a gzip archive"), (128, b"DICM", "a DICOM image"),
    (344, b"n+1\x00", "a NIfTI volume"))
_VOLUMES = ("a DICOM image", "a NIfTI volume")


def _not_a_mesh(path: Path) -> str | None:
    """Why the file at `path` cannot be a mesh by its bytes (one line), or None."""
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    if path.suffix.lower() == ".stl" and len(head) >= 84:
        # A binary STL's 80-byte header may hold anything; its triangle count and the file's
        # size agree.
        count = int.from_bytes(head[80:84], "little")
        if path.stat().st_size == 84 + 50 * count:
            return None
    for offset, magic, kind in _NOT_MESHES:
        if head[offset:offset + len(magic)] == magic:
            what = ("segment the colon and export its surface" if kind in _VOLUMES
                    else "give the colon's surface")
            return (f"{kind}, not a mesh (by its bytes, whatever its name); {what} as "
                    "OBJ, STL, PLY or GLB")
    if path.suffix.lower() == ".obj" and b"\0" in head:
        return "not text (an OBJ file is text; this one holds binary bytes)"
    return None


def _too_many(path: Path, faces: int) -> MeshImportError:
    return MeshImportError(
        f"{path}: {faces:,} triangles, more than the {MAX_IMPORT_FACES:,} the import handles "
        "(minutes and gigabytes of memory at that size); simplify the mesh first, e.g. "
        "quadric decimation in MeshLab or Blender to under a million triangles (the import "
        "then decimates it to --max-faces)")


_COUNT_CHUNK = 1 << 24  # bytes read at a time when counting an OBJ's faces


def count_faces(path: Path) -> int | None:
    """The triangles in the file at `path` as its format states them without reading the
    mesh (at least that many: an OBJ's polygons count once), or None where it does not
    (GLB, glTF, an unreadable header)."""
    suffix = path.suffix.lower()
    with open(path, "rb") as f:
        if suffix == ".obj":
            count, previous = 0, b"\n"
            while chunk := f.read(_COUNT_CHUNK):
                text = previous + chunk
                count += text.count(b"\nf ") + text.count(b"\nf\t")
                previous = text[-2:]  # a line start cut by the chunk's end
            return count
        head = f.read(1 << 12)
    if suffix == ".stl":
        if len(head) >= 84 and path.stat().st_size == 84 + 50 * int.from_bytes(
                head[80:84], "little"):
            return int.from_bytes(head[80:84], "little")
        return None  # ASCII: counted once read
    if suffix == ".ply" and head.startswith(b"ply"):
        for line in head.split(b"end_header")[0].splitlines():
            words = line.split()
            if len(words) == 3 and words[0] == b"element" and words[1] == b"face":
                return int(words[2]) if words[2].isdigit() else None
    return None


def _read(path: Path):
    """trimesh.load of `path`; an OBJ that is not UTF-8 (a Latin-1 comment or name) is
    decoded as Latin-1 here (trimesh would need an optional package to guess its encoding),
    its material and texture files still found beside it."""
    if path.suffix.lower() == ".obj":
        data = path.read_bytes()
        try:
            data.decode("utf-8")
        except UnicodeDecodeError:
            text = data.decode("latin-1").encode("utf-8")
            return trimesh.load(io.BytesIO(text), file_type="obj",
                                resolver=trimesh.resolvers.FilePathResolver(str(path)))
    return trimesh.load(str(path))


@dataclasses.dataclass
class RepairReport:
    """What `repair_colon_mesh` changed."""

    removed_duplicate_faces: int = 0
    removed_degenerate_faces: int = 0
    fixed_winding: bool = False
    filled_holes: int = 0
    flipped_normals: bool = False
    open_ends: int = 0  # boundary loops left open (a tube's two ends)
    # Their lengths [m], measured before any decimation (the mesh as given).
    open_end_perimeters: tuple = ()
    stray_boundary_edges: int = 0  # open edges in no closed loop (at a non-manifold vertex)
    decimated_from: int = 0  # faces before decimation (0: not decimated)
    decimated_to: int = 0
    non_manifold_edges: int = 0  # edges shared by more than two faces (left as they are)

    def lines(self) -> list[str]:
        out = []
        if self.removed_duplicate_faces:
            out.append(f"removed {self.removed_duplicate_faces} duplicate faces")
        if self.removed_degenerate_faces:
            out.append(f"removed {self.removed_degenerate_faces} degenerate faces")
        if self.fixed_winding:
            out.append("made the faces' winding consistent")
        if self.filled_holes:
            out.append(f"filled {self.filled_holes} small holes")
        if self.flipped_normals:
            out.append("turned the normals toward the lumen")
        if self.non_manifold_edges:
            out.append(f"found {self.non_manifold_edges} non-manifold edges (shared by more "
                       "than two faces; left as they are: check the mesh where the lumen "
                       "looks wrong)")
        if self.stray_boundary_edges:
            out.append(f"found {self.stray_boundary_edges} open edges in no loop (left as "
                       "they are)")
        if self.decimated_from:
            out.append(f"decimated from {self.decimated_from} to {self.decimated_to} faces")
        out.append(f"{self.open_ends} open ends left open" if self.open_ends else
                   "no open edges (a closed surface, or a wall with thickness)")
        return out


def load_colon_mesh(path) -> trimesh.Trimesh:
    """Reads OBJ, STL, PLY or GLB/glTF into one triangle mesh (a scene's meshes joined, in
    the scene's frame). Raises MeshImportError with one line if it cannot."""
    path = Path(path)
    if not path.is_file():
        raise MeshImportError(f"{path}: no such file")
    if path.suffix.lower() not in FORMATS:
        raise MeshImportError(f"{path}: unsupported format {path.suffix or '(none)'!r}; "
                              f"expected one of {', '.join(FORMATS)}")
    try:
        reason = _not_a_mesh(path)
    except OSError as e:
        raise MeshImportError(f"{path}: cannot be read ({e.strerror or e})") from None
    if reason is not None:
        raise MeshImportError(f"{path}: {reason}")
    stated = count_faces(path)
    if stated is not None and stated > MAX_IMPORT_FACES:
        raise _too_many(path, stated)
    try:
        loaded = _read(path)
    except ImportError as e:  # an optional package trimesh wants for this file
        raise MeshImportError(
            f"{path}: not a readable mesh (neither a binary {path.suffix.lstrip('.').upper()}"
            " file nor UTF-8 text)" if e.name == "charset_normalizer" else
            f"{path}: reading it needs the Python package {e.name!r}, which is not "
            "installed") from None
    except Exception as e:  # trimesh raises many types for unreadable files
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise MeshImportError(f"{path}: not a readable mesh ({first})") from None
    if isinstance(loaded, trimesh.Scene):
        meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        clouds = [g for g in loaded.dump() if isinstance(g, trimesh.PointCloud)]
        if not meshes:
            if clouds:
                raise MeshImportError(f"{path}: a point cloud ({sum(len(c.vertices) for c in clouds)}"
                                      " points, no faces); mesh it first (e.g. Poisson)")
            raise MeshImportError(f"{path}: contains no triangles")
        loaded = meshes[0] if len(meshes) == 1 else trimesh.util.concatenate(meshes)
    if isinstance(loaded, trimesh.PointCloud):
        raise MeshImportError(f"{path}: a point cloud ({len(loaded.vertices)} points, no faces);"
                              " mesh it first (e.g. Poisson)")
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshImportError(f"{path}: not a triangle mesh ({type(loaded).__name__})")
    if len(loaded.faces) > MAX_IMPORT_FACES:
        raise _too_many(path, len(loaded.faces))
    if len(loaded.faces) == 0:
        if len(loaded.vertices):
            raise MeshImportError(f"{path}: a point cloud ({len(loaded.vertices)} points, "
                                  "no faces); mesh it first (e.g. Poisson)")
        raise MeshImportError(f"{path}: empty (no vertices, no faces)")
    return loaded


def check_colon_mesh(mesh: trimesh.Trimesh, name: str = "mesh") -> None:
    """Refuses, with one line, a mesh that cannot be a colon in metres: non-finite vertices,
    an extent outside 1 cm - 3 m (with the scale that would fix a wrong unit), or a flat
    sheet (no depth for a lumen)."""
    vertices = np.asarray(mesh.vertices, dtype=float)
    if not np.all(np.isfinite(vertices)):
        raise MeshImportError(f"{name}: has non-finite vertex coordinates")
    used = vertices[np.unique(np.asarray(mesh.faces).reshape(-1))]
    extent = float(np.max(np.ptp(used, axis=0)))
    if extent > MAX_EXTENT or extent < MIN_EXTENT:
        scale = _unit_guess(extent)
        hint = f"; if it is in {scale[0]}, scale it by {scale[1]:g}" if scale else ""
        raise MeshImportError(
            f"{name}: {extent:.4g} units across, not a colon in metres "
            f"({MIN_EXTENT:g}-{MAX_EXTENT:g} m){hint}")
    centred = used - used.mean(axis=0)
    spread = np.linalg.svd(centred, compute_uv=False) / np.sqrt(len(used))
    if spread[2] < MIN_THICKNESS_RATIO * spread[0]:
        raise MeshImportError(
            f"{name}: a flat sheet ({spread[2] / spread[0]:.2%} as thick as it is long), "
            "no lumen to drive a capsule in")


def _unit_guess(extent: float):
    """(unit, scale) that brings `extent` into a colon's range, or None."""
    for unit, scale in (("millimetres", 1e-3), ("centimetres", 1e-2), ("inches", 0.0254),
                        ("micrometres", 1e-6)):
        if MIN_EXTENT <= extent * scale <= MAX_EXTENT:
            return unit, scale
    return None


def repair_colon_mesh(mesh: trimesh.Trimesh, max_hole_edges: int = 64,
                      max_hole_perimeter: float = MAX_HOLE_PERIMETER,
                      max_faces: int | None = None, progress=None):
    """Repairs a copy of `mesh`: duplicate and degenerate faces removed, winding made
    consistent, holes of up to `max_hole_edges` boundary edges and `max_hole_perimeter`
    (m) around filled (a tube's open ends, 6 cm and more around, stay open), and longer
    loops that lie in the wall (`_in_the_wall`: a segmentation's ragged holes), normals
    turned toward the lumen (the wall is seen and touched from inside), and decimated to
    `max_faces` triangles if it has more.

    The checks run on the geometry alone (vertices merged by position: a texture's seams
    split vertices, which would look like open edges). A texture, if the mesh has one, is
    kept: every surviving face keeps its texture coordinates; a filled hole's faces take
    those of a vertex at the same place; after decimation each new vertex takes those of
    the nearest original vertex. `progress(text)`, if given, hears each step. Returns
    (mesh, RepairReport)."""
    say = progress or (lambda text: None)
    report = RepairReport()
    texture = _texture_of(mesh)
    vertices = np.asarray(mesh.vertices, dtype=float)
    source_faces = np.asarray(mesh.faces, dtype=np.int64)
    geometry, representative, merged = merge_by_position(vertices, source_faces)
    keep = np.zeros(len(source_faces), dtype=bool)
    keep[geometry.unique_faces()] = True
    report.removed_duplicate_faces = len(source_faces) - int(keep.sum())
    nondegenerate = geometry.nondegenerate_faces()
    report.removed_degenerate_faces = int(np.sum(keep & ~nondegenerate))
    keep &= nondegenerate
    kept = np.flatnonzero(keep)
    geometry.update_faces(keep)
    say("repairing: winding, holes")
    if not geometry.is_winding_consistent:
        trimesh.repair.fix_winding(geometry)
        report.fixed_winding = True
    loops, stray = _closed_loops(geometry)
    report.stray_boundary_edges = stray
    small, ends = [], []
    for loop in loops:
        hole = (len(loop) <= max_hole_edges
                and _perimeter(geometry.vertices, loop) <= max_hole_perimeter) \
            or _in_the_wall(geometry.vertices, loop)
        (small if hole else ends).append(loop)
    if small:
        geometry = trimesh.Trimesh(geometry.vertices,
                                   np.concatenate([geometry.faces, _fans(geometry, small)]),
                                   process=False)
        report.filled_holes = len(small)
    report.open_ends = len(ends)
    report.open_end_perimeters = tuple(_perimeter(geometry.vertices, loop) for loop in ends)
    _, uses = np.unique(geometry.edges_sorted, axis=0, return_counts=True)
    report.non_manifold_edges = int(np.sum(uses > 2))
    say("repairing: normals")
    faces = np.asarray(geometry.faces)
    if _normals_point_outward(geometry):
        faces = faces[:, ::-1]
        report.flipped_normals = True
    if texture is None:
        out = trimesh.Trimesh(geometry.vertices, faces, process=False)
    else:
        # Each kept face in its original (textured) vertices, reversed where the geometry's
        # face now runs the other way round; added faces through a representative vertex.
        textured = source_faces[kept]
        reversed_ = ~_same_cyclic_order(merged[textured], faces[:len(kept)])
        textured[reversed_] = textured[reversed_][:, ::-1]
        added = representative[faces[len(kept):]]
        out = _textured(vertices, np.concatenate([textured, added]), *texture)
    out.remove_unreferenced_vertices()
    if max_faces is not None and len(out.faces) > max_faces:
        report.decimated_from = len(out.faces)
        say(f"repairing: decimating {len(out.faces):,} to {max_faces:,} faces")
        out = _decimate(out, max_faces, texture)
        report.decimated_to = len(out.faces)
    return out, report


def open_end_loops(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    """The repaired wall's open ends: its closed boundary loops longer than a hole the
    repair fills (a decimation can leave small loops and stray open edges of its own)."""
    loops, _ = _closed_loops(mesh)
    return [loop for loop in loops if _perimeter(mesh.vertices, loop) > MAX_HOLE_PERIMETER]


def _closed_loops(mesh: trimesh.Trimesh) -> tuple[list[np.ndarray], int]:
    """The boundary's closed loops (vertex indices, 3 edges or more; the boundary: edges
    used by one face), and the count of its open edges in none (chains broken at a vertex
    where the boundary meets itself)."""
    unique, counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
    graph = {}
    for a, b in unique[counts == 1]:
        graph.setdefault(a, []).append(b)
        graph.setdefault(b, []).append(a)
    loops, stray, seen = [], 0, set()
    for start in graph:
        if start in seen:
            continue
        loop, previous, current = [start], None, start
        seen.add(start)
        while True:
            following = [v for v in graph[current] if v != previous and v not in seen]
            if not following:
                break
            previous, current = current, following[0]
            seen.add(current)
            loop.append(current)
        if len(loop) >= 3 and start in graph[current]:
            loops.append(np.array(loop))
        else:
            stray += max(len(loop) - 1, 1)
    return loops, stray


def _in_the_wall(vertices, loop, depth: float = HOLE_DEPTH, sectors: int = 8) -> bool:
    """Whether a boundary loop is a hole in the wall rather than an open end or the edge
    of a sheet: the surface within 1.5 R of the loop's centre stays within `depth` R of
    the loop's plane (90th percentile; R = perimeter / 2 pi), and goes on beyond the loop
    all round it (in each of `sectors` directions in that plane there is surface between
    1.1 R and 1.5 R from the centre). An open end's wall runs along the lumen, away from
    the plane across it; a sheet's edge has no surface beyond it."""
    vertices = np.asarray(vertices)
    ring = vertices[loop]
    centre = ring.mean(axis=0)
    _, _, axes = np.linalg.svd(ring - centre)
    R = _perimeter(vertices, loop) / (2.0 * np.pi)
    offsets = vertices - centre
    near = offsets[np.einsum("ij,ij->i", offsets, offsets) <= (1.5 * R) ** 2]
    if np.percentile(np.abs(near @ axes[2]), 90) >= depth * R:
        return False
    u, v = near @ axes[0], near @ axes[1]
    beyond = np.hypot(u, v) >= 1.1 * R
    around = np.floor((np.arctan2(v[beyond], u[beyond]) + np.pi) / (2.0 * np.pi) * sectors)
    return len(np.unique(np.clip(around, 0, sectors - 1))) == sectors


def _perimeter(vertices, loop) -> float:
    ring = np.asarray(vertices)[loop]
    return float(np.sum(np.linalg.norm(ring - np.roll(ring, 1, axis=0), axis=1)))


def _fans(mesh: trimesh.Trimesh, loops: list[np.ndarray]) -> np.ndarray:
    """Faces closing each boundary loop: a fan from its first vertex, wound like the faces
    around it (each boundary edge runs the other way in the new face)."""
    directed = {tuple(edge) for edge in np.asarray(mesh.faces)[:, [0, 1, 1, 2, 2, 0]]
                .reshape(-1, 2)}
    out = []
    for loop in loops:
        fan = np.column_stack([np.full(len(loop) - 2, loop[0]), loop[1:-1], loop[2:]])
        if (int(loop[0]), int(loop[1])) in directed:
            fan = fan[:, ::-1]
        out.append(fan)
    return np.concatenate(out)


def merge_by_position(vertices: np.ndarray, faces: np.ndarray, decimals: int = 9):
    """The mesh with vertices at the same place merged: (geometry Trimesh, representative
    (M,) an original vertex of each merged one, merged (V,) the merged index of each
    original vertex). Faces keep their order."""
    _, first, inverse = np.unique(np.round(vertices, decimals), axis=0,
                                  return_index=True, return_inverse=True)
    # Merged vertices in the order of their first appearance: a mesh without duplicates
    # keeps its vertex order.
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    representative = first[order]
    merged = rank[inverse.reshape(-1)]
    geometry = trimesh.Trimesh(vertices[representative], merged[faces], process=False)
    return geometry, representative, merged


def geometry_of(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh's geometry alone, vertices merged by position (texture seams closed)."""
    geometry, _, _ = merge_by_position(np.asarray(mesh.vertices, dtype=float),
                                       np.asarray(mesh.faces, dtype=np.int64))
    geometry.remove_unreferenced_vertices()
    return geometry


def _same_cyclic_order(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per row, whether face b is face a or a rotation of it (not reversed)."""
    return np.any([np.all(np.roll(a, k, axis=1) == b, axis=1) for k in range(3)], axis=0)


def _texture_of(mesh: trimesh.Trimesh):
    """(uv (V, 2), material) if the mesh has per-vertex texture coordinates, else None."""
    visual = getattr(mesh, "visual", None)
    uv = getattr(visual, "uv", None)
    if visual is None or getattr(visual, "kind", None) != "texture" or uv is None \
            or len(uv) != len(mesh.vertices):
        return None
    return np.asarray(uv, dtype=float), visual.material


def _textured(vertices, faces, uv, material) -> trimesh.Trimesh:
    return trimesh.Trimesh(vertices, faces, process=False,
                           visual=trimesh.visual.TextureVisuals(uv=uv, material=material))


def _decimate(mesh: trimesh.Trimesh, max_faces: int, texture) -> trimesh.Trimesh:
    """Quadric decimation to at most `max_faces` (fast_simplification through trimesh), the
    texture coordinates carried over from the nearest original vertex."""
    from scipy.spatial import cKDTree

    geometry = geometry_of(mesh)
    small = geometry.simplify_quadric_decimation(face_count=max_faces)
    small = trimesh.Trimesh(small.vertices, small.faces, process=False)
    if texture is None:
        return small
    _, nearest = cKDTree(np.asarray(mesh.vertices)).query(np.asarray(small.vertices))
    return _textured(np.asarray(small.vertices), np.asarray(small.faces),
                     np.asarray(mesh.visual.uv)[nearest], texture[1])


def _normals_point_outward(mesh: trimesh.Trimesh) -> bool:
    """Whether the face normals point away from the lumen.

    A closed wall with thickness (a solid ring: watertight, Euler number 0) faces the lumen
    where its normals leave the tissue: it is inside out if its volume is negative. Any
    other tube faces the lumen where its normals point toward its axis; that is judged
    against the nearest point of the mesh's principal axis, area-weighted, per stretch
    along it (a curved colon is near-straight over short stretches)."""
    if mesh.is_watertight and mesh.euler_number == 0:
        return bool(mesh.volume < 0.0)
    centres = mesh.triangles_center
    normals = mesh.face_normals
    areas = mesh.area_faces
    # Local axis points: the area-weighted mean of up to 32 consecutive stretches of faces,
    # ordered along the mesh's course.
    order = _order_along(centres)
    votes = 0.0
    for chunk in np.array_split(order, max(1, min(32, len(order) // 50))):
        axis_point = np.average(centres[chunk], axis=0, weights=areas[chunk])
        outward = centres[chunk] - axis_point
        votes += float(np.sum(areas[chunk] * np.einsum("ij,ij->i", outward, normals[chunk])))
    return votes > 0.0


def _order_along(points: np.ndarray) -> np.ndarray:
    """Indices of `points` ordered along the mesh's course: by the geodesic-like distance
    from one end, approximated by walking a k-nearest-neighbour graph from the point farthest
    from the centroid."""
    from scipy.sparse.csgraph import dijkstra
    from scipy.spatial import cKDTree

    tree = cKDTree(points)
    k = min(8, len(points))
    distances, neighbours = tree.query(points, k=k)
    from scipy.sparse import coo_matrix

    rows = np.repeat(np.arange(len(points)), k)
    graph = coo_matrix((distances.reshape(-1) + 1e-12, (rows, neighbours.reshape(-1))),
                       shape=(len(points), len(points))).tocsr()
    start = int(np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1)))
    along = dijkstra(graph, directed=False, indices=start)
    along[~np.isfinite(along)] = np.nanmax(along[np.isfinite(along)]) if np.isfinite(along).any() else 0.0
    return np.argsort(along)
