"""HapticMaster: a Phantom Omni / Geomagic Touch class haptic device (docs/sources.md section 4).

The stylus tip is a point mass in the device frame D (x right, y up, z toward the operator,
origin at the workspace centre), pushed by the operator's hand and by the device's motors
(the feedback force, saturated to the device's peak force), with the back-drive friction of
the linkage and the mechanical stops of the workspace. 3-DoF force, 6-DoF pose (orientation
is sensed, not actuated: the stylus reports the identity here), two buttons.
"""

import dataclasses
import math

import numpy as np
from pydrake.systems.framework import LeafSystem

from capsule_drake.guidance.terms import saturate_checked
from capsule_drake.schema import need_range

STYLUS_SIZE = 9  # position (3), quaternion wxyz (4), clutch (1), mode (1)


@dataclasses.dataclass
class HapticDeviceConfig:
    """The device. YAML-loadable; all fields default (Geomagic Touch figures)."""

    # Half extents of the workspace box in D (m): 160 x 120 x 70 mm (sources.md s. 4).
    workspace_half_extents: list[float] = dataclasses.field(
        default_factory=lambda: [0.08, 0.06, 0.035])
    # Peak force of the motors (N); the rendered force is saturated by its norm.
    force_limit: float = 3.3
    # Servo rate (Hz) of the device loop.
    servo_rate: float = 1000.0
    # Apparent mass of the stylus at the tip (kg) and viscous back-drive friction (N s/m).
    stylus_mass: float = 0.045
    friction: float = 0.4
    # The mechanical stops at the workspace's faces: stiffness (N/m) and damping (N s/m).
    stop_stiffness: float = 2000.0
    stop_damping: float = 5.0


def check_haptic_device_config(config: HapticDeviceConfig) -> None:
    """Raises ValueError naming the first impossible field."""
    if len(config.workspace_half_extents) != 3:
        raise ValueError(f"device.workspace_half_extents must be 3 values (x, y, z), got "
                         f"{config.workspace_half_extents!r}")
    need_range(list(config.workspace_half_extents), "device.workspace_half_extents", "> 0",
               "m")
    for name, unit in (("force_limit", "N"), ("servo_rate", "Hz"), ("stylus_mass", "kg")):
        need_range(getattr(config, name), f"device.{name}", "> 0", unit)
    for name, unit in (("friction", "N s/m"), ("stop_stiffness", "N/m"),
                       ("stop_damping", "N s/m")):
        need_range(getattr(config, name), f"device.{name}", ">= 0", unit)


class HapticMaster(LeafSystem):
    """The device: stylus dynamics at the servo rate, motors saturated, workspace stops.

    .. pydrake_system::

        name: HapticMaster
        input_ports:
        - hand_force
        - feedback_force
        - buttons
        output_ports:
        - stylus
        - stylus_velocity
        - motor_force

    hand_force: the operator's force on the stylus (N, D). feedback_force: the force to
    render (N, D), saturated by norm to `force_limit` (a non-finite one renders zero).
    buttons: [clutch, mode] (1 pressed, 0 released). stylus: [p_D (3), quaternion wxyz (4),
    clutch, mode]. stylus_velocity: (3) m/s. motor_force: the force the motors applied
    (N, D), and whether it was saturated, [F (3), saturated].
    Unconnected inputs read zero. Semi-implicit Euler at the servo rate.
    """

    def __init__(self, config: HapticDeviceConfig | None = None):
        super().__init__()
        self._config = config or HapticDeviceConfig()
        check_haptic_device_config(self._config)
        self._dt = 1.0 / self._config.servo_rate
        self._half = np.asarray(self._config.workspace_half_extents, dtype=float)
        self._hand = self.DeclareVectorInputPort("hand_force", 3)
        self._feedback = self.DeclareVectorInputPort("feedback_force", 3)
        self._buttons = self.DeclareVectorInputPort("buttons", 2)
        # [p (3), v (3), buttons (2), motor force (3), saturated]
        self._state = self.DeclareDiscreteState(12)
        self.DeclareVectorOutputPort("stylus", STYLUS_SIZE, self._calc_stylus,
                                     {self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "stylus_velocity", 3,
            lambda c, out: out.SetFromVector(c.get_discrete_state(self._state).value()[3:6]),
            {self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "motor_force", 4,
            lambda c, out: out.SetFromVector(c.get_discrete_state(self._state).value()[8:12]),
            {self.xd_ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(self._dt, 0.0, self._update)

    @property
    def config(self) -> HapticDeviceConfig:
        return dataclasses.replace(self._config)

    def _read(self, port, context, size):
        if not port.HasValue(context):
            return np.zeros(size)
        value = port.Eval(context)
        if math.isfinite(value.sum()):
            return value
        return np.where(np.isfinite(value), value, 0.0)

    def _calc_stylus(self, context, output):
        x = context.get_discrete_state(self._state).value()
        output.SetFromVector(np.concatenate([x[:3], [1.0, 0.0, 0.0, 0.0], x[6:8]]))

    def stop_force(self, p, v):
        """Force of the mechanical stops on a stylus at p moving at v (N)."""
        c = self._config
        beyond = np.sign(p) * np.maximum(np.abs(p) - self._half, 0.0)
        outward = (beyond != 0.0) & (np.sign(v) == np.sign(beyond))
        return -c.stop_stiffness * beyond - c.stop_damping * v * outward

    def _update(self, context, discrete_state):
        # Runs at the servo rate (1 kHz): kept lean.
        c = self._config
        x = context.get_discrete_state(self._state).value()
        p, v = x[:3], x[3:6]
        feedback = (self._feedback.Eval(context) if self._feedback.HasValue(context)
                    else np.zeros(3))
        motor, saturated, _ = saturate_checked(feedback, c.force_limit)
        force = self._read(self._hand, context, 3) + motor - c.friction * v
        if np.any(np.abs(p) > self._half):
            force += self.stop_force(p, v)
        new = np.empty(12)
        new[3:6] = v + (self._dt / c.stylus_mass) * force
        new[:3] = p + self._dt * new[3:6]
        new[6:8] = self._read(self._buttons, context, 2) > 0.5
        new[8:11] = motor
        new[11] = saturated
        discrete_state.set_value(self._state, new)
