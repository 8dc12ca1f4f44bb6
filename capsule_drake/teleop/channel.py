"""The communication channel of the haptic teleoperation loop, and the passivity controller
that keeps the delayed force feedback stable.

    master side (operator)                       |   robot side
                                                 |
    stylus state --> DelayChannel (forward) -----+--> stylus_out --> pseudo-force
                                                 |                      |
    device <-- PassivityController <-- DelayChannel (backward) <--------+ force_in
                  ^  (PO + PC)                   |
                  +-- stylus position, velocity  |

**DelayChannel** carries one vector signal one way as packets sent at a fixed rate, each with
a one-way delay, a random extra delay (jitter) and a chance of being lost; the receiver holds
the newest packet it has. It is a sampled system whose packets in flight are its discrete
state (a ring buffer), so a context can be cloned and a run repeated exactly.

**Why time-domain passivity (TDPA) and not wave variables.** The force returned to the
operator is computed on the robot side, not measured on a physical slave: the pseudo-force of
``capsule_drake.guidance.terms`` is a function of the capsule's situation, which follows the
(delayed) stylus, and its wall term is a stiff virtual spring. Seen from the stylus, forward
channel, robot-side computation and backward channel together form a *one-port* whose only
physical port is the device. Its passivity can therefore be observed at the master with local
signals alone (the rendered force and the stylus motion; Hannaford & Ryu, IEEE TRA 18(1)
2002; Ryu, Kwon & Hannaford, IEEE TRO 20(2) 2004): nothing extra travels over the network,
the observer is independent of the delay, its jitter and losses, and while the loop generates
no energy the controller does nothing, so the operator feels the force as computed. Wave
variables (Niemeyer & Slotine, IEEE JOE 16(1) 1991) are passive for any constant delay too,
but need the wave transform on both sides of the channel, a wave impedance that trades a
stiff wall for sluggish free motion, let position drift, and need further corrections for
time-varying delay and packet loss.

How this controller limits TDPA's known weaknesses (``passivity_step``): the observer
integrates the exact work of the held (zero-order-hold) force from sampled positions; the
controller predicts the work of the next period including the force's own acceleration of
the bare stylus, which stops the chattering energy leak of a velocity-only prediction at
low speed; it can always cancel the force's component along the motion, so its correction
is bounded by the requested force rather than by a damping divided by a small speed. The
price, with a long delay: while the energy is exhausted a wall only resists being entered
and pushes back out no harder than the hand pushes in, i.e. it feels softer.

**Active environments.** Passivity forbids the loop from delivering net energy to the hand.
Parts of the pseudo-force do exactly that by design: the lumen attraction (its direction
follows the camera, not the stylus) and the forward pull of the potential along the colon,
when the operator follows them. With the scheme on, such guidance is felt only as far as
the hand has put energy in; ``PassivityConfig.energy_budget`` grants a fixed allowance
(by default none, strict passivity).

Energy sign convention: ``energy`` is the energy that has flowed from the device *into* the
channel-plus-environment one-port since the start, ``E = -sum F_k . (x_{k+1} - x_k)`` with
``F_k`` the force held on the stylus over the k-th servo period and ``x`` the stylus position.
``E >= 0`` at all times is passivity (the one-port never delivered more energy to the hand
than it received; its virtual springs start relaxed).
"""

import copy
import dataclasses
import math

import numpy as np
from pydrake.systems.framework import BasicVector, Diagram, DiagramBuilder, LeafSystem

from capsule_drake.schema import need_range

# The random extra delay of a packet is exponential, truncated at this many standard
# deviations (a fraction e^-8 = 3e-4 of the packets; it bounds the ring buffer).
JITTER_TRUNCATION = 8.0

_MASK64 = (1 << 64) - 1


def _splitmix64(x: int) -> int:
    """One step of SplitMix64 (Steele, Lea & Flood, OOPSLA 2014): a 64-bit hash."""
    z = (x + 0x9E3779B97F4A7C15) & _MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31)


def _uniforms(seed: int, packet: int) -> tuple[float, float]:
    """Two independent uniforms in [0, 1) for packet ``packet`` of stream ``seed``: a
    counter-based generator, so the draws need no generator state in the context."""
    h1 = _splitmix64((_splitmix64(seed) + packet) & _MASK64)
    h2 = _splitmix64(h1)
    return (h1 >> 11) * 2.0 ** -53, (h2 >> 11) * 2.0 ** -53


@dataclasses.dataclass
class ChannelConfig:
    """One direction of a network link; YAML-loadable. SI units (s). The defaults are an
    ideal link: the output is the input one period later."""

    # One-way delay of every packet (s); the receiver sees a packet at its first tick at or
    # after the packet's arrival, so delays are rounded up to the period, and a packet is
    # never seen at the tick it is sent (a delay of 0 gives one period).
    delay: float = 0.0
    # Standard deviation of the random extra delay of each packet (s), drawn independently per
    # packet from an exponential distribution (mean = standard deviation = jitter, never
    # negative: queueing delay), truncated at JITTER_TRUNCATION jitters. A packet that arrives
    # after a newer one was already delivered is dropped (UDP with sequence numbers): the
    # output never goes back in time.
    jitter: float = 0.0
    # Probability that a packet is lost, independently per packet; the receiver holds the
    # last value it got (and its `age` grows).
    loss: float = 0.0
    # Packet period (s): the sender samples and sends, and the receiver looks for arrived
    # packets, every `period` (first at t = 0). 1 kHz: the haptic device's servo rate.
    period: float = 0.001
    # Seed of the jitter and loss draws (integer >= 0): a packet's fate is a function of the
    # seed and of its index (time / period), so the same seed gives the same run. Give the
    # two directions of a link different seeds, or their losses coincide.
    seed: int = 0


MAX_LATENCY = 2.0
"""Longest a packet may take (s): delay + JITTER_TRUNCATION x jitter. Haptic teleoperation
works up to a few hundred milliseconds one way (transatlantic telesurgery: ~0.1-0.2 s;
operators cannot close the loop beyond ~1 s), and the ring buffer holds, and every tick
scans, one slot per period of it: 2 s at 1 kHz is 2,000 slots, and with the shortest period
(0.1 ms) 20,000 (a delay of 1e9 s would have asked for 80 TiB)."""


def check_channel_config(config: ChannelConfig, where: str = "channel.") -> None:
    """Raises ValueError naming the first impossible field, its key prefixed by `where`
    (a scenario's Teleop: "channel.forward." or "channel.backward.")."""
    need_range(config.period, f"{where}period", ">= 0.0001", "s",
               "a packet every 0.1 ms; the haptic loop runs at 1 kHz")
    need_range(config.delay, f"{where}delay", ">= 0", "s")
    need_range(config.jitter, f"{where}jitter", ">= 0", "s")
    latency = config.delay + JITTER_TRUNCATION * config.jitter
    if latency > MAX_LATENCY:
        raise ValueError(f"{where}delay {config.delay} + {JITTER_TRUNCATION:g} x jitter "
                         f"{config.jitter} must be at most {MAX_LATENCY:g} s (teleoperation "
                         "fails beyond ~1 s; the delay buffer holds one slot per period of it)")
    need_range(config.loss, f"{where}loss", "[0, 1)")
    need_range(config.seed, f"{where}seed", f"[0, {2 ** 53})", "", "an integer below 2^53")
    if int(config.seed) != config.seed:
        raise ValueError(f"{where}seed must be an integer in [0, 2^53), got {config.seed!r}")


def _latency_ticks(seconds: float, period: float) -> int:
    """Delay in whole periods, rounded up (with a tolerance for round-off), at least 1."""
    return max(1, math.ceil(seconds / period - 1e-9))


def packet_fate(config: ChannelConfig, packet: int, seed: int | None = None) -> tuple[bool, float]:
    """What happens to the packet sent at tick ``packet`` (time ``packet * period``):
    (lost, its one-way delay in s = delay + the random extra delay). The receiver sees it
    at the first tick at or after its arrival, and not before the next tick.

    Args:
        config: the channel (its delay, jitter, loss and seed).
        packet: the packet's index (its send time over the period, an integer).
        seed: overrides ``config.seed`` (a DelayChannel's per-context seed).
    """
    u_loss, u_jitter = _uniforms(int(config.seed if seed is None else seed), int(packet))
    extra = min(-config.jitter * math.log1p(-u_jitter), JITTER_TRUNCATION * config.jitter)
    return u_loss < config.loss, config.delay + extra


class DelayChannel(LeafSystem):
    """A one-way network link: samples its input every ``config.period`` s (first at t = 0)
    into a packet, delivers each packet after its delay (``packet_fate``) unless it is lost
    or overtaken, and holds the newest packet delivered.

    .. pydrake_system::

        name: DelayChannel
        input_ports:
        - in
        output_ports:
        - out
        - age

    - ``in`` (size): the signal on the sender's side, sampled at the ticks.
    - ``out`` (size): the value of the newest packet delivered; ``initial_value`` (zeros by
      default, see ``set_held_value``) until the first one arrives.
    - ``age`` (1, s): how old the value on ``out`` is (now minus its send time); ``inf`` until
      the first packet arrives. It grows while packets are lost; a consumer can compare it with
      the configured delay to detect a stale link.

    At each tick the receiver first takes the packets that have arrived (keeping the newest
    by send time, dropping older ones), then the sender sends the new sample, so a packet is
    seen one period after it is sent at the earliest. The packets in flight are the discrete
    state (a ring buffer of ``capacity()`` slots: send tick, arrival tick, value), so
    ``Clone``-d contexts continue identically. The seed is a numeric parameter (``set_seed``),
    initialised from ``config.seed``: Monte-Carlo runs vary it per context.

    Args:
        size: the signal's size n (>= 1).
        config: a ``ChannelConfig`` (checked and copied).
        initial_value: what ``out`` holds before the first packet arrives (default zeros).
    """

    def __init__(self, size: int, config: ChannelConfig | None = None, initial_value=None):
        LeafSystem.__init__(self)
        self._config = copy.deepcopy(config) if config is not None else ChannelConfig()
        check_channel_config(self._config)
        if int(size) != size or size < 1:
            raise ValueError(f"DelayChannel size {size} must be an integer >= 1")
        self._size = int(size)
        c = self._config
        self._capacity = _latency_ticks(c.delay + JITTER_TRUNCATION * c.jitter, c.period) + 1
        initial = (np.zeros(self._size) if initial_value is None
                   else np.asarray(initial_value, float).reshape(self._size))
        self._in_port = self.DeclareVectorInputPort("in", self._size)
        self._held = self.DeclareDiscreteState(initial)
        self._held_tick = self.DeclareDiscreteState(np.array([-np.inf]))
        # Ring buffer, slot = send tick mod capacity: [send tick, arrival tick, value (n)],
        # NaN ticks = empty slot.
        empty = np.zeros((self._capacity, 2 + self._size))
        empty[:, :2] = np.nan
        self._buffer = self.DeclareDiscreteState(empty.reshape(-1))
        self._seed = self.DeclareNumericParameter(BasicVector([float(c.seed)]))
        self._out_port = self.DeclareStateOutputPort("out", self._held)
        self._age_port = self.DeclareVectorOutputPort(
            "age", 1, self._calc_age, {self.time_ticket(), self.xd_ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(c.period, 0.0, self._update)

    def config(self) -> ChannelConfig:
        return copy.deepcopy(self._config)

    def size(self) -> int:
        return self._size

    def capacity(self) -> int:
        """Slots of the ring buffer: the longest possible delay in periods, plus one."""
        return self._capacity

    def get_input_port_in(self):
        return self._in_port

    def get_output_port_out(self):
        return self._out_port

    def get_output_port_age(self):
        return self._age_port

    def set_seed(self, context, seed: int) -> None:
        """Sets the seed of the jitter and loss draws in ``context``."""
        check_channel_config(dataclasses.replace(self._config, seed=seed))
        context.get_mutable_numeric_parameter(self._seed).SetAtIndex(0, float(seed))

    def set_held_value(self, context, value, sent_at: float = -np.inf) -> None:
        """Makes ``out`` hold ``value`` in ``context`` (e.g. the state a loop starts in), as if
        it had been sent at time ``sent_at`` (``age`` = now - sent_at)."""
        context.get_mutable_discrete_state(self._held).SetFromVector(
            np.asarray(value, float).reshape(self._size))
        context.get_mutable_discrete_state(self._held_tick).SetAtIndex(
            0, sent_at / self._config.period)

    def _calc_age(self, context, output):
        tick = context.get_discrete_state(self._held_tick).GetAtIndex(0)
        output.SetAtIndex(0, context.get_time() - tick * self._config.period)

    def _update(self, context, discrete_state):
        c = self._config
        n, capacity = self._size, self._capacity
        tick = round(context.get_time() / c.period)
        buffer = context.get_discrete_state(self._buffer).value().reshape(capacity, 2 + n).copy()
        held_tick = context.get_discrete_state(self._held_tick).GetAtIndex(0)
        with np.errstate(invalid="ignore"):
            arrived = buffer[:, 1] <= tick  # False on empty (NaN) slots
        if np.any(arrived):
            newest = int(np.argmax(np.where(arrived, buffer[:, 0], -np.inf)))
            if buffer[newest, 0] > held_tick:
                discrete_state.get_mutable_vector(self._held).SetFromVector(buffer[newest, 2:])
                discrete_state.get_mutable_vector(self._held_tick).SetAtIndex(
                    0, buffer[newest, 0])
            buffer[arrived, :2] = np.nan
        seed = int(context.get_numeric_parameter(self._seed).GetAtIndex(0))
        lost, delay = packet_fate(c, tick, seed)
        if not lost:
            slot = buffer[tick % capacity]
            slot[0] = tick
            slot[1] = tick + _latency_ticks(delay, c.period)
            slot[2:] = self._in_port.Eval(context)
        discrete_state.get_mutable_vector(self._buffer).SetFromVector(buffer.reshape(-1))


@dataclasses.dataclass
class PassivityConfig:
    """The time-domain passivity observer and controller at the haptic device; YAML-loadable.
    SI units. DS = Phantom Omni (Geomagic Touch) specifications; U = engineering choice."""

    # False: the observer still integrates the energy (the `energy` output), but the force
    # passes unchanged except for `force_limit` (to compare with and without the scheme).
    enabled: bool = True
    # Servo period of the device (s): the force is computed and held, and the stylus
    # position sampled, every period (first at t = 0). 1 kHz (DS).
    period: float = 0.001
    # Damping the controller may add beyond cancelling the force along the motion (N s/m),
    # to pay back energy already generated. U: well under the sampled-damper limit
    # 2 m / period = 90 N s/m of the bare stylus (`moving_mass`) at 1 kHz.
    max_damping: float = 10.0
    # The smallest mass the rendered force accelerates (kg): the stylus alone, when the
    # operator lets go; apparent mass at the tip 45 g (DS). The controller predicts the work
    # a force F held for one period does by accelerating it, |F|^2 T^2 / (2 m): a smaller
    # value is more conservative.
    moving_mass: float = 0.045
    # Largest force the device renders (N), applied by the controller so the observer counts
    # the force actually rendered; 0 = no limit. 3.3 N peak (DS).
    force_limit: float = 3.3
    # Net energy the channel and environment may deliver to the hand over the whole run (J):
    # the controller keeps `energy` >= -energy_budget. 0 = strict passivity with the virtual
    # springs relaxed at the start. With 0, a force appearing while the stylus is still (not
    # pushed into by the hand) is not rendered, since the work it could do on the bare
    # stylus in one period (|F|^2 T^2 / (2 m)) is not covered; 1.2e-4 J covers 3.3 N from
    # rest (module docstring, "active environments").
    energy_budget: float = 0.0


def check_passivity_config(config: PassivityConfig,
                           where: str = "channel.passivity.") -> None:
    """Raises ValueError naming the first impossible field, its key prefixed by `where`."""
    need_range(config.period, f"{where}period", ">= 0.0001", "s",
               "the device's servo runs at 1 kHz")
    need_range(config.max_damping, f"{where}max_damping", ">= 0", "N s/m")
    need_range(config.moving_mass, f"{where}moving_mass", "> 0", "kg")
    need_range(config.force_limit, f"{where}force_limit", ">= 0", "N", "0: no limit")
    need_range(config.energy_budget, f"{where}energy_budget", ">= 0", "J")


def predicted_work(config: PassivityConfig, force: np.ndarray, velocity: np.ndarray) -> float:
    """The work (J) a force held for one period is predicted to do on the hand: along the
    current motion, ``F.v T``, plus what it does by accelerating ``moving_mass`` itself,
    ``|F|^2 T^2 / (2 m)`` (>= 0; the part a purely velocity-based prediction misses when the
    stylus is slow or reverses within the period)."""
    T = config.period
    return float(force @ velocity) * T + float(force @ force) * T * T / (2.0 * config.moving_mass)


def passivity_step(config: PassivityConfig, energy: float, force: np.ndarray,
                   velocity: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The passivity controller for one servo period: (force to hold, damping added (N s/m),
    scale applied to the force (1 = none)).

    ``energy`` is the energy available (J): the observed energy plus ``energy_budget``;
    ``force`` the force the environment asks for (N, delayed); ``velocity`` the stylus
    velocity (m/s). The force passes unchanged while the work it is predicted to do on the
    hand over the period (``predicted_work``) does not exceed ``energy``. Otherwise:

    1. damping ``F - alpha v``, with the ``alpha`` that makes the velocity part of the
       prediction equal to ``energy``, capped at ``max(F.v / |v|^2, 0) + max_damping``: it can
       always remove the force's component along the motion (a change bounded by |F|, however
       slow the motion), and beyond that dissipates at most ``max_damping`` to pay back energy
       generated earlier;
    2. if the prediction still exceeds ``energy`` (slow motion, reversal within the period),
       the force is scaled down by the largest factor in [0, 1] that satisfies it (or that
       minimises the prediction if none does).

    Then the force is clipped to ``force_limit``. Non-finite inputs count as zero: the output
    is always finite.
    """
    force = np.where(np.isfinite(force), force, 0.0)
    velocity = np.where(np.isfinite(velocity), velocity, 0.0)
    energy = energy if math.isfinite(energy) else 0.0
    alpha, scale = 0.0, 1.0
    T = config.period
    if config.enabled and predicted_work(config, force, velocity) > energy:
        power_out = float(force @ velocity)  # delivered to the hand if > 0
        speed2 = float(velocity @ velocity)
        deficit = power_out * T - energy
        if deficit > 0.0 and speed2 > 0.0:
            alpha = min(deficit / (speed2 * T), max(power_out / speed2, 0.0) + config.max_damping)
            force = force - alpha * velocity
        # W(s) = a s + b s^2 <= energy for the scaled force s F.
        a = float(force @ velocity) * T
        b = float(force @ force) * T * T / (2.0 * config.moving_mass)
        if b > 0.0 and a + b > energy:
            discriminant = a * a + 4.0 * b * energy
            if discriminant >= 0.0:
                scale = (-a + math.sqrt(discriminant)) / (2.0 * b)
            else:
                scale = -a / (2.0 * b)
            scale = min(max(scale, 0.0), 1.0)
            force = scale * force
    norm = float(np.linalg.norm(force))
    if config.force_limit > 0.0 and norm > config.force_limit:
        force = force * (config.force_limit / norm)
    return force, alpha, scale


class PassivityController(LeafSystem):
    """Time-domain passivity observer (PO) and controller (PC) on the master side, between
    the delayed force from the channel and the haptic device (Ryu, Kwon & Hannaford, IEEE
    TRO 2004, impedance-type PC; module docstring for the choice and the sign convention).

    Every ``config.period`` s (first at t = 0) it samples the stylus position, adds the work
    of the force it held over the last period to the observed energy (``E -= F . dx``: exact
    for a force held constant over the period, whatever the motion in between), then holds
    the force of ``passivity_step`` for the next period.

    .. pydrake_system::

        name: PassivityController
        input_ports:
        - force_in
        - stylus_position
        - stylus_velocity
        output_ports:
        - force_out
        - energy
        - force_change

    - ``force_in`` (3, N): the force from the robot side (the backward channel's output).
    - ``stylus_position`` (3, m): the stylus tip position, in the frame of the force.
    - ``stylus_velocity`` (3, m/s): its velocity; if unconnected, the backward difference of
      the sampled positions (as a device driver computes it).
    - ``force_out`` (3, N): the force for the device to render (held, finite, within
      ``force_limit``).
    - ``energy`` (1, J): the observed energy that has flowed from the device into the
      channel and the environment; >= 0 means the loop has not generated energy. The
      controller keeps it >= ``-energy_budget`` (to the error of its one-period prediction).
    - ``force_change`` (3, N): ``force_out`` minus ``force_in`` as sampled: what the controller
      (and the force limit) changed this period; zero when the loop is passive by itself.

    Multi-axis: the port is one 3-D power port (a single energy), as in Ryu et al.

    Args:
        config: a ``PassivityConfig`` (checked and copied).
    """

    def __init__(self, config: PassivityConfig | None = None):
        LeafSystem.__init__(self)
        self._config = copy.deepcopy(config) if config is not None else PassivityConfig()
        check_passivity_config(self._config)
        self._force_in_port = self.DeclareVectorInputPort("force_in", 3)
        self._position_port = self.DeclareVectorInputPort("stylus_position", 3)
        self._velocity_port = self.DeclareVectorInputPort("stylus_velocity", 3)
        self._force = self.DeclareDiscreteState(3)
        self._energy = self.DeclareDiscreteState(1)
        self._change = self.DeclareDiscreteState(3)
        # The position at the last sample; NaN = none yet.
        self._last_position = self.DeclareDiscreteState(np.full(3, np.nan))
        self._force_out_port = self.DeclareStateOutputPort("force_out", self._force)
        self._energy_port = self.DeclareStateOutputPort("energy", self._energy)
        self._change_port = self.DeclareStateOutputPort("force_change", self._change)
        self.DeclarePeriodicDiscreteUpdateEvent(self._config.period, 0.0, self._update)

    def config(self) -> PassivityConfig:
        return copy.deepcopy(self._config)

    def get_force_in_input_port(self):
        return self._force_in_port

    def get_stylus_position_input_port(self):
        return self._position_port

    def get_stylus_velocity_input_port(self):
        return self._velocity_port

    def get_force_out_output_port(self):
        return self._force_out_port

    def get_energy_output_port(self):
        return self._energy_port

    def get_force_change_output_port(self):
        return self._change_port

    def _update(self, context, discrete_state):
        position = np.asarray(self._position_port.Eval(context), float)
        last = context.get_discrete_state(self._last_position).value()
        held = context.get_discrete_state(self._force).value()
        energy = context.get_discrete_state(self._energy).GetAtIndex(0)
        moved = position - last
        if np.all(np.isfinite(moved)):
            energy -= float(held @ moved)
        if self._velocity_port.HasValue(context):
            velocity = np.asarray(self._velocity_port.Eval(context), float)
        else:
            velocity = moved / self._config.period
        requested = np.asarray(self._force_in_port.Eval(context), float)
        force, _, _ = passivity_step(self._config, energy + self._config.energy_budget,
                                     requested, velocity)
        discrete_state.get_mutable_vector(self._force).SetFromVector(force)
        discrete_state.get_mutable_vector(self._energy).SetAtIndex(0, energy)
        discrete_state.get_mutable_vector(self._change).SetFromVector(
            force - np.where(np.isfinite(requested), requested, 0.0))
        discrete_state.get_mutable_vector(self._last_position).SetFromVector(position)


def _default_backward() -> ChannelConfig:
    return ChannelConfig(seed=1)


@dataclasses.dataclass
class TeleopChannelConfig:
    """Both directions of the teleoperation link and the passivity scheme; YAML-loadable."""

    # Master to robot: the stylus state.
    forward: ChannelConfig = dataclasses.field(default_factory=ChannelConfig)
    # Robot to master: the force (a different seed from the forward's by default, so their
    # losses are independent).
    backward: ChannelConfig = dataclasses.field(default_factory=_default_backward)
    # The stabilising scheme at the device; `passivity.enabled: false` switches it off.
    passivity: PassivityConfig = dataclasses.field(default_factory=PassivityConfig)


class TeleopChannel(Diagram):
    """The network part of the haptic loop: forward DelayChannel (the stylus state, size
    ``n_fwd``), backward DelayChannel (the force, 3) and the PassivityController at the
    device.

    .. pydrake_system::

        name: TeleopChannel
        input_ports:
        - stylus_in
        - force_in
        - stylus_position
        - stylus_velocity
        output_ports:
        - stylus_out
        - stylus_age
        - force_out
        - force_age
        - energy
        - force_change

    - ``stylus_in`` (n_fwd): the stylus state on the master side (e.g. position and
      velocity); ``stylus_out`` (n_fwd) is what the robot side receives, ``stylus_age``
      (1, s) its age.
    - ``force_in`` (3, N): the force computed on the robot side (e.g. the pseudo-force,
      in the device frame); ``force_age`` (1, s): the age of the force the device uses.
    - ``stylus_position`` (3, m), ``stylus_velocity`` (3, m/s): the device's own
      measurements, for the passivity observer (``stylus_velocity`` may stay unconnected).
    - ``force_out`` (3, N): the force for the device to render; ``energy`` (1, J) and
      ``force_change`` (3, N): the PassivityController's outputs.

    Args:
        n_fwd: size of the stylus state sent forward.
        config: a ``TeleopChannelConfig`` (copied; its parts are checked by the systems).
    """

    def __init__(self, n_fwd: int, config: TeleopChannelConfig | None = None):
        Diagram.__init__(self)
        self._config = copy.deepcopy(config) if config is not None else TeleopChannelConfig()
        builder = DiagramBuilder()
        forward = builder.AddNamedSystem("forward", DelayChannel(n_fwd, self._config.forward))
        backward = builder.AddNamedSystem("backward", DelayChannel(3, self._config.backward))
        passivity = builder.AddNamedSystem("passivity",
                                           PassivityController(self._config.passivity))
        builder.Connect(backward.get_output_port_out(), passivity.get_force_in_input_port())
        builder.ExportInput(forward.get_input_port_in(), "stylus_in")
        builder.ExportInput(backward.get_input_port_in(), "force_in")
        builder.ExportInput(passivity.get_stylus_position_input_port(), "stylus_position")
        builder.ExportInput(passivity.get_stylus_velocity_input_port(), "stylus_velocity")
        builder.ExportOutput(forward.get_output_port_out(), "stylus_out")
        builder.ExportOutput(forward.get_output_port_age(), "stylus_age")
        builder.ExportOutput(passivity.get_force_out_output_port(), "force_out")
        builder.ExportOutput(backward.get_output_port_age(), "force_age")
        builder.ExportOutput(passivity.get_energy_output_port(), "energy")
        builder.ExportOutput(passivity.get_force_change_output_port(), "force_change")
        builder.BuildInto(self)
        self._forward, self._backward, self._passivity = forward, backward, passivity

    def config(self) -> TeleopChannelConfig:
        return copy.deepcopy(self._config)

    def forward_channel(self) -> DelayChannel:
        return self._forward

    def backward_channel(self) -> DelayChannel:
        return self._backward

    def passivity_controller(self) -> PassivityController:
        return self._passivity
