"""DatasetWriter: frames, poses and sensor streams to a folder while the simulation runs.

The layout follows SimCol3D's (Rau et al., 2023: `Frames_<seq>/FrameBuffer_XXXX.png`,
`Depth_XXXX.png`, `SavedPosition_<seq>.txt`, `SavedRotationQuaternion_<seq>.txt`) with
the sensor streams added, so tools written for it need only the frame convention below:

    <out>/
      README.txt                    this layout, units and conventions
      camera.yaml                   lens model and intrinsics, image size, depth encoding
      Frames/FrameBuffer_0000.png   colour (8-bit RGB)
      Frames/Depth_0000.png         depth, 16-bit: metres = value / 65535 * depth_full_scale
      SavedPosition.txt             per frame: tx ty tz, camera centre in world (m)
      SavedRotationQuaternion.txt   per frame: qx qy qz qw, camera-to-world rotation
      frames.csv                    per frame: index, time (s)
      lumen_truth.csv               per frame: index, time, u, v (px), visible, x, y, z (m), s (m)
      <stream>.csv                  one per sensor stream (IMU, magnetometer, AHRS, ...)

World frame: z up (anterior), x to the patient's left, y to the head, table top at z = 0
(right-handed; SimCol3D's Unity frame is left-handed). Camera frame: +z along the optical
axis, +x right and +y down in the image (OpenCV/Drake convention). Every file is written and
flushed as the simulation goes, so an interrupted run keeps what it recorded.
"""

from pathlib import Path

import cv2
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import EventStatus, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U

from capsule_drake.capsule.model import rotation_from_quaternion

README = __doc__

# How long after a camera tick the writer looks for the new frame (s). The discrete plant's
# state then is the one after its update at the tick: the pose written is at most one plant
# step (1 ms) newer than the image.
FRAME_CHECK_DELAY = 1e-6


class DatasetWriter(LeafSystem):
    """Writes a capsule dataset (see the module docstring) as the simulation runs.

    .. pydrake_system::

        name: DatasetWriter
        input_ports:
        - rgb
        - depth
        - frame_time
        - capsule_state
        - lumen
        - <stream> (one per sensor stream)

    rgb, depth: the camera's images (depth in metres, NaN/inf where nothing was hit).
    frame_time: time of the camera's latest frame (s); a new value means a new frame.
    capsule_state: the capsule's [quaternion wxyz, p_WC, w, v]; with X_BC it gives the
    camera pose. lumen: [u, v, visible, x, y, z, s] from LumenTruth. Each stream input is
    written as one CSV row per `period`.

    Args:
        out_dir: folder to write (created).
        X_BC: camera pose in the capsule body frame.
        frame_check_period: how often to look for a new camera frame (s); at least the
            camera's fastest frame rate.
        streams: list of (name, column names, period) for the sensor CSV files.
        depth_full_scale: metres that the 16-bit depth value 65535 stands for.
        camera_yaml: text for camera.yaml (lens model and intrinsics).
    """

    def __init__(self, out_dir, X_BC: RigidTransform, frame_check_period: float,
                 streams=(), depth_full_scale: float = 0.2, camera_yaml: str = ""):
        super().__init__()
        self._out = Path(out_dir)
        (self._out / "Frames").mkdir(parents=True, exist_ok=True)
        (self._out / "README.txt").write_text(README)
        (self._out / "camera.yaml").write_text(
            camera_yaml + f"depth_png_full_scale_m: {depth_full_scale}\n")
        self._X_BC = X_BC
        self._depth_full_scale = float(depth_full_scale)
        self._rgb = self.DeclareAbstractInputPort("rgb", AbstractValue.Make(ImageRgba8U()))
        self._depth = self.DeclareAbstractInputPort("depth",
                                                    AbstractValue.Make(ImageDepth32F()))
        self._frame_time = self.DeclareVectorInputPort("frame_time", 1)
        self._state = self.DeclareVectorInputPort("capsule_state", 13)
        self._lumen = self.DeclareVectorInputPort("lumen", 7)
        self._files = {
            "position": open(self._out / "SavedPosition.txt", "w"),
            "rotation": open(self._out / "SavedRotationQuaternion.txt", "w"),
            "frames": open(self._out / "frames.csv", "w"),
            "lumen": open(self._out / "lumen_truth.csv", "w"),
        }
        self._write("frames", "index,time_s")
        self._write("lumen", "index,time_s,u_px,v_px,visible,x_m,y_m,z_m,s_m")
        self._frames_written = 0
        self._last_frame_time = None
        # Just after each camera tick: at the tick itself a publish runs before the camera's
        # update, and would see the previous frame (and pair it with the newer pose).
        self.DeclarePeriodicPublishEvent(frame_check_period, FRAME_CHECK_DELAY,
                                         self._on_frame_check)
        self._stream_ports = {}
        for name, columns, period in streams:
            port = self.DeclareVectorInputPort(name, len(columns))
            self._files[name] = open(self._out / f"{name}.csv", "w")
            self._write(name, ",".join(["time_s", *columns]))
            self.DeclarePeriodicPublishEvent(
                period, 0.0, lambda context, name=name, port=port: self._on_stream(
                    context, name, port))
            self._stream_ports[name] = port

    @property
    def frames_written(self) -> int:
        return self._frames_written

    def _write(self, key: str, line: str):
        f = self._files[key]
        f.write(line + "\n")
        f.flush()

    def _on_stream(self, context, name, port):
        values = port.Eval(context)
        self._write(name, ",".join([f"{context.get_time():.6f}",
                                    *(f"{v:.9g}" for v in values)]))
        return EventStatus.Succeeded()

    def _on_frame_check(self, context):
        frame_time = float(self._frame_time.Eval(context)[0])
        if frame_time < 0 or frame_time == self._last_frame_time:
            return EventStatus.DidNothing()
        self._last_frame_time = frame_time
        index = self._frames_written
        rgb = self._rgb.Eval(context).data[:, :, :3]
        cv2.imwrite(str(self._out / "Frames" / f"FrameBuffer_{index:04d}.png"),
                    cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        depth = np.array(self._depth.Eval(context).data[:, :, 0], dtype=np.float64)
        depth[~np.isfinite(depth)] = self._depth_full_scale
        encoded = np.clip(np.round(depth / self._depth_full_scale * 65535.0), 0, 65535)
        cv2.imwrite(str(self._out / "Frames" / f"Depth_{index:04d}.png"),
                    encoded.astype(np.uint16))
        state = self._state.Eval(context)
        X_WC = RigidTransform(RotationMatrix(rotation_from_quaternion(state[:4])),
                              state[4:7]).multiply(self._X_BC)
        q_WC = X_WC.rotation().ToQuaternion()
        p = X_WC.translation()
        self._write("position", f"{p[0]:.9f} {p[1]:.9f} {p[2]:.9f}")
        self._write("rotation", f"{q_WC.x():.9f} {q_WC.y():.9f} {q_WC.z():.9f} {q_WC.w():.9f}")
        self._write("frames", f"{index},{frame_time:.6f}")
        u, v, visible, x, y, z, s = self._lumen.Eval(context)
        self._write("lumen", f"{index},{frame_time:.6f},{u:.3f},{v:.3f},{int(visible)},"
                             f"{x:.6f},{y:.6f},{z:.6f},{s:.6f}")
        self._frames_written += 1
        return EventStatus.Succeeded()

    def close(self):
        """Closes the files (they are flushed after every line already)."""
        for f in self._files.values():
            f.close()


def read_depth_png(path, full_scale: float = 0.2) -> np.ndarray:
    """Metric depth (m) from a dataset's 16-bit depth PNG."""
    value = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return value.astype(np.float64) / 65535.0 * full_scale
