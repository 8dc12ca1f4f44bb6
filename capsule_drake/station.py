"""The capsule station: the one place that builds the diagram, block by block.

    make_station(scenario, meshcat=None) -> Diagram

Every block is a module with its LeafSystem(s) and an `add_<block>(builder, parts, config)`
that adds it, connects it to the blocks before it by their exported port names and exports
its own as `<instance>.<signal>` (README, "The diagram", lists them). The scene (plant,
scene graph, colon, capsule, table, contact) and the EPM's carrier are in every station;
every other block is there when its field of the scenario is set, and is added in the
scenario's order (scenario.py), the EPM's driver last.

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
and epm.status (the arm's controller's report).
"""

from __future__ import annotations

import dataclasses
import types

from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.capsule.camera import add_camera_walls
from capsule_drake.epm.mount import add_epm_models, add_epm_mount, add_epm_pose
from capsule_drake.io.visualization import add_meshcat
from capsule_drake.physics.magnet_force import add_magnet_force, export_magnet_outputs
from capsule_drake.scenario import Scenario
from capsule_drake.scene import (add_block, add_fluid, add_scene, add_table_and_colon,
                                 connect_applied_forces, finish_capsule, is_block,
                                 set_capsule_start)


SCENE_CONFIGS = ("plant", "simulator", "colon", "contact")
"""The scenario's fields that the scene (scene.py add_scene) and the run take whole: no
blocks inside them (the colon's `source` is how the colon is drawn, not a block)."""


def blocks_of(config, skip=SCENE_CONFIGS):
    """The block configs in `config` (a scenario or part of one), depth first in field
    order: each set field whose type a block module registered (scene.block), the fields
    named in `skip` aside. A field that may be null (`X | None`) is a block that may be
    absent: its type must be registered."""
    for item in dataclasses.fields(config):
        value = getattr(config, item.name)
        if value is None or item.name in skip:
            continue
        if is_block(value):
            yield value
        elif dataclasses.is_dataclass(value):
            if isinstance(item.type, types.UnionType) and type(None) in item.type.__args__:
                raise TypeError(f"{type(config).__name__}.{item.name}: no block registered "
                                f"for {type(value).__name__} (scene.block)")
            yield from blocks_of(value, skip=())


def make_station(scenario: Scenario, meshcat=None, capsule_start: RigidTransform | None = None):
    """Builds the diagram for `scenario`; adds Meshcat visualisation only if `meshcat` is
    given. Nothing is simulated and the scenario is not modified.

    Args:
        capsule_start: the capsule's start pose X_WB0, if not the scenario's (on the
            centreline at capsule.start_s). A run with capsule.settle > 0 settles the capsule
            first (app/run.py, settled_start) and passes where it came to rest.
    """
    builder = DiagramBuilder()
    parts = add_scene(builder, scenario, meshcat)
    if capsule_start is not None:
        parts.X_WB0 = capsule_start
    add_epm_models(parts, scenario.epm)
    camera = scenario.capsule.camera
    add_table_and_colon(parts, scenario, perception=camera is None)
    if camera is not None:  # after every other model: the camera sees only these walls
        parts.renderer_for = add_camera_walls(parts.plant, parts.scene_graph, scenario.colon,
                                              parts.colon, camera)
    finish_capsule(parts, scenario.contact)
    parts.plant.Finalize()

    set_capsule_start(parts)
    add_epm_mount(builder, parts, scenario.epm)
    force = add_magnet_force(builder, parts, scenario.magnet_force)
    add_fluid(builder, parts)
    connect_applied_forces(builder, parts)
    parts.export(parts.capsule_state, "capsule.state")
    add_epm_pose(builder, parts)
    for config in blocks_of(scenario):   # sensors, perception, guidance; the driver last
        add_block(builder, parts, config)
    export_magnet_outputs(parts, force)
    parts.export(parts.plant.get_body_poses_output_port(), "body_poses")
    parts.export(parts.plant.get_contact_results_output_port(), "contact_results")
    parts.export(parts.scene_graph.get_query_output_port(), "query_object")
    if meshcat is not None:
        add_meshcat(builder, parts, scenario.outputs.visual_period)
    diagram = builder.Build()
    diagram.set_name("capsule_station")
    return diagram
