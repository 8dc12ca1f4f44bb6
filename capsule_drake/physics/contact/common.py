"""What the contact models share: the contact material (friction, dissipation, point
stiffness), the colon wall's collision geometry as rigid hydroelastic meshes, the capsule's
compliant hydroelastic layer, and the capsule's damped floating joint."""

from pydrake.geometry import (AddCompliantHydroelasticProperties, AddContactMaterial,
                              AddRigidHydroelasticProperties, Box, Convex, Mesh,
                              ProximityProperties, Role, RoleAssign)
from pydrake.math import RigidTransform
from pydrake.multibody.plant import CoulombFriction

from capsule_drake.anatomy import colon_assets
from capsule_drake.anatomy.source import lesion_scene
from capsule_drake.capsule.model import CAPSULE_BODY
from capsule_drake.scene_geometry import add_damped_capsule_joint


def contact_properties(friction: float, dissipation: float,
                       point_stiffness: float | None = None) -> ProximityProperties:
    """Dissipation (Hunt-Crossley, s/m), point stiffness (N/m, point contact only) and
    Coulomb friction (dynamic = static) of the capsule-wall contact."""
    props = ProximityProperties()
    AddContactMaterial(dissipation=dissipation, point_stiffness=point_stiffness,
                       friction=CoulombFriction(friction, friction), properties=props)
    return props


def add_polyp_hulls(plant, colon_params, properties, rigid_hydroelastic: bool) -> int:
    """The polyps' collision geometry on the world body, each its convex hull (a
    pedunculated polyp's head and stalk become a cone, U); `properties()` gives each its
    contact material. Returns how many."""
    polyps = lesion_scene(colon_params)
    for polyp, path in zip(polyps.polyps, polyps.objs):
        props = properties()
        if rigid_hydroelastic:
            AddRigidHydroelasticProperties(properties=props)
        plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform(),
                                        Convex(str(path)), f"polyp_{polyp.index:03d}", props)
    return len(polyps.polyps)


def add_rigid_hydroelastic_wall(plant, colon_params, colon, properties,
                                chunks: bool = True) -> int:
    """The colon wall as rigid hydroelastic triangle-mesh chunks and the boxes that close
    the space around it, on the world body, after the polyps' hulls; `properties()` gives
    each its contact material. Diverticula are in the wall's own meshes (its last chunk
    holds their collars and sacs). Without `chunks`, only the polyps and the boxes (the
    wall's own force is computed elsewhere). Returns how many geometries it took."""
    count = add_polyp_hulls(plant, colon_params, properties, rigid_hydroelastic=True)
    world = plant.world_body()
    meshes = colon_assets(colon_params).collision_objs if chunks else []
    for i, chunk in enumerate(meshes):
        props = properties()
        AddRigidHydroelasticProperties(properties=props)
        plant.RegisterCollisionGeometry(world, RigidTransform(), Mesh(str(chunk)),
                                        f"colon_wall_{i:02d}", props)
    boxes = colon.collision_boxes
    for i, (extents, centre) in enumerate(boxes):
        props = properties()
        AddRigidHydroelasticProperties(properties=props)
        plant.RegisterCollisionGeometry(world, RigidTransform(centre), Box(*extents),
                                        f"colon_surround_{i:02d}", props)
    return count + len(meshes) + len(boxes)


def set_capsule_properties(plant, scene_graph, properties, resolution_hint: float | None = None,
                           hydroelastic_modulus: float | None = None) -> None:
    """Gives the capsule's collision geometry `properties()`: with a hydroelastic modulus
    (Pa) a compliant hydroelastic layer meshed at `resolution_hint` (m), else point
    contact. Call before Finalize."""
    capsule = plant.GetBodyByName(CAPSULE_BODY)
    for geometry_id in plant.GetCollisionGeometriesForBody(capsule):
        props = properties()
        if hydroelastic_modulus is not None:
            AddCompliantHydroelasticProperties(resolution_hint=resolution_hint,
                                               hydroelastic_modulus=hydroelastic_modulus,
                                               properties=props)
        scene_graph.AssignRole(plant.get_source_id(), geometry_id, props, RoleAssign.kReplace)


def set_capsule_field_mesh(plant, scene_graph, properties, mesh_path, hydroelastic_modulus: float):
    """The capsule's contact as a compliant hydroelastic volume mesh (`mesh_path`, a VTK
    tetrahedral mesh in the collision shape's frame, physics/contact/capsule_field.py) of
    modulus `hydroelastic_modulus` (Pa): the shape's own collision geometry keeps no contact
    role, and the mesh is registered on the capsule body at the shape's pose in its place.
    Call before Finalize."""
    capsule = plant.GetBodyByName(CAPSULE_BODY)
    inspector = scene_graph.model_inspector()
    for geometry_id in plant.GetCollisionGeometriesForBody(capsule):
        X_BG = inspector.GetPoseInFrame(geometry_id)
        scene_graph.RemoveRole(plant.get_source_id(), geometry_id, Role.kProximity)
        props = properties()
        AddCompliantHydroelasticProperties(resolution_hint=1.0,
                                           hydroelastic_modulus=hydroelastic_modulus,
                                           properties=props)
        plant.RegisterCollisionGeometry(capsule, X_BG, Mesh(str(mesh_path)), "shell_field",
                                        props)


def add_capsule_drag(plant, translational: float, rotational: float) -> None:
    """With a speed-dependent resistance (N s/m, N m s/rad), the capsule's floating joint is
    declared here, with that damping (relative to the world, where the colon is);
    otherwise Finalize gives it a free one. Call before Finalize."""
    if translational > 0.0 or rotational > 0.0:
        add_damped_capsule_joint(plant, translational, rotational)
