"""Three-axis magnetometer on a plant body: the field of the external magnets, with noise.

The ideal value is the sum of the point-dipole fields (``capsule_drake.physics.magnetics.dipole_field``,
Mahoney & Abbott, IJRR 2016; with field_model "finite", a cylinder source's exact field,
``magnetics.cylinder_field``) of the source magnets at the sensor point S, expressed in the
sensor frame. Magnets on the sensor's own body are left out: their field at the sensor is
constant in the body frame (for a capsule, the internal permanent magnet's self-field), and a
real capsule measures it once and subtracts it (hard-iron calibration). That subtraction works
only while the sum of self-field and external field stays inside the sensor's range; this model
applies the range to the external field alone, i.e. it assumes a sensor placed (or chosen) so
that the self-field does not saturate it. The earth's field (~50 uT) is not modelled: next to
the external magnet it is three orders of magnitude smaller.

The noise is the same per-axis model as the IMU's (``capsule_drake.capsule.imu.ChannelNoise``):
white noise of a one-sided density, bias random walk, turn-on bias, range, quantisation.
"""


import copy
import dataclasses

import numpy as np
from pydrake.common import RandomDistribution
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.framework import LeafSystem

from capsule_drake.blocks import block
from capsule_drake.capsule.model import check_board_sensor
from capsule_drake.physics.magnetics import DEFAULT_MIN_DISTANCE, cylinder_field, dipole_field
from capsule_drake.capsule.imu import (ChannelNoise, add_random_sources, check_resolution_bits,
                                       check_sensor_frame)
from capsule_drake.physics.magnet_force import FIELD_MODELS
from capsule_drake.schema import MAX_RATE, need_range


@dataclasses.dataclass
class MagnetometerConfig:
    """A 3-axis Hall magnetometer in the capsule; YAML-loadable.

    SI units (T, s, Hz). DS = Melexis MLX90393 datasheet (a 3 x 3 mm 3-axis Hall sensor,
    16-bit output, programmable range 5-50 mT); U = engineering assumption.
    """

    # Output data rate (Hz). U.
    sample_rate: float = 100.0
    # Sensor frame S in the capsule body frame: origin (m) and roll-pitch-yaw (deg). On the
    # axis 8 mm ahead of the centre, between the magnet (3 mm behind) and the camera. U.
    p_BS: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.008])
    rpy_BS_deg: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])
    # White-noise density, one-sided (T/sqrt(Hz)): 3.5 uT rms per sample at 100 Hz. U.
    noise_density: float = 0.5e-6
    # Bias random walk (T/sqrt(s)); thermal drift is not modelled by default. U.
    bias_random_walk: float = 0.0
    # Turn-on bias: fixed part per axis (T) and per-run standard deviation (T), the residual
    # of the hard-iron (self-field) calibration. U.
    initial_bias: list[float] = dataclasses.field(default_factory=lambda: [0.0] * 3)
    initial_bias_sigma: float = 20e-6
    # Full-scale range per axis (T): 50 mT, the widest MLX90393 setting (DS). The external
    # magnet exceeds it closer than about 16 cm (57.5 mT on axis at 15 cm, docs/sources.md
    # section 1): raise it to model a wider-range sensor.
    range: float = 0.05
    # ADC resolution (bits) over the full-scale range (16, DS); 0 = no quantisation.
    resolution_bits: int = 16

    def X_BS(self) -> RigidTransform:
        """The sensor frame's pose in the body frame."""
        return RigidTransform(RollPitchYaw(np.deg2rad(self.rpy_BS_deg)), np.array(self.p_BS))

    def channel(self) -> ChannelNoise:
        """Per-sample noise parameters."""
        return ChannelNoise.from_datasheet(
            self.noise_density, self.bias_random_walk, self.sample_rate, self.initial_bias,
            self.initial_bias_sigma, self.range, self.resolution_bits)


def check_magnetometer_config(config: MagnetometerConfig) -> None:
    """Raises ValueError naming the first impossible field (relative to the magnetometer)."""
    need_range(config.sample_rate, "sample_rate", f"(0, {MAX_RATE:g}]", "Hz",
               "the MLX90393 samples at up to ~700 Hz")
    check_sensor_frame(config)
    if len(config.initial_bias) != 3:
        raise ValueError(f"initial_bias must have 3 entries, got {config.initial_bias}")
    for name in ("noise_density", "bias_random_walk", "initial_bias_sigma"):
        need_range(getattr(config, name), name, ">= 0", "", "a standard deviation")
    need_range(config.range, "range", "> 0", "T")
    check_resolution_bits(config.resolution_bits)


def field_in_sensor_frame(X_WS: RigidTransform, sources, min_distance=DEFAULT_MIN_DISTANCE):
    """Sum of the fields of ``sources`` at S, expressed in S (T).

    Args:
        X_WS: the sensor frame's pose in world.
        sources: iterable of ``(p_WM, m_W)`` or ``(p_WM, m_W, cylinder)``: magnet centre (m)
            and moment (A m^2) in world; with a cylinder [diameter, length], its exact field
            (``magnetics.cylinder_field``), else the dipole's.
    """
    p_WS = X_WS.translation()
    B_W = np.zeros(3)
    for p_WM, m_W, *shape in sources:
        if shape and shape[0]:
            B_W += cylinder_field(m_W, [p_WS - p_WM], *shape[0])[0]
        else:
            B_W += dipole_field(m_W, p_WS - p_WM, min_distance)
    return X_WS.rotation().inverse().multiply(B_W)


def resolve_sources(plant, body_index: int, sources, field_model: str):
    """The source magnets as (name, body index (-1: posed), p_BM, m_B, cylinder or ()),
    and the names of those on the body `body_index` (a sensor's own body: left out)."""
    resolved, excluded = [], []
    for spec in sources:
        cylinder = tuple(spec.cylinder) if field_model == "finite" else ()
        if spec.posed:   # pose from the input <name>.pose; moment along its direction
            resolved.append((spec.name, -1, np.zeros(3),
                             np.array([0.0, 0.0, float(spec.moment)]), cylinder))
            continue
        if spec.model_instance:
            source_body = plant.GetBodyByName(
                spec.body, plant.GetModelInstanceByName(spec.model_instance))
        else:
            source_body = plant.GetBodyByName(spec.body)
        if int(source_body.index()) == body_index:
            excluded.append(spec.name)
            continue
        axis = np.asarray(spec.axis_B, float).reshape(3)
        norm = np.linalg.norm(axis)
        if norm == 0.0:
            raise ValueError(f"Magnet {spec.name!r}: axis_B must be nonzero")
        resolved.append((spec.name, int(source_body.index()),
                         np.asarray(spec.p_BM, float).reshape(3),
                         axis * (float(spec.moment) / norm), cylinder))
    return resolved, excluded


def source_poses(resolved, body_poses, posed=None):
    """[(p_WM, m_W, cylinder)] of `resolve_sources`' magnets for a list of body poses and,
    for posed sources, `posed`: name -> [p_WM, m_hat_W]."""
    out = []
    for name, index, p_BM, m_B, cylinder in resolved:
        if index < 0:
            pose = np.asarray(posed[name], dtype=float)
            out.append((pose[:3], m_B[2] * pose[3:] / np.linalg.norm(pose[3:]), cylinder))
            continue
        X_WB = body_poses[index]
        out.append((X_WB @ p_BM, X_WB.rotation() @ m_B, cylinder))
    return out


class Magnetometer(LeafSystem):
    """Samples the field of a set of magnets at a point of a body, with a sensor's errors.

    Every ``1 / config.sample_rate`` s (first at t = 0) the field of the source magnets at S
    (``field_in_sensor_frame``) is sampled, the noise model of ``config.channel()`` applied,
    and the result held. Sources on the sensor's own body are excluded (module docstring).

    .. pydrake_system::

        name: Magnetometer
        input_ports:
        - body_poses
        - white_noise (random)
        - bias_walk_noise (random)
        - initial_bias_noise (random)
        output_ports:
        - B_S
        - B_S_true
        - bias

    - ``body_poses``: ``list[RigidTransform]``, the plant's ``get_body_poses_output_port()``.
    - ``white_noise``, ``bias_walk_noise``, ``initial_bias_noise`` (3 each, standard normal):
      ``RandomDistribution.kGaussian``; feed with
      ``imu.add_random_sources(builder, magnetometer.get_noise_input_ports(), period)``.
    - ``B_S`` (3, T): measured field in the sensor frame.
    - ``B_S_true`` (3, T): the ideal field of the same instant.
    - ``bias`` (3, T): the bias inside the held sample.

    Args:
        plant: a finalized MultibodyPlant; only body indices are read, at construction.
        body: the RigidBody that carries the sensor.
        sources: list of ``MagnetSpec`` (those on ``body`` are ignored).
        config: a ``MagnetometerConfig`` (copied).
        min_distance: guard radius of the dipole model (m).
    """

    def __init__(self, plant, body, sources, config: MagnetometerConfig | None = None,
                 min_distance: float = DEFAULT_MIN_DISTANCE, field_model: str = "dipole"):
        LeafSystem.__init__(self)
        if field_model not in FIELD_MODELS:
            raise ValueError(f"Magnetometer field_model must be one of {FIELD_MODELS}, "
                             f"got {field_model!r}")
        if not plant.is_finalized():
            raise ValueError("Magnetometer needs a finalized MultibodyPlant")
        self._config = copy.deepcopy(config) if config is not None else MagnetometerConfig()
        self._period = 1.0 / self._config.sample_rate
        self._noise = self._config.channel()
        self._min_distance = float(min_distance)
        self._body_index = int(body.index())
        self._X_BS = self._config.X_BS()
        self._sources, self._excluded = resolve_sources(plant, self._body_index, sources,
                                                        field_model)
        self._body_poses_port = self.DeclareAbstractInputPort(
            "body_poses", AbstractValue.Make([RigidTransform()]))
        self._pose_ports = {name: self.DeclareVectorInputPort(f"{name}.pose", 6)
                            for name, index, *_ in self._sources if index < 0}
        gaussian = RandomDistribution.kGaussian
        self._white_port = self.DeclareVectorInputPort("white_noise", 3, gaussian)
        self._walk_port = self.DeclareVectorInputPort("bias_walk_noise", 3, gaussian)
        self._initial_port = self.DeclareVectorInputPort("initial_bias_noise", 3, gaussian)
        self._measured = self.DeclareDiscreteState(3)
        self._true = self.DeclareDiscreteState(3)
        self._bias = self.DeclareDiscreteState(3)
        self._started = self.DeclareDiscreteState(1)
        self._B_S_port = self.DeclareStateOutputPort("B_S", self._measured)
        self._B_S_true_port = self.DeclareStateOutputPort("B_S_true", self._true)
        self._bias_port = self.DeclareStateOutputPort("bias", self._bias)
        self.DeclarePeriodicDiscreteUpdateEvent(self._period, 0.0, self._update)

    @property
    def config(self) -> MagnetometerConfig:
        """The magnetometer's settings (a copy)."""
        return copy.deepcopy(self._config)

    def period(self) -> float:
        return self._period

    def channel(self) -> ChannelNoise:
        return self._noise

    def source_names(self) -> list[str]:
        return [s[0] for s in self._sources]

    def excluded_source_names(self) -> list[str]:
        """Magnets given as sources but on the sensor's own body (not measured)."""
        return list(self._excluded)

    def get_body_poses_input_port(self):
        return self._body_poses_port

    def posed_source_names(self) -> list[str]:
        """Source magnets whose pose is an input (MagnetSpec.posed)."""
        return list(self._pose_ports)

    def get_pose_input_port(self, name):
        """The input [p_WM, m_hat_W] of the posed source magnet `name`."""
        return self._pose_ports[name]

    def get_noise_input_ports(self):
        """(white_noise, bias_walk_noise, initial_bias_noise)."""
        return self._white_port, self._walk_port, self._initial_port

    def get_B_S_output_port(self):
        return self._B_S_port

    def get_B_S_true_output_port(self):
        return self._B_S_true_port

    def get_bias_output_port(self):
        return self._bias_port

    def calc_true_field(self, body_poses, posed=None) -> np.ndarray:
        """The ideal reading (T, sensor frame) for a list of body poses and, for posed
        sources, `posed`: name -> [p_WM, m_hat_W]."""
        X_WS = body_poses[self._body_index] @ self._X_BS
        return field_in_sensor_frame(X_WS, source_poses(self._sources, body_poses, posed),
                                     self._min_distance)

    def _update(self, context, discrete_state):
        truth = self.calc_true_field(
            self._body_poses_port.Eval(context),
            {name: port.Eval(context) for name, port in self._pose_ports.items()})
        if context.get_discrete_state(self._started).get_value()[0] > 0.0:
            bias = (context.get_discrete_state(self._bias).get_value()
                    + self._noise.walk_sigma * self._walk_port.Eval(context))
        else:
            bias = self._noise.first_bias(self._initial_port.Eval(context))
            discrete_state.get_mutable_vector(self._started).SetAtIndex(0, 1.0)
        measured = self._noise.sample(truth, bias, self._white_port.Eval(context))
        discrete_state.get_mutable_vector(self._measured).SetFromVector(measured)
        discrete_state.get_mutable_vector(self._true).SetFromVector(truth)
        discrete_state.get_mutable_vector(self._bias).SetFromVector(bias)


@block("capsule.magnetometer", MagnetometerConfig,
       check=lambda config, _: check_board_sensor(config, "capsule.magnetometer",
                                                  check_magnetometer_config))
def add_magnetometer(builder, parts, config: MagnetometerConfig):
    """`capsule.magnetometer`: the EPM's field at the sensor (the model of the magnet force
    block, parts.field_model), with its noise sources; exports capsule.magnetometer.B_S and
    B_S_true."""
    magnetometer = builder.AddNamedSystem("capsule.magnetometer", Magnetometer(
        parts.plant, parts.capsule_body, parts.magnets, config,
        field_model=parts.field_model))
    builder.Connect(parts.plant.get_body_poses_output_port(),
                    magnetometer.get_body_poses_input_port())
    for name in magnetometer.posed_source_names():   # the kinematic stage's EPM
        builder.Connect(parts.output("epm.pose"), magnetometer.get_pose_input_port(name))
    add_random_sources(builder, magnetometer.get_noise_input_ports(), magnetometer.period())
    parts.export(magnetometer.get_B_S_output_port(), "capsule.magnetometer.B_S")
    parts.export(magnetometer.get_B_S_true_output_port(), "capsule.magnetometer.B_S_true")
    return magnetometer
