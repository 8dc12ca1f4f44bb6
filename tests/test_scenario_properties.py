"""Property-based tests of the scenario loader (hypothesis): whatever text or value a user
gives, loading ends in a scenario or in one line naming what is wrong (ScenarioError),
never in a traceback; a valid scenario round-trips through its dump; a key given twice at
any depth, and a number out of its range, are refused naming it.

Each property runs a few dozen examples (a load of a one-scenario file takes ~3 ms), so the
module takes a few seconds; tests/test_scenario_bounds.py sweeps every field with fixed
values, tests/test_scenario_forms.py the YAML forms one by one."""

import json
import math
import re

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from capsule_drake.scenario import (DEFAULT_SCENARIO_FILE, ScenarioError, dump_scenario,
                                    load_scenario, scenario_names)
from test_scenario_bounds import LEAVES, _names_the_key, _yaml, base_files  # noqa: F401

QUICK = settings(max_examples=40, deadline=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture,
                                        HealthCheck.too_slow])




def _outcome(path, text):
    """The scenario `text` laid over `path` loads to, or the ScenarioError's message, which
    must be one line; anything else (another exception: a defect) fails the test."""
    try:
        return load_scenario(path, override=text)
    except ScenarioError as e:
        message = str(e)
        assert message.strip() and "\n" not in message and "Traceback" not in message, message
        return message


def _field(scenario, leaf):
    """The value of `leaf` in `scenario` (a union member's field: None if another member
    holds the field)."""
    value = scenario
    for name, tag in leaf.steps:
        value = getattr(value, name)
        if tag is not None and type(value).__name__ != tag:
            return None
    return value


# --- Anything at all ----------------------------------------------------------------------

KEYS = sorted({name for leaf in LEAVES for name, _ in leaf.steps})
TAGS = sorted({tag for leaf in LEAVES for _, tag in leaf.steps if tag}) + ["Nope"]
PIECES = st.one_of(
    st.sampled_from(KEYS),
    st.sampled_from(["{", "}", "[", "]", ": ", ":", ", ", ",", "\n", "\n  ", "  ", "- ", "? ",
                     "&a ", "*a", "<<: ", "'", '"', "#", "~", "null", "true", "yes", "off",
                     "0x1F", "010", "08", "1_000", "1:30", ".inf", "-.nan", "1e400", "1e3",
                     "-0", "5.", ".5", "\u0663", "\uff15", "|\n", ">\n", "%YAML 1.2\n",
                     "---\n", "...\n", "\t", "\\", "9" * 30, "\ufeff", "\x85", "\udcff"]),
    st.sampled_from(TAGS).map(lambda tag: f"!{tag} "),
    st.text(max_size=4))


@QUICK
@given(st.lists(PIECES, max_size=40).map("".join))
@example("{duration: \udcff}")   # an argument that is not UTF-8 (Python's surrogateescape)
@example("\x85")                 # a YAML 1.1 line break: an empty document
@example("# nothing but a comment")
def test_any_override_text_loads_or_is_one_line(base_files, text):
    outcome = _outcome(base_files["WithSensors"], text)
    if not isinstance(outcome, str):
        assert math.isfinite(outcome.duration)


def _scalar_text(value) -> str:
    """`value` (None, a bool, an int, a float, text, a list or a dict of them) as YAML."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return _yaml(value)
    if isinstance(value, str):
        return json.dumps(value)   # a double-quoted YAML scalar
    if isinstance(value, list):
        return "[" + ", ".join(_scalar_text(v) for v in value) + "]"
    return "{" + ", ".join(f"{json.dumps(k)}: {_scalar_text(v)}" for k, v in value.items()) + "}"


# Text of any character YAML can escape in double quotes (json.dumps writes \uXXXX; the
# characters beyond it would be written as surrogate pairs, which YAML does not take).
TEXT = st.text(st.characters(max_codepoint=0xFFFF, exclude_categories=["Cs"]), max_size=6)
PLAIN = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | TEXT,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(TEXT, inner, max_size=2),
    max_leaves=5).map(_scalar_text)
RAW = st.sampled_from(["0x10", "010", "0b1", "1:30", "1_0", "yes", "On", "'5'", '"0.5"',
                       "\u0663", "\uff15.\uff15", "inf", "1e3", "+5", ".5", "5.", "2001-01-01",
                       "!HoldAbove {}", "*nothing", "&a 1", "[1, [2]]", "{}", "''", "~"])


@QUICK
@given(st.sampled_from(LEAVES), PLAIN | RAW)
def test_any_value_in_any_field_loads_or_is_one_line_naming_it(base_files, leaf, value):
    outcome = _outcome(base_files[leaf.base()], leaf.override(value))
    if isinstance(outcome, str):
        if "alias" not in outcome:  # *nothing: an alias of no anchor, a syntax error
            assert _names_the_key(outcome, leaf), (leaf.key, value, outcome)
    else:
        read = _field(outcome, leaf)
        numbers = read if isinstance(read, list) else [read]
        assert all(not isinstance(v, float) or math.isfinite(v) for v in numbers), read


# --- What loads comes back the same --------------------------------------------------------

@settings(QUICK, max_examples=8)   # ~0.1 s each: the named scenarios load from the whole file
@given(st.sampled_from(scenario_names(DEFAULT_SCENARIO_FILE)),
       st.floats(0.0, 1e4), st.integers(0, 2 ** 32 - 1), st.integers(0, 2 ** 32 - 1))
def test_a_valid_scenario_round_trips_through_its_dump(tmp_path_factory, name, duration,
                                                       seed, colon_seed):
    # The values are written as Python writes them (repr: 1e-05, 1234.5678), and read back
    # exactly; the dump (scenario.yaml of a run) loads to the same scenario.
    text = f"{{duration: {duration!r}, random_seed: {seed}, colon: {{seed: {colon_seed}}}}}"
    scenario = load_scenario(name=name, override=text)
    assert (scenario.duration, scenario.random_seed, scenario.colon.seed) == (
        duration, seed, colon_seed)
    path = tmp_path_factory.mktemp("dump") / "dumped.yaml"
    path.write_text("Dumped:\n" + "".join(f"  {line}\n"
                                          for line in dump_scenario(scenario).splitlines()))
    assert dump_scenario(load_scenario(path)) == dump_scenario(scenario)
    # As the run writes it (its fields at the top, no name), it loads as it is.
    bare = path.with_name("scenario.yaml")
    bare.write_text(dump_scenario(scenario))
    assert dump_scenario(load_scenario(bare)) == dump_scenario(scenario)


# --- A key given twice, at any depth -------------------------------------------------------

def _nested(leaf, twice: int, block: bool) -> tuple[str, int]:
    """The YAML setting `leaf` to its default, with the key at depth `twice` given twice
    (the same value both times), in flow style or block style; and the line of the second."""
    value = _yaml(leaf.default)
    steps = leaf.steps
    if not block:
        text = value
        for depth in range(len(steps) - 1, -1, -1):
            key, tag = steps[depth]
            item = f"{key}: {'!' + tag + ' ' if tag else ''}{text}"
            text = "{" + (f"{item}, {item}" if depth == twice else item) + "}"
        return text, 1

    def lines(depth: int) -> list[str]:
        key, tag = steps[depth]
        if depth == len(steps) - 1:
            return [f"{key}: {value}"]
        inner = ["  " + line for line in lines(depth + 1)]
        return [f"{key}:{' !' + tag if tag else ''}"] + inner

    def written(depth: int) -> list[str]:
        own = lines(depth)
        if depth == twice:
            return own + own
        key, tag = steps[depth]
        return [f"{key}:{' !' + tag if tag else ''}"] + ["  " + line
                                                         for line in written(depth + 1)]

    text_lines = written(0)
    second = len(text_lines) - len(lines(twice)) + 1
    return "\n".join(text_lines) + "\n", second


@QUICK
@given(st.sampled_from(LEAVES), st.data(), st.booleans())
def test_a_key_given_twice_at_any_depth_is_refused_naming_it(base_files, leaf, data, block):
    twice = data.draw(st.integers(0, len(leaf.steps) - 1), label="depth")
    text, line = _nested(leaf, twice, block)
    where = ".".join(name for name, _ in leaf.steps[:twice + 1])
    outcome = _outcome(base_files[leaf.base()], text)
    assert isinstance(outcome, str), text
    assert outcome.startswith(f"override:{line}: {where}: given twice"), (text, outcome)


# --- Numbers out of range -----------------------------------------------------------------

@QUICK
@given(st.sampled_from(LEAVES), st.sampled_from([math.nan, math.inf, -math.inf]))
def test_a_number_that_is_not_finite_is_refused_naming_its_field(base_files, leaf, value):
    value = value if leaf.kind is float else {math.inf: 2 ** 64}.get(value, -2 ** 64)
    outcome = _outcome(base_files[leaf.base()], leaf.override(value))
    assert isinstance(outcome, str), (leaf.key, value)
    assert _names_the_key(outcome, leaf), (leaf.key, outcome)


OUT_OF_RANGE = {  # field: values outside its stated range
    "duration": st.floats(1e6, 1e300, exclude_min=True) | st.floats(-1e300, 0.0,
                                                                    exclude_max=True),
    "random_seed": st.integers(2 ** 32, 2 ** 63) | st.integers(-2 ** 63, -1),
    "colon.seed": st.integers(2 ** 32, 2 ** 63) | st.integers(-2 ** 63, -1),
    "epm.clearance": st.floats(0.5, 1e300, exclude_min=True) | st.floats(-1e300, 0.0,
                                                                         exclude_max=True),
    "outputs.log_period": st.floats(0.0, 1e-4, exclude_max=True),
    "capsule.ipm.remanence": st.floats(-1e300, 0.0),
}


@QUICK
@given(st.sampled_from(sorted(OUT_OF_RANGE)).flatmap(
    lambda key: st.tuples(st.just(key), OUT_OF_RANGE[key])))
def test_a_number_out_of_its_range_is_refused_naming_its_field(base_files, key_value):
    key, value = key_value
    leaf = next(leaf for leaf in LEAVES if leaf.key == key)
    outcome = _outcome(base_files[leaf.base()], leaf.override(value))
    assert isinstance(outcome, str), (key, value)
    assert key in outcome, outcome


# --- Number forms --------------------------------------------------------------------------

FORMS = {"hexadecimal": hex, "octal": lambda n: "0" + format(n, "o"),
         "binary": bin, "digit separators": lambda n: f"{n:_}",
         "base 60": lambda n: f"{n // 60}:{n % 60:02d}"}


@QUICK
@given(st.sampled_from([leaf for leaf in LEAVES if leaf.kind is int]),
       st.integers(1000, 10 ** 6), st.sampled_from(sorted(FORMS)))
def test_an_integer_is_read_in_decimal_and_refused_in_yaml_11s_other_forms(base_files, leaf, n,
                                                                          form):
    written = FORMS[form](n)
    outcome = _outcome(base_files[leaf.base()], leaf.override(written))
    assert isinstance(outcome, str), (leaf.key, written)
    assert re.search(rf"{re.escape(leaf.key.rsplit('.', 1)[-1])}: {re.escape(written)} reads "
                     rf"as .*{n}", outcome), outcome
    plain = _outcome(base_files[leaf.base()], leaf.override(str(n)))
    if not isinstance(plain, str):  # in its range: read as written
        assert _field(plain, leaf) == n
    else:
        assert "reads as" not in plain and _names_the_key(plain, leaf), plain


@QUICK
@given(st.characters(categories=["Nd"]).filter(lambda c: not "0" <= c <= "9"),
       st.sampled_from([leaf for leaf in LEAVES if leaf.kind is float]))
def test_digits_other_than_0_to_9_are_refused_naming_the_field(base_files, digit, leaf):
    outcome = _outcome(base_files[leaf.base()], leaf.override(f"{digit}.{digit}"))
    assert isinstance(outcome, str) and "digits 0-9" in outcome, (leaf.key, digit, outcome)
    assert _names_the_key(outcome, leaf), outcome
