"""Meshcat: the scene, its contact forces, the capsule's marker and trail, and the EPM's pose
command.

The colon is drawn translucent and the capsule inside it marked, so that the 11.6 mm capsule
can be found in a view of the whole abdomen; Meshcat's default floor grid and world axes are
hidden (the grid lies in the table's plane, its far lines drew stray lines along the top of
every view). What is drawn goes into the run's recording: the marker's pose and which pieces
of the trail are shown are animated, so a replay shows the trail as far as the capsule had
gone at each instant.
"""

import numpy as np
from pydrake.geometry import (Cylinder, MeshcatVisualizer, MeshcatVisualizerParams, Rgba,
                              Sphere)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.meshcat import ContactVisualizer, ContactVisualizerParams
from pydrake.systems.framework import EventStatus, LeafSystem

from capsule_drake.blocks import block
from capsule_drake.io.replay import STREAM_SYSTEM, CameraStream

MARKER_SYSTEM = "capsule_marker"
# The colon's opacity in Meshcat (its mesh's own material times this): the capsule and its
# marker show through its walls, its folds still read.
COLON_OPACITY = 0.6
COLON_PATH = "/drake/visualizer/colon_mucosa"
# The capsule's marker: a translucent sphere around it, drawn over everything (a locator,
# ~20 px across in the default view of the abdomen), moved in steps of MARKER_STEP (fewer
# keyframes in a recording). Its trail: an opaque tube along the path of its centre, a
# point every TRAIL_STEP of travel, drawn in pieces once a piece spans TRAIL_PIECE_TIME or
# holds more than TRAIL_PIECE_POINTS steps (a piece appears in a replay when it is drawn:
# the trail lags the marker by at most a second, or 2.4 cm when it moves fast).
MARKER_PATH = "/capsule_marker"
MARKER_RADIUS = 0.015
MARKER_RGBA = Rgba(0.1, 1.0, 0.25, 0.4)
MARKER_STEP = 0.001
TRAIL_PATH = "/capsule_trail"
TRAIL_RADIUS = 0.0018
TRAIL_RGBA = Rgba(1.0, 0.82, 0.05, 1.0)
TRAIL_STEP = 0.003
TRAIL_PIECE_TIME = 1.0
TRAIL_PIECE_POINTS = 8


@block("meshcat")
def add_meshcat_block(builder, parts, scenario):
    """Meshcat's drawing (`add_meshcat`, every scenario.outputs.visual_period) when the
    station is built with a Meshcat."""
    if parts.meshcat is not None:
        add_meshcat(builder, parts, scenario.outputs.visual_period)


def add_meshcat(builder, parts, period: float):
    """Illustration geometry and contact forces in parts.meshcat, the capsule's marker and
    trail (CapsuleMarker), the capsule camera's frames for the replay (io/replay.py) when
    there is a camera, and (when something other than a path drives the EPM, or the arm
    carries it) a marker at the EPM's command; the view looks at the abdomen from the
    patient's right, above the table, without Meshcat's floor grid and axes."""
    meshcat = parts.meshcat
    MeshcatVisualizer.AddToBuilder(builder, parts.scene_graph, meshcat,
                                   MeshcatVisualizerParams(publish_period=period))
    ContactVisualizer.AddToBuilder(builder, parts.plant, meshcat,
                                   ContactVisualizerParams(publish_period=period,
                                                           newtons_per_meter=20.0))
    meshcat.SetCameraPose(camera_in_world=[-0.55, -0.35, 0.65], target_in_world=[0.0, 0.0, 0.1])
    meshcat.SetProperty("/Grid", "visible", False)
    meshcat.SetProperty("/Axes", "visible", False)
    marker = builder.AddNamedSystem(MARKER_SYSTEM, CapsuleMarker(meshcat, period))
    builder.Connect(parts.capsule_state, marker.get_input_port())
    parts.share("meshcat.flush_trail", marker.flush)
    if parts.has("capsule.camera.rgb_image"):
        stream = builder.AddNamedSystem(STREAM_SYSTEM, CameraStream())
        builder.Connect(parts.output("capsule.camera.rgb_image"),
                        stream.GetInputPort("rgb_image"))
        builder.Connect(parts.output("capsule.camera.frame_info"),
                        stream.GetInputPort("frame_info"))
        parts.share("meshcat.replay_frames", stream.frames)
    if parts.has("epm.command"):
        marker = builder.AddNamedSystem("epm_command_marker", CommandMarker(
            meshcat, parts.epm.magnet, period))
        builder.Connect(parts.output("epm.command"), marker.GetInputPort("epm_command"))


def tube_mesh(points: np.ndarray, radius: float, sides: int = 6):
    """A tube of `radius` along the polyline `points` (N, 3), N >= 2, open at its ends:
    rings of `sides` vertices normal to each point's tangent, joined by quads of two
    triangles. Returns (vertices (3, N * sides), faces (3, 2 * (N - 1) * sides) int32)."""
    p = np.asarray(points, dtype=float)
    tangent = np.gradient(p, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    # A normal carried along the polyline (parallel transport by projection), so the rings
    # do not twist where the tangent turns.
    normals = np.empty_like(p)
    previous = np.eye(3)[np.argmin(np.abs(tangent[0]))]
    for i, t in enumerate(tangent):
        n = previous - t * np.dot(previous, t)
        if np.linalg.norm(n) < 1e-9:  # the path turned back on itself: any normal of t
            e = np.eye(3)[np.argmin(np.abs(t))]
            n = e - t * np.dot(e, t)
        normals[i] = previous = n / np.linalg.norm(n)
    binormals = np.cross(tangent, normals)
    angle = 2.0 * np.pi * np.arange(sides) / sides
    rings = p[:, None, :] + radius * (np.cos(angle)[None, :, None] * normals[:, None, :]
                                      + np.sin(angle)[None, :, None] * binormals[:, None, :])
    i, k = np.meshgrid(np.arange(len(p) - 1), np.arange(sides), indexing="ij")
    a, b = i * sides + k, i * sides + (k + 1) % sides
    c, d = a + sides, b + sides
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                            np.stack([a, d, c], -1).reshape(-1, 3)])
    return rings.reshape(-1, 3).T, faces.T.astype(np.int32)


class CapsuleMarker(LeafSystem):
    """Makes the capsule findable in a view of the abdomen: a translucent sphere around it
    drawn over everything (MARKER_*), a tube along the path of its centre (TRAIL_*), and the
    colon translucent (COLON_OPACITY). Published every `period`; the marker's pose and the
    trail's pieces (each shown from the time it ends) go into a recording.

    .. pydrake_system::

        name: CapsuleMarker
        input_ports:
        - capsule_state

    capsule_state: the capsule's [q_WB (wxyz), p_WB, w_WB, v_WB] (13).

    The trail so far is held here (a visualiser's state, as MeshcatVisualizer's is): one
    simulation at a time per marker; it starts again when a simulation initialises.
    """

    def __init__(self, meshcat, period: float):
        super().__init__()
        self._meshcat = meshcat
        self._state = self.DeclareVectorInputPort("capsule_state", 13)
        meshcat.SetObject(MARKER_PATH, Sphere(MARKER_RADIUS), MARKER_RGBA)
        # Drawn last and whatever is in front of it: it is seen through the torso, the
        # colon's other loops and the EPM.
        meshcat.SetProperty(MARKER_PATH + "/<object>", "material.depthTest", False)
        meshcat.SetProperty(MARKER_PATH + "/<object>", "renderOrder", 10.0)
        self._reset()
        self.DeclareInitializationPublishEvent(self._initialize)
        self.DeclarePeriodicPublishEvent(period, 0.0, self._publish)

    def _reset(self):
        self._piece = []          # (t, p_WB) of the trail's piece being drawn
        self._pieces = 0          # pieces published
        self._colon_styled = False
        self._marker = None       # (time, position) of its last keyframe, time last seen

    def _initialize(self, context):
        self._meshcat.Delete(TRAIL_PATH)
        self._reset()
        return EventStatus.Succeeded()

    def _publish(self, context):
        t = context.get_time()
        p = np.array(self._state.Eval(context)[4:7])
        if not np.all(np.isfinite(p)):
            return EventStatus.DidNothing()
        self._move_marker(t, p)
        if not self._colon_styled and self._meshcat.HasPath(COLON_PATH):
            # The visualiser sets its objects' opacity when it first draws them (in this
            # publish or the one before): set after that.
            self._meshcat.SetProperty(COLON_PATH, "modulated_opacity", COLON_OPACITY)
            # First of the translucent objects: the torso, drawn after it, writes depth
            # over the whole abdomen, and would hide a colon drawn later.
            self._meshcat.SetProperty(COLON_PATH + "/<object>", "renderOrder", -1.0)
            self._colon_styled = True
        if not self._piece or np.linalg.norm(p - self._piece[-1][1]) >= TRAIL_STEP:
            self._piece.append((t, p))
        if len(self._piece) >= 2 and (t - self._piece[0][0] >= TRAIL_PIECE_TIME
                                      or len(self._piece) > TRAIL_PIECE_POINTS):
            self._publish_piece(t)
        return EventStatus.Succeeded()

    def _move_marker(self, t: float, p: np.ndarray):
        """Moves the marker once the capsule has gone MARKER_STEP from where it was last
        put (a replay interpolates between these keyframes; where the capsule paused, the
        pause's end is put too, so it does not creep through the pause)."""
        if self._marker is not None:
            t_key, p_key, t_seen = self._marker
            if np.linalg.norm(p - p_key) < MARKER_STEP:
                self._marker = (t_key, p_key, t)
                return
            if t_seen > t_key:
                self._meshcat.SetTransform(MARKER_PATH, RigidTransform(p_key), t_seen)
        self._meshcat.SetTransform(MARKER_PATH, RigidTransform(p), t)
        self._marker = (t, p, t)

    def flush(self, t: float):
        """Draws the trail's last, unfinished piece (at the end of a run, at time `t`)."""
        if len(self._piece) >= 2:
            self._publish_piece(t)

    def _publish_piece(self, t: float):
        """Draws the piece so far; it shows in a replay from `t` on. The next piece starts
        at its last point (the tube is continuous)."""
        vertices, faces = tube_mesh(np.array([q for _, q in self._piece]), TRAIL_RADIUS)
        path = f"{TRAIL_PATH}/{self._pieces:05d}"
        self._meshcat.SetTriangleMesh(path, vertices, faces, TRAIL_RGBA)
        self._meshcat.SetProperty(path, "visible", False, 0.0)
        self._meshcat.SetProperty(path, "visible", True, t)
        self._pieces += 1
        self._piece = [(t, self._piece[-1][1])]


class CommandMarker(LeafSystem):
    """Shows an EPM pose command in Meshcat: a translucent copy of the magnet (moment along
    its axis) at [p_WE, m_hat_W], published every `period` (and into a recording)."""

    def __init__(self, meshcat, geometry, period: float, path: str = "/epm_command"):
        super().__init__()
        self._meshcat = meshcat
        self._path = path
        dims = geometry.dimensions
        shape = (Sphere(0.5 * dims[0]) if geometry.shape == "sphere" else
                 Cylinder(0.5 * dims[0], dims[1]) if geometry.shape == "cylinder" else
                 Cylinder(0.5 * float(np.hypot(dims[0], dims[1])), dims[2]))
        meshcat.SetObject(path, shape, Rgba(0.2, 0.6, 1.0, 0.3))
        self._command = self.DeclareVectorInputPort("epm_command", 6)
        self.DeclarePeriodicPublishEvent(period, 0.0, self._publish)

    def _publish(self, context):
        command = self._command.Eval(context)
        if not np.all(np.isfinite(command)) or np.linalg.norm(command[3:]) < 1e-9:
            return EventStatus.DidNothing()
        R = RotationMatrix.MakeFromOneVector(command[3:], 2)
        self._meshcat.SetTransform(self._path, RigidTransform(R, command[:3]),
                                   context.get_time())
        return EventStatus.Succeeded()
