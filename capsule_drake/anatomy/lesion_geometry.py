"""Polyps placed on a built colon's wall, each a mesh of its own (anatomy/lesions.py draws
them; the camera sees each with a render label of its own, the capsule touches them).

A polyp stands on the wall where its segment, its place along it and its angle around the
lumen put it (the angle from the floor, the side gravity pulls toward, about the
centreline's tangent), its axis along the wall's inward normal there, its shape draped on
the wall (every height counted from the mucosa under it, across the lumen's curve and a
fold's slope) and its base sunk a millimetre into the wall. Shapes, by the
Paris classification (docs/sources.md section 3.4), each a surface of revolution:
- 0-Is (sessile): a half-ellipsoid, base diameter d, height max(d / 2, 2.5 mm) but at most
  0.9 d: the Paris cut between 0-Is and 0-IIa is a height of 2.5 mm.
- 0-IIa (flat elevated): a plateau (a super-ellipse profile) of height min(0.3 d, 2 mm).
- 0-Ip (pedunculated): a head (an ellipsoid d wide, 0.9 d tall) on a stalk 0.35 d thick
  and 0.8 d long. It stands straight out of the wall (U: a real stalk bends and sways).
Diverticula are pouches cut into the wall itself (anatomy/diverticula.py).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import trimesh

from .lesions import DrawnLesion
from .mesh import cap_faces, tube_faces

ADENOMA_LAB_SHIFT = (-2.4, 1.6, 1.6)
"""A polyp's colour against the mucosa's, in CIELAB (L*, a*, b*): darker and browner (the
NICE classification's adenoma, "browner relative to background"; the direction: S), by a
colour difference of 3.3 (the measured mean contrast of adenomas against the mucosa
around them, delta E 3.3 +- 1.8, hyperplastic polyps 1.3; docs/sources.md section 3.4)."""
PARIS_IS_HEIGHT = 0.0025
"""The Paris classification's height between 0-Is and 0-IIa (m; about a closed biopsy
forceps' cup)."""
POINTS_AROUND = 24
SINK = 0.001
"""How far a polyp's base reaches into the wall (m): no seam shows where they meet."""


@dataclasses.dataclass(frozen=True)
class PlacedPolyp:
    """A polyp on the wall: where it stands and its mesh in the world frame."""

    index: int                 # its place in the patient's list of lesions
    lesion: DrawnLesion
    s: float                   # arc length of its foot on the centreline (m)
    theta: float               # angle around the centreline (rad, the centreline's frame)
    base_W: np.ndarray         # centre of its base on the wall (m)
    axis_W: np.ndarray         # unit inward normal: the way it stands
    height: float              # from the wall to its top (m)
    mesh: trimesh.Trimesh      # closed, in the world frame

    @property
    def top_W(self) -> np.ndarray:
        return self.base_W + self.height * self.axis_W


def profile(kind: str, diameter: float) -> tuple[np.ndarray, np.ndarray, float]:
    """(radius (K,), height (K,), top height) of the shape's outline from its base (z = 0)
    to its tip (r = 0), in metres."""
    a = 0.5 * diameter
    if kind == "0-Is":
        h = min(max(0.5 * diameter, PARIS_IS_HEIGHT), 0.9 * diameter)
        t = np.linspace(0.0, 0.5 * np.pi, 16)
        return a * np.cos(t), h * np.sin(t), h
    if kind == "0-IIa":
        h = min(0.3 * diameter, 0.8 * PARIS_IS_HEIGHT)
        t = np.linspace(0.0, 0.5 * np.pi, 16)
        return a * np.cos(t) ** 0.5, h * np.sin(t) ** 0.5, h
    if kind == "0-Ip":
        stalk, length = 0.175 * diameter, 0.8 * diameter
        c = 0.45 * diameter                      # the head's half height
        # The head's lower half from where it is as wide as the stalk, then its upper half.
        lower = np.arcsin(np.clip(stalk / a, 0.0, 1.0))
        t = np.concatenate([np.linspace(-0.5 * np.pi + lower, 0.0, 8)[:-1],
                            np.linspace(0.0, 0.5 * np.pi, 12)])
        z0 = length + c * np.cos(lower)          # the head's centre height
        r = np.concatenate([[stalk], a * np.cos(t)])
        z = np.concatenate([[0.0], z0 + c * np.sin(t)])
        return r, z, float(z[-1])
    raise ValueError(f"no shape for lesion kind {kind!r}")


def revolve(radius, height, sink: float, around: int = POINTS_AROUND) -> trimesh.Trimesh:
    """The closed surface of revolution of the outline (radius, height) about z, extended
    `sink` below z = 0 (into the wall) and closed by a flat bottom and a point at its tip."""
    r = np.concatenate([[radius[0]], radius])
    z = np.concatenate([[-sink], height])
    r[-1] = 0.0
    k = len(r)
    phi = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
    rings = np.stack([np.outer(r[:-1], np.cos(phi)), np.outer(r[:-1], np.sin(phi)),
                      np.repeat(z[:-1, None], around, axis=1)], axis=-1).reshape(-1, 3)
    tip, bottom = (k - 1) * around, (k - 1) * around + 1
    vertices = np.vstack([rings, [[0.0, 0.0, z[-1]], [0.0, 0.0, -sink]]])
    faces = np.concatenate([tube_faces(k - 1, around),
                            cap_faces((k - 2) * around, around, tip, at_start=False),
                            cap_faces(0, around, bottom, at_start=True)])
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.fix_normals()   # outward (the wall's helpers wind theirs toward its centreline)
    return mesh


def lab_shift(rgb, shift) -> np.ndarray:
    """sRGB colours in [0, 1] (any shape ending in 3) moved by `shift` (per colour, or
    broadcast) in CIELAB, clipped back into [0, 1]."""
    rgb = np.asarray(rgb, np.float32)
    lab = cv2.cvtColor(rgb.reshape(1, -1, 3), cv2.COLOR_RGB2Lab)
    lab += np.asarray(shift, np.float32).reshape(1, -1, 3)
    return np.clip(cv2.cvtColor(lab, cv2.COLOR_Lab2RGB).reshape(rgb.shape), 0.0, 1.0)


def polyp_rgba(mucosa_rgb) -> tuple[float, float, float, float]:
    """The diffuse colour of a polyp on mucosa of colour `mucosa_rgb` (sRGB in [0, 1]):
    shifted by ADENOMA_LAB_SHIFT in CIELAB."""
    out = lab_shift(np.reshape(mucosa_rgb, 3), ADENOMA_LAB_SHIFT)
    return (float(out[0]), float(out[1]), float(out[2]), 1.0)


def floor_angle(colon, s: float) -> float:
    """The angle theta (the centreline's frame at s) of the lumen's floor: the direction
    gravity (-z) takes in the plane across the lumen."""
    t, n, b = colon.centerline.frame_at(s)
    down = np.array([0.0, 0.0, -1.0])
    across = down - (down @ t) * t
    if np.linalg.norm(across) < 1e-9:      # the lumen runs vertically: any angle is the floor
        return 0.0
    return float(np.arctan2(across @ b, across @ n))


@dataclasses.dataclass(frozen=True)
class WallSite:
    """Where a lesion sits on the wall: its arc length, its angle and the frame there."""

    s: float
    theta: float            # the centreline's frame at s
    base_W: np.ndarray      # the point on the wall
    axis_W: np.ndarray      # the wall's unit inward normal there
    tangent_W: np.ndarray   # the centreline's tangent at s
    normal_W: np.ndarray    # the centreline frame's normal at s


def segment_s(colon, lesion: DrawnLesion) -> float:
    """The arc length of `lesion`'s place along its segment (1 cm kept from the ends, or a
    quarter of a short segment)."""
    start, end = colon.centerline.segment_ranges()[lesion.segment]
    margin = min(0.01, 0.25 * (end - start))
    return float(start + margin + lesion.along * (end - start - 2 * margin))


def wall_site(colon, s: float, theta: float) -> WallSite:
    """The wall of `colon` (any TubeColon) at (s, theta) and its inward normal."""
    cl = colon.centerline
    t, n, b = cl.frame_at(s)
    radial = np.cos(theta) * n + np.sin(theta) * b
    r = float(colon.wall_radius(np.array([s]), np.array([theta]))[0])
    base = cl.point_at(s) + r * radial
    # The inward normal: minus the gradient of F = rho - r(s, theta) (TubeColon.excursion).
    h_s, h_theta = 2.0e-4, 1.0e-2
    dr_ds = float((colon.wall_radius(np.array([s + h_s]), np.array([theta]))
                   - colon.wall_radius(np.array([s - h_s]), np.array([theta])))[0] / (2 * h_s))
    dr_dt = float((colon.wall_radius(np.array([s]), np.array([theta + h_theta]))
                   - colon.wall_radius(np.array([s]), np.array([theta - h_theta])))[0]
                  / (2 * h_theta))
    tangential = np.cos(theta) * b - np.sin(theta) * n
    outward = radial - dr_ds * t - (dr_dt / r) * tangential
    return WallSite(float(s), float(theta), base, -outward / np.linalg.norm(outward), t, n)


def site_frame(site: WallSite) -> np.ndarray:
    """4x4 pose of a lesion's frame: z along the inward normal, x across the lumen's axis."""
    axis, t = site.axis_W, site.tangent_W
    x = np.cross(axis, t)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else site.normal_W
    transform = np.eye(4)
    transform[:3, :3] = np.column_stack([x, np.cross(axis, x), axis])
    transform[:3, 3] = site.base_W
    return transform


def drape(colon, vertices: np.ndarray, base: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """`vertices` each raised along `axis` by how far the wall lies above the plane through
    `base` normal to `axis` under it (TubeColon.excursion of its foot on the plane), so that
    heights count from the mucosa across the lumen's curve and a fold's slope."""
    foot = vertices - np.outer((vertices - base) @ axis, axis)
    return vertices + np.outer(colon.excursion(foot), axis)


def place(colon, lesion: DrawnLesion, index: int = 0) -> PlacedPolyp:
    """`lesion` (a polyp) standing on the wall of `colon` (any TubeColon)."""
    if not lesion.polyp:
        raise ValueError("a diverticulum is placed by anatomy/diverticula.py")
    s = segment_s(colon, lesion)
    site = wall_site(colon, s, floor_angle(colon, s) + np.radians(lesion.around_deg))
    diameter = 1e-3 * lesion.size_mm
    radius, height, top = profile(lesion.kind, diameter)
    mesh = revolve(radius, height, SINK)
    mesh.apply_transform(site_frame(site))
    # Draped on the wall, as a lesion grows on it.
    vertices = drape(colon, np.array(mesh.vertices), site.base_W, site.axis_W)
    mesh = trimesh.Trimesh(vertices, mesh.faces, process=False)
    return PlacedPolyp(index, lesion, site.s, site.theta, site.base_W, site.axis_W, top, mesh)


def place_polyps(colon, lesions: list[DrawnLesion]) -> list[PlacedPolyp]:
    """The polyps of `lesions` on the wall of `colon`, indexed by their place in the list."""
    return [place(colon, lesion, k) for k, lesion in enumerate(lesions) if lesion.polyp]
