"""The capsule's contact-force sensor (capsule/contact_sensor.py): at rest on the colon wall
the wall's force balances gravity and the magnet; the reading is the truth plus white noise of
the configured spread, seeded, sampled every 1 / sample_rate and clipped to the range."""

import numpy as np
import pytest
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RotationMatrix
from pydrake.systems.primitives import LogVectorOutput

from capsule_drake.capsule.contact_sensor import ContactForceSensor, ContactSensorConfig
from capsule_drake.capsule.model import CAPSULE_BODY, capsule_model
from capsule_drake.app.run import simulate
from capsule_drake.scenario import ScenarioError, load_scenario

SAMPLE_RATE = 200.0    # 5 ms: five plant steps (1 ms) per sample
NOISE_STD = 0.01       # N
LOG_PERIOD = 0.001     # the plant's step: every sample is seen, and when it was taken
SETTLED = 1.5          # s: the capsule has fallen onto the wall and come to rest by then


def _run(override: str, duration: float, seed: int = 3, extra: str = ""):
    """Simulates FarMagnet with the sensor configured by `override` (YAML for
    capsule.contact_sensor) and `extra` YAML on top; logs the sensor, the capsule's state and
    the EPM's force every plant step. Returns (times, {output name: (n, K) log}, RunResult)."""
    names = ("capsule.contact_sensor.F_B", "capsule.contact_sensor.F_B_true", "capsule.state",
             "epm.F_W")
    loggers = {}

    def extend(builder, station):
        for name in names:
            loggers[name] = LogVectorOutput(station.GetOutputPort(name), builder, LOG_PERIOD)

    scenario = load_scenario(name="FarMagnet", override=[
        f"{{duration: {duration}, random_seed: {seed}}}",
        f"capsule: {{contact_sensor: {override}}}", extra])
    result = simulate(scenario, progress=False, extend=extend)
    assert result.metrics["stopped_early"] is None
    logs = {name: logger.FindLog(result.context) for name, logger in loggers.items()}
    times = logs["capsule.state"].sample_times()
    for log in logs.values():
        np.testing.assert_array_equal(log.sample_times(), times)
    return times, {name: log.data() for name, log in logs.items()}, result


def _gravity(result) -> np.ndarray:
    return result.station.GetSubsystemByName("plant").gravity_field().gravity_vector()


def _contact_force_W(logs) -> np.ndarray:
    """(3, K) the sensor's true force, taken back from the capsule frame B to the world with
    the capsule's logged orientation (Drake's own quaternion -> rotation)."""
    F_B = logs["capsule.contact_sensor.F_B_true"]
    state = logs["capsule.state"]
    out = np.empty_like(F_B)
    for k in range(F_B.shape[1]):
        q = state[:4, k] / np.linalg.norm(state[:4, k])
        out[:, k] = RotationMatrix(Quaternion(q)).matrix() @ F_B[:, k]
    return out


@pytest.fixture(scope="module")
def far_magnet():
    """FarMagnet (the EPM 50 cm above the capsule's start): the capsule drops onto the wall
    and stays there, held by gravity, the wall and a weak pull of the magnet."""
    return _run(f"{{sample_rate: {SAMPLE_RATE}, noise_std: {NOISE_STD}}}", 2.0)


@pytest.fixture(scope="module")
def no_magnet_force():
    """The same, with the magnet's force computed but not applied: gravity and the wall only."""
    return _run(f"{{sample_rate: {SAMPLE_RATE}, noise_std: {NOISE_STD}}}", 2.0,
                extra="magnet_force: {apply: false}")


def _at_rest(times, logs):
    """The samples after SETTLED, checked to be at rest: over those 0.5 s the velocity stays
    below 1 mm/s, so the mean acceleration is below 4 mm/s^2 and m a below 0.05 mN."""
    rest = times >= SETTLED
    v_WB = logs["capsule.state"][10:13, rest]
    w_WB = logs["capsule.state"][7:10, rest]
    assert np.abs(v_WB).max() < 1e-3 and np.abs(w_WB).max() < 0.1
    return rest


def test_wall_force_balances_gravity_and_the_magnet(far_magnet):
    times, logs, result = far_magnet
    rest = _at_rest(times, logs)
    mass = capsule_model().mass
    g_W = _gravity(result)
    assert np.linalg.norm(g_W) == pytest.approx(9.81, rel=0.01)
    F_contact_W = _contact_force_W(logs)[:, rest].mean(axis=1)
    # epm.F_W is [torque; force] on the EPM; the dipoles' forces on each other are equal
    # and opposite, so the capsule feels minus the EPM's force.
    F_magnet_W = -logs["epm.F_W"][3:, rest].mean(axis=1)
    # The magnet, 50 cm away, still pulls with several mN (~4 % of the weight): the check
    # below must see it, so its tolerance (0.1 mN) is well below it.
    assert 0.003 < np.linalg.norm(F_magnet_W) < 0.1 * mass * np.linalg.norm(g_W)
    # At rest (m a ~ 0) within 0.1 mN, a thousandth of the weight.
    residual = F_contact_W + mass * g_W + F_magnet_W
    np.testing.assert_allclose(residual, 0.0, atol=1e-4)
    # And without the magnet's share it would not balance.
    assert np.linalg.norm(F_contact_W + mass * g_W) > 0.003


def test_magnet_force_used_is_the_one_applied_to_the_capsule(far_magnet):
    """The reaction on the EPM is minus the force the magnet_force system applies to the
    capsule's body (what the plant integrates), at the run's final state."""
    _, _, result = far_magnet
    station = result.station
    context = station.GetMyContextFromRoot(result.context)
    plant = station.GetSubsystemByName("plant")
    force = station.GetSubsystemByName("magnet_force")
    capsule = plant.GetBodyByName(CAPSULE_BODY).index()
    applied = [f for f in force.get_applied_spatial_force_output_port().Eval(
        force.GetMyContextFromRoot(result.context)) if f.body_index == capsule]
    assert len(applied) == 1
    F_epm = station.GetOutputPort("epm.F_W").Eval(context)[3:]
    np.testing.assert_allclose(applied[0].F_Bq_W.translational(), -F_epm, rtol=1e-9,
                               atol=1e-12)


def test_without_the_magnet_force_the_wall_carries_the_weight(no_magnet_force):
    times, logs, result = no_magnet_force
    rest = _at_rest(times, logs)
    mass = capsule_model().mass
    g_W = _gravity(result)
    F_contact_W = _contact_force_W(logs)[:, rest].mean(axis=1)
    np.testing.assert_allclose(F_contact_W, -mass * g_W, atol=1e-4)
    # The magnet's force was computed all the same (and is not part of the balance).
    assert np.linalg.norm(logs["epm.F_W"][3:, rest].mean(axis=1)) > 0.003


def test_the_true_force_is_in_the_capsule_frame(far_magnet):
    """At rest the truth in B is R_BW of (minus gravity minus the magnet): it follows the
    capsule's orientation, it is not the world-frame force."""
    times, logs, result = far_magnet
    rest = _at_rest(times, logs)
    mass = capsule_model().mass
    k = np.flatnonzero(rest)[-1]
    q = logs["capsule.state"][:4, k]
    R_WB = RotationMatrix(Quaternion(q / np.linalg.norm(q))).matrix()
    expected_W = -mass * _gravity(result) + logs["epm.F_W"][3:, k]
    np.testing.assert_allclose(logs["capsule.contact_sensor.F_B_true"][:, k],
                               R_WB.T @ expected_W, atol=1e-4)
    # The capsule lies along the colon, its axis far from the vertical: in B the force is
    # not what it is in W, so the check above tells the frames apart.
    assert np.linalg.norm(R_WB.T @ expected_W - expected_W) > 0.05


def test_no_contact_force_before_the_capsule_reaches_the_wall(far_magnet):
    """The capsule starts on the centreline, millimetres off the wall, and falls: in its first
    20 ms (2 mm) it touches nothing, and the reading is noise alone."""
    times, logs, _ = far_magnet
    falling = times <= 0.02
    np.testing.assert_array_equal(logs["capsule.contact_sensor.F_B_true"][:, falling], 0.0)
    noise = logs["capsule.contact_sensor.F_B"][:, falling & (times > 0.0)]
    assert np.all(noise != 0.0) and np.abs(noise).max() < 6 * NOISE_STD
    assert np.linalg.norm(logs["capsule.contact_sensor.F_B_true"][:, -1]) > 0.1


def test_samples_every_one_over_the_sample_rate(far_magnet):
    times, logs, result = far_magnet
    sensor = result.station.GetSubsystemByName("capsule.contact_sensor")
    assert isinstance(sensor, ContactForceSensor)
    assert sensor.period() == pytest.approx(1.0 / SAMPLE_RATE)
    attribute = sensor.GetUniquePeriodicDiscreteUpdateAttribute()
    assert attribute.period_sec() == pytest.approx(1.0 / SAMPLE_RATE)
    assert attribute.offset_sec() == 0.0
    # In the log (every plant step) the noisy reading changes once per sample period, never
    # in between, and at every sample (the noise is new each time). (A log entry at t shows
    # the state before that instant's update: the sample taken at t appears one step later.)
    F_B = logs["capsule.contact_sensor.F_B"]
    changed = np.any(np.diff(F_B, axis=1) != 0.0, axis=0)
    change_times = times[1:][changed]
    assert len(change_times) >= 0.99 * times[-1] * SAMPLE_RATE
    np.testing.assert_allclose(np.diff(change_times), 1.0 / SAMPLE_RATE, atol=1e-9)
    # The truth is held between samples too.
    steps = round(1.0 / (SAMPLE_RATE * LOG_PERIOD))
    truth = logs["capsule.contact_sensor.F_B_true"]
    truth_changed = np.flatnonzero(np.any(np.diff(truth, axis=1) != 0.0, axis=0))
    assert len(truth_changed) > 0
    assert np.all((truth_changed - np.flatnonzero(changed)[0]) % steps == 0)


def test_noise_is_white_with_the_configured_spread(far_magnet):
    times, logs, _ = far_magnet
    F_B = logs["capsule.contact_sensor.F_B"]
    truth = logs["capsule.contact_sensor.F_B_true"]
    # One value per sample (the log holds each for five plant steps).
    steps = round(1.0 / (SAMPLE_RATE * LOG_PERIOD))
    first = int(np.flatnonzero(np.any(np.diff(F_B, axis=1) != 0.0, axis=0))[0]) + 1
    sampled_truth = truth[:, first::steps]
    # The samples the range did not clip (the capsule's landing on the wall peaks above it).
    unclipped = np.all(np.abs(sampled_truth) < ContactSensorConfig().range - 6 * NOISE_STD,
                       axis=0)
    noise = (F_B[:, first::steps] - sampled_truth)[:, unclipped]
    n = noise.shape[1]
    assert n >= 380  # of 400: 2 s at 200 Hz
    # Per axis the sample std has a relative spread of 1 / sqrt(2 n) = 3.5 %: 4 sigma.
    np.testing.assert_allclose(noise.std(axis=1), NOISE_STD, rtol=0.14)
    assert noise.std() == pytest.approx(NOISE_STD, rel=0.08)      # all axes: 2 %, 4 sigma
    np.testing.assert_allclose(noise.mean(axis=1), 0.0, atol=4 * NOISE_STD / np.sqrt(n))
    # Independent axes and samples (correlations spread 1 / sqrt(n) = 0.05: 4 sigma).
    correlation = np.corrcoef(noise)
    assert np.abs(correlation[np.triu_indices(3, 1)]).max() < 0.2
    for axis in noise:
        assert abs(np.corrcoef(axis[:-1], axis[1:])[0, 1]) < 0.2


@pytest.fixture(scope="module")
def seeded_runs():
    config = f"{{sample_rate: {SAMPLE_RATE}, noise_std: {NOISE_STD}}}"
    return [_run(config, 0.3, seed=seed)[1] for seed in (5, 5, 6)]


def test_same_seed_same_readings_other_seed_other_readings(seeded_runs):
    first, again, other = seeded_runs
    np.testing.assert_array_equal(first["capsule.contact_sensor.F_B"],
                                  again["capsule.contact_sensor.F_B"])
    assert not np.array_equal(first["capsule.contact_sensor.F_B"],
                              other["capsule.contact_sensor.F_B"])
    # The noise does not touch the physics: the truth is the same whatever the seed.
    np.testing.assert_array_equal(first["capsule.contact_sensor.F_B_true"],
                                  other["capsule.contact_sensor.F_B_true"])
    assert np.abs(first["capsule.contact_sensor.F_B_true"]).max() > 0.05


def test_reading_saturates_at_the_range():
    """Without noise the reading is the truth clipped to +-range per axis; a range below the
    capsule's weight clips the axis that carries most of it, and only that one."""
    full_scale = 0.05  # N; the weight is 0.118 N
    times, logs, _ = _run(f"{{sample_rate: {SAMPLE_RATE}, noise_std: 0.0, "
                          f"range: {full_scale}}}", 1.0)
    F_B = logs["capsule.contact_sensor.F_B"]
    truth = logs["capsule.contact_sensor.F_B_true"]
    np.testing.assert_array_equal(F_B, np.clip(truth, -full_scale, full_scale))
    assert np.abs(F_B).max() == full_scale
    clipped = np.abs(truth) > full_scale
    assert clipped.any() and (~clipped & (np.abs(truth) > 0.005)).any()
    # At rest the truth is well past the range on some axis.
    assert np.abs(truth[:, -1]).max() > 1.5 * full_scale


@pytest.mark.parametrize("field, value", [("sample_rate", 0.0), ("noise_std", -0.01),
                                          ("range", 0.0)])
def test_bad_config_is_a_one_line_scenario_error_naming_the_key(field, value):
    with pytest.raises(ScenarioError,
                       match=rf"^scenario: capsule.contact_sensor: {field} .*{value}") as error:
        load_scenario(override=f"capsule: {{contact_sensor: {{{field}: {value}}}}}")
    assert "\n" not in str(error.value)


def test_the_sensor_is_off_unless_asked_for():
    assert load_scenario().capsule.contact_sensor is None
    assert load_scenario(name="OneOfEverything").capsule.contact_sensor == ContactSensorConfig(
        sample_rate=50.0, noise_std=0.01, range=1.0)
