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


import trimesh
# mcap_ros2's own Writer uses this to encode; it has no public encoder and registers its
# channels without the QoS metadata rosbag2 replays from.
from pydrake.systems.framework import EventStatus, LeafSystem

from capsule_drake.anatomy.source import lesion_scene
from capsule_drake.app.signals import signals_held
from capsule_drake.capsule.camera_walls import lesion_labels
from capsule_drake.capsule.model import CAPSULE_BODY
from capsule_drake.epm.mount import EPM_BODY
from capsule_drake.station import station_value
from capsule_drake.app.dataset import PlantTiming
from capsule_drake.app.channels import ChannelWriter
from capsule_drake.app.scene_markers import scene_markers, wall_triangles
from capsule_drake.anatomy.source import load_colon
from capsule_drake.capsule.model import capsule_model
from capsule_drake.app.ros2_messages import transform_stamped
from capsule_drake.physics.wall_pressure import WALL_PRESSURE_SYSTEM

from capsule_drake.app.mcap_file import Ros2McapFile
from capsule_drake.app.channel_streams import (CAMERA, CAPSULE, IMU, MAGNETOMETER,
                                               WALL_MAP_PERIOD, _CameraStream,
                                               _ContactSensorStream, _FieldStream, _ImuStream,
                                               _PoseEstimateStream, _PosesStream,
                                               _quaternion_of, _WallPressureStream, hall_frame)


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
        # Every topic the run writes, told to the outputs before it starts (a live server
        # offers them all to a viewer when it connects; app/live/foxglove_out.py).
        log.declare(("/tf_static", *(("/scene/markers",) if scene is not None else ()),
                     *(topic for stream in self._streams for topic in stream.topics)))
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


def add_mcap_logger(builder, station, scenario, path, compression: str = "zstd",
                    wall_map=None) -> ChannelLogger:
    """`add_channel_logger` with the MCAP file at `path` as its one output."""
    return add_channel_logger(builder, station, scenario, [Ros2McapFile(path, compression)],
                              wall_map=wall_map)


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


def add_channel_logger(builder, station, scenario, sinks, scene: bool = True,
                       wall_map=None) -> ChannelLogger:
    """Adds a ChannelLogger for `scenario` beside a built `station` (in `builder`), writing
    to `sinks` (the MCAP file, live outputs: app/channels.py), with a stream for each source
    the station has and, given the run's map of the wall's pressure (`wall_map`, app/run.py
    `add_wall_pressure`) with a pressure field, one of its images, and the scene
    (unless `scene` is False); connects it. Call `close()` on the result when the run ends
    (the Run does: app/run.py)."""
    capsule = scenario.capsule
    outputs = {station.get_output_port(i).get_name() for i in range(station.num_output_ports())}
    plant = station_value(station, "scene.plant")
    body = plant.GetBodyByName(CAPSULE_BODY)
    epm_index = (int(plant.GetBodyByName(EPM_BODY).index()) if plant.HasBodyNamed(EPM_BODY)
                 else None)
    timing = PlantTiming.of(plant)
    streams = [_PosesStream(scenario.outputs.log_period,
                            plant.GetCollisionGeometriesForBody(body), epm_index,
                            plant.num_bodies(), timing, wall="contact.wall" in outputs)]
    static = []
    if "capsule.camera.rgb_image" in outputs:
        static.append((CAPSULE, CAMERA, plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()))
        labels = (lesion_labels(lesion_scene(scenario.colon).lesions)
                  if "capsule.camera.label_image" in outputs else {})
        camera = {name: station_value(station, f"capsule.camera.{name}")
                  for name in ("lens", "tick", "latency", "config")}
        streams.append(_CameraStream(camera["lens"], camera["tick"], camera["latency"],
                                     camera["config"].render_depth,
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
    if wall_map is not None and wall_map.layout.pressure_field:
        streams.append(_WallPressureStream(wall_map.layout, timing=timing))
        sources[f"{WALL_PRESSURE_SYSTEM}.map"] = wall_map.GetOutputPort("map")
    logger = builder.AddNamedSystem("channel_logger", ChannelLogger(
        ChannelWriter(sinks), streams, static, scene_of(scenario) if scene else None))
    for name in logger.stream_inputs():
        builder.Connect(sources[name] if name in sources else station.GetOutputPort(name),
                        logger.GetInputPort(name))
    return logger
