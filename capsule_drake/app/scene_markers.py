"""The scene as ROS 2 markers, for a 3-D viewer of the channels (Foxglove's 3D panel, RViz).

One latched visualization_msgs/MarkerArray on `/scene/markers`: the colon's wall as a
triangle list in `world` (the colon's visual mesh, decimated to at most `MAX_TRIANGLES` so
that the message stays a few MB), the capsule (a cylinder and its two domes) in the
`capsule` frame and the EPM's magnet in the `epm` frame, both `frame_locked` so that the
viewer moves them with /tf.
"""

from __future__ import annotations

import numpy as np
import trimesh

from capsule_drake.app.ros2_messages import header

# Triangles of the colon's wall in the scene (a 150 cm colon's visual mesh has ~10^5).
MAX_TRIANGLES = 40_000
WALL_COLOR = (0.85, 0.45, 0.42, 0.55)
CAPSULE_COLOR = (0.9, 0.9, 0.95, 1.0)
EPM_COLOR = (0.75, 0.2, 0.2, 0.8)


def wall_triangles(mesh: trimesh.Trimesh, max_triangles: int = MAX_TRIANGLES) -> np.ndarray:
    """(n, 3, 3) corners of the wall's triangles, the mesh decimated when it has more than
    `max_triangles` (fast-simplification's quadric decimation)."""
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if len(faces) > max_triangles:
        import fast_simplification
        vertices, faces = fast_simplification.simplify(
            vertices.astype(np.float64), faces.astype(np.int64),
            target_reduction=1.0 - max_triangles / len(faces))
    return np.asarray(vertices)[np.asarray(faces)]


def _color(rgba) -> dict:
    return {"r": float(rgba[0]), "g": float(rgba[1]), "b": float(rgba[2]), "a": float(rgba[3])}


def _marker(frame: str, ns: str, marker_type: int, position=(0.0, 0.0, 0.0),
            scale=(1.0, 1.0, 1.0), rgba=(1.0, 1.0, 1.0, 1.0), points=(),
            frame_locked: bool = False) -> dict:
    return {"header": header(0, frame), "ns": ns, "id": 0, "type": marker_type, "action": 0,
            "pose": {"position": {"x": float(position[0]), "y": float(position[1]),
                                  "z": float(position[2])},
                     "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
            "scale": {"x": float(scale[0]), "y": float(scale[1]), "z": float(scale[2])},
            "color": _color(rgba), "frame_locked": frame_locked, "points": list(points)}


SPHERE, CYLINDER, TRIANGLE_LIST = 2, 3, 11


def scene_markers(wall: np.ndarray, capsule_radius: float, capsule_length: float,
                  epm_diameter: float, epm_length: float) -> dict:
    """The MarkerArray of the scene (module docstring); `wall` from `wall_triangles`."""
    points = [{"x": float(x), "y": float(y), "z": float(z)} for x, y, z in wall.reshape(-1, 3)]
    d = 2.0 * capsule_radius
    markers = [
        _marker("world", "colon_wall", TRIANGLE_LIST, rgba=WALL_COLOR, points=points),
        _marker("capsule", "capsule", CYLINDER, scale=(d, d, capsule_length),
                rgba=CAPSULE_COLOR, frame_locked=True),
        dict(_marker("capsule", "capsule", SPHERE, position=(0, 0, 0.5 * capsule_length),
                     scale=(d, d, d), rgba=CAPSULE_COLOR, frame_locked=True), id=1),
        dict(_marker("capsule", "capsule", SPHERE, position=(0, 0, -0.5 * capsule_length),
                     scale=(d, d, d), rgba=CAPSULE_COLOR, frame_locked=True), id=2),
        _marker("epm", "epm", CYLINDER, scale=(epm_diameter, epm_diameter, epm_length),
                rgba=EPM_COLOR, frame_locked=True),
    ]
    return {"markers": markers}
