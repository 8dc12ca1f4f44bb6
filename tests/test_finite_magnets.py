"""Finite-size magnets: the exact cylinder field against its on-axis closed form and the far
dipole, the pair's force and torque against magpylib's meshed reference at 8-25 cm, the
pair's action and reaction, and the "finite" field model in MagneticForce and a scenario."""

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from capsule_drake.physics.magnetics import (cylinder_field, cylinder_moment,
                                     cylinder_pair_interaction_float, dipole_field,
                                     dipole_pair_interaction_float, meshed_reference_wrench)
from capsule_drake.scenario import ScenarioError, load_scenario

# The Navigation scenario's magnets: N52 cylinders of 101.6 mm and 11.1 mm (D = L), 1.48 T.
D, L, BR = 0.1016, 0.1016, 1.48
d, l = 0.0111, 0.0111
M_EPM = cylinder_moment(D, L, BR)
M_IPM = cylinder_moment(d, l, BR)


def _unit(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def test_cylinder_field_on_its_axis_is_the_textbook_closed_form():
    # B_z(z) = Br/2 [(z + L/2)/sqrt((z + L/2)^2 + R^2) - (z - L/2)/sqrt((z - L/2)^2 + R^2)]
    # (e.g. Furlani 2001, sec. 4.3), with the moment along a tilted axis.
    axis = np.array([0.3, -0.4, 0.866])
    axis /= np.linalg.norm(axis)
    for z in (0.06, 0.08, 0.12, 0.2, 0.3):
        a, b = z + L / 2, z - L / 2
        expected = BR / 2 * (a / math.hypot(a, D / 2) - b / math.hypot(b, D / 2))
        B = cylinder_field(M_EPM * axis, [z * axis], D, L)[0]
        assert_allclose(B, expected * axis, rtol=1e-9, atol=1e-12)


def test_cylinder_field_far_away_is_the_dipole_field():
    # The difference falls as (size / r)^2: ~3e-4 at 2 m, ~3e-6 at 20 m.
    rng = np.random.default_rng(1)
    for _ in range(5):
        m, u = M_EPM * _unit(rng), _unit(rng)
        for r, tolerance in ((2.0, 1e-3), (20.0, 1e-5)):
            B = cylinder_field(m, [r * u], D, L)[0]
            dipole = dipole_field(m, r * u)
            assert np.linalg.norm(B - dipole) < tolerance * np.linalg.norm(dipole)


def _meshed_reference(a, c, p):
    """magpylib's force and torque on the capsule's cylinder magnet, meshed into cells."""
    return meshed_reference_wrench(M_EPM * a, M_IPM * c, p, (D, L), (d, l))


@pytest.mark.parametrize("distance", [0.08, 0.10, 0.12, 0.15, 0.20, 0.25])
def test_pair_matches_the_meshed_reference_within_one_percent(distance):
    rng = np.random.default_rng(int(1000 * distance))
    for _ in range(4):
        a, c, u = _unit(rng), _unit(rng), _unit(rng)
        p = distance * u
        F_ref, T_ref = _meshed_reference(a, c, p)
        ours = cylinder_pair_interaction_float(M_EPM * a, M_IPM * c, p, D, L,
                                               target_size=(d, l))
        # Measured (bench_magnet_model.py): 95th percentiles at most 0.14 % (force) and
        # 0.43 % (torque).
        assert np.linalg.norm(np.array(ours.force_target) - F_ref) < 0.01 * np.linalg.norm(F_ref)
        assert np.linalg.norm(np.array(ours.torque_target) - T_ref) < 0.01 * np.linalg.norm(T_ref)
        dipole = dipole_pair_interaction_float(M_EPM * a, M_IPM * c, p)
        if distance <= 0.10:  # where the point dipole is far off, the test can tell
            assert np.linalg.norm(np.array(dipole.force_target) - F_ref) > \
                0.05 * np.linalg.norm(F_ref)


def test_point_target_is_off_by_percents_at_eight_centimetres():
    """Why the capsule's magnet is integrated over its volume: as a point it misses the
    meshed reference at 8 cm by 0.02-0.3 %, and by 7 % where it all but touches the EPM's
    rim (measured)."""
    rng = np.random.default_rng(8)
    errors = []
    for _ in range(6):
        a, c, u = _unit(rng), _unit(rng), _unit(rng)
        F_ref, _ = _meshed_reference(a, c, 0.08 * u)
        point = cylinder_pair_interaction_float(M_EPM * a, M_IPM * c, 0.08 * u, D, L)
        errors.append(np.linalg.norm(np.array(point.force_target) - F_ref)
                      / np.linalg.norm(F_ref))
    assert 0.01 < max(errors) < 0.2


def test_pair_action_and_reaction():
    rng = np.random.default_rng(3)
    for _ in range(5):
        p = 0.15 * _unit(rng)
        r = cylinder_pair_interaction_float(M_EPM * _unit(rng), M_IPM * _unit(rng), p, D, L,
                                            target_size=(d, l))
        assert_allclose(r.force_source, -np.array(r.force_target), rtol=1e-12)
        # Total torque about the source's centre vanishes.
        total = np.array(r.torque_source) + np.array(r.torque_target) + np.cross(
            p, r.force_target)
        assert np.linalg.norm(total) < 1e-12 * max(1.0, np.linalg.norm(r.torque_target))


def test_finite_field_model_in_magnetic_force():
    from pydrake.math import RigidTransform, RollPitchYaw
    from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
    from pydrake.multibody.tree import SpatialInertia
    from pydrake.systems.framework import DiagramBuilder

    from capsule_drake.physics.magnet_force import MagneticForce, MagnetSpec

    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=1e-3), builder)
    capsule = plant.AddRigidBody("capsule", SpatialInertia.SolidSphereWithMass(0.01, 0.005))
    epm = plant.AddRigidBody("epm", SpatialInertia.SolidSphereWithMass(6.0, 0.05))
    plant.Finalize()
    specs = [MagnetSpec(name="ipm", body="capsule", axis_B=[0, 0, 1], moment=M_IPM,
                        cylinder=[d, l]),
             MagnetSpec(name="epm", body="epm", p_BM=[0.0, 0.01, 0.0], axis_B=[0, 0.3, 1],
                        moment=M_EPM, cylinder=[D, L])]
    magnetic = builder.AddSystem(MagneticForce(plant, specs, field_model="finite"))
    builder.Connect(plant.get_body_poses_output_port(), magnetic.get_body_poses_input_port())
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyContextFromRoot(context)
    X_WC = RigidTransform(RollPitchYaw(0.4, -0.7, 0.2), [0.02, -0.01, 0.0])
    X_WE = RigidTransform(RollPitchYaw(0.1, 0.2, -0.3), [0.03, 0.02, 0.11])
    plant.SetFreeBodyPose(plant_context, capsule, X_WC)
    plant.SetFreeBodyPose(plant_context, epm, X_WE)
    mf_context = magnetic.GetMyContextFromRoot(context)
    # The EPM is magnet index 1, the larger: it is the finite source.
    axis = np.array([0, 0.3, 1.0]) / np.linalg.norm([0, 0.3, 1.0])
    p_E = X_WE @ np.array([0.0, 0.01, 0.0])
    m_E = M_EPM * (X_WE.rotation() @ axis)
    m_C = M_IPM * X_WC.rotation().col(2)
    expected = cylinder_pair_interaction_float(m_E, m_C, X_WC.translation() - p_E, D, L,
                                               target_size=(d, l))
    F_capsule = magnetic.get_F_W_output_port("ipm").Eval(mf_context)
    assert_allclose(F_capsule[3:], expected.force_target, rtol=1e-9)
    assert_allclose(F_capsule[:3], expected.torque_target, rtol=1e-9)
    F_epm = magnetic.get_F_W_output_port("epm").Eval(mf_context)
    assert_allclose(F_epm[3:], expected.force_source, rtol=1e-9)
    B_epm = magnetic.get_B_B_output_port("ipm").Eval(mf_context)
    assert_allclose(X_WC.rotation() @ B_epm, expected.field_at_target, rtol=1e-9)
    # The dipole model differs here (11.4 cm) by 4 %, far more than the finite model's error.
    dipole = dipole_pair_interaction_float(m_E, m_C, X_WC.translation() - p_E)
    assert np.linalg.norm(np.array(dipole.force_target) - expected.force_target) > \
        0.02 * np.linalg.norm(expected.force_target)
    with pytest.raises(ValueError, match="float only"):
        magnetic.ToAutoDiffXd()
    with pytest.raises(ValueError, match="field_model must be one of"):
        MagneticForce(plant, specs, field_model="exact")
    with pytest.raises(ValueError, match="cylinder must be"):
        MagneticForce(plant, [MagnetSpec(name="ipm", body="capsule", moment=1.0,
                                         cylinder=[0.01])], field_model="finite")


def test_finite_magnet_model_scenario_runs_and_checks_its_shapes():
    from pydrake.systems.analysis import Simulator

    from capsule_drake.station import make_station

    scenario = load_scenario(name="Default",
                             override="{magnet_force: {field_model: finite}, duration: 0.2}")
    station = make_station(scenario)
    simulator = Simulator(station)
    simulator.AdvanceTo(0.2)
    state = station.GetOutputPort("capsule.state").Eval(simulator.get_context())
    assert np.all(np.isfinite(state))
    with pytest.raises(ScenarioError) as error:
        load_scenario(name="Default", override=(
            "{magnet_force: {field_model: finite}, epm: {magnet: {shape: cuboid,"
            " dimensions: [0.08, 0.08, 0.1]}}}"))
    assert "epm.magnet is a cuboid" in str(error.value) and "\n" not in str(error.value)
    with pytest.raises(ScenarioError, match="magnet_force.field_model must be"):
        load_scenario(name="Default", override="{magnet_force: {field_model: exact}}")


def test_magnetometer_reads_the_finite_field_with_the_finite_model():
    """With magnet_force.field_model finite the magnetometer reads the EPM's exact cylinder
    field at the sensor (the same field the force uses), not the dipole's."""
    from capsule_drake.capsule.model import CAPSULE_BODY
    from capsule_drake.station import make_station

    for model, field in (("dipole", lambda m, p: dipole_field(m, p)),
                         ("finite", lambda m, p: cylinder_field(m, [p], D, L)[0])):
        scenario = load_scenario(name="Default", override=(
            f"{{magnet_force: {{field_model: {model}}}, duration: 0.0, "
            f"capsule: {{magnetometer: {{}}}}}}"))
        station = make_station(scenario)
        context = station.CreateDefaultContext()
        poses = station.GetOutputPort("body_poses").Eval(context)
        plant = station.GetSubsystemByName("plant")
        X_WS = poses[int(plant.GetBodyByName(CAPSULE_BODY).index())] @ \
            scenario.capsule.magnetometer.X_BS()
        epm = station.GetOutputPort("epm.pose").Eval(context)   # the kinematic stage's
        m_E = M_EPM * epm[3:] / np.linalg.norm(epm[3:])
        expected = X_WS.rotation().inverse() @ field(m_E, X_WS.translation() - epm[:3])
        reading = station.GetSubsystemByName("capsule.magnetometer").calc_true_field(
            poses, {"epm": epm})
        np.testing.assert_allclose(reading, expected, rtol=1e-9)
        if model == "finite":
            dipole = X_WS.rotation().inverse() @ dipole_field(
                m_E, X_WS.translation() - epm[:3])
            assert np.linalg.norm(reading - dipole) > 1e-3 * np.linalg.norm(dipole)
