"""Mucosa coverage: how much of the colon wall the capsule camera has shown.

The wall is the camera's own wall mesh (`Colon.camera_mesh`, the triangles the camera
draws); a triangle counts as seen once a frame shows its centre: inside the lens's field and
image, within the camera's range `far`, on the side of the wall the camera faces, and not
hidden behind nearer tissue (the frame's depth at its pixel reaches it, within
`depth_tolerance` + `depth_fraction` x range). Coverage is the seen triangles' share of the
wall's area, overall and per colon segment.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem
from pydrake.systems.sensors import ImageDepth32F


class WallPatches:
    """Centres, outward-from-lumen normals, areas and segments of a colon's camera wall."""

    def __init__(self, colon):
        mesh = colon.camera_mesh()
        triangles = mesh.vertices[mesh.faces]  # (F, 3, 3)
        self.centres = triangles.mean(axis=1)
        cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        self.areas = 0.5 * np.linalg.norm(cross, axis=1)
        # Faces are wound so their normals face the centreline (into the lumen).
        self.normals = cross / np.maximum(2.0 * self.areas[:, None], 1e-18)
        s = mesh.s[mesh.faces].mean(axis=1)
        self.segment = colon.centerline.segment_index_at(s)
        self.segment_names = colon.centerline.segment_names

    def __len__(self):
        return len(self.areas)


def seen_in_frame(patches: WallPatches, lens, R_WC, p_WC, depth, far: float,
                  depth_tolerance: float = 0.003, depth_fraction: float = 0.03) -> np.ndarray:
    """Indices of the patches a frame shows (module docstring).

    Args:
        patches: the wall's WallPatches.
        lens: the camera's Lens (project).
        R_WC, p_WC: the camera's pose at the frame.
        depth: (H, W) range image of the frame (m along each pixel's ray; +inf for nothing).
        far: the camera's range (m).
    """
    offset = patches.centres - p_WC
    near = np.flatnonzero(np.einsum("ij,ij->i", offset, offset) < far * far)
    if len(near) == 0:
        return near
    offset = offset[near]
    # Facing: the camera is on the lumen side of the patch.
    near = near[np.einsum("ij,ij->i", offset, patches.normals[near]) < 0.0]
    offset = patches.centres[near] - p_WC
    points_C = offset @ np.asarray(R_WC)
    pixels, valid = lens.project(points_C)
    near, pixels, offset = near[valid], pixels[valid], offset[valid]
    height, width = depth.shape
    u = np.clip(np.rint(pixels[:, 0]).astype(int), 0, width - 1)
    v = np.clip(np.rint(pixels[:, 1]).astype(int), 0, height - 1)
    distance = np.linalg.norm(offset, axis=1)
    shown = depth[v, u]
    # Not hidden: the first surface along the pixel's ray is this one (not nearer tissue).
    visible = np.isfinite(shown) & (shown >= distance - (depth_tolerance
                                                        + depth_fraction * distance))
    return near[visible]


class MucosaCoverage(LeafSystem):
    """Marks the wall patches each new camera frame shows (module docstring).

    .. pydrake_system::

        name: MucosaCoverage
        input_ports:
        - depth_image
        - frame_info
        - frame_pose
        output_ports:
        - coverage
        - segment_coverage

    depth_image, frame_info, frame_pose: the CapsuleCamera's. Checks at `period` whether a
    new frame arrived (frame count changed) and marks what it shows; reading its depth
    image is what draws it, so coverage costs a depth frame per `period` at most.
    coverage: [seen area / wall area]. segment_coverage: the same per colon segment, in
    the centreline's segment order.

    Args:
        colon: the run's Colon.
        lens: the camera's Lens.
        far: the camera's range (m).
        period: how often to look for a new frame (s).
    """

    def __init__(self, colon, lens, far: float, period: float = 0.5):
        super().__init__()
        self._patches = WallPatches(colon)
        self._lens = lens
        self._far = far
        n_segments = len(self._patches.segment_names)
        self._segment_area = np.bincount(self._patches.segment, self._patches.areas,
                                         minlength=n_segments)
        W, H = lens.width, lens.height
        self._depth = self.DeclareAbstractInputPort("depth_image",
                                                    AbstractValue.Make(ImageDepth32F(W, H)))
        self._info = self.DeclareVectorInputPort("frame_info", 4)
        self._pose = self.DeclareVectorInputPort("frame_pose", 12)
        self._seen = self.DeclareAbstractState(
            AbstractValue.Make(np.zeros(len(self._patches), dtype=bool)))
        # [last frame count processed, coverage, per-segment coverage...]
        self._state = self.DeclareDiscreteState(
            BasicVector(np.concatenate([[-1.0, 0.0], np.zeros(n_segments)])))
        self.DeclareVectorOutputPort(
            "coverage", 1,
            lambda c, out: out.SetAtIndex(0, c.get_discrete_state(self._state).value()[1]),
            {self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "segment_coverage", n_segments,
            lambda c, out: out.SetFromVector(c.get_discrete_state(self._state).value()[2:]),
            {self.xd_ticket()})
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.0, self._update)

    @property
    def segment_names(self):
        return self._patches.segment_names

    def _update(self, context, state):
        info = self._info.Eval(context)
        values = context.get_discrete_state(self._state).value().copy()
        pose = self._pose.Eval(context)
        if info[1] == values[0] or not np.all(np.isfinite(pose)):
            return EventStatus.DidNothing()
        depth = self._depth.Eval(context).data[..., 0]
        shown = seen_in_frame(self._patches, self._lens, pose[:9].reshape(3, 3), pose[9:],
                              depth, self._far)
        seen = state.get_mutable_abstract_state(self._seen).get_mutable_value()
        seen[shown] = True
        areas = self._patches.areas
        values[0] = info[1]
        values[1] = areas[seen].sum() / areas.sum()
        by_segment = np.bincount(self._patches.segment[seen], areas[seen],
                                 minlength=len(self._segment_area))
        values[2:] = by_segment / np.maximum(self._segment_area, 1e-18)
        state.get_mutable_discrete_state(self._state).set_value(values)
        return EventStatus.Succeeded()
