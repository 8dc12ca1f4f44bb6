"""ROS 2 message definitions for the MCAP logs, and the schema text each needs.

An MCAP channel of ROS 2 messages names its type (`sensor_msgs/msg/Imu`) and carries a
schema of encoding `ros2msg`: the type's .msg field list followed by the field list of every
type it uses, each of those preceded by a line of 80 '=' and a line `MSG: <package>/<Type>`
(the MCAP format registry's "ros2msg data format", the same text rosbag2 writes). Readers
(Foxglove, rosbag2's mcap storage plugin, mcap_ros2) decode the CDR payloads from that text
alone, so no ROS installation is needed on either side.

The field lists below are those of ROS 2's interface packages (builtin_interfaces, std_msgs,
geometry_msgs, sensor_msgs, tf2_msgs, visualization_msgs in common_interfaces and
geometry2; unchanged from Humble to Jazzy), comments left out: only the types the logger
writes and what they use. tests/test_mcap.py checks them field by field against an
independent copy (the `rosbags` package's Humble type store).
"""

import functools

# One entry per type: its .msg field list (constants included, comments left out).
DEFINITIONS = {
    "builtin_interfaces/msg/Time": """
int32 sec
uint32 nanosec
""",
    "builtin_interfaces/msg/Duration": """
int32 sec
uint32 nanosec
""",
    "std_msgs/msg/Header": """
builtin_interfaces/Time stamp
string frame_id
""",
    "std_msgs/msg/ColorRGBA": """
float32 r
float32 g
float32 b
float32 a
""",
    "geometry_msgs/msg/Vector3": """
float64 x
float64 y
float64 z
""",
    "geometry_msgs/msg/Point": """
float64 x
float64 y
float64 z
""",
    "geometry_msgs/msg/Quaternion": """
float64 x 0
float64 y 0
float64 z 0
float64 w 1
""",
    "geometry_msgs/msg/Pose": """
Point position
Quaternion orientation
""",
    "geometry_msgs/msg/PoseWithCovariance": """
Pose pose
float64[36] covariance
""",
    "geometry_msgs/msg/PoseWithCovarianceStamped": """
std_msgs/Header header
PoseWithCovariance pose
""",
    "geometry_msgs/msg/Transform": """
Vector3 translation
Quaternion rotation
""",
    "geometry_msgs/msg/TransformStamped": """
std_msgs/Header header
string child_frame_id
Transform transform
""",
    "geometry_msgs/msg/Wrench": """
Vector3 force
Vector3 torque
""",
    "geometry_msgs/msg/WrenchStamped": """
std_msgs/Header header
Wrench wrench
""",
    "geometry_msgs/msg/PointStamped": """
std_msgs/Header header
Point point
""",
    "sensor_msgs/msg/Image": """
std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
""",
    "sensor_msgs/msg/RegionOfInterest": """
uint32 x_offset
uint32 y_offset
uint32 height
uint32 width
bool do_rectify
""",
    "sensor_msgs/msg/CameraInfo": """
std_msgs/Header header
uint32 height
uint32 width
string distortion_model
float64[] d
float64[9] k
float64[9] r
float64[12] p
uint32 binning_x
uint32 binning_y
RegionOfInterest roi
""",
    "sensor_msgs/msg/Imu": """
std_msgs/Header header
geometry_msgs/Quaternion orientation
float64[9] orientation_covariance
geometry_msgs/Vector3 angular_velocity
float64[9] angular_velocity_covariance
geometry_msgs/Vector3 linear_acceleration
float64[9] linear_acceleration_covariance
""",
    "sensor_msgs/msg/FluidPressure": """
std_msgs/Header header
float64 fluid_pressure
float64 variance
""",
    "sensor_msgs/msg/MagneticField": """
std_msgs/Header header
geometry_msgs/Vector3 magnetic_field
float64[9] magnetic_field_covariance
""",
    "tf2_msgs/msg/TFMessage": """
geometry_msgs/TransformStamped[] transforms
""",
    "visualization_msgs/msg/ImageMarker": """
int32 CIRCLE=0
int32 LINE_STRIP=1
int32 LINE_LIST=2
int32 POLYGON=3
int32 POINTS=4
int32 ADD=0
int32 REMOVE=1
std_msgs/Header header
string ns
int32 id
int32 type
int32 action
geometry_msgs/Point position
float32 scale
std_msgs/ColorRGBA outline_color
uint8 filled
std_msgs/ColorRGBA fill_color
builtin_interfaces/Duration lifetime
geometry_msgs/Point[] points
std_msgs/ColorRGBA[] outline_colors
""",
    "sensor_msgs/msg/CompressedImage": """
std_msgs/Header header
string format
uint8[] data
""",
    "visualization_msgs/msg/UVCoordinate": """
float32 u
float32 v
""",
    "visualization_msgs/msg/MeshFile": """
string filename
uint8[] data
""",
    "visualization_msgs/msg/Marker": """
int32 ARROW=0
int32 CUBE=1
int32 SPHERE=2
int32 CYLINDER=3
int32 LINE_STRIP=4
int32 LINE_LIST=5
int32 CUBE_LIST=6
int32 SPHERE_LIST=7
int32 POINTS=8
int32 TEXT_VIEW_FACING=9
int32 MESH_RESOURCE=10
int32 TRIANGLE_LIST=11
int32 ADD=0
int32 MODIFY=0
int32 DELETE=2
int32 DELETEALL=3
std_msgs/Header header
string ns
int32 id
int32 type
int32 action
geometry_msgs/Pose pose
geometry_msgs/Vector3 scale
std_msgs/ColorRGBA color
builtin_interfaces/Duration lifetime
bool frame_locked
geometry_msgs/Point[] points
std_msgs/ColorRGBA[] colors
string texture_resource
sensor_msgs/CompressedImage texture
UVCoordinate[] uv_coordinates
string text
string mesh_resource
MeshFile mesh_file
bool mesh_use_embedded_materials
""",
    "visualization_msgs/msg/MarkerArray": """
Marker[] markers
""",
    "geometry_msgs/msg/PoseStamped": """
std_msgs/Header header
Pose pose
""",
    "geometry_msgs/msg/Twist": """
Vector3 linear
Vector3 angular
""",
    "geometry_msgs/msg/TwistStamped": """
std_msgs/Header header
Twist twist
""",
}

_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16",
               "uint16", "int32", "uint32", "int64", "uint64", "string", "wstring"}
_SEPARATOR = "=" * 80


def field_lines(type_name: str) -> list[str]:
    """The non-empty lines of a type's field list."""
    return [line.strip() for line in DEFINITIONS[type_name].strip().splitlines()
            if line.strip()]


@functools.cache
def fields(type_name: str) -> tuple[tuple[str, str], ...]:
    """(field type text, field name) of a type's fields, in order, constants left out
    (parsed once per type: the DDS output converts every message by them)."""
    return tuple((line.split()[0], line.split()[1]) for line in field_lines(type_name)
                 if "=" not in line.split()[1])


def dependency(type_name: str, field_type: str) -> str | None:
    """The full name (`pkg/msg/Type`) of a field's type, or None for a primitive."""
    base = field_type.split("[")[0]
    if base in _PRIMITIVES or "<=" in base:
        return None
    package = type_name.split("/")[0]
    if "/" in base:  # `pkg/Type`: another package's, or this one's named in full
        package, base = base.split("/")
    return f"{package}/msg/{base}"


def dependencies(type_name: str) -> list[str]:
    """Every type `type_name` uses, directly or not, each once, in the order a depth-first
    walk of its fields meets them (rosbag2's order)."""
    found: list[str] = []

    def visit(name):
        for field_type, _ in fields(name):
            used = dependency(name, field_type)
            if used is not None and used not in found:
                if used not in DEFINITIONS:
                    raise KeyError(f"{name} uses {used}, which has no definition here")
                found.append(used)
                visit(used)

    visit(type_name)
    return found


def schema_text(type_name: str) -> str:
    """The `ros2msg` schema of a type: its field list, then each dependency's after the
    two-line delimiter (80 '=', then `MSG: pkg/Type`)."""
    parts = ["\n".join(field_lines(type_name)) + "\n"]
    for used in dependencies(type_name):
        package, _, name = used.split("/")
        parts.append(f"{_SEPARATOR}\nMSG: {package}/{name}\n"
                     + "\n".join(field_lines(used)) + "\n")
    return "".join(parts)


# --- Helpers for the message dictionaries the encoder takes ---------------------------------

NANOSECONDS = 1_000_000_000


def stamp(nanoseconds: int) -> dict:
    """builtin_interfaces/Time of a time in nanoseconds (simulated time from 0)."""
    return {"sec": int(nanoseconds // NANOSECONDS), "nanosec": int(nanoseconds % NANOSECONDS)}


def header(nanoseconds: int, frame_id: str) -> dict:
    return {"stamp": stamp(nanoseconds), "frame_id": frame_id}


def vector3(v) -> dict:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def quaternion_wxyz(q) -> dict:
    """geometry_msgs/Quaternion (x, y, z, w) of a [w, x, y, z] quaternion."""
    return {"x": float(q[1]), "y": float(q[2]), "z": float(q[3]), "w": float(q[0])}


def transform_stamped(nanoseconds: int, parent: str, child: str, p, q_wxyz) -> dict:
    """The pose of frame `child` in `parent` (p, q: the child's origin and orientation)."""
    return {"header": header(nanoseconds, parent), "child_frame_id": child,
            "transform": {"translation": vector3(p), "rotation": quaternion_wxyz(q_wxyz)}}


# rosbag2 replays a topic with the QoS it was recorded with, read from the channel's
# `offered_qos_profiles` (YAML). Written with integer policies (rmw's enum values, the
# rosbag2 metadata format up to version 8): history 1 keep-last, reliability 1 reliable,
# durability 1 transient-local (latched, for /tf_static) or 2 volatile, liveliness 1
# automatic; durations "infinite" as rmw writes them.
_INFINITE = "{sec: 9223372036, nsec: 854775807}"


def offered_qos_profiles(latched: bool = False, depth: int = 10) -> str:
    """The `offered_qos_profiles` text of one publisher (see above)."""
    return (f"- history: 1\n  depth: {int(depth)}\n  reliability: 1\n"
            f"  durability: {1 if latched else 2}\n  deadline: {_INFINITE}\n"
            f"  lifespan: {_INFINITE}\n  liveliness: 1\n"
            f"  liveliness_lease_duration: {_INFINITE}\n"
            "  avoid_ros_namespace_conventions: false\n")
