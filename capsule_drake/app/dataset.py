"""DatasetWriter: frames, poses and sensor streams to a folder while the simulation runs.

The layout follows SimCol3D's (Rau et al., 2023: `Frames_<seq>/FrameBuffer_XXXX.png`,
`Depth_XXXX.png`, `SavedPosition_<seq>.txt`, `SavedRotationQuaternion_<seq>.txt`, one folder
per sequence here, without the `_<seq>` suffixes) with the sensor streams added:

    <out>/
      README.md                     the folder described for a user (written by `dataset_readme`)
      camera.yaml                   lens model and intrinsics, mounting in the capsule, depth encoding
      sensors.yaml                  IMU and magnetometer: mounting, rate, range, noise
      mask.png                      8-bit: 255 inside the lens's image circle, 0 outside
      Frames/FrameBuffer_0000.png   colour (8-bit RGB)
      Frames/Depth_0000.png         depth, 16-bit (DEPTH_* below)
      SavedPosition.txt             per frame: tx ty tz, camera centre in world (m)
      SavedRotationQuaternion.txt   per frame: qx qy qz qw, camera-to-world rotation
      frames.csv                    per frame: index, exposure time (s)
      lumen_truth.csv               per frame: where the lumen is in the image
      Frames/Lesions_0000.png, lesions.csv, lesion_frames.csv, lesions_coco.json
                                    with polyps in the colon: app/lesion_dataset.py
      <stream>.csv                  one per sensor stream (imu, ahrs, magnetometer, ground_truth)

One quaternion order in every file: x, y, z, w (scalar last), as SimCol3D's
SavedRotationQuaternion, ROS messages and SciPy's `Rotation.from_quat`; a CSV's columns are
named qx, qy, qz, qw, and every other column's name ends with its unit.

World frame: z up (anterior), x to the patient's left, y to the head, table top at z = 0
(right-handed; SimCol3D's Unity frame is left-handed). Camera frame: +z along the optical
axis, +x right and +y down in the image (OpenCV/Drake convention). Every file is written and
flushed as the simulation goes, so an interrupted run keeps what it recorded.

Timing. Drake publishes at a time t before the discrete updates at t, so a sensor read at its
own sample time would show the previous sample (and, at t = 0, its zero initial state). A
stream is therefore read just after its sensor's update (`Stream.after_update`); a stream
with a warm-up (the AHRS's first estimate) starts at its first real sample
(`Stream.first_sample`). A frame's pose is the pose the camera drew it from (its frame_pose
output), and its lumen truth is computed from that pose and the frame's own depth.

Every row is stamped with the time of the plant state it shows (`state_time`). A discrete
plant holds its state x_{n+1} over (t_n, t_{n+1}] and, with sampled output ports, steps in an
unrestricted update, which Drake runs before the discrete updates at the same time: a
sensor's sample at its tick t measures the state one plant step later, and a camera tick
that floating-point rounding puts just after a plant step (3 x 0.1 > 150 x 0.002) shows the
state of the next step. The ground truth, read at its own ticks, shows the state there.
"""

import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import EventStatus, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I, ImageRgba8U

from capsule_drake.app.lesion_dataset import LesionRecorder
from capsule_drake.app.outputs import OutputError
from capsule_drake.perception.lumen_truth import far_region

# How long after a sample time the writer reads (s): just after the sensors' updates at that
# time (Drake publishes before updating at the same time).
READ_DELAY = 1e-6

# The 16-bit depth encoding: 0 = no measurement (outside the lens's image circle, or tissue
# nearer than the camera's near clip), DEPTH_BEYOND = nothing within the full scale,
# 1..DEPTH_BEYOND - 1 = range (m) = value / DEPTH_SCALE * full scale.
DEPTH_NONE = 0
DEPTH_BEYOND = 65535
DEPTH_SCALE = 65535.0


@dataclasses.dataclass(frozen=True)
class Stream:
    """A sensor stream written as `<name>.csv`: one row per sample.

    name: file name without .csv. columns: column names after time_s (units in the names).
    period: sample period (s). after_update: read just after the sensor's update at each
    sample time (a sampled sensor's state output), else at the sample time itself (the
    plant's state). first_sample: sample time of the first real sample (s); earlier rows are
    not written. order: indices into the input vector for the columns (e.g. to put a w, x, y,
    z quaternion in x, y, z, w order); None keeps the input's order. stamp_shift: added to the
    time stamp (s), for an estimate of a later state than the one its inputs measured.
    """

    name: str
    columns: tuple
    period: float
    after_update: bool = True
    first_sample: float = 0.0
    order: tuple | None = None
    stamp_shift: float = 0.0

    @property
    def size(self) -> int:
        return len(self.columns) if self.order is None else max(self.order) + 1


def state_time(t: float, plant_step: float, after_plant_update: bool) -> float:
    """The time of the plant state that a reading at time t sees (module docstring).

    plant_step: the discrete plant's time step (s), 0 for a continuous plant (then t).
    after_plant_update: whether the reading comes after the plant's update at t when t is
    on the plant's grid (a discrete update after the plant's unrestricted step); else it
    sees the state held up to t. The grid times are computed as Drake does, k x step.
    """
    if plant_step <= 0.0:
        return t
    k = math.floor(t / plant_step)
    while k * plant_step > t:
        k -= 1
    while (k + 1) * plant_step <= t:
        k += 1
    # Now k x step <= t < (k + 1) x step.
    if k * plant_step == t and not after_plant_update:
        return t
    return (k + 1) * plant_step


@dataclasses.dataclass(frozen=True)
class PlantTiming:
    """Which plant state a reading shows (`state_time`): one answer for the dataset's files
    and the MCAP log (app/mcap_log.py), so that both stamp a sample alike.

    step: the discrete plant's time step (s; 0: continuous). step_first: whether the plant
    steps before the sensors' discrete updates at the same time (an unrestricted update,
    Drake's default with sampled output ports).
    """

    step: float = 0.0
    step_first: bool = True

    @classmethod
    def of(cls, plant) -> "PlantTiming":
        return cls(plant.time_step(), plant.GetUniquePeriodicDiscreteUpdateAttribute() is None)

    def sampled(self, tick: float) -> float:
        """The state time of a sensor's sample taken in a discrete update at `tick`."""
        return state_time(tick, self.step, self.step_first)

    def held(self, t: float) -> float:
        """The state time of what a publish event at t reads (the state held up to t: a
        publish runs before the updates at its time), or a camera draws at its exposure t
        (in an unrestricted update, beside the plant's step)."""
        return state_time(t, self.step, after_plant_update=False)


def sample_tick(read_time: float, period: float, offset: float) -> float:
    """The sample time, on its sampler's grid (Drake's k x period), of a periodic reading at
    `read_time` made `offset` after each multiple of `period`."""
    return round((read_time - offset) / period) * period


def encode_depth(depth_m: np.ndarray, mask: np.ndarray, full_scale: float) -> np.ndarray:
    """The 16-bit depth PNG's values of a range image (m; +inf beyond the camera's far clip,
    0 nearer than its near clip, NaN where nothing was measured). See DEPTH_*."""
    depth = np.asarray(depth_m, dtype=np.float64)
    measured = mask & np.isfinite(depth) & (depth > 0.0)
    beyond = mask & np.isposinf(depth)
    encoded = np.full(depth.shape, DEPTH_NONE, dtype=np.uint16)
    value = np.round(np.where(measured, depth, 0.0) / full_scale * DEPTH_SCALE)
    encoded[measured] = np.clip(value[measured], 1, DEPTH_BEYOND - 1).astype(np.uint16)
    encoded[beyond] = DEPTH_BEYOND
    return encoded


def read_depth_png(path, full_scale: float = 0.2) -> np.ndarray:
    """Range (m) from a dataset's 16-bit depth PNG: NaN where there is no measurement
    (outside the lens's image circle, or nearer than the near clip), +inf where nothing is
    within `full_scale`."""
    value = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if value is None:
        raise ValueError(f"{path}: not a readable PNG")
    depth = value.astype(np.float64) / DEPTH_SCALE * full_scale
    depth[value == DEPTH_NONE] = np.nan
    depth[value == DEPTH_BEYOND] = np.inf
    return depth


def _write_image(path: Path, image: np.ndarray) -> None:
    """cv2.imwrite, raising OSError when it fails (it only returns False)."""
    try:
        written = cv2.imwrite(str(path), image)
    except cv2.error as e:
        raise OSError(f"{path}: could not write the image ({e})") from None
    if not written:
        raise OSError(f"{path}: could not write the image (disk full or not writable?)")


def quaternion_xyzw(R: RotationMatrix) -> tuple:
    """(x, y, z, w) of a rotation, w >= 0 (Drake's canonical sign)."""
    q = R.ToQuaternion()
    return q.x(), q.y(), q.z(), q.w()


class DatasetWriter(LeafSystem):
    """Writes a capsule dataset (see the module docstring) as the simulation runs.

    .. pydrake_system::

        name: DatasetWriter
        input_ports:
        - rgb
        - depth
        - frame_time
        - frame_pose
        - labels (with polyps)
        - <stream> (one per sensor stream)

    rgb, depth: the camera's images (depth: range in metres, +inf beyond the far clip).
    frame_time: exposure time of the camera's latest frame (s); a new value is a new frame.
    frame_pose: the camera's pose at that exposure, [R_WC row-major (9), p_WC (3)]. Each
    stream input is written as one CSV row per sample (`Stream`).

    Args:
        out_dir: folder to write (created).
        frame_check_period: how often to look for a new camera frame (s): the camera's tick.
        frame_check_offset: when within that period (s): just after the frame's delivery
            (the camera's latency, if any); the writer adds READ_DELAY.
        streams: the sensor streams (`Stream`).
        mask: (H, W) bool, the pixels inside the lens's image circle; written as mask.png,
            and depth outside it is written as "no measurement".
        depth_full_scale: metres that the 16-bit depth value 65535 stands for.
        lumen_truth: optional `lumen_truth(X_WC, depth) -> (pixel (2,), visible, point_W (3,),
            s)`, the lumen ground truth of a frame; without it lumen_truth.csv is not written.
        far_truth: optional `far_truth(range (H, W)) -> FarRegion`, the image-side
            truth through the camera's lens (`LumenTruth.far_at`: its field and its pixels'
            solid angles); without it, `far_region` of the `mask` with every pixel alike.
        texts: {file name: text} written at once (README.md, camera.yaml, sensors.yaml).
        plant_step: the discrete plant's time step (s; 0: continuous), for `state_time`.
        plant_step_first: whether the plant steps before the sensors' discrete updates at the
            same time (an unrestricted update: Drake's default with sampled output ports).
        polyps: the colon's placed polyps (anatomy/lesion_geometry.PlacedPolyp); with any,
            the `labels` input (the camera's label image) is written as instance masks and
            a COCO file (app/lesion_dataset.py).
    """

    def __init__(self, out_dir, frame_check_period: float, frame_check_offset: float = 0.0,
                 streams=(), mask=None, depth_full_scale: float = 0.2, lumen_truth=None,
                 texts=None, plant_step: float = 0.0, plant_step_first: bool = True,
                 polyps=(), far_truth=None):
        super().__init__()
        self._plant_step = float(plant_step)
        self._plant_step_first = bool(plant_step_first)
        self._out = Path(out_dir)
        self._mask = None if mask is None else np.asarray(mask, dtype=bool)
        try:  # before the run: a folder that cannot take the files is one line, exit 2
            (self._out / "Frames").mkdir(parents=True, exist_ok=True)
            for name, text in (texts or {}).items():
                (self._out / name).write_text(text)
            if self._mask is not None:
                _write_image(self._out / "mask.png",
                             np.where(self._mask, 255, 0).astype(np.uint8))
        except OSError as e:
            raise OutputError(f"{self._out}: cannot write the dataset "
                              f"({e.strerror or e})") from None
        self._depth_full_scale = float(depth_full_scale)
        self._lumen_truth = lumen_truth
        self._far_truth = far_truth
        self._rgb = self.DeclareAbstractInputPort("rgb", AbstractValue.Make(ImageRgba8U()))
        self._depth = self.DeclareAbstractInputPort("depth",
                                                    AbstractValue.Make(ImageDepth32F()))
        self._frame_time = self.DeclareVectorInputPort("frame_time", 1)
        self._frame_pose = self.DeclareVectorInputPort("frame_pose", 12)
        self._files = {}
        self._open("position", "SavedPosition.txt")
        self._open("rotation", "SavedRotationQuaternion.txt")
        self._open("frames", "frames.csv", "index,time_s")
        if lumen_truth is not None:
            self._open("lumen", "lumen_truth.csv",
                       "index,time_s,u_px,v_px,visible,x_m,y_m,z_m,s_m,far_u_px,far_v_px,"
                       "far_visible")
        self._lesions = None
        if polyps:
            self._labels = self.DeclareAbstractInputPort(
                "labels", AbstractValue.Make(ImageLabel16I()))
            try:
                self._lesions = LesionRecorder(self._out, polyps)
            except OSError as e:
                self.close()
                raise OutputError(f"{self._out}: cannot write the dataset's lesion files "
                                  f"({e.strerror or e})") from None
        self._frames_written = 0
        self._last_frame_time = None
        # Just after the frame's delivery: at the tick itself a publish runs before the
        # camera's update, and would see the previous frame.
        self.DeclarePeriodicPublishEvent(frame_check_period, frame_check_offset + READ_DELAY,
                                         self._on_frame_check)
        self._stream_ports = {}
        for stream in streams:
            port = self.DeclareVectorInputPort(stream.name, stream.size)
            self._open(stream.name, f"{stream.name}.csv",
                       ",".join(["time_s", *stream.columns]))
            delay = READ_DELAY if stream.after_update else 0.0
            self.DeclarePeriodicPublishEvent(
                stream.period, delay, lambda context, stream=stream, port=port, delay=delay:
                self._on_stream(context, stream, port, delay))
            self._stream_ports[stream.name] = port

    @property
    def frames_written(self) -> int:
        return self._frames_written

    def _open(self, key: str, name: str, header: str | None = None):
        """Opens `name` for writing (and writes its header line), before the run: a file
        that cannot be written is one line (OutputError), the files opened so far closed."""
        try:
            self._files[key] = open(self._out / name, "w")
            if header is not None:
                self._write(key, header)
        except OSError as e:
            self.close()
            raise OutputError(f"{self._out / name}: cannot write the dataset "
                              f"({e.strerror or e})") from None

    def _write(self, key: str, line: str):
        f = self._files[key]
        f.write(line + "\n")
        f.flush()

    def _on_stream(self, context, stream: Stream, port, delay: float):
        # The sample's tick, on the stream's grid (Drake's k x period), not the reading's.
        tick = sample_tick(context.get_time(), stream.period, delay)
        if tick < stream.first_sample - 0.5 * stream.period:
            return EventStatus.DidNothing()
        values = np.asarray(port.Eval(context), dtype=float)
        if stream.order is not None:
            values = values[list(stream.order)]
        values = values + 0.0  # no "-0" in the file
        t = state_time(tick, self._plant_step,
                       stream.after_update and self._plant_step_first) + stream.stamp_shift
        self._write(stream.name, ",".join([f"{t:.6f}", *(f"{v:.9g}" for v in values)]))
        return EventStatus.Succeeded()

    def _on_frame_check(self, context):
        frame_time = float(self._frame_time.Eval(context)[0])
        if not np.isfinite(frame_time) or frame_time < 0 or frame_time == self._last_frame_time:
            return EventStatus.DidNothing()
        self._last_frame_time = frame_time
        # The camera draws in an unrestricted update, alongside the plant's step at the same
        # time: it shows the state held up to its tick.
        frame_time = state_time(frame_time, self._plant_step, after_plant_update=False)
        index = self._frames_written
        rgb = self._rgb.Eval(context).data[:, :, :3]
        _write_image(self._out / "Frames" / f"FrameBuffer_{index:04d}.png",
                     cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        depth = np.array(self._depth.Eval(context).data[:, :, 0], dtype=np.float64)
        mask = self._mask if self._mask is not None else np.ones(depth.shape, dtype=bool)
        _write_image(self._out / "Frames" / f"Depth_{index:04d}.png",
                     encode_depth(depth, mask, self._depth_full_scale))
        pose = np.asarray(self._frame_pose.Eval(context), dtype=float)
        X_WC = RigidTransform(RotationMatrix(pose[:9].reshape(3, 3)), pose[9:])
        p = X_WC.translation()
        self._write("position", f"{p[0]:.9f} {p[1]:.9f} {p[2]:.9f}")
        self._write("rotation", " ".join(f"{c:.9f}" for c in quaternion_xyzw(X_WC.rotation())))
        self._write("frames", f"{index},{frame_time:.6f}")
        if self._lesions is not None:
            self._lesions.add(index, f"Frames/FrameBuffer_{index:04d}.png",
                              self._labels.Eval(context).data[:, :, 0])
        if self._lumen_truth is not None:
            pixel, visible, point_W, s = self._lumen_truth(X_WC, depth)
            x, y, z = point_W
            far = (self._far_truth(depth) if self._far_truth is not None
                   else far_region(depth, mask, self._depth_full_scale))
            self._write("lumen", f"{index},{frame_time:.6f},{pixel[0]:.3f},{pixel[1]:.3f},"
                                 f"{int(visible)},{x:.6f},{y:.6f},{z:.6f},{s:.6f},"
                                 f"{far.pixel[0]:.3f},{far.pixel[1]:.3f},{int(far.visible)}")
        self._frames_written += 1
        return EventStatus.Succeeded()

    def close(self):
        """Closes the files (they are flushed after every line already) and writes the
        lesions' COCO file."""
        for f in self._files.values():
            f.close()
        if self._lesions is not None:
            lesions, self._lesions = self._lesions, None
            lesions.close()
