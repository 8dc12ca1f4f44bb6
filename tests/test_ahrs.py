"""Mahony AHRS: error bounds for a static and a slowly rotating capsule, bias convergence,
unobservable heading, and the LeafSystem against the pure update.

Stated bounds (MPU-6050 noise of ImuConfig(), 100 Hz, kp = 1 rad/s, ki = 0.25 rad/s^2,
after 10 s of convergence):
- static, calibrated accelerometer: tilt (roll/pitch) error < 0.1 deg;
- static with an accelerometer bias b_a: the filter aligns with the biased vertical, so the
  tilt error is asin(|b_a x up| / g) within 0.1 deg (10 mg gives ~0.6 deg);
- rotating at 20 deg/s about an axis 30 deg off the vertical, calibrated accelerometer,
  gyro turn-on bias of 0.2-1.7 deg/s: tilt error < 0.05 deg + 0.5 x (bias sigma) after 20 s
  (0.15 deg for 0.2 deg/s) and < 0.05 deg + 0.3 x (bias sigma) after 30 s; the gyro-bias
  estimate converges to the true bias with a time constant of about 20 s (the component
  along the rotation axis is seen only through the 30 deg cone the vertical sweeps): its
  error is at least 10x smaller after 60 s;
- rotating with a 10 mg accelerometer bias: tilt error < asin(|b_a| / g) + 0.5 deg;
- heading is unobservable: at rest it drifts as the integral of the gyro bias about the
  vertical (the bias estimate along the vertical stays zero).
"""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.common import RandomGenerator
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import LogVectorOutput
from scipy.spatial.transform import Rotation

from capsule_drake.capsule.ahrs import (
    AhrsConfig,
    MahonyAhrs,
    mahony_update,
    tilt_and_heading_error,
    tilt_quaternion,
)
from capsule_drake.capsule.imu import STANDARD_GRAVITY, Imu, ImuConfig, imu_channels
from capsule_drake.capsule.model import rotation_from_quaternion

DEG = math.pi / 180.0
CALIBRATED = dataclasses.replace(ImuConfig(), accel_initial_bias_sigma=0.0)


def _truth(rate_deg, axis_tilt_deg, seconds, fs, R0=Rotation.from_rotvec([0.3, -0.2, 0.5])):
    """R_WB(t_k) for a rotation at a constant rate about a fixed world axis tilted from the
    vertical, with the ideal gyro (constant in the body) and specific force."""
    n = int(round(seconds * fs))
    t = np.arange(n + 1) / fs
    tilt = axis_tilt_deg * DEG
    w_W = rate_deg * DEG * np.array([math.sin(tilt), 0.0, math.cos(tilt)])
    R = Rotation.from_rotvec(np.outer(t, w_W)) * R0
    gyro = np.tile(R0.inv().apply(w_W), (n, 1))
    accel = R[:n].inv().apply([0.0, 0.0, STANDARD_GRAVITY])
    return R, gyro, accel


def _measure(config, gyro_true, accel_true, seed):
    rng = np.random.default_rng(seed)
    n = len(gyro_true)
    accel, gyro = imu_channels(config)
    a, bias_a = accel.record(accel_true, rng.standard_normal((n, 3)),
                             rng.standard_normal((n, 3)), rng.standard_normal(3))
    w, bias_w = gyro.record(gyro_true, rng.standard_normal((n, 3)),
                            rng.standard_normal((n, 3)), rng.standard_normal(3))
    return a, w, bias_a, bias_w


def _filter(a, w, fs, ahrs=AhrsConfig(), q0=None):
    """The pure filter over a recording; estimate k is the orientation at t_{k+1}."""
    q = q0 if q0 is not None else tilt_quaternion(a[0])
    b = (0.0, 0.0, 0.0)
    qs, bs = [], []
    for k in range(len(a)):
        q, b = mahony_update(q, b, a[k], w[k], 1.0 / fs, ahrs.kp, ahrs.ki,
                             ahrs.accel_rejection)
        qs.append(q)
        bs.append(b)
    return np.array(qs), np.array(bs)


def _errors(qs, R_true):
    """(tilt, heading) errors in degrees; qs[k] against R_true[k + 1]."""
    out = np.array([tilt_and_heading_error(rotation_from_quaternion(q),
                                           R_true[k + 1].as_matrix())
                    for k, q in enumerate(qs)])
    return np.degrees(out[:, 0]), np.degrees(out[:, 1])


def _quat(R: Rotation):
    x, y, z, w = R.as_quat()
    return (w, x, y, z)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_static_tilt_error_and_unobservable_heading(seed):
    fs = CALIBRATED.sample_rate
    R, gyro_true, accel_true = _truth(0.0, 0.0, 60.0, fs)
    a, w, _, bias_w = _measure(CALIBRATED, gyro_true, accel_true, seed)
    qs, bs = _filter(a, w, fs, q0=_quat(R[0]))
    tilt, heading = _errors(qs, R)
    assert tilt[int(10 * fs):].max() < 0.1
    # The bias across the vertical converges (it tilts the estimate, the accelerometer sees
    # it); the one along the vertical does not and integrates into heading.
    up_B = R[0].inv().apply([0.0, 0.0, 1.0])
    error = bs[-1] - bias_w[-1]
    assert np.linalg.norm(error - (error @ up_B) * up_B) < 0.01 * DEG
    assert abs(bs[-1] @ up_B) < 0.01 * DEG
    drift = np.degrees(np.cumsum(bias_w @ up_B) / fs)
    assert heading[-1] == pytest.approx(drift[-1], abs=0.1 + 0.05 * abs(drift[-1]))


def test_static_tilt_error_follows_the_accelerometer_bias():
    config = ImuConfig()  # 10 mg turn-on bias per axis
    fs = config.sample_rate
    R, gyro_true, accel_true = _truth(0.0, 0.0, 30.0, fs)
    for seed in range(3):
        a, w, bias_a, _ = _measure(config, gyro_true, accel_true, seed)
        qs, _ = _filter(a, w, fs)
        tilt, _ = _errors(qs, R)
        up_B = accel_true[0] / np.linalg.norm(accel_true[0])
        expected = np.degrees(math.asin(np.linalg.norm(np.cross(bias_a[0], up_B))
                                        / STANDARD_GRAVITY))
        np.testing.assert_allclose(tilt[int(10 * fs):], expected, atol=0.1)


@pytest.mark.parametrize("seed, bias_deg", [(0, 0.2), (1, 0.2), (2, 1.0)])
def test_rotating_capsule_tilt_error_and_bias_convergence(seed, bias_deg):
    config = dataclasses.replace(CALIBRATED, gyro_initial_bias_sigma=bias_deg * DEG)
    fs = config.sample_rate
    R, gyro_true, accel_true = _truth(20.0, 30.0, 60.0, fs)
    a, w, _, bias_w = _measure(config, gyro_true, accel_true, seed)
    qs, bs = _filter(a, w, fs)
    tilt, _ = _errors(qs, R)
    assert tilt[int(20 * fs):].max() < 0.05 + 0.5 * bias_deg
    assert tilt[int(30 * fs):].max() < 0.05 + 0.3 * bias_deg
    # Turning moves the vertical through the sensor frame: every bias axis is observable.
    assert np.linalg.norm(bias_w[0]) > 0.1 * DEG
    assert np.linalg.norm(bs[-1] - bias_w[-1]) < 0.1 * np.linalg.norm(bias_w[0])


def test_rotating_capsule_with_accelerometer_bias():
    # A body-fixed accelerometer bias looks like a tilt that turns with the capsule: the tilt
    # error stays near asin(|b_a| / g) and the gyro-bias estimate absorbs part of it.
    config = ImuConfig()
    fs = config.sample_rate
    R, gyro_true, accel_true = _truth(20.0, 30.0, 40.0, fs)
    for seed in range(3):
        a, w, bias_a, _ = _measure(config, gyro_true, accel_true, seed)
        qs, _ = _filter(a, w, fs)
        tilt, _ = _errors(qs, R)
        bound = np.degrees(math.asin(np.linalg.norm(bias_a[0]) / STANDARD_GRAVITY)) + 0.5
        assert tilt[int(10 * fs):].max() < bound


def test_initial_tilt_from_the_accelerometer():
    R = RotationMatrix(RollPitchYaw(0.4, -0.7, 2.0))
    up_S = R.inverse() @ np.array([0.0, 0.0, 9.81])
    q = tilt_quaternion(up_S)
    tilt, _ = tilt_and_heading_error(RotationMatrix(rotation_from_quaternion(q)), R)
    assert tilt < 1e-12
    assert tilt_and_heading_error(
        RotationMatrix(rotation_from_quaternion(tilt_quaternion([0, 0, -9.8]))),
        RotationMatrix(RollPitchYaw(math.pi, 0, 0)))[0] < 1e-12


def test_leaf_system_equals_the_pure_filter_and_reports_the_body_frame():
    fs = 100.0
    R, gyro_true, accel_true = _truth(20.0, 30.0, 3.0, fs)
    a, w, _, _ = _measure(ImuConfig(), gyro_true, accel_true, seed=5)
    R_BS = RotationMatrix(RollPitchYaw(0.1, 0.2, -0.3))
    dut = MahonyAhrs(fs, AhrsConfig(), R_BS=R_BS)
    context = dut.CreateDefaultContext()
    # No sample yet (all zero): the filter waits.
    dut.get_accel_input_port().FixValue(context, np.zeros(3))
    dut.get_gyro_input_port().FixValue(context, np.zeros(3))
    context.SetDiscreteState(dut.EvalUniquePeriodicDiscreteUpdate(context))
    np.testing.assert_array_equal(dut.get_q_WB_output_port().Eval(context), [1, 0, 0, 0])
    qs, bs = _filter(a, w, fs)
    for k in range(len(a)):
        dut.get_accel_input_port().FixValue(context, a[k])
        dut.get_gyro_input_port().FixValue(context, w[k])
        context.SetDiscreteState(dut.EvalUniquePeriodicDiscreteUpdate(context))
    q_WB = dut.get_q_WB_output_port().Eval(context)
    R_WB_expected = RotationMatrix(rotation_from_quaternion(qs[-1])) @ R_BS.inverse()
    assert RotationMatrix(rotation_from_quaternion(q_WB)).IsNearlyEqualTo(R_WB_expected,
                                                                          1e-12)
    np.testing.assert_allclose(dut.get_gyro_bias_output_port().Eval(context), bs[-1],
                               atol=1e-15)


def test_given_initial_orientation():
    R0 = RotationMatrix(RollPitchYaw(0.2, 0.1, 1.3))
    q0 = R0.ToQuaternion()
    dut = MahonyAhrs(100.0, AhrsConfig(initial_q_WB=[q0.w(), q0.x(), q0.y(), q0.z()]))
    context = dut.CreateDefaultContext()
    dut.get_accel_input_port().FixValue(context, R0.inverse() @ np.array([0, 0, 9.81]))
    dut.get_gyro_input_port().FixValue(context, np.zeros(3))
    context.SetDiscreteState(dut.EvalUniquePeriodicDiscreteUpdate(context))
    q = dut.get_q_WB_output_port().Eval(context)
    # heading kept too
    assert RotationMatrix(rotation_from_quaternion(q)).IsNearlyEqualTo(R0, 1e-9)


def test_imu_and_ahrs_on_a_spinning_plant_body():
    # End to end in Drake: a torque-free capsule (gravity off for the body; the accelerometer
    # still uses the plant's gravity vector) spinning at 20 deg/s about its own axis, which
    # is tilted 30 deg from the vertical. Truth is the plant's integrated state.
    plant = MultibodyPlant(1e-3)
    body = plant.AddRigidBody(
        "capsule", SpatialInertia.SolidCylinderWithMass(0.012, 0.0058, 0.0315, [0, 0, 1]))
    plant.set_gravity_enabled(body.model_instance(), False)
    plant.Finalize()
    imu_config = dataclasses.replace(CALIBRATED, gyro_initial_bias_sigma=0.5 * DEG)
    builder = DiagramBuilder()
    builder.AddSystem(plant)
    imu = builder.AddNamedSystem("capsule.imu", Imu(plant, body, imu_config))
    imu.connect_to_plant(builder, plant)
    ahrs = builder.AddNamedSystem("capsule.ahrs", MahonyAhrs(
        imu_config.sample_rate, AhrsConfig(), R_BS=imu_config.X_BS().rotation(),
        gravity=float(np.linalg.norm(plant.gravity_field().gravity_vector()))))
    builder.Connect(imu.GetOutputPort("accel"), ahrs.get_accel_input_port())
    builder.Connect(imu.GetOutputPort("gyro"), ahrs.get_gyro_input_port())
    period = 1.0 / imu_config.sample_rate
    q_log = LogVectorOutput(ahrs.get_q_WB_output_port(), builder, period)
    b_log = LogVectorOutput(ahrs.get_gyro_bias_output_port(), builder, period)
    true_b_log = LogVectorOutput(imu.GetOutputPort("gyro_bias"), builder, period)
    x_log = LogVectorOutput(plant.get_state_output_port(), builder, period)
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    diagram.SetRandomContext(context, RandomGenerator(42))
    plant_context = plant.GetMyMutableContextFromRoot(context)
    R0 = RotationMatrix(RollPitchYaw(30 * DEG, 0.0, 0.4))
    plant.SetFreeBodyPose(plant_context, body, RigidTransform(R0, [0, 0, 0]))
    plant.SetFreeBodySpatialVelocity(
        plant_context, body, _spatial_velocity(R0 @ np.array([0.0, 0.0, 20 * DEG])))
    Simulator(diagram, context).AdvanceTo(40.0)
    q_est = q_log.FindLog(context).data().T
    x = x_log.FindLog(context).data().T
    tilts = []
    for k in range(int(20 / period), len(x)):
        R_true = RotationMatrix(Quaternion(x[k, :4] / np.linalg.norm(x[k, :4])))
        tilts.append(tilt_and_heading_error(
            RotationMatrix(rotation_from_quaternion(q_est[k])), R_true)[0])
    assert np.degrees(max(tilts)) < 0.05 + 0.5 * 0.5
    b_est = b_log.FindLog(context).data().T[-1]
    b_true = true_b_log.FindLog(context).data().T
    # 40 s is two time constants of the bias loop at this rate and tilt ([0] is logged
    # before the first sample).
    assert np.linalg.norm(b_est - b_true[-1]) < 0.3 * np.linalg.norm(b_true[1])


def _spatial_velocity(w_W):
    from pydrake.multibody.math import SpatialVelocity
    return SpatialVelocity(w=np.asarray(w_W), v=np.zeros(3))
