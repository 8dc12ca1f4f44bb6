"""The Gymnasium environment's parts (app/gym_env.py): the reward's weights, the contact
statistics it samples, the action toward a target, and the checks of its arguments."""

import dataclasses
import math

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from capsule_drake.schema import need_range

ENV_ID = "capsule_drake/ColonNavigation-v0"
OBSERVATIONS = ("camera", "imu", "magnetometer", "hall", "epm", "truth")
DEFAULT_OBSERVATIONS = ("imu", "magnetometer", "epm")
COMMAND_PERIOD = 0.05
"""Period (s) of the EPM command's ramp within a step: the lumen follower's 20 Hz."""
CONTACT_STATS = "contact_stats"
"""The environment's ContactStats system, beside the run's station."""
CONTACT_SAMPLE_PERIOD = 0.01
"""Period (s) at which the contact load is sampled for the reward (peak, time in contact)."""
DEFAULT_WORKSPACE = ((-0.35, -0.45, 0.0), (0.35, 0.45, 0.7))
"""Box (m, world) the EPM's centre is kept in: over the patient (the abdomen is 0.36 m
wide, 0.56 m long), up to 0.7 m above the table, where the magnet barely pulls."""
# Bounds of the observations without a sensor range (m, rad/s, m/s): a capsule in a
# patient on the table is within 2 m of the origin, and the guard stops it above 2 m/s.
_POSITION_BOUND = 2.0
_ANGULAR_SPEED_BOUND = 1000.0
_SPEED_BOUND = 10.0


@dataclasses.dataclass(frozen=True)
class RewardWeights:
    """The reward's weights (module docstring)."""

    # Per metre of centreline progress (100: 1 per cm; the colon is 1.1-2 m long).
    progress: float = 100.0
    # Per step spent wholly in wall contact (load > 0.05 N): 0.1 per second. A capsule
    # lying on the wall all 600 s loses 60, less than half of what reaching the cecum earns.
    wall_contact: float = 0.01
    # Per newton of the step's peak contact load above force_threshold, per step.
    force: float = 1.0
    # Contact load (N) above which force is penalised: 4 times the capsule's weight, 5 times
    # the lumen follower's mean peak (0.09 N), below the teleoperated runs' worst (3-4 N).
    force_threshold: float = 0.5
    # Once, on reaching the cecum.
    cecum: float = 50.0
    # Once, when the run guard stops the episode (or the simulation fails).
    guard_stop: float = 10.0


def check_reward_weights(weights: RewardWeights) -> None:
    """Raises ValueError naming the first impossible weight."""
    for item in dataclasses.fields(RewardWeights):
        need_range(float(getattr(weights, item.name)), f"reward.{item.name}", "[0, 1e6]")


class ContactStats(LeafSystem):
    """The contact load's peak and the time it spent above a threshold, since the state was
    last zeroed (the environment zeroes it at each step).

    .. pydrake_system::

        name: ContactStats
        input_ports:
        - contact_load
        output_ports:
        - stats

    contact_load: (1) N. stats: [peak load (N), time above `threshold` (s)], sampled every
    `period` (s): an unrestricted update, as the plant's own step and the wall's pressure
    map (physics/wall_pressure.py), so it reads the state before the step, where the
    plant's step has just evaluated the wall's contact and the magnet (a discrete update
    would read them afresh at the state after the other updates).
    """

    def __init__(self, period: float, threshold: float):
        super().__init__()
        self._period = float(period)
        self._threshold = float(threshold)
        self._load = self.DeclareVectorInputPort("contact_load", 1)
        self._state = self.DeclareDiscreteState(BasicVector(np.zeros(2)))
        self.DeclareStateOutputPort("stats", self._state)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self._period, 0.0, self._update)

    def _update(self, context, state):
        peak, time = context.get_discrete_state(self._state).value()
        load = float(self._load.Eval(context)[0])
        if not math.isfinite(load):
            load = 0.0
        state.get_mutable_discrete_state(self._state).set_value(
            [max(peak, load), time + (self._period if load > self._threshold else 0.0)])


def rotate(vector, rotation_vector) -> np.ndarray:
    """`vector` turned by the rotation vector (axis times angle, rad): Rodrigues."""
    v = np.asarray(vector, dtype=float)
    w = np.asarray(rotation_vector, dtype=float)
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return v.copy()
    k = w / angle
    return (v * math.cos(angle) + np.cross(k, v) * math.sin(angle)
            + k * (k @ v) * (1.0 - math.cos(angle)))


def action_toward(epm_command, target, max_move: float, max_turn: float) -> np.ndarray:
    """The action (6, in [-1, 1]) that moves an EPM command [p_WE, m_hat_W] toward the pose
    `target` [p, m_hat] as far as one step allows (max_move m, max_turn rad per step): for
    scripted policies and demonstrations. The env's `max_move` and `max_turn` attributes
    give the step's bounds."""
    command = np.asarray(epm_command, dtype=float)
    target = np.asarray(target, dtype=float)
    move = (target[:3] - command[:3]) / max_move
    m0 = command[3:] / np.linalg.norm(command[3:])
    m1 = target[3:] / np.linalg.norm(target[3:])
    axis = np.cross(m0, m1)
    angle = math.atan2(float(np.linalg.norm(axis)), float(m0 @ m1))
    if np.linalg.norm(axis) > 1e-12:
        turn = axis / np.linalg.norm(axis) * angle / max_turn
    elif m0 @ m1 < 0.0:  # opposite: about any axis across the moment
        across = np.cross(m0, [1.0, 0.0, 0.0])
        if np.linalg.norm(across) < 1e-6:
            across = np.cross(m0, [0.0, 1.0, 0.0])
        turn = across / np.linalg.norm(across) * math.pi / max_turn
    else:
        turn = np.zeros(3)
    # Scaled as a whole, so that a clipped move keeps its direction.
    for part in (move, turn):
        largest = float(np.max(np.abs(part)))
        if largest > 1.0:
            part /= largest
    return np.concatenate([move, turn]).astype(np.float32)


def _number(value, name: str) -> float:
    """`value` as a float, or ValueError naming `name`."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    return float(value)


def _observation_names(observations) -> tuple[str, ...]:
    if isinstance(observations, str):
        observations = (observations,)
    try:
        names = tuple(dict.fromkeys(observations))
    except TypeError:
        raise ValueError(f"observations must be a sequence of names from "
                         f"{', '.join(OBSERVATIONS)}, got {observations!r}") from None
    for name in names:
        if name not in OBSERVATIONS:
            raise ValueError(f"observations: unknown {name!r}; choose from "
                             f"{', '.join(OBSERVATIONS)}")
    if not names:
        raise ValueError(f"observations: give at least one of {', '.join(OBSERVATIONS)}")
    return names


def _colon_seeds(colons) -> tuple[int, ...]:
    try:
        seeds = tuple(colons)
    except TypeError:
        raise ValueError(f"colons must be a sequence of colon seeds, got {colons!r}") from None
    if not seeds:
        raise ValueError("colons: give at least one colon seed")
    for seed in seeds:
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) \
                or not 0 <= int(seed) < 2**32:
            raise ValueError(f"colons: a colon seed must be an integer in [0, 4294967295], "
                             f"got {seed!r}")
    return tuple(int(seed) for seed in seeds)


def _workspace(workspace):
    try:
        low, high = (np.asarray(corner, dtype=float) for corner in workspace)
    except (TypeError, ValueError):
        raise ValueError(f"workspace must be ((x, y, z) low, (x, y, z) high) in m, got "
                         f"{workspace!r}") from None
    if low.shape != (3,) or high.shape != (3,) or not (np.all(np.isfinite(low))
                                                       and np.all(np.isfinite(high))):
        raise ValueError(f"workspace must be two finite (x, y, z) corners in m, got "
                         f"{workspace!r}")
    if np.any(np.abs(np.concatenate([low, high])) > _POSITION_BOUND) or np.any(low >= high):
        raise ValueError(f"workspace must have low < high, within {_POSITION_BOUND:g} m of the "
                         f"origin, got {workspace!r}")
    return low, high
