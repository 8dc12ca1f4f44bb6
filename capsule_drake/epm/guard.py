"""The EPM's guard: what keeps a command off the patient and within the carrier's reach.

`EpmGuard` is the arithmetic (the clearance floor over the skin, the arm's reach);
`EpmCommandGuard` is the system every pose command passes through on its way to the EPM's
carrier, whichever driver produced it (epm/mount.py puts it there): it makes the command safe
and counts what it had to do, exported as `epm.guard_counts` (GUARD_COUNTS).
"""

import numpy as np
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem

from capsule_drake.epm.poses import (disc_samples, highest_skin_under,
                                    magnet_footprint_radius, magnet_vertical_half_extent,
                                    vertical_half_extents)


class EpmGuard:
    """Keeps an EPM command safe and within reach: the magnet's lowest point at least
    `clearance` above the highest skin under it, its centre within `reach` of the shoulder.
    `apply(p, m)` returns (p_safe, m_hat, raised (bool), pulled_in (bool))."""

    def __init__(self, abdomen, geometry, clearance: float, shoulder_W: np.ndarray,
                 reach: float):
        self.abdomen = abdomen
        self.geometry = geometry
        self.clearance = clearance
        self.shoulder_W = np.asarray(shoulder_W, dtype=float)
        self.reach = reach
        self._footprint = magnet_footprint_radius(geometry)

    def lowest_centre_height(self, x: float, y: float, m_hat: np.ndarray) -> float:
        skin = highest_skin_under(self.abdomen, x, y, self._footprint)
        return skin + self.clearance + magnet_vertical_half_extent(m_hat, self.geometry)

    def lowest_centre_heights(self, x, y, m_hat) -> np.ndarray:
        """`lowest_centre_height` over many points at once: x, y (N), unit moments (N, 3)."""
        dx, dy = disc_samples(self._footprint)
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        skin = np.max(self.abdomen.skin_height(x[:, None] + dx, y[:, None] + dy), axis=1)
        return skin + self.clearance + vertical_half_extents(m_hat, self.geometry)

    def apply(self, p_WE, m_hat_W):
        p = np.array(p_WE, dtype=float)
        m = np.asarray(m_hat_W, dtype=float)
        m = m / np.linalg.norm(m)
        pulled_in = False
        offset = p - self.shoulder_W
        distance = np.linalg.norm(offset)
        if distance > self.reach:
            p = self.shoulder_W + offset * (self.reach / distance)
            pulled_in = True
        floor = self.lowest_centre_height(p[0], p[1], m)
        raised = bool(p[2] < floor)
        if raised:
            p[2] = floor
        return p, m, raised, pulled_in


def floor_guard(abdomen, geometry, clearance: float) -> EpmGuard:
    """The guard of the clearance alone (no reach limit): what a driver uses to know how low
    the EPM may go (`lowest_centre_height(x, y, m_hat)`)."""
    return EpmGuard(abdomen, geometry, clearance, np.zeros(3), np.inf)


GUARD_COUNTS = ("commands", "raised", "clamped", "rejected")
"""The layout of `epm.guard_counts`, each a count of commands since the start: every new
command the guard received (a new value, sampled at the plant's step); those raised to the
clearance floor; those whose centre was pulled into the workspace (or whose moment was
rescaled); those rejected (not finite, or no moment direction), for which the last safe
command was held."""

RAISE_SLACK = 1e-9
"""How far below the clearance floor (m) a command passes untouched: the floor computed from
a moment that differs from the driver's in its last bits may lie an ulp above the height the
driver computed from its own."""

MIN_MOMENT_NORM = 1e-9
"""A moment direction shorter than this has no direction: the command is rejected (the
carriers held on such a command before the guard, epm/stage.py, epm/arm.py)."""

WORKSPACE_MARGIN = 1.0
"""The workspace (m): the box around the colon's centreline grown by this much on every side
(a stage or an arm beside the table reaches no farther; the magnet's pull there is nil) ..."""
WORKSPACE_HEADROOM = 2.0
"""... and by this much above it (m): room above every floor (skin + clearance, at most
0.5 m, + the magnet's half size) and every !HoldAbove height (at most 2 m)."""


def command_workspace(colon):
    """(low, high): the box (world, m) the EPM's commanded centre is kept in."""
    points = np.asarray(colon.centerline.points, dtype=float)
    margin = np.array([WORKSPACE_MARGIN, WORKSPACE_MARGIN, WORKSPACE_MARGIN])
    return (points.min(axis=0) - margin,
            points.max(axis=0) + [WORKSPACE_MARGIN, WORKSPACE_MARGIN, WORKSPACE_HEADROOM])


def safe_command(guard: EpmGuard, workspace, command):
    """The command made safe: (command, raised, clamped), or None to reject it (not finite,
    not 6 values, no moment direction). Its centre is clipped into the `workspace` box
    (low, high), then raised to `guard`'s clearance floor (more than RAISE_SLACK below it).
    A command that needs neither comes back as the same array, bit for bit; otherwise only
    what was clamped or raised changes (the moment stays as given, the carriers make it
    unit), except a moment whose length overflows, which is made unit (and counted
    clamped)."""
    command = np.asarray(command, dtype=float)
    if command.shape != (6,) or not np.all(np.isfinite(command)):
        return None
    m = command[3:]
    with np.errstate(over="ignore"):
        norm = np.linalg.norm(m)
    rescaled = not np.isfinite(norm)
    if rescaled:  # finite components whose length overflows: its direction still holds
        m = m / np.max(np.abs(m))
        norm = np.linalg.norm(m)
    if not norm > MIN_MOMENT_NORM:
        return None
    m_hat = m / norm   # as EpmGuard.apply makes it: the same floor to the last bit
    low, high = workspace
    p = np.clip(command[:3], low, high)
    clamped = rescaled or bool(np.any(p != command[:3]))
    floor = guard.lowest_centre_height(p[0], p[1], m_hat)
    raised = bool(p[2] < floor - RAISE_SLACK)
    if not clamped and not raised:
        return command, False, False
    if raised:
        p[2] = floor
    return np.concatenate([p, m_hat if rescaled else command[3:]]), raised, clamped


class EpmCommandGuard(LeafSystem):
    """Between every pose-command driver and the EPM's carrier: each command made safe
    (`safe_command`), a rejected one replaced by the last safe command (at first, the
    EPM's start), and counted.

    .. pydrake_system::

        name: EpmCommandGuard
        input_ports:
        - epm_command
        output_ports:
        - epm_command
        - counts

    epm_command (in): [p_WE (3), m_hat_W (3)] from the driver; may be left unconnected (a
    path driver drives the carrier's joints instead): nothing is guarded then, the counts
    stay 0. epm_command (out): the safe command, at once (direct feedthrough: the carrier
    sees it at the same instant as it would the driver's). counts: GUARD_COUNTS, updated
    every `period` (s; the stations use the plant's step, the finest at which the EPM can
    act) once a driver is connected (`watch`), where a command is counted once per new value.

    Args:
        guard: an EpmGuard (its clearance floor; its reach is not used).
        workspace: (low, high), the box the centre is kept in (`command_workspace`).
        start_command: the EPM's pose at the start, [p_WE, m_hat_W].
        period: s.
    """

    def __init__(self, guard: EpmGuard, workspace, start_command, period: float):
        super().__init__()
        self._guard = guard
        self._workspace = tuple(np.asarray(w, dtype=float) for w in workspace)
        start = safe_command(guard, self._workspace, start_command)
        if start is None:
            raise ValueError(f"the EPM's start command {start_command} is not a pose")
        self._input = self.DeclareVectorInputPort("epm_command", 6)
        # [last safe command (6), last command received (6), counts (GUARD_COUNTS)]
        initial = np.concatenate([start[0], np.full(6, np.nan), np.zeros(len(GUARD_COUNTS))])
        self._state = self.DeclareDiscreteState(BasicVector(initial))
        self.DeclareVectorOutputPort(
            "epm_command", 6, self._calc_command,
            {self.input_port_ticket(self._input.get_index()), self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "counts", len(GUARD_COUNTS),
            lambda context, output: output.SetFromVector(
                context.get_discrete_state(self._state).value()[12:]),
            {self.xd_ticket()})
        self._period = float(period)
        self._watching = False
        self._last = None   # (command bytes, safe_command's answer): commands repeat

    def watch(self) -> None:
        """Starts counting (once a driver's command is connected): no update event runs in
        a station whose driver sends no pose command, at every plant step."""
        if not self._watching:
            self._watching = True
            self.DeclarePeriodicDiscreteUpdateEvent(self._period, 0.0, self._update)

    def _safe(self, command):
        key = command.tobytes()
        if self._last is None or self._last[0] != key:
            self._last = (key, safe_command(self._guard, self._workspace, command))
        return self._last[1]

    def _calc_command(self, context, output):
        command = np.asarray(self._input.Eval(context), dtype=float)
        safe = self._safe(command)
        output.SetFromVector(safe[0] if safe is not None
                             else context.get_discrete_state(self._state).value()[:6])

    def _update(self, context, discrete_state):
        # Nothing new (no driver, or the command of last time, counted, its safe form kept):
        # the state is left as it is, and what depends on it stays valid.
        if not self._input.HasValue(context):
            return EventStatus.DidNothing()
        x = context.get_discrete_state(self._state).value()
        command = np.asarray(self._input.Eval(context), dtype=float)
        if x[12] > 0 and command.tobytes() == x[6:12].tobytes():
            return EventStatus.DidNothing()
        x = x.copy()
        x[6:12] = command
        safe = self._safe(command)
        counts = x[12:]
        counts[0] += 1.0
        if safe is None:
            counts[3] += 1.0
        else:
            x[:6] = safe[0]
            counts[1] += float(safe[1])
            counts[2] += float(safe[2])
        discrete_state.set_value(self._state, x)
        return EventStatus.Succeeded()
