"""Scenario files: defaults, named scenarios, overrides, and one-line errors for bad input."""

import dataclasses
import subprocess
import sys
import types
import typing
from pathlib import Path

import pytest
import yaml

from capsule_drake.scenario import (
    DEFAULT_SCENARIO_FILE,
    MOVED,
    AlongColon,
    Arm,
    HoldAbove,
    LumenFollower,
    Scenario,
    ScenarioError,
    dump_scenario,
    load_scenario,
    scenario_names,
    Stage,
    Teleop,
)


def same(a: Scenario, b: Scenario) -> bool:
    """Equal scenarios: every field, Drake's configs (plant, simulator) too, which have no
    `==` of their own (the dump spells out every field)."""
    return dump_scenario(a) == dump_scenario(b)


def write(tmp_path, text, name="s.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_default_file_scenarios_load():
    names = scenario_names(DEFAULT_SCENARIO_FILE)
    assert "Default" in names and "FarMagnet" in names
    default = load_scenario()
    assert same(default, Scenario())  # `Default: {}` is all defaults
    far = load_scenario(name="FarMagnet")
    assert isinstance(far.epm.driver, HoldAbove) and far.epm.driver.height == 0.5


def test_override_layers_on_top_without_touching_defaults(tmp_path):
    path = write(tmp_path, "A:\n  duration: 2.0\n  epm: {clearance: 0.03}\n")
    s = load_scenario(path, override="{epm: {driver: !AlongColon {speed: 0.02}}}")
    assert s.duration == 2.0 and s.epm.clearance == 0.03
    assert isinstance(s.epm.driver, AlongColon) and s.epm.driver.speed == 0.02
    assert Scenario().epm.clearance == 0.02  # shared defaults were not mutated


def test_exponent_without_sign_is_a_number(tmp_path):
    # YAML 1.1 reads 5e6 as text; scenario files use that notation for moduli and gains.
    path = write(tmp_path, "A:\n  contact: {capsule_hydroelastic_modulus: 5e6}\n")
    assert load_scenario(path).contact.capsule_hydroelastic_modulus == 5e6


def test_dump_round_trips(tmp_path):
    s = load_scenario(name="FarMagnet")
    path = write(tmp_path, "X:\n" + "".join("  " + line + "\n" for line in dump_scenario(s).splitlines()))
    assert same(load_scenario(path), s)


# Where an error is found: in the file's scenario as read ("<file> [<name>]: "), by the
# checks of the loaded scenario ("scenario: "), or by the YAML parser ("<file>:<line>: ").
@pytest.mark.parametrize("text, where, expected", [
    ("A:\n  epm: {clearence: 0.1}\n", "file", "epm.clearence: unknown key"),
    ("A:\n  colon: {seed: 1.5}\n", "file", "colon.seed: expected an integer"),
    ("A:\n  duration: fast\n", "file", "duration: expected a number"),
    ("A:\n  epm: {driver: !Teleport {height: 1}}\n", "file",
     "epm.driver: unknown tag !Teleport"),
    ("A:\n  epm: {driver: !HoldAbove {hieght: 1}}\n", "file",
     "epm.driver.hieght: unknown key"),
    ("A:\n  duration: -1\n", "scenario", "duration must be in [0, "),
    ("A:\n  capsule: {ipm: {shape: torus}}\n", "scenario", "capsule.ipm"),
    ("A: [1, 2\n", "line 2", "YAML syntax error"),
    ("A:\n  colon: {sigmoid: {diameter: -0.03}}\n", "scenario",
     "colon.sigmoid.diameter must be in [0.02, "),
    ("A:\n  colon: {transverse: {length_min: 0.6, length_max: 0.5}}\n", "scenario",
     "colon.transverse.length_max must be >= length_min"),
    ("A:\n  colon: {ascending: {fold_height: 0.05}}\n", "scenario",
     "colon.ascending.fold_height"),
    ("A:\n  colon: {collision_chunks: 0}\n", "scenario", "colon.collision_chunks must be in [1, 100]"),
    ("A:\n  contact: {model: mujoco}\n", "scenario", "contact.model must be one of"),
    ("A:\n  capsule: {magnetometer: {sample_rate: 0}}\n", "scenario",
     "capsule.magnetometer.sample_rate must be > 0"),
    ("A:\n  capsule: {imu: {p_BS: [1, 2]}}\n", "scenario",
     "capsule.imu.p_BS must have 3 entries"),
    ("A:\n  capsule: {magnetometer: {initial_bias: [0]}}\n", "scenario",
     "capsule.magnetometer.initial_bias must have 3 entries"),
    ("A:\n  capsule: {imu: {}, ahrs: {initial_q_WB: [1, 0]}}\n", "scenario",
     "capsule.ahrs.initial_q_WB must be empty"),
])
def test_bad_scenarios_name_the_key(tmp_path, text, where, expected):
    path = write(tmp_path, text)
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    message = str(info.value)
    prefix = {"file": f"{path} [A]: ", "scenario": "scenario: ", "line 2": f"{path}:2: "}[where]
    assert message.startswith(prefix + expected), message
    assert "\n" not in message


def _nested(key: str, value) -> dict:
    """{"a": {"b": value}} for the dotted key "a.b"."""
    for part in reversed(key.split(".")):
        value = {part: value}
    return value


def _attribute(obj, dotted: str):
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


@pytest.mark.parametrize("key", sorted(MOVED))
def test_moved_keys_say_where_they_went(tmp_path, key):
    # The old key is gone and its new home is a field of the scenario.
    new_key = MOVED[key].split(" ")[0]
    _attribute(Scenario(), new_key)
    with pytest.raises(AttributeError):
        _attribute(Scenario(), key)
    path = write(tmp_path, yaml.safe_dump({"A": _nested(key, 1)}))
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert str(info.value) == f"{path} [A]: {key}: moved to {MOVED[key]}"
    with pytest.raises(ScenarioError) as info:
        load_scenario(override=yaml.safe_dump(_nested(key, 1)))
    assert str(info.value) == f"override: {key}: moved to {MOVED[key]}"


def test_missing_file_and_unknown_name(tmp_path):
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario(tmp_path / "nope.yaml")
    with pytest.raises(ScenarioError, match="no scenario named 'Nope'"):
        load_scenario(name="Nope")
    # A run's scenario.yaml is one unnamed scenario: asking it for a name is refused.
    bare = tmp_path / "scenario.yaml"
    bare.write_text(dump_scenario(load_scenario(name="Teleop")))
    assert same(load_scenario(bare), load_scenario(name="Teleop"))
    with pytest.raises(ScenarioError, match="one unnamed scenario.*leave out --scenario"):
        load_scenario(bare, "Teleop")


@pytest.mark.parametrize("text, key", [
    ("A:\n  epm: {clearence: 0.1}\n", "epm.clearence"),
    ("A:\n  time_step: [1]\n", "time_step"),
])
def test_cli_bad_input_is_one_line_and_nonzero(tmp_path, text, key):
    path = write(tmp_path, text)
    proc = subprocess.run([sys.executable, "-m", "capsule_drake.app.cli", "run", str(path),
                           "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and key in lines[0], proc.stderr


@pytest.mark.slow
def test_cli_missing_file(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "capsule_drake.app.cli", "run",
                           str(tmp_path / "missing.yaml")], capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"capsule-sim: error: {tmp_path / 'missing.yaml'}: scenario file not found"


# --- OneOfEverything and OneOfEverythingElse ------------------------------------------------
# The reflection below walks the Scenario dataclasses. A path names a field as a scenario
# file does ("capsule.camera.lens.model"); a tagged union's member is `field[Member]`
# ("epm.driver[Teleop]") and its fields follow it ("epm.driver[Teleop].mapping.mode").
# Drake's configs embedded whole (plant: MultibodyPlantConfig, simulator: SimulatorConfig)
# are leaves.

TESTS_DIR = Path(__file__).resolve().parent

# Selectors that OneOfEverything and OneOfEverythingElse cannot hold beside their own
# choices (one driver per scenario: those two hold !AlongColon and !Teleop) or that would
# make their brief test slow, held by other named scenarios of diagrams/default.yaml that
# the tests simulate.
# path -> (scenario that sets it, the test that simulates that scenario); both are checked.
ELSEWHERE = {
    "colon.source[Procedural]": (  # the default source: every scenario that leaves it out
        "Default", "test_station.py::test_named_scenarios_simulate"),
    "contact[RigidWall].model": (  # convex_pieces: its build (~15 s, ~2 GB) is that test's
        "FastContact",
        "test_station.py::test_fast_contact_model_drags_the_capsule_inside_the_wall"),
    "epm.driver[HoldAbove]": (
        "FarMagnet", "test_station.py::test_capsule_stays_put_with_magnet_50cm_away"),
    "epm.driver[LumenFollower]": (
        "Navigation", "test_station.py::test_named_scenarios_simulate"),
    "epm.driver[LumenFollower].lumen": (  # lumen: detected
        "NavigationDetected", "test_station.py::test_named_scenarios_simulate"),
    "epm.driver[LumenFollower].pose": (  # pose: sensors
        "NavigationSensors", "test_station.py::test_named_scenarios_simulate"),
}

# The only selectors no simulated named scenario sets, each with its reason and the tests
# that exercise it (checked: they exist). Keep this list short: a selector that a
# scenario the tests simulate can hold belongs in OneOfEverything or OneOfEverythingElse.
EXCEPTIONS = {
    "colon.source[Imported]": (
        "an imported colon is a user's mesh or import folder, which no shipped scenario has",
        ("test_imported.py::test_the_drag_runs_on_the_imported_procedural_colon_as_on_the_original",
         "test_imported.py::test_an_import_folder_is_a_colon_source_and_bad_sources_fail_in_one_line")),
    "colon.source[Imported].path": (
        "as colon.source[Imported]",
        ("test_imported.py::test_the_readme_import_example_runs_with_the_capsule_inside",)),
    "colon.source[Imported].reverse": (
        "as colon.source[Imported]; the ex vivo segment's `reverse` is set in "
        "OneOfEverythingElse", ("test_imported.py::test_bad_sources_get_one_line",)),
    "colon.source[Population].tissue_percentile": (
        "every figure of the wall at one percentile in place of the draw: it excludes the "
        "named corner (colon.source[Population].tissue) that OneOfEverything, the only "
        "simulated scenario with a population colon, sets; it changes the compliant wall's "
        "figures, not the wiring",
        ("test_patient_tissue.py::test_the_corners_order_the_wall",
         "test_patient_tissue.py::test_metrics_and_benchmark_columns_say_what_the_wall_was")),
    "simulator": (
        "Drake's SimulatorConfig, a leaf: setting it (target_realtime_rate) would pace the "
        "runs to the wall clock", ()),
    "epm.driver[External]": (
        "one driver per scenario, and the station's epm.command input needs a system "
        "outside the station to drive it",
        ("test_station.py::test_external_driver_takes_the_epm_command_input",)),
    "epm.driver[Plugin]": (
        "one driver per scenario, and the navigator is a test's plug-in module",
        ("test_benchmark.py::test_a_user_navigator_runs_on_two_colons_and_gets_the_table",)),
    "epm.driver[Plugin].factory": (
        "as epm.driver[Plugin]: the factory names the test's plug-in",
        ("test_benchmark.py::test_a_user_navigator_runs_on_two_colons_and_gets_the_table",)),
    "epm.driver[Teleop].operator": (
        "browser needs a Meshcat page, udp a device sending on a socket",
        ("test_teleop.py::test_teleop_from_the_browser_follows_the_sliders",
         "test_teleop.py::test_teleop_over_udp_moves_the_epm_and_a_lost_link_holds_it")),
    "contact[CompliantWall].realisation": (
        "hydroelastic: Drake's realisation of the same wall, kept for comparison; three "
        "times slower than the foundation (the default, which OneOfEverythingElse runs)",
        ("test_foundation.py::test_both_realisations_drag_the_capsule_alike",
         "test_contact_models.py::test_the_simulated_wall_pushes_back_as_its_closed_form")),
    "epm.driver[Teleop].udp.host": (
        "read only with operator: udp (above)",
        ("test_teleop.py::test_teleop_over_udp_moves_the_epm_and_a_lost_link_holds_it",)),
}
# The run's outputs: files outside the run's folder, servers and network topics, which a
# scenario the tests simulate in-process must not open; each is exercised by the tests that
# run them.
_LIVE = ("test_live_outputs.py::test_a_foxglove_client_decodes_every_channel_of_a_running_simulation",
         "test_live_outputs.py::test_ros2_topics_reach_cyclone_dds_and_a_goal_moves_the_epm_held_at_the_clearance",
         "test_live_outputs.py::test_the_output_flags_are_spellings_of_the_scenarios_outputs")
EXCEPTIONS.update({
    "outputs.recording": ("the Meshcat replay: the CLI's --no-recording", _LIVE[1:]),
    "outputs.mcap": ("a file the run writes where it is told, outside its folder",
                     ("test_mcap.py::test_messages_have_the_right_sizes_and_times",)),
    "outputs.mcap.path": ("as outputs.mcap", _LIVE[2:]),
    "outputs.mcap.compression": ("as outputs.mcap", _LIVE[2:]),
    "outputs.meshcat": ("a live page, served until Ctrl-C", _LIVE[2:]),
    "outputs.meshcat.host": ("as outputs.meshcat", _LIVE[2:]),
    "outputs.foxglove": ("a WebSocket server", _LIVE[:1]),
    "outputs.foxglove.host": ("as outputs.foxglove", _LIVE[:1]),
    "outputs.ros2": ("DDS topics on the network", _LIVE[1:2]),
    "outputs.ros2.loopback": ("as outputs.ros2", _LIVE[1:2]),
    "outputs.ros2.epm_command": ("as outputs.ros2, with epm.driver[External]", _LIVE[1:2]),
})


def _alternatives(hint):
    """(the dataclass types a field may hold, whether it may be null)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        return [a for a in args if dataclasses.is_dataclass(a)], type(None) in args
    return ([hint] if dataclasses.is_dataclass(hint) else []), False


def _same(a, b) -> bool:
    fields = getattr(type(a), "__fields__", None)  # Drake's configs: no __eq__
    if fields is not None and type(a) is type(b):
        return all(getattr(a, f.name) == getattr(b, f.name) for f in fields)
    return a == b


def _member(path: str, cls) -> str:
    return f"{path}[{cls.__name__}]"


def _selectors(cls, path: str = "") -> list[str]:
    """The paths of every selector of the dataclass type `cls`: each leaf that is not a
    plain number (int, float), each field that may be null, and each member of a tagged
    union, through nested dataclasses, optional blocks and every union member."""
    hints = typing.get_type_hints(cls)
    out = []
    for item in dataclasses.fields(cls):
        where = f"{path}.{item.name}" if path else item.name
        hint = hints[item.name]
        classes, nullable = _alternatives(hint)
        if nullable:
            out.append(where)  # a block that is there or not, or a value given or derived
        if len(classes) > 1:
            for member in classes:
                out.append(_member(where, member))
                out += _selectors(member, _member(where, member))
        elif classes:
            out += _selectors(classes[0], where)
        elif not nullable and hint not in (int, float):
            out.append(where)
    return out


def _set_paths(value, default, path: str = "") -> set[str]:
    """The paths at which `value` (a dataclass) is away from `default`: leaves with another
    value, null fields given, the union members it holds, and what is set beneath them
    (compared with the default's, or with the member's or block's own defaults)."""
    hints = typing.get_type_hints(type(value))
    out = set()
    for item in dataclasses.fields(value):
        v, d = getattr(value, item.name), getattr(default, item.name)
        where = f"{path}.{item.name}" if path else item.name
        classes, nullable = _alternatives(hints[item.name])
        if nullable and (v is None) != (d is None):
            out.add(where)
        if not classes:  # a leaf
            if not _same(v, d):
                out.add(where)
            continue
        if v is None:  # an absent block: nothing beneath it is set
            continue
        if len(classes) > 1:
            where = _member(where, type(v))
            out.add(where)
        out |= _set_paths(v, d if type(d) is type(v) else type(v)(), where)
    return out


def _uncovered(schema, scenarios) -> list[str]:
    """The selectors of `schema` that none of `scenarios` sets, less the listed ones."""
    covered = set().union(*(_set_paths(s, schema()) for s in scenarios))
    return sorted(set(_selectors(schema)) - covered - set(EXCEPTIONS) - set(ELSEWHERE))


def _test_exists(named: str) -> bool:
    file, name = named.split("::")
    return f"\ndef {name}(" in (TESTS_DIR / file).read_text()


def test_the_reflection_finds_every_selector():
    selectors = _selectors(Scenario)
    assert len(selectors) == len(set(selectors))
    assert {"plant", "simulator", "colon.source[ExVivo]", "colon.source[Imported].path",
            "colon.rectum.has_taeniae",
            "colon.rectal_valve_positions", "capsule.imu", "capsule.camera.lens.fx",
            "capsule.camera.render_process", "epm.mount[Stage]", "epm.mount[Arm]",
            "epm.mount[Arm].posture_deg", "epm.driver[External]",
            "epm.driver[Teleop].mapping.mode"} <= set(selectors)
    assert not {"duration", "random_seed", "capsule.imu.sample_rate",
                "epm.driver[AlongColon].speed", "epm.mount[Stage].translation_gains.p",
                "epm.driver[Teleop].channel.forward.seed"} & set(selectors)
    # A default scenario sets nothing; it holds the unions' default members.
    assert _set_paths(Scenario(), Scenario()) == {"epm.mount[Stage]", "epm.driver[AlongColon]",
                                                  "colon.source[Procedural]",
                                                  "contact[RigidWall]"}
    # A selector added to the scenario and set by neither scenario fails the rule; a
    # number does not.
    extended = dataclasses.make_dataclass("Extended", [
        ("new_switch", bool, dataclasses.field(default=False)),
        ("new_block", AlongColon | None, dataclasses.field(default=None)),
        ("new_gain", float, dataclasses.field(default=1.0))], bases=(Scenario,))
    scenarios = [extended(**{f.name: getattr(s, f.name) for f in dataclasses.fields(s)})
                 for s in (load_scenario(name="OneOfEverything"),
                           load_scenario(name="OneOfEverythingElse"))]
    assert _uncovered(extended, scenarios) == ["new_block", "new_switch"]
    scenarios[1].new_switch = True
    scenarios[0].new_block = AlongColon()
    assert _uncovered(extended, scenarios) == []


def test_one_of_everything_and_else_set_every_selector():
    """The rule: every field of the scenario that *selects behaviour* -- a bool, a str, a
    list, a field that may be null (`X | None`: an optional block, or a value given instead
    of derived), each member of a tagged union (epm.mount: !Stage | !Arm; epm.driver:
    !AlongColon | !HoldAbove | !Teleop | !LumenFollower | !External | !Plugin), and any field
    of another type (Drake's plant and simulator configs) -- is set away from its default (a
    null field: given; a member: held) in OneOfEverything or in OneOfEverythingElse
    (diagrams/default.yaml), which the tests simulate (test_station.py). The second holds
    the options that exclude the first's. Numbers (int, float fields) are exempt: they
    change values, not wiring. The only other ways out: ELSEWHERE (a driver member held by
    another named scenario the tests simulate) and EXCEPTIONS (what no simulated scenario
    can set, each with its reason and the tests that exercise it)."""
    one = load_scenario(name="OneOfEverything")
    other = load_scenario(name="OneOfEverythingElse")
    # One driver and one mount each: the chosen pairs.
    assert isinstance(one.epm.driver, AlongColon) and isinstance(one.epm.mount, Stage)
    assert isinstance(other.epm.driver, Teleop) and isinstance(other.epm.mount, Arm)
    selectors = set(_selectors(Scenario))
    listed = set(EXCEPTIONS) | set(ELSEWHERE)
    assert not set(EXCEPTIONS) & set(ELSEWHERE)
    assert listed <= selectors, f"not selectors (any more): {sorted(listed - selectors)}"
    missing = _uncovered(Scenario, [one, other])
    assert not missing, ("set these in OneOfEverything or OneOfEverythingElse "
                         f"(diagrams/default.yaml): {missing}")
    covered = _set_paths(one, Scenario()) | _set_paths(other, Scenario())
    assert not listed & covered, f"now set, drop from the lists: {sorted(listed & covered)}"


def test_the_listed_selectors_are_exercised_where_they_say():
    for path, (name, test) in ELSEWHERE.items():
        assert path in _set_paths(load_scenario(name=name), Scenario()), (path, name)
        assert _test_exists(test), test
        assert f'"{name}"' in (TESTS_DIR / test.split("::")[0]).read_text(), (name, test)
    assert isinstance(load_scenario(name="FarMagnet").epm.driver, HoldAbove)
    for name in ("Navigation", "NavigationDetected"):
        assert isinstance(load_scenario(name=name).epm.driver, LumenFollower), name
    for path, (reason, tests) in EXCEPTIONS.items():
        assert reason and all(_test_exists(test) for test in tests), (path, tests)
