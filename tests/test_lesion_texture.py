"""A polyp's surface (anatomy/lesion_texture.py): its texture keeps the polyp's measured
colour contrast on average while adding a vessel network, tiles without a seam, and its
textured mesh is the placed polyp's own surface."""

import cv2
import numpy as np
import pytest
import trimesh

from capsule_drake.anatomy import load_colon
from capsule_drake.anatomy.lesion_geometry import POINTS_AROUND, place, polyp_rgba
from capsule_drake.anatomy.lesion_texture import polyp_texture, textured_revolution
from capsule_drake.anatomy.lesions import DrawnLesion
from capsule_drake.anatomy.params import ColonParams

MUCOSA = (0.86, 0.46, 0.40)


def lab(rgb) -> np.ndarray:
    x = np.asarray(rgb, np.float32).reshape(1, -1, 3)
    return cv2.cvtColor(x, cv2.COLOR_RGB2Lab).reshape(-1, 3)


@pytest.mark.parametrize("diameter", [0.004, 0.010, 0.025])
def test_the_texture_keeps_the_polyps_contrast_and_adds_vessels(diameter):
    """On average the texture is the polyp's colour (delta E under 0.5), so its contrast
    against the mucosa stays the measured 3.3; within it, a brown vessel network covers a
    tenth to a half of the surface, darker than the rest by more than 5 L* units."""
    rgba = polyp_rgba(MUCOSA)
    image, vessels = polyp_texture(rgba, np.pi * diameter, diameter, seed=[1, 2])
    pixels = lab(image.reshape(-1, 3) / 255.0)
    target = lab(rgba[:3])[0]
    assert np.linalg.norm(pixels.mean(axis=0) - target) < 0.5
    assert np.linalg.norm(pixels.mean(axis=0) - lab(MUCOSA)[0]) == pytest.approx(3.3, abs=0.5)
    assert 0.1 <= vessels <= 0.5
    dark = pixels[:, 0] < np.percentile(pixels[:, 0], 100 * vessels)
    assert pixels[~dark, 0].mean() - pixels[dark, 0].mean() > 5.0


def test_the_texture_tiles_without_a_seam():
    """Across the wrap (last column to first, last row to first) neighbouring texels differ
    no more than neighbours inside the image do."""
    image, _ = polyp_texture(polyp_rgba(MUCOSA), 0.03, 0.01, seed=3)
    x = image.astype(float)
    inside_u = np.abs(np.diff(x, axis=1)).mean()
    inside_v = np.abs(np.diff(x, axis=0)).mean()
    assert np.abs(x[:, 0] - x[:, -1]).mean() < 1.3 * inside_u
    assert np.abs(x[0] - x[-1]).mean() < 1.3 * inside_v


@pytest.mark.parametrize("kind", ["0-Is", "0-IIa", "0-Ip"])
def test_the_textured_mesh_is_the_polyps_own_surface(kind):
    colon, _ = load_colon(ColonParams(seed=0))
    polyp = place(colon, DrawnLesion(kind, 9.0, "descending", 0.4, 120.0))
    textured = textured_revolution(polyp.mesh, POINTS_AROUND)
    assert textured.uv.min() >= 0.0 and textured.uv.max() <= 1.0
    welded = trimesh.Trimesh(textured.vertices, textured.faces)    # merges the seam
    assert welded.is_watertight and welded.is_winding_consistent
    assert welded.volume == pytest.approx(polyp.mesh.volume, rel=1e-9)
    assert welded.volume > 0.0          # wound outward, as the polyp's mesh
