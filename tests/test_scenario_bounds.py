"""Bad values and bad files cost one line, never a traceback, a hang or a huge allocation.

The sweep walks every number of the Scenario dataclass tree (nested blocks, optional blocks,
every member of a tagged union, Drake's embedded configs), sets it to NaN, the infinities,
zero, a negative, a tiny and a huge value, and loads the scenario: each value is either
refused with one line naming the key (a ScenarioError) or accepted. The slow test builds and
simulates briefly what is accepted.
"""

import dataclasses
import math
import os
import re
import subprocess
import sys
import types
import typing

import pytest

from capsule_drake.scenario import DEFAULT_SCENARIO_FILE, Scenario, ScenarioError, load_scenario
from capsule_drake.schema import MAX_DEPTH, MAX_NODES

# The named scenario of diagrams/default.yaml a key is set in, by its path's beginning: a
# union member's fields need that member (and what it needs of the rest: a camera for the
# teleoperated and autonomous drivers); the optional blocks (sensors, camera, tracker,
# pseudo-force) are all present in WithSensors, the localisation's in NavigationSensors.
BASES = (("epm.driver[Teleop]", "Teleop"), ("epm.driver[LumenFollower]", "Navigation"),
         ("epm.driver[HoldAbove]", "FarMagnet"), ("epm.mount[Arm]", "WithArm"),
         ("capsule.magnetic_array", "NavigationSensors"),
         ("capsule.localizer", "NavigationSensors"), ("", "WithSensors"))

FLOATS = (math.nan, math.inf, -math.inf, 0.0, -1.0, 1e-9, 1e9)
INTS = (-1, 0, 2 ** 32, 2 ** 62)


@dataclasses.dataclass
class Leaf:
    """A number of the scenario: its dotted key (a union member as `field[Member]`), its
    type, the YAML path to it (mapping keys, each with the `!Tag` of its value if any) and
    its default (of a list, the first entry is the one set)."""

    key: str
    kind: type
    steps: list
    default: object

    def base(self) -> str:
        return next(name for prefix, name in BASES if self.key.startswith(prefix))

    def override(self, value) -> str:
        """The YAML text that sets this number to `value`."""
        if isinstance(self.default, list):
            value = [value] + list(self.default[1:])
        text = _yaml(value)
        for key, tag in reversed(self.steps):
            text = f"{{{key}: {'!' + tag + ' ' if tag else ''}{text}}}"
        return text


def _yaml(value) -> str:
    if isinstance(value, list):
        return "[" + ", ".join(_yaml(v) for v in value) + "]"
    if isinstance(value, float):
        if math.isnan(value):
            return ".nan"
        if math.isinf(value):
            return ".inf" if value > 0 else "-.inf"
        return repr(value)
    return str(value)


def _options(hint):
    """(the types a field may hold but None, whether they are a union of several)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(hint) if a is not type(None)]
        return options, len(options) > 1
    return [hint], False


def leaves(cls=Scenario, key: str = "", steps=(), default=None) -> list[Leaf]:
    """Every number (int, float, list of floats) beneath the dataclass type `cls`."""
    default = default if default is not None else cls()
    drake = getattr(cls, "__fields__", None)
    if drake is not None:  # Drake's configs (plant, simulator): fields, no dataclass
        items = [(f.name, f.type, getattr(default, f.name)) for f in drake]
    else:
        hints = typing.get_type_hints(cls)
        items = [(f.name, hints[f.name], getattr(default, f.name))
                 for f in dataclasses.fields(cls)]
    out = []
    for name, hint, value in items:
        where = f"{key}.{name}" if key else name
        options, tagged = _options(hint)
        for option in options:
            if dataclasses.is_dataclass(option) or hasattr(option, "__fields__"):
                member = f"{where}[{option.__name__}]" if tagged else where
                own = value if isinstance(value, option) else option()
                out += leaves(option, member,
                              (*steps, (name, option.__name__ if tagged else None)), own)
            elif option in (int, float):
                out.append(Leaf(where, option, [*steps, (name, None)], value))
            elif (typing.get_origin(option) is list and typing.get_args(option) == (float,)
                  and value):
                out.append(Leaf(where, float, [*steps, (name, None)], list(value)))
    return out


LEAVES = leaves()


@pytest.fixture(scope="module")
def base_files(tmp_path_factory):
    """Each base scenario alone in a file of its own (its text cut from default.yaml), so
    that a load parses a few lines rather than the whole file."""
    text = DEFAULT_SCENARIO_FILE.read_text()
    folder = tmp_path_factory.mktemp("bases")
    files = {}
    for _, name in BASES:
        block = re.search(rf"^{name}:.*?(?=^\S|\Z)", text, re.S | re.M).group(0)
        files[name] = folder / f"{name}.yaml"
        files[name].write_text(block)
    return files


def _load(base_files, leaf: Leaf, value):
    """The outcome of setting `leaf` to `value`: None if accepted, else the message."""
    try:
        load_scenario(base_files[leaf.base()], override=leaf.override(value))
    except ScenarioError as e:
        return str(e)
    return None


def _names_the_key(message: str, leaf: Leaf) -> bool:
    """The message names the field: its name, as a key or in words (`max_crumbs` or
    `max crumbs`), or, for a field checked with its neighbours, the block."""
    name = leaf.key.rsplit(".", 1)[-1]
    return name in message or name.replace("_", " ") in message


def test_the_sweep_walks_every_block():
    keys = [leaf.key for leaf in LEAVES]
    assert len(keys) == len(set(keys)) > 300
    for key in ("colon.rectum.diameter", "capsule.ipm.dimensions", "capsule.camera.lens.width",
                "epm.driver[Teleop].channel.forward.delay", "epm.mount[Arm].base_xyz",
                "epm.driver[LumenFollower].control.max_crumbs", "plant.time_step",
                "simulator.accuracy", "outputs.log_period", "random_seed", "duration"):
        assert key in keys


def _sweep(base_files, values_of):
    """(leaf, value, outcome) of every leaf set to each of `values_of(leaf)`; fails at the
    first outcome that is neither a one-line ScenarioError naming the field nor an
    acceptance (any other exception propagates), and on any NaN, infinity or 2^62 that is
    accepted."""
    results = []
    for leaf in LEAVES:
        for value in values_of(leaf):
            outcome = _load(base_files, leaf, value)
            where = f"{leaf.key} = {value!r}"
            if outcome is None:
                assert not (isinstance(value, float) and not math.isfinite(value)), where
                assert value != 2 ** 62, where
            else:
                assert "\n" not in outcome and "Traceback" not in outcome, (where, outcome)
                assert _names_the_key(outcome, leaf), (where, outcome)
            results.append((leaf, value, outcome))
    return results


@pytest.mark.slow  # ~16 s: all 321 numeric fields, each with seven values
def test_every_number_set_to_nonsense_is_refused_in_one_line_or_accepted(base_files):
    results = _sweep(base_files, lambda leaf: FLOATS if leaf.kind is float else INTS)
    refused = sum(outcome is not None for *_, outcome in results)
    assert refused > 0.7 * len(results)


def _override_many(settings) -> str:
    """The YAML text that sets each (leaf, value) of `settings` at once."""
    tree = {}
    for leaf, value in settings:
        node = tree
        for key, tag in leaf.steps[:-1]:
            node = node.setdefault((key, tag), {})
        if isinstance(leaf.default, list):
            value = [value] + list(leaf.default[1:])
        node[leaf.steps[-1]] = _yaml(value)

    def emit(node) -> str:
        items = []
        for (key, tag), child in node.items():
            text = emit(child) if isinstance(child, dict) else child
            items.append(f"{key}: {'!' + tag + ' ' if tag else ''}{text}")
        return "{" + ", ".join(items) + "}"

    return emit(tree)


# Left to the plant's time-step bound (its own check): a 1 ns step is 10 million steps in
# the 0.01 s run. The duration is the run's own.
NOT_RUN = ("plant.time_step", "duration")


@pytest.mark.slow
@pytest.mark.extended  # ~4 minutes: `./run-tests -m extended` when bounds change
def test_what_the_sweep_accepts_builds_and_runs(base_files):
    """The extreme values the sweep accepts (1e9, 1e-9, 2^32) build a station and simulate
    0.01 s without an error. Each block's accepted values are set together (~60 runs, ~4
    minutes; one run per value took ~30 minutes for the ~550 values accepted before the
    bounds); a set the checks refuse together is split until each part loads. Not in the
    default run (the suite's 15-minute budget): run it with `./run-tests -m extended`."""
    from capsule_drake.app.run import simulate

    results = _sweep(base_files, lambda leaf: FLOATS if leaf.kind is float else INTS)
    groups = {}
    for leaf, value, outcome in results:
        if outcome is None and value in (1e9, 1e-9, 2 ** 32) and leaf.key not in NOT_RUN:
            block = (leaf.base(), leaf.key.rsplit(".", 1)[0], value)
            groups.setdefault(block, []).append((leaf, value))
    pending = list(groups.values())
    runs = 0
    while pending:
        settings = pending.pop()
        base = settings[0][0].base()
        try:
            scenario = load_scenario(base_files[base],
                                     override=[_override_many(settings), "{duration: 0.01}"])
        except ScenarioError:
            assert len(settings) > 1, settings  # each alone loads (the sweep said so)
            half = len(settings) // 2
            pending += [settings[:half], settings[half:]]
            continue
        try:
            result = simulate(scenario, out_dir=None, progress=False)
        except ScenarioError as e:  # what only the colon's geometry tells (one line)
            assert "\n" not in str(e), str(e)
            continue
        runs += 1
        assert result.status in ("completed", "diverged", "left_colon", "perforated"), (
            [(leaf.key, value) for leaf, value in settings], result.metrics)
    assert runs >= 0.9 * len(groups)


# --- Named cases from the bug report, with their messages ---------------------------------

@pytest.mark.parametrize("override, message", [
    ("{epm: {magnet: {dimensions: [.nan, 0.1]}}}",
     "scenario: epm.magnet.dimensions must be in [0.0001, 0.5] m, got [nan, 0.1]"),
    ("{colon: {rectum: {diameter: 10}}}", "scenario: colon.rectum.diameter must be in [0.02, "
     "0.06] m (a distended rectum is taken as ~4 cm across"),
    ("{colon: {transverse: {diameter: .inf}}}",
     "scenario: colon.transverse.diameter must be in [0.02, 0.06] m"),
    ("{epm: {clearance: 1e6}}", "scenario: epm.clearance must be in [0, 0.5] m"),
    ("{random_seed: -1}", "scenario: random_seed must be in [0, 4294967295]"),
    ("{random_seed: 4294967296}", "scenario: random_seed must be in [0, 4294967295]"),
    ("{colon: {seed: -5}}", "scenario: colon.seed must be in [0, 4294967295]"),
    ("{outputs: {visual_period: 0}}", "scenario: outputs.visual_period must be finite and >= "),
    ("{outputs: {log_period: 1e-7}}", "scenario: outputs.log_period must be finite and >= "
     "0.0001 s (10 kHz"),
    ("{duration: 1e5}", "scenario: duration / outputs.log_period must be at most 2,000,000"),
    ("{duration: .nan}", "scenario: duration must be in [0, 1000000] s"),
    ("{duration: .inf}", "scenario: duration must be in [0, 1000000] s"),
    ("{duration: 2e6, outputs: {log_period: 1.0}}", "scenario: duration must be in [0, 1000000]"),
    ("{epm: {magnet: {remanence: -1.48}}}", "scenario: epm.magnet.remanence must be in [0.1, 1.6] T"),
    ("{epm: {magnet: {remanence: 0}}}", "scenario: epm.magnet.remanence must be in [0.1, 1.6] T"),
    ("{capsule: {ipm: {remanence: 0}}}", "scenario: capsule.ipm.remanence must be in [0.1, 1.6] T"),
    ("{capsule: {ipm: {dimensions: [0.02, 0.01]}}}", "scenario: capsule.ipm must fit in the "
     "capsule"),
    ("{contact: {friction: .inf}}", "scenario: contact.friction must be in [0, 2]"),  # Drake
    ("{colon: {taenia_angle: .nan}}", "scenario: colon.taenia_angle must be finite, got nan"),
    ("{contact: {friction: 5}}", "scenario: contact.friction must be in [0, 2]"),
    ("{capsule: {camera: {lens: {width: 100000}}}}",
     "scenario: capsule.camera: lens.width must be in [16, 4096] px"),
    ("{capsule: {camera: {lens: {width: 4096, height: 4096}}}}",
     "scenario: capsule.camera: lens.width x lens.height must be at most"),
    ("{capsule: {camera: {face_resolution_scale: 4, lens: {width: 2048, height: 2048}}}}",
     "scenario: capsule.camera: lens (width, height, fov_deg, fx, fy, distortion) and "
     "face_resolution_scale need render faces of"),
    ("{plant: {stiction_tolerance: 0}}", "scenario: plant.stiction_tolerance must be finite "
     "and > 0"),
    ("{simulator: {start_time: 5}}", "scenario: simulator.start_time must be 0"),
    ("{capsule: {start_s: 0}}", "scenario: capsule.start_s must be finite and >= 0.01575 m"),
    ("{epm: {driver: !AlongColon {speed: 1e-9}}}",  # once asked for 211 GiB of samples
     "scenario: epm.driver.speed must be in [0.001, 1] m/s"),
    ("{epm: {driver: !AlongColon {settle_time: 1e9}}}",
     "scenario: epm.driver.settle_time must be in [0, 1000] s"),
    ("{epm: {mount: !Arm {limit_margin_deg: 200}}}",  # Drake asserted
     "scenario: epm.mount.limit_margin_deg must be in [0, 30] deg"),
    ("{simulator: {integration_scheme: leapfrog}}", "scenario: simulator: Unknown integration "
     "scheme: leapfrog"),
])
def test_reported_values_are_refused_naming_the_key(override, message):
    with pytest.raises(ScenarioError) as info:
        load_scenario(override=override)
    assert str(info.value).startswith(message), str(info.value)


@pytest.mark.parametrize("override, message", [
    ("{epm: {driver: !Teleop {channel: {forward: {delay: 1e9}}}}}",
     "scenario: epm.driver (Teleop): channel.forward.delay 1000000000.0 + 8 x jitter 0.0 "
     "must be at most 2 s"),
    ("{epm: {driver: !Teleop {channel: {backward: {jitter: 0.3}}}}}",
     "scenario: epm.driver (Teleop): channel.backward.delay 0.0 + 8 x jitter 0.3 "),
    ("{epm: {driver: !Teleop {operator: udp, udp: {host: no.such.host.invalid}}}}",
     "scenario: epm.driver (Teleop): udp bridge host 'no.such.host.invalid' does not resolve"),
    ("{epm: {driver: !Teleop {operator: udp, udp: {host: 'a b'}}}}",
     "scenario: epm.driver (Teleop): udp bridge host 'a b' must be a host name or address"),
])
def test_teleop_values_are_refused_naming_the_key(override, message):
    with pytest.raises(ScenarioError) as info:
        load_scenario(name="Teleop", override=override)
    assert str(info.value).startswith(message), str(info.value)


@pytest.mark.slow  # the course search fails after 40 attempts: ~10-30 s
def test_an_anatomy_the_course_cannot_hold_is_refused_at_load():
    # Each diameter within its range, all of them near the top together: no course fits.
    wide = ("{colon: {rectum: {diameter: 0.06}, sigmoid: {diameter: 0.045}, descending: "
            "{diameter: 0.045}, transverse: {diameter: 0.06}, ascending: {diameter: 0.06}, "
            "cecum: {diameter: 0.09}}}")
    with pytest.raises(ScenarioError, match=r"^scenario: colon: the procedural course \(fixed "
                       r"landmarks\) has no room for these segments with colon.seed 0"):
        load_scenario(override=wide)


# --- Files -----------------------------------------------------------------------------------

def test_a_device_a_directory_and_a_pipe_are_not_read(tmp_path):
    with pytest.raises(ScenarioError) as info:
        load_scenario("/dev/zero")
    assert str(info.value) == "/dev/zero: not a regular file (a device)"
    with pytest.raises(ScenarioError) as info:
        load_scenario(tmp_path)
    assert str(info.value) == f"{tmp_path}: not a regular file (a directory)"
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)  # opening it would block until a writer comes
    with pytest.raises(ScenarioError) as info:
        load_scenario(fifo)
    assert str(info.value) == f"{fifo}: not a regular file (a pipe)"


def test_a_large_file_is_not_read(tmp_path):
    path = tmp_path / "big.yaml"
    path.write_text("A: {}\n" + "# padding\n" * 230_000)
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert str(info.value) == f"{path}: 2.3 MB, larger than the 1 MB a scenario file may be"
    with pytest.raises(ScenarioError, match=r"^override: 1.1 MB, larger than the 1 MB"):
        load_scenario(override="{duration: 1}" + " " * 1_100_000)


@pytest.mark.parametrize("data, at", [
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", 0),  # a PNG's first bytes: not UTF-8 at byte 0
    (bytes(range(256)) * 4, 0),                    # binary: NUL at byte 0
    (b"A:\n  duration: 1.0\x00\x01\n", 18),        # text with a NUL in it
    ("A: {}  # caf\u00e9\n".encode() + b"\xff\xfe", 15),  # UTF-8, then not
])
def test_binary_files_are_not_text(tmp_path, data, at):
    path = tmp_path / "s.yaml"
    path.write_bytes(data)
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert str(info.value) == f"{path}: not text (binary data at byte {at})"


def _laughs(levels: int) -> str:
    """The "billion laughs": each level a list of ten aliases of the one before."""
    lines = ["a0: &a0 [lol, lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]")
    return "A: {}\n" + "\n".join(lines) + "\n"


def test_an_alias_bomb_is_refused_before_it_expands(tmp_path):
    path = tmp_path / "bomb.yaml"
    path.write_text(_laughs(9))  # ~700 bytes, 10^9 strings once expanded
    assert path.stat().st_size < 800
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert str(info.value) == (f"{path}:6: the document expands (through its aliases) to "
                               f"more than {MAX_NODES:,} nodes")
    with pytest.raises(ScenarioError, match=r"^override:\d+: the document expands"):
        load_scenario(override="{" + _laughs(9).replace("\n", ", ")[:-2] + "}")
    # A few aliases are fine: a shared block used twice expands to little.
    path.write_text("A:\n  capsule: {imu: &imu {sample_rate: 200.0}, magnetometer: *imu}\n")
    assert load_scenario(path).capsule.magnetometer.sample_rate == 200.0


def test_a_recursive_alias_is_refused(tmp_path):
    path = tmp_path / "loop.yaml"
    path.write_text("A: {}\nB: &b [1, *b]\n")
    with pytest.raises(ScenarioError) as info:
        load_scenario(path, "A")
    assert str(info.value) == f"{path}:2: alias *b refers to a node that contains it"


@pytest.mark.parametrize("depth", [MAX_DEPTH + 1, 20_000])
def test_deep_nesting_is_refused(tmp_path, depth):
    path = tmp_path / "deep.yaml"
    path.write_text("A: {duration: " + "[" * depth + "]" * depth + "}\n")
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert str(info.value) == f"{path}:1: nested deeper than {MAX_DEPTH} levels"
    with pytest.raises(ScenarioError) as info:
        load_scenario(override="{x: " + "[" * depth + "]" * depth + "}")
    assert str(info.value) == f"override:1: nested deeper than {MAX_DEPTH} levels"


def test_scenario_names_must_be_text(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("1: {}\n")
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert str(info.value) == f"{path}: scenario names must be text, got 1"


@pytest.mark.parametrize("make, key", [
    (lambda tmp_path: "/dev/zero", "/dev/zero: not a regular file"),
    (lambda tmp_path: (tmp_path / "bomb.yaml").write_text(_laughs(9)) and tmp_path / "bomb.yaml",
     "the document expands"),
])
def test_cli_bad_files_cost_one_line(tmp_path, make, key):
    path = make(tmp_path)
    proc = subprocess.run([sys.executable, "-m", "capsule_drake.app.cli", "run", str(path),
                           "--out", str(tmp_path / "out")], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("capsule-sim: error: ") and key in lines[0], \
        proc.stderr
