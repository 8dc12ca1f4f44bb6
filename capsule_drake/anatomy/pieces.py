"""The colon wall as small convex pieces, for point contact.

Drake's point contact treats a `Mesh` as its convex hull, so a tube cannot be one collision
mesh; many small `Convex` pieces can. Each piece is the convex hull of a patch of the analytic
wall `wall_radius(s, theta)` (sampled every `sample_step`, so fold crests are caught) plus the
same points pushed `thickness` outward into the tissue. The lumen-facing side of a hull is then
the upper envelope of its patch: exact where the wall is convex seen from the lumen (fold
crests, the inner side of flexures) and a chord where it is concave:

- around the lumen, a column of angular width dtheta bridges the round wall by
  r (1 - cos(dtheta/2)): the number of columns follows the local radius so this stays below
  `max_chord_depth`;
- along the lumen, rings are `axial_length` long, halved where the fold-free tube curves enough
  (tight flexures, a radius flaring between segments) to be bridged by more than
  `max_chord_depth`; the two chords can add, so the worst bridge is ~2 x `max_chord_depth`;
- a fold's concave foot, and the flank where a crescent fold rises from a taenia, are bridged
  by a ramp (a few mm deep in the sharpest corners, under 1 mm at the 90th percentile of the
  lumen side): the capsule rests a little higher there, and a fold looks a little gentler.
  Resolving those corners would take pieces ~2 mm long, too many for Drake, whose build time
  and memory grow with the square of the geometry count (an N x N collision-filter table).

Columns are aligned with the three taeniae: their ridges lie on piece edges, and a column never
straddles two haustral sectors, whose folds are staggered. Patches extend `overlap` past their
edges along the wall, so neighbours overlap and nothing (the capsule least of all) slips between
them. Both ends are closed by a plate `thickness` thick.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

TWO_PI = 2.0 * np.pi


def _columns_around(radius: float, max_chord_depth: float, min_around: int) -> int:
    """Columns around a ring of `radius`: a multiple of 3 whose chords stay within depth."""
    half = np.arccos(np.clip(1.0 - max_chord_depth / radius, -1.0, 1.0))
    n = max(int(np.ceil(np.pi / half - 1e-9)), min_around)
    return 3 * int(np.ceil(n / 3))


def _axial_bridge(colon, s0: float, s1: float, sample_step: float) -> float:
    """How far [m] a straight piece from s0 to s1 would bridge the fold-free wall along the
    lumen (flexures, flaring radius), at the worst of 24 angles."""
    cl = colon.centerline
    s = np.linspace(s0, s1, max(int(np.ceil((s1 - s0) / sample_step)) + 1, 3))
    theta = np.linspace(0.0, TWO_PI, 24, endpoint=False)
    _, n, b = cl.frame_at(s)
    u = (np.cos(theta)[None, :, None] * n[:, None, :]
         + np.sin(theta)[None, :, None] * b[:, None, :])
    r = cl.radius_at(s)[:, None]
    w = r - colon.wall.taenia_depth(np.repeat(s, len(theta)), np.tile(theta, len(s)),
                                     np.repeat(r[:, 0], len(theta))).reshape(r.shape[0], -1)
    p = cl.point_at(s)[:, None, :] + w[..., None] * u
    f = ((s - s0) / (s1 - s0))[:, None, None]
    chord = (1.0 - f) * p[:1] + f * p[-1:]
    # Positive where the chord passes on the lumen side of the wall (against u).
    return float(np.max(np.sum((p - chord) * u, axis=-1)))


def _stations(colon, axial_length: float, max_chord_depth: float, sample_step: float,
              min_length: float) -> np.ndarray:
    """Ring stations from 0 to L: at most `axial_length` apart, halved where the fold-free wall
    curves along the lumen enough that a piece would bridge it by more than the chord
    budget (tight flexures, a radius flaring between segments)."""
    length = colon.centerline.length
    coarse = np.linspace(0.0, length, int(np.ceil(length / axial_length - 1e-9)) + 1)
    out = [0.0]
    stack = [(float(a), float(b)) for a, b in zip(coarse[:-1], coarse[1:])][::-1]
    while stack:
        a, b = stack.pop()
        if (b - a > 2.0 * min_length
                and _axial_bridge(colon, a, b, sample_step) > max_chord_depth):
            m = 0.5 * (a + b)
            stack.extend([(m, b), (a, m)])
        else:
            out.append(b)
    return np.asarray(out)


def _hull_vertices(points: np.ndarray) -> np.ndarray:
    """Vertices (3, K) of the convex hull of points (N, 3)."""
    hull = ConvexHull(points)
    return np.ascontiguousarray(points[hull.vertices].T)


def _patch(colon, s0, s1, t0, t1, sample_step, overlap, thickness):
    """Wall samples of the patch [s0, s1] x [t0, t1] widened by `overlap`, and the same
    points pushed outward; (2 N, 3)."""
    cl = colon.centerline
    s_lo, s_hi = max(s0 - overlap, 0.0), min(s1 + overlap, cl.length)
    n_s = int(np.ceil((s_hi - s_lo) / sample_step)) + 1
    s = np.linspace(s_lo, s_hi, n_s)
    r_max = float(np.max(cl.radius_at(s)))
    dt = overlap / r_max
    n_t = int(np.ceil(r_max * (t1 - t0 + 2 * dt) / sample_step)) + 1
    theta = np.linspace(t0 - dt, t1 + dt, n_t)
    _, n, b = cl.frame_at(s)
    u = (np.cos(theta)[None, :, None] * n[:, None, :]
         + np.sin(theta)[None, :, None] * b[:, None, :])
    w = colon.wall_radius(s[:, None], theta[None, :])
    inner = cl.point_at(s)[:, None, :] + w[..., None] * u
    outer = inner + thickness * u
    return np.concatenate([inner.reshape(-1, 3), outer.reshape(-1, 3)])


def _end_cap(colon, at_start: bool, sample_step: float, thickness: float) -> np.ndarray:
    """Plate closing one end: the disc out to the wall plus `thickness`, `thickness` deep."""
    cl = colon.centerline
    s_end = 0.0 if at_start else cl.length
    t, n, b = cl.frame_at(np.array([s_end]))
    t, n, b = t[0], n[0], b[0]
    r_max = float(cl.radius_at(s_end))
    theta = np.linspace(0.0, TWO_PI, int(np.ceil(TWO_PI * r_max / sample_step)),
                        endpoint=False)
    radius = colon.wall_radius(np.full_like(theta, s_end), theta) + thickness
    ring = cl.point_at(s_end) + radius[:, None] * (np.cos(theta)[:, None] * n
                                                   + np.sin(theta)[:, None] * b)
    outward = -t if at_start else t
    return np.concatenate([ring, ring + thickness * outward])


def wall_pieces(colon, axial_length: float = 0.010, max_chord_depth: float = 0.0005,
                thickness: float = 0.003, sample_step: float = 0.001,
                overlap: float = 0.0005, min_around: int = 6,
                min_length: float = 0.0025) -> list[np.ndarray]:
    """The whole colon wall, both end caps included, as convex pieces in the world frame.

    Deterministic: the same colon and arguments give the same pieces, in the same order
    (the anal cap, then rings of pieces from the anus to the cecum, then the cecal cap).

    Args:
        colon: a `Colon` (its centreline and analytic wall).
        axial_length: longest piece along the centreline [m].
        max_chord_depth: deepest a piece may bridge the round lumen [m]; sets the number of
            pieces around each ring (a multiple of 3, aligned with the taeniae).
        thickness: how far each piece reaches into the tissue behind the wall [m]; it only
            has to exceed how deep the capsule can press into a piece in one step.
        sample_step: spacing of the wall samples in each patch [m].
        overlap: how far each patch extends past its edges along the wall [m].
        min_around: fewest pieces around a ring.
        min_length: shortest piece along the centreline [m] (where flexures refine).

    Returns:
        One (3, K) array per piece: the vertices of its convex hull [m], ready for
        `pydrake.geometry.Convex(vertices, label)`.
    """
    cl = colon.centerline
    taenia = colon.params.taenia_angle
    stations = _stations(colon, axial_length, max_chord_depth, sample_step, min_length)
    pieces = [_hull_vertices(_end_cap(colon, True, sample_step, thickness))]
    for s0, s1 in zip(stations[:-1], stations[1:]):
        r_max = float(np.max(cl.radius_at(np.linspace(s0, s1, 5))))
        around = _columns_around(r_max, max_chord_depth, min_around)
        width = TWO_PI / around
        for k in range(around):
            t0 = taenia + k * width
            points = _patch(colon, s0, s1, t0, t0 + width, sample_step, overlap, thickness)
            pieces.append(_hull_vertices(points))
    pieces.append(_hull_vertices(_end_cap(colon, False, sample_step, thickness)))
    return pieces
