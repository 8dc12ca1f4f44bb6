"""The EPM's clearance where the magnet is, not where it was sent: the watch that stops a run
whose magnet comes closer to the skin than its clearance allows.

The guard (guard.py) makes every command safe and the shaper (shaping.py) keeps the way
between commands clear at speeds the carrier can follow; the path drivers' trajectories lie
on the floor. What the carrier then does is physics: a servo lags its reference and gives
under the magnets' pull, an arm's joints bend. `EpmClearanceWatch` reads the EPM's pose as
simulated (`epm.pose`: the plant's body for the servoed stage and the arm, the commanded pose
for the kinematic stage) and ends the run, with one line, the first time the magnet's lowest
point is less than the clearance minus CLEARANCE_TOLERANCE above the highest skin under it
(the guard's own measure, `skin_gap`).
"""

import functools
import math

import numpy as np
from pydrake.systems.framework import EventStatus, LeafSystem

from capsule_drake.capsule.model import capsule_model

from capsule_drake.epm.poses import (highest_skin_under, magnet_footprint_radius,
                                    magnet_vertical_half_extent)
from capsule_drake.io.guard import guard_reason
from capsule_drake.physics.magnetics import dipole_field, dipole_force

CLEARANCE_TOLERANCE = 0.002
"""How far (m) the simulated magnet may come inside its clearance before the run is stopped.
Commands are kept at or above the clearance (the guard, the shaper); the magnet itself lags
and gives: the servoed stage's default servo gives 0.5 mm under a 10 N pull and its
reference's 1 m/s^2 costs it 0.5 mm more (epm/stage.py, check_stage_servo), the arm's joints
bend under the pull. 2 mm is a tenth of the default 20 mm clearance, and less than the skin
itself moves in quiet breathing (a clearance is a margin for that, and for the skin model's
own error); closer than that, the clearance no longer means what the scenario says."""

CHECK_PERIOD = 0.005
"""How often (s) the watch reads the EPM's pose: the shaped EPM moves at most 0.25 m/s on the
servoed stage and 0.2 m/s on the arm by default (about 1 mm a period), a servo's sag under
the magnets' pull builds over tens of milliseconds (the stage's servo: 7-8 Hz)."""


@functools.lru_cache(maxsize=1)
def _capsule_radius() -> float:
    return float(capsule_model().radius)


def closest_approach(epm_magnet, clearance: float) -> float:
    """The nearest (m) the capsule's magnet can come to the EPM's centre: the EPM's lowest
    point is `clearance` over the skin, its centre at least its smallest half size above
    that, and the capsule's magnet (on its axis) at least the capsule's radius under the
    skin."""
    radius = 0.5 * float(epm_magnet.dimensions[0])
    half = radius if epm_magnet.shape == "sphere" else (
        min(radius, 0.5 * float(epm_magnet.dimensions[1])) if epm_magnet.shape == "cylinder"
        else 0.5 * min(epm_magnet.dimensions))
    return clearance + half + _capsule_radius()


def largest_pull(epm_magnet, ipm_magnet, clearance: float) -> tuple[float, float]:
    """(force (N), torque (N m)): the most the capsule's magnet can pull and twist the EPM,
    as point dipoles at their `closest_approach`: the force of two coaxial moments
    (3 mu0 m_a m_c / (2 pi r^4), the largest of any orientation), the torque of the
    capsule's field on its axis turned across the EPM's moment (m_a mu0 m_c / (2 pi r^3)).
    At such distances the point dipole overstates a finite magnet's force (by 61 % coaxial
    at 8 cm, docs/sources.md section 1): a bound for either field model."""
    r = closest_approach(epm_magnet, clearance)
    m_a, m_c = epm_magnet.moment(), ipm_magnet.moment()
    offset = np.array([0.0, 0.0, r])
    force = float(np.linalg.norm(dipole_force([0.0, 0.0, m_a], [0.0, 0.0, m_c], offset)))
    field = float(np.linalg.norm(dipole_field([0.0, 0.0, m_c], offset)))
    return force, m_a * field


def epm_skin_gap(abdomen, pose, geometry) -> float:
    """The gap (m) between the lowest point of the magnet at `pose` [p_WE, m_W] (any
    length of m) and the highest skin under its footprint: the clearance as the guard
    measures it (guard.py), and as the run's metrics report it."""
    p = np.asarray(pose[:3], dtype=float)
    m = np.asarray(pose[3:6], dtype=float)
    m = m / np.linalg.norm(m)
    skin = highest_skin_under(abdomen, p[0], p[1], magnet_footprint_radius(geometry))
    return float(p[2] - magnet_vertical_half_extent(m, geometry) - skin)


def clearance_breach(abdomen, geometry, clearance: float, pose,
                     tolerance: float = CLEARANCE_TOLERANCE) -> str | None:
    """One line saying how far inside its clearance the magnet at `pose` is, or None when
    it is no more than `tolerance` inside (or the pose is not finite: the run guard and the
    command guard answer for that)."""
    pose = np.asarray(pose, dtype=float)
    x, y, z, u, v, w = pose[:6].tolist()   # (plain floats: checked 200 times a second)
    if not math.isfinite(x + y + z + u + v + w) or not u * u + v * v + w * w > 0.0:
        return None
    gap = epm_skin_gap(abdomen, pose, geometry)
    if gap >= clearance - tolerance:
        return None
    where = f"over (x, y) = ({pose[0]:.3f}, {pose[1]:.3f}) m"
    if gap < 0.0:
        return (f"the EPM's magnet is {-gap * 1000:.1f} mm inside the patient {where}: its "
                f"carrier did not keep the {clearance * 1000:g} mm epm.clearance")
    return (f"the EPM's magnet is {gap * 1000:.1f} mm above the skin {where}, inside its "
            f"{clearance * 1000:g} mm epm.clearance by more than the "
            f"{tolerance * 1000:g} mm its carrier is allowed")


class EpmClearanceWatch(LeafSystem):
    """Ends the simulation when the EPM's magnet, where it is, comes inside its clearance by
    more than CLEARANCE_TOLERANCE (module docstring).

    .. pydrake_system::

        name: EpmClearanceWatch
        input_ports:
        - epm_pose

    epm_pose: [p_WE (3), m_hat_W (3)], the EPM as simulated. Read every `period` (s); a
    breach returns Drake's ReachedTermination with the run guard's message form
    (io/guard.py, kind `epm_clearance`), which the run loop turns into the run's ending.

    Args:
        abdomen: the patient's skin (skin_height(x, y)).
        geometry: the EPM's MagnetGeometry.
        clearance: epm.clearance (m).
    """

    def __init__(self, abdomen, geometry, clearance: float, period: float = CHECK_PERIOD):
        super().__init__()
        self._abdomen = abdomen
        self._geometry = geometry
        self._clearance = float(clearance)
        self._pose = self.DeclareVectorInputPort("epm_pose", 6)
        self.DeclarePeriodicPublishEvent(period, 0.0, self._check)

    def _check(self, context):
        found = clearance_breach(self._abdomen, self._geometry, self._clearance,
                                 self._pose.Eval(context))
        if found is None:
            return EventStatus.Succeeded()
        return EventStatus.ReachedTermination(
            self, guard_reason("epm_clearance", f"t = {context.get_time():.3f} s: {found}"))
