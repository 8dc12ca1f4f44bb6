"""The EPM on the five-axis stage: x, y, z, yaw, pitch.

By default the stage is kinematic: the EPM is where the stage's joint command puts it
(`KinematicStage`), drawn from that pose, with no joints in the plant; a servo that tracks
its command within a few milliseconds moves the EPM so, while the capsule takes tenths of a
second to follow. With `kinematic: false` the stage is models/epm_stage.sdf in the plant, its
five joints PD-servoed (implicit in SAP) and the 6.2 kg magnet's dynamics simulated.

A path driver sends the stage a joint trajectory; a pose-command driver goes through the
EPM's guard (epm/guard.py) and `PoseToStage`.
"""

import dataclasses
import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import (Cylinder, FramePoseVector, GeometryFrame, GeometryInstance,
                              MakePhongIllustrationProperties)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.tree import PdControllerGains
from pydrake.systems.framework import BasicVector, LeafSystem
from pydrake.systems.primitives import TrajectorySource

from capsule_drake.epm.poses import stage_joint_positions, stage_to_pose
from capsule_drake.epm.shaping import MotionLimits
from capsule_drake.lifetime import weak_method
from capsule_drake.models import model_url
from capsule_drake.schema import need_range

STAGE_JOINTS = ("x", "y", "z", "yaw", "pitch")


@dataclasses.dataclass
class Gains:
    """PD gains of a joint servo (implicit in Drake's SAP-family solvers)."""

    # Proportional gain: N/m for translation, N m/rad for rotation.
    p: float = 2.0e4
    # Derivative gain: N s/m for translation, N m s/rad for rotation.
    d: float = 7.0e2


@dataclasses.dataclass
class Stage:
    """The EPM on a commanded five-axis stage: light and fast. Its weight is the stage's
    business (a servo that holds the EPM wherever it is sent, as a stiff arm would)."""

    # True: the EPM is where the command puts it, with no stage in the plant (the fast
    # default). False: the five servoed joints and the 6.2 kg magnet are simulated (about
    # 10 % more per step), with the gains below.
    kinematic: bool = True
    # Servo gains of the x, y, z axes.
    translation_gains: Gains = dataclasses.field(default_factory=Gains)
    # Servo gains of the yaw and pitch axes.
    rotation_gains: Gains = dataclasses.field(default_factory=lambda: Gains(p=400.0, d=4.0))
    # How fast the servoed stage is asked to move the EPM toward a pose command (epm/
    # shaping.py): speed (m/s), acceleration (m/s^2), turn rate of the moment (rad/s). The
    # kinematic stage is where it is asked to be; a path driver's trajectory sets its own.
    max_speed: float = 0.25
    max_acceleration: float = 1.0
    max_turn_rate: float = 1.0


def check_stage(config: Stage) -> None:
    """Raises ValueError naming the first impossible gain: a servo needs p > 0 (it holds the
    EPM) and d >= 0 (a negative damping pumps energy in)."""
    for name in ("translation_gains", "rotation_gains"):
        gains = getattr(config, name)
        unit = ("N/m", "N s/m") if name == "translation_gains" else ("N m/rad", "N m s/rad")
        need_range(gains.p, f"{name}.p", "> 0", unit[0])
        need_range(gains.d, f"{name}.d", ">= 0", unit[1])
    need_range(config.max_speed, "max_speed", "[0.001, 1]", "m/s")
    need_range(config.max_acceleration, "max_acceleration", "[0.01, 10]", "m/s^2")
    need_range(config.max_turn_rate, "max_turn_rate", "[0.01, 10]", "rad/s")


# The servoed stage's moving masses (models/epm_stage.sdf; tests/test_epm_clearance.py reads
# them from the model): the x axis carries every link (9.7 kg), y all but x's carriage
# (8.7 kg), z the yaw link and the magnet (7.7 kg); the yaw and pitch axes turn the magnet
# (its 0.00933 kg m^2 across its axis, plus the yaw link's 0.001 about the vertical).
AXIS_MASSES = {"x": 9.7, "y": 8.7, "z": 7.7}
TURN_INERTIAS = {"yaw": 0.00933 + 0.001, "pitch": 0.00933}


def overshoot_factor(zeta: float) -> float:
    """1 + the overshoot of a second-order servo of damping ratio zeta: what an error the
    servo would settle to without overshoot may reach on the way."""
    if zeta >= 1.0:
        return 1.0
    return 1.0 + math.exp(-math.pi * zeta / math.sqrt(1.0 - zeta * zeta))


def servo_errors(config: Stage, pull: float, twist: float, magnet) -> tuple[float, float]:
    """(translation, turn) parts of the worst lag of the servoed stage's magnet toward the
    skin (m), over its axes, given the largest pull (N) and twist (N m) the capsule's magnet
    puts on the EPM. Translation: what the pull and the shaped reference's acceleration
    (max_acceleration) deflect the servo by, (pull + m a) / p. Turn: the twist's deflection
    and the lag behind the start of a turn at max_turn_rate (a critically damped servo lags
    a velocity step w by at most w / (e wn)), times how fast a turn moves the magnet's
    lowest point (its half diagonal per radian). Each times `overshoot_factor`."""
    t, r = config.translation_gains, config.rotation_gains
    translation = max(
        (pull + mass * config.max_acceleration) / t.p
        * overshoot_factor(t.d / (2.0 * math.sqrt(t.p * mass)))
        for mass in AXIS_MASSES.values())
    radius, half = magnet_half_diagonal(magnet)
    turn = max(
        (twist / r.p + config.max_turn_rate / (math.e * math.sqrt(r.p / inertia)))
        * overshoot_factor(r.d / (2.0 * math.sqrt(r.p * inertia)))
        for inertia in TURN_INERTIAS.values()) * math.hypot(radius, half)
    return translation, turn


def magnet_half_diagonal(magnet) -> tuple[float, float]:
    """(radius, half length) of the cylinder that bounds the magnet."""
    dims = magnet.dimensions
    if magnet.shape == "sphere":
        return 0.5 * dims[0], 0.0
    if magnet.shape == "cylinder":
        return 0.5 * dims[0], 0.5 * dims[1]
    return 0.5 * float(np.hypot(dims[0], dims[1])), 0.5 * dims[2]


def check_stage_servo(config: Stage, pull: float, twist: float, magnet,
                      tolerance: float) -> None:
    """Raises ValueError when the servoed stage, as configured, may let the EPM lag or give
    toward the skin by more than `tolerance` (m) under the largest `pull` (N) and `twist`
    (N m) of the magnets (servo_errors): softer gains, less damping or a faster reference
    than that would take the magnet inside its clearance."""
    translation, turn = servo_errors(config, pull, twist, magnet)
    if translation + turn <= tolerance:
        return
    raise ValueError(
        f"the servoed stage may let the EPM sag {(translation + turn) * 1000:.1f} mm toward "
        f"the skin ({translation * 1000:.1f} mm on x, y, z under a {pull:.3g} N pull and "
        f"its max_acceleration, {turn * 1000:.1f} mm on yaw and pitch), more than the "
        f"{tolerance * 1000:g} mm the EPM's clearance allows: stiffer or better damped "
        "translation_gains or rotation_gains, or a lower max_acceleration or "
        "max_turn_rate")


class PoseToStage(LeafSystem):
    """[p_WE, m_hat_W] -> stage desired state [x, y, z, yaw, pitch, zero rates], the yaw
    unwrapped against the previous sample (so the servo never turns the long way round).

    .. pydrake_system::

        name: PoseToStage
        input_ports:
        - epm_command
        output_ports:
        - desired_state

    A non-finite command holds the last state. Samples every `period` (s): the stations use
    the plant's step, the finest at which the EPM's pose can act on the capsule. With
    `rates`, the desired rates are the joints' change since the last sample over the period
    (a servo's velocity feedforward along a shaped path), else zero.
    """

    def __init__(self, initial_stage_q, period: float = 0.001, rates: bool = False):
        super().__init__()
        self._rates = rates
        self._period = float(period)
        self._command = self.DeclareVectorInputPort("epm_command", 6)
        initial = np.concatenate([np.asarray(initial_stage_q, dtype=float)[:5], np.zeros(5)])
        self._state = self.DeclareDiscreteState(BasicVector(initial))
        self.DeclareStateOutputPort("desired_state", self._state)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)
        self._last = None   # (command and state bytes, the update they give)

    def _update(self, context, discrete_state):
        command = self._command.Eval(context)
        state = context.get_discrete_state(self._state).value()
        # The command changes at its source's rate (a navigator's 20 Hz, a path's samples),
        # this samples at the plant's step: an unchanged command and state give the same
        # update (a pure function of the two), kept from the last time.
        key = command.tobytes() + state.tobytes()
        if self._last is not None and self._last[0] == key:
            discrete_state.set_value(self._state, self._last[1])
            return
        x = state.copy()
        command = np.asarray(command, dtype=float)
        if np.all(np.isfinite(command)) and np.linalg.norm(command[3:]) > 1e-9:
            q = stage_joint_positions(command[:3], command[3:] / np.linalg.norm(command[3:]))
            q[3] = x[3] + np.angle(np.exp(1j * (q[3] - x[3])))
            if self._rates:
                x[5:] = (q - x[:5]) / self._period
            x[:5] = q
        elif self._rates:
            x[5:] = 0.0
        discrete_state.set_value(self._state, x)
        self._last = (key, x)


class KinematicStage(LeafSystem):
    """The stage as a commanded pose: desired joint state in, the same state and the EPM's
    pose [p_WE, m_hat_W] out (direct feedthrough; no dynamics).

    .. pydrake_system::

        name: KinematicStage
        input_ports:
        - desired_state
        output_ports:
        - state
        - pose
    """

    def __init__(self):
        super().__init__()
        self._desired = self.DeclareVectorInputPort("desired_state", 10)
        self.DeclareVectorOutputPort("state", 10, self._calc_state)
        self.DeclareVectorOutputPort("pose", 6, self._calc_pose)

    def _calc_state(self, context, output):
        output.SetFromVector(self._desired.Eval(context))

    def _calc_pose(self, context, output):
        output.SetFromVector(stage_to_pose(self._desired.Eval(context)))


class EpmFrame(LeafSystem):
    """The EPM's frame for SceneGraph from the stage's joints: the moment along the frame's
    +z, yaw and pitch as the stage gives them (no roll about the moment). The EPM is only
    drawn (no collision, no camera sees it), so its pose is sampled every `period` (s): the
    scene graph then reads an unchanged pose at the plant's steps in between."""

    def __init__(self, frame_id, initial_stage_q, period: float = 0.01):
        super().__init__()
        self._frame_id = frame_id
        self._desired = self.DeclareVectorInputPort("desired_state", 10)
        self._sample = self.DeclareDiscreteState(np.asarray(initial_stage_q, dtype=float)[:5])
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)
        self.DeclareInitializationDiscreteUpdateEvent(self._update)
        self.DeclareAbstractOutputPort(
            "geometry_pose", lambda: AbstractValue.Make(FramePoseVector()),
            weak_method(self._calc),
            prerequisites_of_calc={self.discrete_state_ticket(self._sample)})

    def _update(self, context, discrete_state):
        discrete_state.set_value(self._sample, self._desired.Eval(context)[:5])

    def _calc(self, context, output):
        x, y, z, yaw, pitch = context.get_discrete_state(self._sample).value()
        poses = output.get_mutable_value()
        poses.clear()
        poses.set_value(self._frame_id, RigidTransform(
            RotationMatrix.MakeZRotation(yaw) @ RotationMatrix.MakeYRotation(pitch),
            [x, y, z]))


EPM_COLOUR = (0.62, 0.64, 0.68, 1.0)
NORTH_COLOUR = (0.80, 0.15, 0.12, 1.0)


class KinematicStageMount:
    """The kinematic stage in a station: no plant model; the EPM is drawn by SceneGraph
    from its commanded pose (source `epm_stage`, frame `epm`), and the magnet force reads
    that pose (MagnetSpec.posed)."""

    model_name = None
    instance = None

    def __init__(self, config: Stage):
        self.config = config

    def add_models(self, plant, parser):
        """Nothing goes into the plant."""
        return None

    def motion_limits(self) -> MotionLimits:
        """The kinematic stage is where it is asked to be (its path: the shaper's lines)."""
        return MotionLimits()

    def add_visual(self, scene_graph, magnet):
        """The EPM's look: a cylinder of the magnet's size with its north face marked."""
        self._source = scene_graph.RegisterSource("epm_stage")
        frame = scene_graph.RegisterFrame(self._source, GeometryFrame("epm"))
        radius, length = epm_visual_size(magnet)
        for name, shape, z, rgba in (
                ("magnet", Cylinder(radius, length), 0.0, EPM_COLOUR),
                ("north_cap", Cylinder(radius, 0.001), 0.5 * length + 0.0005, NORTH_COLOUR)):
            instance = GeometryInstance(RigidTransform([0.0, 0.0, z]), shape, name)
            instance.set_illustration_properties(MakePhongIllustrationProperties(rgba))
            scene_graph.RegisterGeometry(self._source, frame, instance)
        self._frame = frame

    def connect(self, builder, parts, q0):
        """After Finalize: the stage (`epm_stage`), starting at joints `q0`; exports
        epm.state (stage joints [x y z yaw pitch, rates], as commanded)."""
        self._q0 = np.asarray(q0, dtype=float).ravel()
        self.add_visual(parts.scene_graph, parts.epm.magnet)
        self.stage = builder.AddNamedSystem("epm_stage", KinematicStage())
        frame = builder.AddNamedSystem("epm_frame", EpmFrame(self._frame, self._q0))
        self._inputs = [self.stage.GetInputPort("desired_state"),
                        frame.GetInputPort("desired_state")]
        builder.Connect(frame.get_output_port(),
                        parts.scene_graph.get_source_pose_port(self._source))
        parts.export(self.stage.GetOutputPort("state"), "epm.state")

    def pose_output(self):
        return self.stage.GetOutputPort("pose")

    def _drive(self, builder, parts, port):
        for input_port in self._inputs:
            builder.Connect(port, input_port)
        parts.export(port, "epm.desired_state")

    def follow(self, builder, parts, trajectory):
        """The stage follows the joint trajectory (`epm_path`); exports epm.desired_state.
        Returns the path's system."""
        path = builder.AddNamedSystem(
            "epm_path", TrajectorySource(trajectory, output_derivative_order=1))
        self._drive(builder, parts, path.get_output_port())
        return path

    def carrier_input(self, builder, parts):
        """The input a pose command [p_WE, m_hat_W] goes to (`epm_stage_command`), from the
        EPM's guard (drivers connect to `EpmParts.command_input`); exports
        epm.desired_state."""
        stage = builder.AddNamedSystem("epm_stage_command", PoseToStage(
            self._q0, period=parts.plant.time_step()))
        self._drive(builder, parts, stage.get_output_port())
        return stage.GetInputPort("epm_command")


def epm_visual_size(magnet):
    """(radius, length) of the cylinder that draws the EPM: its own for a cylinder, the
    bounding cylinder of a cuboid, a sphere's diameter for both."""
    dims = magnet.dimensions
    if magnet.shape == "cylinder":
        return 0.5 * dims[0], dims[1]
    if magnet.shape == "sphere":
        return 0.5 * dims[0], dims[0]
    return 0.5 * float(np.hypot(dims[0], dims[1])), dims[2]


class StageMount:
    """The servoed stage in a station: its model, its start, and how a driver commands it."""

    model_name = "epm_stage"

    def __init__(self, config: Stage):
        self.config = config

    def add_models(self, plant, parser):
        """Before Finalize: the stage and its servo gains; returns its model instance."""
        self.instance, = parser.AddModels(url=model_url("epm_stage.sdf"))
        plant.set_gravity_enabled(self.instance, False)
        for name in STAGE_JOINTS:
            gains = (self.config.translation_gains if name in ("x", "y", "z")
                     else self.config.rotation_gains)
            plant.GetJointActuatorByName(name, self.instance).set_controller_gains(
                PdControllerGains(p=gains.p, d=gains.d))
        return self.instance

    def motion_limits(self) -> MotionLimits:
        """The speeds the servoed stage is asked to move at (Stage's max_*)."""
        c = self.config
        return MotionLimits(c.max_speed, c.max_acceleration, c.max_turn_rate)

    def connect(self, builder, parts, q0):
        """After Finalize: start at the stage joints `q0`; exports epm.state (stage joints
        [x y z yaw pitch, rates])."""
        plant = parts.plant
        actuated = [plant.get_joint_actuator(i).joint().name()
                    for i in plant.GetJointActuatorIndices(self.instance)]
        assert tuple(actuated) == STAGE_JOINTS, actuated
        self._q0 = np.asarray(q0, dtype=float).ravel()
        for name, value in zip(STAGE_JOINTS, self._q0):
            joint = plant.GetJointByName(name, self.instance)
            if name in ("x", "y", "z"):
                joint.set_default_translation(value)
            else:
                joint.set_default_angle(value)
        parts.export(plant.get_state_output_port(self.instance), "epm.state")

    def follow(self, builder, parts, trajectory):
        """The stage's servos follow the joint trajectory (`epm_path`); exports
        epm.desired_state. Returns the path's system."""
        path = builder.AddNamedSystem(
            "epm_path", TrajectorySource(trajectory, output_derivative_order=1))
        builder.Connect(path.get_output_port(),
                        parts.plant.get_desired_state_input_port(self.instance))
        parts.export(path.get_output_port(), "epm.desired_state")
        return path

    def carrier_input(self, builder, parts):
        """The input a pose command [p_WE, m_hat_W] goes to (`epm_stage_command`), from the
        EPM's guard (drivers connect to `EpmParts.command_input`); exports
        epm.desired_state."""
        stage = builder.AddNamedSystem("epm_stage_command", PoseToStage(
            self._q0, period=parts.plant.time_step(), rates=True))
        builder.Connect(stage.get_output_port(),
                        parts.plant.get_desired_state_input_port(self.instance))
        parts.export(stage.get_output_port(), "epm.desired_state")
        return stage.GetInputPort("epm_command")
