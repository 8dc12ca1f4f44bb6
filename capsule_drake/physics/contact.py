"""Contact between the capsule and the colon wall: its settings (ContactConfig), their
checks and the contact material (`contact_properties`).

Two models (`ContactConfig.model`): "hydroelastic" registers the wall as rigid hydroelastic
triangle-mesh chunks and the capsule as a compliant hydroelastic capsule; "convex_pieces"
registers ~2,700 convex hulls of wall patches with point contact. A speed-dependent drag on
the capsule's floating joint models the colon's resistance to motion. The scene registers
that geometry (scene_geometry.py).
"""


import dataclasses

from pydrake.geometry import AddContactMaterial, ProximityProperties
from pydrake.multibody.plant import CoulombFriction

from capsule_drake.schema import need_range

CONTACT_MODELS = ("hydroelastic", "convex_pieces")


@dataclasses.dataclass
class ContactConfig:
    """How the capsule touches the colon wall. (Drake's own solver settings, the discrete
    contact approximation among them, are the scenario's `plant`.)"""

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


def check_contact_config(config: ContactConfig) -> None:
    """Raises ValueError naming the first impossible field."""
    if config.model not in CONTACT_MODELS:
        raise ValueError(f"contact.model must be one of {', '.join(CONTACT_MODELS)}, "
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


def contact_properties(config: ContactConfig) -> ProximityProperties:
    """Dissipation, point stiffness and friction of the capsule-wall contact."""
    props = ProximityProperties()
    mu = config.friction
    AddContactMaterial(dissipation=config.hunt_crossley_dissipation,
                       point_stiffness=config.point_stiffness,
                       friction=CoulombFriction(mu, mu), properties=props)
    return props
