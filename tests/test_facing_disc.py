"""A flat cap's end found when the line arrives astray (anatomy/centerline_extraction.py,
`_finish_cap` and `_facing_disc`): on a straight tube closed by a disc, with a ring fold
just before it, a line that leaves the axis and meets the disc near its rim at 37 degrees
is ended at the disc's centre."""

import numpy as np
import trimesh

from capsule_drake.anatomy import centerline_extraction as ce

RADIUS = 0.025
LENGTH = 0.3


def _capped_tube():
    z = np.arange(0.0, LENGTH + 1e-9, 0.002)
    fold = 0.15 * np.exp(-0.5 * ((z - (LENGTH - 0.02)) / 0.002) ** 2)   # a ring fold 2 cm before
    profile = np.column_stack([RADIUS * (1.0 - fold), z])
    disc = np.column_stack([np.linspace(RADIUS, 0.0, 14)[1:], np.full(13, LENGTH)])
    mesh = trimesh.creation.revolve(np.vstack([profile, disc]), sections=96)
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, 0.002)
    return trimesh.Trimesh(vertices, faces)


def _astray_line(tilt=np.radians(37.0)):
    z = np.arange(0.02, 0.24 + 1e-9, 0.005)
    straight = np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    # then an arc of radius R turning toward +x by `tilt`
    bend = 0.08
    a = np.linspace(0.0, tilt, 12)[1:]
    arc = np.column_stack([bend * (1.0 - np.cos(a)), np.zeros_like(a), 0.24 + bend * np.sin(a)])
    return np.vstack([straight, arc])


def test_a_line_meeting_the_disc_near_its_rim_ends_at_its_centre():
    mesh = _capped_tube()
    sections = ce.MeshSections(mesh)
    line = _astray_line()
    assert line[-1][2] < LENGTH and np.hypot(*line[-1][:2]) > 0.4 * RADIUS
    made = ce._finish_cap(sections, line, RADIUS, 0.005)
    assert made is not line
    assert np.linalg.norm(made[-1] - [0.0, 0.0, LENGTH]) < 1e-3
