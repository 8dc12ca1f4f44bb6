"""The whole station: it builds, it simulates, and the capsule goes where the magnet drags it."""

import dataclasses
import json

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.primitives import LogVectorOutput

from capsule_drake.anatomy import load_colon
from capsule_drake.capsule.model import capsule_model
from capsule_drake.app.cli import main as cli_main
from capsule_drake.io.metrics import capsule_poses, capsule_surface_points_C, wall_excursion
from capsule_drake.scenario import Scenario, ScenarioError, load_scenario
from capsule_drake.app.run import simulate
from capsule_drake.app.start import settled_start, settled_state
from capsule_drake.station import make_station


def test_station_exports_named_ports():
    diagram = make_station(Scenario())
    names = {diagram.get_output_port(i).get_name() for i in range(diagram.num_output_ports())}
    assert {"capsule.state", "capsule.ipm_field_B", "epm.state", "epm.desired_state", "epm.F_W",
            "body_poses", "contact_results", "query_object"} <= names


def test_capsule_outside_the_colon_is_a_scenario_error():
    scenario = Scenario()
    scenario.capsule.start_s = 5.0  # the default colon is ~1.5 m long
    with pytest.raises(ScenarioError, match="capsule.start_s 5.0 m is outside this colon"):
        make_station(scenario)


def test_bad_sensor_settings_are_scenario_errors():
    # Checked once, when the scenario is loaded (scenario.validate).
    with pytest.raises(ScenarioError, match="capsule.camera: lens model 'fancy'"):
        load_scenario(override="capsule: {camera: {lens: {model: fancy}}}")
    with pytest.raises(ScenarioError, match="capsule.imu.sample_rate must be > 0, got -5.0"):
        load_scenario(override="capsule: {imu: {sample_rate: -5.0}}")


def test_magnet_field_at_capsule_points_down_the_colon():
    # At t = 0 the EPM hovers over the capsule with its moment chosen so the field at the
    # capsule lies along the colon's tangent; the capsule starts aligned with that tangent,
    # so the field in the capsule frame is along +z (the capsule axis).
    scenario = Scenario()
    diagram = make_station(scenario)
    context = diagram.CreateDefaultContext()
    B_C = diagram.GetOutputPort("capsule.ipm_field_B").Eval(context)
    assert np.linalg.norm(B_C) > 1e-3  # tens of mT at 15-25 cm
    np.testing.assert_allclose(B_C / np.linalg.norm(B_C), [0, 0, 1], atol=0.05)


@pytest.fixture(scope="module")
def drag_run():
    scenario = dataclasses.replace(load_scenario(), duration=40.0)
    return simulate(scenario, progress=False)


@pytest.mark.slow
def test_default_drag_advances_30cm_inside_the_lumen(drag_run):
    m = drag_run.metrics
    print(json.dumps(m, indent=1))
    assert m["stopped_early"] is None
    assert m["advance_m"] >= 0.30
    assert m["max_wall_excursion_m"] < 1e-3
    assert m["min_epm_skin_gap_m"] >= 0.02 - 1e-3  # the EPM keeps its clearance
    assert np.all(np.isfinite(drag_run.capsule_state))
    # The contact's peak pressure against the overlap that the analytic wall measures: the
    # capsule's pressure field is E depth / R (tests/test_tissue.py), so the run's peak is
    # E times its largest excursion over R, to the collision mesh's chords and the samples.
    modulus = load_scenario().contact.capsule_hydroelastic_modulus
    expected = modulus * m["max_wall_excursion_m"] / capsule_model().radius / 1000.0
    assert m["peak_contact_pressure_kPa"] == pytest.approx(expected, rel=0.25)
    assert 0.0 < m["time_above_ischaemia_pressure_s"] <= m["sim_time_s"]


@pytest.mark.slow
def test_default_drag_with_the_arm_advances_as_with_the_stage(drag_run):
    scenario = load_scenario(name="WithArm", override="duration: 40.0")
    arm = simulate(scenario, progress=False).metrics
    stage = drag_run.metrics
    print(f"advance in 40 s: arm {arm['advance_m']:.3f} m, stage {stage['advance_m']:.3f} m")
    assert arm["stopped_early"] is None
    assert abs(arm["advance_m"] - stage["advance_m"]) <= 0.2 * stage["advance_m"]
    assert arm["max_wall_excursion_m"] < 1e-3
    assert arm["min_epm_skin_gap_m"] >= 0.02 - 1e-3


@pytest.mark.slow
def test_the_kinematic_stage_puts_the_epm_where_the_path_says_as_the_servos_do():
    """The default stage is kinematic: no stage joints in the plant (the capsule's 6
    velocities only), the EPM exactly on its path, and the capsule moved as by the
    servoed stage (kinematic: false) whose 6.2 kg magnet lags its command by ~20 ms."""
    from capsule_drake.epm.poses import stage_to_pose
    finals = {}
    for kinematic in (True, False):
        scenario = load_scenario(override=f"{{epm: {{mount: !Stage {{kinematic: {str(kinematic).lower()}}}}}}}")
        station = make_station(scenario)
        plant = station.GetSubsystemByName("plant")
        assert plant.num_velocities() == (6 if kinematic else 11)
        simulator = Simulator(station)
        simulator.AdvanceTo(3.0)
        context = simulator.get_context()
        pose = station.GetOutputPort("epm.pose").Eval(context)
        desired = station.GetOutputPort("epm.desired_state").Eval(context)
        if kinematic:
            np.testing.assert_array_equal(station.GetOutputPort("epm.state").Eval(context),
                                          desired)
            np.testing.assert_allclose(pose, stage_to_pose(desired[:5]), atol=1e-15)
        else:
            assert np.linalg.norm(pose[:3] - desired[:3]) < 1e-3
        finals[kinematic] = station.GetOutputPort("capsule.state").Eval(context)[4:7].copy()
    # Measured: 0.04 mm apart after 3 s.
    assert np.linalg.norm(finals[True] - finals[False]) < 1e-3


@pytest.mark.slow
def test_the_implicit_magnet_torque_runs_the_default_drag_at_four_times_the_explicit_bound():
    """magnet_force.implicit: the Default drag at a 4 ms plant step (the explicit bound is
    1.11 ms) stays inside the wall and moves the capsule as at 1 ms: after 3 s, within 3 mm
    of the explicit 1 ms run's position (measured 1.4 mm, most of it from the start's drop
    onto the wall). A held magnet force cannot be implicit: one line."""
    with pytest.raises(ScenarioError, match="magnet_force.implicit needs update_period 0") as e:
        load_scenario(override="{magnet_force: {implicit: true, update_period: 0.002}}")
    assert "\n" not in str(e.value)
    finals = []
    for step, implicit in ((0.001, "false"), (0.004, "true")):
        scenario = load_scenario(override=f"{{magnet_force: {{implicit: {implicit}}}, "
                                          f"plant: {{time_step: 0.001}}, duration: 3.0}}")
        scenario.plant.time_step = step   # 4 ms: past the contact's bound too
        station = make_station(scenario)
        assert station.GetSubsystemByName("magnet_force").HasInputPort(
            "body_spatial_velocities") == (implicit == "true")
        simulator = Simulator(station)
        simulator.AdvanceTo(3.0)
        state = station.GetOutputPort("capsule.state").Eval(simulator.get_context())
        assert np.all(np.isfinite(state))
        finals.append(state[4:7].copy())
    assert np.linalg.norm(finals[1] - finals[0]) < 3e-3


def settled_positions(scenario):
    """Capsule positions from its first second on (it first drops onto the wall)."""
    result = simulate(scenario, progress=False)
    return result.capsule_state[4:7].T[result.times >= 1.0]


@pytest.mark.slow
def test_capsule_stays_put_with_magnet_50cm_away():
    scenario = load_scenario(name="FarMagnet")
    p = settled_positions(scenario)
    assert np.linalg.norm(p - p[0], axis=1).max() < 1e-3
    s, _, _ = load_colon(scenario.colon)[0].centerline.closest(p)
    assert abs(s[-1] - s[0]) < 1e-3
    # The same magnet 24 cm above does move it (~0.2 N of pull > its 0.12 N weight, so it
    # ends on the upper wall instead of the lower one): the test can fail.
    near = dataclasses.replace(scenario, epm=dataclasses.replace(
        scenario.epm, driver=dataclasses.replace(scenario.epm.driver, height=0.24)))
    p_near = settled_positions(near)
    assert np.linalg.norm(p_near[-1] - p[-1]) > 0.01


def test_cli_run_writes_metrics_and_recording(tmp_path):
    out = tmp_path / "run"
    code = cli_main(["run", "--duration", "0.3", "--out", str(out), "--quiet"])
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["sim_time_s"] == pytest.approx(0.3, abs=0.02)
    html = (out / "recording.html").read_text()
    assert "<html" in html.lower() and len(html) > 10_000
    assert (out / "logs.npz").exists() and (out / "scenario.yaml").exists()


# OneOfEverything and OneOfEverythingElse set every option that selects behaviour
# (tests/test_scenario.py); Navigation, NavigationDetected and NavigationSensors hold the
# lumen follower (the last on the capsule's own pose estimate, with finite magnets).
# Measured wall times (2 cores, colons cached): OneOfEverything ~2 s, OneOfEverythingElse
# ~3 s (~11 s when it first imports the ex vivo colon), the others 1-4 s.
@pytest.mark.parametrize("name", [
    "Default", "WithSensors", "Navigation",
    # ~4-5 s each: the full suite's (the fast loop keeps Navigation's follower).
    pytest.param("NavigationDetected", marks=pytest.mark.slow),
    pytest.param("NavigationSensors", marks=pytest.mark.slow),
    # ~27-68 s on a fresh cache (their colons carry lesions, fluid, an ex vivo segment):
    # the full suite's, not the fast loop's.
    pytest.param("OneOfEverything", marks=pytest.mark.slow),
    pytest.param("OneOfEverythingElse", marks=pytest.mark.slow)])
def test_named_scenarios_simulate(name):
    scenario = load_scenario(name=name)
    scenario = dataclasses.replace(scenario, duration=min(scenario.duration, 0.5))
    logs = {}

    def extend(builder, station):
        logs["F_W"] = LogVectorOutput(station.GetOutputPort("epm.F_W"), builder, 0.05)

    result = simulate(scenario, progress=False, extend=extend)
    assert result.metrics["stopped_early"] is None
    assert np.all(np.isfinite(result.capsule_state))
    # A rigid wall is left by at most 1 mm; a compliant one yields under the capsule by less
    # than its thickness (measured on the navigation scenarios: 1.43-1.47 mm of 2.61 mm).
    limit = getattr(scenario.contact, "thickness", 1e-3)
    assert result.metrics["max_wall_excursion_m"] < limit
    # The magnet force is computed (by the scenario's field model) ...
    F_W = logs["F_W"].FindLog(result.context).data()
    assert np.all(np.isfinite(F_W)) and np.all(np.linalg.norm(F_W[3:], axis=0) > 1e-3)
    if not scenario.magnet_force.apply:
        # ... but not applied: the capsule only settles on the tissue (measured: with the
        # force applied, OneOfEverythingElse's capsule rises 12 mm to the lumen's roof).
        z = result.capsule_state[6]
        assert z.max() - z[0] < 1e-3


def test_external_driver_takes_the_epm_command_input():
    # !External: the station's epm.command is an input, and the stage follows it.
    scenario = load_scenario(override="epm: {driver: !External {}}")
    station = make_station(scenario)
    assert station.HasSubsystemNamed("epm_stage_command")
    assert not station.HasSubsystemNamed("epm_path")
    simulator = Simulator(station)
    context = simulator.get_mutable_context()
    start = station.GetOutputPort("epm.pose").Eval(context).copy()
    command = start.copy()
    command[:3] += [0.02, 0.0, 0.02]  # 2 cm along x, 2 cm higher
    station.GetInputPort("epm.command").FixValue(context, command)
    simulator.AdvanceTo(0.5)
    pose = station.GetOutputPort("epm.pose").Eval(context)
    np.testing.assert_allclose(pose, command, atol=1e-4)  # measured: within 2.3e-5


@pytest.mark.slow
def test_fast_contact_model_drags_the_capsule_inside_the_wall():
    # The convex-pieces wall (point contact) keeps the capsule inside as the hydroelastic one
    # does. 12 s: the capsule is dragged out of the rectum into the sigmoid.
    scenario = dataclasses.replace(load_scenario(name="FastContact"), duration=12.0)
    m = simulate(scenario, progress=False).metrics
    assert m["stopped_early"] is None
    assert m["max_wall_excursion_m"] < 1e-3
    assert m["max_s_m"] > 0.15


def test_a_failing_simulation_still_writes_what_it_logged(tmp_path, monkeypatch):
    import capsule_drake.app.start as start_module   # where the run's Simulator is made

    class FailingSimulator(start_module.Simulator):
        def AdvanceTo(self, t):
            if t > 0.2:
                raise RuntimeError("solver diverged (injected)\nsecond line")
            return super().AdvanceTo(t)

    monkeypatch.setattr(start_module, "Simulator", FailingSimulator)
    scenario = dataclasses.replace(load_scenario(), duration=1.0)
    result = simulate(scenario, progress=False, out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["stopped_early"].startswith("simulation error at t = 0.")
    assert "solver diverged (injected)" in m["stopped_early"]
    assert 0.15 < m["sim_time_s"] < 0.25
    logs = np.load(tmp_path / "logs.npz")
    assert logs["times"][-1] > 0.15 and len(logs["times"]) == len(result.times)


@pytest.mark.slow
def test_sensors_are_wired_and_seeded():
    scenario = dataclasses.replace(load_scenario(name="WithSensors"), duration=0.3)
    diagram = make_station(scenario)
    names = {diagram.get_output_port(i).get_name() for i in range(diagram.num_output_ports())}
    assert {"capsule.imu.accel", "capsule.imu.gyro", "capsule.ahrs.q_WB",
            "capsule.magnetometer.B_S", "capsule.camera.rgb_image",
            "capsule.lumen.lumen_pixel"} <= names

    from pydrake.common import RandomGenerator

    def accel_after(seed, port="capsule.imu.accel"):
        simulator = Simulator(diagram)
        diagram.SetRandomContext(simulator.get_mutable_context(), RandomGenerator(seed))
        simulator.AdvanceTo(0.2)
        return diagram.GetOutputPort(port).Eval(simulator.get_context()).copy()

    # The same seed gives the same noisy sample, another seed another one.
    np.testing.assert_array_equal(accel_after(3), accel_after(3))
    assert not np.array_equal(accel_after(3), accel_after(4))
    # Measured = true + bias (~10 mg) + white noise (~0.03 m/s^2 per sample at 100 Hz).
    error = accel_after(3) - accel_after(3, "capsule.imu.accel_true")
    assert 0.0 < np.linalg.norm(error) < 1.0


@pytest.mark.slow
def test_a_settled_start_begins_at_rest_on_the_wall_without_the_snap():
    """capsule.settle: the Default capsule, let settle 0.5 s (at a 0.5 ms step), starts the
    run touching the wall (its surface within 1 mm of it), not on the centreline, and the
    magnet's snap onto the wall that an unsettled start shows (0.5-0.6 m/s within 0.15 s)
    is gone: under 0.1 m/s over the first 0.5 s. The settled pose is cached: a second
    station of the same physics starts at the same pose."""
    colon, _ = load_colon(load_scenario().colon)
    model = capsule_model()
    points = capsule_surface_points_C(model.radius, model.length)
    speeds, starts = {}, {}
    for settle in (0.0, 0.5):
        scenario = load_scenario(override=f"{{capsule: {{settle: {settle}}}, "
                                          f"outputs: {{log_period: 0.002}}, duration: 0.5}}")
        result = simulate(scenario, progress=False)
        speeds[settle] = np.linalg.norm(result.capsule_state[10:13], axis=0)
        R, p = capsule_poses(result.capsule_state[:, :1])
        starts[settle] = float(wall_excursion(colon, R, p, points)[0])
    assert starts[0.0] < -5e-3          # on the centreline: 8 mm from the wall
    assert -1e-3 < starts[0.5] < 1e-3   # on the wall
    assert speeds[0.0].max() > 0.4
    assert speeds[0.5].max() < 0.1
    scenario = load_scenario(override="{capsule: {settle: 0.5}}")
    # Cached (the second settling is a look-up, the same pose), handed out as copies.
    assert settled_state(scenario) is not settled_state(scenario)
    np.testing.assert_array_equal(settled_start(scenario).GetAsMatrix4(),
                                  settled_start(scenario).GetAsMatrix4())


@pytest.mark.slow
def test_the_default_step_advances_the_capsule_as_a_quarter_millisecond_reference():
    """The Default drag at its own plant step (2 ms, the implicit magnet torque) against the
    same run at 0.25 ms, over 10 s (the start's snap onto the wall and the first centimetres
    of drag): the advance along the colon within 10 % (measured over 30 s: 0.03 %,
    docs/results/performance.md, "Time-step convergence"), the excursion beyond the wall
    under 1 mm in both."""
    runs = {}
    for step in (None, 2.5e-4):
        scenario = load_scenario(override="{duration: 10.0}")
        if step is not None:
            scenario.plant.time_step = step
        runs[step] = simulate(scenario, progress=False).metrics
    own, reference = runs[None], runs[2.5e-4]
    assert reference["advance_m"] > 0.02
    assert abs(own["advance_m"] - reference["advance_m"]) <= 0.1 * reference["advance_m"]
    assert own["max_wall_excursion_m"] < 1e-3 and reference["max_wall_excursion_m"] < 1e-3
