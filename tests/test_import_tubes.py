"""The colon import on tubes it did not make (tests/tube_set.py: random smooth curves,
varying radius with folds, open, hemispherical and flat ends, uniform, jittered and
Delaunay triangulations, metres and millimetres): the centreline within 2 mm of the truth
everywhere, ends included, and stable; what is not one tube refused in one line; the
capsule's start checked inside the lumen and away from open ends."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from capsule_drake.anatomy.importer import MeshImportError
from tube_set import (TUBES, centreline_errors, densify, make_tube, perturbed, y_branch)

FAST = ("plain_open", "ripple_hemi_mm", "small_coarse")
"""Small tubes with open and capped ends, in metres and millimetres: the fast loop's."""
# The 220k-face tube's stability (0.05 mm when measured) is not in the default run: two
# imports of it take ~55 s. Add "huge_mm" here to check it.
STABILITY_SLOW = ("long_ripple", "mid_jitter_flat")

_IMPORTS = {}


def _import(name, folder, perturb=False):
    """(tube, ImportedWall) of the named tube, imported from a file once per session."""
    from capsule_drake.anatomy.imported import import_colon_mesh

    key = (name, perturb)
    if key not in _IMPORTS:
        tube = make_tube(next(spec for spec in TUBES if spec.name == name))
        path = tube.write(folder)
        if perturb:
            path = path.with_name(f"{name}_perturbed.{tube.spec.fmt}")
            perturbed(tube.mesh).export(path)
        _IMPORTS[key] = tube, import_colon_mesh(path, tube.scale)
    return _IMPORTS[key]


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("tubes")


def _marked(names, slow_names):
    return [pytest.param(n, marks=pytest.mark.slow) if n in slow_names else n for n in names]


ALL = [spec.name for spec in TUBES]
SLOW = [n for n in ALL if n not in FAST]


@pytest.mark.parametrize("name", _marked(ALL, SLOW))
def test_centreline_is_within_2_mm_of_the_truth_with_its_length_and_radius(name, folder):
    """Both ways: every recovered point within 2 mm of the true curve, every true point
    (a cap's straight continuation to its wall included) within 2 mm of the recovered line.
    Measured at most 0.07-0.75 mm over the set, both ways (anatomy/centerline_extraction.py).
    The length within 2 mm (measured 0.2 mm); the radius (the section's equal-area
    circle's) within 1.5 % of the truth's (median; measured 0.1-0.6 %), 5 % (95th
    percentile; measured 0.1-1.7 %), away from the ends."""
    tube, wall = _import(name, folder)
    cl = wall.centerline
    to_truth, to_recovered = centreline_errors(tube.truth, cl.points)
    assert to_truth < 0.002 and to_recovered < 0.002, (to_truth, to_recovered)
    assert cl.length == pytest.approx(tube.truth_length, abs=0.002)
    _, nearest = cKDTree(tube.truth).query(cl.points)
    truth_radius = tube.truth_radius[nearest]
    r = float(np.median(truth_radius))
    inside = (cl.s > 1.5 * r) & (cl.s < cl.length - 1.5 * r)
    error = np.abs(cl.radius[inside] / truth_radius[inside] - 1.0)
    assert np.median(error) < 0.015 and np.percentile(error, 95) < 0.05


@pytest.mark.parametrize("name", _marked(("small_coarse", "ripple_hemi_mm") + STABILITY_SLOW,
                                         ("ripple_hemi_mm",) + STABILITY_SLOW))
def test_centreline_is_stable_under_a_millionth_of_noise(name, folder):
    """The same mesh, its vertices moved at random by 1e-6 of its size: the centreline
    within 0.2 mm of the first (measured at most 0.05 mm; the largest tube is decimated
    from 220k to 150k faces, and its decimation differs between the two)."""
    _, first = _import(name, folder)
    _, second = _import(name, folder, perturb=True)
    a, b = first.centerline.points, second.centerline.points
    apart = max(cKDTree(densify(a)).query(b)[0].max(), cKDTree(densify(b)).query(a)[0].max())
    assert apart < 2e-4, apart
    assert second.centerline.length == pytest.approx(first.centerline.length, abs=2e-4)


def _wavy_sheet(n=60):
    x, y = np.meshgrid(np.linspace(0.0, 0.3, n), np.linspace(0.0, 0.2, n))
    z = 0.03 * np.sin(2 * np.pi * x / 0.1) * np.cos(2 * np.pi * y / 0.15)
    index = np.arange(n * n).reshape(n, n)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([b, d, c], -1).reshape(-1, 3)])
    return trimesh.Trimesh(np.column_stack([x.ravel(), y.ravel(), z.ravel()]), faces)


def _half_pipe():
    theta, x = np.meshgrid(np.linspace(0.0, np.pi, 30), np.linspace(0.0, 0.4, 80))
    vertices = np.column_stack([x.ravel(), 0.03 * np.cos(theta.ravel()),
                                -0.03 * np.sin(theta.ravel())])
    index = np.arange(80 * 30).reshape(80, 30)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([b, d, c], -1).reshape(-1, 3)])
    return trimesh.Trimesh(vertices, faces)


NOT_TUBES = {
    "sphere": (lambda: trimesh.creation.icosphere(subdivisions=4, radius=0.05), "closed blob"),
    "ellipsoid": (lambda: trimesh.creation.icosphere(subdivisions=4, radius=1.0)
                  .apply_scale([0.09, 0.03, 0.03]), "closed blob"),
    "wavy_sheet": (_wavy_sheet, "open sheet"),
    "half_pipe": (_half_pipe, "open sheet"),
    "y_closed": (y_branch, "branching mesh"),
    "y_open": (lambda: y_branch(open_ends=True), "3 open ends"),
}


@pytest.mark.parametrize("name", _marked(list(NOT_TUBES), ("y_closed",)))
def test_what_is_not_a_tube_is_refused_in_one_line(name, tmp_path):
    """A sphere and a 3:1 ellipsoid (centreline 2.0 and 6.0 lumen radii long), a wavy
    sheet and a half pipe (no plane section closed around their middle line), a Y closed
    at its three ends (its first line cuts across the junction) and one open at them
    (three open ends)."""
    from capsule_drake.anatomy.imported import import_colon_mesh

    make, words = NOT_TUBES[name]
    path = tmp_path / f"{name}.stl"
    make().export(path)
    with pytest.raises(MeshImportError) as error:
        import_colon_mesh(path)
    message = str(error.value)
    assert "\n" not in message and message.startswith(f"{path}: not a tube:")
    assert words in message, message


@pytest.mark.slow
def test_a_y_with_a_short_arm_is_refused_as_a_branch(tmp_path):
    """Two long arms and a 7 cm one: the centreline follows the long ones; the short arm's
    wall lies up to 9.6 cm from it."""
    from capsule_drake.anatomy.imported import import_colon_mesh

    path = tmp_path / "y.stl"
    y_branch(arms=(0.25, 0.25, 0.07)).export(path)
    with pytest.raises(MeshImportError, match="branch the line does not run through"):
        import_colon_mesh(path)


def test_the_command_refuses_a_sphere_with_one_line(tmp_path, capsys):
    from capsule_drake.app.cli import main

    path = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=3, radius=0.05).export(path)
    assert main(["import-colon", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "not a tube: a closed blob" in error[0]


# --- The capsule's start -----------------------------------------------------------------

def _capsule():
    from capsule_drake.capsule.model import capsule_model

    model = capsule_model()
    return model.radius, 2.0 * model.half_length


def test_the_start_is_checked_inside_an_imported_tube(folder):
    """On an imported open tube (ends open at s = 0 and L): the capsule must sit a capsule
    radius inside an open end; on one with a flat cap, its tip may reach the cap."""
    from capsule_drake.anatomy.imported import ImportedColon, write_import
    from capsule_drake.anatomy.start_check import check_start

    radius, length = _capsule()
    for name in ("plain_open", "flat_caps"):
        _, wall = _import(name, folder)
        write_import(wall, folder / f"{name}_import")
        colon = ImportedColon.load(folder / f"{name}_import")
        end = "open end" if name == "plain_open" else "closed end"
        low = 0.5 * length + (radius if name == "plain_open" else 0.0)
        check_start(colon, low + 0.001, radius, length)
        check_start(colon, colon.centerline.length - low - 0.001, radius, length)
        with pytest.raises(ValueError) as error:
            check_start(colon, 0.002, radius, length)
        message = str(error.value)
        assert "\n" not in message and message.startswith("capsule.start_s 0.002 m:")
        assert f"stick out of the colon's {end} at s = 0 (needs >= {low:.3f} m)" in message
        with pytest.raises(ValueError, match=f"{end} at s = "):
            check_start(colon, colon.centerline.length - 0.01, radius, length)


def test_the_start_is_refused_in_a_lumen_narrower_than_the_capsule(tmp_path):
    """A tube 4.5 mm in radius (the capsule is 5.8 mm): the capsule would start inside its
    wall."""
    from capsule_drake.anatomy.imported import ImportedColon, write_import, import_colon_mesh
    from capsule_drake.anatomy.start_check import check_start
    from tube_set import TubeSpec

    tube = make_tube(TubeSpec("thin", 21, 0.2, (0.0045, 0.0045), tightest_bend=6.0,
                              faces=8000))
    write_import(import_colon_mesh(tube.write(tmp_path), tube.scale), tmp_path / "thin")
    colon = ImportedColon.load(tmp_path / "thin")
    radius, length = _capsule()
    with pytest.raises(ValueError) as error:
        check_start(colon, 0.1, radius, length)
    message = str(error.value)
    assert "\n" not in message and "inside the wall" in message
    assert "the capsule 5.8 mm" in message


def test_the_default_start_is_accepted_in_the_procedural_colon():
    """The Default scenario (start_s 0.05) and the ends of the procedural colon (closed
    caps: the capsule's tip may reach them, not pass them)."""
    from capsule_drake.anatomy import load_colon
    from capsule_drake.anatomy.start_check import check_start
    from capsule_drake.scenario import load_scenario

    scenario = load_scenario(name="Default")
    colon, _ = load_colon(scenario.colon)
    radius, length = _capsule()
    check_start(colon, scenario.capsule.start_s, radius, length)
    with pytest.raises(ValueError, match="closed end at s = 0"):
        check_start(colon, 0.01, radius, length)


@pytest.mark.slow
def test_every_shipped_scenario_starts_inside_its_colon():
    """diagrams/default.yaml, every scenario (the ex vivo segment's included)."""
    from pathlib import Path

    from capsule_drake.anatomy import load_colon
    from capsule_drake.anatomy.start_check import check_start
    from capsule_drake.scenario import load_scenario, scenario_names

    radius, length = _capsule()
    for name in scenario_names(Path(__file__).parent.parent / "diagrams" / "default.yaml"):
        scenario = load_scenario(name=name)
        colon, _ = load_colon(scenario.colon)
        check_start(colon, scenario.capsule.start_s, radius, length)
