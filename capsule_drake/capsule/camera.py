"""CapsuleCamera: the capsule's wide-angle camera with its on-board light, and the block
`capsule.camera` (with the lumen truth, perception/lumen_truth.py).

The camera draws its frames with a LensRenderer (capsule/camera_renderer.py) in the
renderer of the colon window it is in (capsule/camera_walls.py); its config and checks are
capsule/camera_config.py.
"""

import dataclasses
import math

import numpy as np
from pydrake.common import RandomDistribution
from pydrake.common.value import AbstractValue
from pydrake.geometry import FrameId, QueryObject, RenderLabel
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem
from pydrake.systems.primitives import RandomSource
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I, ImageRgba8U

from capsule_drake.blocks import block
from capsule_drake.capsule.camera_config import (CAMERA_CONDITIONS, CameraConfig, camera_tick,
                                                 check_camera_config)
from capsule_drake.capsule.camera_renderer import LensRenderer
from capsule_drake.capsule.render_worker import RenderWorker
from capsule_drake.lifetime import weak_method
from capsule_drake.perception import Lens, photometry
from capsule_drake.perception.lumen_truth import add_lumen_truth


class CapsuleCamera(LeafSystem):
    """The capsule's camera: colour and depth through its lens, sampled and held.

    A periodic unrestricted update renders from the SceneGraph's query object and stores the
    images in abstract state; the outputs are that state (sample-and-hold, no algebraic
    loop). With `latency` > 0 a frame exposed at t is delivered at t + latency by a second
    periodic event (drawn meanwhile by `worker`, when given and able, else at delivery from
    the exposure's pose: the same image). Fixed mode captures every 1 / fps. Adaptive mode ticks at fps_max and captures
    when the time since the last frame reaches 1 / rate, where the rate rises linearly from
    fps_min (camera at rest) to fps_max (image motion >= motion_for_fps_max); image motion
    is estimated from the camera's pose change over the last tick, read from the query
    object. A frame is also captured when the simulation initialises.

    .. pydrake_system::

        name: CapsuleCamera
        input_ports:
        - query_object
        - condition_draw (with config.conditions other than nominal)
        output_ports:
        - rgb_image
        - depth_image
        - frame_info
        - frame_pose
        - label_image (with static_scene)

    condition_draw: two uniform numbers in [0, 1) read at each frame (a RandomSource at
    the camera's tick): which image condition of `config.conditions` the frame meets, and
    the seed of its strengths (`condition_of`).
    rgb_image: ImageRgba8U (H x W); black outside the lens's image circle; with its image
    condition applied.
    depth_image: ImageDepth32F (H x W), metres of RANGE along each pixel's ray from the
    camera centre (not z-depth: beyond 90 degrees z-depth is meaningless); +inf beyond `far`
    and outside the image circle, 0 nearer than `near`. Stays +inf if render_depth is off.
    frame_info: [exposure time of the last frame delivered (s), frames delivered, 1 if the
    camera's last event delivered a frame else 0, current frame rate (1/s)].
    frame_pose: the camera's pose at that frame's exposure, [R_WC row-major (9), p_WC (3)]
    (NaN before the first frame).
    label_image: ImageLabel16I (H x W), the RenderLabel each pixel of that frame sees
    (`LensRenderer.render_label`), drawn when first read: a lesion's label is its own.

    Args:
        config: CameraConfig (lens, frame rate, clipping, light, renderer name). The
            renderer must exist in the SceneGraph (see `add_camera_renderer`).
        parent_frame: SceneGraph frame the camera is fixed to (e.g. the capsule body's,
            `plant.GetBodyFrameIdOrThrow(body.index())`).
        X_PC: camera pose in that frame (e.g. the capsule's `camera` frame in its body).
        renderer_for: optional function of the camera's world position (3,) returning the
            name of the renderer to draw with (the colon window it is in; see
            `add_camera_walls`). None: always `config.renderer_name`.
        static_scene: True when everything the camera can see is anchored (in a colon with
            camera walls, the station strips the perception role from all else). Then the
            depth image of a frame is drawn when something first reads it, from the pose
            the frame was taken at, and never when nothing does: the same image, at no
            cost to a diagram that does not use depth. False: drawn with every frame.
        worker: optional RenderWorker drawing the frames of a camera with latency.
    """

    def __init__(self, config: CameraConfig, parent_frame: FrameId, X_PC: RigidTransform,
                 renderer_for=None, static_scene: bool = False, worker=None):
        super().__init__()
        self._config = dataclasses.replace(config)
        self._renderer = LensRenderer(self._config)
        self._parent_frame = parent_frame
        self._X_PC = RigidTransform(X_PC)
        self._renderer_for = renderer_for
        W, H = self._renderer.width, self._renderer.height
        c = self._config
        self._adaptive = c.fps_mode == "adaptive"
        self._tick = camera_tick(c)
        self._latency = c.latency
        if self._latency > 0.0 and not static_scene:
            raise ValueError("camera latency needs a scene the camera sees unmoving (a "
                             "colon's camera walls): a frame is drawn after its exposure")
        self._worker = worker if self._latency > 0.0 else None

        self._query_object_port = self.DeclareAbstractInputPort(
            "query_object", AbstractValue.Make(QueryObject()))
        # Image conditions: two uniform draws per frame (which condition, its strengths).
        self._conditions = c.conditions
        self._draw_port = None
        if self._conditions != "nominal":
            self._draw_port = self.DeclareVectorInputPort("condition_draw", 2)
            self._field = self._renderer.lens.pixel_rays()[1]
        rgb = ImageRgba8U(W, H)
        depth = ImageDepth32F(W, H)
        depth.mutable_data[...] = np.inf
        self._rgb_index = self.DeclareAbstractState(AbstractValue.Make(rgb))
        self._depth_index = self.DeclareAbstractState(AbstractValue.Make(depth))
        first_rate = c.fps_min if self._adaptive else c.fps
        self._info_index = self.DeclareDiscreteState(
            BasicVector([-np.inf, 0.0, 0.0, first_rate]))
        # Camera pose at the previous tick, [R_WC row-major (9), p_WC (3)], for the motion.
        self._pose_index = self.DeclareDiscreteState(np.full(12, np.nan))
        self._rgb_port = self.DeclareStateOutputPort("rgb_image", self._rgb_index)
        # Depth drawn on demand (static scene): the pose of the last frame, in the same
        # layout, and an output port cached until the next frame. Its calculation reads the
        # query object but depends only on that pose: the scene it sees does not move.
        self._lazy_depth = bool(static_scene and c.render_depth)
        self._depth_memo = None   # (frame pose bytes, range image) of the last lazy depth
        self._frame_pose_index = self.DeclareDiscreteState(np.full(12, np.nan))
        self._frame_pose_port = self.DeclareStateOutputPort("frame_pose",
                                                            self._frame_pose_index)
        if self._lazy_depth:
            self._depth_port = self.DeclareAbstractOutputPort(
                "depth_image", lambda: AbstractValue.Make(ImageDepth32F(W, H)),
                weak_method(self._calc_lazy_depth),
                {self.discrete_state_ticket(self._frame_pose_index)})
        else:
            self._depth_port = self.DeclareStateOutputPort("depth_image", self._depth_index)
        # Render labels of the last frame (static scene), drawn when read, like the lazy
        # depth: each pixel the RenderLabel of what it sees (a lesion's is its own: an
        # instance mask for free; `lesion_labels` names them).
        self._label_memo = None   # (frame pose bytes, label image) of the last one drawn
        self._label_port = None
        if static_scene:
            self._label_port = self.DeclareAbstractOutputPort(
                "label_image", lambda: AbstractValue.Make(ImageLabel16I(W, H)),
                weak_method(self._calc_label),
                {self.discrete_state_ticket(self._frame_pose_index)})
        self._frame_info_port = self.DeclareStateOutputPort("frame_info", self._info_index)
        # A frame in flight (latency > 0): [exposed (0/1), exposure time, pose (12)].
        self._exposure_index = self.DeclareDiscreteState(np.full(14, np.nan))
        self.DeclareInitializationUnrestrictedUpdateEvent(self._initialize)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self._tick, 0.0, self._on_tick)
        if self._latency > 0.0:
            self.DeclarePeriodicUnrestrictedUpdateEvent(self._tick, self._latency,
                                                        self._on_delivery)

    @property
    def lens(self) -> Lens:
        return self._renderer.lens

    @property
    def config(self) -> CameraConfig:
        """The camera's settings (a copy)."""
        return dataclasses.replace(self._config)

    def tick(self) -> float:
        """Period (s) at which the camera checks whether to take a frame."""
        return self._tick

    @property
    def worker(self):
        """The RenderWorker drawing this camera's frames, or None."""
        return self._worker

    def latency(self) -> float:
        """Time (s) from a frame's exposure (at a tick) to its delivery at the outputs."""
        return self._latency

    @property
    def renderer(self) -> LensRenderer:
        return self._renderer

    def get_query_object_input_port(self):
        return self._query_object_port

    def get_rgb_image_output_port(self):
        return self._rgb_port

    def get_depth_image_output_port(self):
        return self._depth_port

    def get_frame_info_output_port(self):
        return self._frame_info_port

    def get_frame_pose_output_port(self):
        return self._frame_pose_port

    # ---- events ---------------------------------------------------------------------------
    def renderer_name(self, query_object) -> str:
        """The renderer this frame draws with (the window the camera is in)."""
        if self._renderer_for is None:
            return self._config.renderer_name
        X_WP = query_object.GetPoseInWorld(self._parent_frame)
        return self._renderer_for(X_WP.multiply(self._X_PC.translation()))

    def _capture(self, context, query_object, state, pose_now=None):
        renderer = self.renderer_name(query_object)
        rgb = state.get_mutable_abstract_state(self._rgb_index).get_mutable_value()
        self._renderer.render_rgba(query_object, self._parent_frame, self._X_PC,
                                   out=rgb.mutable_data, renderer=renderer)
        self._degrade(context, rgb.mutable_data)
        if pose_now is None:
            pose_now = self._camera_pose_vector(query_object)
        state.get_mutable_discrete_state(self._frame_pose_index).set_value(pose_now)
        if not self._lazy_depth and self._config.render_depth:
            depth = state.get_mutable_abstract_state(self._depth_index).get_mutable_value()
            self._renderer.render_range(query_object, self._parent_frame, self._X_PC,
                                        out=depth.mutable_data[..., 0], renderer=renderer)

    def condition_of(self, draw) -> tuple[str, np.random.Generator]:
        """The condition a frame meets and the generator of its strengths, from the two
        uniform numbers `draw` of its condition_draw input."""
        name = self._conditions
        if name == "all":
            name = CAMERA_CONDITIONS[min(int(draw[0] * len(CAMERA_CONDITIONS)),
                                         len(CAMERA_CONDITIONS) - 1)]
        return name, np.random.default_rng(int(draw[1] * 2**32) % 2**32)

    def _degrade(self, context, rgb: np.ndarray) -> None:
        """Applies the frame's image condition to the RGBA buffer `rgb` in place."""
        if self._draw_port is None:
            return
        name, rng = self.condition_of(self._draw_port.Eval(context))
        rgb[..., :3] = photometry.apply(name, rgb[..., :3].copy(), self._field, rng)

    def _view_at(self, pose):
        """(X_WC, renderer name) of a camera pose [R_WC (9), p_WC (3)]."""
        X_WC = RigidTransform(RotationMatrix(pose[:9].reshape(3, 3)), pose[9:])
        renderer = (self._config.renderer_name if self._renderer_for is None
                    else self._renderer_for(pose[9:]))
        return X_WC, renderer

    def _draw_at(self, query_object, pose, rgb: np.ndarray):
        """Draws the colour frame at camera pose [R_WC (9), p_WC (3)] (static scene)."""
        X_WC, renderer = self._view_at(pose)
        self._renderer.render_rgba(query_object, query_object.inspector().world_frame_id(),
                                   X_WC, out=rgb, renderer=renderer)

    def _calc_lazy_depth(self, context, value):
        pose = context.get_discrete_state(self._frame_pose_index).value()
        depth = value.get_mutable_value()
        if not np.all(np.isfinite(pose)):  # no frame yet
            depth.mutable_data[...] = np.inf
            return
        # The depth is a function of the frame's pose alone (static scene), but Drake
        # invalidates this cache at every unrestricted update (the plant's step), so a
        # reader between two frames would render it again (~9 ms): the last frame's range
        # is kept, keyed by its pose.
        key = pose.tobytes()
        if self._depth_memo is not None and self._depth_memo[0] == key:
            depth.mutable_data[..., 0] = self._depth_memo[1]
            return
        query_object = self._query_object_port.Eval(context)
        X_WC, renderer = self._view_at(pose)
        self._renderer.render_range(query_object, query_object.inspector().world_frame_id(),
                                    X_WC, out=depth.mutable_data[..., 0], renderer=renderer)
        self._depth_memo = (key, depth.data[..., 0].copy())

    def _calc_label(self, context, value):
        pose = context.get_discrete_state(self._frame_pose_index).value()
        labels = value.get_mutable_value().mutable_data[..., 0]
        if not np.all(np.isfinite(pose)):  # no frame yet
            labels[...] = int(RenderLabel.kEmpty)
            return
        key = pose.tobytes()
        if self._label_memo is None or self._label_memo[0] != key:
            query_object = self._query_object_port.Eval(context)
            X_WC, renderer = self._view_at(pose)
            self._label_memo = (key, self._renderer.render_label(
                query_object, query_object.inspector().world_frame_id(), X_WC,
                renderer=renderer))
        labels[...] = self._label_memo[1]

    def _camera_pose_vector(self, query_object) -> np.ndarray:
        X_WC = query_object.GetPoseInWorld(self._parent_frame).multiply(self._X_PC)
        return np.concatenate([X_WC.rotation().matrix().ravel(), X_WC.translation()])

    def frame_rate(self, pose_before: np.ndarray, pose_now: np.ndarray, dt: float) -> float:
        """Frame rate (1/s) the camera picks for a pose change over dt (fixed: fps)."""
        c = self._config
        if not self._adaptive:
            return c.fps
        if not np.all(np.isfinite(pose_before)) or dt <= 0.0:
            return c.fps_min
        R_before = pose_before[:9].reshape(3, 3)
        R_now = pose_now[:9].reshape(3, 3)
        cos_angle = np.clip((np.trace(R_before.T @ R_now) - 1.0) / 2.0, -1.0, 1.0)
        angular_speed = math.acos(cos_angle) / dt
        speed = np.linalg.norm(pose_now[9:] - pose_before[9:]) / dt
        motion = speed / c.viewing_distance + angular_speed
        fraction = min(1.0, motion / c.motion_for_fps_max)
        return c.fps_min + fraction * (c.fps_max - c.fps_min)

    def _initialize(self, context, state):
        query_object = self._query_object_port.Eval(context)
        self._capture(context, query_object, state)
        t = context.get_time()
        rate = self._config.fps_min if self._adaptive else self._config.fps
        state.get_mutable_discrete_state(self._info_index).set_value([t, 1.0, 1.0, rate])
        state.get_mutable_discrete_state(self._pose_index).set_value(
            self._camera_pose_vector(query_object))
        return EventStatus.Succeeded()

    def _on_tick(self, context, state):
        query_object = self._query_object_port.Eval(context)
        t = context.get_time()
        t_last, count, _, _ = context.get_discrete_state(self._info_index).value()
        pose_before = context.get_discrete_state(self._pose_index).value()
        pose_now = self._camera_pose_vector(query_object)
        rate = self.frame_rate(pose_before, pose_now, self._tick)
        # Half a tick of slack: ticks land on multiples of the tick period up to rounding.
        take = t - t_last >= 1.0 / rate - 0.5 * self._tick
        delivered = take
        if take and self._latency > 0.0:
            # Exposed now, delivered `latency` later (_on_delivery); meanwhile drawn by the
            # worker, if it can take it.
            state.get_mutable_discrete_state(self._exposure_index).set_value(
                np.concatenate([[1.0, t], pose_now]))
            if self._worker is not None:
                self._worker.submit(pose_now)
            delivered = False
        elif take:
            self._capture(context, query_object, state, pose_now)
            t_last, count = t, count + 1.0
        state.get_mutable_discrete_state(self._info_index).set_value(
            [t_last, count, 1.0 if delivered else 0.0, rate])
        state.get_mutable_discrete_state(self._pose_index).set_value(pose_now)
        return EventStatus.Succeeded()

    def _on_delivery(self, context, state):
        exposure = context.get_discrete_state(self._exposure_index).value()
        if not exposure[0] == 1.0:
            return EventStatus.DidNothing()
        pose = exposure[2:]
        rgb = state.get_mutable_abstract_state(self._rgb_index).get_mutable_value()
        if self._worker is None or not self._worker.collect(pose, rgb.mutable_data):
            self._draw_at(self._query_object_port.Eval(context), pose, rgb.mutable_data)
        self._degrade(context, rgb.mutable_data)
        state.get_mutable_discrete_state(self._frame_pose_index).set_value(pose)
        _, count, _, rate = context.get_discrete_state(self._info_index).value()
        state.get_mutable_discrete_state(self._info_index).set_value(
            [exposure[1], count + 1.0, 1.0, rate])
        state.get_mutable_discrete_state(self._exposure_index).set_value(np.full(14, np.nan))
        return EventStatus.Succeeded()


def capsule_camera_for_frame(plant, frame, config: CameraConfig, renderer_for=None,
                             static_scene: bool = False, worker=None) -> CapsuleCamera:
    """A CapsuleCamera fixed to a plant frame (e.g. the capsule model's `camera` frame):
    resolves the frame's body to its SceneGraph frame and the frame's pose in that body."""
    body = frame.body()
    return CapsuleCamera(config, plant.GetBodyFrameIdOrThrow(body.index()),
                         frame.GetFixedPoseInBodyFrame(), renderer_for, static_scene, worker)

# --- The camera in a colon: its walls, and the camera block --------------------------------

@block("capsule.camera", CameraConfig, check=lambda config, _: check_camera_config(config),
       where="capsule.camera: ")
def add_camera(builder, parts, config: CameraConfig):
    """`capsule.camera` at the capsule's `camera` frame (its own renderers, light at the
    lens) and `capsule.lumen`, the lumen ground truth; exports capsule.camera.<signal> and
    capsule.lumen.<signal>, and shares the camera's lens, config, tick (the period of its
    frames) and latency (`capsule.camera.<that>`). The camera's walls are in the scene
    before (`capsule.camera_walls`, parts.renderer_for), so the camera sees only the
    anchored wall: its depth image is drawn on demand, and frames with latency in a render
    worker on another core."""
    plant = parts.plant
    camera_frame = plant.GetFrameByName("camera", parts.capsule_instance)
    static = parts.renderer_for is not None
    worker = (RenderWorker(parts.colon_params, config)
              if static and config.latency > 0.0 and config.render_process else None)
    camera = builder.AddNamedSystem("capsule.camera", capsule_camera_for_frame(
        plant, camera_frame, config, parts.renderer_for, static_scene=static, worker=worker))
    builder.Connect(parts.scene_graph.get_query_output_port(),
                    camera.get_query_object_input_port())
    if config.conditions != "nominal":   # the draws of the frames' image conditions
        draws = builder.AddNamedSystem("capsule.camera.condition_draws", RandomSource(
            RandomDistribution.kUniform, 2, camera.tick()))
        builder.Connect(draws.get_output_port(), camera.GetInputPort("condition_draw"))
    for name in ("rgb_image", "depth_image", "frame_info", "frame_pose", "label_image"):
        if camera.HasOutputPort(name):
            parts.export(camera.GetOutputPort(name), f"capsule.camera.{name}")
    for name, value in (("lens", camera.lens), ("config", camera.config),
                        ("tick", camera.tick()), ("latency", camera.latency()),
                        ("render_worker", camera.worker)):
        parts.share(f"capsule.camera.{name}", value)
    add_lumen_truth(builder, parts, camera)
    return camera
