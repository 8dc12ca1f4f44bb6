"""The contact's pressure and the tissue-safety measures (physics/tissue.py,
physics/contact_monitor.py peak_contact_pressure, io/metrics.py pressure_metrics)."""

import numpy as np
import pytest
from pydrake.geometry import (AddCompliantHydroelasticProperties, AddContactMaterial,
                              AddRigidHydroelasticProperties, Box, Capsule, ProximityProperties)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, CoulombFriction
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.io.metrics import pressure_metrics
from capsule_drake.physics.contact_monitor import ContactMonitor, peak_contact_pressure
from capsule_drake.physics.tissue import INJURY_PRESSURE, ISCHAEMIA_PRESSURE, time_above

RADIUS, LENGTH = 0.0058, 0.020   # the capsule's collision shape (m)


def capsule_and_plate(modulus: float = 5.0e6, point_contact: bool = False,
                      plate_x: float = 0.0):
    """A capsule (body "capsule", axis along x: lying on its side; compliant hydroelastic of
    `modulus`, or point contact) free above a rigid plate whose top is z = 0, centred at
    x = `plate_x`: (builder, finalised plant, scene graph, body)."""
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, 0.001)
    plant.SetUseSampledOutputPorts(False)   # contact results of the state as it is set
    body = plant.AddRigidBody("capsule", SpatialInertia.SolidCapsuleWithMass(
        0.005, RADIUS, LENGTH, [0.0, 0.0, 1.0]))
    soft, hard = ProximityProperties(), ProximityProperties()
    for props in (soft, hard):
        AddContactMaterial(5.0, 2.0e4, CoulombFriction(0.2, 0.2), props)
    if not point_contact:
        AddCompliantHydroelasticProperties(0.004, modulus, soft)
        AddRigidHydroelasticProperties(properties=hard)
    plant.RegisterCollisionGeometry(body, RigidTransform(RotationMatrix.MakeYRotation(np.pi / 2)),
                                    Capsule(RADIUS, LENGTH), "capsule", soft)
    plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform([plate_x, 0.0, -0.05]),
                                    Box(0.2, 0.2, 0.1), "plate", hard)
    plant.Finalize()
    return builder, plant, scene_graph, body


def capsule_on_a_plate(modulus: float, point_contact: bool = False):
    """`capsule_and_plate` with a ContactMonitor: (plant, its context, the capsule body, the
    monitor's context, the monitor)."""
    builder, plant, _, body = capsule_and_plate(modulus, point_contact)
    monitor = builder.AddSystem(ContactMonitor())
    builder.Connect(plant.get_contact_results_output_port(), monitor.get_input_port())
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    return (plant, plant.GetMyMutableContextFromRoot(context), body,
            monitor.GetMyContextFromRoot(context), monitor)


@pytest.mark.parametrize("modulus", [5.0e6, 2.0e5])
def test_peak_pressure_is_the_hydroelastic_closed_form(modulus):
    """A compliant capsule's pressure field is E times the depth over the radius (Drake's
    field for a capsule: linear from 0 at the surface to E on its axis), so pressed a depth
    delta into a rigid plate its peak is E delta / R: the monitor's output agrees to 1e-9,
    and the force grows with depth."""
    plant, context, body, monitor_context, monitor = capsule_on_a_plate(modulus)
    forces = []
    for delta in (0.0002, 0.0005, 0.001, 0.002):
        plant.SetFreeBodyPose(context, body, RigidTransform([0.0, 0.0, RADIUS - delta]))
        peak = monitor.GetOutputPort("peak_pressure").Eval(monitor_context)[0]
        assert peak == pytest.approx(modulus * delta / RADIUS, rel=1e-9)
        forces.append(monitor.GetOutputPort("contact_load").Eval(monitor_context)[0])
    assert np.all(np.diff(forces) > 0.0)
    plant.SetFreeBodyPose(context, body, RigidTransform([0.0, 0.0, RADIUS + 0.001]))
    assert monitor.GetOutputPort("peak_pressure").Eval(monitor_context)[0] == 0.0


def test_point_contact_has_no_pressure():
    """Point contact has a force but no pressure field: NaN, and the metrics say None."""
    plant, context, body, monitor_context, monitor = capsule_on_a_plate(0.0, point_contact=True)
    plant.SetFreeBodyPose(context, body, RigidTransform([0.0, 0.0, RADIUS - 0.0005]))
    results = plant.get_contact_results_output_port().Eval(context)
    assert results.num_point_pair_contacts() > 0
    assert np.isnan(peak_contact_pressure(results))
    assert monitor.GetOutputPort("contact_load").Eval(monitor_context)[0] > 0.0
    times = np.arange(5) * 0.01
    assert pressure_metrics(times, np.full(5, np.nan)) == {
        "peak_contact_pressure_kPa": None, "time_above_injury_pressure_s": None,
        "time_above_ischaemia_pressure_s": None}
    assert pressure_metrics(times, None)["peak_contact_pressure_kPa"] is None
    # A run's samples before the capsule touched the wall are 0: not a pressure either.
    assert pressure_metrics(times, [0.0, 0.0, np.nan, np.nan, np.nan])[
        "peak_contact_pressure_kPa"] is None


def test_time_above_a_threshold_is_the_measure_of_the_samples_above_it():
    """A pressure ramp 0 -> 600 kPa over 6 s sampled every 10 ms is above 330 kPa for the
    last 2.7 s (to a sample) and above 4 kPa for all but its first 0.04 s."""
    times = np.arange(0.0, 6.0 + 1e-9, 0.01)
    ramp = 100e3 * times
    assert time_above(times, ramp, INJURY_PRESSURE) == pytest.approx(2.7, abs=0.011)
    assert time_above(times, ramp, ISCHAEMIA_PRESSURE) == pytest.approx(5.96, abs=0.011)
    metrics = pressure_metrics(times, ramp)
    assert metrics["peak_contact_pressure_kPa"] == pytest.approx(600.0)
    assert metrics["time_above_injury_pressure_s"] == pytest.approx(2.7, abs=0.011)
    assert time_above(times[:1], ramp[:1], 0.0) == 0.0
    # Uneven samples: each is held until the next.
    assert time_above([0.0, 1.0, 3.0, 3.5], [5.0, 0.0, 5.0, 5.0], 1.0) == pytest.approx(1.5)


def test_the_thresholds_are_the_cited_values():
    """330 kPa (BMJ SIT 2021: 329-330 kPa) and 30 mmHg (Boley 1969) in pascals."""
    assert INJURY_PRESSURE == pytest.approx(330e3)
    assert ISCHAEMIA_PRESSURE == pytest.approx(3999.7, abs=0.1)
