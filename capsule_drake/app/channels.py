"""The run's channels, defined once, and the writer that hands each message to every output.

A channel is a ROS 2 topic with its message type, whether it is latched (a late subscriber
still gets its last message: the static transforms, the scene) and when it is written. The
MCAP file, the live Foxglove server and the ROS 2 topics all take their channels from
`CHANNELS`: a topic the logger's streams write (app/mcap_log.py) appears in each of them, with
the same type, the same CDR payload and the same QoS.

`ChannelWriter` is what the streams write to: it checks the topic against the table, encodes
the message once (CDR, the `ros2msg` schema of app/ros2_messages.py) and gives the bytes to
the outputs that take bytes (the MCAP file, Foxglove) and the message to those that build
their own samples (DDS). An output that fails is handled by its kind: the MCAP file stops
the run (what was recorded is kept: app/mcap_log.py), a live output is dropped with one line
on stderr and the run goes on.
"""

from __future__ import annotations

import dataclasses
import functools
import re
import sys

from mcap_ros2._dynamic import serialize_dynamic

from capsule_drake.app.ros2_messages import schema_text


@dataclasses.dataclass(frozen=True)
class ChannelSpec:
    """One channel: its topic (a `{...}` part stands for an index or a name), its ROS 2
    message type, whether it is latched, and when it is written (for the documentation)."""

    topic: str
    type_name: str
    when: str
    latched: bool = False

    def matches(self, topic: str) -> bool:
        if "{" not in self.topic:
            return topic == self.topic
        pattern = re.sub(r"\\\{[a-z_]+\\\}", r"[A-Za-z0-9_]+", re.escape(self.topic))
        return re.fullmatch(pattern, topic) is not None


_TF = "tf2_msgs/msg/TFMessage"
_WRENCH = "geometry_msgs/msg/WrenchStamped"
_POINT = "geometry_msgs/msg/PointStamped"
_IMAGE = "sensor_msgs/msg/Image"
_INFO = "sensor_msgs/msg/CameraInfo"
_IMAGE_MARKER = "visualization_msgs/msg/ImageMarker"
_FIELD = "sensor_msgs/msg/MagneticField"

CHANNELS: tuple[ChannelSpec, ...] = (
    ChannelSpec("/tf", _TF, "log_period; world -> capsule, epm"),
    ChannelSpec("/tf_static", _TF, "once; capsule -> camera, sensors", latched=True),
    ChannelSpec("/scene/markers", "visualization_msgs/msg/MarkerArray",
                "once; the colon's wall (world), the capsule and the EPM (their frames)",
                latched=True),
    ChannelSpec("/capsule/contact/wrench", _WRENCH, "log_period; capsule"),
    ChannelSpec("/capsule/contact/peak_pressure", "sensor_msgs/msg/FluidPressure",
                "log_period; capsule (Pa)"),
    ChannelSpec("/capsule/contact/wall_pressure/peak", _IMAGE,
                "every 1 s; colon_wall_map, 32FC1 kPa"),
    ChannelSpec("/capsule/contact/wall_pressure/above_{name}", _IMAGE,
                "every 1 s; colon_wall_map, 32FC1 s (injury, ischaemia)"),
    ChannelSpec("/capsule/camera/image_raw", _IMAGE, "each frame; rgb8"),
    ChannelSpec("/capsule/camera/camera_info", _INFO, "each frame"),
    ChannelSpec("/capsule/camera/depth/image_raw", _IMAGE, "each frame; 32FC1 m"),
    ChannelSpec("/capsule/camera/depth/camera_info", _INFO, "each frame"),
    ChannelSpec("/capsule/lumen_truth/pixel", _POINT, "each frame; capsule_camera_image"),
    ChannelSpec("/capsule/lumen_truth/point", _POINT, "each frame; world"),
    ChannelSpec("/capsule/lumen_truth/marker", _IMAGE_MARKER, "each frame"),
    ChannelSpec("/capsule/lumen_truth/far_pixel", _POINT, "each frame; capsule_camera_image"),
    ChannelSpec("/capsule/lumen_truth/far_marker", _IMAGE_MARKER, "each frame"),
    ChannelSpec("/capsule/lumen_tracker/pixel", _POINT, "each frame; capsule_camera_image"),
    ChannelSpec("/capsule/lumen_tracker/marker", _IMAGE_MARKER, "each frame"),
    ChannelSpec("/capsule/lesions/marker", _IMAGE_MARKER, "each frame, with polyps"),
    ChannelSpec("/capsule/imu/data", "sensor_msgs/msg/Imu", "its rate; capsule_imu"),
    ChannelSpec("/capsule/magnetometer", _FIELD, "its rate; capsule_magnetometer (T)"),
    ChannelSpec("/capsule/magnetic_array/hall_{i}", _FIELD, "its rate; capsule_hall_<i> (T)"),
    ChannelSpec("/capsule/contact_sensor/wrench", _WRENCH, "its rate; capsule"),
    ChannelSpec("/capsule/localizer/pose", "geometry_msgs/msg/PoseWithCovarianceStamped",
                "its period; world"),
)

# What a ROS 2 node may send the run (app/live/ros2_out.py): a goal for the EPM's magnet
# (its centre, and its moment along the pose's z axis), through the EPM's guard.
COMMAND_CHANNELS: tuple[ChannelSpec, ...] = (
    ChannelSpec("/epm/goal", "geometry_msgs/msg/PoseStamped",
                "as the node sends it; world: the magnet's centre, its moment along z"),
    ChannelSpec("/epm/velocity", "geometry_msgs/msg/TwistStamped",
                "as the node sends it; world: the centre's velocity (m/s), the moment's "
                "turn (rad/s)"),
)


@functools.cache
def channel_of(topic: str) -> ChannelSpec:
    """The channel `topic` belongs to (looked up once per topic: every message asks);
    KeyError (naming it) for a topic not in the table."""
    for spec in CHANNELS:
        if spec.matches(topic):
            return spec
    raise KeyError(f"{topic}: not a channel of app/channels.py")


class ChannelWriter:
    """The streams' one destination: each message, checked against the channel table and
    encoded once, goes to every output.

    Outputs (`sinks`) have `publish(topic, spec, message, data, log_time_ns)` (data: the CDR
    bytes), `close()`, and `fatal` (True: a failure stops the run, as the MCAP file's; False:
    the output is dropped with one line on stderr, as a live server's). The first fatal
    output is the `log` the run reports (its `path`, `messages`, `error`).
    """

    def __init__(self, sinks):
        self.sinks = list(sinks)
        self._encoders: dict[str, object] = {}
        self._declared: set[str] = set()
        self.messages = 0
        self.dropped: list[str] = []   # one line per live output dropped

    def declare(self, topics) -> None:
        """The topics the run will write, before its first message: each is checked against
        the table, and the outputs that have `declare(specs)` (the Foxglove server: a
        channel advertised while a viewer is connected can lose that viewer's subscription)
        get {topic: spec}. Once topics are declared, writing another is an error."""
        specs = {topic: channel_of(topic) for topic in topics}
        self._declared.update(specs)
        for sink in list(self.sinks):
            if hasattr(sink, "declare"):
                sink.declare(specs)

    def _encoder(self, type_name: str):
        if type_name not in self._encoders:
            self._encoders[type_name] = serialize_dynamic(type_name,
                                                          schema_text(type_name))[type_name]
        return self._encoders[type_name]

    def write(self, topic: str, type_name: str, message: dict, log_time_ns: int,
              latched: bool = False) -> None:
        spec = channel_of(topic)
        if self._declared and topic not in self._declared:
            raise ValueError(f"{topic}: written, but not among the topics declared for the "
                             "run (a stream's `topics`, app/channel_streams.py)")
        if spec.type_name != type_name or spec.latched != latched:
            raise ValueError(f"{topic}: written as {type_name}{' (latched)' * latched}, "
                             f"the channel table says {spec.type_name}"
                             f"{' (latched)' * spec.latched}")
        data = bytes(self._encoder(type_name)(message))
        for sink in list(self.sinks):
            if sink.fatal:
                sink.publish(topic, spec, message, data, log_time_ns)
                continue
            try:
                sink.publish(topic, spec, message, data, log_time_ns)
            except Exception as e:  # a live output never stops the run
                self._drop(sink, e)
        self.messages += 1

    def _drop(self, sink, error: Exception) -> None:
        self.sinks.remove(sink)
        line = f"{sink.name}: stopped ({type(error).__name__}: {error}); the run goes on"
        self.dropped.append(line)
        print(f"capsule-sim: warning: {line}", file=sys.stderr)
        try:
            sink.close()
        except Exception:
            pass

    @property
    def log(self):
        """The first output that stops the run when it fails (the MCAP file), or None."""
        return next((sink for sink in self.sinks if sink.fatal), None)

    def close(self) -> None:
        """Closes every output; a fatal output's failure to finish is raised after the
        others are closed."""
        failure = None
        for sink in list(self.sinks):
            try:
                sink.close()
            except Exception as e:
                if sink.fatal and failure is None:
                    failure = e
        if failure is not None:
            raise failure
