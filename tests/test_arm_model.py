"""The 7-DoF EPM arm model (models/epm_arm.sdf), checked against the LBR iiwa 14 R820 datasheet
figures and against closed forms (cylinder inertias, gravity torques by hand)."""

import math

import numpy as np
import pytest
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import RevoluteJoint

from capsule_drake.models import configure_parser

URL = "package://capsule_drake/epm_arm.sdf"
G = 9.81

# Datasheet, LBR iiwa 14 R820: limits per joint.
POSITION_DEG = [170, 120, 170, 120, 170, 120, 175]
VELOCITY_DEG_S = [85, 85, 100, 75, 130, 135, 135]
EFFORT_NM = [320, 320, 176, 176, 110, 40, 40]
# Axes in the zero configuration (joint 4 turns about -y, as on the real arm).
AXES = [(0, 0, 1), (0, 1, 0), (0, 0, 1), (0, -1, 0), (0, 0, 1), (0, 1, 0), (0, 0, 1)]

# Datasheet heights in the zero ("candle") pose.
SHOULDER_Z, ELBOW_Z, WRIST_Z, FLANGE_Z = 0.36, 0.78, 1.18, 1.306

# The model's design table (header comment of epm_arm.sdf): link mass (kg), cylinder radius and
# length (m), height of the link's joint in the zero pose; centre of mass at the cylinder's centre.
LINKS = {
    "arm_link_0": (6.0, 0.100, 0.1575, 0.0),
    "arm_link_1": (5.2, 0.075, 0.2025, 0.1575),
    "arm_link_2": (4.6, 0.075, 0.2045, 0.36),
    "arm_link_3": (4.1, 0.070, 0.2155, 0.5645),
    "arm_link_4": (3.6, 0.070, 0.1845, 0.78),
    "arm_link_5": (3.2, 0.065, 0.2155, 0.9645),
    "arm_link_6": (2.7, 0.065, 0.0810, 1.18),
    "arm_link_7": (0.5, 0.050, 0.0450, 1.261),
}
EPM_MASS = 6.2
EPM_OFFSET = 0.0508 + 0.02  # magnet radius + adapter plate, beyond the flange face


def _load(weld=True):
    plant = MultibodyPlant(0.0)
    configure_parser(Parser(plant)).AddModels(url=URL)
    if weld:
        plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("arm_link_0"))
    plant.Finalize()
    return plant


@pytest.fixture(scope="module")
def plant():
    return _load()


def _random_configurations(plant, n=20, seed=7):
    rng = np.random.default_rng(seed)
    lo, hi = plant.GetPositionLowerLimits(), plant.GetPositionUpperLimits()
    return [rng.uniform(lo, hi) for _ in range(n)]


def _joint_origin(plant, context, i):
    joint = plant.GetJointByName(f"arm_joint_{i}")
    return joint.frame_on_child().CalcPoseInWorld(context).translation()


def test_model_instance_and_base_not_welded():
    floating = _load(weld=False)
    assert floating.HasModelInstanceNamed("epm_arm")
    # The SDF leaves the base free (the station welds it): unwelded it gets a floating joint.
    assert floating.GetBodyByName("arm_link_0").is_floating_base_body()
    assert floating.num_positions() == 7 + 7


def test_joints_match_datasheet(plant):
    assert plant.num_positions() == 7
    assert plant.num_actuators() == 7
    for i in range(1, 8):
        joint = plant.GetJointByName(f"arm_joint_{i}")
        assert isinstance(joint, RevoluteJoint)
        assert joint.parent_body().name() == f"arm_link_{i - 1}"
        assert joint.child_body().name() == f"arm_link_{i}"
        np.testing.assert_allclose(joint.revolute_axis(), AXES[i - 1], atol=1e-12)
        q_max = math.radians(POSITION_DEG[i - 1])
        v_max = math.radians(VELOCITY_DEG_S[i - 1])
        np.testing.assert_allclose(joint.position_lower_limits(), [-q_max], atol=1e-5)
        np.testing.assert_allclose(joint.position_upper_limits(), [q_max], atol=1e-5)
        np.testing.assert_allclose(joint.velocity_lower_limits(), [-v_max], atol=1e-5)
        np.testing.assert_allclose(joint.velocity_upper_limits(), [v_max], atol=1e-5)
        actuator = plant.GetJointActuatorByName(f"arm_joint_{i}")
        assert actuator.joint().index() == joint.index()
        assert actuator.effort_limit() == pytest.approx(EFFORT_NM[i - 1])
        assert 0.1 <= joint.default_damping() <= 0.9


def test_zero_configuration(plant):
    context = plant.CreateDefaultContext()
    X_WF = plant.GetFrameByName("flange").CalcPoseInWorld(context)
    np.testing.assert_allclose(X_WF.translation(), [0, 0, FLANGE_Z], atol=1e-12)
    np.testing.assert_allclose(X_WF.rotation().matrix()[:, 2], [0, 0, 1], atol=1e-12)
    assert plant.GetFrameByName("flange").body().name() == "arm_link_7"
    heights = {1: 0.1575, 2: SHOULDER_Z, 4: ELBOW_Z, 6: WRIST_Z}
    for i, z in heights.items():
        np.testing.assert_allclose(_joint_origin(plant, context, i), [0, 0, z], atol=1e-12)


def test_forward_kinematics_link_lengths(plant):
    context = plant.CreateDefaultContext()
    flange = plant.GetFrameByName("flange")
    for q in _random_configurations(plant):
        plant.SetPositions(context, q)
        shoulder, elbow, wrist = (_joint_origin(plant, context, i) for i in (2, 4, 6))
        p_flange = flange.CalcPoseInWorld(context).translation()
        np.testing.assert_allclose(shoulder, [0, 0, SHOULDER_Z], atol=1e-12)  # joint 1 turns it in place
        assert np.linalg.norm(elbow - shoulder) == pytest.approx(0.42, abs=1e-9)
        assert np.linalg.norm(wrist - elbow) == pytest.approx(0.40, abs=1e-9)
        assert np.linalg.norm(p_flange - wrist) == pytest.approx(0.126, abs=1e-9)


def test_epm_mount(plant):
    context = plant.CreateDefaultContext()
    epm = plant.GetBodyByName("epm")
    flange = plant.GetFrameByName("flange")
    assert epm.default_mass() == pytest.approx(EPM_MASS)
    np.testing.assert_allclose(epm.default_rotational_inertia().get_moments(),
                               [0.00933, 0.00933, 0.00800], rtol=1e-3)
    for q in [np.zeros(7)] + _random_configurations(plant, n=5):
        plant.SetPositions(context, q)
        X_WF = flange.CalcPoseInWorld(context)
        X_WE = epm.EvalPoseInWorld(context)
        z_F = X_WF.rotation().matrix()[:, 2]
        x_F = X_WF.rotation().matrix()[:, 0]
        z_E = X_WE.rotation().matrix()[:, 2]
        assert abs(z_E @ z_F) < 1e-12  # moment perpendicular to the tool axis
        np.testing.assert_allclose(z_E, x_F, atol=1e-12)  # ... along the flange's +x
        np.testing.assert_allclose(X_WE.translation(),
                                   X_WF.translation() + EPM_OFFSET * z_F, atol=1e-12)
    X_FE = plant.CalcRelativeTransform(context, flange, epm.body_frame())
    np.testing.assert_allclose(X_FE.translation(), [0, 0, 0.0708], atol=1e-12)


def test_masses_and_inertias(plant):
    total = sum(plant.GetBodyByName(name).default_mass() for name in LINKS)
    assert 29.5 <= total <= 30.5  # datasheet 29.9 kg, without the EPM
    for name, (m, r, length, _) in LINKS.items():
        body = plant.GetBodyByName(name)
        M = body.default_spatial_inertia()
        assert M.IsPhysicallyValid()
        assert M.get_mass() == pytest.approx(m)
        np.testing.assert_allclose(M.get_com(), [0, 0, length / 2], atol=1e-12)
        # Solid cylinder about its centre: Ixx = Iyy = m (3 r^2 + L^2) / 12, Izz = m r^2 / 2.
        I_cm = M.Shift(M.get_com()).CalcRotationalInertia()
        expected = np.diag([m * (3 * r**2 + length**2) / 12] * 2 + [m * r**2 / 2])
        np.testing.assert_allclose(I_cm.CopyToFullMatrix3(), expected, rtol=1e-4, atol=1e-9)


def test_mass_matrix_spd(plant):
    context = plant.CreateDefaultContext()
    for q in _random_configurations(plant):
        plant.SetPositions(context, q)
        M = plant.CalcMassMatrix(context)
        np.testing.assert_allclose(M, M.T, atol=1e-12)
        assert np.linalg.eigvalsh(M).min() > 0


def test_gravity_torques_outstretched(plant):
    """Joint 2 at 90 deg: the arm and the EPM lie horizontal along +x from the shoulder. Gravity's
    torque about +y at a pitch joint is g * sum(m d), d = distance of each distal centre of mass
    beyond the joint along the arm (negated at joint 4, whose axis is -y)."""
    context = plant.CreateDefaultContext()
    q = np.zeros(7)
    q[1] = math.pi / 2
    plant.SetPositions(context, q)
    tau_g = plant.CalcGravityGeneralizedForces(context)

    # Heights (in the zero pose) of the distal centres of mass, by hand from the design table.
    masses_heights = [(m, z0 + length / 2) for m, _, length, z0 in LINKS.values()]
    masses_heights.append((EPM_MASS, FLANGE_Z + EPM_OFFSET))

    def by_hand(joint_z):
        return G * sum(m * (z - joint_z) for m, z in masses_heights if z > joint_z)

    tau2 = by_hand(SHOULDER_Z)
    assert tau2 == pytest.approx(146.8, abs=0.1)  # 14.963 kg m x 9.81
    assert tau_g[1] == pytest.approx(tau2, rel=0.01)
    assert abs(tau_g[1]) < EFFORT_NM[1]
    assert tau_g[3] == pytest.approx(-by_hand(ELBOW_Z), rel=0.01)
    assert abs(tau_g[3]) < EFFORT_NM[3]
    assert tau_g[5] == pytest.approx(by_hand(WRIST_Z), rel=0.01)
    assert abs(tau_g[5]) < EFFORT_NM[5]
    np.testing.assert_allclose(tau_g[[0, 2, 4, 6]], 0, atol=1e-9)
