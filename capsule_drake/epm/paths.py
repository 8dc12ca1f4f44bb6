"""EPM drivers that need no feedback: a path over the colon, a fixed pose, or a command
from outside the station.

    !AlongColon    the EPM travels over the colon's course (a stage joint trajectory)
    !HoldAbove     the EPM stays above the capsule's start
    !External      the station exports the input `epm.command` [p_WE, m_hat_W]
"""


import dataclasses

from capsule_drake.epm.poses import along_colon_trajectory, hold_above_trajectory
from capsule_drake.scene import block
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


def stage_trajectory(driver, colon, start_s: float, magnet, clearance: float):
    """The stage joint trajectory of a path driver; for any other driver, the EPM's start
    (the default AlongColon's first pose: over the capsule's start). Raises ScenarioError
    when the path is impossible (a HoldAbove height below the clearance)."""
    path = driver if isinstance(driver, (AlongColon, HoldAbove)) else AlongColon()
    make = along_colon_trajectory if isinstance(path, AlongColon) else hold_above_trajectory
    try:
        return make(colon, start_s, path, clearance, magnet)[0]
    except ValueError as e:
        raise ScenarioError(f"scenario: {e}") from None


@block(AlongColon)
@block(HoldAbove)
def add_path_driver(builder, parts, config):
    """The EPM's carrier follows the path's trajectory (`epm_path`)."""
    return parts.epm.mount.follow(builder, parts, parts.epm.trajectory)


@block(External)
def add_external_driver(builder, parts, config):
    """Exports the EPM's pose command input (its guard's, before the carrier) as the
    station's `epm.command` input."""
    port = parts.epm.command_input(builder, parts)
    builder.ExportInput(port, "epm.command")
    return port
