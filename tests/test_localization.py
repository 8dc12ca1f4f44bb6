"""Magnetic localisation: the sensor position from the EPM's field, recovered from the
forward dipole model, kept on the patient's side, and tracking the capsule in a station."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import Demultiplexer

from capsule_drake.physics.magnetics import dipole_field
from capsule_drake.navigation.localization import MagneticLocalizer, locate_sensor
from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station


def test_the_position_that_makes_the_measured_field_is_recovered():
    rng = np.random.default_rng(1)
    p_E = np.array([0.02, -0.1, 0.35])
    for _ in range(30):
        m_E = 970.0 * (v := rng.normal(size=3)) / np.linalg.norm(v)
        direction = rng.normal(size=3)
        direction[2] = -abs(direction[2]) - 0.5  # the patient is below the magnet
        p_S = p_E + rng.uniform(0.08, 0.25) * direction / np.linalg.norm(direction)
        B_W = dipole_field(m_E, p_S - p_E)
        guess = p_S + rng.uniform(-0.02, 0.02, size=3)
        found, residual = locate_sensor(B_W, p_E, m_E, guess)
        np.testing.assert_allclose(found, p_S, atol=1e-6)
        assert residual < 1e-6 * np.linalg.norm(B_W)
    # From a guess above the magnet (the mirror image, the same field) it comes back down.
    found, _ = locate_sensor(B_W, p_E, m_E, 2.0 * p_E - p_S)
    np.testing.assert_allclose(found, p_S, atol=1e-6)


@pytest.mark.parametrize("sensor_range", [0.5])
def test_the_localizer_follows_the_capsule_in_the_station(sensor_range):
    scenario = load_scenario(name="WithSensors", override=(
        f"{{duration: 3.0, capsule: {{camera: null, lumen_tracker: null, magnetometer: "
        f"{{range: {sensor_range}}}}}, pseudo_force: null}}"))
    builder = DiagramBuilder()
    station = builder.AddSystem(make_station(scenario))
    from capsule_drake.anatomy import load_colon
    from capsule_drake.capsule.model import start_pose
    colon, _ = load_colon(scenario.colon)
    start = start_pose(colon, scenario.capsule.start_s)
    localizer = builder.AddSystem(MagneticLocalizer(
        scenario.capsule.magnetometer.X_BS(), scenario.epm.magnet.moment(),
        start.translation() + [0.01, -0.01, 0.005]))
    builder.Connect(station.GetOutputPort("capsule.magnetometer.B_S"),
                    localizer.GetInputPort("B_S"))
    # The orientation from the truth: the position part is what is tested here. (With the
    # AHRS's orientation, whose heading drifts 4-18 degrees in this run, the position is off
    # by about the sensor's distance from the EPM times that angle, 8-22 mm.)
    quaternion = builder.AddSystem(Demultiplexer([4, 9]))
    builder.Connect(station.GetOutputPort("capsule.state"), quaternion.get_input_port())
    builder.Connect(quaternion.get_output_port(0), localizer.GetInputPort("q_WB"))
    builder.Connect(station.GetOutputPort("epm.pose"), localizer.GetInputPort("epm_pose"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    errors = []
    for t in np.arange(0.5, 3.01, 0.5):
        simulator.AdvanceTo(t)
        context = simulator.get_context()
        estimate = localizer.GetOutputPort("capsule_pose").Eval(
            localizer.GetMyContextFromRoot(context))
        truth = station.GetOutputPort("capsule.state").Eval(station.GetMyContextFromRoot(context))
        assert localizer.GetOutputPort("valid").Eval(localizer.GetMyContextFromRoot(context))[0]
        errors.append(np.linalg.norm(estimate[4:7] - truth[4:7]))
    # Sensor noise (3.5 uT) and the turn-on bias (20 uT) against a field of ~10-50 mT that
    # changes by ~0.2-0.5 T/m: a fraction of a millimetre.
    assert max(errors) < 0.001, errors


def test_a_bad_reading_holds_the_estimate():
    from pydrake.math import RigidTransform
    localizer = MagneticLocalizer(RigidTransform(), 970.0, [0.0, 0.0, 0.1])
    context = localizer.CreateDefaultContext()
    localizer.GetInputPort("B_S").FixValue(context, [np.nan, 0.0, 0.0])
    localizer.GetInputPort("q_WB").FixValue(context, [1.0, 0.0, 0.0, 0.0])
    localizer.GetInputPort("epm_pose").FixValue(context, [0.0, 0.0, 0.3, 0.0, 0.0, 1.0])
    simulator = Simulator(localizer, context)
    simulator.AdvanceTo(0.05)
    np.testing.assert_array_equal(localizer.GetOutputPort("capsule_pose").Eval(context)[4:],
                                  [0.0, 0.0, 0.1])
    assert localizer.GetOutputPort("valid").Eval(context)[0] == 0.0
