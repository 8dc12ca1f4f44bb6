"""DelayChannel, PassivityController and TeleopChannel: the haptic loop's network link and
the time-domain passivity scheme that keeps its delayed force feedback stable."""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.teleop.channel import (
    ChannelConfig, DelayChannel, PassivityConfig, PassivityController, TeleopChannel,
    TeleopChannelConfig, check_channel_config, check_passivity_config, packet_fate,
    passivity_step, predicted_work)
from capsule_drake.app.delay_bench import press_and_hold, run_delay_bench

PERIOD = 0.001


def _step_channel(dut, context, ticks, signal=lambda t: [t]):
    """Runs the channel's periodic update at ticks ``ticks`` (time = tick * period) with the
    input ``signal(t)``; returns out (ticks, n) and age (ticks,) right after each update."""
    out, age = [], []
    for k in ticks:
        t = k * dut.config().period
        context.SetTime(t)
        dut.get_input_port_in().FixValue(context, signal(t))
        context.SetDiscreteState(dut.EvalUniquePeriodicDiscreteUpdate(context))
        out.append(dut.get_output_port_out().Eval(context).copy())
        age.append(dut.get_output_port_age().Eval(context)[0])
    return np.array(out), np.array(age)


def _expected_output(config, ticks):
    """The newest packet (by send tick) delivered by each tick, from ``packet_fate`` alone:
    a packet sent at j arrives at tick j + max(1, ceil(delay / period)) and is seen at the
    first tick at or after that. -1 = none yet."""
    arrival = np.full(len(ticks), np.iinfo(np.int64).max)
    for j in ticks:
        lost, delay = packet_fate(config, j)
        if not lost:
            arrival[j] = j + max(1, math.ceil(delay / config.period - 1e-9))
    newest = np.full(len(ticks), -1)
    for j in ticks:
        if arrival[j] < len(ticks):
            # The output is monotone: a packet only shows if it is newer than what is held.
            newest[arrival[j]:] = np.maximum(newest[arrival[j]:], j)
    return newest


def test_ideal_link_gives_the_input_one_period_later():
    dut = DelayChannel(2)
    out, age = _step_channel(dut, dut.CreateDefaultContext(), range(50),
                             lambda t: [t, -2.0 * t])
    t = np.arange(50) * PERIOD
    np.testing.assert_allclose(out[1:], np.c_[t[:-1], -2.0 * t[:-1]], atol=1e-12)
    np.testing.assert_allclose(age[1:], PERIOD, atol=1e-12)
    # Nothing has arrived after the first tick: the initial zeros, of infinite age.
    np.testing.assert_array_equal(out[0], [0.0, 0.0])
    assert age[0] == math.inf


def test_ramp_comes_out_delayed_by_exactly_the_delay():
    for delay, ticks in ((0.05, 50), (0.0125, 13)):  # 12.5 ms is rounded up to 13 periods
        dut = DelayChannel(1, ChannelConfig(delay=delay))
        out, age = _step_channel(dut, dut.CreateDefaultContext(), range(300))
        t = np.arange(300) * PERIOD
        np.testing.assert_allclose(out[ticks:, 0], t[ticks:] - ticks * PERIOD, atol=1e-12)
        np.testing.assert_allclose(age[ticks:], ticks * PERIOD, atol=1e-12)
        np.testing.assert_array_equal(out[:ticks, 0], 0.0)  # held initial value


def test_jitter_draws_have_the_configured_spread_and_are_never_negative():
    # The extra delay is exponential: mean = standard deviation = jitter.
    config = ChannelConfig(delay=0.02, jitter=0.003, seed=7)
    delays = np.array([packet_fate(config, k)[1] for k in range(20000)])
    extra = delays - config.delay
    assert extra.min() >= 0.0
    # Sampling error of the standard deviation of 20000 exponential draws: ~1 %.
    assert abs(extra.std() / config.jitter - 1.0) < 0.05
    assert abs(extra.mean() / config.jitter - 1.0) < 0.05
    # The draws are those of the seed: another seed gives other draws, the same the same.
    again = np.array([packet_fate(config, k)[1] for k in range(20000)])
    np.testing.assert_array_equal(delays, again)
    other = np.array([packet_fate(dataclasses.replace(config, seed=8), k)[1]
                      for k in range(20000)])
    assert np.mean(other == delays) < 0.01


def test_jittered_lossy_channel_delivers_what_the_packet_fates_say():
    # Jitter of 3 periods reorders packets; the receiver must keep the newest by send time.
    config = ChannelConfig(delay=0.01, jitter=0.003, loss=0.1, seed=3)
    dut = DelayChannel(1, config)
    ticks = range(3000)
    out, age = _step_channel(dut, dut.CreateDefaultContext(), ticks)
    newest = _expected_output(config, ticks)
    seen = newest >= 0
    np.testing.assert_allclose(out[seen, 0], newest[seen] * PERIOD, atol=1e-12)
    np.testing.assert_allclose(age[seen], (np.arange(3000) - newest)[seen] * PERIOD, atol=1e-12)
    # Never back in time; some packets were overtaken (dropped) or lost.
    assert np.all(np.diff(out[:, 0]) >= 0.0)
    assert len(np.unique(out[seen, 0])) < 0.9 * 3000


def test_same_seed_same_run_and_a_cloned_context_continues_identically():
    config = ChannelConfig(delay=0.005, jitter=0.002, loss=0.2, seed=11)
    dut = DelayChannel(1, config)
    first = _step_channel(dut, dut.CreateDefaultContext(), range(1000))
    second = _step_channel(dut, dut.CreateDefaultContext(), range(1000))
    np.testing.assert_array_equal(first[0], second[0])
    reseeded = dut.CreateDefaultContext()
    dut.set_seed(reseeded, 12)
    third = _step_channel(dut, reseeded, range(1000))
    assert not np.array_equal(first[0], third[0])
    # The packets in flight are context state: a clone goes on exactly like the original.
    context = dut.CreateDefaultContext()
    _step_channel(dut, context, range(500))
    clone = context.Clone()
    a = _step_channel(dut, context, range(500, 1000))
    b = _step_channel(dut, clone, range(500, 1000))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[0], first[0][500:])


def test_loss_drops_the_configured_fraction_holds_the_last_value_and_ages():
    config = ChannelConfig(delay=0.01, loss=0.2, seed=5)
    dut = DelayChannel(1, config)
    n = 5000
    out, age = _step_channel(dut, dut.CreateDefaultContext(), range(n))
    delivered = len(np.unique(out[10:, 0]))  # the ramp makes each packet's value unique
    # Binomial: standard deviation sqrt(0.2 * 0.8 / 5000) = 0.0057 of the fraction; 4 sigma.
    assert abs(delivered / (n - 10) - 0.8) < 0.023
    changed = np.r_[True, np.diff(out[:, 0]) != 0.0]
    held = ~changed
    # While nothing arrives the output holds and its age grows by one period per tick.
    np.testing.assert_array_equal(out[1:, 0][held[1:]], out[:-1, 0][held[1:]])
    np.testing.assert_allclose(np.diff(age[10:])[held[11:]], PERIOD, atol=1e-12)
    np.testing.assert_allclose(age[10:][changed[10:]], 0.01, atol=1e-12)
    # A burst of losses: 4 in a row happen ~ 5000 * 0.2^4 * 0.8 = 6 times here.
    assert age[10:].max() >= 0.01 + 4 * PERIOD


def test_passivity_step_passes_the_force_while_there_is_energy_and_never_gives_nan():
    config = PassivityConfig()
    force, velocity = np.array([-1.0, 0.5, 0.0]), np.array([-0.02, 0.0, 0.01])
    out, alpha, scale = passivity_step(config, 1e-3, force, velocity)
    np.testing.assert_array_equal(out, force)
    assert (alpha, scale) == (0.0, 1.0)
    # No stored energy and a force pushing along the motion: the controller cuts what it
    # would deliver, so the predicted work on the hand is not positive.
    out, alpha, _ = passivity_step(config, 0.0, force, velocity)
    assert alpha > 0.0
    assert predicted_work(config, out, velocity) <= 1e-15
    # Nearly at rest, the force's own acceleration of the stylus is the work to bound.
    out, _, scale = passivity_step(config, 1e-6, np.array([2.0, 0, 0]), np.zeros(3))
    assert 0.0 < scale < 1.0
    np.testing.assert_allclose(predicted_work(config, out, np.zeros(3)), 1e-6)
    for bad in (np.nan, np.inf, -np.inf):
        out, _, _ = passivity_step(config, bad, np.full(3, bad), np.full(3, bad))
        assert np.all(np.isfinite(out))
    out, _, _ = passivity_step(dataclasses.replace(config, enabled=False), 0.0,
                               np.array([3.0, 4.0, 0.0]), velocity)
    np.testing.assert_allclose(out, [1.98, 2.64, 0.0])  # clipped to 3.3 N, same direction


def test_passivity_observer_integrates_the_work_of_the_held_force():
    dut = PassivityController(PassivityConfig(enabled=False))
    context = dut.CreateDefaultContext()
    rng = np.random.default_rng(0)
    positions = np.cumsum(rng.normal(0.0, 1e-4, (200, 3)), axis=0)
    forces = rng.normal(0.0, 0.5, (200, 3))
    energies = []
    for k in range(200):
        context.SetTime(k * PERIOD)
        dut.get_stylus_position_input_port().FixValue(context, positions[k])
        dut.get_force_in_input_port().FixValue(context, forces[k])
        context.SetDiscreteState(dut.EvalUniquePeriodicDiscreteUpdate(context))
        energies.append(dut.get_energy_output_port().Eval(context)[0])
    # The force chosen at tick k is held over [k, k+1] and does work F_k . (x_{k+1} - x_k) on
    # the hand; the energy into the one-port is minus its sum.
    work = np.sum(forces[:-1] * np.diff(positions, axis=0), axis=1)
    np.testing.assert_allclose(energies[1:], -np.cumsum(work), rtol=1e-12, atol=1e-15)


def _teleop_loop(delay, enabled, target, x0, wall_stiffness, duration, jitter=0.0, loss=0.0):
    """The one-DoF delay bench (capsule_drake.app.delay_bench): (t, x, v, work, energy,
    force_change, rendered force) sampled at 1 kHz."""
    return tuple(run_delay_bench(delay, enabled, target, x0, wall_stiffness, duration,
                                 jitter, loss))


@pytest.mark.slow
def test_passivity_control_stabilises_a_stiff_wall_behind_100_ms_round_trip():
    """50 ms each way; hand + stylus 0.3 kg gripped at 200 N/m and 3 N s/m toward a target
    moving at 2 mm/s from 2 mm outside to 3 mm inside a virtual wall of 800 N/m (robot
    side); device friction 0.05 N, force limit 3.3 N; 10 s.

    Measured (Drake 1.58): without the scheme the stylus moves 1.7 mm in the first second
    (the approach) and bounces off the wall over 45.8 mm (-27 to +18 mm) in the last second,
    at the force limit; the channel has delivered 3.36 J to the hand, 0.42 J more every
    second. With the scheme the oscillation after contact decays (peak to peak 0.67, 0.48,
    0.27, 0.03, ... 0.001 mm in the last second), the stylus settles at 0.60 mm, the
    undelayed equilibrium 200 * 3 / (200 + 800), the observed energy never goes below 0 and
    the hand never receives net energy (its work <= 0 at all times). The same with 5 ms
    jitter and 5 % loss each way: 0.007 mm in the last second, energy >= 0.
    """
    t, x, _, work, energy, _, force = _teleop_loop(0.05, False, press_and_hold, -0.002,
                                                   800.0, 10.0)
    first, last = np.ptp(x[t < 1.0]), np.ptp(x[t >= 9.0])
    assert last > 3.0 * first, (first, last)
    assert last > 0.02  # 2 cm bounces: unstable, not just a slow contact
    # The energy the channel and the wall deliver to the hand grows without bound (the hand's
    # damping and the friction dissipate it in a limit cycle at the force limit).
    assert work[-1] > 2.0 and work[-1] - work[t.searchsorted(5.0)] > 1.0
    # The observer sees it (its energy is minus the hand's work, to integration error).
    np.testing.assert_allclose(energy[-1], -work[-1], rtol=1e-3)

    for jitter, loss in ((0.0, 0.0), (0.005, 0.05)):
        t, x, _, work, energy, change, force = _teleop_loop(
            0.05, True, press_and_hold, -0.002, 800.0, 10.0, jitter, loss)
        for signal in (x, work, energy, change, force):
            assert np.all(np.isfinite(signal))
        assert energy.min() >= -1e-9  # J
        assert work.max() <= 1e-6  # J, integrated by the plant, independently of the observer
        windows = [np.ptp(x[(t >= s) & (t < s + 1.0)]) for s in range(1, 10)]
        assert windows[-1] < 0.05 * windows[0] and windows[-1] < 2e-5  # decays, < 20 um
        np.testing.assert_allclose(x[-1], 200.0 * 0.003 / (200.0 + 800.0), atol=2e-5)
        assert np.abs(force).max() <= 3.3 + 1e-12


@pytest.mark.slow
def test_with_zero_delay_the_scheme_barely_changes_the_force_of_a_slow_contact():
    """The same wall and hand, no added delay (the loop still has 3 periods of latency),
    target in at 2 mm/s to 3 mm, held 0.5 s, out at 2 mm/s.

    Measured: peak force 0.48 N either way. The latency generates 1.9 uJ over the contact;
    the scheme removes it in the last 0.07 mm of the release, where it changes the force by
    at most 0.053 N (1.6 % of the device's 3.3 N); during the press it changes nothing.
    """

    def target(t):
        return -0.002 + 0.002 * min(t, 2.5) - 0.002 * min(max(t - 3.0, 0.0), 2.5)

    runs = {enabled: _teleop_loop(0.0, enabled, target, -0.002, 800.0, 6.0)
            for enabled in (False, True)}
    t, _, _, work_off, _, _, force_off = runs[False]
    _, x, _, work_on, energy, change, force_on = runs[True]
    assert 0.4 < np.abs(force_off).max() < 0.6  # a real contact: 0.6 mm into 800 N/m
    assert work_off[-1] > 0.0  # the latency alone makes the loop slightly active...
    assert work_on.max() <= 1e-9 and energy.min() >= -1e-9  # ...the scheme makes it passive
    assert np.abs(change).max() < 0.08  # N
    assert np.abs(force_on - force_off).max() < 0.08  # N, against the run without it
    np.testing.assert_array_equal(change[t < 3.0], 0.0)  # nothing while pressing
    acting = np.abs(change) > 1e-3
    assert np.count_nonzero(acting) * PERIOD < 0.5  # s, only at the end of the release


def _still_stylus_force(config):
    """force_out and energy of a TeleopChannel(6, config) after 10.5 ms with a still stylus
    and a constant force on the robot side; also checks the forward direction."""
    dut = TeleopChannel(6, config)
    builder = DiagramBuilder()
    builder.AddSystem(dut)
    simulator = Simulator(builder.Build())
    context = dut.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    stylus = np.arange(6.0)
    dut.GetInputPort("stylus_in").FixValue(context, stylus)
    dut.GetInputPort("force_in").FixValue(context, [0.1, -0.2, 0.3])
    dut.GetInputPort("stylus_position").FixValue(context, np.zeros(3))
    # stylus_velocity left unconnected: the controller differentiates the position.
    simulator.AdvanceTo(0.0105)
    np.testing.assert_array_equal(dut.GetOutputPort("stylus_out").Eval(context), stylus)
    np.testing.assert_allclose(dut.GetOutputPort("stylus_age").Eval(context), 0.0035)
    return (dut.GetOutputPort("force_out").Eval(context).copy(),
            dut.GetOutputPort("energy").Eval(context)[0])


def test_teleop_channel_ports_and_a_force_on_a_still_stylus():
    dut = TeleopChannel(6)
    assert [dut.get_input_port(i).get_name() for i in range(dut.num_input_ports())] == [
        "stylus_in", "force_in", "stylus_position", "stylus_velocity"]
    sizes = {dut.get_output_port(i).get_name(): dut.get_output_port(i).size()
             for i in range(dut.num_output_ports())}
    assert sizes == {"stylus_out": 6, "stylus_age": 1, "force_out": 3, "force_age": 1,
                     "energy": 1, "force_change": 3}
    assert dut.backward_channel().config().seed != dut.forward_channel().config().seed
    links = dict(forward=ChannelConfig(delay=0.003), backward=ChannelConfig(delay=0.002))
    # Strict passivity: a force that appears on a still stylus could push the bare stylus
    # (0.045 kg) by F T^2 / (2 m) in a period, work the loop has not received: not rendered.
    force, energy = _still_stylus_force(TeleopChannelConfig(**links))
    np.testing.assert_array_equal(force, 0.0)
    assert energy == 0.0
    # A budget of 1.2e-4 J covers |F|^2 T^2 / (2 m) = 1.6e-6 J: the force passes, and since
    # the stylus does not move no energy is spent.
    budget = PassivityConfig(energy_budget=1.2e-4)
    force, energy = _still_stylus_force(TeleopChannelConfig(**links, passivity=budget))
    np.testing.assert_allclose(force, [0.1, -0.2, 0.3])
    assert energy == 0.0
    # Switched off, the force passes whatever the energy.
    force, _ = _still_stylus_force(
        TeleopChannelConfig(**links, passivity=PassivityConfig(enabled=False)))
    np.testing.assert_allclose(force, [0.1, -0.2, 0.3])


def test_config_yaml_round_trip_defaults_and_unknown_keys():
    config = TeleopChannelConfig(
        forward=ChannelConfig(delay=0.05, jitter=0.002, loss=0.01, period=0.002, seed=4),
        backward=ChannelConfig(delay=0.04, seed=9),
        passivity=PassivityConfig(enabled=False, max_damping=5.0, moving_mass=0.1,
                                  force_limit=0.0))
    text = yaml_dump_typed(config)
    assert yaml_load_typed(schema=TeleopChannelConfig, data=text) == config
    assert yaml_load_typed(schema=TeleopChannelConfig, data="{}") == TeleopChannelConfig()
    partial = yaml_load_typed(schema=ChannelConfig, data="{delay: 0.05}")
    assert partial == ChannelConfig(delay=0.05)
    with pytest.raises(RuntimeError):
        yaml_load_typed(schema=ChannelConfig, data="{latency: 0.05}")
    check_channel_config(ChannelConfig())
    check_passivity_config(PassivityConfig())


@pytest.mark.parametrize("field, value", [
    ("delay", -0.01), ("delay", math.inf), ("jitter", -1e-3), ("jitter", math.nan),
    ("loss", 1.0), ("loss", -0.1), ("period", 0.0), ("period", -1e-3), ("seed", -1),
    ("seed", 1.5), ("seed", math.nan)])
def test_bad_channel_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        DelayChannel(1, dataclasses.replace(ChannelConfig(), **{field: value}))


@pytest.mark.parametrize("field, value", [
    ("period", 0.0), ("max_damping", -1.0), ("moving_mass", 0.0), ("force_limit", -3.3),
    ("force_limit", math.nan)])
def test_bad_passivity_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        PassivityController(dataclasses.replace(PassivityConfig(), **{field: value}))


def test_bad_channel_size_is_refused():
    with pytest.raises(ValueError, match="size"):
        DelayChannel(0)
