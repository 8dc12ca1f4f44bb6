"""Flexures added to a course (anatomy/tortuosity.py), checked by routes of their own: the
energy's gradient by finite differences; the bent course's length, curvature and clearance
by brute force on its points; its flexures by the counting rule (anatomy/morphology.py,
itself tested on known shapes in test_population.py)."""

import numpy as np
import pytest

from capsule_drake.anatomy.abdomen import Abdomen
from capsule_drake.anatomy.morphology import acute_flexures
from capsule_drake.anatomy.params import AbdomenParams
from capsule_drake.anatomy.tortuosity import (SPACING, WEIGHTS, _Energy, add_flexures,
                                              choose_places)

RADIUS = 0.018
# A roomy abdomen around a straight tube 60 cm long (its containment terms stay idle).
ROOMY = Abdomen(AbdomenParams(depth_at_umbilicus=0.5, depth_at_pubis=0.5,
                              depth_at_xiphoid=0.5, flank_height=0.25, half_width=0.6,
                              pubis_y=-0.6, xiphoid_y=0.6))


def straight(length=0.6, step=0.001):
    s = np.linspace(0.0, length, int(round(length / step)) + 1)
    points = np.column_stack([np.zeros_like(s), s - 0.5 * length, np.full_like(s, 0.25)])
    return s, points


def radius_of(s, boundaries):
    return np.full_like(np.asarray(s, dtype=float), RADIUS)


def test_the_energys_gradient_is_its_finite_difference():
    """Every term active (a bead pushed into another's clearance, beads out of the abdomen,
    turns beyond the cap, a flexure short of its turn) and the gradient against central
    differences of the energy."""
    rng = np.random.default_rng(4)
    n = 40
    t = np.linspace(0.0, 3.0 * np.pi, n)
    x0 = np.column_stack([0.05 * np.cos(t), 0.012 * t * 3, 0.02 + 0.04 * np.sin(t)])
    radius = np.full(n, 0.02)
    energy = _Energy(x0, radius, [(5, 14, np.cos(np.radians(120.0))),
                                  (20, 29, np.cos(np.radians(100.0)))],
                     np.array([0, 20, 39]), Abdomen(AbdomenParams()), WEIGHTS, 0.012)
    y = (x0 + rng.normal(0.0, 0.002, x0.shape)).ravel() / 0.012
    value, grad = energy(y)
    assert value > 0.0
    h = 1e-6
    for k in rng.choice(np.arange(3, 3 * n), size=40, replace=False):
        e = np.zeros_like(y)
        e[k] = h
        numeric = (energy(y + e)[0] - energy(y - e)[0]) / (2 * h)
        assert grad[k] == pytest.approx(numeric, rel=2e-4, abs=1e-4 * max(1.0, abs(numeric)))
    assert np.all(grad[:3] == 0.0)   # the first bead (the anus) is held


def test_places_keep_their_spacing_and_avoid_the_existing_flexures():
    s = np.linspace(0.0, 1.0, 1001)
    rng = np.random.default_rng(1)
    places = choose_places(s, [0.5], 5, lambda q: q > 0.1, rng)
    assert len(places) == 5
    everything = np.sort(np.array(places + [0.5]))
    assert np.min(np.diff(everything)) >= SPACING - 1e-9
    assert min(places) > 0.1
    # No room for 20: as many as fit, fewer than asked.
    assert len(choose_places(s, [], 20, lambda q: q > 0.0, rng)) < 20


@pytest.mark.parametrize("count", [2, 3, 4])
def test_a_straight_tube_bent_toward_its_count(count):
    """A straight tube of 18 mm radius, 60 cm long, its far end free, bent toward 2, 3 and 4
    flexures: the count it reports is the rule's on its points, within one of the request
    (a bend may fall short or the tube make one more finding room); the length kept to
    1 mm; no radius of curvature below 1.2 lumen radii and no two points more than 10 cm
    apart along it closer than two radii and 3 mm, measured on the points themselves; the
    first point does not move."""
    s, points = straight()
    out = add_flexures(s, points, np.array([0.0, 0.6]), radius_of, ROOMY, count,
                       np.random.default_rng(count))
    assert out is not None
    s2, p2, b2, found = out
    assert found == len(acute_flexures(s2, p2))
    assert abs(found - count) <= 1
    assert s2[-1] == pytest.approx(s[-1], abs=1e-3)
    np.testing.assert_allclose(b2, [0.0, 0.6], atol=1e-3)
    assert np.allclose(p2[0], points[0], atol=1e-9)
    # Radius of curvature from three points 5 mm apart (the circle through them).
    k = 5
    a, b, c = p2[:-2 * k], p2[k:-k], p2[2 * k:]
    ab, bc, ca = (np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1),
                  np.linalg.norm(a - c, axis=1))
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    circumradius = ab * bc * ca / np.maximum(2.0 * area2, 1e-15)
    assert circumradius.min() >= 1.2 * RADIUS
    # Clearance: every pair of points 10 cm or more apart along the course.
    q, sq = p2[::5], s2[::5]
    d = np.linalg.norm(q[:, None] - q[None, :], axis=2)
    far = np.abs(sq[:, None] - sq[None, :]) > 0.10
    assert d[far].min() >= 2 * RADIUS + 0.003


def test_no_room_is_said():
    """Six flexures do not fit in 30 cm: the tube gets as many as fit (fewer); a tube 10 cm
    long has room for none: None, and why."""
    from capsule_drake.anatomy import tortuosity
    s, points = straight(0.3)
    out = add_flexures(s, points, np.array([0.0, 0.3]), radius_of, ROOMY, 6,
                       np.random.default_rng(0))
    assert out is not None and 1 <= out[3] < 6
    s, points = straight(0.1)
    assert add_flexures(s, points, np.array([0.0, 0.1]), radius_of, ROOMY, 2,
                        np.random.default_rng(0)) is None
    assert "room for none" in tortuosity.last_failure
