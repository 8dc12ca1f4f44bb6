"""The capsule station: the one place that builds the diagram, block by block.

    make_station(scenario, meshcat=None) -> Diagram

Every part of the diagram is a block (blocks.py): a module registers its config type, its
check and its add together, and the station adds the blocks `STATION_BLOCKS` names
(scenario.py, beside the fields that hold their configs), in that order, each whose config
the scenario holds: first every block's models (before the plant is finalised), then every
block's systems. A block connects to the blocks before it by their exported port names and
exports its own as `<instance>.<signal>` (docs/diagram.md, "The order and the exported
ports", lists them). The scene (plant, scene graph, colon, capsule, table, contact), the
magnet force and the EPM's carrier are in every station; every other block is there when its
field of the scenario is set; the EPM's driver comes last but for Meshcat.

Exported in every station:
    capsule.state          [q_WB (wxyz), p_WB, w_WB, v_WB] of the capsule body
    capsule.ipm_field_B    field at the IPM in the capsule frame (T): a magnetometer's truth
    epm.pose               the EPM's centre and moment direction [p_WE, m_hat_W]
    epm.state              the carrier's joint state: stage [x y z yaw pitch, rates], or
                           the arm's [q (7), v (7)]
    epm.desired_state      the carrier's commanded joint state
    epm.F_W                spatial force on the EPM at its centre, world frame [torque; force]
    epm.guard_counts       the EPM guard's counts [commands, raised, clamped, rejected]:
                           every pose command passes the guard (epm/guard.py)
    body_poses, contact_results, query_object   the plant's and scene graph's
and with some drivers epm.command (the pose command, an output; an input with !External)
and epm.status (the arm's controller's report); on the compliant wall's foundation route,
contact.wall (its own contact, physics/contact/foundation.py WallContact).

Besides its ports, a built station carries the build-time values its blocks shared
(`parts.share`), for the application beside it to read with `station_value(station, name)`:
    scene.plant                  the MultibodyPlant (bodies, frames, time step)
    capsule.camera.lens|config|tick|latency|render_worker   with a camera
    capsule.lumen.truth_at|far_at                            the lumen truth's functions
    teleop.device.address        a network device's address(): (host, port) it listens on
    meshcat.flush_trail|replay_frames    with Meshcat: flush_trail(t), replay_frames()
The application never looks a system up by its name (tests/test_blocks.py).
"""

from __future__ import annotations

from types import MappingProxyType

from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder

from capsule_drake import blocks
from capsule_drake.scene import StationParts
from capsule_drake.scenario import STATION_BLOCKS


def make_station(scenario, meshcat=None, capsule_start: RigidTransform | None = None,
                 systems_of: dict | None = None):
    """Builds the diagram for `scenario`; adds Meshcat visualisation only if `meshcat` is
    given. Nothing is simulated and the scenario is not modified.

    Args:
        capsule_start: the capsule's start pose X_WB0, if not the scenario's (on the
            centreline at capsule.start_s). A run with capsule.settle > 0 settles the capsule
            first (app/run.py, settled_start) and passes where it came to rest.
        systems_of: if given, filled with {block name: [names of the systems it added]}.
    """
    builder = DiagramBuilder()
    parts = StationParts(builder, scenario, meshcat, start_override=capsule_start)
    present = blocks.present(STATION_BLOCKS, scenario)

    def each(hook: str, *args):
        for item, config in present:
            function = getattr(item, hook)
            if function is None:
                continue
            before = len(builder.GetSystems())
            function(*args, config)
            if systems_of is not None:
                systems_of.setdefault(item.name, []).extend(
                    s.get_name() for s in builder.GetSystems()[before:])

    each("models", parts)     # models and geometry, before the plant is finalised
    parts.plant.Finalize()
    each("add", builder, parts)
    parts.share("scene.plant", parts.plant)
    diagram = builder.Build()
    diagram.set_name("capsule_station")
    diagram.shared_values = MappingProxyType(dict(parts.shared_values()))
    return diagram


def station_value(station, name: str, default=KeyError):
    """The build-time value the station's blocks shared as `name` (module docstring), or
    `default` when none did (KeyError when no default is given)."""
    values = station.shared_values
    if name in values:
        return values[name]
    if default is KeyError:
        raise KeyError(f"the station shared no {name!r} (has: {', '.join(values)})")
    return default
