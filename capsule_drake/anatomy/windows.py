"""The camera's wall cut into overlapping windows along the colon, one renderer each.

A software (llvmpipe) render costs in proportion to every triangle its renderer holds, seen
or not: RenderEngineVtk culls nothing, however the wall is split into objects (measured).
A capsule camera sees only a short stretch of lumen, so the wall is cut into windows along
the arc length, each registered with a renderer of its own, and the camera renders with the
window of the stretch it is in.

What a window must hold. A camera at arc length s_p (the foot of the centreline point
nearest to it) sees tissue at range at most `far`, along a straight sight line inside the
lumen. In tube coordinates (s, rho, phi) about a centreline of curvature kappa, moving
along any path changes s by at most |dx| / (1 - kappa rho), and rho <= r_max(s), the largest
wall radius at s. So with G(s) = integral of (1 - kappa r_max) ds, a sight line of length
`far` from s_p stays within G(s) in [G(s_p) - far, G(s_p) + far]. The window centred at
s_k serves cameras with |s_p - s_k| <= spacing / 2 and holds every face whose arc-length
span meets the union of those reaches and that has a vertex within
far + longest edge + r_max + spacing / 2 of the centreline point at s_k (the camera lies
within r_max of its foot, and the foot within spacing / 2 of s_k). Beyond `far` the camera
reports no depth, and the on-board light leaves under 4 % of its intensity there.
The bound needs kappa r_max < 1 (tube coordinates are unique), which the course's smoothing
keeps (kappa r_max <= 0.82 over seeds 0-5).
"""

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .cache import write_atomic
from .mesh import TexturedMesh, write_textured_obj

VISUAL_MTL = ("colon_visual.mtl", "mucosa")


@dataclass
class CameraWindows:
    """Overlapping stretches of the camera wall and where they serve.

    Attributes:
        centres: (K,) arc lengths [m] of the window centres, evenly spaced from 0 to L.
        objs: the K textured OBJ files (sharing the visual mesh's material and texture).
        triangles: (K,) triangles in each window.
        far: the sight range [m] the windows were cut for.
    """

    centres: np.ndarray
    objs: list[Path]
    triangles: np.ndarray
    far: float

    @property
    def spacing(self) -> float:
        return float(self.centres[1] - self.centres[0]) if len(self.centres) > 1 else np.inf

    def index_at(self, s: float) -> int:
        """The window serving a camera whose centreline foot is at arc length s [m]."""
        if len(self.centres) == 1:
            return 0
        return int(np.clip(np.rint(s / self.spacing), 0, len(self.centres) - 1))


def sight_reach(colon, s, far: float, step: float = 0.001):
    """Arc lengths (lo, hi) [m] between which a straight sight line of length `far` [m]
    inside the lumen, starting at arc length(s) s, must stay (module docstring)."""
    length = colon.centerline.length
    grid = np.linspace(0.0, length, int(np.ceil(length / step)) + 1)
    shrink = 1.0 - colon.centerline.curvature_at(grid) * colon.max_wall_radius(grid)
    if np.any(shrink <= 0.0):
        raise ValueError("colon bends tighter than its radius (kappa r >= 1): tube "
                         "coordinates are ambiguous, camera windows cannot be bounded")
    g = np.concatenate([[0.0], np.cumsum(0.5 * (shrink[1:] + shrink[:-1]) * np.diff(grid))])
    g_s = np.interp(s, grid, g)
    lo = np.interp(g_s - far, g, grid, left=0.0)
    hi = np.interp(g_s + far, g, grid, right=length)
    return lo, hi


def window_faces(colon, mesh: TexturedMesh, centres: np.ndarray, far: float) -> list:
    """Boolean face masks (F,) of the windows centred at `centres` (evenly spaced)."""
    half = 0.5 * (centres[1] - centres[0]) if len(centres) > 1 else np.inf
    length = colon.centerline.length
    tri_s = mesh.s[mesh.faces]
    s_min, s_max = tri_s.min(axis=1), tri_s.max(axis=1)
    corners = mesh.vertices[mesh.faces]
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)
    r_max = float(np.max(colon.max_wall_radius(np.linspace(0.0, length, 2000))))
    masks = []
    for centre in centres:
        if not np.isfinite(half):
            masks.append(np.ones(len(mesh.faces), dtype=bool))
            continue
        served = np.linspace(max(0.0, centre - half), min(length, centre + half), 9)
        lo, hi = sight_reach(colon, served, far)
        in_arc = (s_max >= lo.min()) & (s_min <= hi.max())
        radius = far + float(edges.max()) + r_max + half
        distance = np.linalg.norm(mesh.vertices - colon.centerline.point_at(centre), axis=1)
        near = np.any(distance[mesh.faces] <= radius, axis=1)
        masks.append(in_arc & near)
    return masks


def window_key(far: float, spacing: float) -> str:
    """Short tag of a window set in file names."""
    return hashlib.sha256(f"{far:.6f} {spacing:.6f}".encode()).hexdigest()[:8]


def camera_windows(colon, directory: Path, far: float, spacing: float) -> CameraWindows:
    """The camera wall of `colon` cut into windows `spacing` [m] apart (0 or inf: one window,
    the whole wall), written as OBJs into `directory` (the colon's asset folder, which holds
    the visual material and texture) unless already there. Each file is written to a
    temporary name and renamed, so concurrent processes never read half a file."""
    length = colon.centerline.length
    if spacing > 0.0 and np.isfinite(spacing):
        count = max(2, int(np.ceil(length / spacing)) + 1)
        centres = np.linspace(0.0, length, count)
    else:
        centres = np.array([0.5 * length])
    key = window_key(far, spacing if len(centres) > 1 else 0.0)
    objs = [Path(directory) / f"camera_{key}_{k:02d}.obj" for k in range(len(centres))]
    counts_file = Path(directory) / f"camera_{key}.npy"
    if all(path.exists() for path in objs) and counts_file.exists():
        return CameraWindows(centres, objs, np.load(counts_file), far)
    mesh = colon.camera_mesh()
    masks = window_faces(colon, mesh, centres, far)
    for path, mask in zip(objs, masks):
        write_atomic(path, lambda tmp, m=mask: write_textured_obj(tmp, mesh.subset(m),
                                                                     VISUAL_MTL))
    triangles = np.array([int(mask.sum()) for mask in masks])
    write_atomic(counts_file, lambda tmp: np.save(tmp, triangles))
    return CameraWindows(centres, objs, triangles, far)

