"""Magnetometer: the field of the other magnets at the sensor, in its frame, with noise."""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.common import RandomGenerator
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource, LogVectorOutput

from capsule_drake.physics.magnetics import dipole_field
from capsule_drake.capsule.imu import add_random_sources
from capsule_drake.physics.magnet_force import MagneticForce, MagnetSpec
from capsule_drake.capsule.magnetometer import Magnetometer, MagnetometerConfig

MU0 = 4e-7 * math.pi
EPM_MOMENT = 970.0  # A m^2, docs/sources.md section 1
IPM = MagnetSpec(name="ipm", body="capsule", p_BM=[0.0, 0.0, -0.003], axis_B=[0, 0, 1],
                 moment=1.26)
EPM = MagnetSpec(name="epm", body="epm", p_BM=[0.0, 0.0, 0.0], axis_B=[0, 0, 1],
                 moment=EPM_MOMENT)
IDEAL = MagnetometerConfig(noise_density=0.0, initial_bias_sigma=0.0, range=10.0,
                           resolution_bits=0)


def _plant():
    plant = MultibodyPlant(1e-3)
    capsule = plant.AddRigidBody(
        "capsule", SpatialInertia.SolidCylinderWithMass(0.012, 0.0058, 0.0315, [0, 0, 1]))
    plant.AddRigidBody("epm", SpatialInertia.SolidCylinderWithMass(6.2, 0.05, 0.1, [0, 0, 1]))
    plant.Finalize()
    return plant, capsule


def _poses(plant, X_W_capsule, X_W_epm):
    poses = [RigidTransform()] * plant.num_bodies()
    poses[int(plant.GetBodyByName("capsule").index())] = X_W_capsule
    poses[int(plant.GetBodyByName("epm").index())] = X_W_epm
    return poses


def _read(dut, poses):
    context = dut.CreateDefaultContext()
    dut.get_body_poses_input_port().FixValue(context, poses)
    for port in dut.get_noise_input_ports():
        port.FixValue(context, np.zeros(3))
    context.SetDiscreteState(dut.EvalUniquePeriodicDiscreteUpdate(context))
    return (dut.get_B_S_output_port().Eval(context).copy(),
            dut.get_B_S_true_output_port().Eval(context).copy())


def test_coaxial_field_matches_the_textbook_closed_form():
    # On the axis of a dipole, B = mu0 / (4 pi) * 2 m / r^3 along the moment (Furlani 2001).
    plant, capsule = _plant()
    config = dataclasses.replace(IDEAL, p_BS=[0.0, 0.0, 0.008])
    dut = Magnetometer(plant, capsule, [EPM], config)
    r = 0.15
    poses = _poses(plant, RigidTransform([0.0, 0.0, -0.008]),
                   RigidTransform([0.0, 0.0, r]))
    _, truth = _read(dut, poses)
    np.testing.assert_allclose(truth, [0.0, 0.0, MU0 / (4 * math.pi) * 2 * EPM_MOMENT / r**3],
                               rtol=1e-12)
    assert truth[2] == pytest.approx(0.0575, rel=0.01)  # sources.md s. 1: 57.5 mT at 15 cm


def test_reading_is_the_dipole_field_at_the_sensor_rotated_into_the_sensor_frame():
    plant, capsule = _plant()
    config = dataclasses.replace(IDEAL, p_BS=[0.001, -0.002, 0.008],
                                 rpy_BS_deg=[10.0, -20.0, 35.0])
    dut = Magnetometer(plant, capsule, [IPM, EPM], config)
    X_WC = RigidTransform(RollPitchYaw(0.3, -1.1, 2.0), [0.02, -0.05, 0.01])
    R_WE = RollPitchYaw(0.7, 0.2, -0.4).ToRotationMatrix()
    X_WE = RigidTransform(R_WE, [0.05, 0.08, 0.14])
    _, truth = _read(dut, _poses(plant, X_WC, X_WE))
    # Independent route: explicit matrices.
    R_BS = RollPitchYaw(np.deg2rad([10.0, -20.0, 35.0])).ToRotationMatrix().matrix()
    R_WS = X_WC.rotation().matrix() @ R_BS
    p_WS = X_WC.rotation().matrix() @ np.array(config.p_BS) + X_WC.translation()
    m_W = R_WE.matrix() @ np.array([0.0, 0.0, EPM_MOMENT])
    expected = R_WS.T @ dipole_field(m_W, p_WS - X_WE.translation())
    np.testing.assert_allclose(truth, expected, rtol=1e-12)
    # The capsule's own magnet is not a source.
    assert dut.excluded_source_names() == ["ipm"]
    assert dut.source_names() == ["epm"]


def test_sensor_at_the_magnet_reads_what_magnetic_force_reports():
    # MagneticForce's ipm.B_B is the field of the other magnets at the IPM in the body frame:
    # a magnetometer placed at the IPM centre must read the same.
    plant, capsule = _plant()
    config = dataclasses.replace(IDEAL, p_BS=IPM.p_BM)
    dut = Magnetometer(plant, capsule, [IPM, EPM], config)
    force = MagneticForce(plant, [IPM, EPM])
    poses = _poses(plant, RigidTransform(RollPitchYaw(0.2, 0.5, -0.3), [0.0, 0.01, 0.0]),
                   RigidTransform(RollPitchYaw(0.0, 0.4, 0.0), [0.03, 0.0, 0.12]))
    context = force.CreateDefaultContext()
    force.get_body_poses_input_port().FixValue(context, poses)
    _, truth = _read(dut, poses)
    np.testing.assert_allclose(truth, force.get_B_B_output_port("ipm").Eval(context),
                               rtol=1e-12)


def test_saturation_and_quantisation():
    plant, capsule = _plant()
    config = dataclasses.replace(IDEAL, range=0.05, resolution_bits=16)
    dut = Magnetometer(plant, capsule, [EPM], config)
    # 10 cm coaxial: about 194 mT, beyond the 50 mT range.
    measured, truth = _read(dut, _poses(plant, RigidTransform([0, 0, -0.008]),
                                        RigidTransform([0, 0, 0.10])))
    assert truth[2] > 0.19
    assert measured[2] == 0.05
    # Side-on at 30 cm: about 3.6 mT, rounded to the 1.5 uT step.
    measured, truth = _read(dut, _poses(plant, RigidTransform([0, 0, -0.008]),
                                        RigidTransform([0.3, 0, 0.0])))
    step = 0.1 / 2**16
    assert abs(measured[2] - truth[2]) <= step / 2 + 1e-15
    assert measured[2] / step == pytest.approx(round(measured[2] / step), abs=1e-9)


def _static_recording(config, seconds, seed):
    plant, capsule = _plant()
    builder = DiagramBuilder()
    dut = builder.AddNamedSystem("capsule.magnetometer",
                                 Magnetometer(plant, capsule, [IPM, EPM], config))
    poses = _poses(plant, RigidTransform([0, 0, -0.008]), RigidTransform([0.05, 0.0, 0.2]))
    source = builder.AddSystem(ConstantValueSource(AbstractValue.Make(poses)))
    builder.Connect(source.get_output_port(), dut.get_body_poses_input_port())
    add_random_sources(builder, dut.get_noise_input_ports(), dut.period())
    logs = [LogVectorOutput(port, builder, dut.period()) for port in
            (dut.get_B_S_output_port(), dut.get_B_S_true_output_port(),
             dut.get_bias_output_port())]
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    diagram.SetRandomContext(context, RandomGenerator(seed))
    Simulator(diagram, context).AdvanceTo(seconds)
    return [log.FindLog(context).data()[:, 1:].T for log in logs]


def test_noise_statistics_and_seeding():
    config = dataclasses.replace(MagnetometerConfig(), range=1.0, resolution_bits=0,
                                 bias_random_walk=0.0)
    measured, truth, bias = _static_recording(config, 30.0, seed=3)
    n = len(measured)
    sigma = config.noise_density * math.sqrt(config.sample_rate / 2.0)
    residual = measured - truth - bias
    # Per-sample standard deviation = density sqrt(fs / 2) (sources.md s. 2), within
    # the ~2 % sampling error of 3000 samples (3 x that); zero mean within 4 standard errors.
    np.testing.assert_allclose(residual.std(axis=0), sigma, rtol=0.06)
    assert np.all(np.abs(residual.mean(axis=0)) < 4 * sigma / math.sqrt(n))
    # No random walk configured: the turn-on bias holds; it is a draw of the configured size.
    np.testing.assert_array_equal(bias, np.tile(bias[0], (n, 1)))
    assert np.all(np.abs(bias[0]) < 5 * config.initial_bias_sigma)
    again = _static_recording(config, 1.0, seed=3)[0]
    other = _static_recording(config, 1.0, seed=4)[0]
    np.testing.assert_array_equal(again, measured[:len(again)])
    assert not np.array_equal(other, again)
