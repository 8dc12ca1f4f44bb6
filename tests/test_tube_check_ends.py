"""The branch check (anatomy/tube_check.py, `check_tube`) beyond a centreline's ends: an
oblique, flared open end's far rim reaches past the line's end along its axis and wider
than the radius held from the sections behind it, and is not a branch; wall that goes on
along the axis past the end is."""

import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from capsule_drake.anatomy.tube_check import NotATubeError, check_tube

sys.path.insert(0, str(Path(__file__).parent))
from tube_set import ring_faces  # noqa: E402

RADIUS = 0.02
LENGTH = 0.15


def _cut_tube(flare=1.5, oblique=60.0, length=LENGTH, around=64, rings=160):
    """An open tube along +z of RADIUS, widened linearly to `flare` times over its last 4 cm
    and cut at its end (z = `length`) by a plane through (0, 0, `length`) tilted `oblique` degrees about y."""
    theta = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
    slope = np.tan(np.radians(oblique))
    vertices = []
    for k in np.linspace(0.0, 1.0, rings):
        z0 = k * length
        # the rim's z at each angle, reached by the last ring; earlier rings sheared less
        widen = 1.0 + (flare - 1.0) * np.clip((z0 - (length - 0.04)) / 0.04, 0.0, 1.0)
        rho = RADIUS * widen
        z = z0 + k ** 8 * slope * rho * np.cos(theta)
        vertices.append(np.column_stack([rho * np.cos(theta), rho * np.sin(theta), z]))
    vertices = np.concatenate(vertices)
    return trimesh.Trimesh(vertices, ring_faces(rings, around), process=False)


def _line(upto):
    s = np.arange(0.0, upto + 1e-9, 0.005)
    return s, np.column_stack([np.zeros_like(s), np.zeros_like(s), s]), np.full(len(s), RADIUS)


def test_an_oblique_flared_rim_beyond_the_line_end_is_not_a_branch():
    mesh = _cut_tube()
    far = np.linalg.norm(mesh.vertices - [0.0, 0.0, LENGTH], axis=1).max()
    assert far > 2.0 * RADIUS + 0.005   # farther from the end than the check's reach
    check_tube(mesh, *_line(LENGTH))   # 2.7 % of the wall was refused as a branch before


def test_wall_going_on_along_the_axis_past_the_line_end_is_refused():
    with pytest.raises(NotATubeError, match="branch"):
        check_tube(_cut_tube(flare=1.0, oblique=0.0, length=0.3), *_line(0.15))
