"""The EPM's guard: what keeps a command off the patient and within the carrier's reach."""

import numpy as np

from capsule_drake.epm.poses import (highest_skin_under, magnet_footprint_radius,
                                    magnet_vertical_half_extent)


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
