"""The geometry the scene's blocks (scene.py) register in the plant before it is
finalised: the colon's wall by the contact model (ContactConfig, physics/contact.py), its
polyps' hulls, the mucosa, fluid, lesions and torso as seen and drawn, and the capsule's
contact properties and damped floating joint.
"""

import numpy as np
from pydrake.geometry import (AddCompliantHydroelasticProperties, AddRigidHydroelasticProperties,
                              Box, Convex, GeometryInstance, IllustrationProperties,
                              MakePhongIllustrationProperties, Mesh, PerceptionProperties, Rgba,
                              RoleAssign)
from pydrake.math import RigidTransform
from pydrake.multibody.tree import QuaternionFloatingJoint

from capsule_drake.anatomy import colon_assets, colon_wall_pieces
from capsule_drake.anatomy.lesion_geometry import polyp_rgba
from capsule_drake.anatomy.lumen_state import BUBBLE_RGBA, FLUID_RGBA
from capsule_drake.anatomy.source import fluid_scene, lesion_scene
from capsule_drake.capsule.model import CAPSULE_BODY
from capsule_drake.physics.contact import ContactConfig, contact_properties

TORSO_RGBA = np.array([0.93, 0.78, 0.68, 0.18])


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
