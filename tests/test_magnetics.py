"""Point-dipole magnetics, each result checked against an independent route."""

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose
from pydrake.autodiffutils import AutoDiffXd, ExtractGradient, InitializeAutoDiff
from pydrake.common.yaml import yaml_load_typed
from scipy.spatial.transform import Rotation

from capsule_drake.physics.magnetics import (
    DEFAULT_MIN_DISTANCE,
    MU0,
    MagnetGeometry,
    cuboid_moment,
    cylinder_moment,
    dipole_energy,
    dipole_field,
    dipole_force,
    dipole_pair_interaction,
    dipole_pair_interaction_float,
    dipole_pair_wrench,
    dipole_torque,
    legacy_seed_moment,
    sphere_moment,
)

EPM_MOMENT = 970.0  # A m^2, N52 cylinder 101.6 x 101.6 mm
IPM_MOMENT = 1.26  # A m^2, N52 cylinder ~11.1 x 11.1 mm
Z = np.array([0.0, 0.0, 1.0])
X = np.array([1.0, 0.0, 0.0])


def random_cases(count=20, seed=7):
    """Random moments and offsets between 5 and 30 cm."""
    rng = np.random.default_rng(seed)
    for _ in range(count):
        m_s = rng.normal(size=3)
        m_s *= EPM_MOMENT / np.linalg.norm(m_s)
        m_t = rng.normal(size=3)
        m_t *= IPM_MOMENT / np.linalg.norm(m_t)
        p = rng.normal(size=3)
        p *= rng.uniform(0.05, 0.3) / np.linalg.norm(p)
        yield m_s, m_t, p


# --- force ---------------------------------------------------------------------


@pytest.mark.parametrize("m_s, m_t, p", list(random_cases()))
def test_force_is_minus_energy_gradient_by_finite_differences(m_s, m_t, p):
    # F = -dU/dr_target; dr_target = dp with the source fixed.
    h = 1e-6
    grad = np.zeros(3)
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = h
        grad[k] = (dipole_energy(m_s, m_t, p + dp) - dipole_energy(m_s, m_t, p - dp)) / (
            2 * h
        )
    force = dipole_force(m_s, m_t, p)
    assert_allclose(force, -grad, rtol=1e-6, atol=1e-9 * np.linalg.norm(force))


@pytest.mark.parametrize("m_s, m_t, p", list(random_cases()))
def test_force_is_minus_energy_gradient_by_autodiff(m_s, m_t, p):
    p_ad = InitializeAutoDiff(p).reshape(3)
    energy = dipole_energy(m_s, m_t, p_ad)
    assert isinstance(energy, AutoDiffXd)
    grad = energy.derivatives()
    assert_allclose(dipole_force(m_s, m_t, p), -grad, rtol=1e-10, atol=1e-14)


# --- torque --------------------------------------------------------------------


@pytest.mark.parametrize("m_s, m_t, p", list(random_cases()))
def test_torque_is_m_cross_b(m_s, m_t, p):
    assert_allclose(
        dipole_torque(m_s, m_t, p), np.cross(m_t, dipole_field(m_s, p)), rtol=1e-12
    )


@pytest.mark.parametrize("m_s, m_t, p", list(random_cases()))
def test_torque_is_minus_energy_gradient_wrt_rotation(m_s, m_t, p):
    # Rotating m_t by a small angle about axis k changes U by -T_k * angle.
    h = 1e-6
    grad = np.zeros(3)
    for k in range(3):
        rotvec = np.zeros(3)
        rotvec[k] = h
        m_plus = Rotation.from_rotvec(rotvec).apply(m_t)
        m_minus = Rotation.from_rotvec(-rotvec).apply(m_t)
        grad[k] = (dipole_energy(m_s, m_plus, p) - dipole_energy(m_s, m_minus, p)) / (
            2 * h
        )
    torque = dipole_torque(m_s, m_t, p)
    assert_allclose(torque, -grad, rtol=1e-6, atol=1e-9 * np.linalg.norm(torque))


def paper_torque_as_printed(m_a, m_c, p):
    """The seed paper's torque with its typo: |p_hat|^3 (= 1) in the denominator."""
    r = np.linalg.norm(p)
    u = p / r
    D = 3 * np.outer(u, u) - np.eye(3)
    p_hat_cubed = np.linalg.norm(u) ** 3
    return MU0 / (4 * math.pi * p_hat_cubed) * np.cross(m_c, D @ m_a)


def test_torque_scales_as_inverse_cube_and_paper_typo_would_fail():
    m_s = EPM_MOMENT * Z
    m_t = IPM_MOMENT * X  # perpendicular: maximal torque on axis
    direction = np.array([0.2, -0.1, 1.0])
    direction /= np.linalg.norm(direction)
    t1 = dipole_torque(m_s, m_t, 0.1 * direction)
    t2 = dipole_torque(m_s, m_t, 0.2 * direction)
    # Doubling the distance divides the torque by 8 (B ~ 1/r^3).
    assert_allclose(t2, t1 / 8, rtol=1e-12)
    # The printed formula has no distance dependence at all; at 15 cm it is off
    # by 1/r^3 ~ 296x, so the rotation-gradient test above would reject it.
    p = 0.15 * direction
    printed = paper_torque_as_printed(m_s, m_t, p)
    assert_allclose(printed, paper_torque_as_printed(m_s, m_t, 2 * p), rtol=1e-12)
    assert_allclose(printed * 0.15**-3, dipole_torque(m_s, m_t, p), rtol=1e-12)
    assert not np.allclose(printed, dipole_torque(m_s, m_t, p), rtol=0.01)


# --- conservation --------------------------------------------------------------


@pytest.mark.parametrize("m_s, m_t, p", list(random_cases()))
@pytest.mark.parametrize("min_distance", [DEFAULT_MIN_DISTANCE, 0.5])
def test_newton_third_law_and_angular_momentum_balance(m_s, m_t, p, min_distance):
    # min_distance = 0.5 m puts every case inside the guard: balance must hold there too.
    rng = np.random.default_rng(3)
    r_source = rng.normal(size=3)
    r_target = r_source + p
    wrench = dipole_pair_wrench(m_s, m_t, p, min_distance)
    scale_f = np.linalg.norm(wrench.force_target)
    assert_allclose(wrench.force_target + wrench.force_source, 0, atol=1e-15 * scale_f)
    # Total torque about several arbitrary points O vanishes.
    for origin in rng.normal(size=(3, 3)):
        total = (
            wrench.torque_target
            + np.cross(r_target - origin, wrench.force_target)
            + wrench.torque_source
            + np.cross(r_source - origin, wrench.force_source)
        )
        scale = np.linalg.norm(wrench.torque_target) + scale_f * np.linalg.norm(
            r_target - origin
        )
        assert_allclose(total, 0, atol=1e-13 * scale)


@pytest.mark.parametrize("m_s, m_t, p", list(random_cases()))
def test_reaction_torque_equals_target_field_on_source(m_s, m_t, p):
    # Second route for -T - p x F: the source feels the target's field, m_s x B_t(-p).
    wrench = dipole_pair_wrench(m_s, m_t, p)
    assert_allclose(
        wrench.torque_source,
        np.cross(m_s, dipole_field(m_t, -p)),
        rtol=1e-9,
        atol=1e-12 * np.linalg.norm(wrench.torque_source),
    )


# --- published figures and signs ----------------------------------------------


@pytest.mark.parametrize("distance, newtons", [(0.10, 7.33), (0.15, 1.45), (0.20, 0.46)])
def test_published_coaxial_force(distance, newtons):
    force = dipole_force(EPM_MOMENT * Z, IPM_MOMENT * Z, distance * Z)
    assert_allclose(np.linalg.norm(force), newtons, rtol=0.01)


def test_published_side_on_force_and_axial_field():
    force = dipole_force(EPM_MOMENT * Z, IPM_MOMENT * Z, 0.15 * X)
    assert_allclose(np.linalg.norm(force), 0.72, rtol=0.01)
    field = dipole_field(EPM_MOMENT * Z, 0.15 * Z)
    assert_allclose(field, [0, 0, 57.5e-3], rtol=0.001, atol=1e-12)


def test_coaxial_aligned_attract_side_by_side_parallel_repel():
    # Target above the source, both moments up: force on the target points down.
    force = dipole_force(EPM_MOMENT * Z, IPM_MOMENT * Z, 0.15 * Z)
    assert force[2] < 0 and abs(force[0]) + abs(force[1]) < 1e-15
    # Target beside the source, both moments up: pushed further away (+x).
    force = dipole_force(EPM_MOMENT * Z, IPM_MOMENT * Z, 0.15 * X)
    assert force[0] > 0 and abs(force[1]) + abs(force[2]) < 1e-15


def test_aligned_dipole_feels_no_torque_perpendicular_one_is_turned_into_field():
    assert_allclose(dipole_torque(EPM_MOMENT * Z, IPM_MOMENT * Z, 0.15 * Z), 0, atol=1e-18)
    torque = dipole_torque(EPM_MOMENT * Z, IPM_MOMENT * X, 0.15 * Z)
    # m = +x in B = +z: m x B = -y rotates m towards +z.
    assert torque[1] < 0


# --- moments -------------------------------------------------------------------


def test_n52_four_inch_cylinder_is_970_am2():
    assert_allclose(cylinder_moment(0.1016, 0.1016, 1.48), 970.0, rtol=0.005)
    assert_allclose(cylinder_moment(0.0111, 0.0111, 1.48), 1.26, rtol=0.005)


def test_sphere_and_cuboid_moments_from_volume():
    br = 1.3
    d = 0.02
    assert_allclose(sphere_moment(d, br), br * (4 / 3) * math.pi * (d / 2) ** 3 / MU0)
    assert_allclose(cuboid_moment(0.01, 0.02, 0.03, br), br * 6e-6 / MU0)
    # Magnetisation of N52 (Br/mu0 ~ 1.18e6 A/m) times 1 cm^3.
    assert_allclose(cuboid_moment(0.01, 0.01, 0.01, 1.48), 1.1777, rtol=1e-3)


def test_legacy_formula_matches_only_equal_aspect_cylinder():
    br, h = 1.48, 0.05
    assert_allclose(legacy_seed_moment(br, h), cylinder_moment(h, h, br), rtol=1e-12)
    assert_allclose(legacy_seed_moment(br, h), 1.5 * sphere_moment(h, br), rtol=1e-12)
    # A cylinder twice as long as wide: legacy (h = L) is off by (L/D)^2 = 4.
    assert_allclose(
        legacy_seed_moment(br, 2 * h), 4 * cylinder_moment(h, 2 * h, br), rtol=1e-12
    )


def test_magnet_geometry_moments_and_yaml():
    assert_allclose(MagnetGeometry().moment(), 970.0, rtol=0.005)
    sphere = MagnetGeometry(shape="sphere", dimensions=[0.02], remanence=1.3)
    assert_allclose(sphere.moment(), sphere_moment(0.02, 1.3))
    legacy = MagnetGeometry(shape="sphere", dimensions=[0.02], remanence=1.3, legacy=True)
    assert_allclose(legacy.moment(), 1.5 * sphere.moment())
    cuboid = MagnetGeometry(shape="cuboid", dimensions=[0.01, 0.02, 0.03])
    assert_allclose(cuboid.moment(), cuboid_moment(0.01, 0.02, 0.03, 1.48))
    loaded = yaml_load_typed(
        schema=MagnetGeometry,
        data="{shape: cylinder, dimensions: [0.0111, 0.0111], remanence: 1.48}",
    )
    assert_allclose(loaded.moment(), 1.26, rtol=0.005)
    with pytest.raises(ValueError):
        MagnetGeometry(shape="torus").moment()
    with pytest.raises(ValueError):
        MagnetGeometry(shape="cylinder", dimensions=[0.01]).moment()


# --- against an exact finite-size field ----------------------------------------


def test_far_field_matches_magpylib_exact_cylinder():
    magpylib = pytest.importorskip("magpylib")
    diameter = length = 0.1016
    br = 1.48
    magnet = magpylib.magnet.Cylinder(
        dimension=(diameter, length), polarization=(0, 0, br)
    )
    m = cylinder_moment(diameter, length, br) * Z
    rng = np.random.default_rng(11)
    directions = np.vstack([Z, X, rng.normal(size=(8, 3))])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points = 0.5 * directions
    exact = magnet.getB(points)
    for point, b_exact in zip(points, exact):
        b_dipole = dipole_field(m, point)
        assert_allclose(b_dipole, b_exact, atol=0.01 * np.linalg.norm(b_exact))
    # Near the magnet the finite size matters (docs/sources.md section 1: +18 % force at 10 cm):
    # the dipole must be visibly off there, or this comparison proves nothing.
    near = 0.08 * Z
    assert not np.allclose(dipole_field(m, near), magnet.getB(near), rtol=0.01)


# --- r -> 0 guard ---------------------------------------------------------------


@pytest.mark.parametrize("r", [0.0, 1e-9])
def test_guard_is_finite_near_zero(r):
    p = r * np.array([0.6, 0.0, 0.8])
    m_s, m_t = EPM_MOMENT * Z, IPM_MOMENT * X
    for value in (
        dipole_field(m_s, p),
        dipole_force(m_s, m_t, p),
        dipole_torque(m_s, m_t, p),
        *dipole_pair_wrench(m_s, m_t, p),
        *dipole_pair_interaction(m_s, m_t, p),
        *dipole_pair_interaction_float(m_s, m_t, p),
    ):
        assert np.all(np.isfinite(value))
    assert np.isfinite(dipole_energy(m_s, m_t, p))
    if r == 0.0:
        assert_allclose(dipole_force(m_s, m_t, p), 0)
        assert_allclose(dipole_field(m_s, p), 0)
    else:
        # Frozen at min_distance along the same direction.
        p_min = DEFAULT_MIN_DISTANCE * p / r
        assert_allclose(dipole_force(m_s, m_t, p), dipole_force(m_s, m_t, p_min))
        assert_allclose(dipole_field(m_s, p), dipole_field(m_s, p_min))


def test_guard_is_continuous_at_min_distance_and_autodiff_safe_at_zero():
    m_s, m_t = EPM_MOMENT * Z, IPM_MOMENT * X
    u = np.array([0.0, 0.6, 0.8])
    d = 0.01
    just_out = dipole_force(m_s, m_t, (d * (1 + 1e-9)) * u, min_distance=d)
    just_in = dipole_force(m_s, m_t, (d * (1 - 1e-9)) * u, min_distance=d)
    assert_allclose(just_in, just_out, rtol=1e-6)
    zero_ad = InitializeAutoDiff(np.zeros(3)).reshape(3)
    force = dipole_force(m_s, m_t, zero_ad)
    assert np.all(np.isfinite(ExtractGradient(force)))


# --- fast float path ------------------------------------------------------------


@pytest.mark.parametrize("m_s, m_t, p", list(random_cases()))
@pytest.mark.parametrize("min_distance", [DEFAULT_MIN_DISTANCE, 0.4])
def test_float_fast_path_equals_generic_path(m_s, m_t, p, min_distance):
    generic = dipole_pair_interaction(m_s, m_t, p, min_distance)
    fast = dipole_pair_interaction_float(m_s, m_t, p, min_distance)
    for name, a, b in zip(generic._fields, generic, fast):
        assert_allclose(b, a, rtol=1e-12, atol=1e-15 * np.linalg.norm(a), err_msg=name)
    # And the generic pair interaction agrees with the single functions.
    assert_allclose(generic.force_target, dipole_force(m_s, m_t, p, min_distance))
    assert_allclose(generic.field_at_source, dipole_field(m_t, -p, min_distance))
