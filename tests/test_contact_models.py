"""The contact models (physics/contact/): a tagged union whose members each live in one
module, and the compliant wall checked against its closed form."""

import ast
import math
from pathlib import Path

import numpy as np
import pytest
from pydrake.geometry import (AddCompliantHydroelasticProperties, AddContactMaterial,
                              AddRigidHydroelasticProperties, Box, FramePoseVector,
                              GeometryFrame, GeometryInstance, HydroelasticContactRepresentation,
                              Mesh, ProximityProperties, SceneGraph)
from pydrake.math import RigidTransform, RotationMatrix

from capsule_drake.capsule.model import capsule_model
from capsule_drake.physics.contact import CONTACT_MODELS, CompliantWall, RigidWall
from capsule_drake.physics.contact.capsule_field import capsule_field_mesh, capsule_field_tets
from capsule_drake.physics.contact.compliant import (capsule_modulus, foundation_modulus,
                                                      hoop_modulus, indentation_force)
from capsule_drake.scenario import Scenario, ScenarioError, load_scenario
from capsule_drake.schema import field_types

PACKAGE = Path(__file__).resolve().parents[1] / "capsule_drake"
CONTACT = PACKAGE / "physics" / "contact"
# What the rest of the package may ask of any contact model (the models' shared interface).
SHARED = {"label", "wall_allowance", "wall_tears", "pressure_field", "step_bound"}


def test_a_contact_model_touches_its_module_and_the_union_only():
    # The scenario's `contact` is the union of CONTACT_MODELS, the rigid wall its default.
    union = field_types(Scenario)["contact"]
    assert set(getattr(union, "__args__", ())) == set(CONTACT_MODELS)
    assert isinstance(Scenario().contact, RigidWall)
    for model in CONTACT_MODELS:
        module = Path(__import__(model.__module__, fromlist=["_"]).__file__)
        # The files that name the model's class: its own module, the union's package and the
        # scenario (its annotation), nothing else.
        naming = {path.relative_to(PACKAGE).as_posix() for path in PACKAGE.rglob("*.py")
                  if model.__name__ in path.read_text()}
        assert naming <= {module.relative_to(PACKAGE).as_posix(), "physics/contact/__init__.py",
                          "scenario.py"}, (model.__name__, naming)
    # Outside physics/contact/, a scenario's contact is asked only the shared interface: no
    # module reads a model's settings sideways.
    for path in PACKAGE.rglob("*.py"):
        if CONTACT in path.parents:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute)
                    and node.value.attr == "contact"):
                assert node.attr in SHARED, f"{path.relative_to(PACKAGE)} reads contact.{node.attr}"


# --- the compliant wall's mechanics ---------------------------------------------------------

def test_the_foundation_modulus_is_the_hoop_stretch_and_support_in_series_with_the_wall():
    wall = CompliantWall()
    # By hand, at the nominal figures and a 25 mm lumen: 0.63 MPa x 2.61 mm / (25 mm)^2.
    assert hoop_modulus(wall, 0.025) == pytest.approx(0.63e6 * 2.61e-3 / 0.025**2)
    outward = 0.63e6 * 2.61e-3 / 0.025**2 + 3.0e5
    through = 1.76e6 / 2.61e-3
    assert foundation_modulus(wall, 0.025) == pytest.approx(outward * through / (outward + through))
    # The wall's thickness barely counts: within 1 % of the outward part alone.
    assert foundation_modulus(wall, 0.025) == pytest.approx(outward, rel=0.01)
    # A wider lumen is softer (1 / R^2), a stiffer support stiffer.
    assert foundation_modulus(wall, 0.04) < foundation_modulus(wall, 0.025)
    stiffer = CompliantWall(support_stiffness=3.0e6)
    assert foundation_modulus(stiffer, 0.025) > foundation_modulus(wall, 0.025)


def numerical_indentation_force(k, depth, radius, length, n=801):
    """Second route: the pressure k (r - distance to the axis) summed over a fine grid of the
    wall's plane under a capsule lying along x, its axis at height r - depth."""
    c = radius - depth
    half = 0.5 * length + radius
    x = np.linspace(-half, half, 2 * n)
    y = np.linspace(-radius, radius, n)
    X, Y = np.meshgrid(x, y)
    along = np.clip(np.abs(X) - 0.5 * length, 0.0, None)   # beyond the cylinder: the cap
    distance = np.sqrt(along**2 + Y**2 + c**2)
    pressure = k * np.clip(radius - distance, 0.0, None)
    return float(np.sum(pressure) * (x[1] - x[0]) * (y[1] - y[0]))


@pytest.mark.parametrize("depth", [0.0003, 0.001, 0.003, 0.0058])
def test_the_closed_form_is_the_integral_of_the_pressure(depth):
    model = capsule_model()
    k = 3.0e6
    closed = indentation_force(k, depth, model.radius, model.length)
    assert closed == pytest.approx(
        numerical_indentation_force(k, depth, model.radius, model.length), rel=2e-3)
    # Small indentations: the cylinder's Hertz-like 4/3 k L sqrt(2 r) d^(3/2) dominates.
    if depth <= 0.0003:
        hertz = 4.0 / 3.0 * k * model.length * math.sqrt(2.0 * model.radius) * depth**1.5
        assert closed == pytest.approx(hertz, rel=0.1)


def field_mesh_force(k: float, depth: float, roll: float = 0.0, pitch: float = 0.0) -> float:
    """The normal force (N) of Drake's hydroelastic contact between the compliant wall's
    capsule (its field mesh, modulus k r) lying on a rigid flat wall and pressed `depth` (m)
    into it, rolled about its axis by `roll` and its nose tilted down by `pitch` (rad)."""
    model = capsule_model()
    scene_graph = SceneGraph()
    source = scene_graph.RegisterSource("test")
    frame = scene_graph.RegisterFrame(source, GeometryFrame("capsule"))
    capsule = ProximityProperties()
    AddContactMaterial(dissipation=0.0, properties=capsule)
    AddCompliantHydroelasticProperties(resolution_hint=1.0,
                                       hydroelastic_modulus=capsule_modulus(k, model.radius),
                                       properties=capsule)
    mesh = capsule_field_mesh(model.radius, model.length)
    geometry = scene_graph.RegisterGeometry(source, frame, GeometryInstance(
        RigidTransform(), Mesh(str(mesh)), "capsule"))
    scene_graph.AssignRole(source, geometry, capsule)
    wall = ProximityProperties()
    AddContactMaterial(dissipation=0.0, properties=wall)
    AddRigidHydroelasticProperties(resolution_hint=0.004, properties=wall)
    ground = scene_graph.RegisterAnchoredGeometry(source, GeometryInstance(
        RigidTransform([0.0, 0.0, -0.05]), Box(0.2, 0.2, 0.1), "wall"))
    scene_graph.AssignRole(source, ground, wall)
    context = scene_graph.CreateDefaultContext()
    # The capsule's axis along x, its lowest point `depth` below the wall's plane (z = 0).
    R = (RotationMatrix.MakeYRotation(pitch) @ RotationMatrix.MakeYRotation(math.pi / 2)
         @ RotationMatrix.MakeZRotation(roll))
    lowest = (model.radius + 0.5 * model.length * abs(math.sin(pitch)))
    poses = FramePoseVector()
    poses.set_value(frame, RigidTransform(R, [0.0, 0.0, lowest - depth]))
    scene_graph.get_source_pose_port(source).FixValue(context, poses)
    query = scene_graph.get_query_output_port().Eval(context)
    force = 0.0
    for surface in query.ComputeContactSurfaces(HydroelasticContactRepresentation.kPolygon):
        mesh_W, pressure = surface.poly_mesh_W(), surface.poly_e_MN()
        for face in range(mesh_W.num_faces()):
            force += (pressure.EvaluateCartesian(face, mesh_W.element_centroid(face))
                      * mesh_W.area(face) * abs(mesh_W.face_normal(face)[2]))
    return force


@pytest.mark.parametrize("roll", [0.0, math.pi / 48])   # on a vertex of the mesh, on a facet
def test_the_simulated_wall_pushes_back_as_its_closed_form(roll):
    # The acceptance: within 5 % over the indentations runs reach (a Default run on the
    # compliant wall goes 2.8-3.1 mm into the wall's undeformed surface; a capsule at rest
    # under its weight alone, ~0.3 mm), at the nominal wall and a stiffer and a softer one.
    model = capsule_model()
    for k in (1.0e6, 3.0e6, 1.0e7):
        for depth in (0.0003, 0.0005, 0.001, 0.002, 0.003, 0.004):
            closed = indentation_force(k, depth, model.radius, model.length)
            simulated = field_mesh_force(k, depth, roll)
            assert simulated == pytest.approx(closed, rel=0.05), (k, depth, simulated, closed)


def test_the_field_mesh_is_the_capsule():
    # Interior vertices on the axis; surface vertices half a chord depth outside the round
    # surface, so that each facet's middle lies as far inside it (mean radius r); every
    # tetrahedron positive, and the volume the capsule's within 1 % (the caps are coarser).
    model = capsule_model()
    r, length = model.radius, model.length
    vertices, tets = capsule_field_tets(r, length, around=48)
    along = np.clip(np.abs(vertices[:, 2]) - 0.5 * length, 0.0, None)
    distance = np.hypot(np.hypot(vertices[:, 0], vertices[:, 1]), along)
    on_axis = np.hypot(vertices[:, 0], vertices[:, 1]) < 1e-12
    depth = r * (1.0 - math.cos(math.pi / 48))
    assert np.allclose(distance[~on_axis], r + 0.5 * depth, atol=1e-12)
    midpoint = (r + 0.5 * depth) * math.cos(math.pi / 48)
    assert midpoint == pytest.approx(r - 0.5 * depth, abs=1e-7)   # to second order in the angle
    a, b, c, d = (vertices[tets[:, i]] for i in range(4))
    volumes = np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0
    assert np.all(volumes > 0.0)
    capsule = math.pi * r**2 * length + 4.0 / 3.0 * math.pi * r**3
    assert volumes.sum() == pytest.approx(capsule, rel=0.01)


@pytest.mark.parametrize("text, key", [
    ("{contact: !CompliantWall {thickness: -0.001}}", "contact.thickness"),
    ("{contact: !CompliantWall {circumferential_modulus: .nan}}",
     "contact.circumferential_modulus"),
    ("{contact: !CompliantWall {friction: -0.1}}", "contact.friction"),
    ("{contact: !CompliantWall {support_stiffness: -1.0}}", "contact.support_stiffness"),
    ("{contact: !CompliantWall {lumen_radius: 1.0}}", "contact.lumen_radius"),
    ("{contact: !RigidWall {friction: -0.1}}", "contact.friction"),
])
def test_impossible_tissue_is_one_line_at_load_naming_the_key(text, key):
    with pytest.raises(ScenarioError) as caught:
        load_scenario(override=text)
    message = str(caught.value)
    assert "\n" not in message and key in message, message


def test_every_printed_contact_line_names_its_model():
    # The default run's contact figures came from the stand-in and read as the patient's; a
    # printed line now names the model, and the stand-in's says it is not a tissue figure.
    from capsule_drake.app.commands.common import contact_words, pressure_summary
    rigid = {"contact_model": RigidWall().label(), "wall_pressure_field": True,
             "wall_patch_length_m": 0.01, "wall_patch_angle_deg": 30.0,
             "site_peak_pressure_kPa": 375.0, "site_peak_at_s_m": 0.155,
             "site_peak_segment": "sigmoid", "site_longest_above_injury_s": 0.01,
             "site_longest_above_ischaemia_s": 7.4, "site_longest_above_ischaemia_at_s_m": 0.5,
             "site_longest_above_ischaemia_segment": "descending"}
    assert contact_words(rigid) == ("contact on the rigid stand-in wall (hydroelastic), not a "
                                    "tissue figure")
    assert "rigid stand-in wall (hydroelastic), not a tissue figure" in pressure_summary(rigid)
    compliant = dict(rigid, contact_model=CompliantWall().label())
    assert contact_words(compliant) == "contact on the compliant wall"
    assert "contact on the compliant wall: peak 375 kPa" in pressure_summary(compliant)
