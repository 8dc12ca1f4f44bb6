"""Anterior abdominal skin of a supine patient, and a coarse torso mesh for display.

The torso cross-section at height y is an ellipse centred on the flank line: half width
`half_width`, reaching the skin height h(y) on top (the anterior skin) and the table below.
h(y) is a smooth dome: `depth_at_umbilicus` at the umbilicus, falling quadratically to the
pubis and the xiphoid values.
"""

import numpy as np
import trimesh

from .params import AbdomenParams


class Abdomen:
    """The anterior abdominal wall, z = skin_height(x, y) [m] above the table."""

    display_rgba = None  # the torso's colour in Meshcat: the station's skin colour

    def __init__(self, params: AbdomenParams):
        self.params = params

    def midline_height(self, y) -> np.ndarray:
        """Skin height on the midline x = 0 [m]."""
        p = self.params
        y = np.asarray(y, dtype=float)
        below = (y - p.umbilicus_y) / (p.pubis_y - p.umbilicus_y)
        above = (y - p.umbilicus_y) / (p.xiphoid_y - p.umbilicus_y)
        drop = np.where(y < p.umbilicus_y,
                        (p.depth_at_umbilicus - p.depth_at_pubis) * below**2,
                        (p.depth_at_umbilicus - p.depth_at_xiphoid) * above**2)
        return np.maximum(p.depth_at_umbilicus - drop, p.flank_height + 0.01)

    def skin_height(self, x, y) -> np.ndarray:
        """Height of the anterior skin above the table at (x, y) [m]."""
        p = self.params
        x = np.asarray(x, dtype=float)
        u = np.clip(x / p.half_width, -1.0, 1.0)
        return p.flank_height + (self.midline_height(y) - p.flank_height) * np.sqrt(1.0 - u**2)

    def depth(self, points) -> np.ndarray:
        """Depth of world points below the anterior skin [m] (negative above it)."""
        points = np.atleast_2d(points)
        return self.skin_height(points[:, 0], points[:, 1]) - points[:, 2]

    def torso_mesh(self, rings: int = 24, around: int = 32) -> trimesh.Trimesh:
        """Closed coarse torso surface (outward normals) for semi-transparent display."""
        p = self.params
        y = np.linspace(p.torso_y_min, p.torso_y_max, rings)
        phi = np.linspace(0.0, 2.0 * np.pi, around, endpoint=False)
        top = self.midline_height(y)[:, None] - p.flank_height
        x = p.half_width * np.cos(phi)[None, :] * np.ones_like(top)
        up = np.sin(phi)[None, :]
        z = p.flank_height + np.where(up > 0.0, top * up, p.flank_height * up)
        verts = np.stack([x, np.broadcast_to(y[:, None], x.shape), z], axis=-1).reshape(-1, 3)
        i = np.arange(rings - 1)[:, None]
        j = np.arange(around)[None, :]
        a, b = i * around + j, i * around + (j + 1) % around
        c, d = a + around, b + around
        faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                                np.stack([b, d, c], -1).reshape(-1, 3)])
        n = len(verts)
        verts = np.concatenate([verts, [[0.0, y[0], p.flank_height],
                                        [0.0, y[-1], p.flank_height]]])
        ring0 = np.arange(around)
        ring1 = (rings - 1) * around + ring0
        caps = np.concatenate([
            np.stack([np.full(around, n), (ring0 + 1) % around, ring0], -1),
            np.stack([np.full(around, n + 1), ring1, (rings - 1) * around
                      + (ring0 + 1) % around], -1)])
        mesh = trimesh.Trimesh(verts, np.concatenate([faces, caps]), process=False)
        if mesh.volume < 0.0:
            mesh.invert()
        return mesh
