"""Is an imported mesh a tube? The geometric checks that refuse, in one line each, what the
centreline cannot follow.

A colon (or a length of one) is one tube: a wall around a lumen, open or closed at each of
its two ends, much longer than it is wide, without branches. Checked in the import
(anatomy/imported.py), after the mesh is repaired:

1. Open ends (`check_open_ends`): the boundary loops left after small holes are filled
   (anatomy/importer.py fills those up to 3 cm around) are a tube's open ends: at most
   two. Three or more is a branching mesh (a Y has three ends) or a wall with a large tear.
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
from scipy.spatial import cKDTree

from .importer import MeshImportError

MIN_CLOSED_SHARE = 0.8
MIN_LENGTH_RADII = 7.0
BRANCH_RADII = 2.0
MAX_OFF_AREA = 0.02


class NotATubeError(MeshImportError):
    """The mesh is not one tube; the message is one line saying why."""


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
    far = distance > BRANCH_RADII * widest[nearest] + 0.005
    share = float(areas[far].sum() / areas.sum()) if areas.sum() > 0 else 0.0
    if share > MAX_OFF_AREA:
        worst = float(distance[far].max())
        raise NotATubeError(
            f"not a tube: {share:.0%} of the wall lies more than {BRANCH_RADII:g} lumen radii "
            f"from the centreline (up to {100 * worst:.1f} cm): a branch the line does not "
            "run through (a branching mesh?)")
