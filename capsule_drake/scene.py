"""What every station has, and what each block is given to add itself.

`add_scene` puts the parts present in every scenario into a builder: the MultibodyPlant and
SceneGraph, the patient's colon (any source, anatomy/source.py), the capsule
(capsule/model.py) with its contact, and the table. It returns `StationParts`, which every
block's `add_<block>(builder, parts, config)` receives: the plant, the colon, the capsule's
model and start pose, the EPM (once its mount is added), and the station's output ports by
name (`parts.output("capsule.camera.rgb_image")`), so that a block connects to the blocks
before it by the same names a user reads on the built station.

A block registers its add function for its config type with `@block(ConfigType)`; the
station adds every config of a registered type that the scenario holds, in the scenario's
order (station.py).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, ExternallyAppliedSpatialForceMultiplexer

from capsule_drake.anatomy import ColonSourceError, load_colon
from capsule_drake.anatomy.source import fluid_scene
from capsule_drake.capsule.model import CAPSULE_BODY, CapsuleModel, capsule_model, start_pose
from capsule_drake.models import configure_parser, model_url
from capsule_drake.physics.fluid_force import add_fluid_force
from capsule_drake.physics.contact import (add_capsule_drag, add_colon_visuals, add_colon_wall,
                                           set_capsule_contact)
from capsule_drake.schema import ScenarioError


@dataclasses.dataclass
class StationParts:
    """The station under construction, as its blocks see it."""

    builder: object
    plant: object
    scene_graph: object
    colon: object                  # a TubeColon: centreline, wall, abdomen
    colon_params: object           # the scenario's ColonParams (its source, for workers)
    capsule: CapsuleModel          # frames X_BC, X_BM, size, mass
    capsule_instance: object
    start_s: float                 # the capsule's start: arc length along the centreline
    X_WB0: object                  # the capsule's start pose
    ipm: object                    # the capsule magnet's MagnetGeometry
    lumen_lookahead: float         # the lumen truth's target: this far ahead (m)
    meshcat: object = None
    epm: object = None             # EpmParts, once the EPM's mount is added (epm/mount.py)
    magnets: list = dataclasses.field(default_factory=list)   # MagnetSpec of every magnet
    field_model: str = "dipole"
    renderer_for: Callable | None = None   # the camera walls' renderer picker, if any
    parser: object = None          # the plant's Parser (models go in before Finalize)
    # Ports of list[ExternallyAppliedSpatialForce] for the plant (the magnet's, the fluid's):
    # `connect_applied_forces` wires them, through a multiplexer when there are several.
    applied_forces: list = dataclasses.field(default_factory=list)
    _outputs: dict = dataclasses.field(default_factory=dict)

    @property
    def gravity(self) -> float:
        """|g| of the plant (m/s^2): the one value of gravity in a station."""
        return float(np.linalg.norm(self.plant.gravity_field().gravity_vector()))

    @property
    def capsule_body(self):
        return self.plant.GetBodyByName(CAPSULE_BODY, self.capsule_instance)

    @property
    def capsule_state(self):
        """The capsule's state output [q_WB, p_WB, w_WB, v_WB] (13)."""
        return self.plant.get_state_output_port(self.capsule_instance)

    def export(self, port, name: str):
        """Exports `port` as the station's output `name` and remembers it for later blocks."""
        self.builder.ExportOutput(port, name)
        self._outputs[name] = port
        return port

    def export_outputs(self, system, prefix: str, names=None):
        """Exports the system's output ports (all, or `names`) as `<prefix>.<port name>`."""
        for i in range(system.num_output_ports()):
            port = system.get_output_port(i)
            if names is None or port.get_name() in names:
                self.export(port, f"{prefix}.{port.get_name()}")

    def has(self, name: str) -> bool:
        return name in self._outputs

    def output(self, name: str):
        """The station output `name` exported by an earlier block. The scenario's checks
        make sure it exists; a block asking for one that does not is a bug."""
        if name not in self._outputs:
            raise KeyError(f"no station output {name!r} yet (has: {', '.join(self._outputs)})")
        return self._outputs[name]


_BLOCKS: dict[type, Callable] = {}


def block(config_type: type):
    """Decorator: registers `add(builder, parts, config)` as the block for `config_type`."""
    def register(add):
        _BLOCKS[config_type] = add
        return add
    return register


def is_block(config) -> bool:
    return type(config) in _BLOCKS


def add_block(builder, parts: StationParts, config):
    """Adds the block that `config` configures."""
    return _BLOCKS[type(config)](builder, parts, config)


def add_scene(builder, scenario, meshcat=None) -> StationParts:
    """Adds the plant (scenario.plant), the colon (scenario.colon) with its contact
    (scenario.contact), the capsule at its start (scenario.capsule.start_s) and the table.
    Models are added, the plant is not finalised: the EPM's mount and the camera's walls
    come next (station.py)."""
    try:
        colon, _ = load_colon(scenario.colon)
    except ColonSourceError as e:
        raise ScenarioError(f"scenario: {e}") from None
    model = capsule_model()
    start_s = scenario.capsule.start_s
    if not model.half_length <= start_s <= colon.centerline.length - model.half_length:
        raise ScenarioError(
            f"scenario: capsule.start_s {start_s} m is outside this colon (the capsule "
            f"fits between {model.half_length:.4f} and "
            f"{colon.centerline.length - model.half_length:.3f} m)")
    plant, scene_graph = AddMultibodyPlant(scenario.plant, builder)
    plant.set_name("plant")
    parser = configure_parser(Parser(plant))
    capsule_instance, = parser.AddModels(url=model_url("capsule.sdf"))
    parts = StationParts(builder, plant, scene_graph, colon, scenario.colon, model,
                         capsule_instance, start_s, start_pose(colon, start_s),
                         scenario.capsule.ipm, scenario.capsule.lumen_lookahead, meshcat,
                         parser=parser)
    return parts


def add_table_and_colon(parts: StationParts, scenario, perception: bool):
    """The table, and the colon's wall (by scenario.contact's model) and visuals.
    `perception`: the mucosa is seen by every renderer (no capsule camera: a capsule camera
    sees walls of its own: capsule/camera.py, `add_camera_walls`)."""
    parts.parser.AddModels(url=model_url("table.sdf"))
    add_colon_wall(parts.plant, scenario.contact, scenario.colon, parts.colon)
    add_colon_visuals(parts.plant, scenario.colon, parts.colon, perception=perception)


def finish_capsule(parts: StationParts, contact):
    """Before Finalize, after every model: the capsule's contact properties and drag."""
    set_capsule_contact(parts.plant, parts.scene_graph, contact)
    add_capsule_drag(parts.plant, contact)


def add_fluid(builder, parts: StationParts):
    """The residual fluid's buoyancy and drag on the capsule (colon.lumen), when the colon
    has pools (physics/fluid_force.py)."""
    pools = fluid_scene(parts.colon_params).pools if parts.colon_params.lumen else []
    if pools:
        force = add_fluid_force(builder, parts, pools)
        parts.applied_forces.append(force.GetOutputPort("applied_spatial_force"))
        parts.export(force.GetOutputPort("submerged"), "capsule.submerged")


def connect_applied_forces(builder, parts: StationParts):
    """The applied forces (`parts.applied_forces`) into the plant: one directly, several
    through an ExternallyAppliedSpatialForceMultiplexer."""
    ports = parts.applied_forces
    if not ports:
        return
    if len(ports) == 1:
        builder.Connect(ports[0], parts.plant.get_applied_spatial_force_input_port())
        return
    mux = builder.AddNamedSystem("applied_forces",
                                 ExternallyAppliedSpatialForceMultiplexer(len(ports)))
    for k, port in enumerate(ports):
        builder.Connect(port, mux.get_input_port(k))
    builder.Connect(mux.get_output_port(), parts.plant.get_applied_spatial_force_input_port())


def set_capsule_start(parts: StationParts):
    """After Finalize: the capsule starts on the centreline at its start, down the lumen."""
    plant = parts.plant
    if plant.HasJointNamed("capsule_floating"):  # declared with damping (add_capsule_drag)
        plant.GetJointByName("capsule_floating").SetDefaultPose(parts.X_WB0)
    else:
        plant.SetDefaultFloatingBaseBodyPose(parts.capsule_body, parts.X_WB0)
