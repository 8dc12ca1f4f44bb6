"""MEMS IMU: Drake's ideal accelerometer and gyroscope followed by a sampled noise model.

    plant --> Accelerometer (specific force at S, in S) ---+
                                                           +--> ImuNoise --> accel, gyro
    plant --> Gyroscope     (angular velocity, in S)  -----+                 (+ truth, biases)
                            RandomSource x3 (Gaussian) ----+

The error model of each axis of each sensor (IEEE Std 952-1997 Annex C, IEEE Std 1293-2018;
El-Sheimy, Hou and Niu, IEEE TIM 2008) is

    y_k = Q(sat(x_k + b_k + s_w w_k)),      b_k = b_{k-1} + s_b v_k,      b_0 = b_init + s_0 u

with x the ideal value, w, v, u independent standard normal draws, sat a clip to the full-scale
range and Q an optional rounding to the ADC step. The parameters are what datasheets give:

- **White-noise density** ``d`` (units/sqrt(Hz)), as in the MPU-6050 Product Specification
  (InvenSense PS-MPU-6000A-00 rev. 3.4: accelerometer 400 ug/sqrt(Hz), gyroscope
  0.005 deg/s/sqrt(Hz)). InvenSense's density is one-sided (their total RMS noise is the
  density times sqrt(bandwidth)), so a sample band-limited to Nyquist has
  ``s_w = d sqrt(f_s / 2)``. Its Allan deviation is ``d / sqrt(2 tau)``: IEEE 952's white-noise
  coefficient (two-sided density) is ``N = d / sqrt(2)``. Keep that factor in mind when
  comparing a datasheet density with an Allan plot.
- **Bias random walk** ``K`` (units/s/sqrt(s) = units/s * 1/sqrt(Hz)): the bias is a Wiener
  process whose standard deviation grows as ``K sqrt(t)``, ``s_b = K sqrt(1 / f_s)``; its Allan
  deviation rises as ``K sqrt(tau / 3)`` (IEEE 952 "rate random walk"). Datasheets and Allan
  studies quote a *bias instability* ``B`` (the flicker floor, ADEV ``0.664 B``) instead;
  ``bias_random_walk_from_instability`` picks the ``K`` whose Allan curve, together with the
  white noise, bottoms out at that floor (``min ADEV = sqrt(2 N K / sqrt(3))`` at
  ``tau = sqrt(3) N / K``). A random walk has no flat floor and grows without bound over hours,
  which is the drift the seed asks for; over a minutes-long run it is the conservative choice.
- **Initial bias**: a given offset plus a per-run Gaussian draw (turn-on bias after calibration).
- **Range** and **resolution**: saturation at the full-scale range and a 16-bit ADC step.
"""


import copy
import dataclasses
import math

import numpy as np
from pydrake.common import RandomDistribution
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import RandomSource
from pydrake.systems.sensors import Accelerometer, Gyroscope

from capsule_drake.blocks import block
from capsule_drake.capsule.model import check_board_sensor
from capsule_drake.schema import MAX_RATE, need_range

STANDARD_GRAVITY = 9.80665  # m/s^2 (CGPM 1901), the "g" of datasheets
DEG = math.pi / 180.0


def bias_random_walk_from_instability(bias_instability: float, noise_density: float) -> float:
    """The bias random walk ``K`` (units/s/sqrt(s)) that makes the Allan deviation of white
    noise of one-sided density ``noise_density`` plus the walk reach its minimum at the
    flicker floor ``0.664 * bias_instability`` of IEEE 952 (same units as the signal).

    ADEV^2 = N^2 / tau + K^2 tau / 3 (N = density / sqrt(2)) has its minimum
    2 N K / sqrt(3) at tau = sqrt(3) N / K; setting it to (0.664 B)^2 gives K.
    """
    white = noise_density / math.sqrt(2.0)
    return math.sqrt(3.0) * (0.664 * bias_instability) ** 2 / (2.0 * white)


@dataclasses.dataclass
class ImuConfig:
    """A MEMS IMU on the capsule; YAML-loadable, defaults are an MPU-6050.

    SI units throughout (m/s^2, rad/s, s, Hz). Sources: MPU-6050 Product Specification
    (InvenSense PS-MPU-6000A-00 rev. 3.4) = DS; docs/sources.md section 2; U = engineering
    assumption.
    """

    # Output data rate (Hz). The MPU-6050 samples at up to 1 kHz (accel) / 8 kHz (gyro), DS;
    # 100 Hz keeps the Python cost per simulated second small. U.
    sample_rate: float = 100.0
    # Sensor frame S in the capsule body frame: origin (m) and roll-pitch-yaw (deg). The
    # board sits on the capsule axis beside the magnet; the centre is an assumption. U.
    p_BS: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])
    rpy_BS_deg: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])

    # Accelerometer white-noise density, one-sided (m/s^2/sqrt(Hz)): 400 ug/sqrt(Hz), DS.
    accel_noise_density: float = 400e-6 * STANDARD_GRAVITY
    # Accelerometer bias random walk (m/s^2/sqrt(s)): from an assumed bias instability of
    # 0.1 mg (U) with bias_random_walk_from_instability(0.1e-3 g, 400 ug/sqrt(Hz)).
    accel_bias_random_walk: float = 1.3239e-4
    # Accelerometer turn-on bias: fixed part per axis (m/s^2) and the standard deviation of
    # the per-run draw (m/s^2). The DS allows +-50 mg (x, y) / +-80 mg (z) uncalibrated; 10 mg
    # is the residual after an at-rest calibration. U.
    accel_initial_bias: list[float] = dataclasses.field(default_factory=lambda: [0.0] * 3)
    accel_initial_bias_sigma: float = 10e-3 * STANDARD_GRAVITY
    # Accelerometer full-scale range (m/s^2): +-2 g, the most sensitive setting, DS.
    accel_range: float = 2.0 * STANDARD_GRAVITY

    # Gyroscope white-noise density, one-sided (rad/s/sqrt(Hz)): 0.005 deg/s/sqrt(Hz), DS.
    gyro_noise_density: float = 0.005 * DEG
    # Gyroscope bias random walk (rad/s/sqrt(s)): from the bias instability 4 deg/h measured
    # on one MPU-6050 (docs/sources.md section 2; 5-30 deg/h typical) with
    # bias_random_walk_from_instability(4 deg/h, 0.005 deg/s/sqrt(Hz)); Allan minimum at 46 s.
    gyro_bias_random_walk: float = 2.3270e-6
    # Gyroscope turn-on bias: fixed part per axis (rad/s) and the per-run standard deviation
    # (rad/s). The DS allows +-20 deg/s uncalibrated; 0.2 deg/s remains after an at-rest
    # calibration. U.
    gyro_initial_bias: list[float] = dataclasses.field(default_factory=lambda: [0.0] * 3)
    gyro_initial_bias_sigma: float = 0.2 * DEG
    # Gyroscope full-scale range (rad/s): +-250 deg/s, the most sensitive setting, DS.
    gyro_range: float = 250.0 * DEG

    # ADC resolution (bits) over the full-scale range (16, DS); 0 = no quantisation.
    resolution_bits: int = 16

    def X_BS(self) -> RigidTransform:
        """The sensor frame's pose in the body frame."""
        return RigidTransform(RollPitchYaw(np.deg2rad(self.rpy_BS_deg)), np.array(self.p_BS))


def check_sensor_frame(config) -> None:
    """Raises ValueError unless the sensor frame (p_BS, rpy_BS_deg) is 3 numbers each
    (where in the capsule the sensor sits is the scenario's check: it knows the capsule)."""
    for name in ("p_BS", "rpy_BS_deg"):
        value = getattr(config, name)
        if len(value) != 3:
            raise ValueError(f"{name} must have 3 entries, got {value}")
    need_range(config.rpy_BS_deg, "rpy_BS_deg", "[-360, 360]", "deg")


def check_imu_config(config: ImuConfig) -> None:
    """Raises ValueError naming the first impossible field (relative to the IMU)."""
    need_range(config.sample_rate, "sample_rate", f"(0, {MAX_RATE:g}]", "Hz",
               "the MPU-6050 samples at up to 8 kHz")
    check_sensor_frame(config)
    for name in ("accel_initial_bias", "gyro_initial_bias"):
        value = getattr(config, name)
        if len(value) != 3:
            raise ValueError(f"{name} must have 3 entries, got {value}")
    for name in ("accel_noise_density", "accel_bias_random_walk", "accel_initial_bias_sigma",
                 "gyro_noise_density", "gyro_bias_random_walk", "gyro_initial_bias_sigma"):
        need_range(getattr(config, name), name, ">= 0", "", "a standard deviation")
    need_range(config.accel_range, "accel_range", "> 0", "m/s^2")
    need_range(config.gyro_range, "gyro_range", "> 0", "rad/s")
    check_resolution_bits(config.resolution_bits)


def check_resolution_bits(bits: int) -> None:
    """An ADC's bits: 0 (no quantisation) to 32 (ADCs have 8-24; the step is then far below
    any noise, and 2^bits stays a modest float)."""
    need_range(bits, "resolution_bits", "[0, 32]", "", "0: no quantisation")


@dataclasses.dataclass(frozen=True)
class ChannelNoise:
    """Per-sample parameters of one 3-axis channel (see the module docstring)."""

    white_sigma: float  # s_w: white noise per sample
    walk_sigma: float  # s_b: bias increment per sample
    initial_bias: tuple  # b_init, 3 floats
    initial_bias_sigma: float  # s_0
    full_scale: float  # saturation (inf = none)
    step: float  # quantisation step (0 = none)

    @staticmethod
    def from_datasheet(noise_density, bias_random_walk, sample_rate, initial_bias=(0, 0, 0),
                       initial_bias_sigma=0.0, full_scale=math.inf, resolution_bits=0):
        """Discrete parameters from the continuous ones (density one-sided, see module)."""
        if sample_rate <= 0:
            raise ValueError(f"sample_rate must be positive, got {sample_rate}")
        if min(noise_density, bias_random_walk, initial_bias_sigma) < 0 or full_scale <= 0:
            raise ValueError("noise parameters must be >= 0 and the range > 0")
        step = 0.0
        if resolution_bits and math.isfinite(full_scale):
            step = 2.0 * full_scale / 2.0 ** resolution_bits
        return ChannelNoise(
            white_sigma=noise_density * math.sqrt(sample_rate / 2.0),
            walk_sigma=bias_random_walk * math.sqrt(1.0 / sample_rate),
            initial_bias=tuple(float(x) for x in np.reshape(initial_bias, 3)),
            initial_bias_sigma=float(initial_bias_sigma),
            full_scale=float(full_scale),
            step=step)

    def first_bias(self, draw):
        """b_0 from a standard normal 3-vector ``draw``."""
        return np.asarray(self.initial_bias) + self.initial_bias_sigma * np.asarray(draw)

    def sample(self, truth, bias, white_draw):
        """One measurement (or many: broadcasts over leading axes)."""
        y = np.asarray(truth) + bias + self.white_sigma * np.asarray(white_draw)
        if self.step > 0.0:
            y = np.round(y / self.step) * self.step
        return np.clip(y, -self.full_scale, self.full_scale)

    def record(self, truth, white_draws, walk_draws, initial_draw):
        """A whole recording at once, the same arithmetic as ``ImuNoise``'s update.

        Args:
            truth: ideal values, (n, 3) or (3,) (held constant).
            white_draws, walk_draws: standard normal draws, (n, 3); ``walk_draws[0]`` is unused
                (the first sample carries the initial bias).
            initial_draw: standard normal 3-vector for the turn-on bias.

        Returns:
            (measured, bias), each (n, 3): the samples and the bias inside each.
        """
        walk = self.walk_sigma * np.asarray(walk_draws, float)
        walk[0] = 0.0
        bias = self.first_bias(initial_draw) + np.cumsum(walk, axis=0)
        return self.sample(truth, bias, white_draws), bias


def imu_channels(config: ImuConfig) -> tuple[ChannelNoise, ChannelNoise]:
    """(accelerometer, gyroscope) per-sample noise parameters of ``config``."""
    accel = ChannelNoise.from_datasheet(
        config.accel_noise_density, config.accel_bias_random_walk, config.sample_rate,
        config.accel_initial_bias, config.accel_initial_bias_sigma, config.accel_range,
        config.resolution_bits)
    gyro = ChannelNoise.from_datasheet(
        config.gyro_noise_density, config.gyro_bias_random_walk, config.sample_rate,
        config.gyro_initial_bias, config.gyro_initial_bias_sigma, config.gyro_range,
        config.resolution_bits)
    return accel, gyro


def add_random_sources(builder, ports, period: float):
    """Feeds each of ``ports`` (Gaussian random input ports of one system) from its own
    standard normal ``RandomSource`` sampled every ``period``. Unlike ``AddRandomInputs`` it
    leaves other systems' random ports alone. Seed with
    ``diagram.SetRandomContext(context, RandomGenerator(seed))``."""
    for port in ports:
        name = f"{port.get_system().get_name()}.{port.get_name()}_source"
        source = builder.AddNamedSystem(
            name, RandomSource(RandomDistribution.kGaussian, port.size(), period))
        builder.Connect(source.get_output_port(), port)


class ImuNoise(LeafSystem):
    """Samples ideal accelerometer and gyroscope values and adds a MEMS error model.

    Every ``1 / config.sample_rate`` s (first at t = 0) the update draws one sample per axis
    (module docstring: white noise, bias random walk, turn-on bias on the first update,
    saturation, quantisation) and holds it until the next: outputs are discrete state, so
    this system never makes an algebraic loop. Before the first update all outputs are zero.

    .. pydrake_system::

        name: ImuNoise
        input_ports:
        - accel_true
        - gyro_true
        - white_noise (random)
        - bias_walk_noise (random)
        - initial_bias_noise (random)
        output_ports:
        - accel
        - gyro
        - accel_true
        - gyro_true
        - accel_bias
        - gyro_bias

    - ``accel_true`` (3, m/s^2): specific force (proper acceleration, "up" at rest) of the
      sensor point, in the sensor frame S: Drake's ``Accelerometer`` with the plant's gravity.
    - ``gyro_true`` (3, rad/s): angular velocity of S in world, in S: Drake's ``Gyroscope``.
    - ``white_noise``, ``bias_walk_noise``, ``initial_bias_noise`` (6 each, standard normal,
      accelerometer xyz then gyroscope xyz): ``RandomDistribution.kGaussian`` ports, fed by
      ``add_random_sources`` at the sample rate (or fixed by a test).
    - ``accel`` (3, m/s^2), ``gyro`` (3, rad/s): the measured samples.
    - ``accel_true``, ``gyro_true``: the ideal values of the same instant.
    - ``accel_bias`` (3, m/s^2), ``gyro_bias`` (3, rad/s): the bias inside the held sample.

    Args:
        config: an ``ImuConfig`` (copied).
    """

    def __init__(self, config: ImuConfig):
        LeafSystem.__init__(self)
        self._config = copy.deepcopy(config)
        self._period = 1.0 / config.sample_rate
        self._accel_noise, self._gyro_noise = imu_channels(config)
        gaussian = RandomDistribution.kGaussian
        self._accel_true_port = self.DeclareVectorInputPort("accel_true", 3)
        self._gyro_true_port = self.DeclareVectorInputPort("gyro_true", 3)
        self._white_port = self.DeclareVectorInputPort("white_noise", 6, gaussian)
        self._walk_port = self.DeclareVectorInputPort("bias_walk_noise", 6, gaussian)
        self._initial_port = self.DeclareVectorInputPort("initial_bias_noise", 6, gaussian)
        names = ("accel", "gyro", "accel_true", "gyro_true", "accel_bias", "gyro_bias")
        self._groups = {n: self.DeclareDiscreteState(3) for n in names}
        self._started = self.DeclareDiscreteState(1)
        self._ports = {n: self.DeclareStateOutputPort(n, g) for n, g in self._groups.items()}
        self.DeclarePeriodicDiscreteUpdateEvent(self._period, 0.0, self._update)

    def config(self) -> ImuConfig:
        return copy.deepcopy(self._config)

    def period(self) -> float:
        return self._period

    def channels(self) -> tuple[ChannelNoise, ChannelNoise]:
        """(accelerometer, gyroscope) ``ChannelNoise``: the same model as a pure function."""
        return self._accel_noise, self._gyro_noise

    def get_accel_true_input_port(self):
        return self._accel_true_port

    def get_gyro_true_input_port(self):
        return self._gyro_true_port

    def get_noise_input_ports(self):
        """(white_noise, bias_walk_noise, initial_bias_noise)."""
        return self._white_port, self._walk_port, self._initial_port

    def get_output_port_by_signal(self, name: str):
        """``accel``, ``gyro``, ``accel_true``, ``gyro_true``, ``accel_bias``, ``gyro_bias``."""
        return self._ports[name]

    def _update(self, context, discrete_state):
        accel_true = self._accel_true_port.Eval(context)
        gyro_true = self._gyro_true_port.Eval(context)
        white = self._white_port.Eval(context)
        groups = self._groups
        started = context.get_discrete_state(self._started).get_value()[0] > 0.0
        if started:
            walk = self._walk_port.Eval(context)
            accel_bias = (context.get_discrete_state(groups["accel_bias"]).get_value()
                          + self._accel_noise.walk_sigma * walk[:3])
            gyro_bias = (context.get_discrete_state(groups["gyro_bias"]).get_value()
                         + self._gyro_noise.walk_sigma * walk[3:])
        else:
            initial = self._initial_port.Eval(context)
            accel_bias = self._accel_noise.first_bias(initial[:3])
            gyro_bias = self._gyro_noise.first_bias(initial[3:])
            discrete_state.get_mutable_vector(self._started).SetAtIndex(0, 1.0)
        values = {
            "accel": self._accel_noise.sample(accel_true, accel_bias, white[:3]),
            "gyro": self._gyro_noise.sample(gyro_true, gyro_bias, white[3:]),
            "accel_true": accel_true,
            "gyro_true": gyro_true,
            "accel_bias": accel_bias,
            "gyro_bias": gyro_bias,
        }
        for name, value in values.items():
            discrete_state.get_mutable_vector(groups[name]).SetFromVector(value)


class Imu(Diagram):
    """A MEMS IMU rigidly attached to a plant body: Drake's ideal ``Accelerometer`` and
    ``Gyroscope`` at the sensor frame S (``config.X_BS()``), an ``ImuNoise``, and the
    Gaussian ``RandomSource``s that feed it, sampled at the IMU rate.

    .. pydrake_system::

        name: Imu
        input_ports:
        - body_poses
        - body_spatial_velocities
        - body_spatial_accelerations
        output_ports:
        - accel
        - gyro
        - accel_true
        - gyro_true
        - accel_bias
        - gyro_bias

    Inputs come from the plant's ``get_body_poses_output_port()``,
    ``get_body_spatial_velocities_output_port()`` and
    ``get_body_spatial_accelerations_output_port()``; outputs are ``ImuNoise``'s. The
    accelerometer uses the plant's gravity vector, so a capsule at rest reads +g along the
    world's up direction, expressed in S. Seed the noise with
    ``diagram.SetRandomContext(context, RandomGenerator(seed))``.

    Args:
        plant: the MultibodyPlant (finalized) that ``body`` belongs to.
        body: the RigidBody carrying the IMU.
        config: an ``ImuConfig``.
    """

    def __init__(self, plant, body, config: ImuConfig):
        Diagram.__init__(self)
        builder = DiagramBuilder()
        X_BS = config.X_BS()
        gravity = np.asarray(plant.gravity_field().gravity_vector())
        accelerometer = builder.AddNamedSystem(
            "accelerometer", Accelerometer(body, X_BS, gravity))
        gyroscope = builder.AddNamedSystem("gyroscope", Gyroscope(body, X_BS))
        noise = builder.AddNamedSystem("noise", ImuNoise(config))
        builder.ExportInput(accelerometer.get_body_poses_input_port(), "body_poses")
        builder.ConnectInput("body_poses", gyroscope.get_body_poses_input_port())
        builder.ExportInput(accelerometer.get_body_velocities_input_port(),
                            "body_spatial_velocities")
        builder.ConnectInput("body_spatial_velocities",
                             gyroscope.get_body_velocities_input_port())
        builder.ExportInput(accelerometer.get_body_accelerations_input_port(),
                            "body_spatial_accelerations")
        builder.Connect(accelerometer.get_measurement_output_port(),
                        noise.get_accel_true_input_port())
        builder.Connect(gyroscope.get_measurement_output_port(),
                        noise.get_gyro_true_input_port())
        add_random_sources(builder, noise.get_noise_input_ports(), noise.period())
        for name in ("accel", "gyro", "accel_true", "gyro_true", "accel_bias", "gyro_bias"):
            builder.ExportOutput(noise.get_output_port_by_signal(name), name)
        builder.BuildInto(self)
        self._noise = noise
        self.config = copy.deepcopy(config)

    def noise_system(self) -> ImuNoise:
        return self._noise

    def connect_to_plant(self, builder, plant) -> None:
        """Connects the plant's body poses, velocities and accelerations to this IMU."""
        builder.Connect(plant.get_body_poses_output_port(), self.GetInputPort("body_poses"))
        builder.Connect(plant.get_body_spatial_velocities_output_port(),
                        self.GetInputPort("body_spatial_velocities"))
        builder.Connect(plant.get_body_spatial_accelerations_output_port(),
                        self.GetInputPort("body_spatial_accelerations"))



@block("capsule.imu", ImuConfig,
       check=lambda config, _: check_board_sensor(config, "capsule.imu", check_imu_config))
def add_imu(builder, parts, config: ImuConfig):
    """`capsule.imu` on the capsule body, fed by the plant; exports capsule.imu.<signal> and
    shares its config (`capsule.imu.config`: its rate and its frame in the capsule)."""
    imu = builder.AddNamedSystem("capsule.imu", Imu(parts.plant, parts.capsule_body, config))
    imu.connect_to_plant(builder, parts.plant)
    parts.export_outputs(imu, "capsule.imu")
    parts.share("capsule.imu.config", imu.config)
    return imu
