"""Residual fluid pooled in the dependent parts of the lumen.

After a bowel preparation some fluid stays in the colon: 155 +- 114 ml after magnesium
citrate and 143 +- 100 ml after sodium phosphate, under 200 ml in 77-82 % of examinations
(automated volumetry of 500 CT colonographies, Pickhardt et al., docs/sources.md section
3.3, V). It lies in the lowest parts of the lumen with a level surface: in a supine patient
the posterior segments and the pelvic loops.

`fluid_pools(colon, volume)` finds the basins of the lumen (the local minima of its lowest
wall point along the centreline), shares the volume among them in proportion to what each
holds up to its rim (an assumption, U) and solves each one's level so that the lumen below
it holds its share: the volume is the integral along the centreline of the area of each
wall ring below the level. `surface_mesh(colon, pool)` is the liquid's surface, the chords
where the level cuts the rings, as the camera sees it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.signal import find_peaks

from .mesh import tube_rings

FLUID_DENSITY = 1000.0
"""Density of the residual fluid (kg/m^3): water-like lavage fluid (U)."""
STATION_STEP = 0.002
"""Spacing of the wall rings the pools are measured on (m)."""
RING_POINTS = 64
"""Points around each ring (the ring's polygon approximates the wall)."""
MIN_PROMINENCE = 0.004
"""A basin is a low point of the lumen at least this much below both of its rims (m):
shallower dips (between folds) hold a film, not a pool."""


@dataclass
class FluidPool:
    """One pool: its stretch of centreline, its level and the volume below it."""

    s_min: float      # m, where the level meets the lumen's floor toward the anus
    s_max: float      # m, ... toward the cecum
    level: float      # m, world z of the liquid's surface
    volume: float     # m^3


def _rings(colon, step: float = STATION_STEP):
    """(s, rings (R, M, 3)) of the wall every `step` along the whole centreline."""
    length = colon.centerline.length
    s = np.linspace(0.0, length, int(np.ceil(length / step)) + 1)
    s, _, rings = tube_rings(colon, s, RING_POINTS)
    return s, rings


def _area_below(ring: np.ndarray, centre: np.ndarray, level: float,
                with_centroid: bool = False):
    """Area (m^2) of the part of a ring's polygon below the world height `level`, in the
    ring's plane (the polygon clipped by the level and its area by the shoelace formula);
    with its centroid (relative to `centre`) if `with_centroid`."""
    z = ring[:, 2]
    if z.max() <= level:
        inside = ring
    elif z.min() >= level:
        return (0.0, np.zeros(3)) if with_centroid else 0.0
    else:
        inside = _clip_below(ring, level)
    # Shoelace in 3D: half the norm of the sum of cross products about the centre; the
    # centroid from the triangles fanned from it.
    rel = inside - centre
    cross = np.cross(rel, np.roll(rel, -1, axis=0))
    total = cross.sum(axis=0)
    area = 0.5 * float(np.linalg.norm(total))
    if not with_centroid:
        return area
    unit = total / max(np.linalg.norm(total), 1e-30)
    weights = 0.5 * cross @ unit
    centroid = ((rel + np.roll(rel, -1, axis=0)) / 3.0 * weights[:, None]).sum(axis=0) \
        / max(weights.sum(), 1e-30)
    return area, centroid


def _clip_below(ring: np.ndarray, level: float) -> np.ndarray:
    """The polygon `ring` cut by the plane z = level, the part below (Sutherland-Hodgman
    against one plane)."""
    out = []
    n = len(ring)
    for k in range(n):
        a, b = ring[k], ring[(k + 1) % n]
        a_in, b_in = a[2] <= level, b[2] <= level
        if a_in:
            out.append(a)
        if a_in != b_in:
            t = (level - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out)


def _volume(s, rings, centres, lo: int, hi: int, level: float) -> float:
    """Volume (m^3) of the lumen below `level` from ring lo to ring hi (inclusive): each
    ring's area below the level swept along the centreline, by Pappus's theorem for a bent
    tube: dV = A (1 - k . c) ds, with k the centreline's curvature vector and c the area's
    centroid from the centreline (liquid on the outside of a bend fills more)."""
    if hi <= lo:
        return 0.0
    span = slice(max(lo - 1, 0), min(hi + 2, len(s)))
    tangent = np.gradient(centres[span], s[span], axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    bend = np.gradient(tangent, s[span], axis=0)[lo - span.start:hi - span.start + 1]
    values = []
    for k, curvature in zip(range(lo, hi + 1), bend):
        area, centroid = _area_below(rings[k], centres[k], level, with_centroid=True)
        values.append(area * (1.0 - curvature @ centroid))
    return float(np.trapezoid(values, s[lo:hi + 1]))


def _extent(floor: np.ndarray, bottom: int, level: float) -> tuple[int, int]:
    """The rings around `bottom` whose floor lies below `level` (contiguous)."""
    lo = bottom
    while lo > 0 and floor[lo - 1] < level:
        lo -= 1
    hi = bottom
    while hi < len(floor) - 1 and floor[hi + 1] < level:
        hi += 1
    return lo, hi


def basins(colon, step: float = STATION_STEP):
    """The lumen's basins: [(ring index of its lowest point, the height of its lower rim)],
    deepest first, with (s, rings, centres, floor) they were found on. Basins are found on
    the floor of the lumen without its folds (the centreline's height less the nominal
    radius): the dips between folds are part of the basin they lie in; one that lies within
    a deeper basin's pool at that basin's rim is part of it."""
    s, rings = _rings(colon, step)
    centres = colon.centerline.point_at(s)
    floor = rings[:, :, 2].min(axis=1)
    smooth = centres[:, 2] - colon.centerline.radius_at(s)
    peaks, props = find_peaks(-smooth, prominence=MIN_PROMINENCE)
    # The rim: where fluid would spill over, the lower of the two heights between this
    # basin and deeper ground on either side (find_peaks' prominence bases).
    rims = [min(smooth[left:bottom + 1].max(), smooth[bottom:right + 1].max())
            for bottom, left, right in zip(peaks, props["left_bases"], props["right_bases"])]
    found, taken = [], []
    for bottom, rim in sorted(zip(peaks.tolist(), rims), key=lambda item: smooth[item[0]]):
        bottom = int(np.argmin(np.where(np.abs(np.arange(len(s)) - bottom) * step < 0.03,
                                        floor, np.inf)))   # the folds' own lowest point
        if any(lo <= bottom <= hi for lo, hi in taken):
            continue
        taken.append(_extent(floor, bottom, rim))
        found.append((bottom, float(rim)))
    return found, (s, rings, centres, floor)


def fluid_pools(colon, volume: float, step: float = STATION_STEP) -> list[FluidPool]:
    """The pools that `volume` (m^3) of fluid forms in `colon`: shared among the basins in
    proportion to what each holds up to its rim, each level solved by bisection to 1e-7 of
    its share. A basin cannot hold more than its rim allows: a volume larger than all the
    basins hold fills each to its rim (the rest is not placed)."""
    if volume <= 0.0:
        return []
    found, (s, rings, centres, floor) = basins(colon, step)
    capacity = []
    for bottom, rim in found:
        lo, hi = _extent(floor, bottom, rim)
        capacity.append(_volume(s, rings, centres, lo, hi, rim))
    total = sum(capacity)
    pools = []
    for (bottom, rim), held in zip(found, capacity):
        if held <= 0.0:
            continue
        share = min(held, volume * held / total)
        low, high = floor[bottom], rim
        for _ in range(60):
            mid = 0.5 * (low + high)
            lo, hi = _extent(floor, bottom, mid)
            if _volume(s, rings, centres, lo, hi, mid) < share:
                low = mid
            else:
                high = mid
            if high - low < 1e-7:
                break
        level = 0.5 * (low + high)
        lo, hi = _extent(floor, bottom, level)
        pools.append(FluidPool(float(s[max(lo - 1, 0)]), float(s[min(hi + 1, len(s) - 1)]),
                               float(level), _volume(s, rings, centres, lo, hi, level)))
    return sorted(pools, key=lambda pool: pool.s_min)


def surface_mesh(colon, pool: FluidPool, across: int = 1,
                 step: float = STATION_STEP) -> trimesh.Trimesh | None:
    """The liquid's surface of `pool`: at each ring the level cuts, the chord between the
    two points where it crosses the wall, split into `across` pieces, the chords joined
    into a strip (normals up). None when the level cuts no ring twice. The surface is flat:
    one piece across is enough (a camera renders in proportion to the triangles), its
    outline follows the wall ring by ring."""
    n = max(int(np.ceil((pool.s_max - pool.s_min) / step)), 1) + 1
    s, _, rings = tube_rings(colon, np.linspace(pool.s_min, pool.s_max, n), RING_POINTS)
    chords = []
    for ring in rings:
        z = ring[:, 2] - pool.level
        up = np.flatnonzero((z[:-1] <= 0.0) != (np.roll(z, -1)[:-1] <= 0.0))
        last = (z[-1] <= 0.0) != (z[0] <= 0.0)
        crossings = []
        for k in list(up) + ([len(z) - 1] if last else []):
            a, b = ring[k], ring[(k + 1) % len(ring)]
            t = (pool.level - a[2]) / (b[2] - a[2])
            crossings.append((k, a + t * (b - a), z[k] <= 0.0))
        if len(crossings) != 2:
            chords.append(None)
            continue
        # Order the ends the same way at every ring: first where the wall leaves the liquid.
        (_, p, a_below), (_, q, _) = crossings
        start, end = (p, q) if a_below else (q, p)
        chords.append(start[None, :] + np.linspace(0.0, 1.0, across + 1)[:, None]
                      * (end - start)[None, :])
    vertices, faces = [], []
    for k in range(len(chords) - 1):
        a, b = chords[k], chords[k + 1]
        if a is None or b is None:
            continue
        base = sum(len(v) for v in vertices)
        vertices += [a, b]
        i = base + np.arange(across)
        j = i + across + 1
        faces += [np.stack([i, j, i + 1], axis=1), np.stack([i + 1, j, j + 1], axis=1)]
    if not faces:
        return None
    vertices, faces = np.concatenate(vertices), np.concatenate(faces)
    normal = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                      vertices[faces[:, 2]] - vertices[faces[:, 0]])
    if normal[:, 2].sum() < 0.0:   # seen from above: normals up
        faces = faces[:, ::-1]
    return trimesh.Trimesh(vertices, faces, process=False)
