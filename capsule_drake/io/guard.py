"""The run guard: stops a simulation that has stopped meaning anything.

A discrete simulation that is pushed past what it can resolve (a time step too long for
the magnet's stiffness, a capsule squeezed through a wall, a capsule that slides out of an
open end) does not fail by itself: it carries on and ends with numbers that look like
results (a capsule "advanced 23.3 cm" after being flung 68 m). The guard watches the
capsule's state as the run goes and ends the run, with one line saying what happened and
when, at the first of:

- a state that is not finite (NaN or infinite position, orientation or velocity);
- a capsule faster than `max_speed` (2 m/s by default). A magnetically dragged capsule
  moves at millimetres to centimetres per second; the fastest it legitimately goes is when
  it drops onto the wall at the start of a run (measured over the scenarios of
  diagrams/default.yaml: 0.47-0.73 m/s, as a fall of 1-3 cm gives) or snaps across the
  lumen toward a near magnet. Free fall across the widest lumen (9 cm, the cecum) gives
  1.3 m/s; 2 m/s leaves room for the magnet's pull. A diverging integration passes it
  within a few steps (a 0.1 s step: tens of m/s);
- any point of the capsule's surface farther than `max_wall_excursion` beyond the colon
  wall (5 mm by default: the rigid wall lets the capsule into it by well under 1 mm, and a
  fold is a few millimetres thick, so 5 mm means the capsule has gone through it), plus what
  the contact model's wall gives (physics/contact/: `wall_allowance`, the compliant wall's
  stretch to its failure strain). Through a wall that cannot yield, that is a failed
  simulation (kind "wall", the run diverged); through a wall that yields (the contact
  model's `wall_tears`), it is what the patient's wall would have done: stretched past its
  failure strain, a perforation (kind "wall_torn", the run's figures up to it stand);
- the capsule's centre past one of the colon's ends (it has left the colon).

The cheap checks (finite, speed) run every `period` (10 ms); the wall check, which
evaluates the wall's geometry at ~400 surface points (~2 ms, most of it fixed cost of the
wall model), every `wall_period` (0.25 s: ~8 ms of wall time per simulated second, 2 % of a
Default run).

The guard is a LeafSystem whose periodic publish event returns Drake's
`EventStatus.ReachedTermination` with the reason: the simulator returns from AdvanceTo
with that message, and the run loop (app/run.py) writes what was logged and exits non-zero.
"""

import dataclasses

import numpy as np
from pydrake.systems.framework import EventStatus, LeafSystem

from capsule_drake.capsule.model import rotation_from_quaternion
from capsule_drake.io.metrics import capsule_surface_points_C
from capsule_drake.schema import need_range


@dataclasses.dataclass
class GuardConfig:
    """When a run is stopped as no longer physical (io/guard.py)."""

    # Fastest credible capsule speed (m/s).
    max_speed: float = 2.0
    # Farthest any point of the capsule may be beyond the colon wall (m).
    max_wall_excursion: float = 0.005
    # Period of the finite-state and speed checks (s).
    period: float = 0.01
    # Period of the wall check (s).
    wall_period: float = 0.25


def check_guard_config(config: GuardConfig) -> None:
    """Raises ValueError naming the first impossible field."""
    need_range(config.max_speed, "guard.max_speed", "> 0", "m/s")
    need_range(config.max_wall_excursion, "guard.max_wall_excursion", "> 0", "m")
    for name in ("period", "wall_period"):
        need_range(getattr(config, name), f"guard.{name}", ">= 1e-4", "s",
                   "the checks cost ~2 ms")


# A GuardTrip's `kind` for the reasons after which a run's distances mean nothing.
DIVERGED = ("not_finite", "speed", "wall")

# A run's ending (app/run.py, Ending.status) for each kind of guard stop: the run guard's
# here, and the EPM's clearance watch (epm/clearance.py), which stops a run whose magnet came
# too close to the skin (the capsule's figures still mean what they say).
# A yielding wall stretched past its failure strain ("wall_torn") ends the run as
# "perforated": a physical event, the run's figures up to it stand.
ENDING_OF_KIND = {**{kind: "diverged" for kind in DIVERGED}, "left_colon": "left_colon",
                  "wall_torn": "perforated", "epm_clearance": "epm_clearance"}


def guard_reason(kind: str, text: str) -> str:
    """The message a guard stop carries: 'guard:<kind>: <text>'."""
    return f"guard:{kind}: {text}"


def parse_guard_reason(message: str):
    """(kind, text) of a guard stop's message, or None for any other message."""
    if not message or not message.startswith("guard:"):
        return None
    kind, _, text = message[len("guard:"):].partition(": ")
    return kind, text


def check_capsule_state(state: np.ndarray, max_speed: float) -> tuple[str, str] | None:
    """(kind, text) if the capsule state [q_wxyz, p, w, v] is not finite or too fast."""
    state = np.asarray(state, dtype=float)
    if not np.all(np.isfinite(state)):
        parts = [name for name, rows in (("orientation", slice(0, 4)),
                                          ("position", slice(4, 7)),
                                          ("angular velocity", slice(7, 10)),
                                          ("velocity", slice(10, 13)))
                 if not np.all(np.isfinite(state[rows]))]
        return "not_finite", f"the capsule's {' and '.join(parts)} became NaN or infinite"
    speed = float(np.linalg.norm(state[10:13]))
    if speed > max_speed:
        return "speed", (f"the capsule moves at {speed:.3g} m/s, faster than the "
                         f"{max_speed:g} m/s a capsule can (guard.max_speed)")
    return None


def check_capsule_in_colon(colon, state: np.ndarray, points_C: np.ndarray,
                           max_excursion: float, wall_allowance: float = 0.0,
                           wall_tears: bool = False) -> tuple[str, str] | None:
    """(kind, text) if the capsule's centre is past one of the colon's ends, or a point of
    its surface is farther than `max_excursion` beyond the wall, and the `wall_allowance`
    a yielding wall gives (the contact model's, physics/contact/). `wall_tears`: the wall
    yields, so a capsule beyond both has torn it ("wall_torn"), not passed through a wall
    the simulation could not hold ("wall")."""
    p_WC = np.asarray(state[4:7], dtype=float)
    centerline = colon.centerline
    s, _, _ = centerline.closest(p_WC)
    for s_end, sign, name in ((0.0, -1.0, "start (s = 0)"),
                              (centerline.length, 1.0, "end")):
        if s == s_end:
            past = sign * float((p_WC - centerline.point_at(s_end)) @ centerline.tangent_at(s_end))
            if past > 0.0:
                return "left_colon", (f"the capsule left the colon through its {name}, "
                                      f"{past * 1000:.1f} mm past it")
    R_WC = rotation_from_quaternion(state[:4])
    points_W = points_C @ R_WC.T + p_WC
    excursion = colon.excursion(points_W, beyond=max_excursion + wall_allowance)
    worst = int(np.argmax(excursion))
    if excursion[worst] > max_excursion + wall_allowance:
        s_worst = float(centerline.closest(points_W[worst])[0])
        if s_worst in (0.0, centerline.length):
            return "left_colon", (f"the capsule sticks out {excursion[worst] * 1000:.1f} mm "
                                  f"past the colon's {'start (s = 0)' if s_worst == 0 else 'end'}")
        if wall_tears:
            return "wall_torn", (
                f"the capsule is {excursion[worst] * 1000:.1f} mm beyond the colon wall's "
                f"undeformed surface at s = {s * 100:.1f} cm, past the "
                f"{wall_allowance * 1000:.3g} mm the wall stretches before it tears and the "
                f"{max_excursion * 1000:g} mm guard.max_wall_excursion: the wall would "
                "have torn (a perforation)")
        given = (f" beyond the {wall_allowance * 1000:.3g} mm the wall gives"
                 if wall_allowance > 0.0 else "")
        return "wall", (f"the capsule is {excursion[worst] * 1000:.1f} mm beyond the colon "
                        f"wall at s = {s * 100:.1f} cm, more than the "
                        f"{max_excursion * 1000:g} mm guard.max_wall_excursion{given}: it "
                        "went through the wall")
    return None


class RunGuard(LeafSystem):
    """Ends the simulation when the capsule's state stops being physical (module docstring).

    .. pydrake_system::

        name: RunGuard
        input_ports:
        - capsule_state

    Input: capsule_state (13): [q_WC (wxyz), p_WC (m), w_WC (rad/s), v_WC (m/s)].

    Args:
        colon: the run's colon (its centreline and wall).
        capsule_radius, capsule_length: the capsule's shape (m).
        config: GuardConfig.
        wall_allowance, wall_tears: the contact model's (check_capsule_in_colon).
    """

    def __init__(self, colon, capsule_radius: float, capsule_length: float,
                 config: GuardConfig | None = None, wall_allowance: float = 0.0,
                 wall_tears: bool = False):
        super().__init__()
        self._colon = colon
        self._config = config or GuardConfig()
        self._wall_allowance = float(wall_allowance)
        self._wall_tears = bool(wall_tears)
        self._points_C = capsule_surface_points_C(capsule_radius, capsule_length)
        self._state_port = self.DeclareVectorInputPort("capsule_state", 13)
        self.DeclarePeriodicPublishEvent(self._config.period, 0.0, self._check_state)
        self.DeclarePeriodicPublishEvent(self._config.wall_period, 0.0, self._check_wall)

    def _stop(self, context, found):
        if found is None:
            return EventStatus.Succeeded()
        kind, text = found
        return EventStatus.ReachedTermination(
            self, guard_reason(kind, f"t = {context.get_time():.3f} s: {text}"))

    def _check_state(self, context):
        state = self._state_port.Eval(context)
        return self._stop(context, check_capsule_state(state, self._config.max_speed))

    def _check_wall(self, context):
        state = self._state_port.Eval(context)
        if check_capsule_state(state, self._config.max_speed) is not None:
            return EventStatus.Succeeded()  # the state check reports it
        return self._stop(context, check_capsule_in_colon(
            self._colon, state, self._points_C, self._config.max_wall_excursion,
            self._wall_allowance, self._wall_tears))
