"""IMU noise model and Allan deviation: closed forms, datasheet densities, seeding, limits."""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.common import RandomGenerator
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import LogVectorOutput

from capsule_drake.capsule.allan import allan_deviation, log_log_slope, white_noise_coefficient
from capsule_drake.capsule.imu import (
    STANDARD_GRAVITY,
    Imu,
    ImuConfig,
    ImuNoise,
    bias_random_walk_from_instability,
    imu_channels,
)

DEG = math.pi / 180.0


# --- Allan deviation against closed forms -------------------------------------------------

def test_allan_deviation_of_white_noise_is_sigma_over_sqrt_m():
    # Averaging m independent samples divides the standard deviation by sqrt(m); the Allan
    # variance of white noise is exactly that variance (IEEE 952 Annex C).
    rng = np.random.default_rng(1)
    sigma, dt = 2.0, 0.01
    y = sigma * rng.standard_normal((20000, 64))
    m = np.array([1, 2, 5, 10, 30, 100, 300, 1000])
    tau, adev = allan_deviation(y, dt, m)
    np.testing.assert_allclose(tau, m * dt)
    pooled = np.sqrt(np.mean(adev ** 2, axis=1))
    np.testing.assert_allclose(pooled, sigma / np.sqrt(m), rtol=0.04)


def test_allan_deviation_of_random_walk_matches_discrete_closed_form():
    # Increments of standard deviation q per sample: sigma^2(m) = q^2 (2 m^2 + 1) / (6 m),
    # which tends to K^2 tau / 3 (IEEE 952 rate random walk).
    rng = np.random.default_rng(2)
    q, dt = 0.5, 0.01
    y = np.cumsum(q * rng.standard_normal((8192, 256)), axis=0)
    m = np.array([1, 3, 10, 30, 100, 300, 800])
    _, adev = allan_deviation(y, dt, m)
    pooled = np.sqrt(np.mean(adev ** 2, axis=1))
    np.testing.assert_allclose(pooled, q * np.sqrt((2 * m ** 2 + 1) / (6 * m)), rtol=0.08)


def test_allan_deviation_checks_its_arguments():
    with pytest.raises(ValueError):
        allan_deviation(np.zeros(10), 0.1, [6])
    tau, adev = allan_deviation(np.arange(100.0), 0.1)
    assert tau.shape == adev.shape and tau[0] == pytest.approx(0.1)


# --- the noise model ------------------------------------------------------------------------

def test_default_random_walks_follow_from_the_stated_bias_instabilities():
    config = ImuConfig()
    assert config.gyro_bias_random_walk == pytest.approx(
        bias_random_walk_from_instability(4.0 * DEG / 3600.0, config.gyro_noise_density),
        rel=1e-4)
    assert config.accel_bias_random_walk == pytest.approx(
        bias_random_walk_from_instability(0.1e-3 * STANDARD_GRAVITY,
                                          config.accel_noise_density), rel=1e-4)


def _static_recording(config, seconds, seed, truth_accel=(0.0, 0.0, STANDARD_GRAVITY)):
    rng = np.random.default_rng(seed)
    n = int(round(seconds * config.sample_rate))
    accel, gyro = imu_channels(config)
    a, _ = accel.record(np.asarray(truth_accel), rng.standard_normal((n, 3)),
                        rng.standard_normal((n, 3)), rng.standard_normal(3))
    w, _ = gyro.record(np.zeros(3), rng.standard_normal((n, 3)),
                       rng.standard_normal((n, 3)), rng.standard_normal(3))
    return a, w


def test_static_recording_adev_matches_datasheet_density_at_short_tau():
    # MPU-6050 defaults, one hour at 100 Hz. White noise of one-sided density d sampled with
    # sigma = d sqrt(fs / 2) has ADEV(tau) = (d / sqrt(2)) / sqrt(tau): IEEE 952's N is
    # d / sqrt(2). The fit over tau <= 1 s must give it within 10 % on every axis.
    config = ImuConfig()
    a, w = _static_recording(config, 3600.0, seed=3)
    dt = 1.0 / config.sample_rate
    for samples, density in ((a, config.accel_noise_density), (w, config.gyro_noise_density)):
        tau, adev = allan_deviation(samples, dt, np.arange(1, 101))
        for axis in range(3):
            N = white_noise_coefficient(tau, adev[:, axis], tau_max=1.0)
            assert N == pytest.approx(density / math.sqrt(2.0), rel=0.10), (axis, N, density)
            # And the per-sample standard deviation is d sqrt(fs / 2) (sources.md s. 2).
            assert np.std(np.diff(samples[:, axis])) / math.sqrt(2.0) == pytest.approx(
                density * math.sqrt(config.sample_rate / 2.0), rel=0.05)


def test_static_recording_shows_the_bias_random_walk_slope():
    # A test sensor whose bias walk dominates from tau ~ 1 s (crossover sqrt(3) N / K):
    # beyond ~30 s the Allan deviation rises as K sqrt(tau / 3), slope +1/2.
    base = ImuConfig()
    walk = 2.0 * base.gyro_noise_density  # rad/s/sqrt(s); crossover at ~0.6 s
    config = dataclasses.replace(base, gyro_bias_random_walk=walk, resolution_bits=0,
                                 gyro_range=1e3)
    _, w = _static_recording(config, 2 * 3600.0, seed=4)
    tau, adev = allan_deviation(w, 1.0 / config.sample_rate)
    for axis in range(3):
        slope = log_log_slope(tau, adev[:, axis], 30.0, 700.0)
        assert slope == pytest.approx(0.5, abs=0.12), (axis, slope)
        long = (tau >= 30.0) & (tau <= 700.0)
        K = np.exp(np.mean(np.log(adev[long, axis] / np.sqrt(tau[long] / 3.0))))
        assert K == pytest.approx(walk, rel=0.3), (axis, K, walk)
        # The short-tau end still reads the white noise.
        assert white_noise_coefficient(tau, adev[:, axis], 0.05) == pytest.approx(
            config.gyro_noise_density / math.sqrt(2.0), rel=0.1)


def test_saturation_clips_and_quantisation_rounds():
    config = ImuConfig()
    accel, gyro = imu_channels(config)
    rng = np.random.default_rng(5)
    n = 500
    big = np.array([10.0, -10.0, 0.5])  # rad/s; the MPU-6050 gyro reads +-250 deg/s at most
    w, _ = gyro.record(big, rng.standard_normal((n, 3)), rng.standard_normal((n, 3)),
                       rng.standard_normal(3))
    np.testing.assert_array_equal(w[:, 0], config.gyro_range)
    np.testing.assert_array_equal(w[:, 1], -config.gyro_range)
    assert np.all(np.abs(w[:, 2] - 0.5) < 0.02)
    # 16 bits over +-250 deg/s: every reading is a multiple of the ADC step.
    step = 2.0 * config.gyro_range / 2 ** 16
    np.testing.assert_allclose(w[:, 2] / step, np.round(w[:, 2] / step), atol=1e-9)
    a, _ = accel.record(np.array([0.0, 0.0, -30.0]), rng.standard_normal((n, 3)),
                        rng.standard_normal((n, 3)), rng.standard_normal(3))
    np.testing.assert_array_equal(a[:, 2], -config.accel_range)


def _step_leaf(system, context, n, fix_inputs):
    """Runs n periodic updates of a LeafSystem, fixing its inputs before each."""
    out = []
    for k in range(n):
        fix_inputs(k)
        context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))
        out.append(context.Clone())
    return out


def test_leaf_system_update_equals_the_vectorised_model():
    # ImuNoise (one sample per event) and ChannelNoise.record (a whole recording in numpy)
    # must be the same model: same draws in, same samples and biases out.
    config = dataclasses.replace(ImuConfig(), gyro_bias_random_walk=1e-3,
                                 accel_bias_random_walk=1e-2)
    dut = ImuNoise(config)
    context = dut.CreateDefaultContext()
    rng = np.random.default_rng(6)
    n = 200
    truth_a = rng.normal(0.0, 5.0, (n, 3))
    truth_w = rng.normal(0.0, 1.0, (n, 3))
    white, walk, initial = (rng.standard_normal((n, 6)), rng.standard_normal((n, 6)),
                            rng.standard_normal(6))
    white_port, walk_port, initial_port = dut.get_noise_input_ports()
    initial_port.FixValue(context, initial)

    def fix(k):
        dut.get_accel_true_input_port().FixValue(context, truth_a[k])
        dut.get_gyro_true_input_port().FixValue(context, truth_w[k])
        white_port.FixValue(context, white[k])
        walk_port.FixValue(context, walk[k])

    measured = {name: [] for name in ("accel", "gyro", "accel_bias", "gyro_bias", "accel_true")}
    for k in range(n):
        fix(k)
        context.SetDiscreteState(dut.EvalUniquePeriodicDiscreteUpdate(context))
        for name in measured:
            measured[name].append(dut.get_output_port_by_signal(name).Eval(context).copy())
    accel, gyro = dut.channels()
    a, ba = accel.record(truth_a, white[:, :3], walk[:, :3], initial[:3])
    w, bw = gyro.record(truth_w, white[:, 3:], walk[:, 3:], initial[3:])
    np.testing.assert_allclose(measured["accel"], a, atol=1e-12)
    np.testing.assert_allclose(measured["gyro"], w, atol=1e-12)
    np.testing.assert_allclose(measured["accel_bias"], ba, atol=1e-12)
    np.testing.assert_allclose(measured["gyro_bias"], bw, atol=1e-12)
    np.testing.assert_array_equal(measured["accel_true"], truth_a)


# --- the Imu diagram on a plant ---------------------------------------------------------------

R_WB_STATIC = RollPitchYaw(0.3, -0.4, 1.0)


def _static_imu_diagram(config):
    """An Imu on a body welded to the world, tilted; logs every sample."""
    plant = MultibodyPlant(0.0)
    body = plant.AddRigidBody(
        "capsule", SpatialInertia.SolidCylinderWithMass(0.012, 0.0058, 0.0315, [0, 0, 1]))
    plant.WeldFrames(plant.world_frame(), body.body_frame(),
                     RigidTransform(R_WB_STATIC, [0.1, 0.2, 0.3]))
    plant.Finalize()
    builder = DiagramBuilder()
    builder.AddSystem(plant)
    imu = builder.AddNamedSystem("capsule.imu", Imu(plant, body, config))
    imu.connect_to_plant(builder, plant)
    period = 1.0 / config.sample_rate
    logs = {name: LogVectorOutput(imu.GetOutputPort(name), builder, period)
            for name in ("accel", "gyro", "accel_true", "gyro_true", "accel_bias", "gyro_bias")}
    return builder.Build(), logs


def _record(config, seconds, seed):
    diagram, logs = _static_imu_diagram(config)
    context = diagram.CreateDefaultContext()
    diagram.SetRandomContext(context, RandomGenerator(seed))
    simulator = Simulator(diagram, context)
    simulator.AdvanceTo(seconds)
    # The loggers publish before the sampling update at the same instant: drop t = 0.
    return {name: log.FindLog(context).data()[:, 1:].T for name, log in logs.items()}


def test_imu_on_a_static_tilted_body_reads_gravity_up_in_its_frame():
    config = dataclasses.replace(ImuConfig(), rpy_BS_deg=[0.0, 0.0, 90.0])
    rec = _record(config, 2.0, seed=1)
    R_WS = R_WB_STATIC.ToRotationMatrix() @ config.X_BS().rotation()
    # Drake's Accelerometer with the plant's gravity (MultibodyPlant's default is 9.81 m/s^2).
    up_S = R_WS.inverse() @ np.array([0.0, 0.0, 9.81])
    np.testing.assert_allclose(rec["accel_true"][-1], up_S, atol=1e-9)
    np.testing.assert_allclose(rec["gyro_true"][-1], 0.0, atol=1e-12)
    # Measured = truth + bias + white noise: the mean of 200 samples is within 4 standard
    # errors (sigma / sqrt(200)) of truth + bias.
    accel, gyro = imu_channels(config)
    for name, channel in (("accel", accel), ("gyro", gyro)):
        error = rec[name] - rec[f"{name}_true"] - rec[f"{name}_bias"]
        assert np.all(np.abs(error.mean(axis=0)) < 4 * channel.white_sigma / math.sqrt(200))


def test_drake_recording_adev_matches_density_and_seed_reproduces():
    # The same check as on the vectorised model, on 120 s sampled by Drake's simulator with
    # Drake's random sources: N = d / sqrt(2) within 10 % (three axes pooled).
    config = ImuConfig()
    rec = _record(config, 120.0, seed=11)
    dt = 1.0 / config.sample_rate
    for name, density in (("accel", config.accel_noise_density),
                          ("gyro", config.gyro_noise_density)):
        tau, adev = allan_deviation(rec[name], dt, np.arange(1, 51))
        pooled = np.sqrt(np.mean(adev ** 2, axis=1))
        N = white_noise_coefficient(tau, pooled, tau_max=0.5)
        assert N == pytest.approx(density / math.sqrt(2.0), rel=0.10), (name, N)


def test_same_seed_same_recording_other_seed_other_recording():
    config = ImuConfig()
    first = _record(config, 1.0, seed=7)
    again = _record(config, 1.0, seed=7)
    other = _record(config, 1.0, seed=8)
    for name in ("accel", "gyro", "accel_bias", "gyro_bias"):
        np.testing.assert_array_equal(first[name], again[name])
        assert not np.array_equal(first[name], other[name])
    # The turn-on bias is drawn per run, with the configured spread (0.2 deg/s).
    assert np.all(np.abs(first["gyro_bias"][0]) < 5 * config.gyro_initial_bias_sigma)
    assert not np.allclose(first["gyro_bias"][0], other["gyro_bias"][0])


def test_sensor_configs_load_from_yaml_and_reject_unknown_keys():
    from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed

    from capsule_drake.capsule.ahrs import AhrsConfig
    from capsule_drake.capsule.magnetometer import MagnetometerConfig

    for schema in (ImuConfig, AhrsConfig, MagnetometerConfig):
        assert yaml_load_typed(schema=schema, data=yaml_dump_typed(schema())) == schema()
        with pytest.raises(RuntimeError, match="unknown"):
            yaml_load_typed(schema=schema, data="{no_such_field: 1}")
    config = yaml_load_typed(schema=ImuConfig, data="{sample_rate: 200, p_BS: [0, 0, 0.004]}")
    assert config.sample_rate == 200.0 and config.p_BS == [0.0, 0.0, 0.004]
    assert config.gyro_noise_density == ImuConfig().gyro_noise_density
