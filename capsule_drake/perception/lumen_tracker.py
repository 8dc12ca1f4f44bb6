"""LumenTracker: the lumen detector run on each new camera frame."""

import dataclasses
import logging

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem
from pydrake.systems.sensors import ImageGrey8U, ImageRgba8U

from capsule_drake.blocks import block, checked, need
from capsule_drake.perception.lumen import (BUILT_IN_DETECTORS, LumenParams,
                                            check_lumen_params, detection_problem,
                                            load_detector)
from capsule_drake.plugins import PluginError, read_only
from capsule_drake.schema import need_range

log = logging.getLogger(__name__)


@dataclasses.dataclass
class LumenTrackerConfig:
    """Which detector the tracker runs. YAML-loadable; all fields default."""

    # "net" (the learned detector, perception/lumen_net.py: trained on generated frames of
    # colon seeds no reported figure uses; docs/models/lumen.md, "The learned detector"),
    # "gaussian" (the seed's dark-class detector), "median" (the STORM implementation's),
    # "core" (the darkest point's core, perception/lumen.py), or "package.module:function":
    # a user's detector with the signature (rgb (H, W, 3|4) uint8, field_mask (H, W) bool)
    # -> an object with `visible`, `pixel` (u, v), `confidence` and, optionally, `region`
    # (H, W) (see perception/lumen.py).
    detector: str = "net"
    # Settings of the built-in detectors (ignored by a user's).
    params: LumenParams = dataclasses.field(default_factory=LumenParams)
    # Consistency over frames: a detection is reported only once this many consecutive
    # frames have detected a lumen, each frame's ray within `agree_deg` of the one before.
    # A confident dark patch on a view of the wall comes and goes and jumps as the capsule
    # moves; the lumen stays where it was. 1: every detection is reported as it comes.
    confirm_frames: int = 1
    agree_deg: float = 10.0


def check_lumen_tracker_config(config: LumenTrackerConfig) -> None:
    """Raises ValueError naming the first impossible field."""
    check_lumen_params(config.params)
    need_range(config.confirm_frames, "confirm_frames", "[1, 100]")
    if config.confirm_frames != int(config.confirm_frames):
        raise ValueError(f"confirm_frames must be an integer in [1, 100], got "
                         f"{config.confirm_frames}")
    need_range(config.agree_deg, "agree_deg", "(0, 180]", "deg")


class LumenTracker(LeafSystem):
    """Runs a lumen detector on every new frame of the capsule camera and holds the result.

    .. pydrake_system::

        name: LumenTracker
        input_ports:
        - rgb_image
        - frame_info
        output_ports:
        - lumen_pixel
        - lumen_ray
        - lumen_confidence
        - lumen_visible
        - region
        - stats

    rgb_image, frame_info: the CapsuleCamera's outputs; a frame is new when the frame count
    (frame_info[1]) changes. The tracker checks at `period` (the camera's tick), `delay`
    after the camera's ticks, so it sees the frame taken at that tick. The detector is given
    read-only views of the frame and the field mask.
    lumen_pixel: (u, v) px, NaN when not visible. lumen_ray: unit ray through that pixel in
    the camera frame (x right, y down, z forward), through the lens model; [0, 0, 0] when
    not visible. lumen_confidence: [0, 1]. lumen_visible: 1.0 or 0.0. region: ImageGrey8U,
    255 on the detected dark region (for overlays). stats: [frames processed, detector
    failures]; a detector that raises or returns garbage counts as a failure and reports
    "not visible" for that frame: the simulation goes on. A user's detector (a plug-in named
    in `config.detector`) is held to the detector contract instead: a result that breaks it
    (perception/lumen.py `detection_problem`) raises PluginError, which ends the run.

    Args:
        lens: the camera's lens model (`unproject`, `pixel_rays`).
        config: LumenTrackerConfig.
        period: how often to look for a new frame (s).
        detector: optional detector function overriding `config.detector`.
        delay: offset of the checks after the camera's ticks (s).
    """

    def __init__(self, lens, config: LumenTrackerConfig | None = None, period: float = 0.01,
                 detector=None, delay: float = 1e-6):
        super().__init__()
        self._config = config or LumenTrackerConfig()
        check_lumen_tracker_config(self._config)
        self._cos_agree = float(np.cos(np.radians(self._config.agree_deg)))
        self._detector = detector or load_detector(self._config.detector, self._config.params)
        # The user's detector named in the config, held to the contract (None: a built-in).
        self._plugin = (self._config.detector if detector is None
                        and self._config.detector not in BUILT_IN_DETECTORS else None)
        self._lens = lens
        _, field = lens.pixel_rays()
        self._field = read_only(field)
        W, H = lens.width, lens.height
        self._rgb_port = self.DeclareAbstractInputPort("rgb_image",
                                                       AbstractValue.Make(ImageRgba8U(W, H)))
        self._frame_info_port = self.DeclareVectorInputPort("frame_info", 4)
        # [u, v, ray (3), confidence, visible, last frame count, processed, failures,
        #  the last frame's detected ray (3; zeros: none), consecutive agreeing detections]
        initial = [np.nan, np.nan, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                   0.0]
        self._state = self.DeclareDiscreteState(BasicVector(initial))
        self._region = self.DeclareAbstractState(AbstractValue.Make(ImageGrey8U(W, H)))
        for name, start, size in (("lumen_pixel", 0, 2), ("lumen_ray", 2, 3),
                                  ("lumen_confidence", 5, 1), ("lumen_visible", 6, 1),
                                  ("stats", 8, 2)):
            self.DeclareVectorOutputPort(
                name, size, lambda context, output, start=start, size=size: output.SetFromVector(
                    context.get_discrete_state(self._state).value()[start:start + size]),
                {self.xd_ticket()})
        self.DeclareStateOutputPort("region", self._region)
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, delay, self._update)

    def detect(self, rgb: np.ndarray):
        """Runs the detector on one image; returns (pixel (2,), ray (3,), confidence,
        visible, region (H, W) uint8 or None, failed)."""
        nothing = (np.full(2, np.nan), np.zeros(3), 0.0, False, None)
        rgb = read_only(rgb)
        try:
            result = self._detector(rgb, self._field)
        except Exception as e:  # a detector's error must not stop the simulation
            log.warning("lumen detector failed on a frame: %s: %s", type(e).__name__, e)
            return nothing + (True,)
        problem = detection_problem(result, rgb.shape) if self._plugin is not None else None
        if problem is not None:
            raise PluginError(f"lumen detector {self._plugin!r} {problem}")
        try:
            visible = bool(result.visible)
            pixel = np.asarray(result.pixel, dtype=float).reshape(2)
            confidence = float(result.confidence)
            region = getattr(result, "region", None)
        except Exception as e:  # a result that is not one
            log.warning("lumen detector failed on a frame: %s: %s", type(e).__name__, e)
            return nothing + (True,)
        if not np.isfinite(confidence):
            return nothing + (True,)
        if not visible:
            return nothing[:2] + (float(np.clip(confidence, 0.0, 1.0)), False, region, False)
        if not np.all(np.isfinite(pixel)):
            return nothing + (True,)
        ray = self._lens.unproject(pixel[None, :])[0]
        return pixel, ray, float(np.clip(confidence, 0.0, 1.0)), True, region, False

    def _update(self, context, state):
        info = self._frame_info_port.Eval(context)
        values = context.get_discrete_state(self._state).value().copy()
        if info[1] == values[7]:
            return EventStatus.DidNothing()
        rgba = self._rgb_port.Eval(context).data
        pixel, ray, confidence, visible, region, failed = self.detect(rgba[..., :3])
        before = values[10:13]
        if not visible:
            streak = 0.0
        elif np.any(before) and float(before @ ray) >= self._cos_agree * np.linalg.norm(ray):
            streak = values[13] + 1.0
        else:
            streak = 1.0
        values[10:13] = ray if visible else 0.0
        values[13] = streak
        if visible and streak < self._config.confirm_frames:
            pixel, ray, visible = np.full(2, np.nan), np.zeros(3), False  # not yet confirmed
        values[0:2], values[2:5] = pixel, ray
        values[5], values[6], values[7] = confidence, 1.0 if visible else 0.0, info[1]
        values[8] += 1.0
        values[9] += 1.0 if failed else 0.0
        state.get_mutable_discrete_state(self._state).set_value(values)
        image = state.get_mutable_abstract_state(self._region).get_mutable_value()
        grey = image.mutable_data[..., 0]
        if region is not None and np.shape(region) == grey.shape:
            grey[...] = np.where(np.asarray(region) > 0, 255, 0)
        else:
            grey[...] = 0
        return EventStatus.Succeeded()


def check_tracker_resources(params) -> None:
    """What the lumen detector's own check (perception/lumen.py) leaves unbounded and
    costs memory or time per frame: its working image, filters and opening."""
    key = "capsule.lumen_tracker.params"
    need_range(params.work_size, f"{key}.work_size", "[16, 4096]", "px",
               "the working image's longest side; frames are at most 4096 px")
    need_range(params.median_size, f"{key}.median_size", "[1, 255]", "px")
    need_range(params.blur_sigma, f"{key}.blur_sigma", "[0, 100]", "px")
    need_range(params.opening, f"{key}.opening", "[0, 64]", "px")
    need_range(params.dark_bias, f"{key}.dark_bias", "[0, 10]", "", "an exponent")
    need_range(params.max_radius, f"{key}.max_radius", "(0, 2]", "",
               "relative to the field's radius")


def check_lumen_tracker(config: LumenTrackerConfig, scenario) -> None:
    need(scenario.capsule.camera is not None,
         "capsule.lumen_tracker needs capsule.camera (give a camera, e.g. camera: {})")
    checked("capsule.lumen_tracker: ", check_lumen_tracker_config, config)
    checked("", check_tracker_resources, config.params)
    checked("capsule.lumen_tracker: ", load_detector, config.detector, config.params)


@block("capsule.lumen_tracker", LumenTrackerConfig, check=check_lumen_tracker)
def add_lumen_tracker(builder, parts, config: LumenTrackerConfig):
    """`capsule.lumen_tracker` on every new frame of capsule.camera (its check makes sure
    there is one), as it is delivered; exports capsule.lumen_tracker.<signal>."""
    tracker = builder.AddNamedSystem("capsule.lumen_tracker", LumenTracker(
        parts.shared("capsule.camera.lens"), config, period=parts.shared("capsule.camera.tick"),
        delay=parts.shared("capsule.camera.latency") + 1e-6))
    builder.Connect(parts.output("capsule.camera.rgb_image"), tracker.GetInputPort("rgb_image"))
    builder.Connect(parts.output("capsule.camera.frame_info"),
                    tracker.GetInputPort("frame_info"))
    parts.export_outputs(tracker, "capsule.lumen_tracker")
    return tracker
