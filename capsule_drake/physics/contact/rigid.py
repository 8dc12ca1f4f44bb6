"""The rigid wall: today's stand-in contact, kept for comparison and for the speed runs
(`contact: !RigidWall {}`).

The colon wall does not yield. Two geometries (`RigidWall.model`): "hydroelastic" registers
the wall as rigid hydroelastic triangle-mesh chunks and the capsule with a stiff compliant
layer (5 MPa: a property of the layer, not of the patient); "convex_pieces" registers ~2,700
convex hulls of wall patches with point contact (no pressure field at all). Its friction
(Coulomb 0.2) and its optional drag on the capsule's floating joint are stand-ins too: a
contact figure from this model describes the stand-in, not a patient.
"""


import dataclasses
import math

from pydrake.geometry import Convex
from pydrake.math import RigidTransform

from capsule_drake.anatomy import colon_wall_pieces
from capsule_drake.blocks import block, need
from capsule_drake.physics.contact.common import (add_capsule_drag, add_polyp_hulls,
                                                  add_rigid_hydroelastic_wall,
                                                  contact_properties, set_capsule_properties)
from capsule_drake.schema import need_range

RIGID_GEOMETRIES = ("hydroelastic", "convex_pieces")


@dataclasses.dataclass
class RigidWall:
    """A colon wall that does not yield, the capsule's stiff layer and Coulomb friction: the
    stand-in (module docstring). (Drake's own solver settings, the discrete contact
    approximation among them, are the scenario's `plant`.)"""

    # "hydroelastic" (fidelity): the colon wall is a rigid non-convex triangle mesh split into
    # chunks and the capsule a compliant hydroelastic capsule; contact forces are pressure
    # fields over contact patches. ~3x real time.
    # "convex_pieces" (speed, for long batch runs): the wall is ~2,700 small convex hulls of
    # wall patches and contact is Drake's point contact; ~9-14x real time, but the diagram
    # takes ~15 s and ~2 GB to build, and pieces bridge the sharpest fold feet (the capsule
    # rides up to ~1 mm higher there). Point contact is cheap enough that sampling the
    # plant's outputs is a measurable cost: set plant.use_sampled_output_ports false with it
    # (as the FastContact scenario does).
    model: str = "hydroelastic"
    # Hydroelastic modulus of the capsule's compliant layer (Pa). 5e6 keeps the penetration
    # under a 1 N load near 0.6 mm (measured, docs/sources.md section 6). Engineering assumption.
    capsule_hydroelastic_modulus: float = 5.0e6
    # Edge length of the capsule's tetrahedral pressure mesh (m). Finer costs query time.
    capsule_resolution_hint: float = 0.004
    # Hunt-Crossley dissipation of the contact (s/m). Engineering assumption.
    hunt_crossley_dissipation: float = 5.0
    # convex_pieces: stiffness of each point contact (N/m; capsule and wall in series halve
    # it), and the pieces' axial length and largest chord depth below the round wall (m).
    point_stiffness: float = 2.0e4
    piece_axial_length: float = 0.010
    piece_max_chord_depth: float = 0.0005
    # Coulomb friction between capsule and mucosa (dynamic = static). Measured values span
    # 0.0004-0.054 on small-bowel mucosa; sources.md s. 3 suggests sweeping 0.05-0.3.
    friction: float = 0.2
    # Resistance to the capsule's motion that grows with its speed (tissue drag, mucus; the
    # colon's friction rises with sliding velocity, Gao et al., IEEE Trans. Biomed. Eng.):
    # a linear damping of the capsule's velocity relative to the colon, translational
    # (N s/m) and rotational (N m s/rad), on its floating joint. 0 (default): not modelled,
    # only Coulomb friction resists motion, so a capsule that breaks free accelerates.
    drag_translational: float = 0.0
    drag_rotational: float = 0.0

    def label(self) -> str:
        """How a printed contact figure names the model it comes from."""
        return f"rigid stand-in wall ({self.model})"

    @property
    def pressure_field(self) -> bool:
        """Whether the contact has a pressure field (hydroelastic), or point contact."""
        return self.model == "hydroelastic"

    def step_bound(self, capsule) -> tuple[float, str]:
        """(longest plant step in s, why) of the model's own (physics/step_bound.py): none,
        Drake's contact being implicit."""
        return math.inf, ""

    def wall_allowance(self, capsule_radius: float, colon=None) -> float:
        """The rigid wall gives nothing: the run guard's max_wall_excursion alone."""
        return 0.0

    def wall_tears(self) -> bool:
        """No: a capsule through a wall that does not yield is a simulation that failed
        (the run guard's "wall", a diverged run), not an event of the patient."""
        return False


# Bounds of the contact settings (check_contact_config).
MAX_FRICTION = 2.0
"""Largest Coulomb coefficient: 0.0004-0.054 is measured on mucosa (docs/sources.md section 3),
rubber on dry steel is ~1; beyond 2 is no surface pair."""
MIN_RESOLUTION_HINT = 5e-4
"""Finest capsule pressure mesh (m): its tetrahedra number ~ (capsule size / hint)^3, so
0.5 mm (22 across the 11.6 mm capsule) already costs ~100x the default's query time."""
MIN_PIECE_LENGTH, MIN_CHORD_DEPTH = 5e-3, 1e-4
"""Smallest convex wall pieces (m): the defaults (10 mm, 0.5 mm) cut ~2,700 pieces in a ~15 s
build; the count grows as 1 / length and 1 / sqrt(chord depth), so these give ~12,000."""


def check_rigid_wall_config(config: RigidWall) -> None:
    """Raises ValueError naming the first impossible field."""
    if config.model not in RIGID_GEOMETRIES:
        raise ValueError(f"contact.model must be one of {', '.join(RIGID_GEOMETRIES)}, "
                         f"got {config.model!r}")
    need_range(config.capsule_hydroelastic_modulus, "contact.capsule_hydroelastic_modulus",
               "[1e3, 1e11]", "Pa", "from soft gel to steel")
    need_range(config.capsule_resolution_hint, "contact.capsule_resolution_hint",
               f"[{MIN_RESOLUTION_HINT:g}, 0.02]", "m", "the capsule is 11.6 mm wide")
    need_range(config.hunt_crossley_dissipation, "contact.hunt_crossley_dissipation", ">= 0",
               "s/m")
    need_range(config.point_stiffness, "contact.point_stiffness", "> 0", "N/m")
    need_range(config.piece_axial_length, "contact.piece_axial_length",
               f"[{MIN_PIECE_LENGTH:g}, 0.1]", "m")
    need_range(config.piece_max_chord_depth, "contact.piece_max_chord_depth",
               f"[{MIN_CHORD_DEPTH:g}, 0.005]", "m")
    need_range(config.friction, "contact.friction", f"[0, {MAX_FRICTION:g}]", "",
               "measured on mucosa: 0.0004-0.054")
    need_range(config.drag_translational, "contact.drag_translational", ">= 0", "N s/m")
    need_range(config.drag_rotational, "contact.drag_rotational", ">= 0", "N m s/rad")


def rigid_properties(config: RigidWall):
    """The contact material of every geometry of the rigid model, capsule and wall."""
    return contact_properties(config.friction, config.hunt_crossley_dissipation,
                              config.point_stiffness)


def check_rigid_wall(config: RigidWall, scenario) -> None:
    check_rigid_wall_config(config)
    need(config.model != "convex_pieces" or scenario.colon.procedural,
         "contact.model convex_pieces needs a procedural colon (its pieces are cut from "
         f"the analytic wall), not colon.source {scenario.colon.source_name()}")


def add_rigid_contact(plant, scene_graph, colon_params, colon, config: RigidWall) -> int:
    """Before Finalize, after every other model: the wall's collision geometry (rigid
    hydroelastic chunks, or the convex pieces), the polyps' hulls, the capsule's contact
    properties and its drag. Returns how many wall geometries it registered."""

    def properties():
        return rigid_properties(config)

    if config.model == "convex_pieces":
        count = add_polyp_hulls(plant, colon_params, properties, rigid_hydroelastic=False)
        pieces = colon_wall_pieces(colon_params, config.piece_axial_length,
                                   config.piece_max_chord_depth)
        add_convex_pieces(plant, pieces, properties)
        set_capsule_properties(plant, scene_graph, properties)
        count += len(pieces)
    else:
        count = add_rigid_hydroelastic_wall(plant, colon_params, colon, properties)
        set_capsule_properties(plant, scene_graph, properties,
                               config.capsule_resolution_hint,
                               config.capsule_hydroelastic_modulus)
    add_capsule_drag(plant, config.drag_translational, config.drag_rotational)
    return count


def add_rigid_wall(parts, config: RigidWall) -> None:
    """The "contact" block's models: `add_rigid_contact` in the station."""
    add_rigid_contact(parts.plant, parts.scene_graph, parts.colon_params, parts.colon, config)


def add_convex_pieces(plant, pieces, properties) -> None:
    """The convex pieces of the wall (anatomy/pieces.py), point contact."""
    for i, vertices in enumerate(pieces):
        name = f"colon_piece_{i:04d}"
        plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform(),
                                        Convex(vertices, name), name, properties())


block("contact", RigidWall, check=check_rigid_wall, models=add_rigid_wall, where="")(None)
