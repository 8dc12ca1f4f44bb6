"""The scene's blocks, in every station, and what each block is given to add itself.

The scene's blocks (registered here, in the station's order of station.py):
    scene           the MultibodyPlant and SceneGraph, the patient's colon (any source,
                    anatomy/source.py) and the capsule (capsule/model.py) at its start;
                    exports capsule.state, body_poses, contact_results, query_object
    colon           the table, the colon's wall (by contact.model) and its visuals
    contact         the capsule's contact properties and drag
    colon.fluid     the residual fluid's buoyancy and drag, when the colon has pools
    applied_forces  the applied forces (the magnet's, the fluid's) into the plant

Every block's `add(builder, parts, config)` receives `StationParts`: the plant, the colon,
the capsule's model and start pose, the EPM (once its mount is added), the station's output
ports by name (`parts.output("capsule.camera.rgb_image")`, the same names a user reads on
the built station) and the build-time values blocks share (`parts.shared("capsule.camera
.lens")`). A block registers itself with `@block` (blocks.py).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import (AddMultibodyPlant, ApplyMultibodyPlantConfig,
                                    ExternallyAppliedSpatialForceMultiplexer, MultibodyPlant)
from pydrake.systems.primitives import ConstantValueSource

from capsule_drake.physics.contact.foundation import no_forces

from capsule_drake.anatomy import ColonParams, ColonSourceError, check_colon_params, load_colon
from capsule_drake.anatomy.course import solve_course
from capsule_drake.anatomy.params import SEGMENT_NAMES
from capsule_drake.anatomy.population import resolve_population
from capsule_drake.anatomy.source import fluid_scene
from capsule_drake.blocks import block, checked, need
from capsule_drake.capsule.model import CAPSULE_BODY, CapsuleModel, capsule_model, start_pose
from capsule_drake.models import configure_parser, model_url
from capsule_drake.physics.contact.tissue import check_tissue_request
from capsule_drake.physics.fluid_force import FluidForce
from capsule_drake.physics.magnetics import check_magnet_geometry
from capsule_drake.scene_geometry import add_colon_visuals
from capsule_drake.schema import ScenarioError, need_range


@dataclasses.dataclass
class StationParts:
    """The station under construction, as its blocks see it."""

    builder: object
    scenario: object               # the Scenario being built (read-only)
    meshcat: object = None
    plant: object = None           # the scene's (set by the scene block's models)
    scene_graph: object = None
    colon: object = None           # a TubeColon: centreline, wall, abdomen
    colon_params: object = None    # the scenario's ColonParams (its source, for workers)
    capsule: CapsuleModel = None   # frames X_BC, X_BM, size, mass
    capsule_instance: object = None
    start_s: float = 0.0           # the capsule's start: arc length along the centreline
    X_WB0: object = None           # the capsule's start pose
    ipm: object = None             # the capsule magnet's MagnetGeometry
    lumen_lookahead: float = 0.05  # the lumen truth's target: this far ahead (m)
    epm: object = None             # EpmParts, once the EPM's mount is added (epm/mount.py)
    magnets: list = dataclasses.field(default_factory=list)   # MagnetSpec of every magnet
    field_model: str = "dipole"
    renderer_for: Callable | None = None   # the camera walls' renderer picker, if any
    parser: object = None          # the plant's Parser (models go in before Finalize)
    # Ports of list[ExternallyAppliedSpatialForce] for the plant (the magnet's, the fluid's):
    # the `applied_forces` block wires them, through a multiplexer when there are several.
    applied_forces: list = dataclasses.field(default_factory=list)
    # A system the applied forces pass through on their way into the plant (input, output
    # ports), when a block needs them all (the compliant wall's implicit force).
    applied_through: tuple | None = None
    start_override: object = None  # a capsule start pose given to make_station
    _outputs: dict = dataclasses.field(default_factory=dict)
    _shared: dict = dataclasses.field(default_factory=dict)

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

    def export_input(self, port, name: str):
        """Exports the input `port` as the station's input `name`."""
        return self.builder.ExportInput(port, name)

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

    def share(self, name: str, value):
        """Makes a build-time value (a lens, a sample rate, a frame) known to later blocks as
        `name` (by convention `<block>.<what>`)."""
        self._shared[name] = value
        return value

    def shared(self, name: str, default=KeyError):
        """The value an earlier block shared as `name` (`default` if none did, when given)."""
        if name not in self._shared:
            if default is KeyError:
                raise KeyError(f"no shared value {name!r} yet (has: {', '.join(self._shared)})")
            return default
        return self._shared[name]

    def shared_values(self) -> dict:
        """Every value the blocks shared (the built station carries them: station.py)."""
        return dict(self._shared)


# --- scene: the plant, the colon, the capsule ----------------------------------------------

MIN_TIME_STEP = 1e-5


def check_scene(scenario, _=None) -> None:
    """The plant's settings, the capsule's magnet (it fits in the shell) and its start."""
    plant = scenario.plant
    checked("", need_range, plant.time_step, "plant.time_step", f">= {MIN_TIME_STEP:g}", "s",
            "a shorter step turns a minute of simulation into days; the convergence "
            "reference is 0.25 ms")
    checked("", need_range, plant.penetration_allowance, "plant.penetration_allowance", "> 0",
            "m")
    checked("", need_range, plant.stiction_tolerance, "plant.stiction_tolerance", "> 0", "m/s")
    checked("", need_range, plant.sap_near_rigid_threshold, "plant.sap_near_rigid_threshold",
            ">= 0")
    try:  # Drake checks its own settings when it applies them (and asserts on some); on a
        # plant of its own: one added to a builder that is never built is never freed
        ApplyMultibodyPlantConfig(plant, MultibodyPlant(plant.time_step))
    except (RuntimeError, ValueError, SystemExit) as e:
        raise ScenarioError(f"scenario: plant: {str(e).strip().splitlines()[0]}") from None
    capsule = scenario.capsule
    checked("capsule.ipm.", check_magnet_geometry, capsule.ipm)
    model = capsule_model()
    diameter, length = 2.0 * model.radius, model.length + 2.0 * model.radius
    ipm = capsule.ipm
    across = {"cylinder": ipm.dimensions[:1], "sphere": ipm.dimensions,
              "cuboid": [math.hypot(*ipm.dimensions[:2])]}[ipm.shape]
    need(max(across) <= diameter and max(ipm.dimensions) <= length,
         f"capsule.ipm must fit in the capsule ({1000 * diameter:.1f} mm wide, "
         f"{1000 * length:.1f} mm long), got a {ipm.shape} of {ipm.dimensions} m")
    half_length = model.half_length
    checked("", need_range, capsule.start_s, "capsule.start_s", f">= {half_length:g}", "m",
            "the capsule's half length: it starts inside the colon")
    if scenario.colon.procedural:
        shortest = sum(scenario.colon.segment(name).length_min for name in SEGMENT_NAMES)
        checked("", need_range, capsule.start_s, "capsule.start_s",
                f"[{half_length:g}, {shortest - half_length:.3f}]", "m",
                "inside the shortest colon the segments' length_min allow")
    checked("", need_range, capsule.settle, "capsule.settle", "[0, 5]", "s",
            "0: no settling; the capsule comes to rest within ~0.5 s")
    checked("", need_range, capsule.lumen_lookahead, "capsule.lumen_lookahead", "(0, 0.5]", "m")


def add_scene_models(parts: StationParts, scenario):
    """The plant (scenario.plant) and scene graph, the colon (scenario.colon), the capsule
    at its start (scenario.capsule.start_s, or the pose given to make_station)."""
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
    plant, scene_graph = AddMultibodyPlant(scenario.plant, parts.builder)
    plant.set_name("plant")
    parser = configure_parser(Parser(plant))
    capsule_instance, = parser.AddModels(url=model_url("capsule.sdf"))
    parts.plant, parts.scene_graph, parts.parser = plant, scene_graph, parser
    parts.colon, parts.colon_params = colon, scenario.colon
    parts.capsule, parts.capsule_instance, parts.start_s = model, capsule_instance, start_s
    parts.X_WB0 = (parts.start_override if parts.start_override is not None
                   else start_pose(colon, start_s))
    parts.ipm, parts.lumen_lookahead = scenario.capsule.ipm, scenario.capsule.lumen_lookahead


@block("scene", check=check_scene, models=add_scene_models)
def add_scene(builder, parts: StationParts, scenario):
    """After Finalize: the capsule starts on the centreline at its start, down the lumen;
    exports capsule.state and the plant's and scene graph's body_poses, contact_results
    and query_object."""
    plant = parts.plant
    if plant.HasJointNamed("capsule_floating"):  # declared with damping (contact's drag)
        plant.GetJointByName("capsule_floating").SetDefaultPose(parts.X_WB0)
    else:
        plant.SetDefaultFloatingBaseBodyPose(parts.capsule_body, parts.X_WB0)
    parts.export(parts.capsule_state, "capsule.state")
    parts.export(plant.get_body_poses_output_port(), "body_poses")
    parts.export(plant.get_contact_results_output_port(), "contact_results")
    parts.export(parts.scene_graph.get_query_output_port(), "query_object")


# --- colon: its visuals (its wall is the contact model's) -----------------------------------

# The fields the procedural colon's course depends on (anatomy/course.py: `solve_course`),
# besides the segments' lengths and diameters.
_COURSE_FIELDS = ("radius_blend_length", "landmark_jitter", "course_smoothing",
                  "centerline_step")
_COURSES_FOUND: dict = {}


def check_colon_course(params: ColonParams) -> None:
    """Raises ValueError (one line) when the procedural course has no room for the given
    anatomy: solves the course once when any of the fields it depends on (the segments'
    lengths and diameters, the landmark jitter and smoothing, the blend and the step) is away
    from its default (the defaults found a course for each seed 0-59). About 0.2 s when the
    course is found; ~10 s for the 40 attempts that fail, which the build would otherwise
    spend before a traceback."""
    default = ColonParams()
    if params.population is not None:   # draws until the course has room (or says why not)
        resolve_population(params, bend=False)
        return

    def anatomy(p):
        return (repr([p.segment(name) for name in SEGMENT_NAMES]),
                tuple(getattr(p, name) for name in _COURSE_FIELDS))

    key = anatomy(params) + (params.seed,)
    if anatomy(params) == anatomy(default) or key in _COURSES_FOUND:
        return
    try:
        solve_course(params, np.random.default_rng(params.seed))
    except RuntimeError:
        raise ValueError(
            f"colon: the procedural course (fixed landmarks) has no room for these segments "
            f"with colon.seed {params.seed}: no course without kinks or overlaps in 40 "
            "attempts (narrower or shorter segments, or a smaller landmark_jitter, fit; "
            "another seed may)") from None
    if len(_COURSES_FOUND) > 100:
        _COURSES_FOUND.clear()
    _COURSES_FOUND[key] = True


def check_colon(params: ColonParams, scenario) -> None:
    check_colon_params(params)
    if params.population is not None:   # the patient's wall (physics/contact/tissue.py)
        check_tissue_request(params.population.tissue, params.population.tissue_percentile)
    if params.procedural:
        check_colon_course(params)


def add_colon_models(parts: StationParts, params: ColonParams):
    """The table and the colon's visuals (its collision geometry is the contact model's,
    physics/contact/). Without a capsule camera every renderer sees the mucosa; a capsule
    camera sees walls of its own (capsule/camera.py, `add_camera_walls`)."""
    parts.parser.AddModels(url=model_url("table.sdf"))
    add_colon_visuals(parts.plant, params, parts.colon,
                      perception=parts.scenario.capsule.camera is None)


block("colon", ColonParams, check=check_colon, models=add_colon_models, where="")(None)


# --- forces on the capsule other than contact ---------------------------------------------

@block("colon.fluid")
def add_fluid(builder, parts: StationParts, scenario):
    """The residual fluid's buoyancy and drag on the capsule (colon.lumen), when the colon
    has pools (physics/fluid_force.py)."""
    pools = fluid_scene(parts.colon_params).pools if parts.colon_params.lumen else []
    if pools:
        plant = parts.plant
        force = builder.AddNamedSystem("fluid_force", FluidForce(
            parts.capsule_body, parts.colon, pools, parts.capsule.radius, parts.capsule.length,
            parts.gravity))
        builder.Connect(plant.get_body_poses_output_port(), force.GetInputPort("body_poses"))
        builder.Connect(plant.get_body_spatial_velocities_output_port(),
                        force.GetInputPort("body_spatial_velocities"))
        parts.applied_forces.append(force.GetOutputPort("applied_spatial_force"))
        parts.export(force.GetOutputPort("submerged"), "capsule.submerged")


@block("applied_forces")
def connect_applied_forces(builder, parts: StationParts, scenario):
    """The applied forces (`parts.applied_forces`) into the plant: one directly, several
    through an ExternallyAppliedSpatialForceMultiplexer."""
    ports = parts.applied_forces
    into = parts.plant.get_applied_spatial_force_input_port()
    if parts.applied_through is not None:   # the forces pass through a system first
        into, out = parts.applied_through
        builder.Connect(out, parts.plant.get_applied_spatial_force_input_port())
        if not ports:
            none = builder.AddNamedSystem("applied_forces", ConstantValueSource(no_forces()))
            builder.Connect(none.get_output_port(), into)
            return
    if not ports:
        return
    if len(ports) == 1:
        builder.Connect(ports[0], into)
        return
    mux = builder.AddNamedSystem("applied_forces",
                                 ExternallyAppliedSpatialForceMultiplexer(len(ports)))
    for k, port in enumerate(ports):
        builder.Connect(port, mux.get_input_port(k))
    builder.Connect(mux.get_output_port(), into)
