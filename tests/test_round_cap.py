"""A round cap's end fitted as a capsule's end (anatomy/centerline_extraction.py,
`_fit_round_cap`, `_capsule_end`, `_round_cap_end`), checked on closed-form shapes: a capsule
whose pole is known, the same with inward folds on its body, an open tube it must refuse, and
a blunt flat cap whose line it must keep."""

import functools

import numpy as np
import pytest
import trimesh

from capsule_drake.anatomy import centerline_extraction as ce

RADIUS = 0.02
HEIGHT = 0.12
POLE = np.array([0.0, 0.0, 0.5 * HEIGHT + RADIUS])
"""trimesh's capsule lies along z about the origin: its top pole."""


def _capsule(folds: float = 0.0):
    mesh = trimesh.creation.capsule(height=HEIGHT, radius=RADIUS, count=[96, 96])
    # Its body is one band of long triangles: cut into rings 4 mm apart (as a scan's is).
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, 0.004)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    if folds:
        # Crescents standing inward on the body (not on the cap): three bands at full radius,
        # `folds` of the radius deep between them, every 3 cm along the tube.
        v = mesh.vertices.copy()
        body = np.abs(v[:, 2]) < 0.5 * HEIGHT - 0.004
        theta = np.arctan2(v[:, 1], v[:, 0])
        ring = (0.5 + 0.5 * np.cos(2 * np.pi * v[:, 2] / 0.03)) ** 6
        scale = 1.0 - folds * ring * np.abs(np.sin(1.5 * theta))
        v[body, :2] *= scale[body, None]
        mesh = trimesh.Trimesh(v, mesh.faces, process=False)
    return mesh


@functools.cache
def _plain_sections():
    return ce.MeshSections(_capsule())


def _line_off_axis(tilt_degrees: float, offset: float):
    """A centreline along z that drifts `offset` [m] aside over the 4 cm before the cap's
    base and then goes straight to the cap's wall `tilt_degrees` off the axis: a march
    that left a cap astray (its end on the wall, as the march's is)."""
    base = POLE[2] - RADIUS
    z = np.arange(-0.05, base - 0.01 + 1e-9, 0.005)
    u = np.clip((z - (base - 0.05)) / 0.04, 0.0, 1.0)
    line = np.column_stack([offset * u ** 2, np.zeros_like(z), z])
    tilt = np.radians(tilt_degrees)
    d = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    q = line[-1] - (POLE - [0.0, 0.0, RADIUS])   # from the hemisphere's centre
    reach = -q @ d + np.sqrt((q @ d) ** 2 - q @ q + RADIUS ** 2)
    ray = line[-1] + np.arange(0.005, reach, 0.005)[:, None] * d
    return np.vstack([line, ray, line[-1] + reach * d])


@pytest.mark.parametrize("tilt, offset", [(0.0, 0.0),
                                          pytest.param(20.0, 0.004, marks=pytest.mark.slow),
                                          pytest.param(35.0, 0.008, marks=pytest.mark.slow)])
def test_the_fitted_pole_is_the_capsule_pole_from_a_line_that_went_astray(tilt, offset):
    """From a line whose end is up to 8 mm aside and 35 degrees off the axis, the fitted
    hemisphere's pole within 0.3 mm of the capsule's and its radius within 0.2 mm."""
    sections = _plain_sections()
    line = _line_off_axis(tilt, offset)
    c, a, r, body = ce._capsule_end(sections, line, RADIUS)
    assert np.linalg.norm(c + r * a - POLE) < 3e-4
    assert r == pytest.approx(RADIUS, abs=2e-4)
    made = ce._round_cap_end(sections, line, RADIUS, 0.005)
    assert np.linalg.norm(made[-1] - POLE) < 3e-4
    # The made line stays on the axis from where the fitted body begins (8 mm behind the
    # hemisphere's base at most), and joins the line behind without a kink.
    tail = made[made[:, 2] > POLE[2] - RADIUS - body + 1e-6]
    assert np.abs(tail[:, :2]).max() < 3e-4
    steps = np.diff(made, axis=0)
    steps /= np.linalg.norm(steps, axis=1, keepdims=True)
    assert np.sum(steps[1:] * steps[:-1], axis=1).min() > np.cos(np.radians(20.0))


@pytest.mark.slow
def test_folds_on_the_body_do_not_pull_the_pole():
    """Crescent folds 30 % deep on the body in front of the cap: the fit follows the
    wall's outer envelope (the wall inside the fit weighs a tenth), the pole within 0.5 mm."""
    sections = ce.MeshSections(_capsule(folds=0.3))
    line = _line_off_axis(20.0, 0.004)
    c, a, r, _ = ce._capsule_end(sections, line, RADIUS)
    assert np.linalg.norm(c + r * a - POLE) < 5e-4


def test_a_fit_down_an_open_lumen_is_refused():
    """An open tube has no cap: a hemisphere fitted near its end cannot have the wall round
    its centre (`_closed_around`), and the line is returned as it was."""
    tube = trimesh.creation.cylinder(radius=RADIUS, height=0.2, sections=96)
    keep = np.abs(tube.face_normals[:, 2]) < 0.5   # the side wall only: both ends open
    tube = trimesh.Trimesh(tube.vertices, tube.faces[keep], process=False)
    sections = ce.MeshSections(tube)
    line = np.column_stack([np.zeros(30), np.zeros(30), np.linspace(-0.07, 0.075, 30)])
    assert not ce._closed_around(sections.near(np.array([0.0, 0.0, 0.08]), 3 * RADIUS),
                                 np.array([0.0, 0.0, 0.08]), np.array([0.0, 0.0, 1.0]),
                                 RADIUS)
    made = ce._round_cap_end(sections, line, RADIUS, 0.005)
    assert made is line or np.allclose(made, line)


def test_the_fits_jacobian_is_the_residuals_derivative():
    """The closed-form Jacobian of the capsule end's residuals against central differences,
    at a point off the fit (tilted, tapered, faces on the cap, on the body, inside and out)."""
    rng = np.random.default_rng(3)
    faces = _capsule().triangles_center[::7] + rng.normal(scale=5e-4, size=(1, 3))
    a0 = np.array([0.1, -0.05, 1.0]) / np.linalg.norm([0.1, -0.05, 1.0])
    _, e1, e2 = ce._plane_basis(a0)
    x = np.r_[0.001, -0.002, 0.055, 0.03, -0.02, 0.021, 0.05]
    weights = rng.uniform(0.5, 1.5, len(faces))
    args = (a0, e1, e2, faces, weights, 0.1)
    jac = ce._capsule_end_jacobian(x, *args)
    h = 1e-7
    numeric = np.column_stack([
        (ce._capsule_end_residuals(x + h * np.eye(7)[k], *args)
         - ce._capsule_end_residuals(x - h * np.eye(7)[k], *args)) / (2 * h) for k in range(7)])
    # Faces within h of a switch (sphere/body, inside/outside) differ: leave them out.
    gap = ce._capsule_end_parts(x, a0, e1, e2, faces)
    smooth = (np.abs(gap[3]) > 1e-5) & (np.abs(gap[-1]) > 1e-5)
    assert smooth.sum() > 0.9 * len(faces)
    np.testing.assert_allclose(jac[smooth], numeric[smooth], atol=1e-6)


def _blunt_cap(fillet: float):
    """A tube of RADIUS along z closed at z = HEIGHT / 2 by a flat disc whose rim is rounded
    with radius `fillet` (a segmentation's voxels and blur blunt a flat cap so), remeshed to
    2 mm edges."""
    z = np.arange(-0.5 * HEIGHT, 0.5 * HEIGHT - fillet, 0.002)
    t = np.linspace(0.0, 0.5 * np.pi, 16)
    rho = np.arange(RADIUS - fillet, 0.0, -0.002)[1:]
    profile = np.vstack([[[0.0, -0.5 * HEIGHT]], np.column_stack([np.full_like(z, RADIUS), z]),
                         np.column_stack([RADIUS - fillet + fillet * np.cos(t),
                                          0.5 * HEIGHT - fillet + fillet * np.sin(t)]),
                         np.column_stack([rho, np.full_like(rho, 0.5 * HEIGHT)]),
                         [[0.0, 0.5 * HEIGHT]]])
    mesh = trimesh.creation.revolve(profile, sections=96)
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, 0.002)
    return trimesh.Trimesh(vertices, faces)


@pytest.mark.slow
def test_a_blunt_flat_cap_fitted_as_a_larger_sphere_keeps_the_line(monkeypatch):
    """A flat cap with its rim rounded by a quarter of the radius, which the march can call
    round: the 4 mm fit takes it for a larger sphere whose pole lies in the corner, where
    the made line's sections are no longer centred on it (`end_residual`); the line, ending
    on the disc's centre, is kept. Without that check the end would move by millimetres."""
    sections = ce.MeshSections(_blunt_cap(0.25 * RADIUS))
    line = np.column_stack([np.zeros(30), np.zeros(30), np.linspace(-0.03, 0.5 * HEIGHT, 30)])
    made = ce._round_cap_end(sections, line, RADIUS, 0.005)
    assert np.linalg.norm(made[-1] - line[-1]) < 5e-4
    monkeypatch.setattr(ce, "ROUND_CAP_SECTIONS", np.inf)
    unchecked = ce._round_cap_end(sections, line, RADIUS, 0.005)
    assert np.linalg.norm(unchecked[-1] - line[-1]) > 0.004


@pytest.mark.slow
def test_a_cap_more_than_twice_the_radius_before_it_is_fitted_when_the_end_is_that_wide():
    """A flared end's cap can be more than twice the radius measured 2.5-7.5 cm before the
    end (seed 240066 of the random sweep: ring folds and a flare by half, a 42 mm cap against
    18 mm; no fit was kept and the line stayed 6 cm short of the pole). Given a radius before
    the end of 0.45 of the cap's, the fit is refused as too large unless the end's own
    sections are as wide as the cap (`widest`); with them, its pole within 0.3 mm."""
    sections = _plain_sections()
    line = _line_off_axis(0.0, 0.0)
    before = 0.45 * RADIUS
    assert ce._capsule_end(sections, line, before) is None
    c, a, r, _ = ce._capsule_end(sections, line, before, widest=RADIUS)
    assert np.linalg.norm(c + r * a - POLE) < 3e-4
    assert r == pytest.approx(RADIUS, abs=2e-4)
