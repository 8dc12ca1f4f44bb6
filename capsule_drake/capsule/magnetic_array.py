"""The capsule's localisation sensors: three-axis Hall sensors around the internal magnet.

A capsule that localises itself in the field of the external magnet (EPM) carries several
three-axis Hall sensors around its internal magnet (IPM) (Di Natali et al., IEEE T-RO 2016;
Taddese et al., IJRR 2018). Each sensor i reads, per axis, in its frame S_i (the capsule's
axes, at p_BSi):

    raw_i = clip(Q(G_i (B_ipm,i (1 + d) + B_epm,i) + o_i + do_i + n_i), +-range)

- B_ipm,i: the IPM's own field at the sensor (the exact field of its cylinder,
  ``magnetics.cylinder_field``): 60-150 mT at 11-15 mm from an 11 mm N52 magnet, ten times
  the EPM's 5-25 mT at the capsule. It is fixed in the capsule frame, so it is measured
  once (calibration) and subtracted; d is its change since then (NdFeB loses 0.12 % of its
  remanence per kelvin: a capsule calibrated at room temperature and used at body
  temperature, after compensating with its temperature sensor, keeps a residual).
- B_epm,i: the EPM's field (the station's field model: with "finite", its cylinder's exact
  field), what the localiser wants.
- G_i = I + diag(gain errors) + cross-axis terms, o_i the offset, do_i its drift since the
  calibration: per sensor, drawn per run.
- n_i: white noise; Q: the ADC step; clip: the sensor's range, applied to the SUM of the
  self-field and the EPM's: a sensor near the IPM's pole saturates first, and its axis then
  reads the rail whatever the EPM does.

Calibration (the first sample, as a bench calibration before the capsule is swallowed):
the reading with the EPM away, averaged over ``calibration_samples``,

    c_i = G_i B_ipm,i + o_i + mean noise,

is what each sensor subtracts from then on: B_i = raw_i - c_i = G_i (B_epm,i + d B_ipm,i)
+ do_i + noise. The estimator reads B_i and, per sensor, whether any axis is at its rail
(`saturated`): such a reading is not B_epm plus noise and is excluded, not trusted.

Defaults: a TMAG5273A2-class sensor (Texas Instruments TMAG5273 datasheet, SLYS045, +-266 mT
range) at four places around the IPM, two ahead of it and two behind (the config's
defaults); U = engineering assumption, DS = datasheet.
"""

import copy
import dataclasses

import numpy as np
from pydrake.common import RandomDistribution
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from capsule_drake.capsule.imu import add_random_sources, check_resolution_bits
from capsule_drake.capsule.magnetometer import resolve_sources, source_poses
from capsule_drake.physics.magnet_force import FIELD_MODELS
from capsule_drake.physics.magnetics import (DEFAULT_MIN_DISTANCE, cylinder_field,
                                             dipole_field)
from capsule_drake.blocks import block, checked
from capsule_drake.capsule.model import check_inside_capsule
from capsule_drake.schema import MAX_RATE, need_range

# Most sensors an array may have (3 numbers of state per axis each).
MAX_SENSORS = 16


@dataclasses.dataclass
class MagneticArrayConfig:
    """Three-axis Hall sensors around the capsule's magnet; YAML-loadable, SI units (T)."""

    # Output data rate (Hz): the estimator's update rate. U (the TMAG5273 converts at up to
    # 20 kSPS per axis, DS; 100 Hz with 32x averaging is well inside that).
    sample_rate: float = 100.0
    # Sensor positions in the capsule body (m), one [x, y, z] each; the sensors' axes are
    # the capsule's. The IPM's centre is 3 mm behind the body origin, its faces at z = -8.6
    # and +2.6 mm: two sensors ahead of it on the camera's board (z = 12 mm, 5 mm off the
    # axis, either side), two behind it in the rear dome (z = -14.5 mm, 2.8 mm off the
    # axis), so that the array spans the capsule's length (the baseline that separates a
    # sideways shift from a turn, the estimate's weakest direction). The self-field there
    # is 64 mT ahead and 150 mT behind. U.
    positions: list[list[float]] = dataclasses.field(default_factory=lambda: [
        [0.0035, 0.0035, 0.012], [-0.0035, -0.0035, 0.012],
        [0.002, -0.002, -0.0145], [-0.002, 0.002, -0.0145]])
    # Full-scale range per axis (T): +-266 mT, the TMAG5273A2's wide setting (DS).
    range: float = 0.266
    # ADC resolution (bits) over the range: 16-bit results with averaging (DS: 12-bit
    # conversions, 16-bit registers); 0 = no quantisation.
    resolution_bits: int = 16
    # White noise per sample and axis (T, 1 sigma). The datasheet's RMS noise with 32x
    # averaging (0.4 kSPS for three axes, DS) is 24 uT (x, y) and 15 uT (z) at 25 C, as
    # specified for the family; taken as 50 uT on every axis for the wide range. U.
    noise_rms: float = 50e-6
    # Offset per axis, per run (T, 1 sigma): +-300 uT typical (DS, the +-40/80 mT variant);
    # removed by the calibration with the self-field.
    offset_sigma: float = 300e-6
    # What of the offset the calibration cannot remove (T, 1 sigma per axis, per run): its
    # drift, 3 uT/K typical (DS, as above), over the capsule's temperature change since
    # the calibration. Calibrated warm (at 37 C, as it will be used), the residual is the
    # body's +-1.5 K: 5 uT. U. Calibrated on the bench at 25 C, it would be 36 uT, and it
    # then dominates the localisation error (docs/models/localisation.md, "What limits it").
    offset_drift_sigma: float = 5e-6
    # Gain error per axis after calibration (fraction, 1 sigma): the sensors' sensitivity
    # error (+-5 % typical, DS) and axis mismatch (+-0.5-1 %, DS), calibrated with each
    # sensor's 3 x 3 matrix in a known uniform field (a Helmholtz coil) to this residual.
    # U. The self-field's part is calibrated away with the offset; the EPM field's is not.
    # The localisation's worst runs double with 1 % (docs/models/localisation.md, "What
    # limits it").
    gain_sigma: float = 0.003
    # Cross-axis sensitivity after the same calibration (fraction of each other axis,
    # 1 sigma per term; the datasheet calls it insignificant for this monolithic sensor,
    # the board's placement adds to it). U.
    cross_axis_sigma: float = 0.002
    # Change of the IPM's field between calibration and use (fraction, 1 sigma per run):
    # NdFeB's remanence falls 0.12 %/K; over the +-1.5 K above. U.
    self_field_drift_sigma: float = 0.0018
    # Samples averaged by the calibration (its noise is noise_rms / sqrt(this)).
    calibration_samples: int = 1000
    # An axis within this share of the range of its rail counts as saturated.
    saturation_margin: float = 0.002

    def X_BS(self, i: int) -> RigidTransform:
        """Sensor i's frame in the body frame (the capsule's axes)."""
        return RigidTransform(np.asarray(self.positions[i], dtype=float))


def check_magnetic_array_config(config: MagneticArrayConfig) -> None:
    """Raises ValueError naming the first impossible field (relative to the array)."""
    need_range(config.sample_rate, "sample_rate", f"(0, {MAX_RATE:g}]", "Hz")
    if not 1 <= len(config.positions) <= MAX_SENSORS:
        raise ValueError(f"positions must list 1 to {MAX_SENSORS} sensors, got "
                         f"{len(config.positions)}")
    for i, p in enumerate(config.positions):
        if len(p) != 3:
            raise ValueError(f"positions[{i}] must have 3 entries, got {p}")
        need_range(list(p), f"positions[{i}]", "[-0.1, 0.1]", "m", "inside a capsule")
    need_range(config.range, "range", "(0, 10]", "T", "Hall sensors read up to a few tesla")
    check_resolution_bits(config.resolution_bits)
    need_range(config.noise_rms, "noise_rms", "[0, 1]", "T")
    need_range(config.offset_sigma, "offset_sigma", "[0, 1]", "T")
    need_range(config.offset_drift_sigma, "offset_drift_sigma", "[0, 1]", "T")
    for name in ("gain_sigma", "cross_axis_sigma", "self_field_drift_sigma"):
        need_range(getattr(config, name), name, "[0, 0.5]", "", "a fraction")
    need_range(config.calibration_samples, "calibration_samples", "[1, 1000000]")
    need_range(config.saturation_margin, "saturation_margin", "[0, 0.5]", "",
               "a share of the range")


def self_field(ipm, X_BM: RigidTransform, positions) -> np.ndarray:
    """The IPM's field (T) at each of `positions` (n x 3, body frame), in the body frame:
    a cylinder's exact field, a sphere's dipole field (exact outside it), a cuboid's dipole
    field (an approximation near it)."""
    positions = np.atleast_2d(np.asarray(positions, dtype=float))
    m_B = X_BM.rotation().matrix()[:, 2] * ipm.moment()
    offsets = positions - X_BM.translation()
    if ipm.shape == "cylinder":
        return cylinder_field(m_B, offsets, *ipm.dimensions)
    return np.array([dipole_field(m_B, r) for r in offsets])


class SensorErrors:
    """One run's draw of the array's errors: gains with cross-axis terms, offsets, the
    self-field's drift since calibration, the calibration's noise and the offsets' drift
    since (`draw`: standard normal numbers, `size(n)` of them)."""

    @staticmethod
    def size(n: int) -> int:
        return 9 * n + 3 * n + 1 + 3 * n + 3 * n

    def __init__(self, config: MagneticArrayConfig, draw):
        n = len(config.positions)
        draw = np.asarray(draw, dtype=float)
        off_diagonal = ~np.eye(3, dtype=bool)
        G = np.empty((n, 3, 3))
        raw = draw[:9 * n].reshape(n, 3, 3)
        for i in range(n):
            G[i] = np.eye(3) + config.gain_sigma * np.diag(np.diag(raw[i]))
            G[i][off_diagonal] = config.cross_axis_sigma * raw[i][off_diagonal]
        self.G = G
        self.offset = config.offset_sigma * draw[9 * n:12 * n].reshape(n, 3)
        self.drift = config.self_field_drift_sigma * draw[12 * n]
        self.calibration_noise = (config.noise_rms / np.sqrt(config.calibration_samples)
                                  * draw[12 * n + 1:15 * n + 1].reshape(n, 3))
        self.offset_drift = config.offset_drift_sigma * draw[15 * n + 1:18 * n + 1].reshape(n, 3)


class MagneticSensorArray(LeafSystem):
    """Three-axis Hall sensors on the capsule around its magnet (module docstring).

    .. pydrake_system::

        name: MagneticSensorArray
        input_ports:
        - body_poses
        - white_noise (random)
        - error_draw (random)
        output_ports:
        - B
        - saturated
        - B_raw
        - B_true
        - calibration

    - ``body_poses``: the plant's body poses; posed source magnets (the kinematic stage's
      EPM) add an input ``<name>.pose`` ([p_WM, m_hat_W]).
    - ``B`` (3n, T): each sensor's calibrated reading (raw minus calibration), sensor after
      sensor, in the sensors' frames (the capsule's axes).
    - ``saturated`` (n): 1 where an axis of the sensor's raw reading is at its rail.
    - ``B_raw`` (3n, T): what the sensors put out, self-field included.
    - ``B_true`` (3n, T): the EPM's ideal field at each sensor, the truth ``B`` estimates.
    - ``calibration`` (3n, T): what the calibration subtracts (the self-field as measured).

    Args:
        plant: a finalized MultibodyPlant; body indices are read at construction.
        body: the capsule's body.
        sources: MagnetSpec list; those on ``body`` (the IPM) are the self-field, given by
            ``ipm`` and ``X_BM`` instead.
        ipm: the IPM's MagnetGeometry; X_BM: its pose in the body (axis +z).
        config: MagneticArrayConfig (copied).
        field_model: the EPM's field, "dipole" or "finite" (the station's).
    """

    def __init__(self, plant, body, sources, ipm, X_BM, config: MagneticArrayConfig | None = None,
                 field_model: str = "dipole", min_distance: float = DEFAULT_MIN_DISTANCE):
        LeafSystem.__init__(self)
        if field_model not in FIELD_MODELS:
            raise ValueError(f"MagneticSensorArray field_model must be one of {FIELD_MODELS}, "
                             f"got {field_model!r}")
        self._config = copy.deepcopy(config) if config is not None else MagneticArrayConfig()
        check_magnetic_array_config(self._config)
        c = self._config
        self._n = n = len(c.positions)
        self._period = 1.0 / c.sample_rate
        self._positions = np.asarray(c.positions, dtype=float)
        self._body_index = int(body.index())
        self._sources, _ = resolve_sources(plant, self._body_index, sources, field_model)
        self._min_distance = float(min_distance)
        self._self_field = self_field(ipm, X_BM, self._positions)
        self._step = 2.0 * c.range / 2.0 ** c.resolution_bits if c.resolution_bits else 0.0
        self._rail = c.range * (1.0 - c.saturation_margin)
        self._errors_cache = (None, None, None)   # (draw bytes, SensorErrors, calibration)
        self._body_poses_port = self.DeclareAbstractInputPort(
            "body_poses", AbstractValue.Make([RigidTransform()]))
        self._pose_ports = {name: self.DeclareVectorInputPort(f"{name}.pose", 6)
                            for name, index, *_ in self._sources if index < 0}
        gaussian = RandomDistribution.kGaussian
        self._white_port = self.DeclareVectorInputPort("white_noise", 3 * n, gaussian)
        self._draw_port = self.DeclareVectorInputPort("error_draw", SensorErrors.size(n),
                                                      gaussian)
        self._B = self.DeclareDiscreteState(3 * n)
        self._saturated = self.DeclareDiscreteState(n)
        self._raw = self.DeclareDiscreteState(3 * n)
        self._true = self.DeclareDiscreteState(3 * n)
        self._calibration = self.DeclareDiscreteState(3 * n)
        # The run's error draw (kept: drawn once, at the first sample), and whether it was.
        self._draw = self.DeclareDiscreteState(SensorErrors.size(n) + 1)
        for name, state in (("B", self._B), ("saturated", self._saturated),
                            ("B_raw", self._raw), ("B_true", self._true),
                            ("calibration", self._calibration)):
            self.DeclareStateOutputPort(name, state)
        self.DeclarePeriodicDiscreteUpdateEvent(self._period, 0.0, self._update)

    @property
    def config(self) -> MagneticArrayConfig:
        """The array's settings (a copy)."""
        return copy.deepcopy(self._config)

    def period(self) -> float:
        return self._period

    def num_sensors(self) -> int:
        return self._n

    def self_field(self) -> np.ndarray:
        """The IPM's field at each sensor (n x 3, T, capsule frame), without errors."""
        return self._self_field.copy()

    def posed_source_names(self) -> list[str]:
        return list(self._pose_ports)

    def get_pose_input_port(self, name):
        return self._pose_ports[name]

    def get_noise_input_ports(self):
        return self._white_port, self._draw_port

    def external_field(self, body_poses, posed=None) -> np.ndarray:
        """The EPM's (every source's) ideal field at each sensor (n x 3, T, capsule frame)."""
        X_WB = body_poses[self._body_index]
        p_W = self._positions @ X_WB.rotation().matrix().T + X_WB.translation()
        B_W = np.zeros_like(p_W)
        for p_WM, m_W, cylinder in source_poses(self._sources, body_poses, posed):
            if cylinder:
                B_W += cylinder_field(m_W, p_W - p_WM, *cylinder)
            else:
                B_W += np.array([dipole_field(m_W, p - p_WM, self._min_distance) for p in p_W])
        return B_W @ X_WB.rotation().matrix()

    def measure(self, B_epm, errors: SensorErrors, white) -> np.ndarray:
        """The raw readings (n x 3, T) for the EPM's field B_epm (n x 3) and one white-noise
        draw (n x 3, standard normal)."""
        total = self._self_field * (1.0 + errors.drift) + B_epm
        y = np.einsum("nij,nj->ni", errors.G, total) + errors.offset + errors.offset_drift
        y = y + self._config.noise_rms * np.asarray(white).reshape(self._n, 3)
        if self._step > 0.0:
            y = np.round(y / self._step) * self._step
        return np.clip(y, -self._config.range, self._config.range)

    def calibration(self, errors: SensorErrors) -> np.ndarray:
        """What the calibration measured (n x 3, T): the self-field through the sensors'
        errors, with the EPM away, averaged."""
        return (np.einsum("nij,nj->ni", errors.G, self._self_field) + errors.offset
                + errors.calibration_noise)

    def _errors(self, draw):
        """The run's SensorErrors and calibration for its error draw: drawn once per run,
        so built once and kept while the draw is the same (a pure function of it)."""
        key = draw.tobytes()
        if self._errors_cache[0] != key:
            errors = SensorErrors(self._config, draw)
            self._errors_cache = (key, errors, self.calibration(errors))
        return self._errors_cache[1:]

    def _update(self, context, discrete_state):
        draw_state = discrete_state.get_mutable_vector(self._draw)
        if draw_state.GetAtIndex(SensorErrors.size(self._n)) < 0.5:
            draw = np.append(np.asarray(self._draw_port.Eval(context), dtype=float), 1.0)
            draw_state.SetFromVector(draw)
        errors, calibration = self._errors(draw_state.value()[:-1])
        B_epm = self.external_field(
            self._body_poses_port.Eval(context),
            {name: port.Eval(context) for name, port in self._pose_ports.items()})
        raw = self.measure(B_epm, errors, self._white_port.Eval(context))
        saturated = np.any(np.abs(raw) >= self._rail, axis=1).astype(float)
        discrete_state.get_mutable_vector(self._B).SetFromVector((raw - calibration).ravel())
        discrete_state.get_mutable_vector(self._saturated).SetFromVector(saturated)
        discrete_state.get_mutable_vector(self._raw).SetFromVector(raw.ravel())
        discrete_state.get_mutable_vector(self._true).SetFromVector(B_epm.ravel())
        discrete_state.get_mutable_vector(self._calibration).SetFromVector(
            calibration.ravel())


def check_magnetic_array(config: MagneticArrayConfig, scenario) -> None:
    checked("capsule.magnetic_array.", check_magnetic_array_config, config)
    for i, p_BS in enumerate(config.positions):
        checked("", check_inside_capsule, p_BS, f"capsule.magnetic_array.positions[{i}]")


@block("capsule.magnetic_array", MagneticArrayConfig, check=check_magnetic_array)
def add_magnetic_array(builder, parts, config: MagneticArrayConfig):
    """`capsule.magnetic_array`: the Hall sensors around the IPM reading the EPM's field
    (the station's field model), with their noise sources; exports
    capsule.magnetic_array.{B, saturated, B_raw, B_true} and shares its sensors' positions
    (`capsule.magnetic_array.positions`) and the IPM's field at them (`.self_field`)."""
    array = builder.AddNamedSystem("capsule.magnetic_array", MagneticSensorArray(
        parts.plant, parts.capsule_body, parts.magnets, parts.ipm, parts.capsule.X_BM,
        config, field_model=parts.field_model))
    builder.Connect(parts.plant.get_body_poses_output_port(),
                    array.GetInputPort("body_poses"))
    for name in array.posed_source_names():
        builder.Connect(parts.output("epm.pose"), array.get_pose_input_port(name))
    add_random_sources(builder, array.get_noise_input_ports(), array.period())
    parts.export_outputs(array, "capsule.magnetic_array",
                         ["B", "saturated", "B_raw", "B_true"])
    parts.share("capsule.magnetic_array.positions", array.config.positions)
    parts.share("capsule.magnetic_array.self_field", array.self_field())
    return array
