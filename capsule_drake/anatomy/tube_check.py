"""Is an imported mesh a tube? The geometric checks that refuse, in one line each, what the
centreline cannot follow.

A colon (or a length of one) is one tube: a wall around a lumen, open or closed at each of
its two ends, much longer than it is wide, without branches. Checked in the import
(anatomy/imported.py), after the mesh is repaired:

0. In pieces (`check_one_piece`, before the repairs, whose cost grows with the pieces):
   faces join through vertices at the same place (a texture's seams split vertices, not
   the wall). At least `MIN_WALL_SHARE` of the area lies in pieces that each hold
   `MIN_PIECE_SHARE` of it or more: a wall, or the inner and outer surfaces of a closed
   thick one, with stray fragments beside it (a segmentation's noise). A triangle soup
   (every triangle its own three vertices), or a wall shredded into strips, is refused.
1. Open ends (`check_open_ends`): the boundary loops left after small holes are filled
   (anatomy/importer.py fills those up to 3 cm around, and longer ones lying in the wall)
   are a tube's open ends: at most two. Three or more is a branching mesh (a Y has three ends) or a wall with a large tear.
2. Sections (`extract_centerline`, anatomy/centerline_extraction.py): the plane normal to
   the first centreline estimate (ring centroids of geodesic distance from one end) cuts a
   tube's wall in a closed loop around that line. If fewer than `MIN_CLOSED_SHARE` of
   those sections are (or fewer than 5 in all), the mesh is an open sheet, flat or wavy
   (nothing encloses a lumen; a flat sheet is refused before, by its thickness), or a
   branching mesh whose first line cuts across a junction (a Y with arms of about equal
   length).
3. Length (`check_tube`): the centreline at least `MIN_LENGTH_RADII` times the lumen's
   radius (the 90th percentile of the sections' equal-area radii along it: a tube's
   widest stretches, not its capped ends). A sphere measures ~2.3, an ellipsoid with
   semi-axes a > b = c about 2 a / b; a 20 cm colon segment 4 cm across, 10.
4. Branches (`check_tube`): every part of the wall is near the centreline: within
   `BRANCH_RADII` times the widest lumen radius within 2 cm along it (and 5 mm). A branch
   the centreline does not run through (a Y closed at its three ends, one arm shorter: the
   line follows the two longer ones) lies farther; more than `MAX_OFF_AREA` of the wall's
   area that far is a branching mesh. (A stub up to ~3 radii long, a pouch, passes.)
"""

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .importer import MeshImportError

MIN_PIECE_SHARE = 0.05
MIN_WALL_SHARE = 0.5
MIN_CLOSED_SHARE = 0.8
MIN_LENGTH_RADII = 7.0
BRANCH_RADII = 2.0
MAX_OFF_AREA = 0.02


class NotATubeError(MeshImportError):
    """The mesh is not one tube; the message is one line saying why."""


def check_one_piece(vertices, faces) -> None:
    """The wall is not in crumbs: at least MIN_WALL_SHARE of its area lies in pieces (faces
    sharing a vertex, vertices at the same place merged) of MIN_PIECE_SHARE of the area or
    more. `vertices` (V, 3), `faces` (F, 3): the mesh as read, before any repair."""
    vertices = np.round(np.asarray(vertices, dtype=float), 9)
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) < 2:
        return
    order = np.lexsort(vertices.T[::-1])
    ranked = vertices[order]
    first = np.r_[True, np.any(ranked[1:] != ranked[:-1], axis=1)]
    merged = np.empty(len(vertices), dtype=np.int64)
    merged[order] = np.cumsum(first) - 1
    f = merged[faces]
    count = int(first.sum())
    graph = coo_matrix((np.ones(2 * len(f), dtype=np.int8),
                        (np.r_[f[:, 0], f[:, 1]], np.r_[f[:, 1], f[:, 2]])),
                       shape=(count, count))
    pieces, label = connected_components(graph, directed=False)
    if pieces == 1:
        return
    corners = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                         corners[:, 2] - corners[:, 0]), axis=1)
    by_piece = np.bincount(label[f[:, 0]], weights=area, minlength=pieces)
    total = float(by_piece.sum())
    if total <= 0.0:
        return
    share = float(by_piece[by_piece >= MIN_PIECE_SHARE * total].sum()) / total
    if share < MIN_WALL_SHARE:
        soup = " (a triangle soup)" if pieces >= 0.5 * len(f) else ""
        raise NotATubeError(
            f"not a tube: its {len(f):,} triangles fall apart into {pieces:,} separate "
            f"pieces{soup}, {1.0 - share:.0%} of the area in pieces of less than "
            f"{MIN_PIECE_SHARE:.0%} of it each; a colon's wall is one connected surface: "
            "weld its vertices, or mesh the scan into one surface first")


def check_open_ends(loop_perimeters) -> None:
    """At most two open ends. `loop_perimeters`: the boundary loops' lengths [m]."""
    if len(loop_perimeters) > 2:
        around = ", ".join(f"{100 * p:.1f}" for p in sorted(loop_perimeters, reverse=True)[:5])
        raise NotATubeError(
            f"not a tube: {len(loop_perimeters)} open ends (boundary loops {around} cm "
            "around); a colon has at most two: a branching mesh, or a large tear in the wall?")


def check_tube(mesh: trimesh.Trimesh, s, points, radius) -> None:
    """Refuses a centreline that is too short for its width (a blob) or a wall that reaches
    far from it (a branch). `mesh`: the wall's geometry; (s, points, radius): its
    centreline as `extract_centerline` returns it."""
    s, points, radius = np.asarray(s), np.asarray(points), np.asarray(radius)
    length = float(s[-1]) if len(s) else 0.0
    wide = float(np.percentile(radius, 90)) if len(radius) else 0.0
    if wide <= 0.0 or length < MIN_LENGTH_RADII * wide:
        ratio = length / wide if wide > 0 else 0.0
        raise NotATubeError(
            f"not a tube: a closed blob, its centreline {100 * length:.1f} cm long only "
            f"{ratio:.1f} times the lumen's radius ({1000 * wide:.1f} mm); a tube is at "
            f"least {MIN_LENGTH_RADII:g} times as long")
    # Every face near the centreline: distance to a densified line against the widest
    # lumen radius within 2 cm along it.
    step = 0.001
    fine = np.arange(0.0, length + 0.5 * step, step)
    line = np.column_stack([np.interp(fine, s, points[:, k]) for k in range(3)])
    r = np.interp(fine, s, radius)
    window = max(1, int(round(0.02 / step)))
    padded = np.concatenate([np.full(window, r[0]), r, np.full(window, r[-1])])
    widest = np.max(np.lib.stride_tricks.sliding_window_view(padded, 2 * window + 1), axis=1)
    centres = np.asarray(mesh.triangles_center)
    areas = np.asarray(mesh.area_faces)
    distance, nearest = cKDTree(line).query(centres)
    # Beyond an end (an oblique cut's far rim reaches past the line's end along it by up to
    # the radius times the cut's slope, a flare widens it where the end's radius is held
    # from the sections behind it), the larger of the distances across and along the end's
    # axis: a branch beyond the end is far along it, a rim is not.
    if len(line) > 1:
        for end, inward in ((0, line[min(5, len(line) - 1)]), (len(line) - 1,
                                                               line[max(0, len(line) - 6)])):
            at = nearest == end
            axis = line[end] - inward
            if not at.any() or np.linalg.norm(axis) < 1e-9:
                continue
            axis /= np.linalg.norm(axis)
            offset = centres[at] - line[end]
            along = offset @ axis
            across = np.linalg.norm(offset - along[:, None] * axis, axis=1)
            distance[at] = np.maximum(across, np.abs(along))
    far = distance > BRANCH_RADII * widest[nearest] + 0.005
    share = float(areas[far].sum() / areas.sum()) if areas.sum() > 0 else 0.0
    if share > MAX_OFF_AREA:
        worst = float(distance[far].max())
        raise NotATubeError(
            f"not a tube: {share:.0%} of the wall lies more than {BRANCH_RADII:g} lumen radii "
            f"from the centreline (up to {100 * worst:.1f} cm): a branch the line does not "
            "run through (a branching mesh?)")
