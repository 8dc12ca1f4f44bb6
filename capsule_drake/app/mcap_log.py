"""ChannelLogger: a run's signals as ROS 2 messages, written as the run goes to its channel
outputs (the MCAP file, Foxglove, ROS 2 topics: app/channels.py, whose table they follow).

A scenario with any of `outputs.mcap`, `foxglove`, `ros2` (`capsule-sim run|record|teleop
--mcap FILE`, `--foxglove`, `--ros2`) has one ChannelLogger beside the station. It writes,
for whatever the scenario has (a topic whose source is switched off is absent):

    topic                              type (package/msg/...)       when; frame_id
    /tf                                tf2_msgs TFMessage           log_period; world -> capsule,epm
    /tf_static                         tf2_msgs TFMessage           once; capsule -> camera, sensors
    /scene/markers                     visualization_msgs MarkerArray   once (latched); the colon's
                                       wall (world), capsule and EPM (app/scene_markers.py)
    /capsule/contact/wrench            geometry_msgs WrenchStamped  log_period; capsule
    /capsule/contact/peak_pressure     sensor_msgs FluidPressure Pa log_period; capsule
    /capsule/contact/wall_pressure/peak            sensor_msgs Image, 32FC1 kPa  every 1 s
    /capsule/contact/wall_pressure/above_injury    sensor_msgs Image, 32FC1 s    every 1 s
    /capsule/contact/wall_pressure/above_ischaemia sensor_msgs Image, 32FC1 s    every 1 s
                                       (the wall's patches unrolled, physics/wall_pressure.py:
                                       frame colon_wall_map; with a pressure field)
    /capsule/camera/image_raw          sensor_msgs Image, rgb8      each frame; camera optical
    /capsule/camera/camera_info        sensor_msgs CameraInfo       each frame
    /capsule/camera/depth/image_raw    sensor_msgs Image, 32FC1 m   each frame (render_depth)
    /capsule/camera/depth/camera_info  sensor_msgs CameraInfo       each frame (render_depth)
    /capsule/lumen_truth/pixel         geometry_msgs PointStamped   each frame; capsule_camera_image
    /capsule/lumen_truth/point         geometry_msgs PointStamped   each frame; world
    /capsule/lumen_truth/marker        visualization_msgs ImageMarker   each frame
    /capsule/lumen_truth/far_pixel     geometry_msgs PointStamped   each frame; capsule_camera_image
                                       (the image-side truth, far_region: z 1 = lumen in view)
    /capsule/lumen_truth/far_marker    visualization_msgs ImageMarker   each frame
    /capsule/lumen_tracker/pixel       geometry_msgs PointStamped   each frame; capsule_camera_image
    /capsule/lumen_tracker/marker      visualization_msgs ImageMarker   each frame
    /capsule/lesions/marker            visualization_msgs ImageMarker   each frame (with polyps):
                                       each polyp in view its box (POLYGON, id = its index)
    /capsule/imu/data                  sensor_msgs Imu              its rate; capsule_imu
    /capsule/magnetometer              sensor_msgs MagneticField T  its rate; capsule_magnetometer
    /capsule/magnetic_array/hall_<i>   sensor_msgs MagneticField T  its rate; capsule_hall_<i>
    /capsule/contact_sensor/wrench     geometry_msgs WrenchStamped  its rate; capsule
    /capsule/localizer/pose            geometry_msgs PoseWithCovarianceStamped   its period; world

Frames (REP 103: right-handed, metres, radians): `world` is the simulator's W (z up, x to the
patient's left, y to the head; the patient supine, table top at z = 0); `capsule` its body
frame B (origin at the centre, +z along the axis toward the camera dome: the capsule's
"forward" is z, not REP 103's x, so that the frame is the one of capsule.state and the
model); `capsule_camera_optical_frame` the camera C (REP 103's optical convention: +z along
the optical axis, +x right, +y down); `capsule_imu`, `capsule_magnetometer`, `capsule_hall_<i>`
the sensor frames S of their configs; `epm` the external magnet E (centre, +z its moment);
`capsule_camera_image` (not a tf frame) the image's pixel coordinates, for the lumen's pixels;
`colon_wall_map` (not a tf frame either) the unrolled wall's patches: column i the arc
length from i to i + 1 patch lengths from the anus, row j the angle around the centreline
from j to j + 1 patch angles (from the frame's normal toward its binormal, as the colon's
wall_radius(s, theta)).

Times: header.stamp is simulated time from 0 (so the file starts at 1970-01-01 in a viewer):
the time of the plant state the value describes, the time the dataset's files give the same
sample (`PlantTiming`, on app/dataset.py's `state_time`). A discrete plant steps before the
sensors sample at the same time, so a sensor's sample at its tick t (IMU, AHRS, magnetometer,
Hall sensors, contact sensor, and the localiser's estimate on them) measures the state one
plant step later and is stamped t + step; a camera frame shows the state held up to its
exposure; /tf, the contact wrench and the lumen truth show the state held when they are read.
So the capsule's /tf at a message's stamp is the state the message saw, where /tf has a
sample at that time (at every stamp when outputs.log_period is the plant's step; otherwise a
viewer interpolates between /tf samples). The MCAP log time is when the simulation produced
the message: after a camera's latency or a detector's run, and for a sensor's sample one
plant step before its stamp (the discrete plant computes the next step's state first).

Each event's messages are written with Ctrl-C and the termination signals held, so an
interrupt lands between messages; `close()` (the run loop's close hook) then finishes the
file (its last chunk, index and footer) however the run ended.
"""

import contextlib
import errno
import math
import os
import stat
from pathlib import Path

import numpy as np
import trimesh
from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from mcap.writer import CompressionType, Writer
# mcap_ros2's own Writer uses this to encode; it has no public encoder and registers its
# channels without the QoS metadata rosbag2 replays from.
from mcap_ros2._dynamic import serialize_dynamic
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.plant import ContactResults
from pydrake.systems.framework import EventStatus, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I, ImageRgba8U

from capsule_drake.anatomy.source import lesion_scene
from capsule_drake.app.signals import signals_held
from capsule_drake.capsule.camera_walls import lesion_labels
from capsule_drake.capsule.imu import imu_channels
from capsule_drake.capsule.model import CAPSULE_BODY, rotation_from_quaternion
from capsule_drake.epm.mount import EPM_BODY
from capsule_drake.epm.poses import stage_joint_positions
from capsule_drake.lifetime import id_values
from capsule_drake.app.dataset import READ_DELAY, PlantTiming, sample_tick
from capsule_drake.app.lesion_dataset import box_of
from capsule_drake.app.outputs import MCAP_LIBRARY, check_file_output, is_capsule_mcap
from capsule_drake.app.channels import ChannelWriter
from capsule_drake.app.scene_markers import scene_markers, wall_triangles
from capsule_drake.anatomy.source import load_colon
from capsule_drake.capsule.model import capsule_model
from capsule_drake.app.ros2_messages import (NANOSECONDS, header, offered_qos_profiles,
                                            quaternion_wxyz, schema_text, transform_stamped,
                                            vector3)
from capsule_drake.physics.contact.foundation import empty_wall_contact
from capsule_drake.physics.contact_monitor import (capsule_contact_wrench_W,
                                                   peak_contact_pressure)
from capsule_drake.physics.wall_pressure import WALL_PRESSURE_SYSTEM

WORLD = "world"
CAPSULE = "capsule"
CAMERA = "capsule_camera_optical_frame"
# The frame_id of the lumen's pixel topics: not a tf frame (x, y are pixels, not metres, so
# that a 3-D viewer places nothing), the camera's image (u right, v down, OpenCV's pixel
# convention: the first pixel's centre at (0, 0)).
PIXELS = "capsule_camera_image"
IMU = "capsule_imu"
MAGNETOMETER = "capsule_magnetometer"
EPM = "epm"
WALL_MAP = "colon_wall_map"
# Seconds between the wall's pressure maps: a map holds the whole run so far (it only grows),
# so its changes come at the pace the capsule moves from patch to patch.
WALL_MAP_PERIOD = 1.0


def hall_frame(i: int) -> str:
    return f"capsule_hall_{i}"


def _ns(t: float) -> int:
    return int(round(t * NANOSECONDS))


def _quaternion_of(R: RotationMatrix) -> np.ndarray:
    q = R.ToQuaternion()
    return np.array([q.w(), q.x(), q.y(), q.z()])


def check_mcap_path(path, replace: bool | None = False, expected_bytes: float = 0.0) -> Path:
    """The file `--mcap` names, checked before anything is simulated (app/outputs.py's
    `check_file_output`): a regular file or a new one, not a link, in a folder that exists
    and can be written, with room for `expected_bytes`; an existing file is refused unless
    `replace` (None: the command has no --force to offer) and it is an MCAP log this
    simulator wrote. The command line checks it with its other outputs (`plan_outputs`).
    Raises OutputError (one line)."""
    return check_file_output(path, "--mcap", replace=replace, previous=is_capsule_mcap,
                             previous_name="an MCAP log written by capsule-sim",
                             expected_bytes=expected_bytes)


class McapWriteError(OSError):
    """Writing the MCAP log failed (a full disk, an I/O error, a file size limit): one line
    naming the file; the file is left as far as it was written, unless that is not even
    its header (then it is removed: `Ros2McapFile._failed`)."""


class Ros2McapFile:
    """An MCAP file of ROS 2 messages (profile ros2, schemas ros2msg, messages CDR) being
    written: each type's schema and each topic's channel registered at its first message,
    the channel with the QoS rosbag2 replays it with; messages are gathered into chunks
    (`chunk_size` bytes, compressed) that are written as they fill.

    The file is created at the first message; `close()` finishes it (idempotent). A write
    that fails (at a message, or when the file is finished, flushed and synced) raises
    McapWriteError once, naming the file, and leaves `error` set; the file is closed and
    later messages are refused. A file that failed before its header was on disk is
    removed: it holds nothing to read, and the retry's --force (which replaces only an MCAP
    log of this simulator's) would refuse it.
    """

    def __init__(self, path, compression: str = "zstd", chunk_size: int = 1 << 20):
        self.path = Path(path)
        self._compression = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                             "none": CompressionType.NONE}[compression]
        self._chunk_size = int(chunk_size)
        self._stream = None
        self._writer = None
        self._schemas = {}    # type name -> (schema id, encoder)
        self._channels = {}   # topic -> (channel id, encoder, type name)
        self.messages = 0
        self.created = False  # whether this created (or emptied) the file at `path`
        self.closed = False
        self.error: str | None = None  # why writing failed (one line), or None

    def _open(self):
        # Not through a symbolic link, and without blocking on a named pipe (no reader:
        # ENXIO); only a regular file is written (the command line checked the path, but
        # it may have changed since).
        flags = (os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NONBLOCK
                 | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0))
        fd = os.open(self.path, flags, 0o666)
        self.created = True
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise OSError(errno.EINVAL, "not a regular file")
        os.set_blocking(fd, True)
        stream = os.fdopen(fd, "wb")
        try:
            writer = Writer(stream, chunk_size=self._chunk_size, compression=self._compression)
            writer.start(profile=Profile.ROS2, library=MCAP_LIBRARY)
            # rosbag2 reads the channels' QoS with the metadata format its "rosbag2" record
            # names; an empty one means version 8 and before: integer policies (ros2_messages).
            writer.add_metadata("rosbag2", {"serialized_metadata": ""})
        except BaseException:
            with contextlib.suppress(OSError):
                stream.close()
            raise
        self._stream, self._writer = stream, writer

    def _channel(self, topic: str, type_name: str, latched: bool):
        if self._writer is None:
            self._open()
        if type_name not in self._schemas:
            text = schema_text(type_name)
            schema_id = self._writer.register_schema(type_name, SchemaEncoding.ROS2,
                                                     text.encode())
            self._schemas[type_name] = (schema_id, serialize_dynamic(type_name, text)[type_name])
        schema_id, encoder = self._schemas[type_name]
        channel_id = self._writer.register_channel(
            topic, MessageEncoding.CDR, schema_id,
            {"offered_qos_profiles": offered_qos_profiles(latched, depth=1 if latched else 10)})
        self._channels[topic] = (channel_id, encoder, type_name)
        return self._channels[topic]

    # As an output of a ChannelWriter (app/channels.py): a failure stops the run.
    fatal = True

    @property
    def name(self) -> str:
        return f"the MCAP log {self.path}"

    def write(self, topic: str, type_name: str, message: dict, log_time_ns: int,
              latched: bool = False):
        """Encodes `message` (a dict of the type's fields) and adds it to `topic`."""
        self._add(topic, type_name, latched, message, None, log_time_ns)

    def publish(self, topic: str, spec, message: dict, data: bytes, log_time_ns: int):
        """Adds a message the ChannelWriter encoded (`data`, CDR) to `topic`."""
        self._add(topic, spec.type_name, spec.latched, message, data, log_time_ns)

    def _add(self, topic, type_name, latched, message, data, log_time_ns):
        if self.closed or self.error is not None:
            raise RuntimeError(f"{self.path}: the MCAP log is closed")
        try:
            channel = self._channels.get(topic) or self._channel(topic, type_name, latched)
            channel_id, encoder, known_type = channel
            if known_type != type_name:
                raise ValueError(f"topic {topic} carries {known_type}, not {type_name}")
            self._writer.add_message(channel_id, log_time=log_time_ns,
                                     data=encoder(message) if data is None else data,
                                     publish_time=log_time_ns, sequence=self.messages)
        except OSError as e:
            raise self._failed(e) from None
        self.messages += 1

    def _failed(self, e: OSError) -> McapWriteError:
        """Notes a failed write, closes the file (dropping what is unwritten; removing it
        if not even its header is on disk) and returns the error to raise."""
        stream, self._writer, self._stream = self._stream, None, None
        if stream is not None:
            with contextlib.suppress(OSError):  # its flush fails again; the file is closed
                stream.close()
        if self.error is None:
            kept = "the file is incomplete"
            if (self.created and self.path.is_file() and not self.path.is_symlink()
                    and not is_capsule_mcap(self.path)):
                with contextlib.suppress(OSError):
                    self.path.unlink()
                    kept = "nothing of it could be kept (removed)"
            reason = e.strerror or str(e)
            self.error = (f"{self.path}: could not write the MCAP log ({reason}) after "
                          f"{self.messages} messages; {kept}")
        return McapWriteError(self.error)

    def close(self):
        """Writes the last chunk, the summary and the footer, flushes and syncs the file
        and closes it, which is closed even if finishing it fails (McapWriteError, once).
        Idempotent: later calls do nothing, as does a close after a write that failed."""
        if self.closed:
            return
        self.closed = True
        if self.error is not None:
            return
        writer, stream = self._writer, self._stream
        try:
            if writer is not None:
                writer.finish()
            if stream is not None:
                stream.flush()
                os.fsync(stream.fileno())
        except OSError as e:
            raise self._failed(e) from None
        finally:
            self._writer = None
            if self._stream is not None:
                self._stream = None
                try:
                    stream.close()
                except OSError as e:
                    raise self._failed(e) from None


# --- What is logged: one stream per source, each read by its own periodic event ------------

class _Stream:
    """A source of messages: the station outputs it reads (name -> vector size, or a model
    value for an abstract port), when (every `period` s from `offset`), and `write`;
    `timing` the plant's, for the stamps."""

    inputs: dict = {}
    period: float = 0.01
    offset: float = 0.0
    timing: PlantTiming = PlantTiming()

    def tick(self, t: float) -> float:
        """The sample time (on the stream's grid) that the reading at t follows."""
        return sample_tick(t, self.period, self.offset)

    def write(self, log: Ros2McapFile, t: float, values: dict) -> None:
        raise NotImplementedError


class _PosesStream(_Stream):
    """/tf (world -> capsule, world -> epm) and the capsule's contact wrench, at the run's
    log period (read when logs.npz is), stamped with the time of the state they show: the
    sample time itself when it is on the plant's grid. The EPM's frame: its body's pose
    when the plant has it (arm, servoed stage), else the kinematic stage's axes (yaw about
    z, then pitch about y; +z its moment) from epm.pose."""

    def __init__(self, period, capsule_geometries, epm_body_index=None, num_bodies=0,
                 timing: PlantTiming = PlantTiming(), wall: bool = False):
        self.period = period
        self.timing = timing
        # Their values: the ids a plant returns keep it alive (capsule_drake/lifetime.py).
        self._geometries = id_values(capsule_geometries)
        self._epm_index = epm_body_index
        self.inputs = {"capsule.state": 13, "epm.pose": 6,
                       "contact_results": AbstractValue.Make(ContactResults())}
        if epm_body_index is not None:
            self.inputs["body_poses"] = AbstractValue.Make([RigidTransform()] * num_bodies)
        if wall:   # the compliant wall's own force (its foundation realisation)
            self.inputs["contact.wall"] = AbstractValue.Make(empty_wall_contact())

    def epm_pose(self, values) -> tuple[np.ndarray, np.ndarray]:
        if self._epm_index is not None:
            X_WE = values["body_poses"][self._epm_index]
            return X_WE.translation(), _quaternion_of(X_WE.rotation())
        pose = np.asarray(values["epm.pose"])
        _, _, _, yaw, pitch = stage_joint_positions(pose[:3], pose[3:])
        R = RotationMatrix.MakeZRotation(yaw).multiply(RotationMatrix.MakeYRotation(pitch))
        return pose[:3], _quaternion_of(R)

    def write(self, log, t, values):
        ns = _ns(self.timing.held(t))
        state = np.asarray(values["capsule.state"])
        q_WB = state[:4] / np.linalg.norm(state[:4])
        p_WE, q_WE = self.epm_pose(values)
        log.write("/tf", "tf2_msgs/msg/TFMessage", {"transforms": [
            transform_stamped(ns, WORLD, CAPSULE, state[4:7], q_WB),
            transform_stamped(ns, WORLD, EPM, p_WE, q_WE)]}, _ns(t))
        R_WB = rotation_from_quaternion(q_WB)
        wall = values.get("contact.wall")
        torque_W, force_W = capsule_contact_wrench_W(values["contact_results"], self._geometries,
                                                     state[4:7], wall)
        log.write("/capsule/contact/wrench", "geometry_msgs/msg/WrenchStamped", {
            "header": header(ns, CAPSULE),
            "wrench": {"force": vector3(R_WB.T @ force_W),
                       "torque": vector3(R_WB.T @ torque_W)}}, _ns(t))
        # The contact's peak pressure (Pa; NaN for point contact, which has none): what the
        # thresholds of mucosal injury (physics/tissue.py) are stated in.
        log.write("/capsule/contact/peak_pressure", "sensor_msgs/msg/FluidPressure", {
            "header": header(ns, CAPSULE),
            "fluid_pressure": peak_contact_pressure(values["contact_results"], wall),
            "variance": 0.0}, _ns(t))


def _diagonal(variance: float) -> list[float]:
    return [float(variance), 0.0, 0.0, 0.0, float(variance), 0.0, 0.0, 0.0, float(variance)]


class _ImuStream(_Stream):
    """sensor_msgs/Imu in the IMU's frame: its samples, their white-noise variance per
    sample as covariance, and the AHRS's orientation of that frame in world when there is
    an AHRS, else orientation_covariance[0] = -1 (ROS's "no orientation given").

    The AHRS's orientation is of the state the same sample saw (it steps each sample one
    period forward: capsule/ahrs.py). Its first estimate comes with the second sample:
    before it the AHRS holds a placeholder (the identity), so the first message says "no
    orientation". The AHRS gives no uncertainty, so orientation_covariance is all zeros,
    which ROS reads as "covariance unknown" (not "exact"): tilt (roll, pitch) is corrected
    toward the accelerometer's vertical, but heading (yaw) is the gyro's integral only, with
    no absolute reference (no magnetometer in the filter), and drifts with the gyro's bias
    for as long as the run lasts.
    """

    def __init__(self, config, with_ahrs: bool, timing: PlantTiming = PlantTiming()):
        self.period = 1.0 / config.sample_rate
        self.offset = READ_DELAY
        self.timing = timing
        # The AHRS updates half a period after each sample (capsule/ahrs.py): the sample at
        # one period is the first read with its estimate.
        self._first_estimate = self.period
        self._R_BS = config.X_BS().rotation()
        accel, gyro = imu_channels(config)
        self._accel_cov = _diagonal(accel.white_sigma ** 2)
        self._gyro_cov = _diagonal(gyro.white_sigma ** 2)
        self.inputs = {"capsule.imu.accel": 3, "capsule.imu.gyro": 3}
        if with_ahrs:
            self.inputs["capsule.ahrs.q_WB"] = 4

    def write(self, log, t, values):
        tick = self.tick(t)
        stamp = _ns(self.timing.sampled(tick))
        if ("capsule.ahrs.q_WB" in values
                and tick >= self._first_estimate - 0.5 * self.period):
            q_WB = np.asarray(values["capsule.ahrs.q_WB"])
            R_WS = RotationMatrix(rotation_from_quaternion(q_WB)).multiply(self._R_BS)
            orientation, orientation_cov = quaternion_wxyz(_quaternion_of(R_WS)), [0.0] * 9
        else:
            orientation, orientation_cov = quaternion_wxyz([1.0, 0.0, 0.0, 0.0]), [-1.0] + [0.0] * 8
        log.write("/capsule/imu/data", "sensor_msgs/msg/Imu", {
            "header": header(stamp, IMU),
            "orientation": orientation, "orientation_covariance": orientation_cov,
            "angular_velocity": vector3(values["capsule.imu.gyro"]),
            "angular_velocity_covariance": self._gyro_cov,
            "linear_acceleration": vector3(values["capsule.imu.accel"]),
            "linear_acceleration_covariance": self._accel_cov}, _ns(t))


class _FieldStream(_Stream):
    """sensor_msgs/MagneticField (T) of 3-axis field sensors, one topic and frame each, with
    their white-noise variance per sample as covariance."""

    def __init__(self, port: str, topics_frames, sample_rate: float, noise_sigma: float,
                 timing: PlantTiming = PlantTiming()):
        self.period = 1.0 / sample_rate
        self.offset = READ_DELAY
        self.timing = timing
        self._port = port
        self._topics_frames = list(topics_frames)
        self._cov = _diagonal(noise_sigma ** 2)
        self.inputs = {port: 3 * len(self._topics_frames)}

    def write(self, log, t, values):
        stamp = _ns(self.timing.sampled(self.tick(t)))
        B = np.asarray(values[self._port]).reshape(-1, 3)
        for (topic, frame), field in zip(self._topics_frames, B):
            log.write(topic, "sensor_msgs/msg/MagneticField", {
                "header": header(stamp, frame), "magnetic_field": vector3(field),
                "magnetic_field_covariance": self._cov}, _ns(t))


class _ContactSensorStream(_Stream):
    """The contact sensor's reading, a force in the capsule frame (no torque)."""

    def __init__(self, config, timing: PlantTiming = PlantTiming()):
        self.period = 1.0 / config.sample_rate
        self.offset = READ_DELAY
        self.timing = timing
        self.inputs = {"capsule.contact_sensor.F_B": 3}

    def write(self, log, t, values):
        log.write("/capsule/contact_sensor/wrench", "geometry_msgs/msg/WrenchStamped", {
            "header": header(_ns(self.timing.sampled(self.tick(t))), CAPSULE),
            "wrench": {"force": vector3(values["capsule.contact_sensor.F_B"]),
                       "torque": vector3([0.0, 0.0, 0.0])}}, _ns(t))


class _PoseEstimateStream(_Stream):
    """The localiser's estimate of the capsule's pose in world with its covariance, turned
    from the estimator's [position, rotation vector on the body side] to ROS's [position,
    rotation about the world's fixed axes]: dtheta_W = R_WB dtheta_B. It updates half a
    period after the sensors sample, on those samples: stamped as they are."""

    def __init__(self, config, timing: PlantTiming = PlantTiming()):
        self.period = config.period
        self.offset = 0.5 * config.period + READ_DELAY
        self.timing = timing
        self.inputs = {"capsule.localizer.pose": 7, "capsule.localizer.covariance": 36}

    def write(self, log, t, values):
        pose = np.asarray(values["capsule.localizer.pose"])
        q_WB = pose[:4] / np.linalg.norm(pose[:4])
        T = np.eye(6)
        T[3:, 3:] = rotation_from_quaternion(q_WB)
        covariance = T @ np.asarray(values["capsule.localizer.covariance"]).reshape(6, 6) @ T.T
        log.write("/capsule/localizer/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", {
            "header": header(_ns(self.timing.sampled(self.tick(t))), WORLD),
            "pose": {"pose": {"position": vector3(pose[4:7]),
                              "orientation": quaternion_wxyz(q_WB)},
                     "covariance": [float(c) for c in covariance.ravel()]}}, _ns(t))


class _WallPressureStream(_Stream):
    """The map of the wall's pressure (physics/wall_pressure.py, the `map` output of the
    run's WallPressureMap) as three images of the colon unrolled, one pixel a patch (column
    i: along, from the anus; row j: around, frame `colon_wall_map`), 32FC1: each patch's
    peak pressure so far (kPa) and its longest spell above each threshold so far (s; 0
    where it never went above, or was never touched). Every WALL_MAP_PERIOD from 1 s on,
    stamped with the state its last sample saw (held up to that sample's time, as /tf's);
    none before the first sample."""

    def __init__(self, layout, period: float = WALL_MAP_PERIOD,
                 timing: PlantTiming = PlantTiming()):
        self.period, self.offset = period, period
        self.timing = timing
        self._layout = layout
        self.inputs = {f"{WALL_PRESSURE_SYSTEM}.map": layout.size}

    def _image(self, log, topic, stamp, values, now):
        H, W = values.shape
        log.write(topic, "sensor_msgs/msg/Image", {
            "header": header(stamp, WALL_MAP), "height": H, "width": W, "encoding": "32FC1",
            "is_bigendian": 0, "step": 4 * W,
            "data": np.ascontiguousarray(values, dtype="<f4").tobytes()}, now)

    def write(self, log, t, values):
        wall = self._layout.map_of(values[f"{WALL_PRESSURE_SYSTEM}.map"])
        if wall.samples == 0:
            return
        stamp, now = _ns(self.timing.held(wall.last_time)), _ns(t)
        self._image(log, "/capsule/contact/wall_pressure/peak", stamp, wall.peak.T / 1000.0,
                    now)
        for name, longest in wall.longest_above.items():
            self._image(log, f"/capsule/contact/wall_pressure/above_{name}", stamp, longest.T,
                        now)


def camera_info(lens, stamp_ns: int) -> dict:
    """sensor_msgs/CameraInfo of a capsule lens (perception/lens.py). The fisheye models
    (equidistant, kannala_brandt) are OpenCV's fisheye model, which ROS names "equidistant"
    (sensor_msgs/distortion_models.hpp; image_geometry undistorts it with cv::fisheye) with
    D = [k1, k2, k3, k4] (all 0 for the ideal equidistant lens); the pinhole lens is
    "plumb_bob", D = [k1, k2, p1, p2, k3]. K and P hold fx, fy, cx, cy: the pixel convention
    (the first pixel's centre at (0, 0)) is ROS's and OpenCV's. A monocular camera: R = I,
    P = [K | 0]."""
    config = lens.config
    if lens.is_fisheye:
        model = "equidistant"
        d = [0.0] * 4 if lens.model == "equidistant" else [float(k) for k in config.kb_coefficients]
    else:
        model, d = "plumb_bob", [float(k) for k in config.radtan_coefficients]
    fx, fy, cx, cy = lens.fx, lens.fy, lens.cx, lens.cy
    return {"header": header(stamp_ns, CAMERA), "height": lens.height, "width": lens.width,
            "distortion_model": model, "d": d,
            "k": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
            "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            "p": [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
            "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}


def depth_for_ros(range_m: np.ndarray, ray_z: np.ndarray, in_field: np.ndarray) -> np.ndarray:
    """A REP 118 depth image (float32, metres along the optical axis) from the camera's
    range image (metres along each pixel's ray; 0 nearer than `near`, +inf beyond `far` and
    outside the lens's field), each pixel's unit-ray z component and the lens's field mask.
    Following REP 117: -inf where tissue is too near to measure, +inf where nothing is within
    range, NaN where the pixel sees nothing (outside the image circle, or a ray at or beyond
    90 degrees from the axis, where a z-depth says nothing)."""
    depth = (range_m * ray_z).astype(np.float32)
    depth[range_m <= 0.0] = -np.inf
    depth[np.isinf(range_m)] = np.inf
    depth[~(in_field & (ray_z > 0.0))] = np.nan
    return depth


def _image_marker(stamp_ns: int, ns: str, pixel, visible: bool, radius: float, rgb) -> dict:
    color = {"r": float(rgb[0]), "g": float(rgb[1]), "b": float(rgb[2]), "a": 1.0}
    return {"header": header(stamp_ns, CAMERA), "ns": ns, "id": 0, "type": 0,  # CIRCLE
            "action": 0 if visible else 1,  # ADD, REMOVE
            "position": {"x": float(pixel[0]) if visible else 0.0,
                         "y": float(pixel[1]) if visible else 0.0, "z": 0.0},
            "scale": float(radius), "outline_color": color, "filled": 0,
            "fill_color": {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.0},
            "lifetime": {"sec": 0, "nanosec": 0}, "points": [], "outline_colors": []}


class _CameraStream(_Stream):
    """Each new camera frame (frame_info's count changed), read just after the camera (and
    the tracker, which runs `latency` + 1 us after the tick) delivered it:

    - the colour image (rgb8) and, when rendered, the depth (32FC1, `depth_for_ros`), each
      with a CameraInfo, stamped with the time of the state the frame shows: its exposure
      (the next plant step's time when rounding puts the exposure just after a step), as
      the dataset's frames.csv;
    - the lumen truth: its pixel (PointStamped: x = u, y = v in pixels, z = 1 visible or 0;
      NaN pixel when behind the lens) and its 3-D target point in world, stamped with the
      time of the capsule's state it is computed from, the one held at the frame's delivery
      (with no latency and a discrete plant, one plant step after the exposure), and an
      ImageMarker (green circle) stamped as the image;
    - with a tracker, its detection on that frame: pixel (x = u, y = v, NaN when not found;
      z = its confidence in [0, 1]) and an ImageMarker (orange circle), stamped as the image
      so a viewer overlays it; a frame without a detection gets a REMOVE marker.
    """

    def __init__(self, lens, tick: float, latency: float, render_depth: bool,
                 with_tracker: bool, timing: PlantTiming = PlantTiming(),
                 lesion_labels: dict | None = None):
        self.period = tick
        self.offset = latency + 2.0 * READ_DELAY
        self.timing = timing
        self._lens = lens
        rays, self._in_field = lens.pixel_rays()
        self._ray_z = rays[..., 2]
        self._depth = render_depth
        self._tracker = with_tracker
        self._marker_radius = 0.04 * min(lens.width, lens.height)
        W, H = lens.width, lens.height
        self.inputs = {"capsule.camera.frame_info": 4,
                       "capsule.camera.rgb_image": AbstractValue.Make(ImageRgba8U(W, H)),
                       "capsule.lumen.lumen_pixel": 2, "capsule.lumen.lumen_visible": 1,
                       "capsule.lumen.lumen_point_W": 4, "capsule.lumen.far_pixel": 2,
                       "capsule.lumen.far_visible": 1}
        if render_depth:
            self.inputs["capsule.camera.depth_image"] = AbstractValue.Make(ImageDepth32F(W, H))
        if with_tracker:
            self.inputs.update({"capsule.lumen_tracker.lumen_pixel": 2,
                                "capsule.lumen_tracker.lumen_confidence": 1,
                                "capsule.lumen_tracker.lumen_visible": 1})
        self._lesions = dict(lesion_labels or {})
        self._lesions_shown: set[int] = set()
        if self._lesions:
            self.inputs["capsule.camera.label_image"] = AbstractValue.Make(ImageLabel16I(W, H))
        self._last_count = None
        self.frames = 0

    def _write_lesions(self, log, stamp, now, labels):
        """Each polyp in view as a box (ImageMarker POLYGON, ns "lesions", id its index);
        one that has left the view since the last frame, a REMOVE."""
        shown = set()
        for label in np.unique(labels):
            k = self._lesions.get(int(label))
            if k is None:
                continue
            x, y, w, h = box_of(labels == label)
            corners = [(x - 0.5, y - 0.5), (x + w - 0.5, y - 0.5), (x + w - 0.5, y + h - 0.5),
                       (x - 0.5, y + h - 0.5)]
            log.write("/capsule/lesions/marker", "visualization_msgs/msg/ImageMarker", {
                "header": header(stamp, CAMERA), "ns": "lesions", "id": k, "type": 3,
                "action": 0, "position": {"x": 0.0, "y": 0.0, "z": 0.0}, "scale": 1.0,
                "outline_color": {"r": 1.0, "g": 0.9, "b": 0.1, "a": 1.0}, "filled": 0,
                "fill_color": {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.0},
                "lifetime": {"sec": 0, "nanosec": 0},
                "points": [{"x": float(u), "y": float(v), "z": 0.0} for u, v in corners],
                "outline_colors": []}, now)
            shown.add(k)
        for k in sorted(self._lesions_shown - shown):
            log.write("/capsule/lesions/marker", "visualization_msgs/msg/ImageMarker",
                      dict(_image_marker(stamp, "lesions", (0.0, 0.0), False, 1.0,
                                         (1.0, 0.9, 0.1)), id=k), now)
        self._lesions_shown = shown

    def write(self, log, t, values):
        exposure, count = float(values["capsule.camera.frame_info"][0]), \
            float(values["capsule.camera.frame_info"][1])
        if count == self._last_count or count < 1:
            return
        self._last_count = count
        now, stamp = _ns(t), _ns(self.timing.held(exposure))
        rgb = np.ascontiguousarray(values["capsule.camera.rgb_image"].data[:, :, :3])
        H, W = rgb.shape[:2]
        info = camera_info(self._lens, stamp)
        log.write("/capsule/camera/image_raw", "sensor_msgs/msg/Image", {
            "header": header(stamp, CAMERA), "height": H, "width": W, "encoding": "rgb8",
            "is_bigendian": 0, "step": 3 * W, "data": rgb.tobytes()}, now)
        log.write("/capsule/camera/camera_info", "sensor_msgs/msg/CameraInfo", info, now)
        if self._depth:
            depth = depth_for_ros(values["capsule.camera.depth_image"].data[:, :, 0],
                                  self._ray_z, self._in_field)
            log.write("/capsule/camera/depth/image_raw", "sensor_msgs/msg/Image", {
                "header": header(stamp, CAMERA), "height": H, "width": W,
                "encoding": "32FC1", "is_bigendian": 0, "step": 4 * W,
                "data": depth.astype("<f4").tobytes()}, now)
            log.write("/capsule/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo", info,
                      now)
        pixel = np.asarray(values["capsule.lumen.lumen_pixel"], dtype=float)
        visible = float(values["capsule.lumen.lumen_visible"][0]) > 0.5
        point = np.asarray(values["capsule.lumen.lumen_point_W"])[:3]
        stamp_truth = _ns(self.timing.held(t))  # the pose it is computed from
        log.write("/capsule/lumen_truth/pixel", "geometry_msgs/msg/PointStamped", {
            "header": header(stamp_truth, PIXELS),
            "point": {"x": pixel[0], "y": pixel[1], "z": 1.0 if visible else 0.0}}, now)
        log.write("/capsule/lumen_truth/point", "geometry_msgs/msg/PointStamped", {
            "header": header(stamp_truth, WORLD), "point": vector3(point)}, now)
        log.write("/capsule/lumen_truth/marker", "visualization_msgs/msg/ImageMarker",
                  _image_marker(stamp, "lumen_truth", pixel, visible, self._marker_radius,
                                (0.2, 1.0, 0.2)), now)
        # The image-side truth: the far region of this frame's range image.
        far = np.asarray(values["capsule.lumen.far_pixel"], dtype=float)
        far_visible = float(values["capsule.lumen.far_visible"][0]) > 0.5
        log.write("/capsule/lumen_truth/far_pixel", "geometry_msgs/msg/PointStamped", {
            "header": header(stamp, PIXELS),
            "point": {"x": far[0], "y": far[1], "z": 1.0 if far_visible else 0.0}}, now)
        log.write("/capsule/lumen_truth/far_marker", "visualization_msgs/msg/ImageMarker",
                  _image_marker(stamp, "lumen_far", far, far_visible, self._marker_radius,
                                (0.2, 0.6, 1.0)), now)
        if self._tracker:
            found = float(values["capsule.lumen_tracker.lumen_visible"][0]) > 0.5
            detected = np.asarray(values["capsule.lumen_tracker.lumen_pixel"], dtype=float)
            confidence = float(values["capsule.lumen_tracker.lumen_confidence"][0])
            log.write("/capsule/lumen_tracker/pixel", "geometry_msgs/msg/PointStamped", {
                "header": header(stamp, PIXELS),
                "point": {"x": detected[0] if found else math.nan,
                          "y": detected[1] if found else math.nan, "z": confidence}}, now)
            log.write("/capsule/lumen_tracker/marker", "visualization_msgs/msg/ImageMarker",
                      _image_marker(stamp, "lumen_tracker", detected, found,
                                    self._marker_radius, (1.0, 0.6, 0.1)), now)
        if self._lesions:
            self._write_lesions(log, stamp, now,
                                values["capsule.camera.label_image"].data[:, :, 0])
        self.frames += 1


class ChannelLogger(LeafSystem):
    """Writes the station's signals as ROS 2 messages to the run's outputs (the MCAP file,
    the live Foxglove server, ROS 2 topics: a ChannelWriter of app/channels.py) as the
    simulation runs (module docstring: topics, frames, times).

    .. pydrake_system::

        name: ChannelLogger
        input_ports:
        - <station output> (one per output a stream reads, named as it)

    Each stream reads its inputs in a periodic publish event of its own; the latched
    messages (/tf_static, the scene) are written with the first message.

    Args:
        log: the ChannelWriter the messages are written to (closed by `close()`).
        streams: the _Stream objects of what the scenario has.
        static_transforms: (parent, child, X_PC) written once on /tf_static.
        scene: the /scene/markers MarkerArray (app/scene_markers.py), or None.
    """

    def __init__(self, log: ChannelWriter, streams, static_transforms=(),
                 scene: dict | None = None):
        super().__init__()
        self._log = log
        self._streams = list(streams)
        self._static = list(static_transforms)
        self._scene = scene
        self._started = False
        self._ports = {}
        for stream in self._streams:
            for name, model in stream.inputs.items():
                if name in self._ports:
                    continue
                if isinstance(model, int):
                    self._ports[name] = self.DeclareVectorInputPort(name, model)
                else:
                    self._ports[name] = self.DeclareAbstractInputPort(name, model)
            self.DeclarePeriodicPublishEvent(
                stream.period, stream.offset,
                lambda context, stream=stream: self._on_event(context, stream))

    @property
    def log(self):
        """The MCAP file the run reports on (a ChannelWriter's fatal output), or None."""
        return self._log.log

    @property
    def writer(self):
        return self._log

    def stream_inputs(self) -> list[str]:
        """The station outputs the logger reads (its input ports' names)."""
        return list(self._ports)

    def _on_event(self, context, stream):
        values = {name: self._ports[name].Eval(context) for name in stream.inputs}
        t = context.get_time()
        with signals_held():
            if not self._started:
                self._started = True
                self._log.write("/tf_static", "tf2_msgs/msg/TFMessage", {"transforms": [
                    transform_stamped(0, parent, child, X.translation(),
                                      _quaternion_of(X.rotation()))
                    for parent, child, X in self._static]}, 0, latched=True)
                if self._scene is not None:
                    self._log.write("/scene/markers", "visualization_msgs/msg/MarkerArray",
                                    self._scene, 0, latched=True)
            stream.write(self._log, t, values)
        return EventStatus.Succeeded()

    def close(self):
        """Finishes every output (the run loop's close hook)."""
        with signals_held():
            self._log.close()


def expected_mcap_bytes(scenario) -> float:
    """About how large the log of `scenario` grows, before compression (bytes): its
    frames (colour 3 and depth 4 bytes a pixel) at the camera's fastest rate, and ~400
    bytes per sensor message."""
    capsule, seconds = scenario.capsule, scenario.duration
    total = 600.0 / scenario.outputs.log_period * seconds
    camera = capsule.camera
    if camera is not None:
        fps = camera.fps_max if camera.fps_mode == "adaptive" else camera.fps
        pixels = camera.lens.width * camera.lens.height
        total += fps * seconds * (pixels * (7 if camera.render_depth else 3) + 2000)
    for sensor, messages in ((capsule.imu, 1), (capsule.magnetometer, 1),
                             (capsule.contact_sensor, 1)):
        if sensor is not None:
            total += 400.0 * messages * sensor.sample_rate * seconds
    if capsule.magnetic_array is not None:
        array = capsule.magnetic_array
        total += 400.0 * len(array.positions) * array.sample_rate * seconds
    if capsule.localizer is not None:
        total += 700.0 / capsule.localizer.period * seconds
    # The wall's pressure maps: three float images of a patch a pixel (~1,800 patches).
    total += 3 * (4 * 2000 + 200) / WALL_MAP_PERIOD * seconds
    return total


def add_mcap_logger(builder, station, scenario, path,
                    compression: str = "zstd") -> ChannelLogger:
    """`add_channel_logger` with the MCAP file at `path` as its one output."""
    return add_channel_logger(builder, station, scenario, [Ros2McapFile(path, compression)])


def scene_of(scenario) -> dict:
    """The /scene/markers MarkerArray of `scenario`'s colon, capsule and EPM."""
    model = capsule_model()
    wall = wall_triangles(trimesh.load(load_colon(scenario.colon)[1].visual_obj,
                                       force="mesh", process=False))
    geometry = scenario.epm.magnet   # a sphere or a cuboid drawn as its bounding cylinder
    dims = list(geometry.dimensions)
    diameter, length = {"cylinder": dims[:2], "sphere": dims[:1] * 2}.get(
        geometry.shape, [max(dims[:2]), dims[-1]])
    return scene_markers(wall, model.radius, model.length, diameter, length)


def add_channel_logger(builder, station, scenario, sinks, scene: bool = True) -> ChannelLogger:
    """Adds a ChannelLogger for `scenario` beside a built `station` (in `builder`), writing
    to `sinks` (the MCAP file, live outputs: app/channels.py), with a stream for each source
    the station has and, when `builder` holds the run's map of the wall's pressure with a
    pressure field (app/run.py `add_wall_pressure`), one of its images, and the scene
    (unless `scene` is False); connects it. Call `close()` on the result when the run ends
    (it is what `simulate`'s extend returns)."""
    capsule = scenario.capsule
    outputs = {station.get_output_port(i).get_name() for i in range(station.num_output_ports())}
    plant = station.GetSubsystemByName("plant")
    body = plant.GetBodyByName(CAPSULE_BODY)
    epm_index = (int(plant.GetBodyByName(EPM_BODY).index()) if plant.HasBodyNamed(EPM_BODY)
                 else None)
    timing = PlantTiming.of(plant)
    streams = [_PosesStream(scenario.outputs.log_period,
                            plant.GetCollisionGeometriesForBody(body), epm_index,
                            plant.num_bodies(), timing, wall="contact.wall" in outputs)]
    static = []
    if "capsule.camera.rgb_image" in outputs:
        camera = station.GetSubsystemByName("capsule.camera")
        static.append((CAPSULE, CAMERA, plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()))
        labels = (lesion_labels(lesion_scene(scenario.colon).lesions)
                  if "capsule.camera.label_image" in outputs else {})
        streams.append(_CameraStream(camera.lens, camera.tick(), camera.latency(),
                                     camera.config.render_depth,
                                     "capsule.lumen_tracker.lumen_pixel" in outputs, timing,
                                     lesion_labels=labels))
    if "capsule.imu.accel" in outputs:
        static.append((CAPSULE, IMU, capsule.imu.X_BS()))
        streams.append(_ImuStream(capsule.imu, "capsule.ahrs.q_WB" in outputs, timing))
    if "capsule.magnetometer.B_S" in outputs:
        config = capsule.magnetometer
        static.append((CAPSULE, MAGNETOMETER, config.X_BS()))
        streams.append(_FieldStream("capsule.magnetometer.B_S",
                                    [("/capsule/magnetometer", MAGNETOMETER)],
                                    config.sample_rate, config.channel().white_sigma,
                                    timing))
    if "capsule.magnetic_array.B" in outputs:
        array = capsule.magnetic_array
        n = len(array.positions)
        static += [(CAPSULE, hall_frame(i), array.X_BS(i)) for i in range(n)]
        streams.append(_FieldStream("capsule.magnetic_array.B",
                                    [(f"/capsule/magnetic_array/hall_{i}", hall_frame(i))
                                     for i in range(n)], array.sample_rate, array.noise_rms,
                                    timing))
    if "capsule.contact_sensor.F_B" in outputs:
        streams.append(_ContactSensorStream(capsule.contact_sensor, timing))
    if "capsule.localizer.pose" in outputs:
        streams.append(_PoseEstimateStream(capsule.localizer, timing))
    sources = {}  # what the logger reads from beside the station
    if builder.HasSubsystemNamed(WALL_PRESSURE_SYSTEM):
        wall = builder.GetSubsystemByName(WALL_PRESSURE_SYSTEM)
        if wall.layout.pressure_field:
            streams.append(_WallPressureStream(wall.layout, timing=timing))
            sources[f"{WALL_PRESSURE_SYSTEM}.map"] = wall.GetOutputPort("map")
    logger = builder.AddNamedSystem("channel_logger", ChannelLogger(
        ChannelWriter(sinks), streams, static, scene_of(scenario) if scene else None))
    for name in logger.stream_inputs():
        builder.Connect(sources[name] if name in sources else station.GetOutputPort(name),
                        logger.GetInputPort(name))
    return logger
