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
from pathlib import Path

import numpy as np
import trimesh

FORMATS = (".obj", ".stl", ".ply", ".glb", ".gltf")

# A colon or a segment of one, in metres: its largest extent between these.
MIN_EXTENT = 0.01
MAX_EXTENT = 3.0
# A lumen needs depth: the smallest principal extent at least this share of the largest.
MIN_THICKNESS_RATIO = 0.02


class MeshImportError(ValueError):
    """A mesh that cannot become a colon; the message is one line naming file and problem."""


@dataclasses.dataclass
class RepairReport:
    """What `repair_colon_mesh` changed."""

    removed_duplicate_faces: int = 0
    removed_degenerate_faces: int = 0
    fixed_winding: bool = False
    filled_holes: int = 0
    flipped_normals: bool = False
    open_ends: int = 0  # boundary loops left open (a tube's two ends)

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
        out.append(f"{self.open_ends} open ends left open")
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
        loaded = trimesh.load(str(path))
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


def repair_colon_mesh(mesh: trimesh.Trimesh, max_hole_edges: int = 64):
    """Repairs a copy of `mesh`: duplicate and degenerate faces removed, winding made
    consistent, holes of up to `max_hole_edges` boundary edges filled (a tube's open ends
    are larger and stay open), normals turned toward the lumen (inward: the wall is seen and
    touched from inside). Returns (mesh, RepairReport)."""
    mesh = mesh.copy()
    report = RepairReport()
    faces = len(mesh.faces)
    mesh.update_faces(mesh.unique_faces())
    report.removed_duplicate_faces = faces - len(mesh.faces)
    faces = len(mesh.faces)
    mesh.update_faces(mesh.nondegenerate_faces())
    report.removed_degenerate_faces = faces - len(mesh.faces)
    mesh.remove_unreferenced_vertices()
    mesh.merge_vertices()
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
        report.fixed_winding = True
    loops = _boundary_loops(mesh)
    small = [loop for loop in loops if len(loop) <= max_hole_edges]
    if small:
        before = len(_boundary_loops(mesh))
        trimesh.repair.fill_holes(mesh)
        report.filled_holes = before - len(_boundary_loops(mesh))
    report.open_ends = len(_boundary_loops(mesh))
    if _normals_point_outward(mesh):
        # Reversed winding, as a new mesh (the same vertices, so a texture's coordinates
        # stay): in-place inversion after the checks above left stale cached normals.
        mesh = trimesh.Trimesh(mesh.vertices, np.asarray(mesh.faces)[:, ::-1],
                               visual=mesh.visual, process=False)
        report.flipped_normals = True
    return mesh, report


def _boundary_loops(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    """Vertex index loops of the mesh's boundary (edges used by one face)."""
    edges = mesh.edges_sorted
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = unique[counts == 1]
    if len(boundary) == 0:
        return []
    graph = {}
    for a, b in boundary:
        graph.setdefault(a, []).append(b)
        graph.setdefault(b, []).append(a)
    loops, seen = [], set()
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
        loops.append(np.array(loop))
    return loops


def _normals_point_outward(mesh: trimesh.Trimesh) -> bool:
    """Whether the face normals point away from the lumen: for a tube, away from its axis.
    Judged against the nearest point of the mesh's principal axis, area-weighted, per
    stretch along it (a curved colon is near-straight over short stretches)."""
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
