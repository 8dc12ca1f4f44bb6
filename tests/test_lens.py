"""Lens models: round trips over the whole image, OpenCV as an independent route, the image
circle against the configured field of view."""

import math

import cv2
import numpy as np
import pytest
from pydrake.common.yaml import yaml_load_typed

from capsule_drake.perception import Lens, LensConfig

# A strongly distorted Kannala-Brandt lens (coefficients of the size calibrations of
# wide-angle endoscope cameras report) and a barrel-distorted 120-degree pinhole.
KB = [-0.02, 0.003, -0.0005, 0.0001]
RADTAN = [-0.28, 0.07, 1.0e-4, -2.0e-4, 0.01]

CONFIGS = {
    "equidistant": LensConfig(),
    "kannala_brandt": LensConfig(model="kannala_brandt", kb_coefficients=KB),
    "kannala_brandt_320_150": LensConfig(model="kannala_brandt", kb_coefficients=KB,
                                         width=320, height=320, fov_deg=150.0),
    "pinhole": LensConfig(model="pinhole_radtan"),
    "pinhole_radtan": LensConfig(model="pinhole_radtan", radtan_coefficients=RADTAN),
    "pinhole_radtan_offcentre": LensConfig(model="pinhole_radtan", radtan_coefficients=RADTAN,
                                           width=320, height=240, fx=150.0, fy=152.0,
                                           cx=165.2, cy=117.9),
}


def _random_rays(rng, n, max_theta):
    """Unit rays uniformly spread in angle up to max_theta from +z."""
    theta = rng.uniform(0.0, max_theta, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    return np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                            np.cos(theta)])


@pytest.mark.parametrize("name", CONFIGS)
def test_pixel_ray_pixel_round_trip_over_the_whole_image(name):
    lens = Lens(CONFIGS[name])
    # Every pixel centre and a sub-pixel grid offset from it: dense over the image.
    pixels = np.concatenate([lens.pixel_grid(), lens.pixel_grid() + [0.37, -0.29]])
    rays = lens.unproject(pixels)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    back, valid = lens.project(rays)
    assert np.max(np.abs(back - pixels)) < 0.1
    # Newton converged far below the tolerance, not just below 0.1 px.
    assert np.max(np.abs(back - pixels)) < 1e-6


@pytest.mark.parametrize("name", CONFIGS)
def test_ray_pixel_ray_round_trip(name):
    lens = Lens(CONFIGS[name])
    rng = np.random.default_rng(1)
    rays = _random_rays(rng, 5000, lens.max_theta if lens.is_fisheye else 0.9)
    pixels, _ = lens.project(rays)
    np.testing.assert_allclose(lens.unproject(pixels), rays, atol=1e-10)


def test_fisheye_sees_behind_the_image_plane():
    """172 degrees: rays up to 86 degrees off axis are in view; an equidistant lens also maps
    rays past 90 degrees (z < 0) to pixels, in the corners outside the image circle."""
    lens = Lens(LensConfig(model="equidistant", fov_deg=200.0))
    ray = np.array([[math.sin(math.radians(95.0)), 0.0, math.cos(math.radians(95.0))]])
    pixel, valid = lens.project(ray)
    assert ray[0, 2] < 0.0 and valid[0]
    # Equidistant: radius in px proportional to the angle, 100 deg at the circle's edge.
    assert pixel[0, 0] - lens.cx == pytest.approx(128.0 * 95.0 / 100.0)
    np.testing.assert_allclose(lens.unproject(pixel), ray, atol=1e-12)


@pytest.mark.parametrize("name", ["kannala_brandt", "kannala_brandt_320_150"])
def test_kannala_brandt_agrees_with_opencv_fisheye(name):
    """cv2.fisheye uses theta = atan(r) of z-normalised points, so only below 90 degrees."""
    lens = Lens(CONFIGS[name])
    rng = np.random.default_rng(2)
    rays = _random_rays(rng, 2000, min(lens.max_theta, math.radians(89.0)))
    points = (rays * rng.uniform(0.01, 0.2, (len(rays), 1))).reshape(-1, 1, 3)
    K = np.array([[lens.fx, 0.0, lens.cx], [0.0, lens.fy, lens.cy], [0.0, 0.0, 1.0]])
    expected, _ = cv2.fisheye.projectPoints(points, np.zeros(3), np.zeros(3), K,
                                            np.array(CONFIGS[name].kb_coefficients))
    pixels, valid = lens.project(points.reshape(-1, 3))
    np.testing.assert_allclose(pixels, expected.reshape(-1, 2), atol=1e-6)
    assert valid.all()


@pytest.mark.parametrize("name", ["pinhole", "pinhole_radtan", "pinhole_radtan_offcentre"])
def test_radtan_agrees_with_opencv_project_points(name):
    lens = Lens(CONFIGS[name])
    rng = np.random.default_rng(3)
    rays = _random_rays(rng, 2000, math.radians(55.0))
    points = rays * rng.uniform(0.01, 0.2, (len(rays), 1))
    K = np.array([[lens.fx, 0.0, lens.cx], [0.0, lens.fy, lens.cy], [0.0, 0.0, 1.0]])
    expected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K,
                                    np.array(CONFIGS[name].radtan_coefficients))
    pixels, _ = lens.project(points)
    np.testing.assert_allclose(pixels, expected.reshape(-1, 2), atol=1e-6)


@pytest.mark.parametrize("name", ["equidistant", "kannala_brandt", "kannala_brandt_320_150"])
def test_image_circle_matches_the_field_of_view(name):
    lens = Lens(CONFIGS[name])
    phi = np.linspace(-np.pi, np.pi, 37)
    for theta, inside in [(lens.max_theta - 1e-9, True), (lens.max_theta + 1e-3, False)]:
        rays = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                                np.full_like(phi, np.cos(theta))])
        pixels, valid = lens.project(rays)
        radius = np.hypot(pixels[:, 0] - lens.cx, pixels[:, 1] - lens.cy)
        if inside:
            # The field's edge is the circle inscribed in the image.
            np.testing.assert_allclose(radius, min(lens.width, lens.height) / 2.0, atol=1e-6)
        assert (valid == inside).all()
    # The unprojected image circle: the pixels whose rays are in the field form a disc of
    # the inscribed radius (pi r^2 of the W H pixels, to the discretisation of its rim).
    _, mask = lens.pixel_rays()
    r = min(lens.width, lens.height) / 2.0
    assert abs(mask.sum() - math.pi * r * r) < 2.0 * math.pi * r


def test_pinhole_field_of_view_spans_the_width():
    lens = Lens(CONFIGS["pinhole"])
    half = math.radians(60.0)
    pixels, valid = lens.project([[math.sin(half), 0.0, math.cos(half)],
                                  [-math.sin(half), 0.0, math.cos(half)]])
    np.testing.assert_allclose(pixels[:, 0], [lens.width - 0.5, -0.5], atol=1e-9)
    assert valid.all()
    _, behind = lens.project([[0.0, 0.0, -1.0]])
    assert not behind[0]


def test_lens_config_loads_from_yaml():
    config = yaml_load_typed(schema=LensConfig, data="""
model: kannala_brandt
width: 320
height: 320
fov_deg: 150
kb_coefficients: [-0.02, 0.003, -0.0005, 0.0001]
""")
    lens = Lens(config)
    assert lens.width == 320 and lens.fov_deg == 150.0
    assert Lens(LensConfig()).fov_deg == 172.0
    assert Lens(LensConfig(model="pinhole_radtan")).fov_deg == 120.0


def test_bad_configs_are_rejected():
    with pytest.raises(ValueError, match="model"):
        Lens(LensConfig(model="orthographic"))
    with pytest.raises(ValueError, match="fov_deg"):
        Lens(LensConfig(model="pinhole_radtan", fov_deg=180.0))
    with pytest.raises(ValueError, match="fold"):
        # This polynomial turns over near 50 degrees.
        Lens(LensConfig(model="kannala_brandt", kb_coefficients=[-0.5, 0.0, 0.0, 0.0]))


def _field_solid_angle_by_sampling(lens, n=2_000_000, seed=0):
    """4 pi times the share of directions, uniform on the sphere, that the lens sees inside
    its image: a route to the field's solid angle that never differentiates the lens."""
    rays = np.random.default_rng(seed).standard_normal((n, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    pixels, valid = lens.project(rays)
    inside = (valid & lens.in_field(rays)
              & (pixels[:, 0] >= -0.5) & (pixels[:, 0] <= lens.width - 0.5)
              & (pixels[:, 1] >= -0.5) & (pixels[:, 1] <= lens.height - 0.5))
    return 4.0 * np.pi * inside.mean()


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_pixels_solid_angles_add_up_to_the_field(name):
    """The pixels' solid angles sum to the field's: against the closed forms of the
    equidistant fisheye's cone, 2 pi (1 - cos theta_max), and of the undistorted pinhole's
    pyramid, 4 asin(sin(a) sin(b)) with a, b its half-angles; for every lens against the
    share of random directions it sees (the field's edge pixels count whole or not at all,
    hence 1 %)."""
    lens = Lens(CONFIGS[name])
    omega = lens.solid_angles()
    assert np.all(omega >= 0.0) and np.all(omega[~lens.pixel_rays()[1]] == 0.0)
    total = omega.sum()
    assert total == pytest.approx(_field_solid_angle_by_sampling(lens), rel=0.01)
    if name == "equidistant":
        assert total == pytest.approx(2 * np.pi * (1 - np.cos(lens.max_theta)), rel=0.01)
    if name == "pinhole":
        a = math.atan((lens.width / 2) / lens.fx)
        b = math.atan((lens.height / 2) / lens.fy)
        assert total == pytest.approx(4 * math.asin(math.sin(a) * math.sin(b)), rel=1e-3)


def test_a_pinhole_pixel_sees_cos_cubed_of_the_axis_pixels_solid_angle():
    """An undistorted pinhole's pixel at angle theta off the axis sees cos^3(theta) / (fx fy)
    sr (its area 1 / (fx fy) on the image plane at z = 1, at distance 1 / cos(theta), tilted
    by theta)."""
    lens = Lens(CONFIGS["pinhole"])
    rays, _ = lens.pixel_rays()
    cos = rays[..., 2] / np.linalg.norm(rays, axis=-1)
    np.testing.assert_allclose(lens.solid_angles(), cos ** 3 / (lens.fx * lens.fy),
                               rtol=1e-3)


def test_inside_angles_are_the_angle_to_the_fields_edge():
    """The equidistant fisheye's: theta_max - theta (its image circle is a cone), to within
    the border pixels' spacing. The undistorted pinhole's, on the principal row: the angle
    to the image's side, atan((W / 2) / f) - theta, where the side is nearest."""
    fisheye = Lens(CONFIGS["equidistant"])
    rays, field = fisheye.pixel_rays()
    theta = np.degrees(np.arccos(np.clip(rays[..., 2], -1.0, 1.0)))
    step = math.degrees(fisheye.max_theta) / (fisheye.width / 2)
    np.testing.assert_allclose(fisheye.inside_angles()[field],
                               (math.degrees(fisheye.max_theta) - theta)[field],
                               atol=1.5 * step)
    assert np.all(fisheye.inside_angles()[~field] == 0.0)
    pinhole = Lens(CONFIGS["pinhole"])
    rays, _ = pinhole.pixel_rays()
    row = pinhole.height // 2
    u = np.arange(pinhole.width // 2 + 1, pinhole.width - 1)
    edge = math.degrees(math.atan((pinhole.width - 1 - pinhole.cx) / pinhole.fx))
    off = np.degrees(np.arctan((u - pinhole.cx) / pinhole.fx))
    np.testing.assert_allclose(pinhole.inside_angles()[row, u], edge - off, atol=0.5)
