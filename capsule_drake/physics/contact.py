"""Contact between the capsule and the colon wall: its settings and the geometry it needs.

Two models (`ContactConfig.model`): "hydroelastic" registers the wall as rigid hydroelastic
triangle-mesh chunks and the capsule as a compliant hydroelastic capsule; "convex_pieces"
registers ~2,700 convex hulls of wall patches with point contact. A speed-dependent drag on
the capsule's floating joint models the colon's resistance to motion.
"""


import dataclasses

import numpy as np
from pydrake.geometry import (AddCompliantHydroelasticProperties, AddContactMaterial,
                              AddRigidHydroelasticProperties, Box, Convex, GeometryInstance,
                              IllustrationProperties, MakePhongIllustrationProperties, Mesh,
                              PerceptionProperties, ProximityProperties, Rgba, RoleAssign)
from pydrake.math import RigidTransform
from pydrake.multibody.plant import CoulombFriction
from pydrake.multibody.tree import QuaternionFloatingJoint

from capsule_drake.anatomy import colon_assets, colon_wall_pieces
from capsule_drake.anatomy.lumen_state import BUBBLE_RGBA, FLUID_RGBA
from capsule_drake.anatomy.lesion_geometry import polyp_rgba
from capsule_drake.anatomy.source import fluid_scene, lesion_scene
from capsule_drake.capsule.model import CAPSULE_BODY
from capsule_drake.schema import need_range

CONTACT_MODELS = ("hydroelastic", "convex_pieces")
TORSO_RGBA = np.array([0.93, 0.78, 0.68, 0.18])


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


def add_colon_wall(plant, config: ContactConfig, colon_params, colon) -> int:
    """Registers the colon wall's collision geometry on the world body, by the contact
    model, and its polyps' (each its convex hull: a pedunculated polyp's head and stalk
    become a cone, U); returns how many geometries it took. Diverticula are in the wall's
    own meshes (its last chunk holds their collars and sacs); the convex pieces, which wrap
    the analytic wall, bridge their necks."""
    world = plant.world_body()
    polyps = lesion_scene(colon_params)
    for polyp, path in zip(polyps.polyps, polyps.objs):
        props = contact_properties(config)
        if config.model != "convex_pieces":
            AddRigidHydroelasticProperties(properties=props)
        plant.RegisterCollisionGeometry(world, RigidTransform(), Convex(str(path)),
                                        f"polyp_{polyp.index:03d}", props)
    if config.model == "convex_pieces":
        pieces = colon_wall_pieces(colon_params, config.piece_axial_length,
                                   config.piece_max_chord_depth)
        for i, vertices in enumerate(pieces):
            name = f"colon_piece_{i:04d}"
            plant.RegisterCollisionGeometry(world, RigidTransform(), Convex(vertices, name),
                                            name, contact_properties(config))
        return len(pieces) + len(polyps.polyps)
    chunks = colon_assets(colon_params).collision_objs
    for i, chunk in enumerate(chunks):
        props = contact_properties(config)
        AddRigidHydroelasticProperties(properties=props)
        plant.RegisterCollisionGeometry(world, RigidTransform(), Mesh(str(chunk)),
                                        f"colon_wall_{i:02d}", props)
    boxes = colon.collision_boxes
    for i, (extents, centre) in enumerate(boxes):
        props = contact_properties(config)
        AddRigidHydroelasticProperties(properties=props)
        plant.RegisterCollisionGeometry(world, RigidTransform(centre), Box(*extents),
                                        f"colon_surround_{i:02d}", props)
    return len(chunks) + len(boxes) + len(polyps.polyps)


def add_colon_visuals(plant, colon_params, colon, perception: bool = True):
    """The mucosa (its look from the mesh's own material; seen by every renderer if
    `perception`) and the torso (drawn for orientation only: cameras never see it)."""
    assets = colon_assets(colon_params)
    world = plant.world_body()
    mucosa = GeometryInstance(RigidTransform(), Mesh(str(assets.visual_obj)), "colon_mucosa")
    mucosa.set_illustration_properties(IllustrationProperties())
    if perception:
        mucosa.set_perception_properties(PerceptionProperties())
    plant.RegisterVisualGeometry(world, mucosa)
    torso = GeometryInstance(RigidTransform(), Mesh(str(assets.torso_obj)), "torso")
    rgba = colon.abdomen.display_rgba or TORSO_RGBA
    torso.set_illustration_properties(MakePhongIllustrationProperties(rgba))
    plant.RegisterVisualGeometry(world, torso)
    fluid = fluid_scene(colon_params)
    for name, path, colour in (("fluid_surface", fluid.surface_obj, FLUID_RGBA),
                               ("fluid_bubbles", fluid.bubbles_obj, BUBBLE_RGBA)):
        if path is None:   # the liquid's surface and bubbles (colon.lumen), seen like the mucosa
            continue
        instance = GeometryInstance(RigidTransform(), Mesh(str(path)), name)
        instance.set_illustration_properties(MakePhongIllustrationProperties(colour))
        if perception:
            properties = PerceptionProperties()
            properties.AddProperty("phong", "diffuse", Rgba(*colour))
            instance.set_perception_properties(properties)
        plant.RegisterVisualGeometry(world, instance)
    polyp_colour = list(polyp_rgba(colon_params.mucosa.base_color))
    sac_colour = list(colon_params.mucosa.base_color) + [1.0]
    lesions = lesion_scene(colon_params)
    for name, path, colour in (   # drawn (the cameras' are their own)
            [(f"polyp_{p.index:03d}", o, polyp_colour)
             for p, o in zip(lesions.polyps, lesions.objs)]
            + [(f"diverticulum_{d.index:03d}", o, sac_colour)
               for d, o in zip(lesions.diverticula, lesions.sac_objs)]):
        instance = GeometryInstance(RigidTransform(), Mesh(str(path)), name)
        instance.set_illustration_properties(MakePhongIllustrationProperties(colour))
        plant.RegisterVisualGeometry(world, instance)


def set_capsule_contact(plant, scene_graph, config: ContactConfig):
    """Gives the capsule's collision geometry the contact properties (compliant
    hydroelastic, or point contact for the convex-pieces wall). Call before Finalize."""
    capsule = plant.GetBodyByName(CAPSULE_BODY)
    for geometry_id in plant.GetCollisionGeometriesForBody(capsule):
        props = contact_properties(config)
        if config.model == "convex_pieces":
            scene_graph.AssignRole(plant.get_source_id(), geometry_id, props,
                                   RoleAssign.kReplace)
            continue
        AddCompliantHydroelasticProperties(
            resolution_hint=config.capsule_resolution_hint,
            hydroelastic_modulus=config.capsule_hydroelastic_modulus,
            properties=props)
        scene_graph.AssignRole(plant.get_source_id(), geometry_id, props, RoleAssign.kReplace)


def add_capsule_drag(plant, config: ContactConfig):
    """With a speed-dependent resistance (drag_*), the capsule's floating joint is declared
    here, with that damping (relative to the world, where the colon is); otherwise Finalize
    gives it a free one. Call before Finalize."""
    if config.drag_translational > 0.0 or config.drag_rotational > 0.0:
        add_damped_capsule_joint(plant, config.drag_translational, config.drag_rotational)


def add_damped_capsule_joint(plant, translational: float, angular: float):
    """The capsule's floating joint "capsule_floating", damped against the world
    (N s/m, N m s). Call before Finalize."""
    capsule = plant.GetBodyByName(CAPSULE_BODY)
    return plant.AddJoint(QuaternionFloatingJoint(
        "capsule_floating", plant.world_frame(), capsule.body_frame(),
        angular_damping=angular, translational_damping=translational))
