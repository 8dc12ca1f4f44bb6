"""An open end's last stretch settled on its own sections (anatomy/centerline_extraction.py,
`_settle_open_end`), checked on a closed-form shape: a straight tube flared over its last
4 cm, open at both ends, whose axis is known, from a line that bulges off it before the rim."""

import numpy as np
import pytest
import trimesh

from capsule_drake.anatomy import centerline_extraction as ce
from capsule_drake.anatomy.importer import open_end_loops

RADIUS = 0.015
LENGTH = 0.3
FLARE = 0.04
"""The last FLARE [m] widen to 1.5 times the radius (quadratically): the flared end."""


def _flared_tube():
    z = np.arange(0.0, LENGTH + 1e-9, 0.002)
    rho = RADIUS * (1.0 + 0.5 * np.clip((z - (LENGTH - FLARE)) / FLARE, 0.0, 1.0) ** 2)
    mesh = trimesh.creation.revolve(np.column_stack([rho, z]), sections=96)
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, 0.002)
    return trimesh.Trimesh(vertices, faces)


@pytest.mark.parametrize("bulge", [0.0, 0.005])
def test_a_line_bulging_before_a_flared_rim_settles_on_the_axis(bulge):
    """A line on the axis but for a bulge of `bulge` [m] over the 4 cm before the rim (its
    end on the rim's plane, at the centre): the settled stretch is within 0.3 mm of the
    axis, its end within 0.3 mm of the loop's centre, and its sections centred on it."""
    mesh = _flared_tube()
    sections = ce.MeshSections(mesh)
    loops = [np.asarray(mesh.vertices)[loop] for loop in open_end_loops(mesh)]
    assert len(loops) == 2
    z = np.arange(0.02, LENGTH + 1e-9, 0.005)
    x = bulge * np.sin(np.pi * np.clip((z - (LENGTH - 0.045)) / 0.04, 0.0, 1.0))
    line = np.column_stack([x, np.zeros_like(z), z])
    settled = ce._settle_open_end(sections, line, RADIUS, 0.005, loops)
    assert settled is not line
    assert np.abs(settled[:, :2]).max() < 3e-4
    assert np.linalg.norm(settled[-1] - [0.0, 0.0, LENGTH]) < 3e-4
    assert ce.end_residual(sections, settled, RADIUS) < 3e-4
    if bulge:   # the bulge is what the end's sections see: they are off-centre by mm
        assert ce.end_residual(sections, line, RADIUS) > 1e-3


def test_a_line_too_short_to_settle_is_returned_as_it_is():
    """A line shorter than three settled stretches is left alone."""
    mesh = _flared_tube()
    sections = ce.MeshSections(mesh)
    loops = [np.asarray(mesh.vertices)[loop] for loop in open_end_loops(mesh)]
    line = np.column_stack([np.zeros(20), np.zeros(20), np.linspace(LENGTH - 0.1, LENGTH, 20)])
    assert ce._settle_open_end(sections, line, RADIUS, 0.005, loops) is line
