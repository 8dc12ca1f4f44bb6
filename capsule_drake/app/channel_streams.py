"""The channel logger's streams (app/mcap_log.py): one per source of the station, each read
by its own periodic event and written as ROS 2 messages, with the frames and stamps
app/mcap_log.py's docstring describes.
"""

import math

import numpy as np
# mcap_ros2's own Writer uses this to encode; it has no public encoder and registers its
# channels without the QoS metadata rosbag2 replays from.
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.plant import ContactResults
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I, ImageRgba8U

from capsule_drake.app.channels import ChannelWriter
from capsule_drake.capsule.imu import imu_channels
from capsule_drake.capsule.model import rotation_from_quaternion
from capsule_drake.epm.poses import stage_joint_positions
from capsule_drake.lifetime import id_values
from capsule_drake.app.dataset import READ_DELAY, PlantTiming, sample_tick
from capsule_drake.app.lesion_dataset import box_of
from capsule_drake.app.ros2_messages import (NANOSECONDS, header, quaternion_wxyz,
                                             transform_stamped, vector3)
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


class _Stream:
    """A source of messages: the station outputs it reads (name -> vector size, or a model
    value for an abstract port), the topics it writes (declared before the run, so a live
    viewer is offered every channel when it connects: app/live/foxglove_out.py), when
    (every `period` s from `offset`), and `write`; `timing` the plant's, for the stamps."""

    inputs: dict = {}
    topics: tuple = ()
    period: float = 0.01
    offset: float = 0.0
    timing: PlantTiming = PlantTiming()

    def tick(self, t: float) -> float:
        """The sample time (on the stream's grid) that the reading at t follows."""
        return sample_tick(t, self.period, self.offset)

    def write(self, log: ChannelWriter, t: float, values: dict) -> None:
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
        self.topics = ("/tf", "/capsule/contact/wrench", "/capsule/contact/peak_pressure")
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
        self.topics = ("/capsule/imu/data",)
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
        self.topics = tuple(topic for topic, _ in self._topics_frames)

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
        self.topics = ("/capsule/contact_sensor/wrench",)

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
        self.topics = ("/capsule/localizer/pose",)

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
        self.topics = ("/capsule/contact/wall_pressure/peak",
                       *(f"/capsule/contact/wall_pressure/above_{name}"
                         for name, _ in layout.thresholds))

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
        self.topics = ("/capsule/camera/image_raw", "/capsule/camera/camera_info",
                       *(("/capsule/camera/depth/image_raw",
                          "/capsule/camera/depth/camera_info") if render_depth else ()),
                       "/capsule/lumen_truth/pixel", "/capsule/lumen_truth/point",
                       "/capsule/lumen_truth/marker", "/capsule/lumen_truth/far_pixel",
                       "/capsule/lumen_truth/far_marker",
                       *(("/capsule/lumen_tracker/pixel", "/capsule/lumen_tracker/marker")
                         if with_tracker else ()),
                       *(("/capsule/lesions/marker",) if self._lesions else ()))
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
