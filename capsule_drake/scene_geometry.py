"""The geometry the scene's blocks (scene.py) register in the plant before it is
finalised: the mucosa, fluid, lesions and torso as seen and drawn, and the capsule's damped
floating joint. The wall's collision geometry and the capsule's contact properties are the
contact model's (physics/contact/).
"""

import numpy as np
from pydrake.geometry import (GeometryInstance, IllustrationProperties,
                              MakePhongIllustrationProperties, Mesh, PerceptionProperties, Rgba)
from pydrake.math import RigidTransform
from pydrake.multibody.tree import QuaternionFloatingJoint

from capsule_drake.anatomy import colon_assets
from capsule_drake.anatomy.lesion_geometry import polyp_rgba
from capsule_drake.anatomy.lumen_state import BUBBLE_RGBA, FLUID_RGBA
from capsule_drake.anatomy.source import fluid_scene, lesion_scene
from capsule_drake.capsule.model import CAPSULE_BODY

TORSO_RGBA = np.array([0.93, 0.78, 0.68, 0.18])


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


def add_damped_capsule_joint(plant, translational: float, angular: float):
    """The capsule's floating joint "capsule_floating", damped against the world
    (N s/m, N m s). Call before Finalize."""
    capsule = plant.GetBodyByName(CAPSULE_BODY)
    return plant.AddJoint(QuaternionFloatingJoint(
        "capsule_floating", plant.world_frame(), capsule.body_frame(),
        angular_damping=angular, translational_damping=translational))
