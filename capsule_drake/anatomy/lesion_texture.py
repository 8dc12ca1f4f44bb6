"""A polyp's surface: a seeded texture of the adenoma's vascular and surface pattern, and its
mesh with texture coordinates (what the capsule camera renders; anatomy/lesion_geometry.py
places the polyp).

The pattern is the NICE classification's type 2 (adenoma): brown vessels surrounding oval or
tubular white structures (S: the classification's published descriptors; docs/sources.md
section 3.4). Drawn as a cellular pattern: cells around random seed points (a periodic
Voronoi tiling, stretched along the polyp into tubular structures), their interiors paler
(the white structures), their borders a brown vessel network, over a fine grain. Sizes
(cells 0.35 mm across, vessels 0.05 mm wide, stretched 1.6 x) are assumptions (U): at the
capsule camera's resolution (about 0.1-0.2 mm per pixel at 10-20 mm) the network reads as a
brownish mottle rather than resolved pits. The texture's mean colour is then moved in CIELAB
onto the polyp's colour (`polyp_rgba`: delta E 3.3 browner than the mucosa, the measured
contrast), so the pattern adds texture without changing that contrast.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .lesion_geometry import lab_shift
from .mesh import TexturedMesh
from .texture import periodic_field

TEXELS = 256
"""Texture size (square) of one polyp."""
CELL_M = 0.00035
"""Mean spacing of the surface structures (m; U)."""
VESSEL_M = 0.00005
"""Width of the vessels around them (m; U)."""
STRETCH = 1.6
"""Tubular structures: cells this much longer along the polyp (v) than around it (U)."""
VESSEL_LAB = (-14.0, 4.0, 10.0)
"""A vessel's colour against the polyp's in CIELAB: darker and browner (NICE type 2's
"brown vessels"; the amount: U)."""
WHITE_LAB = (6.0, -3.0, -3.0)
"""A structure's centre against the polyp's colour: paler (its "white structures"; U)."""


def mean_lab(rgb: np.ndarray) -> np.ndarray:
    """Mean CIELAB colour of an sRGB image in [0, 1] (float) or uint8."""
    x = np.asarray(rgb, np.float32)
    if np.asarray(rgb).dtype == np.uint8:
        x = x / 255.0
    return cv2.cvtColor(x.reshape(1, -1, 3), cv2.COLOR_RGB2Lab).reshape(-1, 3).mean(axis=0)


def polyp_texture(rgba, size_u: float, size_v: float, seed) -> tuple[np.ndarray, float]:
    """(image (TEXELS, TEXELS, 3) uint8 sRGB, its vessel share) of a polyp of colour `rgba`
    whose surface measures `size_u` around and `size_v` along (m), periodic both ways."""
    rng = np.random.default_rng(seed)
    n = TEXELS
    # Texel sizes (m) around (x) and along (y), and seed points in a unit torus scaled so
    # that their spacing is CELL_M across and STRETCH x CELL_M along.
    du, dv = size_u / n, size_v / n
    count = max(int(size_u * size_v / (CELL_M * CELL_M * STRETCH)), 8)
    points = rng.uniform(0.0, 1.0, (count, 2)) * [size_u, size_v / STRETCH]
    tiles = [points + [i * size_u, j * size_v / STRETCH]
             for i in (-1, 0, 1) for j in (-1, 0, 1)]
    tree = cKDTree(np.concatenate(tiles))
    x, y = np.meshgrid((np.arange(n) + 0.5) * du, (np.arange(n) + 0.5) * dv / STRETCH)
    distance, _ = tree.query(np.column_stack([x.ravel(), y.ravel()]), k=2)
    f1, f2 = distance[:, 0].reshape(n, n), distance[:, 1].reshape(n, n)
    vessel = np.clip(1.0 - (f2 - f1) / VESSEL_M, 0.0, 1.0)       # at cell borders
    centre = np.clip(1.0 - f1 / (0.5 * CELL_M), 0.0, 1.0)         # toward cell centres
    base = np.asarray(rgba[:3], np.float32)[None, None, :]
    colour = np.broadcast_to(base, (n, n, 3)).copy()
    colour = colour + centre[..., None] * (lab_shift(colour, WHITE_LAB) - colour)
    colour = colour + (0.8 * vessel)[..., None] * (lab_shift(colour, VESSEL_LAB) - colour)
    colour *= (1.0 + 0.03 * periodic_field(rng, (n, n), 0.7))[..., None]
    colour = np.clip(colour, 0.0, 1.0).astype(np.float32)
    # The mean colour onto the polyp's own.
    offset = mean_lab(base) - mean_lab(colour)
    colour = lab_shift(colour, offset)
    return np.round(colour * 255.0).astype(np.uint8), float(np.mean(vessel >= 0.5))


def textured_revolution(mesh, around: int) -> TexturedMesh:
    """The polyp mesh `mesh` (anatomy/lesion_geometry.py `revolve`'s layout after placing:
    rings of `around` vertices from its sunk base to its top, then the tip and the bottom's
    centre) with texture coordinates: u around (the seam's column doubled at u = 1), v from
    the base (0) to the tip (1). Positions and normals are the mesh's own."""
    vertices = np.asarray(mesh.vertices)
    normals = np.asarray(mesh.vertex_normals)
    rings = (len(vertices) - 2) // around
    tip, bottom = rings * around, rings * around + 1
    column = np.r_[np.arange(around), 0]
    source = (np.arange(rings)[:, None] * around + column[None, :]).ravel()
    source = np.concatenate([source, [tip, bottom]])
    u = np.tile(np.arange(around + 1) / around, rings)
    v = np.repeat(np.arange(rings) / rings, around + 1)
    uv = np.column_stack([np.concatenate([u, [0.5, 0.5]]), np.concatenate([v, [1.0, 0.0]])])
    m = around + 1
    i = np.arange(rings - 1)[:, None]
    j = np.arange(around)[None, :]
    a, b = i * m + j, i * m + j + 1
    c, d = a + m, b + m
    t_tip, t_bottom = rings * m, rings * m + 1
    faces = np.concatenate([
        np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3),
        np.stack([(rings - 1) * m + j[0], (rings - 1) * m + j[0] + 1,
                  np.full(around, t_tip)], -1),
        np.stack([j[0] + 1, j[0], np.full(around, t_bottom)], -1)])
    positions = vertices[source]
    # Wound as the mesh is (outward): flip all if the first side triangle is not.
    f = positions[faces[0]]
    if np.cross(f[1] - f[0], f[2] - f[0]) @ normals[source[faces[0]]].sum(axis=0) < 0.0:
        faces = faces[:, ::-1]
    return TexturedMesh(positions, normals[source], uv, faces, np.zeros(len(positions)))
