"""Scenario: everything that defines one simulation, as typed dataclasses loaded from YAML.

A scenario file holds one or more named scenarios as top-level keys:

    Default: {}
    FarMagnet:
      epm:
        path: !HoldAbove {height: 0.5}

Every field has a default, so `Default: {}` is a complete scenario. Unknown keys, wrong types
and missing files raise `ScenarioError` with one line naming the file and the key.
Units are SI throughout (metres, seconds, newtons, tesla, A m^2).
"""


import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed

from capsule_drake.anatomy import ColonParams, check_colon_params
from capsule_drake.guidance.terms import PseudoForceConfig, check_pseudo_force_config
from capsule_drake.physics.magnetics import MagnetGeometry
from capsule_drake.schema import SchemaError, check, parse_yaml
from capsule_drake.capsule.ahrs import AhrsConfig
from capsule_drake.capsule.camera import CameraConfig, check_camera_config
from capsule_drake.teleop.channel import (TeleopChannelConfig, check_channel_config,
                                           check_passivity_config)
from capsule_drake.teleop.haptic_master import HapticDeviceConfig, check_haptic_device_config
from capsule_drake.epm.arm import ArmConfig, check_arm_config
from capsule_drake.capsule.imu import ImuConfig
from capsule_drake.perception.lumen_tracker import LumenTrackerConfig
from capsule_drake.physics.magnet_force import FIELD_MODELS
from capsule_drake.capsule.magnetometer import MagnetometerConfig
from capsule_drake.teleop.mapping import MappingConfig, check_mapping_config
from capsule_drake.teleop.operator import OperatorConfig, check_operator_config
from capsule_drake.teleop.udp import UdpBridgeConfig, check_udp_bridge_config
from capsule_drake.perception.lumen import check_lumen_params, load_detector

REPO_ROOT = Path(__file__).resolve().parents[1]
DIAGRAMS_DIR = REPO_ROOT / "diagrams"
DEFAULT_SCENARIO_FILE = DIAGRAMS_DIR / "default.yaml"


CONTACT_MODELS = ("hydroelastic", "convex_pieces")
EPM_MOUNTS = ("stage", "arm")


class ScenarioError(ValueError):
    """A scenario file or override is wrong; the message is one line naming where."""


@dataclass
class ContactConfig:
    """How the capsule touches the colon wall."""

    # "hydroelastic" (fidelity): the colon wall is a rigid non-convex triangle mesh split into
    # chunks and the capsule a compliant hydroelastic capsule; contact forces are pressure
    # fields over contact patches. ~3x real time.
    # "convex_pieces" (speed, for long batch runs): the wall is ~2,700 small convex hulls of
    # wall patches and contact is Drake's point contact; ~9-14x real time, but the diagram
    # takes ~15 s and ~2 GB to build, and pieces bridge the sharpest fold feet (the capsule
    # rides up to ~1 mm higher there).
    model: str = "hydroelastic"
    # Hydroelastic modulus of the capsule's compliant layer (Pa). 5e6 keeps the penetration
    # under a 1 N load near 0.6 mm (measured, REFERENCE section 6). Engineering assumption.
    capsule_hydroelastic_modulus: float = 5.0e6
    # Edge length of the capsule's tetrahedral pressure mesh (m). Finer costs query time.
    capsule_resolution_hint: float = 0.004
    # Hunt-Crossley dissipation of the contact (s/m). Engineering assumption.
    hunt_crossley_dissipation: float = 5.0
    # convex_pieces: stiffness of each point contact (N/m; capsule and wall in series halve
    # it), and the pieces' axial length and largest chord depth below the round wall (m).
    point_stiffness: float = 2.0e4
    piece_axial_length: float = 0.010
    piece_max_chord_depth: float = 0.0005
    # Coulomb friction between capsule and mucosa (dynamic = static). Measured values span
    # 0.0004-0.054 on small-bowel mucosa; REFERENCE section 3 suggests sweeping 0.05-0.3.
    friction: float = 0.2
    # Resistance to the capsule's motion that grows with its speed (tissue drag, mucus; the
    # colon's friction rises with sliding velocity, Gao et al., IEEE Trans. Biomed. Eng.):
    # a linear damping of the capsule's velocity relative to the colon, translational
    # (N s/m) and rotational (N m s/rad), on its floating joint. 0 (default): not modelled,
    # only Coulomb friction resists motion, so a capsule that breaks free accelerates.
    drag_translational: float = 0.0
    drag_rotational: float = 0.0
    # Drake's discrete contact approximation: "lagged" (default of Drake 1.58), "sap",
    # "similar" or "tamsi" (gone in 1.58).
    discrete_contact_approximation: str = "lagged"


@dataclass
class CapsuleConfig:
    """The capsule: where it starts and its internal permanent magnet (IPM)."""

    # Arc length along the colon's centerline, from the anus, where the capsule starts (m).
    start_s: float = 0.05
    # The IPM: an N52 cylinder of 11.1 x 11.1 mm, m = 1.26 A m^2 (REFERENCE section 1).
    # Its pose in the capsule is the `ipm` frame of models/capsule.sdf (axial magnetisation).
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
    # The camera at the front dome (null: none, the default, since rendering costs more
    # than the physics; `capsule-sim record` switches it on). `camera: {}` gives the
    # 172-degree fisheye at 256 px and 10 fps with the LED light at the lens.
    camera: CameraConfig | None = None
    # Lumen ground truth: the centerline point this far ahead of the camera (m).
    lumen_lookahead: float = 0.05
    # The lumen tracker on the camera's frames (needs the camera): `lumen_tracker: {}` runs
    # the seed's detector; `detector: my_package.module:function` plugs in a user's.
    lumen_tracker: LumenTrackerConfig | None = None


@dataclass
class AlongColon:
    """The EPM travels over the colon's course at a constant speed, outside the abdomen.

    At each instant it hovers over the centerline point s(t), as low as its clearance from the
    skin allows, with its moment turned so that its field at that centerline point lies along
    the colon's tangent (REFERENCE section 1: m_E along (3/2 u u^T - I) h), so the capsule's
    magnet, and with it the camera, points down the lumen.
    """

    # Seconds the EPM waits over the capsule's start before moving (the capsule settles).
    settle_time: float = 1.0
    # Travel speed along the centerline (m/s).
    speed: float = 0.01
    # How far ahead of the capsule's start the EPM begins (m).
    lead: float = 0.0
    # Arc length at which the EPM stops (m); 0 means the cecum end of the colon.
    end_s: float = 0.0


@dataclass
class HoldAbove:
    """The EPM stays still, straight above the capsule's start point."""

    # Distance from the capsule's start point up to the EPM's centre (m).
    height: float = 0.5


@dataclass
class Gains:
    """PD gains of the EPM stage's joint servos (implicit in Drake's SAP-family solvers)."""

    # Proportional gain: N/m for translation, N m/rad for rotation.
    p: float = 2.0e4
    # Derivative gain: N s/m for translation, N m s/rad for rotation.
    d: float = 7.0e2


@dataclass
class EpmConfig:
    """The external permanent magnet and the stage that carries it."""

    # 101.6 x 101.6 mm N52 cylinder, 970 A m^2 (REFERENCE section 1).
    magnet: MagnetGeometry = field(default_factory=MagnetGeometry)
    # Where the EPM goes: !AlongColon (default) or !HoldAbove.
    path: AlongColon | HoldAbove = field(default_factory=AlongColon)
    # Smallest allowed gap between the magnet's surface and the patient's skin (m).
    clearance: float = 0.02
    # Servo gains of the x, y, z axes.
    translation_gains: Gains = field(default_factory=Gains)
    # Servo gains of the yaw and pitch axes.
    rotation_gains: Gains = field(default_factory=lambda: Gains(p=400.0, d=4.0))
    # What carries the magnet: "stage" (a commanded five-axis body, light and fast) or
    # "arm" (the 7-DoF arm of models/epm_arm.sdf with its controller; `arm` configures it).
    # The gains above are the stage's.
    mount: str = "stage"
    arm: ArmConfig = field(default_factory=ArmConfig)


OPERATORS = ("simulated", "browser", "udp")
LUMEN_SOURCES = ("tracker", "truth")


@dataclass
class TeleopConfig:
    """Haptic teleoperation: the operator moves a stylus, the EPM follows the mapping, and
    the operator feels the pseudo-force (scenario's `pseudo_force`; null: no guidance) plus
    the capsule's contact with the wall. Replaces the EPM's path."""

    # Who holds the stylus: "simulated" (a model of a hand), "browser" (keyboard, gamepad
    # and sliders in Meshcat, paced in real time) or "udp" (a real device over the
    # network bridge).
    operator: str = "simulated"
    # The haptic device (Geomagic Touch figures).
    device: HapticDeviceConfig = field(default_factory=HapticDeviceConfig)
    # Stylus to EPM mapping (position or rate mode, scales, clutch).
    mapping: MappingConfig = field(default_factory=MappingConfig)
    # The simulated operator's hand and intent.
    simulated: OperatorConfig = field(default_factory=OperatorConfig)
    # What the simulated operator sees of the lumen: the lumen tracker's detection (needs
    # capsule.lumen_tracker) or the truth (needs capsule.camera).
    lumen_source: str = "tracker"
    # Delay, jitter and loss both ways, and the passivity scheme at the device. The scheme
    # (time-domain passivity) acts only when the link has delay, jitter or loss: with an
    # ideal link there is nothing to stabilise, and strict passivity would also mute the
    # guidance, which puts energy into the hand by design.
    channel: TeleopChannelConfig = field(default_factory=TeleopChannelConfig)
    # Device newtons per newton of the capsule's contact force with the wall.
    contact_gain: float = 1.0
    # The network bridge for a real device (operator "udp"): loopback by default.
    udp: UdpBridgeConfig = field(default_factory=UdpBridgeConfig)


@dataclass
class Scenario:
    """One simulation: patient, capsule, magnet, contact model and timing."""

    # The patient's colon (anatomy, seed, mesh resolution).
    colon: ColonParams = field(default_factory=ColonParams)
    # The capsule and its internal magnet.
    capsule: CapsuleConfig = field(default_factory=CapsuleConfig)
    # The external magnet and its path.
    epm: EpmConfig = field(default_factory=EpmConfig)
    # Contact between capsule and colon wall.
    contact: ContactConfig = field(default_factory=ContactConfig)
    # Haptic teleoperation (null: none; the EPM follows its path).
    teleop: TeleopConfig | None = None
    # The pseudo-force for the operator's haptic hand (lumen attraction from the lumen
    # tracker, wall avoidance, potential along the colon), in the device frame, saturated
    # to the device's limit. Null: none.
    pseudo_force: PseudoForceConfig | None = None
    # Seed of the sensors' noise (the patient's seed is colon.seed): the same seed gives the
    # same recording.
    random_seed: int = 0
    # Discrete time step of the MultibodyPlant (s).
    time_step: float = 1.0e-3
    # Period at which the magnetic force is recomputed (s); 0 = every plant step. Holding it
    # over 2 ms halves the Python cost per step; the held force is stable while the magnet's
    # rotational stiffness keeps omega * period < ~1 (omega ~ 500 rad/s at the 10 cm the EPM's
    # clearance allows at most).
    magnet_update_period: float = 0.0
    # Field model of the magnets: "dipole" (point dipoles: fast, differentiable, off by 18 %
    # at 10 cm and 3 % at 20 cm from the EPM) or "finite" (the exact field of a cylinder
    # EPM and the capsule's cylinder magnet integrated over its volume: within 0.1 % of a
    # meshed reference; float only). Spheres are exact dipoles in either; cuboids have
    # only the dipole model.
    magnet_model: str = "dipole"
    # Simulated time of a run (s).
    duration: float = 60.0
    # Period at which the run records poses and contact forces for its metrics (s).
    log_period: float = 0.01
    # Period at which Meshcat is updated, when it is used (s).
    visual_period: float = 1.0 / 32.0


def _read(path: Path) -> str:
    try:
        return Path(path).read_text()
    except FileNotFoundError:
        raise ScenarioError(f"{path}: scenario file not found") from None
    except OSError as e:
        raise ScenarioError(f"{path}: cannot read scenario file ({e.strerror})") from None


def scenario_names(path: Path) -> list[str]:
    """The named scenarios in a scenario file."""
    try:
        doc = parse_yaml(_read(path), str(path))
    except SchemaError as e:
        raise ScenarioError(str(e)) from None
    if not isinstance(doc, dict):
        raise ScenarioError(f"{path}: expected a mapping of scenario names to scenarios")
    return list(doc)


def _load_one(text: str, source: str, child_name: str | None, base: Scenario | None) -> Scenario:
    try:
        doc = parse_yaml(text, source)
        node = doc if child_name is None else doc[child_name]
        if node is None:
            node = {}
        check(Scenario, node, "")
    except SchemaError as e:
        message = str(e)
        raise ScenarioError(message if message.startswith(source) else f"{source}: {message}") from None
    try:
        return yaml_load_typed(schema=Scenario, data=text, child_name=child_name,
                               defaults=base if base is not None else Scenario())
    except (RuntimeError, ValueError) as e:
        raise ScenarioError(f"{source}: {str(e).splitlines()[0]}") from None


def layered(base: dict, extra: dict) -> dict:
    """`base` (a YAML mapping) with `extra` laid over it, nested mappings merged."""
    out = dict(base)
    for key, value in extra.items():
        out[key] = (layered(out[key], value) if isinstance(value, dict)
                    and isinstance(out.get(key), dict) else value)
    return out


def load_scenario(path: Path | str | None = None, name: str | None = None,
                  override: str | None = None) -> Scenario:
    """Loads scenario `name` from `path` (default: diagrams/default.yaml), then layers the
    YAML text `override` (same schema, e.g. "duration: 5") on top.

    Without a name, a file holding a single scenario yields it, and otherwise the one called
    `Default`.
    """
    path = Path(path) if path is not None else DEFAULT_SCENARIO_FILE
    names = scenario_names(path)
    if name is None:
        if len(names) == 1:
            name = names[0]
        elif "Default" in names:
            name = "Default"
        else:
            raise ScenarioError(f"{path}: holds several scenarios ({', '.join(names)}); "
                                "choose one with --scenario")
    if name not in names:
        raise ScenarioError(f"{path}: no scenario named {name!r} "
                            f"(the file has: {', '.join(names)})")
    scenario = _load_one(_read(path), f"{path} [{name}]", name, None)
    if override:
        scenario = _load_one(override, "override", None, scenario)
    validate(scenario)
    return scenario


def validate(scenario: Scenario) -> None:
    """Range checks that the type system cannot express; raises ScenarioError."""
    def need(ok: bool, what: str):
        if not ok:
            raise ScenarioError(f"scenario: {what}")

    need(scenario.time_step > 0, f"time_step must be positive, got {scenario.time_step}")
    need(scenario.duration >= 0, f"duration must be >= 0, got {scenario.duration}")
    need(scenario.log_period > 0, f"log_period must be positive, got {scenario.log_period}")
    need(scenario.magnet_update_period >= 0,
         f"magnet_update_period must be >= 0, got {scenario.magnet_update_period}")
    need(scenario.magnet_model in FIELD_MODELS,
         f"magnet_model must be one of {', '.join(FIELD_MODELS)}, "
         f"got {scenario.magnet_model!r}")
    if scenario.magnet_model == "finite":
        for where, geometry in (("epm.magnet", scenario.epm.magnet),
                                ("capsule.ipm", scenario.capsule.ipm)):
            need(geometry.shape in ("cylinder", "sphere") and not geometry.legacy,
                 f"magnet_model 'finite' needs cylinder or sphere magnets without the legacy "
                 f"moment, but {where} is a {'legacy ' if geometry.legacy else ''}"
                 f"{geometry.shape}")
    need(scenario.contact.model in CONTACT_MODELS,
         f"contact.model must be one of {', '.join(CONTACT_MODELS)}, "
         f"got {scenario.contact.model!r}")
    need(scenario.contact.friction >= 0, "contact.friction must be >= 0")
    need(scenario.contact.drag_translational >= 0, "contact.drag_translational must be >= 0")
    need(scenario.contact.drag_rotational >= 0, "contact.drag_rotational must be >= 0")
    need(scenario.epm.clearance >= 0, "epm.clearance must be >= 0")
    need(scenario.epm.mount in EPM_MOUNTS,
         f"epm.mount must be one of {', '.join(EPM_MOUNTS)}, got {scenario.epm.mount!r}")
    try:
        check_arm_config(scenario.epm.arm)
    except ValueError as e:
        raise ScenarioError(f"scenario: {e}") from None
    for where, magnet in (("capsule.ipm", scenario.capsule.ipm), ("epm.magnet", scenario.epm.magnet)):
        try:
            magnet.moment()
        except ValueError as e:
            raise ScenarioError(f"scenario: {where}: {e}") from None
    try:
        check_colon_params(scenario.colon)
    except ValueError as e:
        raise ScenarioError(f"scenario: {e}") from None
    need(scenario.contact.model != "convex_pieces" or scenario.colon.source == "procedural",
         "contact.model convex_pieces needs the procedural colon (its pieces are cut from "
         f"the analytic wall), not colon.source {scenario.colon.source!r}")
    need(scenario.capsule.start_s >= 0, "capsule.start_s must be >= 0")
    if scenario.capsule.camera is not None:
        try:
            check_camera_config(scenario.capsule.camera)
        except ValueError as e:
            raise ScenarioError(f"scenario: capsule.camera: {e}") from None
    need(scenario.capsule.lumen_lookahead > 0, "capsule.lumen_lookahead must be > 0")
    teleop = scenario.teleop
    if teleop is not None:
        need(teleop.operator in OPERATORS,
             f"teleop.operator must be one of {', '.join(OPERATORS)}, got {teleop.operator!r}")
        need(teleop.lumen_source in LUMEN_SOURCES,
             f"teleop.lumen_source must be one of {', '.join(LUMEN_SOURCES)}, got "
             f"{teleop.lumen_source!r}")
        need(teleop.contact_gain >= 0, "teleop.contact_gain must be >= 0")
        try:
            check_haptic_device_config(teleop.device)
            check_mapping_config(teleop.mapping)
            check_operator_config(teleop.simulated)
            check_channel_config(teleop.channel.forward)
            check_channel_config(teleop.channel.backward)
            check_passivity_config(teleop.channel.passivity)
            check_udp_bridge_config(teleop.udp)
        except ValueError as e:
            raise ScenarioError(f"scenario: teleop: {e}") from None
        if teleop.operator == "simulated":
            need(scenario.capsule.camera is not None,
                 "teleop.operator simulated needs capsule.camera (it watches the image)")
            need(teleop.lumen_source == "truth" or scenario.capsule.lumen_tracker is not None,
                 "teleop.lumen_source tracker needs capsule.lumen_tracker")
    if scenario.pseudo_force is not None:
        try:
            check_pseudo_force_config(scenario.pseudo_force)
        except ValueError as e:
            raise ScenarioError(f"scenario: pseudo_force: {e}") from None
        need(scenario.pseudo_force.lumen_weight == 0 or scenario.capsule.lumen_tracker is not None,
             "pseudo_force.lumen_weight needs capsule.lumen_tracker (and a camera), or set "
             "lumen_weight: 0")
    tracker = scenario.capsule.lumen_tracker
    if tracker is not None:
        need(scenario.capsule.camera is not None,
             "capsule.lumen_tracker needs capsule.camera (give a camera, e.g. camera: {})")
        try:
            check_lumen_params(tracker.params)
            load_detector(tracker.detector, tracker.params)
        except ValueError as e:
            raise ScenarioError(f"scenario: capsule.lumen_tracker: {e}") from None
    for name in ("imu", "magnetometer"):
        sensor = getattr(scenario.capsule, name)
        need(sensor is None or sensor.sample_rate > 0,
             f"capsule.{name}.sample_rate must be > 0, got "
             f"{getattr(sensor, 'sample_rate', None)}")
    need(scenario.capsule.ahrs is None or scenario.capsule.imu is not None,
         "capsule.ahrs needs capsule.imu (set ahrs: null too, or give an imu)")
    path = scenario.epm.path
    if isinstance(path, AlongColon):
        need(path.speed >= 0, "epm.path.speed must be >= 0")
        need(path.settle_time >= 0, "epm.path.settle_time must be >= 0")


def dump_scenario(scenario: Scenario) -> str:
    """The scenario as YAML, every field spelled out (for a run's output folder)."""
    return yaml_dump_typed(scenario)


def with_changes(scenario: Scenario, **changes) -> Scenario:
    """A copy of the scenario with top-level fields replaced; the original is untouched."""
    return dataclasses.replace(scenario, **changes)
