"""Does the capsule fit where a scenario starts it? One line saying why not.

`start_pose` (capsule/model.py) puts the capsule's centre on the centreline at arc length
`capsule.start_s`, its axis along the tangent there. `check_start` refuses a start where
- the capsule would stick out of an end of the colon: its tips must lie within the
  centreline's [0, L], and a capsule radius inside an open end (a cut tube, an imported
  segment: there is no wall beyond it, the ragged cut of a scan least of all);
- the capsule would start inside the wall: points on its surface (its cylinder and domes,
  every 1 mm along and 24 around) lie more than `WALL_TOLERANCE` beyond the lumen's wall
  (`TubeColon.excursion`: the procedural colon's analytic wall, an imported colon's
  tabulated one), e.g. in a lumen narrower than the capsule, or in a tight bend (the
  capsule is straight).
An end is open if a ray along the line outward, from a lumen radius inside its end, meets
no wall within two lumen radii past the end (the procedural colon's ends are closed caps).
"""

import numpy as np

from .centerline_extraction import MeshSections

WALL_TOLERANCE = 0.0005
"""How far [m] the capsule's surface may start beyond the wall (its contact is compliant,
and a tabulated wall is a polygon's approximation)."""


def _open_ends(colon) -> tuple[bool, bool]:
    """Whether each end of the centreline (s = 0, s = L) is open."""
    geometry = getattr(colon, "geometry", None)
    if geometry is None:  # the procedural colon: closed at both ends
        return False, False
    sections = MeshSections(geometry)
    cl = colon.centerline
    out = []
    for s, sign in ((0.0, -1.0), (cl.length, 1.0)):
        # From a lumen radius inside (a closed end's line ends on its cap), outward.
        radius = float(np.max(colon.wall_radius(s, np.linspace(0, 2 * np.pi, 16))))
        inside = float(np.clip(s - sign * radius, 0.0, cl.length))
        start = cl.point_at(inside)
        hit = sections.ray(start, sign * cl.tangent_at(s), reach=abs(s - inside) + 2.0 * radius)
        out.append(not np.isfinite(hit))
    return out[0], out[1]


def _surface_points(centre, axis, radius, length, step=0.001, around=24):
    """Points on a capsule's surface: its overall `length` (tip to tip) along `axis`."""
    half = 0.5 * length
    cylinder = max(0.0, half - radius)
    x = np.linspace(-half, half, max(3, int(np.ceil(length / step)) + 1))
    rho = np.where(np.abs(x) <= cylinder, radius,
                   np.sqrt(np.maximum(radius ** 2 - (np.abs(x) - cylinder) ** 2, 0.0)))
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    theta = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
    ring = np.cos(theta)[:, None] * u + np.sin(theta)[:, None] * v
    points = centre + x[:, None, None] * axis + rho[:, None, None] * ring[None, :, :]
    return points.reshape(-1, 3), np.repeat(x, around)


def check_start(colon, start_s: float, capsule_radius: float, capsule_length: float) -> None:
    """Raises ValueError (one line) if a capsule of `capsule_radius` and overall
    `capsule_length` (tip to tip, m), started on the centreline at `start_s` (m) along the
    tangent, would stick out of the colon's ends or start inside its wall. `colon`: a
    `TubeColon` (procedural or imported)."""
    cl = colon.centerline
    half = 0.5 * capsule_length
    length = cl.length
    open_start, open_end = _open_ends(colon)
    low = half + (capsule_radius if open_start else 0.0)
    high = length - half - (capsule_radius if open_end else 0.0)
    if start_s < low:
        kind = "open end" if open_start else "closed end"
        raise ValueError(f"capsule.start_s {start_s:g} m: the capsule would stick out of the "
                         f"colon's {kind} at s = 0 (needs >= {low:.3f} m)")
    if start_s > high:
        kind = "open end" if open_end else "closed end"
        raise ValueError(f"capsule.start_s {start_s:g} m: the capsule would stick out of the "
                         f"colon's {kind} at s = {length:.3f} m (needs <= {high:.3f} m)")
    centre = cl.point_at(start_s)
    axis = cl.tangent_at(start_s)
    points, x = _surface_points(centre, axis, capsule_radius, capsule_length)
    excursion = colon.excursion(points)
    worst = int(np.argmax(excursion))
    if excursion[worst] > WALL_TOLERANCE:
        s_worst = cl.closest(points[worst])[0]
        around = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
        narrowest = float(np.min(colon.wall_radius(np.full(64, s_worst), around)))
        raise ValueError(
            f"capsule.start_s {start_s:g} m: the capsule would start "
            f"{1000 * excursion[worst]:.1f} mm inside the wall (at s = {s_worst:.3f} m the "
            f"lumen is {1000 * narrowest:.1f} mm in radius at its narrowest, the capsule "
            f"{1000 * capsule_radius:.1f} mm)")
