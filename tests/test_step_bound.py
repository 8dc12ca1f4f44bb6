"""The time-step bound (physics/step_bound.py): its formula against independent routes (the
explicit-Euler map of a torsional oscillator, and Drake's own discrete plant turning the
capsule under the magnet), and the shipped scenarios accepted at their own steps."""

import math
import time

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.multibody.tree import RevoluteJoint, SpatialInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.models import configure_parser, model_url
from capsule_drake.physics.implicit_torque import restoring_part
from capsule_drake.physics.magnet_force import MagneticForce, MagnetSpec
from capsule_drake.physics.magnetics import MagnetGeometry, dipole_field, dipole_force
from capsule_drake.physics.step_bound import (SAFETY, capsule_inertia, closest_distance,
                                              magnet_stiffness, step_bounds, time_step_bound)
from capsule_drake.scenario import DEFAULT_SCENARIO_FILE, load_scenario, scenario_names

EPM_MOMENT = MagnetGeometry().moment()           # 970 A m^2
IPM_MOMENT = MagnetGeometry(shape="cylinder", dimensions=[0.0111, 0.0111]).moment()


# --- explicit (symplectic) Euler on x'' = -omega^2 x: the map the bound rests on ----------

def symplectic_euler(omega, dt, steps, hold=1, x0=1.0):
    """Positions of x'' = -omega^2 x stepped as Drake steps an explicit force: v first from
    the force of the state at the start of the step, then x from the new v; the force is
    recomputed every `hold` steps (a ZeroOrderHold)."""
    x, v, force = x0, 0.0, 0.0
    xs = np.empty(steps)
    for k in range(steps):
        if k % hold == 0:
            force = -omega * omega * x
        v += dt * force
        x += dt * v
        xs[k] = x
    return xs


def test_explicit_euler_is_stable_below_two_over_omega_and_diverges_above():
    omega = 853.0
    for h, stable in ((1.9, True), (1.99, True), (2.01, False), (2.2, False)):
        xs = symplectic_euler(omega, h / omega, 400 if not stable else 4000)
        # Below the limit the invariant ellipse bounds |x| by 1 / sqrt(1 - h^2/4).
        peak = np.max(np.abs(xs))
        if stable:
            assert peak <= 1.0 / math.sqrt(1.0 - h * h / 4.0) + 1e-9
        else:
            assert peak > 1e6


def test_explicit_euler_frequency_error_at_the_bound():
    """At omega dt = 2 SAFETY = 1 the oscillation runs 4.7 % fast (2 asin(h/2) / h - 1)."""
    omega, h = 300.0, 2.0 * SAFETY
    dt = h / omega
    xs = symplectic_euler(omega, dt, 4000)
    crossings = np.flatnonzero(np.diff(xs > 0.0))
    period = 2.0 * (crossings[-1] - crossings[0]) / (len(crossings) - 1) * dt
    error = 2.0 * math.pi / period / omega - 1.0
    assert error == pytest.approx(2.0 * math.asin(h / 2.0) / h - 1.0, abs=2e-3)
    assert 0.04 < error < 0.05


@pytest.mark.parametrize("n", [2, 4])
def test_a_held_force_feeds_energy_in_at_any_period(n):
    """With the force held n > 1 steps, the amplitude grows by sqrt(1 + (n-1) h^2 / (2n))
    per hold (h = omega T): even at omega T = 0.2, far inside the per-step limit."""
    omega, h = 100.0, 0.2
    dt = h / omega / n
    holds = 2000
    xs = symplectic_euler(omega, dt, holds * n, hold=n)
    growth = math.sqrt(1.0 + (n - 1) * h * h / (2 * n)) ** holds
    late = np.max(np.abs(xs[-20 * n:]))
    assert late == pytest.approx(growth, rel=0.1)
    assert late > 5.0


# --- the stiffness formula against the dipole model --------------------------------------

def test_largest_force_gradient_is_at_most_four_force_over_r():
    """K = 4 F / r (F the coaxial force) bounds the force's Jacobian over random attitudes."""
    rng = np.random.default_rng(0)
    r = 0.0708
    coaxial = 3.0 * 1e-7 * 2.0 * EPM_MOMENT * IPM_MOMENT / r**4
    worst = 0.0
    for _ in range(300):
        a, c = rng.normal(size=3), rng.normal(size=3)
        m_a = EPM_MOMENT * a / np.linalg.norm(a)
        m_c = IPM_MOMENT * c / np.linalg.norm(c)
        u = rng.normal(size=3)
        p = r * u / np.linalg.norm(u)
        eps = 1e-6
        J = np.column_stack([(dipole_force(m_a, m_c, p + eps * e)
                              - dipole_force(m_a, m_c, p - eps * e)) / (2 * eps)
                             for e in np.eye(3)])
        worst = max(worst, np.linalg.norm(J, 2))
        assert np.linalg.norm(dipole_force(m_a, m_c, p)) <= coaxial * (1 + 1e-9)
    assert worst <= 4.0 * coaxial / r * (1 + 1e-6)
    assert worst > 0.8 * 4.0 * coaxial / r   # and it is nearly reached


def rotation(axis, angle):
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * K @ K


def test_rotational_stiffness_bounds_the_dipole_energy_over_all_attitudes():
    """k_rot = m_c B + 2 F d + K d^2 bounds U'' of U(theta) = -m_c . B, the capsule at
    equilibrium (its magnet along the field) turned about its centre of mass (its magnet d
    off it along the axis) across its axis, over random attitudes of both magnets; and the
    largest U'' found comes close to it."""
    capsule = capsule_inertia()
    r, d = 0.0708, capsule.ipm_offset
    bound = magnet_stiffness(EPM_MOMENT, IPM_MOMENT, r, capsule).rotational
    rng = np.random.default_rng(1)
    worst = 0.0
    for _ in range(1500):
        u, a = rng.normal(size=3), rng.normal(size=3)
        p_M = r * u / np.linalg.norm(u)
        m_E = EPM_MOMENT * a / np.linalg.norm(a)
        axis = dipole_field(m_E, p_M)
        axis /= np.linalg.norm(axis)
        across = np.cross(axis, rng.normal(size=3))
        for sign in (1.0, -1.0):
            centre = p_M - sign * d * axis
            for turn in (across, np.cross(axis, across)):
                def energy(theta):
                    R = rotation(turn, theta)
                    return -(IPM_MOMENT * R @ axis) @ dipole_field(m_E, centre + R @ (p_M - centre))
                h = 1e-4
                k = (energy(h) - 2.0 * energy(0.0) + energy(-h)) / (h * h)
                worst = max(worst, k)
    assert worst <= bound
    assert worst > 0.97 * bound


# --- Drake's plant: the capsule turned by the magnet, at the bound's limit ---------------

EXPLICIT = "{plant: {time_step: 0.001}, magnet_force: {implicit: false}}"
"""The Default scenario with its magnet force explicit, at a step its bound allows."""


def magnet_pendulum(dt, r, theta0=0.02, implicit=False):
    """The capsule of models/capsule.sdf on a pin across its axis at its centre of mass, the
    EPM welded below it, its centre r from the capsule's magnet (3 mm below the pin), both
    magnetised up: coaxial (the stiffest field), the magnet's pull on the lever arm
    stiffening too, as the bound assumes. No gravity. `implicit`: the magnet's torque made
    implicit (MagneticForce's implicit_step). (simulator, plant, context, joint)."""
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=dt), builder)
    plant.mutable_gravity_field().set_gravity_vector([0.0, 0.0, 0.0])
    instance, = configure_parser(Parser(plant)).AddModels(url=model_url("capsule.sdf"))
    capsule = plant.GetBodyByName("capsule", instance)
    pin = plant.AddJoint(RevoluteJoint("pin", plant.world_frame(), capsule.body_frame(),
                                       [1.0, 0.0, 0.0]))
    epm = plant.AddRigidBody("epm", plant.AddModelInstance("epm"),
                             SpatialInertia.SolidSphereWithMass(6.2, 0.05))
    p_BM = list(plant.GetFrameByName("ipm", instance).GetFixedPoseInBodyFrame().translation())
    plant.WeldFrames(plant.world_frame(), epm.body_frame(),
                     RigidTransform([0.0, 0.0, p_BM[2] - r]))
    plant.Finalize()
    force = builder.AddSystem(MagneticForce(plant, [
        MagnetSpec(name="ipm", body="capsule", p_BM=p_BM, axis_B=[0.0, 0.0, 1.0],
                   moment=IPM_MOMENT),
        MagnetSpec(name="epm", body="epm", axis_B=[0.0, 0.0, 1.0], moment=EPM_MOMENT)],
        implicit_step=dt if implicit else 0.0))
    builder.Connect(plant.get_body_poses_output_port(), force.get_body_poses_input_port())
    if implicit:
        builder.Connect(plant.get_body_spatial_velocities_output_port(),
                        force.get_body_spatial_velocities_input_port())
    builder.Connect(force.get_applied_spatial_force_output_port(),
                    plant.get_applied_spatial_force_input_port())
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = plant.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    pin.set_angle(context, theta0)
    return simulator, plant, context, pin


def pendulum_angles(dt, r, duration, theta0=0.02, implicit=False):
    simulator, _, context, pin = magnet_pendulum(dt, r, theta0, implicit)
    angles = []
    for k in range(1, int(round(duration / dt)) + 1):
        simulator.AdvanceTo(k * dt)
        angle = pin.get_angle(context)
        angles.append(angle)
        if not abs(angle) < 10.0:   # spun off (or NaN): diverged
            break
    return np.array(angles)


def measured_omega(r):
    """The pendulum's angular frequency, measured in Drake at a short step (0.02 ms)."""
    dt = 2e-5
    angles = pendulum_angles(dt, r, 0.03)
    crossings = np.flatnonzero(np.diff(angles > 0.0))
    return math.pi * (len(crossings) - 1) / ((crossings[-1] - crossings[0]) * dt)


R_PENDULUM = 0.0708   # the Default scenario's closest EPM distance


def test_drake_turns_the_capsule_at_the_omega_the_bound_assumes():
    """Drake's own oscillation (independent of the formula) in the stiffest attitude is the
    bound's omega within 1 % (measured 895 rad/s, formula 898)."""
    omega = measured_omega(R_PENDULUM)
    bound = magnet_stiffness(EPM_MOMENT, IPM_MOMENT, R_PENDULUM, capsule_inertia())
    assert omega == pytest.approx(bound.omega_rotation, rel=0.01)


def test_drake_applies_the_magnet_explicitly_stable_below_two_over_omega_unstable_above():
    """The magnet pendulum in Drake's discrete plant: bounded at 0.9 x 2/omega, spun off
    within 100 steps at 1.1 x 2/omega (omega measured in Drake): the magnet torque is an
    explicit force, and the stability limit is explicit Euler's. At the bound's own step
    the amplitude stays within the invariant ellipse's 1 / sqrt(1 - (omega dt / 2)^2)."""
    omega = measured_omega(R_PENDULUM)
    limit = 2.0 / omega
    stable = pendulum_angles(0.9 * limit, R_PENDULUM, 300 * 0.9 * limit)
    assert len(stable) == 300 and np.max(np.abs(stable)) < 3.0 * 0.02
    unstable = pendulum_angles(1.1 * limit, R_PENDULUM, 100 * 1.1 * limit)
    assert np.max(np.abs(unstable)) > 1.0
    # and the bound's step (SAFETY x the limit at the bound's own, larger omega) is well
    # inside: stable, and the amplitude kept within the invariant ellipse's.
    dt = step_bounds(load_scenario(name="Default", override=EXPLICIT)).magnet_step
    assert dt == pytest.approx(SAFETY * limit, rel=0.01)
    inside = pendulum_angles(dt, R_PENDULUM, 300 * dt)
    assert np.max(np.abs(inside)) < 1.2 * 0.02


# --- the implicit magnet torque ---------------------------------------------------------

@pytest.mark.parametrize("factor", [0.1, 2.0, 8.0])
def test_the_implicit_torque_is_backward_euler_of_the_magnet_pendulum(factor):
    """With the torque implicit, the pendulum at `factor` x the explicit limit 2/omega (where
    explicit Euler spins off within 3 steps at 2x) follows the closed-form recurrence of
    backward Euler for I theta'' = -k theta, k = I omega^2 (omega measured in Drake):
    w+ = (I w - h k theta) / (I + h^2 k), theta+ = theta + h w+; within 3 % of the start
    angle over 60 steps, decaying, never growing."""
    omega = measured_omega(R_PENDULUM)
    dt = factor * 2.0 / omega
    angles = pendulum_angles(dt, R_PENDULUM, 60 * dt, implicit=True)
    assert len(angles) == 60
    a = (omega * dt) ** 2
    theta, rate, expected = 0.02, 0.0, []
    for _ in range(60):
        rate = (rate - dt * omega**2 * theta) / (1.0 + a)
        theta = theta + dt * rate
        expected.append(theta)
    assert np.max(np.abs(angles - np.array(expected))) < 0.03 * 0.02
    assert np.max(np.abs(angles)) <= 0.02 + 1e-12
    explicit = pendulum_angles(max(dt, 2.2 / omega), R_PENDULUM, 40 * dt)
    assert factor < 1.0 or np.max(np.abs(explicit)) > 1.0


def test_a_held_capsule_comes_to_feel_the_full_magnet_torque():
    """The pendulum's pin locked (the capsule held, as friction holds it on the wall) at the
    explicit limit 2/omega (a = (omega h)^2 = 4): the applied torque converges to the
    explicit one, m x B plus the pull's moment. A prediction that took the capsule to turn
    freely would apply only 1 / (1 + a) of it for good; the last step's reaction, read off
    the velocity, corrects it by a factor a / (1 + a) = 0.8 a step: within 1e-5 after 60
    steps. (At a = 64 the same takes ~900 steps: the convergence slows as the step grows.)"""
    omega = measured_omega(R_PENDULUM)
    dt = 2.0 / omega
    simulator, plant, context, pin = magnet_pendulum(dt, R_PENDULUM, 0.05, implicit=True)
    pin.Lock(context)
    diagram = simulator.get_system()
    force = next(s for s in diagram.GetSystems() if isinstance(s, MagneticForce))
    force_context = force.GetMyContextFromRoot(simulator.get_context())
    simulator.AdvanceTo(60 * dt)
    applied = force.get_applied_spatial_force_output_port().Eval(force_context)[0]
    explicit = force.get_F_W_output_port("ipm").Eval(force_context)[:3]
    assert np.linalg.norm(explicit) > 1e-3
    np.testing.assert_allclose(applied.F_Bq_W.rotational(), explicit, rtol=1e-5,
                               atol=1e-9 * np.linalg.norm(explicit))
    assert pin.get_angle(context) == pytest.approx(0.05, abs=1e-12)


def test_the_pendulum_turned_against_the_field_is_not_held_back():
    """The capsule pinned upside down (its magnet against the EPM's field, an unstable
    equilibrium: the torque turns it further away) at 8 x the explicit limit: there the
    symmetric stiffness has modes with h^2 omega^2 far above 1/2, so only its restoring part
    is implicit (restoring_part) and the unstable turn is left explicit. The capsule turns
    away from upside down, as the physics does, monotonically at first, its angle finite
    (with the full stiffness taken implicitly, I - h^2 S is not positive definite: the step
    has no sound solution)."""
    omega = measured_omega(R_PENDULUM)
    dt = 8.0 * 2.0 / omega
    angles = pendulum_angles(dt, R_PENDULUM, 10 * dt, theta0=math.pi - 0.02, implicit=True)
    assert np.all(np.isfinite(angles))
    away = np.abs(angles - math.pi)
    assert away[1] > away[0] > 0.02
    assert away[-1] > 0.5
    S = np.array([[-2.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(restoring_part(tuple(map(tuple, S.tolist())),
                                              tuple(map(tuple, np.eye(3).tolist()))),
                               np.diag([-2.0, 0.0, 0.0]), atol=1e-12)


# --- the bound on the shipped scenarios --------------------------------------------------

def test_default_bound_numbers():
    """The Default scenario's numbers in the module's docstring: with the magnet explicit,
    its turning bounds the step at 1.11 ms; with its torque implicit (the default), the
    contact's 2 ms, the pull allowing 2.69 ms."""
    scenario = load_scenario(name="Default", override=EXPLICIT)
    distance, _ = closest_distance(scenario)
    assert distance == pytest.approx(0.0708, abs=1e-4)
    bounds = step_bounds(scenario)
    assert bounds.stiffness.field == pytest.approx(0.547, abs=1e-3)
    assert bounds.stiffness.omega == pytest.approx(898, abs=2)
    assert bounds.plant_step == pytest.approx(1.11e-3, abs=1e-5)
    assert bounds.contact_step == pytest.approx(2e-3)
    implicit = step_bounds(load_scenario(name="Default"))
    assert implicit.stiffness.omega_translation == pytest.approx(371, abs=2)
    assert implicit.magnet_step == pytest.approx(1.0 / 371, rel=0.01)
    assert implicit.plant_step == pytest.approx(2e-3)


@pytest.mark.parametrize("name", scenario_names(DEFAULT_SCENARIO_FILE))
def test_shipped_scenarios_are_within_their_bound(name):
    scenario = load_scenario(name=name)
    bound, why = time_step_bound(scenario)
    assert scenario.plant.time_step <= bound, why
    assert "\n" not in why and why


def test_a_long_step_is_over_the_bound_with_a_one_line_reason():
    scenario = load_scenario(name="Default", override=EXPLICIT)
    scenario.plant.time_step = 0.1
    bound, why = time_step_bound(scenario)
    assert scenario.plant.time_step > bound
    text = (f"scenario: plant.time_step {scenario.plant.time_step} s is longer than the "
            f"{bound} s this scenario allows ({why})")
    assert "\n" not in text
    assert "0.00111 s" in text and "898 rad/s" in text and "70.8 mm" in text


def test_bound_follows_the_scenario():
    """Closer or stronger magnets shorten the bound; no applied force leaves the contact's."""
    base = load_scenario(name="Default")
    closer = load_scenario(name="Default",
                           override="{epm: {clearance: 0.0}, plant: {time_step: 0.0005}}")
    assert time_step_bound(closer)[0] < time_step_bound(base)[0]
    off = load_scenario(name="Default", override="magnet_force: {apply: false}")
    bounds = step_bounds(off)
    assert math.isinf(bounds.magnet_step) and bounds.plant_step == bounds.contact_step
    assert "contact" in time_step_bound(off)[1]


def test_bound_is_fast():
    scenario = load_scenario(name="Default")
    time_step_bound(scenario)   # the model file read once
    start = time.perf_counter()
    for _ in range(10):
        time_step_bound(scenario)
    assert (time.perf_counter() - start) / 10 < 0.05


@pytest.mark.slow
def test_the_issue_step_diverges_and_the_bound_does_not():
    """The issue's 0.1 s step: the run guard stops the Default run (it no longer means
    anything); at the bound it completes."""
    from capsule_drake.app.run import simulate

    scenario = load_scenario(name="Default", override="duration: 1.5")
    scenario.plant.time_step = 0.1
    assert simulate(scenario, progress=False).status != "completed"
    scenario.plant.time_step = time_step_bound(scenario)[0]
    result = simulate(scenario, progress=False)
    assert result.status == "completed"
    assert result.metrics["max_wall_excursion_m"] < 1e-3
