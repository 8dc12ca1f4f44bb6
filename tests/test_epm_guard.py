"""The EPM's command guard (epm/guard.py, put before the carrier by epm/mount.py): every pose
command, whoever sends it (a user's plug-in, the !External input, a built-in driver), is
made safe before it reaches the carrier, and what the guard did is counted on
`epm.guard_counts`. The EPM's clearance is checked on its logged pose against the skin under
the magnet's sampled surface, not through the guard's own formula."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.anatomy import load_colon
from capsule_drake.app.run import simulate
from capsule_drake.epm.guard import (GUARD_COUNTS, RAISE_SLACK, WORKSPACE_HEADROOM,
                                     EpmCommandGuard, command_workspace, floor_guard,
                                     safe_command)
from capsule_drake.io.metrics import guard_metrics
from capsule_drake.physics.magnetics import MagnetGeometry
from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station

MAGNET = MagnetGeometry()   # the 101.6 x 101.6 mm cylinder
CLEARANCE = 0.02


class FlatSkin:
    """A patient whose skin is flat at `height` (m) everywhere."""

    def __init__(self, height):
        self.height = height

    def skin_height(self, x, y):
        return np.full(np.broadcast(np.asarray(x), np.asarray(y)).shape, self.height)


class Line:
    """A colon's centreline of two points, for the workspace."""

    def __init__(self, points):
        self.centerline = type("Centerline", (), {"points": np.asarray(points, float)})()


WORKSPACE = command_workspace(Line([[-0.1, -0.15, 0.05], [0.1, 0.15, 0.15]]))


def magnet_skin_gap(abdomen, pose, magnet=MAGNET):
    """Smallest vertical gap (m) between the EPM cylinder's surface at `pose` [p, m_hat]
    (its side and caps, sampled) and the skin straight under each sample."""
    p, m = np.asarray(pose[:3], float), np.asarray(pose[3:], float)
    m = m / np.linalg.norm(m)
    e1 = np.cross(m, [1.0, 0.0, 0.0] if abs(m[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(m, e1)
    radius, half = 0.5 * magnet.dimensions[0], 0.5 * magnet.dimensions[1]
    phi = np.linspace(0.0, 2.0 * np.pi, 180, endpoint=False)
    ring = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    points = [p + t * m + radius * ring for t in np.linspace(-half, half, 21)]
    points += [p + side * half * m + r * ring for side in (-1, 1)
               for r in np.linspace(0.0, radius, 11)]
    points = np.concatenate(points)
    return float(np.min(points[:, 2] - abdomen.skin_height(points[:, 0], points[:, 1])))


def test_a_safe_command_passes_bit_for_bit_and_an_unsafe_one_is_made_safe():
    skin = FlatSkin(0.2)
    guard = floor_guard(skin, MAGNET, CLEARANCE)
    up = [0.0, 0.0, 1.0]
    # The floor by hand: skin 0.2 m + clearance 0.02 m + half the 101.6 mm cylinder, upright.
    floor = 0.2 + 0.02 + 0.0508
    command = np.array([0.05, -0.02, floor + 0.01, *up])
    safe, raised, clamped = safe_command(guard, WORKSPACE, command)
    assert safe is command and not raised and not clamped
    # Into the patient: raised to the floor, nothing else touched.
    safe, raised, clamped = safe_command(guard, WORKSPACE, [0.05, -0.02, -0.5, *up])
    assert raised and not clamped
    np.testing.assert_allclose(safe, [0.05, -0.02, floor, *up], rtol=0, atol=1e-12)
    assert magnet_skin_gap(skin, safe) == pytest.approx(CLEARANCE, abs=1e-9)
    # Lying on its side (moment along x), the floor is the radius above the clearance, and a
    # moment that is not unit is passed on as it is (the carriers make it unit).
    safe, raised, _ = safe_command(guard, WORKSPACE, [0.0, 0.0, 0.0, 3.0, 0.0, 0.0])
    assert raised and safe[2] == pytest.approx(0.2 + 0.02 + 0.0508, abs=1e-12)
    np.testing.assert_array_equal(safe[3:], [3.0, 0.0, 0.0])
    assert magnet_skin_gap(skin, safe) == pytest.approx(CLEARANCE, abs=1e-9)
    # A thousand kilometres up: pulled into the workspace (2 m above the colon's top).
    safe, raised, clamped = safe_command(guard, WORKSPACE, [0.0, 0.0, 1e6, *up])
    assert clamped and not raised
    assert safe[2] == pytest.approx(0.15 + WORKSPACE_HEADROOM)
    safe, raised, clamped = safe_command(guard, WORKSPACE, [-1e300, 5.0, -1e300, *up])
    assert clamped and raised
    np.testing.assert_allclose(safe[:3], [-1.1, 1.15, floor], rtol=0, atol=1e-12)
    # A moment whose length overflows keeps its direction, made unit.
    safe, _, clamped = safe_command(guard, WORKSPACE, [0.0, 0.0, 0.5, 1e308, 0.0, 1e308])
    assert clamped
    np.testing.assert_allclose(safe[3:], [np.sqrt(0.5), 0.0, np.sqrt(0.5)])
    # Within the slack below the floor: untouched (a driver's floor from its own moment).
    command = np.array([0.0, 0.0, floor - 0.5 * RAISE_SLACK, *up])
    assert safe_command(guard, WORKSPACE, command)[0] is command
    # Not a pose: rejected.
    for bad in ([np.nan, 0, 0.5, *up], [0, 0, np.inf, *up], [0, 0, 0.5, 0, 0, 0],
                [0, 0, 0.5, 0, 0, -np.inf], [0, 0, 0.5, 0, 0, 1e-12]):
        assert safe_command(guard, WORKSPACE, np.array(bad, float)) is None


def test_the_guard_system_holds_the_last_safe_command_and_counts_each_command_once():
    skin = FlatSkin(0.2)
    start = np.array([0.0, 0.0, 0.4, 0.0, 0.0, 1.0])
    builder = DiagramBuilder()
    guard = builder.AddSystem(EpmCommandGuard(floor_guard(skin, MAGNET, CLEARANCE), WORKSPACE,
                                              start, period=0.001))
    guard.watch()   # as a connected driver does (EpmParts.command_input)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    local = guard.GetMyContextFromRoot(context)
    port = guard.GetInputPort("epm_command")
    out = guard.GetOutputPort("epm_command")

    def hold(command, t):
        port.FixValue(local, np.asarray(command, float))
        simulator.AdvanceTo(t)
        return out.Eval(local).copy(), guard.GetOutputPort("counts").Eval(local).copy()

    # NaN before any command: the start is held.
    command, counts = hold(np.full(6, np.nan), 0.0105)
    np.testing.assert_array_equal(command, start)
    np.testing.assert_array_equal(counts, [1, 0, 0, 1])
    # A safe command goes through at once (feedthrough) and is counted once, however long.
    good = np.array([0.02, 0.01, 0.35, 0.0, 0.0, 1.0])
    command, counts = hold(good, 0.0505)
    np.testing.assert_array_equal(command, good)
    np.testing.assert_array_equal(counts, [2, 0, 0, 1])
    # Into the skin: raised; then lost: the raised command is held.
    command, counts = hold([0.02, 0.01, 0.0, 0.0, 0.0, 1.0], 0.0605)
    np.testing.assert_allclose(command, [0.02, 0.01, 0.2708, 0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_array_equal(counts, [3, 1, 0, 1])
    held, counts = hold([0.0, 0.0, np.inf, 0.0, 0.0, 1.0], 0.0705)
    np.testing.assert_array_equal(held, command)
    np.testing.assert_array_equal(counts, [4, 1, 0, 2])
    # Far away and into the skin at once: both counted.
    command, counts = hold([50.0, 0.0, -3.0, 1.0, 0.0, 0.0], 0.0805)
    np.testing.assert_allclose(command[:3], [WORKSPACE[1][0], 0.0, 0.2708], atol=1e-12)
    np.testing.assert_array_equal(counts, [5, 2, 1, 2])
    assert dict(zip(GUARD_COUNTS, counts)) == {"commands": 5, "raised": 2, "clamped": 1,
                                                "rejected": 2}
    assert guard_metrics(counts) == {"epm_commands": 5, "epm_commands_raised": 2,
                                     "epm_commands_clamped": 1, "epm_commands_rejected": 2}


def load_colon_abdomen(scenario):
    return load_colon(scenario.colon)[0].abdomen


def _counts(result):
    station = result.station
    return station.GetOutputPort("epm.guard_counts").Eval(
        station.GetMyContextFromRoot(result.context))


def _plugin_run(factory, duration=1.0, mount=""):
    scenario = load_scenario(override=f"{{duration: {duration}, epm: {{driver: !Plugin "
                                      f"{{factory: 'plugins.unsafe:{factory}'}}{mount}}}}}")
    return scenario, simulate(scenario, progress=False)


# The counts of a second's run (commands, raised, clamped, rejected): one command held
# throughout; for flicker, NaN and into the table by turns every 0.15 s (7 commands, 4 NaN).
PLUGINS = {"into_the_table": [1, 1, 0, 0], "kilometre_up": [1, 0, 1, 0],
           "flicker": [7, 3, 0, 4]}


@pytest.mark.slow
@pytest.mark.parametrize("factory", sorted(PLUGINS))
def test_a_plugin_cannot_put_the_epm_into_the_patient_or_out_of_the_room(factory):
    # The issue: a navigator commanding z = -0.5 m had the magnet 769 mm inside the patient
    # (and z = 1e6 m, a thousand kilometres up), the run "completed".
    scenario, result = _plugin_run(factory)
    assert result.status == "completed"
    pose = result.epm_pose
    assert pose.shape[1] == 101 and np.all(np.isfinite(pose))
    abdomen = load_colon_abdomen(scenario)
    gaps = [magnet_skin_gap(abdomen, pose[:, k], scenario.epm.magnet)
            for k in range(pose.shape[1])]
    assert min(gaps) >= scenario.epm.clearance - 1e-9, min(gaps)
    # Within 2 m above the colon's highest point, and the summary's gap is the clearance.
    assert pose[2].max() < 2.5
    assert result.metrics["min_epm_skin_gap_m"] == pytest.approx(scenario.epm.clearance,
                                                                 abs=1e-6)
    counts = _counts(result)
    np.testing.assert_array_equal(counts, PLUGINS[factory])
    # What the run's metrics.json gets: the station's counts at the end of the run.
    assert [result.metrics[key] for key in ("epm_commands", "epm_commands_raised",
                                            "epm_commands_clamped", "epm_commands_rejected")] \
        == PLUGINS[factory]


@pytest.mark.slow
def test_the_guard_is_below_the_arm_too():
    # The arm's controller has a guard of its own; the station's raises the command first
    # (the same floor), so the arm holds the EPM where it starts, and the counts say so.
    scenario, result = _plugin_run("into_the_table", duration=0.5, mount=", mount: !Arm {}")
    np.testing.assert_array_equal(_counts(result), [1, 1, 0, 0])
    start = result.epm_pose[:, 0]
    assert np.abs(result.epm_pose[:3] - start[:3, None]).max() < 1e-3
    abdomen = load_colon_abdomen(scenario)
    assert min(magnet_skin_gap(abdomen, result.epm_pose[:, k])
               for k in range(result.epm_pose.shape[1])) > scenario.epm.clearance - 1e-3


def test_the_external_input_is_guarded():
    # !External (a script's, a notebook's, the Gymnasium environment's command): the station's
    # epm.command input goes through the guard as a plug-in's command does.
    scenario = load_scenario(override="epm: {driver: !External {}}")
    station = make_station(scenario)
    simulator = Simulator(station)
    context = simulator.get_mutable_context()
    start = station.GetOutputPort("epm.pose").Eval(context).copy()
    station.GetInputPort("epm.command").FixValue(context, np.full(6, np.nan))
    simulator.AdvanceTo(0.1)
    np.testing.assert_allclose(station.GetOutputPort("epm.pose").Eval(context), start,
                               rtol=0, atol=1e-12)
    below = start.copy()
    below[:3] += [0.02, 0.0, -0.3]
    station.GetInputPort("epm.command").FixValue(context, below)
    simulator.AdvanceTo(0.2)
    pose = station.GetOutputPort("epm.pose").Eval(context)
    np.testing.assert_allclose(pose[:2], below[:2], atol=1e-9)
    abdomen = load_colon_abdomen(scenario)
    # On the floor (the guard's, over the skin's highest point under the magnet's footprint:
    # the sampled surface is farther from the skin that slopes away under it), not above.
    gap = magnet_skin_gap(abdomen, pose)
    assert scenario.epm.clearance - 1e-9 <= gap < scenario.epm.clearance + 0.05, gap
    np.testing.assert_array_equal(station.GetOutputPort("epm.guard_counts").Eval(context),
                                  [2, 1, 0, 1])


@pytest.mark.slow
@pytest.mark.parametrize("name", ["Default", "Navigation"])
def test_the_built_in_drivers_pass_the_guard_untouched(name):
    # Default's path drives the stage's joints (no pose command: the guard has none);
    # Navigation's follower keeps its commands on the floor: none is raised.
    result = simulate(load_scenario(name=name, override="{duration: 1.0}"), progress=False)
    counts = _counts(result)
    if name == "Default":
        np.testing.assert_array_equal(counts, [0, 0, 0, 0])
    else:
        assert counts[0] >= 20 and not counts[1:].any(), counts
