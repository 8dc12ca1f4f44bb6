"""The EPM's path between commands: what its carrier is asked to do, shaped so that the
magnet stays clear of the skin on the way, not only where it is sent.

The guard (epm/guard.py) makes each command safe where it points: its magnet's lowest point
at least the clearance over the highest skin under it (the floor). A carrier sent from one
safe command to the next goes there by its own way: the kinematic stage at once, a servo
along the line between them (or past it, as fast as its gains make it), the arm along its
controller's straight line. Between two floor commands over the flanks that line passes
through the belly. So every pose command goes through `EpmPathShaper` between the guard and
the carrier:

- **The line is checked.** The segment from where the EPM is asked to be now to the new
  command (its moment turned along the segment in step with the move) is sampled against
  the floor, every `SAMPLE_SPACING` and every `SAMPLE_TURN`. A clear line is followed.
- **Else the EPM goes over.** It rises where it is to the highest floor along the way (plus
  `ROUTE_MARGIN`), crosses at that height while it turns, and comes down onto the command.
- **At speeds its carrier can follow.** Each mount gives its `MotionLimits`: speed,
  acceleration (the servo's reference has no jumps the servo would lag behind) and turn
  rate. The kinematic stage's are infinite: it is where it is asked to be, so it takes the
  same clear line or the same three legs, each at once.
- **Never below the floor.** Each step's pose is raised to the floor if it would lie under it.

The pure functions (`chord_is_clear`, `route_height`, `shape_step`) are the shaper; the
system adapts them to ports. A command the carrier can reach along a clear line within one
step (the kinematic stage's every clear command) passes bit for bit.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem

SAMPLE_SPACING = 0.005
"""Largest distance (m) between the floor samples along a line: the floor (the highest skin
under the magnet's footprint, 14 cm across for the default EPM) changes over centimetres."""
SAMPLE_TURN = math.radians(5.0)
"""Largest turn of the moment (rad) between samples: the magnet's vertical extent changes
by at most 7 % of its diagonal over 5 degrees."""
MAX_SAMPLES = 400
"""At most this many samples a line (a 2 m line is sampled every 5 mm)."""
CHORD_SLACK = 1.0e-4
"""How far (m) a sample of a line may lie under the floor and the line still count as
clear: the chord between two floor points over the convex belly sags under it by
L^2 / (8 R) (a 5 mm step under a 0.2 m radius: 16 micrometres)."""
ROUTE_MARGIN = 0.002
"""Height (m) kept over the highest floor while the EPM crosses over: room for a servo's
lag on the crossing (see epm/clearance.py, CLEARANCE_TOLERANCE)."""
ARRIVED = 1.0e-6
"""Distance (m) and angle (rad) within which a leg's end is reached."""


@dataclasses.dataclass(frozen=True)
class MotionLimits:
    """How fast a carrier can follow its reference: the EPM's speed (m/s), acceleration
    (m/s^2) and its moment's turn rate (rad/s). Infinite: the kinematic stage."""

    max_speed: float = math.inf
    max_acceleration: float = math.inf
    max_turn_rate: float = math.inf

    @property
    def instant(self) -> bool:
        return math.isinf(self.max_speed) and math.isinf(self.max_acceleration) \
            and math.isinf(self.max_turn_rate)


def unit(v) -> np.ndarray:
    """v / |v|, for any finite v of three components and non-zero length (its largest
    component first scaled to 1: a moment of 1e300 A m^2 has a direction too)."""
    x, y, z = (float(c) for c in v)
    scale = max(abs(x), abs(y), abs(z))
    x, y, z = x / scale, y / scale, z / scale
    n = math.sqrt(x * x + y * y + z * z)
    return np.array([x / n, y / n, z / n])


def _cross(a, b) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def turn_angle(m0, m1) -> float:
    """Angle (rad) between two moments (of any non-zero length)."""
    m0, m1 = unit(m0), unit(m1)
    c = _cross(m0, m1)
    return math.atan2(math.sqrt(float(c @ c)), float(m0 @ m1))


def turn_toward_many(m0, m1, fractions) -> np.ndarray:
    """(N, 3) unit moments the given fractions of the way from m0 to m1 along the great
    circle (a half turn goes about an axis across m0 chosen from m0 alone)."""
    fractions = np.asarray(fractions, dtype=float)
    a, b = unit(m0), unit(m1)
    angle = turn_angle(a, b)
    if angle < ARRIVED:
        return np.tile(a, (len(fractions), 1))
    axis = _cross(a, b)
    if math.sqrt(float(axis @ axis)) < 1e-12:   # opposite: any axis across m0
        axis = _cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    across = _cross(unit(axis), a)   # a and `across`: the great circle's plane
    phi = np.clip(fractions, 0.0, 1.0)[:, None] * angle
    return a * np.cos(phi) + across * np.sin(phi)


def turn_toward(m0, m1, fraction: float) -> np.ndarray:
    """The unit moment `fraction` of the way from m0 to m1 along the great circle; m0 or m1
    themselves, as given, at a fraction of 0 or 1 (so that a move's end is its command)."""
    if fraction >= 1.0:
        return np.array(m1, dtype=float)
    if fraction <= 0.0 or turn_angle(m0, m1) < ARRIVED:
        return np.array(m0, dtype=float)
    return turn_toward_many(m0, m1, [fraction])[0]


def _samples(length: float, angle: float, ends: bool) -> np.ndarray:
    """Fractions along a line of `length` (m) and turn `angle` (rad): every SAMPLE_SPACING
    and SAMPLE_TURN, at most MAX_SAMPLES; the two ends too if `ends`."""
    n = int(min(MAX_SAMPLES, max(2, math.ceil(length / SAMPLE_SPACING),
                                 math.ceil(angle / SAMPLE_TURN))))
    t = np.linspace(0.0, 1.0, n + 1)
    return t if ends else t[1:-1]


def chord_is_clear(floor, p0, m0, p1, m1) -> bool:
    """True when the straight line from pose (p0, m0) to (p1, m1), the moment turned in step
    with the move, keeps the EPM's centre over the floor (within CHORD_SLACK) at every
    sample. `floor(x, y, m)`: the lowest centre heights the clearance allows over points
    (x, y) (arrays, N) for unit moments m (N, 3). The ends are the caller's (each a guarded
    command or a shaped pose)."""
    p0, p1 = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
    length, angle = float(np.linalg.norm(p1 - p0)), turn_angle(m0, m1)
    if length < ARRIVED and angle < ARRIVED:
        return True
    t = _samples(length, angle, ends=False)
    points = p0 + t[:, None] * (p1 - p0)
    lowest = floor(points[:, 0], points[:, 1], turn_toward_many(m0, m1, t))
    return bool(np.all(points[:, 2] >= lowest - CHORD_SLACK))


def route_height(floor, p0, m0, p1, m1) -> float:
    """The height (m) at which the EPM crosses from over p0 to over p1, turning from m0 to
    m1 on the way: the highest floor along the crossing (samples as `chord_is_clear`'s,
    ends included) plus ROUTE_MARGIN, and no lower than either end."""
    p0, p1 = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
    length = float(np.hypot(*(p1[:2] - p0[:2])))
    t = _samples(length, turn_angle(m0, m1), ends=True)
    xy = p0[:2] + t[:, None] * (p1[:2] - p0[:2])
    lowest = floor(xy[:, 0], xy[:, 1], turn_toward_many(m0, m1, t))
    return float(max(p0[2], p1[2], float(np.max(lowest)) + ROUTE_MARGIN))


# The shaper's state: [p (3), v (3), m (3), the command planned for (6), leg, height]. The
# moments are kept as given (the guard passes a command's moment as it came, the carriers
# make it unit): a command that passes untouched passes bit for bit.
P, V, M, PLANNED, LEG, HEIGHT = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 15), 15, 16
STATE_SIZE = 17
# Legs: along the clear line; over the skin: rising where it is, then crossing at height.
DIRECT, RISE, CROSS = 0.0, 1.0, 2.0


def initial_state(start_command) -> np.ndarray:
    """The shaper at rest at the EPM's start [p_WE, m_hat_W] (a guarded pose), planned
    for it."""
    start = np.asarray(start_command, dtype=float)
    return np.concatenate([start[:3], np.zeros(3), start[3:], start, [DIRECT, start[2]]])


def plan(state: np.ndarray, command: np.ndarray, floor) -> np.ndarray:
    """The state with the leg for a new `command` [p, m_hat]: the clear line, or over the
    skin (its crossing height from `route_height`)."""
    x = state.copy()
    x[PLANNED] = command
    if chord_is_clear(floor, x[P], x[M], command[:3], command[3:]):
        x[LEG] = DIRECT
    else:
        x[LEG] = RISE
        x[HEIGHT] = route_height(floor, x[P], x[M], command[:3], command[3:])
    return x


def aim_of(x: np.ndarray):
    """(the point the reference moves toward, its moment) on the current leg; moves `x` on
    to the next leg when its leg's end is reached."""
    target, m_target = x[PLANNED][:3], x[PLANNED][3:]
    if x[LEG] == RISE:
        if x[P][2] < x[HEIGHT] - ARRIVED:
            return np.array([x[P][0], x[P][1], x[HEIGHT]]), x[M].copy()
        x[LEG] = CROSS
    if x[LEG] == CROSS:
        over = np.array([target[0], target[1], x[HEIGHT]])
        if np.linalg.norm(x[P] - over) >= ARRIVED or turn_angle(x[M], m_target) >= ARRIVED:
            return over, m_target.copy()
        x[LEG] = DIRECT   # straight down onto the command: the floor under it is lower
    return target.copy(), m_target.copy()


def move_toward(p, v, m, aim, m_aim, limits: MotionLimits, dt: float):
    """One step of the reference toward (aim, m_aim). The speed is the one that stops at the
    aim within the acceleration limit, capped by the speed limit; the velocity changes by
    at most the acceleration limit times dt. The moment turns by the fraction of its
    remaining turn that the step covers of the remaining distance, so that a line's poses
    are the ones `chord_is_clear` checked; where the turn-rate limit allows less, the move
    slows to the turn's pace. Returns (p, v, m)."""
    if limits.instant:
        return aim.copy(), np.zeros(3), m_aim.copy()
    d = aim - p
    distance = float(np.linalg.norm(d))
    angle = turn_angle(m, m_aim)
    turnable = limits.max_turn_rate * dt / angle if angle > ARRIVED else math.inf
    if distance < ARRIVED:   # there (a turn in place, if any, at its rate)
        if turnable >= 1.0:
            return aim.copy(), np.zeros(3), m_aim.copy()
        return p.copy(), np.zeros(3), turn_toward(m, m_aim, turnable)
    step_velocity = d / dt
    if distance <= limits.max_speed * dt and turnable >= 1.0 and \
            float(np.linalg.norm(step_velocity - v)) <= limits.max_acceleration * dt:
        return aim.copy(), step_velocity, m_aim.copy()   # within reach of this step
    speed = min(limits.max_speed, math.sqrt(2.0 * limits.max_acceleration * distance),
                distance / dt)
    change = d * (speed / distance) - v
    norm = float(np.linalg.norm(change))
    most = limits.max_acceleration * dt
    v_next = v + (change * (most / norm) if norm > most else change)
    covered = min(max(float(np.dot(v_next, d)) * dt / (distance * distance), 0.0), 1.0)
    if turnable < covered:   # the turn sets the pace
        v_next = v_next * (turnable / covered)
        covered = turnable
    p_next = p + v_next * dt
    if covered >= 1.0 and float(np.linalg.norm(aim - p_next)) < ARRIVED:
        return aim.copy(), v_next, m_aim.copy()
    return p_next, v_next, turn_toward(m, m_aim, covered)


def shape_step(state: np.ndarray, command: np.ndarray, floor, limits: MotionLimits,
               dt: float) -> np.ndarray:
    """The shaper's next state for the guarded `command` [p, m_hat]: a new command is
    planned, the leg followed one step, the pose kept over the floor. `floor(x, y, m)`
    is chord_is_clear's."""
    x = state.copy()
    if not np.array_equal(command, x[PLANNED]):
        x = plan(x, command, floor)
    aim, m_aim = aim_of(x)
    p, v, m = move_toward(x[P], x[V], x[M], aim, m_aim, limits, dt)
    arrived = np.array_equal(p, command[:3]) and np.array_equal(m, command[3:])
    # (the guarded command itself is over the floor by the guard's measure: re-evaluated
    # there, the floor can differ from it in the last bit)
    if not limits.instant and not arrived and (not np.array_equal(p, x[P])
                                               or not np.array_equal(m, x[M])):
        lowest = float(floor(p[:1], p[1:2], unit(m)[None, :])[0])
        if p[2] < lowest:   # never under the floor, whatever the filter did
            v[2] = max(v[2], (lowest - x[P][2]) / dt)
            p[2] = lowest
    x[P], x[V], x[M] = p, v, m
    return x


class EpmPathShaper(LeafSystem):
    """Between the EPM's guard and its carrier: the guarded command's path shaped so that
    the magnet stays clear of the skin on the way and the carrier can follow it (module
    docstring).

    .. pydrake_system::

        name: EpmPathShaper
        input_ports:
        - epm_command
        output_ports:
        - epm_command

    epm_command (in): [p_WE (3), m_hat_W (3)], a guarded command (the guard's output).
    epm_command (out): the pose [p_WE, m_hat_W] the carrier is to be at now: this step's
    shaped pose, at once (direct feedthrough, as the guard's: the carrier samples it at the
    same instant as it did the guard's), kept as state every `period` (the plant's step).

    Args:
        floor: function (x, y, m_hat) -> the lowest EPM centre heights the clearance allows
            over points (x, y) for unit moments m_hat (arrays: N, N, (N, 3);
            EpmGuard.lowest_centre_heights).
        limits: MotionLimits of the carrier.
        start_command: the EPM's start pose [p_WE, m_hat_W] (guarded).
        period: s.
    """

    def __init__(self, floor, limits: MotionLimits, start_command, period: float):
        super().__init__()
        self._floor = floor
        self._limits = limits
        self._dt = float(period)
        self._input = self.DeclareVectorInputPort("epm_command", 6)
        self._state = self.DeclareDiscreteState(BasicVector(initial_state(start_command)))
        self.DeclareVectorOutputPort(
            "epm_command", 6, self._calc_command,
            {self.input_port_ticket(self._input.get_index()), self.xd_ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(self._dt, 0.0, self._update)
        self._last = None   # (state and command bytes, the next state): asked twice a step

    def _next(self, context) -> np.ndarray:
        x = context.get_discrete_state(self._state).value()
        command = np.asarray(self._input.Eval(context), dtype=float)
        key = x.tobytes() + command.tobytes()
        if self._last is None or self._last[0] != key:
            self._last = (key, shape_step(x, command, self._floor, self._limits, self._dt))
        return self._last[1]

    def _calc_command(self, context, output):
        x = self._next(context)
        output.SetFromVector(np.concatenate([x[P], x[M]]))

    def _update(self, context, discrete_state):
        x_next = self._next(context)
        if np.array_equal(x_next, context.get_discrete_state(self._state).value()):
            return EventStatus.DidNothing()   # holding where it was sent
        discrete_state.set_value(self._state, x_next)
        return EventStatus.Succeeded()
