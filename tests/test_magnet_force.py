"""MagneticForce in a MultibodyPlant diagram, checked against the pure functions."""

import numpy as np
import pytest
from numpy.testing import assert_allclose
from pydrake.autodiffutils import AutoDiffXd, ExtractGradient, InitializeAutoDiff
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RigidTransform_, RollPitchYaw, RotationMatrix
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, InputPortSelection, OutputPortSelection
from pydrake.systems.primitives import FirstOrderTaylorApproximation

from capsule_drake.physics.magnetics import dipole_field, dipole_pair_wrench
from capsule_drake.physics.magnet_force import MagneticForce, MagneticForce_, MagnetSpec

CAPSULE_MASS = 0.005  # kg
EPM_MASS = 6.2  # kg
P_BM_IPM = [0.002, -0.001, 0.008]  # IPM off the capsule origin, to expose the lever arm
P_BM_EPM = [0.0, 0.01, -0.02]
AXIS_IPM = [0.0, 0.0, 1.0]
AXIS_EPM = [0.0, 0.3, 1.0]
X_W_CAPSULE = RigidTransform(RollPitchYaw(0.4, -0.7, 0.2), [0.02, -0.01, 0.0])
X_W_EPM = RigidTransform(RollPitchYaw(0.1, 0.2, -0.3), [0.03, 0.02, 0.14])


def magnet_specs():
    return [
        MagnetSpec(name="ipm", body="capsule", p_BM=P_BM_IPM, axis_B=AXIS_IPM, moment=1.26),
        MagnetSpec(name="epm", body="epm", p_BM=P_BM_EPM, axis_B=AXIS_EPM, moment=970.0),
    ]


def build(weld_epm=False, gravity=True, magnets=None, extra_body=False):
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(
        MultibodyPlantConfig(time_step=1e-3, use_sampled_output_ports=False), builder
    )
    capsule = plant.AddRigidBody(
        "capsule",
        SpatialInertia.SolidCylinderWithMass(CAPSULE_MASS, 0.0055, 0.026, [0, 0, 1]),
    )
    epm = plant.AddRigidBody(
        "epm", SpatialInertia.SolidCylinderWithMass(EPM_MASS, 0.0508, 0.1016, [0, 0, 1])
    )
    if extra_body:
        plant.AddRigidBody(
            "third", SpatialInertia.SolidSphereWithMass(0.01, 0.005)
        )
    if weld_epm:
        plant.WeldFrames(plant.world_frame(), epm.body_frame(), X_W_EPM)
    if not gravity:
        plant.mutable_gravity_field().set_gravity_vector([0, 0, 0])
    plant.Finalize()
    magnetic = builder.AddSystem(
        MagneticForce(plant, magnets if magnets is not None else magnet_specs())
    )
    magnetic.set_name("magnetic_force")
    builder.Connect(plant.get_body_poses_output_port(), magnetic.get_body_poses_input_port())
    builder.Connect(
        magnetic.get_applied_spatial_force_output_port(),
        plant.get_applied_spatial_force_input_port(),
    )
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyContextFromRoot(context)
    plant.SetFreeBodyPose(plant_context, capsule, X_W_CAPSULE)
    if not weld_epm:
        plant.SetFreeBodyPose(plant_context, epm, X_W_EPM)
    return diagram, plant, magnetic, context


def world_magnets():
    """Magnet centres and moments in world, computed here independently."""
    p_ipm = X_W_CAPSULE @ np.array(P_BM_IPM)
    p_epm = X_W_EPM @ np.array(P_BM_EPM)
    axis = np.array(AXIS_EPM) / np.linalg.norm(AXIS_EPM)
    m_ipm = 1.26 * X_W_CAPSULE.rotation().multiply(np.array(AXIS_IPM))
    m_epm = 970.0 * X_W_EPM.rotation().multiply(axis)
    return p_ipm, m_ipm, p_epm, m_epm


def test_applied_force_equals_pure_functions_at_the_magnet_point():
    diagram, plant, magnetic, context = build()
    mf_context = magnetic.GetMyContextFromRoot(context)
    p_ipm, m_ipm, p_epm, m_epm = world_magnets()
    expected = dipole_pair_wrench(m_epm, m_ipm, p_ipm - p_epm)
    forces = magnetic.get_applied_spatial_force_output_port().Eval(mf_context)
    by_body = {int(f.body_index): f for f in forces}
    assert len(by_body) == 2
    capsule = by_body[int(plant.GetBodyByName("capsule").index())]
    epm = by_body[int(plant.GetBodyByName("epm").index())]
    # The wrench acts at the magnet centre, not the body origin or centre of mass.
    assert_allclose(capsule.p_BoBq_B, P_BM_IPM)
    assert_allclose(epm.p_BoBq_B, P_BM_EPM)
    assert_allclose(capsule.F_Bq_W.translational(), expected.force_target, rtol=1e-10)
    assert_allclose(capsule.F_Bq_W.rotational(), expected.torque_target, rtol=1e-10)
    assert_allclose(epm.F_Bq_W.translational(), expected.force_source, rtol=1e-10)
    assert_allclose(epm.F_Bq_W.rotational(), expected.torque_source, rtol=1e-10)
    # At 14 cm the capsule is pulled with ~1-2 N: a sanity check on magnitude.
    assert 0.5 < np.linalg.norm(expected.force_target) < 5


def test_lever_arm_reaches_the_plant_dynamics():
    # No gravity, zero velocity: the capsule's acceleration comes from the magnet only.
    diagram, plant, magnetic, context = build(gravity=False)
    plant_context = plant.GetMyContextFromRoot(context)
    p_ipm, m_ipm, p_epm, m_epm = world_magnets()
    wrench = dipole_pair_wrench(m_epm, m_ipm, p_ipm - p_epm)
    f, tau_M = wrench.force_target, wrench.torque_target
    # Shift the wrench from the magnet M to the body origin Bo (= centre of mass).
    p_BoM_W = X_W_CAPSULE.rotation().multiply(np.array(P_BM_IPM))
    tau_Bo = tau_M + np.cross(p_BoM_W, f)
    R = X_W_CAPSULE.rotation().matrix()
    capsule = plant.GetBodyByName("capsule")
    I_B = capsule.default_rotational_inertia().CopyToFullMatrix3()
    I_W = R @ I_B @ R.T
    vdot = plant.get_generalized_acceleration_output_port().Eval(plant_context)
    start = capsule.floating_velocities_start_in_v()
    alpha, a = vdot[start : start + 3], vdot[start + 3 : start + 6]
    assert_allclose(a, f / CAPSULE_MASS, rtol=1e-8)
    assert_allclose(alpha, np.linalg.solve(I_W, tau_Bo), rtol=1e-6)
    # Dropping the lever arm (applying at the centre of mass) changes alpha by
    # ~10 %, so the assertion above would catch it.
    alpha_at_com = np.linalg.solve(I_W, tau_M)
    assert np.linalg.norm(alpha - alpha_at_com) > 0.05 * np.linalg.norm(alpha)


def test_newton_third_law_between_outputs_and_field_in_body_frame():
    diagram, plant, magnetic, context = build()
    mf_context = magnetic.GetMyContextFromRoot(context)
    p_ipm, m_ipm, p_epm, m_epm = world_magnets()
    F_ipm = magnetic.get_F_W_output_port("ipm").Eval(mf_context)
    F_epm = magnetic.get_F_W_output_port("epm").Eval(mf_context)
    assert_allclose(F_ipm[3:] + F_epm[3:], 0, atol=1e-14)
    # Total torque about the world origin vanishes: no net angular momentum.
    total = F_ipm[:3] + np.cross(p_ipm, F_ipm[3:]) + F_epm[:3] + np.cross(p_epm, F_epm[3:])
    assert_allclose(total, 0, atol=1e-14)
    # Magnetometer reading: world field rotated into the body frame.
    B_ipm = magnetic.get_B_B_output_port("ipm").Eval(mf_context)
    B_W = dipole_field(m_epm, p_ipm - p_epm)
    assert_allclose(B_ipm, X_W_CAPSULE.rotation().inverse().multiply(B_W), rtol=1e-10)
    B_epm = magnetic.get_B_B_output_port("epm").Eval(mf_context)
    B_W = dipole_field(m_ipm, p_epm - p_ipm)
    assert_allclose(B_epm, X_W_EPM.rotation().inverse().multiply(B_W), rtol=1e-10)


def test_welded_magnet_gets_no_force_but_makes_a_field():
    diagram, plant, magnetic, context = build(weld_epm=True)
    mf_context = magnetic.GetMyContextFromRoot(context)
    forces = magnetic.get_applied_spatial_force_output_port().Eval(mf_context)
    assert [int(f.body_index) for f in forces] == [int(plant.GetBodyByName("capsule").index())]
    p_ipm, m_ipm, p_epm, m_epm = world_magnets()
    expected = dipole_pair_wrench(m_epm, m_ipm, p_ipm - p_epm)
    assert_allclose(forces[0].F_Bq_W.translational(), expected.force_target, rtol=1e-10)
    B_ipm = magnetic.get_B_B_output_port("ipm").Eval(mf_context)
    assert np.linalg.norm(B_ipm) > 0.01  # tens of mT from the welded EPM
    # The welded magnet still reports its reaction wrench (what a holder carries).
    F_epm = magnetic.get_F_W_output_port("epm").Eval(mf_context)
    assert_allclose(F_epm[3:], expected.force_source, rtol=1e-10)


def test_three_magnets_sum_pairwise():
    specs = magnet_specs() + [
        MagnetSpec(name="third", body="third", p_BM=[0, 0, 0], axis_B=[1, 0, 0], moment=0.5)
    ]
    diagram, plant, magnetic, context = build(magnets=specs, extra_body=True)
    plant_context = plant.GetMyContextFromRoot(context)
    X_third = RigidTransform(RotationMatrix.MakeZRotation(0.5), [-0.05, 0.04, 0.06])
    plant.SetFreeBodyPose(plant_context, plant.GetBodyByName("third"), X_third)
    mf_context = magnetic.GetMyContextFromRoot(context)
    p_ipm, m_ipm, p_epm, m_epm = world_magnets()
    p_3 = X_third.translation()
    m_3 = 0.5 * X_third.rotation().multiply([1.0, 0, 0])
    from_epm = dipole_pair_wrench(m_epm, m_ipm, p_ipm - p_epm)
    from_3 = dipole_pair_wrench(m_3, m_ipm, p_ipm - p_3)
    F_ipm = magnetic.get_F_W_output_port("ipm").Eval(mf_context)
    assert_allclose(F_ipm[3:], from_epm.force_target + from_3.force_target, rtol=1e-10)
    assert_allclose(F_ipm[:3], from_epm.torque_target + from_3.torque_target, rtol=1e-10)
    B_W = dipole_field(m_epm, p_ipm - p_epm) + dipole_field(m_3, p_ipm - p_3)
    assert_allclose(
        magnetic.get_B_B_output_port("ipm").Eval(mf_context),
        X_W_CAPSULE.rotation().inverse().multiply(B_W),
        rtol=1e-10,
    )
    assert len(magnetic.get_applied_spatial_force_output_port().Eval(mf_context)) == 3


def test_construction_errors():
    diagram, plant, magnetic, context = build()
    with pytest.raises(ValueError, match="unique"):
        MagneticForce(plant, magnet_specs() + magnet_specs())
    with pytest.raises(ValueError, match="axis_B"):
        MagneticForce(plant, [MagnetSpec(name="a", body="capsule", axis_B=[0, 0, 0])])
    with pytest.raises(KeyError):
        magnetic.get_B_B_output_port("nope")
    assert magnetic.magnet_names() == ["ipm", "epm"]


def test_diagram_autodiff_matches_finite_differences():
    diagram, plant, magnetic, context = build()
    plant_context = plant.GetMyContextFromRoot(context)
    q0 = plant.GetPositions(plant_context)

    def ipm_wrench(q):
        plant.SetPositions(plant_context, q)
        mf_context = magnetic.GetMyContextFromRoot(context)
        return magnetic.get_F_W_output_port("ipm").Eval(mf_context).copy()

    h = 1e-7
    fd = np.column_stack(
        [(ipm_wrench(q0 + h * e) - ipm_wrench(q0 - h * e)) / (2 * h) for e in np.eye(len(q0))]
    )

    diagram_ad = diagram.ToAutoDiffXd()
    context_ad = diagram_ad.CreateDefaultContext()
    plant_ad = diagram_ad.GetSubsystemByName(plant.get_name())
    magnetic_ad = diagram_ad.GetSubsystemByName("magnetic_force")
    assert isinstance(magnetic_ad, MagneticForce_[AutoDiffXd])
    plant_ad.SetPositions(plant_ad.GetMyContextFromRoot(context_ad), InitializeAutoDiff(q0))
    wrench_ad = magnetic_ad.get_F_W_output_port("ipm").Eval(
        magnetic_ad.GetMyContextFromRoot(context_ad)
    )
    value = np.array([x.value() for x in wrench_ad])
    assert_allclose(value, ipm_wrench(q0), rtol=1e-12)
    grad = ExtractGradient(wrench_ad)
    assert_allclose(grad, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())
    # The force is stiff: at ~14 cm its gradient is tens of N/m.
    assert np.abs(grad[3:, -3:]).max() > 10


def test_standalone_autodiff_conversion():
    diagram, plant, magnetic, context = build()
    magnetic_ad = magnetic.ToAutoDiffXd()
    ad_context = magnetic_ad.CreateDefaultContext()
    poses = plant.get_body_poses_output_port().Eval(plant.GetMyContextFromRoot(context))
    poses_ad = [RigidTransform_[AutoDiffXd](X.GetAsMatrix34()) for X in poses]
    magnetic_ad.get_body_poses_input_port().FixValue(ad_context, AbstractValue.Make(poses_ad))
    forces = magnetic_ad.get_applied_spatial_force_output_port().Eval(ad_context)
    reference = magnetic.get_applied_spatial_force_output_port().Eval(
        magnetic.GetMyContextFromRoot(context)
    )
    for f_ad, f in zip(forces, reference):
        got = np.array([x.value() for x in f_ad.F_Bq_W.get_coeffs()])
        assert_allclose(got, f.F_Bq_W.get_coeffs(), rtol=1e-12)


def test_short_simulation_with_gravity_is_finite_and_attracts():
    diagram, plant, magnetic, context = build()
    plant_context = plant.GetMyContextFromRoot(context)
    capsule, epm = plant.GetBodyByName("capsule"), plant.GetBodyByName("epm")
    # Coaxial 0.5 m apart: ~12 mN of attraction on a 50 mN capsule.
    X_epm = RigidTransform([0, 0, 0.5])
    plant.SetFreeBodyPose(plant_context, capsule, RigidTransform())
    plant.SetFreeBodyPose(plant_context, epm, X_epm)
    simulator = Simulator(diagram, context)
    simulator.AdvanceTo(0.2)
    state = plant.GetPositionsAndVelocities(plant_context)
    assert np.all(np.isfinite(state))
    gap = (
        plant.EvalBodyPoseInWorld(plant_context, epm).translation()[2]
        - plant.EvalBodyPoseInWorld(plant_context, capsule).translation()[2]
    )
    # Both fall together under gravity; the magnets close the gap a little.
    assert 0.40 < gap < 0.4995


def test_linearized_plant_sees_the_magnetic_stiffness():
    # Discrete step v+ = v + h M^-1 F(q): d(v+)/d(p_capsule) = h K / m, with K the
    # gradient of the magnetic force w.r.t. the magnet's position (EPM welded).
    # The capsule is pulled, so not at rest: a first-order Taylor approximation
    # (Linearize without the equilibrium requirement).
    diagram, plant, magnetic, context = build(weld_epm=True, gravity=False)
    linear = FirstOrderTaylorApproximation(
        diagram,
        context,
        input_port_index=InputPortSelection.kNoInput,
        output_port_index=OutputPortSelection.kNoOutput,
    )
    capsule = plant.GetBodyByName("capsule")
    q_start = capsule.floating_positions_start() + 4  # after the quaternion
    v_start = plant.num_positions() + capsule.floating_velocities_start_in_v() + 3
    block = linear.A()[v_start : v_start + 3, q_start : q_start + 3]
    assert np.all(np.isfinite(linear.A()))

    p_ipm, m_ipm, p_epm, m_epm = world_magnets()
    h = 1e-7
    stiffness = np.column_stack(
        [
            (
                dipole_pair_wrench(m_epm, m_ipm, p_ipm + h * e - p_epm).force_target
                - dipole_pair_wrench(m_epm, m_ipm, p_ipm - h * e - p_epm).force_target
            )
            / (2 * h)
            for e in np.eye(3)
        ]
    )
    time_step = plant.time_step()
    assert_allclose(block, time_step * stiffness / CAPSULE_MASS, rtol=1e-5, atol=1e-8)


def test_outputs_share_one_computation_per_context():
    diagram, plant, magnetic, context = build()
    mf_context = magnetic.GetMyContextFromRoot(context)
    calls = []
    original = magnetic._pair

    def counting_pair(*args):
        calls.append(1)
        return original(*args)

    magnetic._pair = counting_pair
    magnetic.get_applied_spatial_force_output_port().Eval(mf_context)
    for name in magnetic.magnet_names():
        magnetic.get_B_B_output_port(name).Eval(mf_context)
        magnetic.get_F_W_output_port(name).Eval(mf_context)
    assert len(calls) == 1  # one pair, evaluated once for all five outputs
    # Moving a body invalidates the cache.
    plant_context = plant.GetMyContextFromRoot(context)
    plant.SetFreeBodyPose(plant_context, plant.GetBodyByName("capsule"), RigidTransform())
    magnetic.get_F_W_output_port("ipm").Eval(mf_context)
    assert len(calls) == 2


def _three_magnet_diagram():
    specs = magnet_specs() + [
        MagnetSpec(name="third", body="third", p_BM=[0.001, 0, 0], axis_B=[1, 0, 0], moment=0.5)
    ]
    diagram, plant, magnetic, context = build(magnets=specs, extra_body=True)
    plant.SetFreeBodyPose(
        plant.GetMyContextFromRoot(context),
        plant.GetBodyByName("third"),
        RigidTransform(RotationMatrix.MakeZRotation(0.5), [-0.05, 0.04, 0.06]),
    )
    return diagram, plant, magnetic, context


def test_float_fast_path_equals_generic_path():
    # MagneticForce_[float] runs a plain-float kernel; MagneticForce_[AutoDiffXd]
    # runs the generic numpy functions. Same poses in, same outputs out.
    diagram, plant, magnetic, context = _three_magnet_diagram()
    mf_context = magnetic.GetMyContextFromRoot(context)
    poses = magnetic.get_body_poses_input_port().Eval(mf_context)
    generic = magnetic.ToAutoDiffXd()
    generic_context = generic.CreateDefaultContext()
    generic.get_body_poses_input_port().FixValue(
        generic_context,
        AbstractValue.Make([RigidTransform_[AutoDiffXd](X.GetAsMatrix34()) for X in poses]),
    )

    def values(x):
        return np.array([a.value() for a in np.asarray(x).ravel()])

    fast_forces = magnetic.get_applied_spatial_force_output_port().Eval(mf_context)
    generic_forces = generic.get_applied_spatial_force_output_port().Eval(generic_context)
    assert len(fast_forces) == len(generic_forces) == 3
    for fast, slow in zip(fast_forces, generic_forces):
        assert fast.body_index == slow.body_index
        assert_allclose(fast.p_BoBq_B, values(slow.p_BoBq_B), rtol=0, atol=0)
        assert_allclose(fast.F_Bq_W.get_coeffs(), values(slow.F_Bq_W.get_coeffs()), rtol=1e-12)
    for name in magnetic.magnet_names():
        for getter in ("get_B_B_output_port", "get_F_W_output_port"):
            fast = getattr(magnetic, getter)(name).Eval(mf_context)
            slow = getattr(generic, getter)(name).Eval(generic_context)
            assert_allclose(fast, values(slow), rtol=1e-12, atol=1e-300, err_msg=name)
    # The fast kernel relies on plain Python floats: numpy scalars would make
    # every product several times slower, silently.
    for magnet in magnetic._magnets:
        assert all(type(x) is float for x in magnet.p_BM + magnet.m_B)


def test_applied_forces_of_two_contexts_are_independent():
    # The calc reuses one set of ExternallyAppliedSpatialForce objects; the
    # output value must be a copy, not an alias that the next calc overwrites.
    diagram, plant, magnetic, context = build()
    port = magnetic.get_applied_spatial_force_output_port()
    first = port.Eval(magnetic.GetMyContextFromRoot(context))
    before = [f.F_Bq_W.get_coeffs().copy() for f in first]
    other = diagram.CreateDefaultContext()
    plant.SetFreeBodyPose(
        plant.GetMyContextFromRoot(other), plant.GetBodyByName("capsule"), RigidTransform([0, 0, 0.3])
    )
    second = port.Eval(magnetic.GetMyContextFromRoot(other))
    assert not np.allclose(second[0].F_Bq_W.get_coeffs(), before[0])
    again = port.Eval(magnetic.GetMyContextFromRoot(context))
    for f, coeffs in zip(again, before):
        assert_allclose(f.F_Bq_W.get_coeffs(), coeffs, rtol=0, atol=0)


@pytest.mark.parametrize("scalar", [float, AutoDiffXd])
def test_a_posed_magnet_acts_as_the_same_magnet_on_a_body(scalar):
    """The EPM given as a pose input (MagnetSpec.posed, as the kinematic stage gives it)
    yields the same force, torque and fields as the EPM on a plant body at that pose, in
    both scalar types; the posed magnet is given no applied force."""
    diagram, plant, body_force, context = build(weld_epm=True)
    _, _, p_epm, m_epm = world_magnets()
    posed = [magnet_specs()[0],
             MagnetSpec(name="epm", moment=970.0, posed=True)]
    force = MagneticForce(plant, posed)
    if scalar is AutoDiffXd:
        body_force, force = body_force.ToAutoDiffXd(), force.ToAutoDiffXd()
    plant_context = plant.GetMyContextFromRoot(context)
    poses = plant.get_body_poses_output_port().Eval(plant_context)
    if scalar is AutoDiffXd:
        poses = [RigidTransform_[AutoDiffXd](X.GetAsMatrix4()) for X in poses]
    values = []
    for system in (body_force, force):
        system_context = system.CreateDefaultContext()
        system.get_body_poses_input_port().FixValue(system_context, poses)
        if system is force:
            pose = np.concatenate([p_epm, m_epm / np.linalg.norm(m_epm) * 3.0])  # unnormalised
            system.get_pose_input_port("epm").FixValue(
                system_context, pose if scalar is float else InitializeAutoDiff(pose).ravel())
        outputs = [system.get_F_W_output_port(name).Eval(system_context)
                   for name in ("ipm", "epm")]
        outputs.append(system.get_B_B_output_port("ipm").Eval(system_context))
        applied = system.get_applied_spatial_force_output_port().Eval(system_context)
        values.append(([np.array([float(getattr(x, "value", lambda: x)()) for x in v])
                        for v in outputs], len(applied)))
    for a, b in zip(values[0][0], values[1][0]):
        assert_allclose(b, a, rtol=1e-12, atol=1e-15)
    assert values[0][1] == values[1][1] == 1   # only the capsule's magnet is pushed
    B_epm = force.get_B_B_output_port("epm").Eval(system_context)
    B_epm = np.array([float(getattr(x, "value", lambda: x)()) for x in B_epm])
    assert np.linalg.norm(B_epm) > 0.0   # the capsule's field at the EPM, in its frame
