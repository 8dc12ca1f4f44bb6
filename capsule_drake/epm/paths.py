"""EPM drivers that need no feedback: a path over the colon, a fixed pose, or a command
from outside the station.

    !AlongColon    the EPM travels over the colon's course (a stage joint trajectory)
    !HoldAbove     the EPM stays above the capsule's start
    !External      the station exports the input `epm.command` [p_WE, m_hat_W]

Where the EPM starts is decided in one place, `epm_start`: a driver registered with a
`start` (the paths: where their trajectory begins) says so itself; every other driver starts
the EPM over the capsule's start (`start_over_capsule`).
"""


import dataclasses

import numpy as np

from capsule_drake.blocks import block, need, registered
from capsule_drake.epm.poses import (along_colon_trajectory, epm_pose_over,
                                     hold_above_trajectory, stage_joint_positions)
from capsule_drake.schema import ScenarioError, need_range


@dataclasses.dataclass
class AlongColon:
    """The EPM travels over the colon's course at a constant speed, outside the abdomen.

    At each instant it hovers over the centerline point s(t), as low as its clearance from the
    skin allows, with its moment turned so that its field at that centerline point lies along
    the colon's tangent (docs/sources.md section 1: m_E along (3/2 u u^T - I) h), so the capsule's
    magnet, and with it the camera, points down the lumen.
    """

    # Seconds the EPM waits over the capsule's start before moving (the capsule settles).
    settle_time: float = 1.0
    # Travel speed along the centerline (m/s).
    speed: float = 0.01
    # How far ahead of the capsule's start the EPM begins (m).
    lead: float = 0.0
    # Arc length at which the EPM stops (m); 0 means the cecum end of the colon.
    end_s: float = 0.0


@dataclasses.dataclass
class HoldAbove:
    """The EPM stays still, straight above the capsule's start point."""

    # Distance from the capsule's start point up to the EPM's centre (m).
    height: float = 0.5


@dataclasses.dataclass
class External:
    """The EPM follows the station's input port `epm.command` ([p_WE (3), m_hat_W (3)]),
    connected by whoever builds around the station (a script, a notebook, an environment),
    through the EPM's guard (epm/guard.py) as every driver's command."""


def check_path(path) -> None:
    """Raises ValueError naming the first impossible field of a path driver. The EPM's
    trajectory is sampled every 50 ms over settle_time + the colon's length / speed, so
    these bounds keep it under ~150,000 samples (a few seconds to compute; a speed of 1e-9
    m/s once asked for 211 GiB)."""
    if isinstance(path, AlongColon):
        if path.speed != 0:
            need_range(path.speed, "epm.driver.speed", "[0.001, 1]", "m/s",
                       "or 0: the EPM holds over the start; a dragged capsule moves at mm/s "
                       "to cm/s, and slower the path's samples grow as 1 / speed")
        need_range(path.settle_time, "epm.driver.settle_time", "[0, 1000]", "s")
        need_range(path.lead, "epm.driver.lead", "[-1, 1]", "m")
        need_range(path.end_s, "epm.driver.end_s", "[0, 10]", "m",
                   "0: the cecum end; a colon is 1.1-2 m long")
    elif isinstance(path, HoldAbove):
        need_range(path.height, "epm.driver.height", "(0, 2]", "m",
                   "from the capsule's start up to the EPM's centre")


def check_path_driver(path, scenario) -> None:
    check_path(path)
    clearance = scenario.epm.clearance
    need(not isinstance(path, HoldAbove) or path.height > clearance,
         f"epm.driver.height {getattr(path, 'height', None)} m must be above "
         f"epm.clearance ({clearance} m): the skin lies between the capsule and the magnet")


def start_over_capsule(colon, start_s: float, magnet, clearance: float) -> np.ndarray:
    """Stage joints [x y z yaw pitch] over the centreline point at `start_s`, as low as the
    clearance allows, the field there along the colon's tangent: the EPM's start for every
    driver that does not give its own."""
    s = float(np.clip(start_s, 0.0, float(colon.centerline.s[-1])))
    return stage_joint_positions(*epm_pose_over(colon, s, clearance, magnet))


def epm_start(epm, colon, start_s: float) -> np.ndarray:
    """The stage joints [x y z yaw pitch] the EPM of `epm` (EpmConfig) starts at: its
    driver's own start, if its block registers one, or `start_over_capsule`. Raises
    ScenarioError when the driver's start is impossible (a HoldAbove below the clearance)."""
    for item in registered("epm.driver"):
        if isinstance(epm.driver, item.config_type) and item.start is not None:
            return item.start(epm.driver, colon, start_s, epm.magnet, epm.clearance)
    return start_over_capsule(colon, start_s, epm.magnet, epm.clearance)


def path_trajectory(path, colon, start_s: float, magnet, clearance: float):
    """The stage joint trajectory of a path driver (!AlongColon, !HoldAbove). Raises
    ScenarioError when the path is impossible (a HoldAbove height below the clearance)."""
    make = along_colon_trajectory if isinstance(path, AlongColon) else hold_above_trajectory
    try:
        return make(colon, start_s, path, clearance, magnet)[0]
    except ValueError as e:
        raise ScenarioError(f"scenario: {e}") from None


def path_start(path, colon, start_s: float, magnet, clearance: float) -> np.ndarray:
    """Where a path driver's trajectory begins (stage joints)."""
    if isinstance(path, AlongColon):   # its first sample, without sampling the whole path
        return start_over_capsule(colon, start_s + path.lead, magnet, clearance)
    trajectory = path_trajectory(path, colon, start_s, magnet, clearance)
    return trajectory.value(trajectory.start_time()).ravel()


def add_path_driver(builder, parts, path):
    """The EPM's carrier follows the path's trajectory (`epm_path`)."""
    epm = parts.scenario.epm
    trajectory = path_trajectory(path, parts.colon, parts.start_s, epm.magnet, epm.clearance)
    return parts.epm.mount.follow(builder, parts, trajectory)


for _path in (AlongColon, HoldAbove):
    block("epm.driver", _path, check=check_path_driver, start=path_start,
          where="")(add_path_driver)


@block("epm.driver", External)
def add_external_driver(builder, parts, config):
    """Exports the EPM's pose command input (its guard's, before the carrier) as the
    station's `epm.command` input."""
    return parts.export_input(parts.epm.command_input(builder, parts), "epm.command")
