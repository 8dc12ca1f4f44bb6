"""Scenario: everything that defines one simulation, as typed dataclasses loaded from YAML.

Each field names a block of the station's diagram (docs/diagram.md); a block that is
null is not there. What drives the EPM is one tagged field, `epm.driver`:

    Default: {}
    FarMagnet:
      epm:
        driver: !HoldAbove {height: 0.5}
    Teleop:
      epm:
        mount: !Arm {}
        driver: !Teleop {operator: simulated}

A scenario file holds one or more named scenarios as top-level keys. Every field has a
default, so `Default: {}` is a complete scenario. Unknown keys, wrong types, impossible
values and missing files raise `ScenarioError` with one line naming the file and the key;
`load_scenario` checks everything once, and the station trusts what it is given.
Units are SI throughout (metres, seconds, newtons, tesla, A m^2).

What loading a scenario may cost is bounded, so that nonsense costs one line and not a
traceback, a hang or a huge allocation: a scenario file is read only if it is a regular
file (not a directory, device or pipe) of text of at most 1 MB; a YAML document may nest 50
levels and expand, through its aliases, to 100,000 nodes (schema.py); every number must be
finite, and each block's check bounds its values, each bound with its reason beside it
(anatomical ranges for the colon, material limits for the magnets, rates, image sizes, delay
buffers and log lengths for what costs memory or time).
"""

import math
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed
from pydrake.multibody.plant import MultibodyPlantConfig
from pydrake.systems.analysis import GetIntegrationSchemes, SimulatorConfig

from capsule_drake import blocks, scene
from capsule_drake.anatomy import ColonParams
from capsule_drake.anatomy.params import SEED_RANGE
from capsule_drake.capsule import camera, camera_walls
from capsule_drake.capsule.ahrs import AhrsConfig
from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.capsule.contact_sensor import ContactSensorConfig
from capsule_drake.capsule.imu import ImuConfig
from capsule_drake.capsule.magnetic_array import MagneticArrayConfig
from capsule_drake.capsule.magnetometer import MagnetometerConfig
from capsule_drake.epm import mount
from capsule_drake.epm.arm import Arm
from capsule_drake.epm.paths import AlongColon, External, HoldAbove
from capsule_drake.epm.stage import Stage
from capsule_drake.guidance.pseudo_force import PseudoForceConfig
from capsule_drake.io import visualization
from capsule_drake.io.guard import GuardConfig, check_guard_config
from capsule_drake.navigation.autonomy import LumenFollower
from capsule_drake.navigation.localization import LocalizerConfig
from capsule_drake.navigation.plugin import Plugin
from capsule_drake.perception.lumen_tracker import LumenTrackerConfig
from capsule_drake.physics.contact import CompliantWall, RigidWall
from capsule_drake.physics.magnet_force import MagnetForceConfig
from capsule_drake.physics.magnetics import MagnetGeometry
from capsule_drake.physics.step_bound import time_step_bound
from capsule_drake.schema import (MAX_TEXT_BYTES, MIN_PERIOD, ScenarioError, SchemaError, check,
                                  field_types, need_range, parse_yaml)
from capsule_drake.teleop.driver import Teleop

REPO_ROOT = Path(__file__).resolve().parents[1]
DIAGRAMS_DIR = REPO_ROOT / "diagrams"
DEFAULT_SCENARIO_FILE = DIAGRAMS_DIR / "default.yaml"

STATION_BLOCKS = (
    "scene",                  # the plant, scene graph, colon and capsule (scene.py)
    "epm.mount",              # the EPM's carrier: !Stage or !Arm (epm/mount.py)
    "colon",                  # the table, the colon's wall and visuals (scene.py)
    "capsule.camera_walls",   # the camera's own walls, after every other model (camera_walls.py)
    "contact",                # the wall's and capsule's contact, by model (physics/contact/)
    "magnet_force",           # physics/magnet_force.py
    "colon.fluid",            # buoyancy and drag in residual fluid (scene.py)
    "applied_forces",         # the forces above into the plant (scene.py)
    "epm.pose",               # epm/mount.py
    "capsule.imu",            # capsule/imu.py
    "capsule.ahrs",           # capsule/ahrs.py
    "capsule.magnetometer",   # capsule/magnetometer.py
    "capsule.magnetic_array",  # capsule/magnetic_array.py
    "capsule.localizer",      # navigation/localization.py
    "capsule.contact_sensor",  # capsule/contact_sensor.py
    "capsule.camera",         # capsule/camera.py, with the lumen truth
    "capsule.lumen_tracker",  # perception/lumen_tracker.py
    "pseudo_force",           # guidance/pseudo_force.py
    "epm.driver",             # epm/paths.py, teleop/driver.py, navigation/{autonomy,plugin}.py
    "meshcat",                # io/visualization.py
)
"""The station's blocks, in the order they are checked and added."""

# The modules that register blocks (blocks.py) and hold no config type of the scenario: the
# scene's blocks, the EPM's carrier and pose, the camera and its walls, Meshcat. Every other
# block's module is imported above for its config.
BLOCK_MODULES = (scene, mount, camera, camera_walls, visualization)
_missing = [name for name in STATION_BLOCKS if not blocks.registered(name)]
if _missing:
    raise RuntimeError(f"blocks named in STATION_BLOCKS but not registered: {_missing}")


def station_blocks(scenario) -> list[str]:
    """The names of the blocks a station of `scenario` holds, in order."""
    return [item.name for item, _ in blocks.present(STATION_BLOCKS, scenario)]


# Keys of earlier versions, and where they went (a scenario that uses one is told).
MOVED = {
    "time_step": "plant.time_step",
    "contact.discrete_contact_approximation": "plant.discrete_contact_approximation",
    "magnet_model": "magnet_force.field_model",
    "magnet_update_period": "magnet_force.update_period",
    "log_period": "outputs.log_period",
    "visual_period": "outputs.visual_period",
    "epm.path": "epm.driver (e.g. driver: !HoldAbove {height: 0.5})",
    "teleop": "epm.driver (driver: !Teleop {...})",
    "epm.arm": "epm.mount (mount: !Arm {...})",
    "epm.translation_gains": "epm.mount (mount: !Stage {translation_gains: ...})",
    "epm.rotation_gains": "epm.mount (mount: !Stage {rotation_gains: ...})",
}


@dataclass
class CapsuleConfig:
    """The capsule: where it starts, its internal permanent magnet (IPM), its sensors."""

    # Arc length along the colon's centerline, from the anus, where the capsule starts (m).
    start_s: float = 0.05
    # Seconds the capsule is let settle before the run (0: it starts on the centreline, at
    # rest, and the magnet snaps it onto the wall in the run's first 0.1-0.2 s). The
    # scenario's physics alone (no sensors, the EPM held where the run starts it) is
    # simulated that long at a 0.5 ms step (station.settled_start), and the run starts with
    # the capsule where that leaves it, at rest: the snap (0.5-0.6 m/s) is then resolved
    # at a step that keeps it within 0.6 mm of the wall, whatever the run's own step.
    settle: float = 0.0
    # The IPM: an N52 cylinder of 11.1 x 11.1 mm, m = 1.26 A m^2 (docs/sources.md section 1).
    # Its pose in the capsule is the `ipm` frame of models/capsule.sdf (frame M, axial
    # magnetisation).
    ipm: MagnetGeometry = field(default_factory=lambda: MagnetGeometry(
        shape="cylinder", dimensions=[0.0111, 0.0111], remanence=1.48))
    # On-board sensors, off (null) unless the scenario asks for them (`imu: {}` gives the
    # MPU-6050-like defaults); `capsule-sim record` switches every one on. The IMU
    # (accelerometer + gyroscope, MEMS noise, bias drift), its AHRS, and a magnetometer
    # reading the EPM's field. Together they add ~0.08 ms to a ~0.36 ms physics step
    # (measured: IMU 0.037, magnetometer 0.030, AHRS 0.012), though they sample at 100 Hz.
    imu: ImuConfig | None = None
    # The Mahony AHRS on the IMU (needs the IMU). An empty initial_q_WB starts it from the
    # capsule's true start pose.
    ahrs: AhrsConfig | None = None
    magnetometer: MagnetometerConfig | None = None
    # The Hall sensors around the IPM for localisation (capsule/magnetic_array.py), and the
    # pose estimator on them, the IMU and the EPM's pose (navigation/localization.py; needs
    # capsule.imu and capsule.magnetic_array).
    magnetic_array: MagneticArrayConfig | None = None
    localizer: LocalizerConfig | None = None
    # The force the colon wall presses on the capsule, as a force sensor in its shell
    # would measure it (capsule/contact_sensor.py).
    contact_sensor: ContactSensorConfig | None = None
    # The camera at the front dome (null: none, the default, since rendering costs more
    # than the physics; `capsule-sim record` switches it on). `camera: {}` gives the
    # 172-degree fisheye at 256 px and 10 fps with the LED light at the lens. With a camera,
    # the lumen ground truth (capsule.lumen) comes too.
    camera: CameraConfig | None = None
    # Lumen ground truth: the centerline point this far ahead of the camera (m).
    lumen_lookahead: float = 0.05
    # The lumen tracker on the camera's frames (needs the camera): `lumen_tracker: {}` runs
    # the seed's detector; `detector: my_package.module:function` plugs in a user's.
    lumen_tracker: LumenTrackerConfig | None = None


@dataclass
class EpmConfig:
    """The external permanent magnet, what carries it, and what drives it."""

    # 101.6 x 101.6 mm N52 cylinder, 970 A m^2 (docs/sources.md section 1).
    magnet: MagnetGeometry = field(default_factory=MagnetGeometry)
    # Smallest allowed gap between the magnet's surface and the patient's skin (m).
    clearance: float = 0.02
    # What carries the magnet: !Stage (a commanded five-axis body, light and fast) or !Arm
    # (the 7-DoF arm of models/epm_arm.sdf with its controller).
    mount: Stage | Arm = field(default_factory=Stage)
    # What commands it: !AlongColon (a path over the colon's course, the default),
    # !HoldAbove (still, above the capsule's start), !Teleop (a haptic operator),
    # !LumenFollower (the autonomous follower), !External (the station's `epm.command`
    # input) or !Plugin (a user's navigator, "package.module:function").
    driver: AlongColon | HoldAbove | Teleop | LumenFollower | External | Plugin = field(
        default_factory=AlongColon)


@dataclass
class McapOutput:
    """The run's channels (app/channels.py) as ROS 2 messages in an MCAP file."""

    # The file (relative to the working directory). The CLI's --mcap FILE sets it.
    path: str = ""
    # Chunk compression: "zstd", "lz4" or "none".
    compression: str = "zstd"


@dataclass
class MeshcatOutput:
    """A live Meshcat page of the run (the CLI's --meshcat)."""

    # Address and port the page is served on (the loopback unless told otherwise).
    host: str = "127.0.0.1"
    port: int = 7000


@dataclass
class FoxgloveOutput:
    """The run's channels live on a Foxglove WebSocket server (foxglove-sdk): open
    Foxglove, "Open connection", ws://host:port (the CLI's --foxglove)."""

    host: str = "127.0.0.1"
    # 0: any free port (the run prints which).
    port: int = 8765
    # Seconds the run waits, at its first message, for a viewer to subscribe (0: none).
    wait_for_client: float = 0.0
    # Messages queued per client before the oldest is dropped (foxglove-sdk's default): a
    # viewer slower than the stream loses messages, never the run; raise it for a slow one.
    backlog: int = 1024


@dataclass
class Ros2Output:
    """The run's channels as ROS 2 topics over DDS (Cyclone DDS, no ROS installation
    needed here; the CLI's --ros2), and the EPM's goal from a ROS 2 topic."""

    # The DDS domain (ROS_DOMAIN_ID of the ROS 2 machines that should see it).
    domain_id: int = 0
    # Only this machine (the loopback); false: Cyclone DDS's own configuration
    # ($CYCLONEDDS_URI, else every interface).
    loopback: bool = True
    # The EPM follows geometry_msgs/PoseStamped goals on /epm/goal (world: the magnet's
    # centre, its moment along the pose's z) and geometry_msgs/TwistStamped velocities on
    # /epm/velocity (world: the centre's velocity, the moment's turn), through the EPM's
    # guard as every driver's command; needs epm.driver !External.
    epm_command: bool = False
    # A goal older than this (s, wall clock) is a lost link: the EPM holds.
    hold_after: float = 0.5


@dataclass
class OutputsConfig:
    """What a run records and where it is shown. The live ones (meshcat, foxglove, ros2)
    pace the run to simulator.target_realtime_rate (1, real time, when that is 0)."""

    # Period at which the run records poses and contact forces for its metrics (s).
    log_period: float = 0.01
    # Period at which Meshcat is updated, when it is used (s).
    visual_period: float = 1.0 / 32.0
    # The Meshcat replay, recording.html (the CLI's --no-recording: false).
    recording: bool = True
    # The MCAP file of the run's channels. Null: none.
    mcap: McapOutput | None = None
    # A live Meshcat page. Null: none.
    meshcat: MeshcatOutput | None = None
    # A live Foxglove server. Null: none.
    foxglove: FoxgloveOutput | None = None
    # ROS 2 topics. Null: none.
    ros2: Ros2Output | None = None

    def live(self) -> bool:
        """Whether any output is watched as the run goes (it is then paced)."""
        return any(o is not None for o in (self.meshcat, self.foxglove, self.ros2))


def _plant_config() -> MultibodyPlantConfig:
    return MultibodyPlantConfig(time_step=2.0e-3, discrete_contact_approximation="lagged")


@dataclass
class Scenario:
    """One simulation: patient, capsule, magnets, contact, guidance, driver and timing.
    The station adds the blocks in this order (station.py)."""

    # The patient's colon: its source (procedural, ex vivo, a mesh), anatomy, seed.
    colon: ColonParams = field(default_factory=ColonParams)
    # The capsule, its internal magnet and its sensors.
    capsule: CapsuleConfig = field(default_factory=CapsuleConfig)
    # Contact between capsule and colon wall, one model of physics/contact/: !RigidWall (the
    # stand-in: a wall that does not yield) or !CompliantWall (the wall of measured
    # thickness and moduli on an elastic support).
    contact: RigidWall | CompliantWall = field(default_factory=RigidWall)
    # The force and torque between the two magnets.
    magnet_force: MagnetForceConfig = field(default_factory=MagnetForceConfig)
    # The pseudo-force for the operator's haptic hand (lumen attraction from the lumen
    # tracker, wall avoidance, potential along the colon), in the device frame, saturated
    # to the device's limit. Null: none.
    pseudo_force: PseudoForceConfig | None = None
    # The external magnet, its carrier and its driver.
    epm: EpmConfig = field(default_factory=EpmConfig)
    # Drake's MultibodyPlant settings: time step (s), discrete contact approximation
    # ("lagged", "sap", "similar"), and the rest of MultibodyPlantConfig.
    plant: MultibodyPlantConfig = field(default_factory=_plant_config)
    # Drake's Simulator settings (target_realtime_rate: 1 paces a run to the wall clock).
    simulator: SimulatorConfig = field(default_factory=SimulatorConfig)
    # What a run records.
    outputs: OutputsConfig = field(default_factory=OutputsConfig)
    # When a run is stopped as no longer physical: a state that is not finite, a capsule
    # faster than max_speed, through the wall, out of the colon (io/guard.py).
    guard: GuardConfig = field(default_factory=GuardConfig)
    # Seed of the sensors' noise (the patient's seed is colon.seed): the same seed gives the
    # same recording.
    random_seed: int = 0
    # Simulated time of a run (s).
    duration: float = 60.0


def _read(path: Path) -> str:
    """The text of a scenario file: a regular file (not a directory, device or pipe, which
    could be endless or block), at most MAX_TEXT_BYTES, and text (UTF-8 without control
    characters other than tab and line ends)."""
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        raise ScenarioError(f"{path}: scenario file not found") from None
    except OSError as e:
        raise ScenarioError(f"{path}: cannot read scenario file ({e.strerror})") from None
    if not stat.S_ISREG(info.st_mode):
        kind = ("a directory" if stat.S_ISDIR(info.st_mode) else
                "a device" if stat.S_ISCHR(info.st_mode) or stat.S_ISBLK(info.st_mode) else
                "a pipe" if stat.S_ISFIFO(info.st_mode) else
                "a socket" if stat.S_ISSOCK(info.st_mode) else "not a file")
        raise ScenarioError(f"{path}: not a regular file ({kind})")

    def too_large(size: int) -> ScenarioError:
        return ScenarioError(f"{path}: {size / 1e6:.1f} MB, larger than the "
                             f"{MAX_TEXT_BYTES / 1e6:g} MB a scenario file may be")

    if info.st_size > MAX_TEXT_BYTES:
        raise too_large(info.st_size)
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_TEXT_BYTES + 1)  # the file may have grown since stat()
    except OSError as e:
        raise ScenarioError(f"{path}: cannot read scenario file ({e.strerror})") from None
    if len(data) > MAX_TEXT_BYTES:
        raise too_large(len(data))
    control = _CONTROL.search(data)
    at = control.start() if control is not None else len(data)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        at = min(at, e.start)
    if at < len(data):
        raise ScenarioError(f"{path}: not text (binary data at byte {at})")
    return text


# Bytes no text file holds: the C0 controls but tab, line feed and carriage return, and DEL.
_CONTROL = re.compile(rb"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f]")


def _document(path: Path) -> tuple[str, dict]:
    """(text, parsed document) of a scenario file: a mapping of names to scenarios."""
    text = _read(path)
    try:
        doc = parse_yaml(text, str(path))
    except SchemaError as e:
        raise ScenarioError(str(e)) from None
    if not isinstance(doc, dict):
        raise ScenarioError(f"{path}: expected a mapping of scenario names to scenarios")
    for name in doc:
        if not isinstance(name, str):
            raise ScenarioError(f"{path}: scenario names must be text, got {name!r}")
    return text, doc


def scenario_names(path: Path) -> list[str]:
    """The named scenarios in a scenario file."""
    return list(_document(path)[1])


def _load_one(text: str, source: str, child_name: str | None, base: Scenario | None,
              doc=None) -> Scenario:
    """The scenario of YAML `text` (its child `child_name`, if given) laid over `base`;
    `doc`: the text already parsed."""
    try:
        if doc is None:
            doc = parse_yaml(text, source)
        if doc is None and child_name is None:  # an override of blank lines or comments
            return base if base is not None else Scenario()
        node = doc if child_name is None else doc[child_name]
        if node is None:
            node = {}
        check(Scenario, node, "")
    except SchemaError as e:
        message = _moved(str(e))
        raise ScenarioError(message if message.startswith(source) else f"{source}: {message}") from None
    try:
        return yaml_load_typed(schema=Scenario, data=text, child_name=child_name,
                               defaults=base if base is not None else Scenario())
    except (RuntimeError, ValueError, TypeError, KeyError, ArithmeticError,
            yaml.YAMLError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ScenarioError(f"{source}: {first}") from None


def layered(base: dict, extra: dict) -> dict:
    """`base` (a YAML mapping) with `extra` laid over it, nested mappings merged."""
    out = dict(base)
    for key, value in extra.items():
        out[key] = (layered(out[key], value) if isinstance(value, dict)
                    and isinstance(out.get(key), dict) else value)
    return out


def _moved(message: str) -> str:
    """A schema error about a key that moved says where it went."""
    key = message.split(": unknown key")[0].rsplit(" ", 1)[-1] if ": unknown key" in message else ""
    if key in MOVED:
        return f"{key}: moved to {MOVED[key]}"
    return message


def _chosen_name(path: Path, names: list[str], name: str | None) -> str:
    """The scenario `load_scenario` takes from a file of named ones."""
    if name is None:
        if len(names) == 1:
            return names[0]
        if "Default" in names:
            return "Default"
        raise ScenarioError(f"{path}: holds several scenarios ({', '.join(names)}); "
                            "choose one with --scenario")
    if name not in names:
        raise ScenarioError(f"{path}: no scenario named {name!r} "
                            f"(the file has: {', '.join(names)})")
    return name


def load_scenario(path: Path | str | None = None, name: str | None = None,
                  override: str | list[str] | None = None) -> Scenario:
    """Loads scenario `name` from `path` (default: diagrams/default.yaml), then layers the
    YAML text `override` (same schema, e.g. "duration: 5"; or a list of such texts, in
    order: a user's text, then a command's own flags) on top, then checks it (`validate`).

    Without a name, a file holding a single scenario yields it, and otherwise the one called
    `Default`. A file whose keys are all a scenario's own fields (a run's scenario.yaml) is
    that one scenario, unnamed: it loads as it was run.
    """
    path = Path(path) if path is not None else DEFAULT_SCENARIO_FILE
    text, doc = _document(path)
    names = list(doc)
    if names and set(names) <= set(field_types(Scenario)):
        if name is not None:
            raise ScenarioError(f"{path}: holds one unnamed scenario (as a run's scenario.yaml "
                                f"does), not one named {name!r}; leave out --scenario")
        scenario = _load_one(text, str(path), None, None, doc)
    else:
        name = _chosen_name(path, names, name)
        scenario = _load_one(text, f"{path} [{name}]", name, None, doc)
    overrides = [override] if isinstance(override, str) else list(override or [])
    for text in overrides:
        if text:
            scenario = _load_one(text, "override", None, scenario)
    validate(scenario)
    return scenario


# Bounds of the run's own settings (validate), each with its reason.
MAX_DURATION = 1e6
"""Longest run (s of simulated time): 11.6 days; the longest shipped scenario is 600 s, and
a run goes at most ~10x real time."""
MAX_LOG_SAMPLES = 2_000_000
"""Most samples a run logs (duration / outputs.log_period): each is ~180 bytes (the
capsule's state, the contact load, the EPM's pose) held in memory at the end of the run, so
2 million are ~360 MB (the default run logs 6,000)."""
MIN_VISUAL_PERIOD = 1e-3
"""Shortest period (s) of the Meshcat drawing: a screen shows 60 frames per second."""


def _numbers(obj, key: str = ""):
    """(dotted key, value) of every number, and list of numbers, of a scenario, through its
    blocks and Drake's configs (plant, simulator); absent (null) blocks have none."""
    for name in field_types(type(obj)) or ():
        value = getattr(obj, name)
        where = f"{key}.{name}" if key else name
        if isinstance(value, bool) or value is None or isinstance(value, str):
            continue
        if isinstance(value, (int, float)):
            yield where, value
        elif isinstance(value, list):
            if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
                yield where, value
        else:
            yield from _numbers(value, where)


def _check_finite(scenario: Scenario) -> None:
    """Every number of the scenario is finite: no field means anything at NaN or infinity
    (a NaN magnet size or an infinite friction reaches Drake, which asserts and exits)."""
    for key, value in _numbers(scenario):
        values = value if isinstance(value, list) else [value]
        if not all(isinstance(v, int) or math.isfinite(v) for v in values):
            raise ScenarioError(f"scenario: {key} must be finite, got {value!r}")


def _check_outputs(outputs: OutputsConfig, scenario: Scenario, bound) -> None:
    need = blocks.need
    if outputs.mcap is not None:
        need(outputs.mcap.path.strip() != "", "outputs.mcap.path: the file to write is empty")
        need(outputs.mcap.compression in ("zstd", "lz4", "none"),
             f"outputs.mcap.compression must be zstd, lz4 or none, got "
             f"{outputs.mcap.compression!r}")
    for name in ("meshcat", "foxglove"):
        server = getattr(outputs, name)
        if server is not None:
            need(isinstance(server.host, str) and server.host.strip() != "",
                 f"outputs.{name}.host: the address to listen on is empty")
            bound(server.port, f"outputs.{name}.port", "[0, 65535]", "",
                  "0: any free port" if name == "foxglove" else "")
    if outputs.foxglove is not None:
        bound(outputs.foxglove.wait_for_client, "outputs.foxglove.wait_for_client",
              "[0, 3600]", "s")
        bound(outputs.foxglove.backlog, "outputs.foxglove.backlog", "[16, 1000000]", "",
              "messages queued per client")
    if outputs.ros2 is not None:
        bound(outputs.ros2.domain_id, "outputs.ros2.domain_id", "[0, 232]", "",
              "DDS maps domains 0-232 to UDP ports")
        bound(outputs.ros2.hold_after, "outputs.ros2.hold_after", "(0, 60]", "s")
        need(not outputs.ros2.epm_command or type(scenario.epm.driver).__name__ == "External",
             "outputs.ros2.epm_command needs epm.driver !External (the goal topic drives the "
             f"EPM), got !{type(scenario.epm.driver).__name__}")


def _check_run(scenario: Scenario) -> None:
    """The run's own settings, which are no block of the station: its duration and seed,
    what it records, its simulator and its guard."""
    need = blocks.need

    def bound(value, key: str, interval: str, unit: str = "", why: str = ""):
        blocks.checked("", need_range, value, key, interval, unit, why)

    outputs = scenario.outputs
    bound(scenario.duration, "duration", f"[0, {MAX_DURATION:.0f}]", "s",
          "a million simulated seconds is 11.6 days")
    bound(scenario.random_seed, "random_seed", SEED_RANGE, "",
          "Drake's RandomGenerator keeps 32 bits: 2^32 would repeat seed 0's noise")
    bound(outputs.log_period, "outputs.log_period", f">= {MIN_PERIOD:g}", "s",
          "10 kHz; the plant's state changes once a step (1 ms by default)")
    samples = scenario.duration / outputs.log_period
    need(samples <= MAX_LOG_SAMPLES,
         f"duration / outputs.log_period must be at most {MAX_LOG_SAMPLES:,} samples "
         f"(~180 bytes each, held in memory), got {scenario.duration:g} s / "
         f"{outputs.log_period:g} s = {samples:,.0f}")
    bound(outputs.visual_period, "outputs.visual_period", f">= {MIN_VISUAL_PERIOD:g}", "s",
          "a screen shows 60 frames per second")
    _check_outputs(outputs, scenario, bound)
    simulator = scenario.simulator
    bound(simulator.max_step_size, "simulator.max_step_size", "> 0", "s")
    bound(simulator.accuracy, "simulator.accuracy", "(0, 1]")
    need(simulator.start_time == 0,
         f"simulator.start_time must be 0 (a run's duration counts from 0), got "
         f"{simulator.start_time!r}")
    if simulator.target_realtime_rate != 0:
        bound(simulator.target_realtime_rate, "simulator.target_realtime_rate", ">= 0.01", "",
              "or 0: as fast as it goes; slower pacing turns a minute into hours")
    # What ApplySimulatorConfig would refuse when the run builds its Simulator (app/run.py).
    need(simulator.integration_scheme in GetIntegrationSchemes(),
         f"simulator: Unknown integration scheme: {simulator.integration_scheme} (known: "
         f"{', '.join(GetIntegrationSchemes())})")
    blocks.checked("", check_guard_config, scenario.guard)


def validate(scenario: Scenario) -> None:
    """Every check a scenario gets, once, when it is loaded; raises ScenarioError (one line):
    the run's settings, then each block's check in the station's order (station.py), which
    checks what the block needs of the others too (a tracker needs a camera)."""
    _check_run(scenario)
    blocks.check_blocks(STATION_BLOCKS, scenario)
    # Last, what no block's check bounds (the blocks' checks say what a NaN or an infinity
    # should have been, and none lets one through).
    _check_finite(scenario)
    # The time step against what the magnets and the contact allow, once what it is
    # computed from has been checked (physics/step_bound.py).
    longest, why = time_step_bound(scenario)
    if not scenario.plant.time_step <= longest:
        raise ScenarioError(
            f"scenario: plant.time_step {scenario.plant.time_step:g} s is longer than the "
            f"{longest:g} s this scenario allows ({why})")


def dump_scenario(scenario: Scenario) -> str:
    """The scenario as YAML, every field spelled out (for a run's output folder)."""
    return yaml_dump_typed(scenario)
