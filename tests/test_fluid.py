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


@pytest.mark.parametrize("tilt_deg", [0.0, 35.0, 80.0])
def test_buoyancy_volume_is_the_capsules_by_closed_form(tilt_deg):
    """The sliced capsule (physics/fluid_force.py): wholly under the level it displaces
    pi R^2 L + 4/3 pi R^3 (to 0.5 %); with the level through its centre, half of that at any
    tilt (the slices pair up about the centre), its centre of buoyancy below the centre."""
    from capsule_drake.physics.fluid_force import capsule_slices, submerged

    radius, length = 0.0058, 0.0194
    whole = np.pi * radius ** 2 * length + 4.0 / 3.0 * np.pi * radius ** 3
    slices = capsule_slices(radius, length)
    tilt = np.radians(tilt_deg)
    axis = np.array([np.cos(tilt), 0.0, np.sin(tilt)])
    p = np.array([0.1, 0.0, 0.05])
    assert submerged(p, axis, 0.2, *slices)[0] == pytest.approx(whole, rel=5e-3)
    assert submerged(p, axis, -0.2, *slices)[0] == 0.0
    volume, centre = submerged(p, axis, p[2], *slices)
    assert volume == pytest.approx(0.5 * submerged(p, axis, 0.2, *slices)[0], rel=1e-9)
    if tilt_deg < 80.0:
        assert centre[2] < p[2]


def test_the_lumen_state_is_drawn_as_published():
    """2,000 patients: the residual fluid's mean within 3 standard errors of 149 ml and its
    share under 200 ml within the two preparations' 77-82 % (+-3 %); 10.4 % of segments
    not fully distended (+-1.5 %), the sigmoid most often."""
    from capsule_drake.anatomy.lumen_state import drawn_lumen
    from capsule_drake.anatomy.params import LumenState, SEGMENT_NAMES

    states = [drawn_lumen(ColonParams(seed=seed, lumen=LumenState())) for seed in range(2000)]
    fluid = np.array([s.fluid_ml for s in states])
    assert abs(fluid.mean() - 149.0) < 3 * 107.0 / np.sqrt(len(fluid))
    assert 0.74 <= np.mean(fluid < 200.0) <= 0.85
    share = {name: np.mean([name in s.collapsed for s in states]) for name in SEGMENT_NAMES}
    assert np.mean(list(share.values())) == pytest.approx(0.104, abs=0.015)
    assert max(share, key=share.get) == "sigmoid"
    assert drawn_lumen(ColonParams(seed=3)) is None


def test_a_narrowed_segment_keeps_its_course_and_passes_the_capsule():
    """A collapsed sigmoid: the same centreline as the distended patient's, the sigmoid's
    nominal radius 0.7 of it (above the floor that leaves the capsule 6.8 mm past its
    folds), the other segments' unchanged."""
    from capsule_drake.anatomy.colon import build_colon
    from capsule_drake.anatomy.params import LumenState

    open_ = build_colon(ColonParams(seed=2))
    shut = build_colon(ColonParams(seed=2, lumen=LumenState(fluid_ml=0.0,
                                                             collapsed=["sigmoid"])))
    np.testing.assert_array_equal(open_.centerline.s, shut.centerline.s)
    s0, s1 = open_.centerline.segment_ranges()["sigmoid"]
    mid = 0.5 * (s0 + s1)
    assert shut.centerline.radius_at(mid) == pytest.approx(0.7 * open_.centerline.radius_at(mid))
    d0, d1 = open_.centerline.segment_ranges()["descending"]
    assert shut.centerline.radius_at(0.5 * (d0 + d1)) == open_.centerline.radius_at(
        0.5 * (d0 + d1))


def test_the_centre_of_buoyancy_of_a_half_submerged_horizontal_capsule():
    """Horizontal, the level through the axis: the submerged half's centroid lies below the
    axis by the closed form of half a cylinder and two quarter spheres:
    (4 R / 3 pi * pi R^2 L / 2 + 3 R / 8 * 2/3 pi R^3) / (pi R^2 L / 2 + 2/3 pi R^3), to 1 %."""
    from capsule_drake.physics.fluid_force import capsule_slices, submerged

    radius, length = 0.0058, 0.0194
    p = np.zeros(3)
    _, centre = submerged(p, np.array([1.0, 0.0, 0.0]), 0.0,
                          *capsule_slices(radius, length, slices=400))
    half_cylinder, domes = np.pi * radius ** 2 * length / 2, 2.0 / 3.0 * np.pi * radius ** 3
    expected = (4 * radius / (3 * np.pi) * half_cylinder + 3 * radius / 8 * domes) / (
        half_cylinder + domes)
    assert -centre[2] == pytest.approx(expected, rel=0.01)


@pytest.mark.slow
def test_a_capsule_resting_in_a_pool_presses_on_the_wall_less_by_its_buoyancy():
    """The capsule let settle in seed 0's rectum (the EPM 50 cm away), dry and in 150 ml of
    fluid: the wall carries its weight m g dry, and m g less the buoyancy rho g V_sub in
    the pool (V_sub from its final pose and the pool's level), to 5 % of m g."""
    import dataclasses

    from capsule_drake.anatomy.source import fluid_scene
    from capsule_drake.app.run import simulate
    from capsule_drake.capsule.model import capsule_model
    from capsule_drake.physics.fluid_force import capsule_slices, submerged
    from capsule_drake.scenario import load_scenario
    from pydrake.common.eigen_geometry import Quaternion

    def settled(fluid_ml):
        scenario = load_scenario(name="FarMagnet", override=(
            f"{{colon: {{lumen: {{fluid_ml: {fluid_ml}, collapsed: []}}}}}}"))
        scenario = dataclasses.replace(scenario, duration=1.5)
        result = simulate(scenario, progress=False)
        return scenario, result, float(np.median(result.contact_load[-20:]))

    model = capsule_model()
    weight = model.mass * 9.81
    _, _, dry = settled(0.0)
    assert dry == pytest.approx(weight, rel=0.05)
    scenario, result, wet = settled(150.0)
    q = result.capsule_state[:4, -1]
    p = result.capsule_state[4:7, -1]
    axis = Quaternion(q / np.linalg.norm(q)).rotation()[:, 2]
    pool = next(pool for pool in fluid_scene(scenario.colon).pools if pool.s_min < 0.05)
    volume, _ = submerged(p, axis, pool.level, *capsule_slices(model.radius, model.length))
    assert volume > 0.0
    assert wet == pytest.approx(weight - 1000.0 * 9.81 * volume, abs=0.05 * weight)


@pytest.mark.slow   # ~18 s: it draws colons until one cannot hold its fluid
def test_fluid_a_colon_cannot_hold_is_reported_in_one_line(caplog):
    """The ex vivo segment lies flat in its tray: no basin holds fluid, and the 20 ml asked
    for are reported as not placed (one warning line), not silently lost."""
    from capsule_drake.anatomy.source import fluid_scene
    from capsule_drake.scenario import load_scenario

    scenario = load_scenario(name="ExVivoSegment", override="{colon: {lumen: {fluid_ml: 20}}}")
    with caplog.at_level("WARNING", logger="capsule_drake.anatomy"):
        scene = fluid_scene(scenario.colon)
    assert scene.pools == [] and scene.surface_obj is None
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "hold 0.0 ml of the 20.0 ml" in lines[0] and "\n" not in lines[0]


def test_bubbles_float_on_the_surface():
    """30 bubbles asked for in seed 0's colon with 150 ml: 30 spheres, each centred on one
    of the pools' levels (within the largest bubble radius), none wider than it."""
    import trimesh

    from capsule_drake.anatomy.lumen_state import BUBBLE_RADIUS
    from capsule_drake.anatomy.params import LumenState
    from capsule_drake.anatomy.source import fluid_scene

    params = ColonParams(seed=0, lumen=LumenState(fluid_ml=150.0, collapsed=[], bubbles=30))
    scene = fluid_scene(params)
    mesh = trimesh.load(scene.bubbles_obj, force="mesh", process=True)
    spheres = mesh.split(only_watertight=False)
    assert len(spheres) == 30
    levels = np.array([pool.level for pool in scene.pools])
    for sphere in spheres:
        centre = sphere.bounds.mean(axis=0)
        assert np.min(np.abs(levels - centre[2])) < 1e-6 + 0.2 * BUBBLE_RADIUS[1]
        assert 0.5 * np.ptp(sphere.vertices[:, 2]) <= BUBBLE_RADIUS[1] + 1e-9


def test_patients_differing_only_in_fluid_share_one_built_colon():
    """The fluid and the bubbles are not part of the wall: seed 0 with 150 ml and bubbles,
    with none, and without a lumen state at all load the same colon and files; a narrowed
    sigmoid is another colon."""
    from capsule_drake.anatomy.params import LumenState

    dry = load_colon(ColonParams(seed=0))
    wet = load_colon(ColonParams(seed=0, lumen=LumenState(fluid_ml=150.0, collapsed=[],
                                                           bubbles=10)))
    assert wet[0] is dry[0] and wet[1] == dry[1]
    shut = load_colon(ColonParams(seed=0, lumen=LumenState(fluid_ml=10.0,
                                                            collapsed=["sigmoid"])))
    assert shut[1].visual_obj.parent != dry[1].visual_obj.parent
