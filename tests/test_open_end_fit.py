"""An open end made again from its wall fitted as a tube (anatomy/centerline_extraction.py,
`_fitted_open_end`), checked on a closed-form tube: straight along z, flared by 30 % over its
last 4 cm, with haustral crescents 40 % deep, its end cut 40 degrees obliquely through the
axis at z = LENGTH. Its true centre line is the z axis up to (0, 0, LENGTH)."""

import functools

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from capsule_drake.anatomy import centerline_extraction as ce
from capsule_drake.anatomy.importer import open_end_loops
from tube_set import TubeSpec, densify, make_tube, ring_faces

RADIUS = 0.02
LENGTH = 0.3
CUT = np.radians(40.0)
FLARE = 0.3


def _radius(z, theta, folds):
    t = np.clip(1.0 - (LENGTH - z) / 0.04, 0.0, 1.0)
    r = RADIUS * (1.0 + FLARE * t * t * (3.0 - 2.0 * t))
    ring = (0.5 + 0.5 * np.cos(2 * np.pi * z / 0.035)) ** 6
    return r * (1.0 - folds * ring * np.abs(np.sin(1.5 * theta)))


@functools.cache
def _tube(folds: float = 0.4):
    """(sections, loops) of the tube: rings every 2 mm, 96 vertices round; the far end's
    ring in the plane through (0, 0, LENGTH) tilted by CUT about y (the start is square)."""
    theta = np.linspace(0.0, 2 * np.pi, 96, endpoint=False)
    v = np.linspace(0.0, 1.0, int(LENGTH / 0.002) + 1)
    # Where each generator meets the cut plane (z - LENGTH = tan(CUT) x), found by damped
    # fixed-point iteration (the flare and the folds make x depend on z).
    def cut(z):
        return LENGTH + np.tan(CUT) * _radius(np.minimum(z, LENGTH), theta, folds) * \
            np.cos(theta)

    z_end = np.full_like(theta, LENGTH)
    for _ in range(400):
        z_end = 0.7 * z_end + 0.3 * cut(z_end)
    assert np.max(np.abs(z_end - cut(z_end))) < 1e-9   # the rim lies in the plane
    z = v[:, None] * z_end[None, :]
    r = _radius(np.minimum(z, LENGTH), theta[None, :], folds)
    points = np.stack([r * np.cos(theta), r * np.sin(theta), z], axis=-1).reshape(-1, 3)
    n, m = len(v), len(theta)
    faces = ring_faces(n, m)
    mesh = trimesh.Trimesh(points, np.array(faces), process=False)
    loops = [mesh.vertices[loop] for loop in open_end_loops(mesh)]
    return ce.MeshSections(mesh), loops


@functools.cache
def _capped_tube(folds: float = 0.4):
    """The same tube, square at z = LENGTH and closed there by a flat disc (rings of the
    end's section shrunk to its centre every 2 mm)."""
    theta = np.linspace(0.0, 2 * np.pi, 96, endpoint=False)
    z = np.linspace(0.0, LENGTH, int(LENGTH / 0.002) + 1)
    r = _radius(z[:, None], theta[None, :], folds)
    wall = np.stack([r * np.cos(theta), r * np.sin(theta), np.broadcast_to(z[:, None], r.shape)],
                    axis=-1)
    shrink = np.linspace(1.0, 0.0, int(RADIUS * (1 + FLARE) / 0.002) + 1)[1:-1]
    disc = np.stack([np.outer(shrink, wall[-1][:, 0]), np.outer(shrink, wall[-1][:, 1]),
                     np.full((len(shrink), len(theta)), LENGTH)], axis=-1)
    grid = np.concatenate([wall, disc])
    n, m = grid.shape[:2]
    points = np.vstack([grid.reshape(-1, 3), [[0.0, 0.0, LENGTH]]])
    faces = ring_faces(n, m)
    centre = n * m
    faces += [[(n - 1) * m + j, (n - 1) * m + (j + 1) % m, centre] for j in range(m)]
    mesh = trimesh.Trimesh(points, np.array(faces), process=False)
    return ce.MeshSections(mesh)


def _line(bulge: float, turn_degrees: float = 0.0):
    """The z axis every 5 mm to the cut, bending `bulge` [m] aside (along x, the cut's
    tilt) over its last 5 cm: the end of a line its rim's open sections pulled astray."""
    z = np.arange(0.02, LENGTH + 1e-9, 0.005)
    u = np.clip((z - (LENGTH - 0.05)) / 0.05, 0.0, 1.0)
    line = np.column_stack([bulge * u ** 2, np.zeros_like(z), z])
    if turn_degrees:
        # the last 5 cm along an arc turning by `turn_degrees` about y
        k = np.radians(turn_degrees) / 0.05
        w = np.maximum(z - (LENGTH - 0.05), 0.0)
        line = np.column_stack([(1.0 - np.cos(k * w)) / k, np.zeros_like(z),
                                np.where(w > 0, LENGTH - 0.05 + np.sin(k * w) / k, z)])
    return line


def _off_axis(line):
    """Largest distance [m] of the line's last 5 cm from the z axis, and of its end from the
    true end."""
    tail = line[line[:, 2] > LENGTH - 0.05]
    return (float(np.max(np.linalg.norm(tail[:, :2], axis=1))),
            float(np.linalg.norm(line[-1] - [0.0, 0.0, LENGTH])))


@pytest.mark.parametrize("folds", [0.0, 0.4])
def test_a_line_pulled_aside_at_an_oblique_flared_rim_is_taken_back_to_the_axis(folds):
    sections, loops = _tube(folds)
    line = _line(0.003)
    assert _off_axis(line)[0] > 0.0029
    made = ce._fitted_open_end(sections, line, RADIUS, 0.005, loops)
    assert made is not line
    off, end = _off_axis(made)
    assert off < 0.0006, off     # measured 0.27 mm (no folds), 0.38 mm (folds)
    assert end < 0.0007, end     # 0.26, 0.50 mm (the line began 3 mm aside)
    # the line behind the stretch is kept
    behind = made[made[:, 2] < LENGTH - 0.04]
    assert np.max(np.abs(behind[:, 0] - np.interp(behind[:, 2], line[:, 2], line[:, 0]))) \
        < 1e-4


def test_the_tubes_parts_are_zero_on_a_tube_of_the_fitted_shape():
    # A tube along the chord with an offset cubic axis and a linear radius: faces on it are
    # at zero distance, faces 1 mm outside at 1 mm (the Newton steps find the foot).
    rng = np.random.default_rng(1)
    x = np.zeros(12)
    x[0:4] = [0.001, 0.002, 0.0015, 0.0]
    x[4:8] = [-0.001, 0.0, 0.001, 0.0005]
    x[8:12] = [0.02, -0.002, 0.0, 0.0]
    poly = np.polynomial.polynomial
    zeta = rng.uniform(-1.0, 0.5, 500)
    phi = rng.uniform(0.0, 2 * np.pi, 500)
    h = 1e-6
    rows = []
    for k in range(500):
        z = zeta[k]
        c = np.array([poly.polyval(z, x[0:4]), poly.polyval(z, x[4:8]),
                      z * ce.OPEN_FIT_LENGTH])
        t = np.array([poly.polyval(z + h, x[0:4]) - poly.polyval(z - h, x[0:4]),
                      poly.polyval(z + h, x[4:8]) - poly.polyval(z - h, x[4:8]),
                      2 * h * ce.OPEN_FIT_LENGTH])
        t /= np.linalg.norm(t)
        _, e1, e2 = ce._plane_basis(t)
        p = c + (poly.polyval(z, x[8:12]) + 0.001 * (k % 2)) * \
            (np.cos(phi[k]) * e1 + np.sin(phi[k]) * e2)
        rows.append([p[0], p[1], p[2] / ce.OPEN_FIT_LENGTH])
    gap = ce._open_tube_parts(x, np.array(rows))
    expected = 0.001 * (np.arange(500) % 2)
    assert np.max(np.abs(gap - expected)) < 2e-6


def test_a_line_that_turns_more_than_the_fit_follows_is_kept():
    sections, loops = _tube(0.0)
    line = _line(0.0, turn_degrees=70.0)
    assert ce._fitted_open_end(sections, line, RADIUS, 0.005, loops) is line


@pytest.mark.parametrize("folds", [0.0, 0.4])
def test_a_line_bulging_before_a_flared_flat_cap_is_taken_back_to_the_axis(folds):
    sections = _capped_tube(folds)
    # the line bulges 3 mm aside over its last 5 cm, but ends on the disc's centre (as
    # `_finish_cap` leaves it)
    line = _line(0.003)
    z = line[:, 2]
    line[:, 0] *= np.clip((LENGTH - z) / 0.015, 0.0, 1.0)
    assert _off_axis(line)[0] > 0.001
    made = ce._fitted_cap_end(sections, line, RADIUS, 0.005)
    assert made is not line
    off, end = _off_axis(made)
    assert off < 0.0005, off
    assert end < 0.0005, end


def test_a_flat_cap_fit_that_misses_the_disc_centre_is_not_taken(monkeypatch):
    sections = _capped_tube(0.0)
    line = _line(0.003)
    line[:, 0] *= np.clip((LENGTH - line[:, 2]) / 0.015, 0.0, 1.0)
    monkeypatch.setattr(ce, "CAP_FIT_AGREE", 0.0)   # (the fit meets it within 4 um)
    assert ce._fitted_cap_end(sections, line, RADIUS, 0.005) is line


@pytest.mark.parametrize("seed, bend", [(0, 40.0),
                                        pytest.param(1, -40.0, marks=pytest.mark.slow)])
def test_a_line_curling_past_a_bend_before_an_oblique_cut_is_taken_back(seed, bend):
    # A tube of the independent set (tests/tube_set.py) that turns by `bend` degrees 1-5 cm
    # before its far end and is straight after it, cut 35 degrees obliquely there; the line
    # given is the true one to 2 cm before the end, then carried on along the bend's
    # curvature (a curl past the bend, 4-5 mm off at its end). The fit's axis (its offsets
    # quadratics at an oblique cut) straightens it: measured 0.17 and 0.05 mm at the end.
    tube = make_tube(TubeSpec("bent_oblique", seed, 0.3, (0.018, 0.022), oblique=(0.0, 35.0),
                              end_bend=(0.0, bend), ends=("open", "open"), mesh="rings",
                              faces=10000))
    mesh = trimesh.Trimesh(tube.mesh.vertices, tube.mesh.faces, process=False)
    loops = [mesh.vertices[loop] for loop in open_end_loops(mesh)]
    truth = tube.truth
    s = ce._arc(truth)
    keep = truth[s <= s[-1] - 0.02][::50]     # every 5 mm
    t = ce._tangents(keep)
    curvature = (t[-1] - t[-5]) / (ce._arc(keep)[-1] - ce._arc(keep)[-5])
    u = np.arange(0.005, 0.0201, 0.005)[:, None]
    line = np.vstack([keep, keep[-1] + u * t[-1] + 0.5 * u * u * curvature])
    assert np.linalg.norm(line[-1] - truth[-1]) > 0.004
    made = ce._fitted_open_end(ce.MeshSections(mesh), line, RADIUS, 0.005, loops)
    assert made is not line
    assert np.linalg.norm(made[-1] - truth[-1]) < 0.0005
    tail = made[ce._arc(made) >= ce._arc(made)[-1] - 0.05]
    assert cKDTree(densify(truth)).query(tail)[0].max() < 0.0005
