"""Residual fluid (anatomy/fluid.py): the area below a level against the circular segment's
closed form, a pool's volume against a Monte Carlo count of points inside the lumen and
below the level, the surface on the level and inside the wall."""

import numpy as np
import pytest

from capsule_drake.anatomy import load_colon
from capsule_drake.anatomy.fluid import _area_below, fluid_pools, surface_mesh
from capsule_drake.anatomy.params import ColonParams


@pytest.mark.parametrize("tilt_deg", [0.0, 30.0])
@pytest.mark.parametrize("depth", [0.003, 0.02, 0.037])
def test_area_below_a_level_is_the_circular_segment(depth, tilt_deg):
    """A ring of radius r in a vertical plane (tilted about z: its area below a level is the
    same) cut `depth` above its lowest point: r^2 acos((r - d) / r) - (r - d) sqrt(2 r d - d^2)."""
    r = 0.02
    theta = np.linspace(0.0, 2.0 * np.pi, 4000, endpoint=False)
    c, s_ = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    centre = np.array([0.1, 0.2, 0.05])
    ring = centre + r * np.column_stack([np.cos(theta) * c, np.cos(theta) * s_, np.sin(theta)])
    d = depth
    expected = r * r * np.arccos((r - d) / r) - (r - d) * np.sqrt(2 * r * d - d * d)
    assert _area_below(ring, centre, centre[2] - r + d) == pytest.approx(expected, rel=1e-4)


@pytest.fixture(scope="module")
def colon():
    return load_colon(ColonParams(seed=0))[0]


@pytest.mark.slow
def test_the_pools_hold_the_volume_by_an_independent_count(colon):
    """150 ml in seed 0's colon: the pools' volumes add up to it (the levels' bisection),
    and each pool's volume is what a Monte Carlo count of points finds inside the lumen
    (within the wall's radius of their closest centreline station) and below the level,
    within 3 standard errors and 3 %."""
    pools = fluid_pools(colon, 150e-6)
    assert sum(p.volume for p in pools) == pytest.approx(150e-6, rel=1e-3)
    rng = np.random.default_rng(1)
    cl = colon.centerline
    for pool in pools:
        if pool.volume < 20e-6:
            continue
        s = np.linspace(pool.s_min, pool.s_max, 200)
        centre = cl.point_at(s)
        reach = colon.max_wall_radius(s).max() + 0.002
        low, high = centre.min(axis=0) - reach, centre.max(axis=0) + reach
        high[2] = pool.level
        box = np.prod(high - low)
        n = 200_000
        points = low + rng.uniform(size=(n, 3)) * (high - low)
        station, dist, angle = cl.closest(points)
        inside = ((dist < colon.wall_radius(station, angle)) & (station >= pool.s_min)
                  & (station <= pool.s_max))
        fraction = inside.mean()
        estimate = box * fraction
        error = box * np.sqrt(fraction * (1 - fraction) / n)
        assert abs(estimate - pool.volume) < max(3 * error, 0.03 * pool.volume), (
            pool, estimate, error)


def test_the_surface_lies_on_the_level_inside_the_wall(colon):
    pool = max(fluid_pools(colon, 150e-6), key=lambda p: p.volume)
    mesh = surface_mesh(colon, pool)
    assert mesh is not None and len(mesh.faces) > 100
    np.testing.assert_allclose(mesh.vertices[:, 2], pool.level, atol=1e-9)
    assert np.all(mesh.face_normals[:, 2] > 0.99)
    # Every vertex within the lumen (the chords' ends on the wall's polygon, to 1 mm).
    assert np.all(colon.excursion(mesh.vertices) < 1e-3)
