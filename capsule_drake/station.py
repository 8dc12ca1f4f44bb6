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
    body_poses, contact_results, query_object   the plant's and scene graph's
and with some drivers epm.command (the pose command, an output; an input with !External)
and epm.status (the arm's controller's report).
"""

from __future__ import annotations

import copy
import dataclasses
import types

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.anatomy import load_colon
from capsule_drake.capsule.camera import add_camera_walls
from capsule_drake.epm.mount import add_epm_models, add_epm_mount, add_epm_pose
from capsule_drake.epm.paths import External, stage_trajectory
from capsule_drake.epm.poses import stage_to_pose
from capsule_drake.epm.stage import Stage
from capsule_drake.io.visualization import add_meshcat
from capsule_drake.physics.magnet_force import add_magnet_force, export_magnet_outputs
from capsule_drake.scenario import CapsuleConfig, Scenario
from capsule_drake.scene import (add_block, add_scene, add_table_and_colon, finish_capsule,
                                 is_block, set_capsule_start)


def blocks_of(config):
    """The block configs in `config` (a scenario or part of one), depth first in field
    order: each set field whose type a block module registered (scene.block). A field that
    may be null (`X | None`) is a block that may be absent: its type must be registered."""
    for item in dataclasses.fields(config):
        value = getattr(config, item.name)
        if value is None:
            continue
        if is_block(value):
            yield value
        elif dataclasses.is_dataclass(value):
            if isinstance(item.type, types.UnionType) and type(None) in item.type.__args__:
                raise TypeError(f"{type(config).__name__}.{item.name}: no block registered "
                                f"for {type(value).__name__} (scene.block)")
            yield from blocks_of(value)


SETTLE_STEP = 5e-4
"""Plant step of the settling (s): where the capsule's first snap onto the wall, at
0.5-0.6 m/s, stays within 0.6 mm of it (README, Performance)."""


def make_station(scenario: Scenario, meshcat=None):
    """Builds the diagram for `scenario`; adds Meshcat visualisation only if `meshcat` is
    given. The scenario is not modified; nothing is simulated but, with capsule.settle,
    the settling of the capsule's start (settled_start)."""
    builder = DiagramBuilder()
    parts = add_scene(builder, scenario, meshcat)
    if scenario.capsule.settle > 0.0:
        parts.X_WB0 = settled_start(scenario)
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


def settled_start(scenario: Scenario) -> RigidTransform:
    """Where the capsule comes to rest when let settle (capsule.settle): the scenario's
    physics alone (its colon, contact, magnets; no sensors, no driver) simulated for
    `capsule.settle` seconds at SETTLE_STEP, the capsule starting on the centreline and the
    EPM held, on the kinematic stage, at the pose the run starts it at. The run then starts
    there, at rest. Cached: stations of the same physics settle once per process."""
    physics = copy.deepcopy(scenario)
    physics.capsule = CapsuleConfig(start_s=scenario.capsule.start_s,
                                    ipm=scenario.capsule.ipm)
    physics.pseudo_force = None
    physics.epm.mount, physics.epm.driver = Stage(), External()
    physics.plant.time_step = SETTLE_STEP
    colon, _ = load_colon(scenario.colon)
    epm_start = stage_to_pose(stage_trajectory(
        scenario.epm.driver, colon, scenario.capsule.start_s, scenario.epm.magnet,
        scenario.epm.clearance).value(0.0).ravel())
    key = (repr(physics), scenario.capsule.settle, tuple(epm_start))
    if key not in _SETTLED:
        diagram = make_station(physics)
        simulator = Simulator(diagram)
        context = simulator.get_mutable_context()
        diagram.GetInputPort("epm.command").FixValue(context, epm_start)
        simulator.AdvanceTo(scenario.capsule.settle)
        state = diagram.GetOutputPort("capsule.state").Eval(context)
        if len(_SETTLED) >= 16:
            _SETTLED.clear()
        _SETTLED[key] = RigidTransform(Quaternion(state[:4] / np.linalg.norm(state[:4])),
                                       state[4:7])
    return _SETTLED[key]


_SETTLED: dict = {}
