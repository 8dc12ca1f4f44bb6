"""An open end finishes on the plane of its loop (anatomy/centerline_extraction.py,
`_reach_loop_plane`), checked on a straight tube cut obliquely, whose axis meets the cut at
(0, 0, length)."""

import sys
from pathlib import Path

import numpy as np

from capsule_drake.anatomy import centerline_extraction as ce
from capsule_drake.anatomy.importer import open_end_loops

sys.path.insert(0, str(Path(__file__).parent))
from test_tube_check_ends import RADIUS, _cut_tube  # noqa: E402

LENGTH = 0.2


def _setup(oblique=45.0):
    mesh = _cut_tube(flare=1.0, oblique=oblique, length=LENGTH)
    loops = [np.asarray(mesh.vertices)[loop] for loop in open_end_loops(mesh)]
    assert len(loops) == 2
    return loops


def _axis(upto):
    z = np.arange(0.0, upto + 1e-9, 0.005)
    return np.column_stack([np.zeros_like(z), np.zeros_like(z), z])


def test_a_line_short_of_an_oblique_cut_is_taken_to_the_axis_crossing():
    loops = _setup()
    line = _axis(LENGTH - 0.007)
    made = ce._reach_loop_plane(line, RADIUS, 0.005, loops)
    assert np.linalg.norm(made[-1] - [0.0, 0.0, LENGTH]) < 5e-4   # the rim's loop is polygonal
    assert np.abs(made[:, :2]).max() < 1e-9                          # along the tangent


def test_a_line_past_the_cut_is_cut_at_it():
    loops = _setup()
    line = _axis(LENGTH + 0.008)
    made = ce._reach_loop_plane(line, RADIUS, 0.005, loops)
    assert np.linalg.norm(made[-1] - [0.0, 0.0, LENGTH]) < 5e-4
    assert len(made) < len(line) + 1


def test_a_line_on_the_plane_or_leading_off_the_loop_is_left_as_it_is():
    loops = _setup()
    on = _axis(LENGTH)
    assert ce._reach_loop_plane(on, RADIUS, 0.005, loops) is on
    # heading for the rim, 0.6 radii off the axis: the crossing is not well inside the loop
    astray = _axis(LENGTH - 0.01) + [0.6 * RADIUS, 0.0, 0.0]
    assert ce._reach_loop_plane(astray, RADIUS, 0.005, loops) is astray
