"""Scenario files: defaults, named scenarios, overrides, and one-line errors for bad input."""

import subprocess
import sys

import pytest

from capsule_drake.scenario import (
    DEFAULT_SCENARIO_FILE,
    AlongColon,
    HoldAbove,
    Scenario,
    ScenarioError,
    dump_scenario,
    load_scenario,
    scenario_names,
)


def write(tmp_path, text, name="s.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_default_file_scenarios_load():
    names = scenario_names(DEFAULT_SCENARIO_FILE)
    assert "Default" in names and "FarMagnet" in names
    default = load_scenario()
    assert default == Scenario()  # `Default: {}` is all defaults
    far = load_scenario(name="FarMagnet")
    assert isinstance(far.epm.path, HoldAbove) and far.epm.path.height == 0.5


def test_override_layers_on_top_without_touching_defaults(tmp_path):
    path = write(tmp_path, "A:\n  duration: 2.0\n  epm: {clearance: 0.03}\n")
    s = load_scenario(path, override="{epm: {path: !AlongColon {speed: 0.02}}}")
    assert s.duration == 2.0 and s.epm.clearance == 0.03
    assert isinstance(s.epm.path, AlongColon) and s.epm.path.speed == 0.02
    assert Scenario().epm.clearance == 0.02  # shared defaults were not mutated


def test_exponent_without_sign_is_a_number(tmp_path):
    # YAML 1.1 reads 5e6 as text; scenario files use that notation for moduli and gains.
    path = write(tmp_path, "A:\n  contact: {capsule_hydroelastic_modulus: 5e6}\n")
    assert load_scenario(path).contact.capsule_hydroelastic_modulus == 5e6


def test_dump_round_trips(tmp_path):
    s = load_scenario(name="FarMagnet")
    path = write(tmp_path, "X:\n" + "".join("  " + line + "\n" for line in dump_scenario(s).splitlines()))
    assert load_scenario(path) == s


@pytest.mark.parametrize("text, expected", [
    ("A:\n  epm: {clearence: 0.1}\n", "epm.clearence: unknown key"),
    ("A:\n  colon: {seed: 1.5}\n", "colon.seed: expected an integer"),
    ("A:\n  duration: fast\n", "duration: expected a number"),
    ("A:\n  epm: {path: !Teleport {height: 1}}\n", "epm.path: unknown tag !Teleport"),
    ("A:\n  epm: {path: !HoldAbove {hieght: 1}}\n", "epm.path.hieght: unknown key"),
    ("A:\n  duration: -1\n", "duration must be >= 0"),
    ("A:\n  capsule: {ipm: {shape: torus}}\n", "capsule.ipm"),
    ("A: [1, 2\n", "YAML syntax error"),
    ("A:\n  colon: {sigmoid: {diameter: -0.03}}\n", "colon.sigmoid.diameter must be > 0"),
    ("A:\n  colon: {transverse: {length_min: 0.6, length_max: 0.5}}\n",
     "colon.transverse.length_max must be >= length_min"),
    ("A:\n  colon: {ascending: {fold_height: 0.05}}\n", "colon.ascending.fold_height"),
    ("A:\n  colon: {collision_chunks: 0}\n", "colon.collision_chunks must be >= 1"),
    ("A:\n  contact: {model: mujoco}\n", "contact.model must be one of"),
    ("A:\n  capsule: {magnetometer: {sample_rate: 0}}\n",
     "capsule.magnetometer.sample_rate must be > 0"),
])
def test_bad_scenarios_name_the_key(tmp_path, text, expected):
    path = write(tmp_path, text)
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    message = str(info.value)
    assert expected in message
    assert "\n" not in message


def test_missing_file_and_unknown_name(tmp_path):
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario(tmp_path / "nope.yaml")
    with pytest.raises(ScenarioError, match="no scenario named 'Nope'"):
        load_scenario(name="Nope")


@pytest.mark.parametrize("text, key", [
    ("A:\n  epm: {clearence: 0.1}\n", "epm.clearence"),
    ("A:\n  time_step: [1]\n", "time_step"),
])
def test_cli_bad_input_is_one_line_and_nonzero(tmp_path, text, key):
    path = write(tmp_path, text)
    proc = subprocess.run([sys.executable, "-m", "capsule_drake.cli", "run", str(path),
                           "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and key in lines[0], proc.stderr


def test_cli_missing_file(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "capsule_drake.cli", "run",
                           str(tmp_path / "missing.yaml")], capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"capsule-sim: error: {tmp_path / 'missing.yaml'}: scenario file not found"
