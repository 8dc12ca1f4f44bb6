"""A contact-force sensor in the capsule's shell: the force the colon wall presses on it.

The smallest sensor a user might add, and the example of how one is added
(docs/guides/add-a-block.md): this module (config, LeafSystem, `add_contact_sensor`) plus
one field of `CapsuleConfig`. Force-sensing capsules and tethered tips carry such sensors to
limit the pressure on the mucosa; the figures below are an engineering assumption (a
thin-film three-axis sensor), not a datasheet.

Every 1 / sample_rate s it samples the net contact force on the capsule (from the plant's
ContactResults), expressed in the capsule frame B, adds white Gaussian noise of
`noise_std` per axis and clips each axis to +-`range`; the truth is output beside it.
"""


import dataclasses

import numpy as np
from pydrake.common import RandomDistribution
from pydrake.common.value import AbstractValue
from pydrake.multibody.plant import ContactResults

from capsule_drake.physics.contact.foundation import empty_wall_contact
from pydrake.systems.framework import BasicVector, LeafSystem

from capsule_drake.capsule.imu import add_random_sources
from capsule_drake.capsule.model import rotation_from_quaternion
from capsule_drake.lifetime import id_values
from capsule_drake.physics.contact_monitor import capsule_contact_force_W
from capsule_drake.blocks import block
from capsule_drake.schema import MAX_RATE, need_range


@dataclasses.dataclass
class ContactSensorConfig:
    """The capsule's contact-force sensor (engineering assumption)."""

    # Samples per second (1/s).
    sample_rate: float = 100.0
    # White noise per axis and sample (N).
    noise_std: float = 0.005
    # Full scale per axis (N): a reading saturates there.
    range: float = 2.0


def check_contact_sensor_config(config: ContactSensorConfig) -> None:
    """Raises ValueError naming the first impossible field."""
    need_range(config.sample_rate, "sample_rate", f"(0, {MAX_RATE:g}]", "Hz")
    need_range(config.noise_std, "noise_std", ">= 0", "N")
    need_range(config.range, "range", "> 0", "N")


class ContactForceSensor(LeafSystem):
    """Samples the wall's contact force on the capsule in the capsule frame B.

    .. pydrake_system::

        name: ContactForceSensor
        input_ports:
        - contact_results
        - capsule_state
        - noise
        output_ports:
        - F_B
        - F_B_true

    F_B: the reading (N, frame B; noisy, clipped), F_B_true: the exact force. Both are
    discrete state, zero before the first sample (at t = 0). `noise` is a standard normal
    3-vector (a random input: seed the diagram's random context).

    Args:
        capsule_geometries: the capsule's collision GeometryIds, or their values.
        config: a ContactSensorConfig.
    """

    def __init__(self, capsule_geometries, config: ContactSensorConfig, wall: bool = False):
        super().__init__()
        # Their values: the ids a plant returns keep it alive (capsule_drake/lifetime.py).
        self._geometries = id_values(capsule_geometries)
        self._config = dataclasses.replace(config)
        self._results = self.DeclareAbstractInputPort(
            "contact_results", AbstractValue.Make(ContactResults()))
        # The compliant wall's own force (its foundation realisation), when it has one.
        self._wall = (self.DeclareAbstractInputPort("wall_contact",
                                                    AbstractValue.Make(empty_wall_contact()))
                      if wall else None)
        self._state_port = self.DeclareVectorInputPort("capsule_state", 13)
        self._noise = self.DeclareVectorInputPort(
            "noise", 3, random_type=RandomDistribution.kGaussian)
        self._reading = self.DeclareDiscreteState(BasicVector(np.zeros(3)))
        self._truth = self.DeclareDiscreteState(BasicVector(np.zeros(3)))
        self.DeclareStateOutputPort("F_B", self._reading)
        self.DeclareStateOutputPort("F_B_true", self._truth)
        self.DeclarePeriodicDiscreteUpdateEvent(self.period(), 0.0, self._sample)

    def period(self) -> float:
        return 1.0 / self._config.sample_rate

    def _sample(self, context, discrete_state):
        x = self._state_port.Eval(context)
        F_W = capsule_contact_force_W(self._results.Eval(context), self._geometries,
                                      self._wall.Eval(context) if self._wall else None)
        F_B = rotation_from_quaternion(x[:4]).T @ F_W
        c = self._config
        reading = np.clip(F_B + c.noise_std * np.asarray(self._noise.Eval(context)),
                          -c.range, c.range)
        discrete_state.set_value(self._reading, reading)
        discrete_state.set_value(self._truth, F_B)


def check_contact_sensor(config: ContactSensorConfig, scenario) -> None:
    check_contact_sensor_config(config)


@block("capsule.contact_sensor", ContactSensorConfig, check=check_contact_sensor,
       where="capsule.contact_sensor: ")
def add_contact_sensor(builder, parts, config: ContactSensorConfig):
    """`capsule.contact_sensor` on the plant's contact results and the capsule's state,
    its noise from a seeded random source; exports capsule.contact_sensor.{F_B, F_B_true}."""
    plant = parts.plant
    wall = parts.has("contact.wall")
    sensor = builder.AddNamedSystem("capsule.contact_sensor", ContactForceSensor(
        plant.GetCollisionGeometriesForBody(parts.capsule_body), config, wall=wall))
    builder.Connect(plant.get_contact_results_output_port(),
                    sensor.GetInputPort("contact_results"))
    if wall:
        builder.Connect(parts.output("contact.wall"), sensor.GetInputPort("wall_contact"))
    builder.Connect(parts.capsule_state, sensor.GetInputPort("capsule_state"))
    add_random_sources(builder, [sensor.GetInputPort("noise")], sensor.period())
    parts.export_outputs(sensor, "capsule.contact_sensor")
    return sensor
