"""The EPM keeps its clearance where it is, not only where it is sent (epm/shaping.py,
epm/clearance.py, the servoed stage's check in epm/stage.py).

The issue: a navigator whose every command sat at the legal floor over one flank and then the
other took the EPM 90 mm below the skin on the servoed stage (its servo went the straight way,
through the belly) and soft servo gains alone took it 140 mm in, each with exit 0. Checked
here: the shaper's path against the floor for any commands (hypothesis), the servo's error
bound against a simulated servo, and every mount under every kind of driver, with the gap
measured on the logged pose by sampling the magnet's surface against the skin under each
sample (not through the guard's formula)."""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import LeafSystem

from capsule_drake.anatomy import load_colon
from capsule_drake.app.run import simulate
from capsule_drake.epm.clearance import (CLEARANCE_TOLERANCE, clearance_breach,
                                         closest_approach, epm_skin_gap, largest_pull)
from capsule_drake.epm.guard import command_workspace, floor_guard, safe_command
from capsule_drake.epm.paths import epm_start
from capsule_drake.epm.poses import stage_to_pose
from capsule_drake.epm.shaping import (CHORD_SLACK, M, P, V, MotionLimits, initial_state,
                                       shape_step, turn_toward, unit)
from capsule_drake.epm.stage import (AXIS_MASSES, TURN_INERTIAS, Gains, Stage,
                                     check_stage_servo, servo_errors)
from capsule_drake.models import configure_parser, model_url
from capsule_drake.physics.magnetics import MU0, MagnetGeometry
from capsule_drake.scenario import load_scenario
from capsule_drake.schema import ScenarioError
from plugins.sweeper import FLANK_X
from test_epm_guard import magnet_skin_gap

MAGNET = MagnetGeometry()   # the default EPM: a 101.6 x 101.6 mm N52 cylinder
IPM = MagnetGeometry(dimensions=[0.0111, 0.0111])
CLEARANCE = 0.02
DT = 0.001


class Dome:
    """A belly: skin at `base` beyond an elliptic dome `height` above it, `half_width` across
    and `half_length` along (m), as the default abdomen's, with its centre at (x0, y0)."""

    def __init__(self, base=0.11, height=0.11, half_width=0.2, half_length=0.3, x0=0.0,
                 y0=0.0):
        self.base, self.height = base, height
        self.a, self.b, self.x0, self.y0 = half_width, half_length, x0, y0

    def skin_height(self, x, y):
        u = (np.asarray(x, float) - self.x0) / self.a
        v = (np.asarray(y, float) - self.y0) / self.b
        return self.base + self.height * np.sqrt(np.clip(1.0 - u * u - v * v, 0.0, None))


class Line:
    def __init__(self, points):
        self.centerline = type("Centerline", (), {"points": np.asarray(points, float)})()


WORKSPACE = command_workspace(Line([[-0.3, -0.3, 0.05], [0.3, 0.3, 0.2]]))


def floor_of(skin):
    """The floor of the shaper (vectorised: x, y (N), moments (N, 3))."""
    return floor_guard(skin, MAGNET, CLEARANCE).lowest_centre_heights


def floor_at(floor, x, y, m) -> float:
    """The floor at one point, for one moment of any length."""
    return float(floor(np.array([x]), np.array([y]), unit(m)[None, :])[0])


# --- the shaper, as a pure function --------------------------------------------------------

def run_shaper(commands, holds, limits, floor, start):
    """Steps the shaper through `commands`, each held `holds[k]` steps; returns the poses
    [p, m] after every step (the start first) and the velocities."""
    x = initial_state(start)
    poses, velocities = [np.concatenate([x[P], x[M]])], [x[V].copy()]
    for command, hold in zip(commands, holds):
        for _ in range(hold):
            x = shape_step(x, command, floor, limits, DT)
            poses.append(np.concatenate([x[P], x[M]]))
            velocities.append(x[V].copy())
    return np.array(poses), np.array(velocities)


def lowest_gap_along(poses, floor, spacing=1e-3):
    """The smallest height (m) of the path's centre over the floor, the path being the
    straight lines between consecutive poses (the moment turned along each), sampled every
    `spacing` m and every degree (finer than the shaper's own samples: 5 mm, 5 degrees)."""
    first = poses[0]
    worst = first[2] - floor_at(floor, first[0], first[1], first[3:])
    for a, b in zip(poses[:-1], poses[1:]):
        if np.array_equal(a, b):
            continue
        length = np.linalg.norm(b[:3] - a[:3])
        angle = math.acos(np.clip(unit(a[3:]) @ unit(b[3:]), -1.0, 1.0))
        n = max(1, int(math.ceil(length / spacing)), int(math.ceil(math.degrees(angle))))
        for t in np.linspace(0.0, 1.0, n + 1)[1:]:
            p = a[:3] + t * (b[:3] - a[:3])
            worst = min(worst, p[2] - floor_at(floor, p[0], p[1],
                                                  turn_toward(a[3:], b[3:], t)))
    return worst


limits_strategy = st.one_of(
    st.just(MotionLimits()),
    st.builds(MotionLimits, st.floats(0.02, 1.0), st.floats(0.2, 10.0), st.floats(0.2, 5.0)))
xy = st.floats(-0.3, 0.3)
moment = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(
    lambda m: np.linalg.norm(m) > 0.1)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(limits=limits_strategy,
       dome=st.builds(Dome, height=st.floats(0.0, 0.15), half_width=st.floats(0.05, 0.3),
                      x0=st.floats(-0.1, 0.1)),
       raw=st.lists(st.tuples(xy, xy, st.floats(-0.5, 0.6), moment, st.integers(1, 300)),
                    min_size=1, max_size=4))
def test_the_shaped_path_stays_over_the_floor_whatever_is_commanded(limits, dome, raw):
    # Commands anywhere (into the patient too) go through the guard, then the shaper: every
    # pose it asks of the carrier, and the straight way between consecutive poses, lies on
    # or over the floor; it never moves faster than its speed limit.
    floor = floor_of(dome)
    guard = floor_guard(dome, MAGNET, CLEARANCE)
    start = safe_command(guard, WORKSPACE, np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))[0]
    commands = [safe_command(guard, WORKSPACE, np.array([x, y, z, *m]))[0]
                for x, y, z, m, _ in raw]
    poses, velocities = run_shaper(commands, [hold for *_, hold in raw], limits, floor,
                                   start)
    assert np.all(np.isfinite(poses))
    assert lowest_gap_along(poses, floor) >= -CHORD_SLACK - 1e-6
    if not limits.instant:
        speeds = np.linalg.norm(velocities, axis=1)
        assert speeds.max() <= limits.max_speed * (1 + 1e-9) + 1e-12


@settings(max_examples=10, deadline=None)
@given(limits=st.one_of(st.just(MotionLimits()), st.builds(
           MotionLimits, st.floats(0.1, 1.0), st.floats(0.5, 10.0), st.floats(0.5, 5.0))),
       x=st.floats(0.3, 0.35), z_up=st.floats(0.0, 0.05),
       moment_end=moment)
@pytest.mark.slow
def test_a_command_across_the_belly_goes_over_it_and_arrives(limits, x, z_up, moment_end):
    # Flank to flank at the floor: the straight way is through the dome; the shaper rises,
    # crosses and comes down onto the command, which it reaches exactly.
    dome = Dome()
    floor = floor_of(dome)
    guard = floor_guard(dome, MAGNET, CLEARANCE)
    start = safe_command(guard, WORKSPACE, np.array([-x, 0.0, 0.0, 0.0, 0.0, 1.0]))[0]
    target = safe_command(guard, WORKSPACE, np.array([x, 0.0, 0.0, *moment_end]))[0]
    target[2] += z_up
    # The straight way is not clear: the belly's floor is far above the chord.
    middle = 0.5 * (start[:3] + target[:3])
    assert middle[2] < floor_at(floor, middle[0], middle[1], target[3:]) - 0.05
    steps = 20 if limits.instant else int(15.0 / DT)
    x_state = initial_state(start)
    poses = [np.concatenate([x_state[P], x_state[M]])]
    for _ in range(steps):
        x_state = shape_step(x_state, target, floor, limits, DT)
        poses.append(np.concatenate([x_state[P], x_state[M]]))
        if np.array_equal(poses[-1], np.concatenate([target[:3], target[3:]])):
            break
    poses = np.array(poses)
    np.testing.assert_array_equal(poses[-1], target)   # there, bit for bit
    assert lowest_gap_along(poses, floor) >= -CHORD_SLACK - 1e-6
    if limits.instant:
        assert len(poses) == 4   # up, across, down: three legs, each at once


def test_a_clear_command_passes_the_kinematic_shaper_bit_for_bit():
    # The kinematic stage's every clear command reaches it untouched (the navigators' small
    # steps along the floor): the shaper changes nothing it need not.
    dome = Dome()
    floor = floor_of(dome)
    guard = floor_guard(dome, MAGNET, CLEARANCE)
    x = initial_state(safe_command(guard, WORKSPACE, np.array([0.0, 0.0, 0.0, 0.3, 0.1, 2.0]))[0])
    rng = np.random.default_rng(3)
    for _ in range(200):
        p = x[P] + rng.normal(scale=0.002, size=3) + [0.0, 0.0, 0.003]
        command = np.concatenate([p, [0.3, 0.1, 2.0] + rng.normal(scale=0.01, size=3)])
        command = safe_command(guard, WORKSPACE, command)[0]
        x = shape_step(x, command, floor, MotionLimits(), DT)
        np.testing.assert_array_equal(np.concatenate([x[P], x[M]]), command)


@settings(max_examples=20, deadline=None)
@given(raw=st.lists(st.tuples(*[st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                                          st.floats(-1.0, 1.0)) for _ in range(6)]),
                    min_size=1, max_size=12),
       limits=limits_strategy)
def test_the_command_path_keeps_the_floor_for_any_numbers(raw, limits):
    # The whole path of a command (the guard: reject what is not a pose, hold the last safe
    # one; then the shaper) on arbitrary floats, NaN, infinities and huge values included.
    dome = Dome()
    floor = floor_of(dome)
    guard = floor_guard(dome, MAGNET, CLEARANCE)
    last = safe_command(guard, WORKSPACE, np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))[0]
    x = initial_state(last)
    poses = [np.concatenate([x[P], x[M]])]
    for values in raw:
        safe = safe_command(guard, WORKSPACE, np.array(values, dtype=float))
        last = safe[0] if safe is not None else last
        for _ in range(10):
            x = shape_step(x, last, floor, limits, DT)
            poses.append(np.concatenate([x[P], x[M]]))
    poses = np.array(poses)
    assert np.all(np.isfinite(poses))
    low, high = WORKSPACE
    assert np.all(poses[:, :2] >= low[:2] - 1e-12) and np.all(poses[:, :2] <= high[:2] + 1e-12)
    assert min(p[2] - floor_at(floor, p[0], p[1], p[3:]) for p in poses) >= -1e-9


# --- the servo's error bound -----------------------------------------------------------------

def simulated_servo_error(mass, p, d, force, accel, speed=0.05, h=2e-5, duration=1.5):
    """The largest error (m) of a PD servo of `mass` (kg) following a reference that speeds
    up at `accel` to `speed`, cruises, and slows down at `accel` to a stop, with a constant
    `force` (N) pushing it off, integrated with semi-implicit Euler at `h` (s), the reference's
    velocity fed forward."""
    x = v = 0.0
    r = rv = 0.0
    worst = 0.0
    t_ramp = speed / accel
    for k in range(int(duration / h)):
        t = k * h
        a_ref = accel if t < t_ramp else (-accel if 0.6 * duration < t < 0.6 * duration
                                          + t_ramp else 0.0)
        rv = max(rv + a_ref * h, 0.0)
        r += rv * h
        u = p * (r - x) + d * (rv - v) - force
        v += u / mass * h
        x += v * h
        worst = max(worst, abs(r - x))
    return worst


@pytest.mark.parametrize("zeta", [0.2, 0.5, 0.8, 1.0])
def test_the_servo_bound_holds_against_a_simulated_servo(zeta):
    # Second route: a 1-DoF PD servo of the heaviest axis, integrated finely, under the pull
    # and the reference's acceleration, never lags more than servo_errors' translation part,
    # and not less than half of it (the bound is not vacuous).
    mass = AXIS_MASSES["x"]
    p = 2.0e4
    d = 2.0 * zeta * math.sqrt(p * mass)
    force, accel = 15.0, 1.0
    config = Stage(kinematic=False, translation_gains=Gains(p=p, d=d), max_acceleration=accel)
    bound, _ = servo_errors(config, force, 0.0, MAGNET)
    worst = simulated_servo_error(mass, p, d, force, accel)
    assert worst <= bound, (worst, bound)
    assert worst >= 0.5 * bound, (worst, bound)


def test_the_turn_bound_holds_against_a_simulated_servo():
    # A turn that starts at max_turn_rate at once: the critically damped axis lags it by at
    # most w / (e wn), plus the twist's deflection.
    inertia = max(TURN_INERTIAS.values())
    gains = Gains(p=400.0, d=2.0 * math.sqrt(400.0 * inertia))
    rate, twist = 1.0, 0.5
    config = Stage(kinematic=False, rotation_gains=gains, max_turn_rate=rate)
    _, turn = servo_errors(config, 0.0, twist, MAGNET)
    lever = math.hypot(0.0508, 0.0508)
    x = v = 0.0
    worst = 0.0
    h = 1e-6
    for k in range(int(0.2 / h)):
        t = k * h
        reference = rate * t
        u = gains.p * (reference - x) + gains.d * (rate - v) - twist
        v += u / inertia * h
        x += v * h
        worst = max(worst, abs(reference - x))
    assert worst * lever <= turn <= 1.5 * worst * lever, (worst * lever, turn)


def test_the_stage_masses_are_the_models():
    # AXIS_MASSES and TURN_INERTIAS, read again from models/epm_stage.sdf: the mass each
    # joint moves (its child link and all below it).
    plant = MultibodyPlant(0.0)
    configure_parser(Parser(plant)).AddModels(url=model_url("epm_stage.sdf"))
    plant.Finalize()
    chain = ["stage_x", "stage_y", "stage_z", "stage_yaw", "epm"]
    masses = [plant.GetBodyByName(name).default_mass() for name in chain]
    for axis, first in (("x", 0), ("y", 1), ("z", 2)):
        assert AXIS_MASSES[axis] == pytest.approx(sum(masses[first:]))
    epm = plant.GetBodyByName("epm").default_rotational_inertia().CopyToFullMatrix3()
    yaw_link = plant.GetBodyByName("stage_yaw").default_rotational_inertia()
    assert TURN_INERTIAS["pitch"] == pytest.approx(epm[1, 1])
    # About the vertical, the magnet turns about its x or y axis at the working pitch (90).
    assert TURN_INERTIAS["yaw"] == pytest.approx(
        max(epm[0, 0], epm[2, 2]) + yaw_link.CopyToFullMatrix3()[2, 2])


def test_the_largest_pull_is_the_coaxial_dipole_at_the_closest_approach():
    r = closest_approach(MAGNET, CLEARANCE)
    # The EPM's lowest point 20 mm over the skin, its centre 50.8 mm above that, the capsule's
    # axis at least its radius (5.8 mm, models/capsule.sdf) under the skin.
    assert r == pytest.approx(0.02 + 0.0508 + 0.0058, abs=1e-12)
    force, torque = largest_pull(MAGNET, IPM, CLEARANCE)
    m_a, m_c = MAGNET.moment(), IPM.moment()
    assert force == pytest.approx(3.0 * MU0 * m_a * m_c / (2.0 * math.pi * r**4), rel=1e-12)
    assert torque == pytest.approx(m_a * MU0 * m_c / (2.0 * math.pi * r**3), rel=1e-12)
    # No orientation of the two moments pulls harder (random pairs at that distance).
    from capsule_drake.physics.magnetics import dipole_force, dipole_torque
    rng = np.random.default_rng(0)
    for _ in range(2000):
        a, c, u = (unit(rng.normal(size=3)) for _ in range(3))
        assert np.linalg.norm(dipole_force(m_c * c, m_a * a, r * u)) <= force * (1 + 1e-9)
        assert np.linalg.norm(dipole_torque(m_c * c, m_a * a, r * u)) <= torque * (1 + 1e-9)


def test_the_default_servo_passes_and_soft_gains_are_refused_in_one_line():
    pull, twist = largest_pull(MAGNET, IPM, CLEARANCE)
    check_stage_servo(Stage(kinematic=False), pull, twist, MAGNET, CLEARANCE_TOLERANCE)
    for soft in ({"translation_gains": Gains(p=100.0, d=10.0)},
                 {"translation_gains": Gains(p=2.0e4, d=0.0)},
                 {"rotation_gains": Gains(p=1.0, d=0.1)},
                 {"max_acceleration": 10.0}):
        with pytest.raises(ValueError, match="more than the 2 mm") as caught:
            check_stage_servo(Stage(kinematic=False, **soft), pull, twist, MAGNET,
                              CLEARANCE_TOLERANCE)
        assert "\n" not in str(caught.value)
    # Through the scenario: the soft gains are refused at load, before any build.
    with pytest.raises(ScenarioError, match="epm.mount: the servoed stage may let the EPM"):
        load_scenario(override="{epm: {mount: !Stage {kinematic: false, translation_gains: "
                               "{p: 100, d: 10}}}}")


def test_the_watch_reads_the_guards_measure():
    dome = Dome()
    floor = floor_of(dome)
    m = np.array([0.0, 0.0, 1.0])
    on_floor = np.array([0.05, 0.02, floor_at(floor, 0.05, 0.02, m), *m])
    assert epm_skin_gap(dome, on_floor, MAGNET) == pytest.approx(CLEARANCE, abs=1e-12)
    assert clearance_breach(dome, MAGNET, CLEARANCE, on_floor) is None
    lower = on_floor.copy()
    lower[2] -= CLEARANCE_TOLERANCE * 0.99
    assert clearance_breach(dome, MAGNET, CLEARANCE, lower) is None
    lower[2] -= CLEARANCE_TOLERANCE * 0.02
    assert "inside its 20 mm epm.clearance" in clearance_breach(dome, MAGNET, CLEARANCE, lower)
    lower[2] -= 0.05
    assert "inside the patient" in clearance_breach(dome, MAGNET, CLEARANCE, lower)
    assert clearance_breach(dome, MAGNET, CLEARANCE, np.full(6, np.nan)) is None


# --- every mount under every kind of driver, in the station ---------------------------------

def softest_stage_gains() -> str:
    """The softest servoed stage the scenario accepts at its default speeds: no damping at
    all, and the lowest stiffness that passes (bisected)."""
    pull, twist = largest_pull(MAGNET, IPM, CLEARANCE)
    low, high = 1.0, 1.0e6
    for _ in range(60):
        p = math.sqrt(low * high)
        try:
            check_stage_servo(Stage(kinematic=False, translation_gains=Gains(p=p, d=0.0)),
                              pull, twist, MAGNET, CLEARANCE_TOLERANCE)
            high = p
        except ValueError:
            low = p
    return f"!Stage {{kinematic: false, translation_gains: {{p: {high * 1.0001:.6g}, d: 0}}}}"


# The mounts, at their defaults and as soft as the scenario lets them be. The arm's softest
# (any positive stiffness passes) is test_a_run_whose_magnet_comes_too_close's.
MOUNTS = {"kinematic": "!Stage {}", "servoed-softest": softest_stage_gains(), "arm": "!Arm {}",
          "servoed": "!Stage {kinematic: false}"}   # the default servo: the benchmark's only
SMALL_CAMERA = "capsule: {camera: {fps: 5.0, lens: {width: 64, height: 64}}"
# Each kind of driver: its scenario text, what else it needs, and how long it runs (s).
# (!HoldAbove is a path driver as !AlongColon is: the benchmark runs it, the test does not.)
DRIVERS = {
    "along": ("!AlongColon {speed: 0.05}", "", 1.0),
    "hold": ("!HoldAbove {height: 0.3}", "", 0.5),
    # 2.5 s on one flank, then toward the other: 2 s of it is enough for every mount to
    # cross the top of the belly (the arm, bounding its accelerations, rises over it first).
    "plugin-sweep": ("!Plugin {factory: 'plugins.sweeper:flanks'}", "", 4.5),
    "external-sweep": ("!External {}", "", 4.5),
    "follower": ("!LumenFollower {lumen: truth}", SMALL_CAMERA + "},", 1.0),
    "teleop": ("!Teleop {}", SMALL_CAMERA + ", lumen_tracker: {}},", 1.0),
}


class Sweep(LeafSystem):
    """A script's command on the station's epm.command input (!External): the sweeper's
    flanks, from the EPM's start (its y and moment)."""

    def __init__(self, floor, start):
        super().__init__()
        self._floor, self._start = floor, np.asarray(start, float)
        self.DeclareVectorOutputPort("command", 6, self._calc)

    def _calc(self, context, output):
        x = FLANK_X if int(context.get_time() / 2.5) % 2 == 0 else -FLANK_X
        m = unit(self._start[3:])
        output.SetFromVector([x, self._start[1], self._floor(x, self._start[1], m), *m])


def run_and_measure(mount: str, driver: str):
    """Simulates `mount` under `driver`; returns the scenario, the result and the magnet's
    smallest gap to the skin over the run, twice: its surface sampled against the skin
    under each sample (the true gap, up to the sampling), and as the guard and the watch
    measure it (its lowest point against the highest skin under its footprint: smaller
    where the skin falls away under the magnet)."""
    command, extra, duration = DRIVERS[driver]
    scenario = load_scenario(override=(
        f"{{duration: {duration}, outputs: {{log_period: 0.005}}, {extra} "
        f"epm: {{mount: {MOUNTS[mount]}, driver: {command}}}}}"))
    colon = load_colon(scenario.colon)[0]
    extend = None
    if driver == "external-sweep":
        guard = floor_guard(colon.abdomen, scenario.epm.magnet, scenario.epm.clearance)
        start = stage_to_pose(epm_start(scenario.epm, colon, scenario.capsule.start_s))

        def extend(builder, station):
            sweep = builder.AddSystem(Sweep(guard.lowest_centre_height, start))
            builder.Connect(sweep.get_output_port(), station.GetInputPort("epm.command"))

    result = simulate(scenario, progress=False, extend=extend)
    pose = result.epm_pose
    gap = min(magnet_skin_gap(colon.abdomen, pose[:, k], scenario.epm.magnet)
              for k in range(pose.shape[1]))
    guards_gap = min(epm_skin_gap(colon.abdomen, pose[:, k], scenario.epm.magnet)
                     for k in range(pose.shape[1]))
    return scenario, result, gap, guards_gap


@pytest.mark.slow
@pytest.mark.parametrize("mount, driver", [(mount, driver) for mount in sorted(MOUNTS)
                                           if mount != "servoed" for driver in sorted(DRIVERS)
                                           if driver != "hold"])
def test_every_mount_keeps_the_clearance_under_every_driver(mount, driver):
    # The sweep at the floor from flank to flank (a plug-in, and a script on the
    # !External input), the built-in drivers, on each mount: the magnet's smallest gap over
    # the run is the clearance less at most CLEARANCE_TOLERANCE, and the run is not stopped
    # (the servo as soft as accepted, undamped, included).
    scenario, result, gap, guards_gap = run_and_measure(mount, driver)
    assert result.status == "completed", (result.status, result.metrics.get("stopped_early"))
    assert gap >= scenario.epm.clearance - CLEARANCE_TOLERANCE, (mount, driver, gap)
    assert guards_gap >= scenario.epm.clearance - CLEARANCE_TOLERANCE, (mount, driver,
                                                                        guards_gap)
    if driver.endswith("sweep"):
        # It did go from one flank toward the other, over the top of the belly (x = 0).
        assert result.epm_pose[0].min() < -0.05 and result.epm_pose[0].max() > 0.1


@pytest.mark.slow
def test_a_run_whose_magnet_comes_too_close_stops_with_one_line_and_exit_1(tmp_path):
    # The arm with joints a hundred times softer than its defaults: the pull bends it toward
    # the skin; the watch stops the run, the CLI says so in one line and exits 1, and the
    # logs and metrics are on disk.
    import subprocess
    import sys
    out = tmp_path / "run"
    done = subprocess.run(
        [sys.executable, "-m", "capsule_drake.app.entry", "run", "--duration", "3",
         "--no-recording", "--out", str(out), "--scenario-text",
         "{epm: {mount: !Arm {joint_stiffness: [80, 80, 50, 50, 20, 10, 5], "
         "joint_damping: [30, 30, 15, 15, 4, 2, 0.8]}}}"],
        capture_output=True, text=True, timeout=600)
    assert done.returncode == 1, done.stderr
    stopped = [line for line in done.stderr.splitlines() if "clearance watch" in line]
    assert len(stopped) == 1 and "epm.clearance" in stopped[0], done.stderr
    assert "Traceback" not in done.stderr
    assert (out / "metrics.json").exists() and (out / "logs.npz").exists()
    import json
    assert json.loads((out / "metrics.json").read_text())["status"] == "epm_clearance"
