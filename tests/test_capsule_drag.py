"""The capsule's speed-dependent resistance (contact.drag_*): a linear damping of its velocity
relative to the world (the colon), checked against the closed form of m v' = -c v."""

import numpy as np
import pytest
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.capsule.model import CAPSULE_BODY
from capsule_drake.models import configure_parser, model_url
from capsule_drake.physics.contact.common import add_capsule_drag
from capsule_drake.scenario import ScenarioError, load_scenario


def _free_capsule(override):
    """The capsule alone, no gravity, no contact, with the scenario's drag."""
    scenario = load_scenario(override=override)
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=0.001), builder)
    configure_parser(Parser(plant)).AddModels(url=model_url("capsule.sdf"))
    add_capsule_drag(plant, scenario.contact.drag_translational,
                     scenario.contact.drag_rotational)
    plant.mutable_gravity_field().set_gravity_vector([0.0, 0.0, 0.0])
    plant.Finalize()
    diagram = builder.Build()
    return diagram, plant


def test_drag_decays_the_velocity_as_the_closed_form():
    c, c_r = 0.5, 2.0e-6
    diagram, plant = _free_capsule(
        f"{{contact: {{drag_translational: {c}, drag_rotational: {c_r}}}}}")
    body = plant.GetBodyByName(CAPSULE_BODY)
    m = body.default_mass()
    I_zz = body.default_rotational_inertia().get_moments()[2]
    simulator = Simulator(diagram)
    context = plant.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    v0, w0 = np.array([0.1, -0.05, 0.02]), 3.0
    # Spin about the body's axis of symmetry (z, a principal axis): no gyroscopic coupling.
    plant.SetVelocities(context, np.concatenate([[0.0, 0.0, w0], v0]))
    T = 0.05
    simulator.AdvanceTo(T)
    v = plant.GetVelocities(context)
    # Drake integrates joint damping implicitly over the 1 ms step: v_n = v0 / (1 + c dt /
    # m)^n exactly, which tends to the continuous exp(-c t / m) (5 % apart here, where the
    # velocity falls 8-fold in 50 steps).
    n, dt = round(T / 0.001), 0.001
    np.testing.assert_allclose(v[3:], v0 / (1.0 + c * dt / m) ** n, rtol=1e-6)
    np.testing.assert_allclose(v[3:], v0 * np.exp(-c * T / m), rtol=0.05)
    assert np.linalg.norm(v[:2]) < 1e-9
    assert v[2] == pytest.approx(w0 / (1.0 + c_r * dt / I_zz) ** n, rel=1e-6)
    assert v[2] == pytest.approx(w0 * np.exp(-c_r * T / I_zz), rel=0.05)
    # And the decay is real: the time constants are within the run.
    assert np.exp(-c * T / m) < 0.2 and np.exp(-c_r * T / I_zz) < 0.9


def test_no_drag_keeps_the_velocity():
    diagram, plant = _free_capsule("{}")
    simulator = Simulator(diagram)
    context = plant.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    plant.SetVelocities(context, [0.0, 0.0, 0.0, 0.1, 0.0, 0.0])
    simulator.AdvanceTo(0.05)
    np.testing.assert_allclose(plant.GetVelocities(context)[3:], [0.1, 0.0, 0.0], rtol=1e-12)


def test_negative_drag_is_a_scenario_error():
    with pytest.raises(ScenarioError, match="drag_translational"):
        load_scenario(override="{contact: {drag_translational: -1.0}}")
