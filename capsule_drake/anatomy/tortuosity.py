"""Acute-angle flexures added to a colon's course: the course relaxed as a chain of beads.

The procedural course (anatomy/course.py) has 4-5 acute-angle flexures (anatomy/morphology.py:
places where the centreline turns by more than 90 degrees within 10 cm); CT colonography
counts more (docs/sources.md section 3.2). `add_flexures` bends the course at chosen places
until it has the patient's count, and keeps it a colon:

- the centreline is a chain of beads `BEAD` apart, so every segment keeps its length;
- each chosen place (a window of beads) turns by its drawn angle, in whatever plane the rest
  of the energy prefers; the course's own flexures are held at their turn;
- no bead bends more sharply than `RADIUS_RATIO` lumen radii;
- parts of the tube more than 10 cm apart along it keep twice the larger lumen radius and a
  margin between their centrelines (the course check's clearance, anatomy/course.py);
- the tube stays inside the abdomen (under the skin, above the table, within the flanks), and
  each segment's ends near where the course put them (the anatomy's fixed points).

The energy is minimised with L-BFGS (scipy) from the procedural course.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.optimize import minimize
from scipy.spatial import cKDTree

from .abdomen import Abdomen
from .course import MIN_CLEARANCE, MIN_CURVATURE_RATIO, course_defects
from .morphology import acute_flexures, turning_angles

BEAD = 0.01
"""Spacing of the chain's beads [m]."""
RADIUS_RATIO = 1.5
"""Smallest radius of curvature / lumen radius (the course check asks 1.2)."""
CLEARANCE = 0.006
"""Margin between non-neighbouring parts of the tube, beyond twice the larger radius [m]."""
NEIGHBOUR_ARC = 0.105
"""Beads closer than this along the chain [m] are not pushed apart (the check's 10 cm)."""
WINDOW = 0.10
"""Arc length over which an added flexure makes its turn [m]."""
SPACING = 0.105
"""Closest arc distance between two flexures' centres [m]."""
TURN_RANGE = (100.0, 125.0)
"""Turn of an added flexure [degrees] (U)."""
KICK = 0.005
"""Sideways start of an added flexure [m]."""


def _resample(s, points, step):
    n = int(round(s[-1] / step))
    sb = np.linspace(0.0, s[-1], n + 1)
    return sb, CubicSpline(s, points, axis=0)(sb)


def choose_places(s_beads, existing, count, allowed, rng, spacing=SPACING, margin=0.06,
                  trials=50, weight=None):
    """Arc positions [m] of up to `count` new flexures: at least `spacing` from each other
    and from the `existing` ones, `margin` from the ends, where `allowed(s)` is true; drawn
    in turn from the free places (in proportion to `weight(s)`, default uniform), in up to
    `trials` random orders, the first that places them all or else the one that places the
    most (fewer than `count` when there is no room for more)."""
    s_beads = np.asarray(s_beads, dtype=float)
    candidates = s_beads[(s_beads > margin) & (s_beads < s_beads[-1] - margin)]
    candidates = candidates[allowed(candidates)]
    odds = np.ones(len(candidates)) if weight is None else weight(candidates)
    best = []
    for _ in range(trials):
        taken, out = list(existing), []
        for _ in range(count):
            free = np.ones(len(candidates), dtype=bool)
            if taken:
                gap = np.min(np.abs(candidates[:, None] - np.array(taken)[None, :]), axis=1)
                free = gap >= spacing
            if not np.any(free):
                break
            p = odds * free
            pick = float(rng.choice(candidates, p=p / p.sum()))
            out.append(pick)
            taken.append(pick)
        if len(out) > len(best):
            best = out
        if len(best) == count:
            break
    return sorted(best)


class _Energy:
    def __init__(self, x0, radius, windows, anchors, abdomen: Abdomen, weights, rest):
        self.x0 = x0
        self.n = len(x0)
        self.radius = radius
        self.windows = windows          # (first edge, last edge, cos target)
        self.anchors = anchors          # bead indices held near x0
        self.abdomen = abdomen
        self.w = weights
        self.rest = rest
        r_edge = np.maximum(radius[:-1], radius[1:])
        # Largest turn between consecutive edges: chord BEAD on a circle of the smallest radius.
        self.cos_cap = np.cos(rest / (RADIUS_RATIO * r_edge[1:]))
        self.wa = np.array([a for a, _, _ in windows], dtype=int)
        self.wb = np.array([b for _, b, _ in windows], dtype=int)
        self.wt = np.array([c for _, _, c in windows])
        self.reach = 2.0 * float(np.max(radius)) + CLEARANCE
        self.pairs_at = None

    def _pairs(self, x):
        """Pairs of non-neighbouring beads that may come within reach: found again once a
        bead has moved by half the search's margin since they were."""
        margin = 0.03
        if self.pairs_at is None or np.max(np.linalg.norm(x - self.pairs_at, axis=1)) > 0.5 * margin:
            pairs = cKDTree(x).query_pairs(self.reach + margin, output_type="ndarray")
            pairs = pairs[np.abs(pairs[:, 0] - pairs[:, 1]) * self.rest >= NEIGHBOUR_ARC]
            self.pi, self.pj = pairs[:, 0], pairs[:, 1]
            self.dmin = 2.0 * np.maximum(self.radius[self.pi], self.radius[self.pj]) + CLEARANCE
            self.pairs_at = x.copy()
        return self.pi, self.pj, self.dmin

    def __call__(self, flat):
        """Energy and gradient at bead positions `flat` in units of the rest length."""
        x = flat.reshape(-1, 3).copy() * self.rest
        x[0] = self.x0[0]
        g = np.zeros_like(x)
        w = self.w
        e = np.diff(x, axis=0)
        le = np.linalg.norm(e, axis=1)
        # Bead spacing.
        d = le / self.rest - 1.0
        energy = w["length"] * np.sum(d * d)
        ge = (2.0 * w["length"] * d / le / self.rest)[:, None] * e
        # Turn between consecutive edges (the cosine of unit edges): capped, and weakly
        # straightened.
        u = e / le[:, None]
        c = np.einsum("ij,ij->i", u[:-1], u[1:])
        over = np.maximum(self.cos_cap - c, 0.0)
        energy += w["cap"] * np.sum(over * over) + w["straight"] * np.sum(1.0 - c)
        dc = -2.0 * w["cap"] * over - w["straight"]
        # d(u_a . u_b)/d e_a = (u_b - (u_a . u_b) u_a) / |e_a|.
        ge[:-1] += dc[:, None] * (u[1:] - c[:, None] * u[:-1]) / le[:-1, None]
        ge[1:] += dc[:, None] * (u[:-1] - c[:, None] * u[1:]) / le[1:, None]
        # Curvature that changes smoothly from bead to bead (no spikes between beads).
        v = u[2:] - 2.0 * u[1:-1] + u[:-2]
        energy += w["smooth"] * np.sum(v * v)
        gu = np.zeros_like(u)
        gv = 2.0 * w["smooth"] * v
        gu[2:] += gv
        gu[1:-1] -= 2.0 * gv
        gu[:-2] += gv
        ge += (gu - np.einsum("ij,ij->i", gu, u)[:, None] * u) / le[:, None]
        # Flexures: the edges before and after each window at least the target's turn.
        ua, ub = u[self.wa], u[self.wb]
        cf = np.einsum("ij,ij->i", ua, ub)
        short = np.maximum(cf - self.wt, 0.0)
        energy += w["flexure"] * np.sum(short * short)
        coef = (2.0 * w["flexure"] * short)[:, None]
        np.add.at(ge, self.wa, coef * (ub - cf[:, None] * ua) / le[self.wa, None])
        np.add.at(ge, self.wb, coef * (ua - cf[:, None] * ub) / le[self.wb, None])
        g[1:] += ge
        g[:-1] -= ge
        # Clearance between non-neighbouring beads.
        pi, pj, dmin = self._pairs(x)
        diff = x[pi] - x[pj]
        dist = np.sqrt(np.einsum("ij,ij->i", diff, diff))
        near = dist < dmin
        if np.any(near):
            pen = (dmin[near] - dist[near]) / self.rest
            energy += w["clear"] * np.sum(pen * pen)
            gp = ((-2.0 * w["clear"] * pen / self.rest / np.maximum(dist[near], 1e-9))[:, None]
                  * diff[near])
            np.add.at(g, pi[near], gp)
            np.add.at(g, pj[near], -gp)
        # Inside the abdomen: under the skin, above the table, within the flanks.
        room = self.radius + 0.012
        depth = self.abdomen.depth(x)
        short = np.maximum(room - depth, 0.0) / self.rest
        under = np.flatnonzero(short)
        if len(under):
            h, xu, su = 1e-4, x[under], short[under]
            dx = (self.abdomen.depth(xu + [h, 0, 0]) - self.abdomen.depth(xu - [h, 0, 0])) / (2 * h)
            dy = (self.abdomen.depth(xu + [0, h, 0]) - self.abdomen.depth(xu - [0, h, 0])) / (2 * h)
            energy += w["contain"] * np.sum(su * su)
            coef = -2.0 * w["contain"] * su / self.rest
            g[under, 0] += coef * dx
            g[under, 1] += coef * dy
            g[under, 2] -= coef
        low = np.maximum(room - x[:, 2], 0.0) / self.rest
        energy += w["contain"] * np.sum(low * low)
        g[:, 2] += -2.0 * w["contain"] * low / self.rest
        side = np.maximum(np.abs(x[:, 0]) + room - self.abdomen.params.half_width, 0.0) / self.rest
        energy += w["contain"] * np.sum(side * side)
        g[:, 0] += 2.0 * w["contain"] * side * np.sign(x[:, 0]) / self.rest
        # Anchors, and a weak tether to the course.
        da = (x[self.anchors] - self.x0[self.anchors]) / self.rest
        energy += w["anchor"] * np.sum(da * da)
        np.add.at(g, self.anchors, 2.0 * w["anchor"] * da / self.rest)
        dt = (x - self.x0) / self.rest
        energy += w["tether"] * np.sum(dt * dt)
        g += 2.0 * w["tether"] * dt / self.rest
        g[0] = 0.0
        # d/d(x / rest) = rest d/dx.
        return energy, (g * self.rest).ravel()


WEIGHTS = {"length": 100.0, "cap": 100000.0, "straight": 0.01, "smooth": 5.0, "flexure": 40.0,
           "clear": 100.0, "contain": 100.0, "anchor": 1.0, "tether": 0.01}


def _relax(start, radius, windows, anchors, abdomen, rest, maxiter, tether_to):
    """The chain relaxed from `start`, held (anchors, tether) to `tether_to`."""
    energy = _Energy(tether_to, radius, windows, anchors, abdomen, WEIGHTS, rest)
    result = minimize(energy, start.ravel() / rest, jac=True, method="L-BFGS-B",
                      options={"maxiter": maxiter, "maxfun": 2 * maxiter})
    x = result.x.reshape(-1, 3) * rest
    x[0] = tether_to[0]
    return x


def _arc(points, step):
    """(s, points) every ~`step` m of arc length along the spline through `points`."""
    chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0),
                                                            axis=1))])
    spline = CubicSpline(chord, points, axis=0)
    fine = np.linspace(0.0, chord[-1], 20 * len(points))
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(spline(fine), axis=0),
                                                          axis=1))])
    s = np.linspace(0.0, arc[-1], int(np.ceil(arc[-1] / step)) + 1)
    return s, spline(np.interp(s, arc, fine))


last_failure = ""
"""Why the last `add_flexures` returned None (for messages)."""


def _fail(why: str):
    global last_failure
    last_failure = why
    return None


def add_flexures(s, points, boundaries, radius_of, abdomen: Abdomen, count: int,
                 rng: np.random.Generator, allowed=None, step=0.001, weight=None):
    """(s, points, boundaries, flexures) of the course bent toward `count` acute-angle
    flexures, sampled every ~`step` m, with the flexures it has (a bend can fall short of
    90 degrees, or one more form where the course makes room); None when there is no room
    for them or the relaxed chain fails the course's checks (anatomy/course.py,
    `course_defects`): `last_failure` says which. `radius_of(s, boundaries)` is the lumen
    radius along a course; `allowed(s)` where new flexures may go (default: anywhere) and
    `weight(s)` how likely each place is (default: uniform). The segments keep their lengths
    (between `boundaries`)."""
    s, points = np.asarray(s, dtype=float), np.asarray(points, dtype=float)
    boundaries = np.asarray(boundaries, dtype=float)
    sb, xb = _resample(s, points, BEAD)
    rest = sb[1] - sb[0]
    existing = list(acute_flexures(s, points))
    extra = count - len(existing)
    if extra < 0:
        return _fail(f"the course has {len(existing)} flexures already")
    places = choose_places(sb, existing, extra, allowed or (lambda q: np.ones_like(q, bool)),
                           rng, weight=weight)
    if not places:
        return _fail(f"room for none of {extra} more flexures")
    radius = radius_of(sb, boundaries)
    half = int(round(0.5 * WINDOW / rest))
    turns = turning_angles(sb, xb)
    windows = []
    for p in existing:
        k = int(round(p / rest))
        target = np.radians(max(float(np.nan_to_num(turns[k], nan=TURN_RANGE[0])), TURN_RANGE[0]))
        windows.append((max(k - half, 0), min(k + half - 1, len(sb) - 2), np.cos(target)))
    start = xb.copy()
    for p in places:
        k = int(round(p / rest))
        target = np.radians(rng.uniform(*TURN_RANGE))
        windows.append((k - half, k + half - 1, np.cos(target)))
        # A start off the straight line (where the bend's pull has no sideways part): a
        # bump of KICK toward a drawn side, which also draws the bend's plane.
        tangent = xb[min(k + 1, len(xb) - 1)] - xb[max(k - 1, 0)]
        tangent /= np.linalg.norm(tangent)
        side = rng.normal(size=3)
        side -= (side @ tangent) * tangent
        side /= np.linalg.norm(side)
        j = np.arange(max(k - half, 1), min(k + half + 1, len(xb)))
        start[j] += KICK * np.cos(0.5 * np.pi * (j - k) / half)[:, None] ** 2 * side
    # The segments' ends stay near where the course put them; the cecum's pole may move.
    anchors = np.unique(np.clip(np.round(boundaries[:-1] / rest).astype(int), 0, len(sb) - 1))
    x = _relax(start, radius, windows, anchors, abdomen, rest, 10000, tether_to=xb)
    # The curve through the beads is not as long as their chords: change the beads'
    # spacing by as much and relax again from there.
    longer = _arc(x, step)[0][-1] / s[-1]
    x = _relax(x, radius, windows, anchors, abdomen, rest / longer, 3000, tether_to=xb)
    s_out, p_out = _arc(x, step)
    b_out = boundaries * (s_out[-1] / boundaries[-1])
    ratio, clearance = course_defects(s_out, p_out, radius_of(s_out, b_out))
    if ratio < MIN_CURVATURE_RATIO or clearance < MIN_CLEARANCE:
        return _fail(f"curvature {ratio:.2f} lumen radii, clearance {1000 * clearance:.1f} mm")
    return s_out, p_out, b_out, len(acute_flexures(s_out, p_out))
