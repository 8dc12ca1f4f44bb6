"""The run guard (io/guard.py): what it finds in a capsule's state, and a run it stops."""

import json

import numpy as np
import pytest

from capsule_drake.anatomy import load_colon
from capsule_drake.capsule.model import capsule_model
from capsule_drake.app.cli import main as cli_main
from capsule_drake.io.guard import (ENDING_OF_KIND, GuardConfig, check_capsule_in_colon,
                                    check_capsule_state, parse_guard_reason)
from capsule_drake.physics.contact import CompliantWall, RigidWall
from capsule_drake.io.metrics import OUTCOMES, capsule_surface_points_C
from capsule_drake.app.run import simulate
from capsule_drake.scenario import ScenarioError, load_scenario


@pytest.fixture(scope="module")
def colon():
    return load_colon(load_scenario().colon)[0]


def _state(p, q=(1.0, 0.0, 0.0, 0.0), v=(0.0, 0.0, 0.0)):
    return np.concatenate([q, p, [0.0, 0.0, 0.0], v])


def _points():
    model = capsule_model()
    return capsule_surface_points_C(model.radius, model.length)


def test_state_checks_name_what_went_wrong():
    assert check_capsule_state(_state([0, 0, 0], v=[0.3, 0.0, 0.0]), 2.0) is None
    kind, text = check_capsule_state(_state([0, 0, 0], v=[0.0, 3.0, 0.0]), 2.0)
    assert kind == "speed" and "3 m/s" in text
    kind, text = check_capsule_state(_state([0, np.nan, 0]), 2.0)
    assert kind == "not_finite" and "position" in text and "velocity" not in text
    kind, text = check_capsule_state(_state([0, 0, 0], q=(np.inf, 0, 0, 0)), 2.0)
    assert kind == "not_finite" and "orientation" in text


def test_the_wall_check_follows_the_colon(colon):
    cl = colon.centerline
    s = 0.6
    t, n, _ = cl.frame_at(s)
    q_along = _quaternion_z_to(t)
    # On the centreline: inside.
    assert check_capsule_in_colon(colon, _state(cl.point_at(s), q_along), _points(), 0.005) is None
    # Moved sideways by the wall's radius there plus 8 mm: the near side is ~8 mm + the
    # capsule's radius beyond the wall.
    radius = float(colon.wall_radius(s, 0.0))
    outside = cl.point_at(s) + (radius + 0.008) * n
    kind, text = check_capsule_in_colon(colon, _state(outside, q_along), _points(), 0.005)
    assert kind == "wall" and "beyond the colon wall" in text
    # The same place passes with a guard that allows more than that.
    assert check_capsule_in_colon(colon, _state(outside, q_along), _points(), 0.05) is None
    # Through a wall that yields (the compliant wall's `wall_tears`): the wall tore.
    kind, text = check_capsule_in_colon(colon, _state(outside, q_along), _points(), 0.005,
                                        wall_allowance=0.002, wall_tears=True)
    assert kind == "wall_torn" and "would have torn" in text and "2 mm the wall stretches" in text
    assert ENDING_OF_KIND["wall_torn"] == "perforated" and ENDING_OF_KIND["wall"] == "diverged"
    # Past the start (s = 0) along the axis: out of the colon.
    before = cl.point_at(0.0) - 0.03 * cl.tangent_at(0.0)
    kind, text = check_capsule_in_colon(colon, _state(before, q_along), _points(), 0.005)
    assert kind == "left_colon" and "start" in text


def _quaternion_z_to(direction):
    """A unit quaternion (wxyz) turning +z onto `direction`."""
    z = np.array([0.0, 0.0, 1.0])
    d = direction / np.linalg.norm(direction)
    axis = np.cross(z, d)
    w = 1.0 + float(z @ d)
    q = np.array([w, *axis])
    return q / np.linalg.norm(q)


def test_a_guarded_run_stops_writes_its_logs_and_reports_no_distances(tmp_path):
    # A guard that a sound run trips (the capsule's starting drop onto the wall reaches
    # ~0.5 m/s): the mechanism, without needing a diverging simulation.
    scenario = load_scenario(override="{duration: 2.0, guard: {max_speed: 0.05}}")
    result = simulate(scenario, out_dir=tmp_path / "run", progress=False)
    assert result.status == "diverged"
    kind_text = result.metrics["stopped_early"]
    assert kind_text.startswith("stopped by the run guard at t = ")
    assert "faster than the 0.05 m/s" in kind_text
    stop_time = float(result.context.get_time())
    assert 0.0 < stop_time < 1.0
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["status"] == "diverged" and metrics["diverged"] is True
    assert all(metrics[key] is None for key in OUTCOMES)
    with np.load(tmp_path / "run" / "logs.npz") as logs:
        assert logs["times"][-1] == pytest.approx(stop_time, abs=scenario.outputs.log_period)
        assert logs["capsule_state"].shape[1] == len(logs["times"]) >= 2
    assert (tmp_path / "run" / "scenario.yaml").is_file()
    assert not (tmp_path / "run" / "logs.parts").exists()


def test_a_torn_wall_ends_the_run_as_a_perforation_with_its_figures(tmp_path, monkeypatch,
                                                                    capsys):
    # The compliant wall yields, the rigid one does not: only through the first is a capsule
    # beyond the wall an event of the patient.
    assert CompliantWall().wall_tears() and not RigidWall().wall_tears()
    # A guard that a sound run on the compliant wall trips: no stretch allowed and 0.1 mm
    # beyond the undeformed wall (the capsule settles into it by more as it lands).
    monkeypatch.setattr(CompliantWall, "wall_allowance", lambda self, radius, colon=None: 0.0)
    code = cli_main(["run", "--duration", "2", "--no-recording", "--quiet",
                     "--scenario-text", "{contact: !CompliantWall {}, "
                                        "capsule: {start_s: 0.2}, "
                                        "guard: {max_wall_excursion: 1.0e-4}}",
                     "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 1
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "would have torn" in lines[0], err
    assert "figures up to it are reported" in lines[0] and "Traceback" not in err
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["status"] == "perforated" and metrics["diverged"] is False
    # Its figures stand: the capsule's excursion is beyond the guard's 0.1 mm.
    assert all(metrics[key] is not None for key in OUTCOMES)
    assert metrics["max_wall_excursion_m"] > 1.0e-4


def test_the_cli_says_why_in_one_line_and_exits_1(tmp_path, capsys):
    code = cli_main(["run", "--duration", "2", "--no-recording", "--quiet",
                     "--scenario-text", "{guard: {max_speed: 0.05}}",
                     "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 1
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "run guard" in lines[0] and "no distance" in lines[0]
    assert "Traceback" not in err


def test_guard_settings_are_checked():
    for text in ("{guard: {max_speed: 0}}", "{guard: {max_wall_excursion: .nan}}",
                 "{guard: {period: 1e-9}}"):
        with pytest.raises(ScenarioError, match="guard"):
            load_scenario(override=text)
    assert GuardConfig().max_speed == 2.0


def test_guard_messages_round_trip():
    assert parse_guard_reason("reached the cecum") is None
    assert parse_guard_reason("guard:speed: t = 1.000 s: fast") == ("speed", "t = 1.000 s: fast")
