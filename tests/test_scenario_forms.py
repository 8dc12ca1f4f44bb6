"""Scenario text read as it looks (docs/runs.md, "Bad inputs get one line"): a key given twice,
the number forms YAML 1.1 reads otherwise than a reader does (hexadecimal, octal, binary,
base 60, digit separators, leading zeros, yes/no/on/off), text where a number belongs
(quoted, or in digits other than 0-9) are refused with one line naming the field; the
forms a reader reads as numbers are read so."""

import math

import pytest

from capsule_drake.scenario import ScenarioError, load_scenario, scenario_names


def _refused(text: str, **kwargs) -> str:
    with pytest.raises(ScenarioError) as info:
        load_scenario(override=text, **kwargs)
    message = str(info.value)
    assert "\n" not in message and "Traceback" not in message
    return message


# (override text, the one line's beginning, what it goes on to say)
REFUSED = [
    # Keys given twice: the last one won, silently (a whole block of the first was lost).
    ("{duration: 1, duration: 2}", "override:1: duration: given twice", "also at line 1"),
    ("epm: {clearance: 0.03}\nepm: {magnet: {remanence: 1.4}}\n",
     "override:2: epm: given twice", "also at line 1"),
    ("{epm: {magnet: {remanence: 1.4,\n  remanence: 1.3}}}",
     "override:2: epm.magnet.remanence: given twice", "also at line 1"),
    ("{epm: {driver: !HoldAbove {height: 0.3, height: 0.5}}}",
     "override:1: epm.driver.height: given twice", ""),
    ("{colon: {lesions: {placed: [{s: 0.3, s: 0.4}]}}}",
     "override:1: colon.lesions.placed[0].s: given twice", ""),
    # YAML 1.1's number forms.
    ("{duration: 0x10}", "override:1: duration: 0x10 reads as the hexadecimal number 16",
     "write 16"),
    ("{random_seed: 0x10}", "override:1: random_seed: 0x10 reads as the hexadecimal number 16",
     ""),
    ("{duration: 010}", "override:1: duration: 010 reads as the octal number 8", "write 8"),
    ("{random_seed: 017}", "override:1: random_seed: 017 reads as the octal number 15", ""),
    ("{random_seed: 0b101}", "override:1: random_seed: 0b101 reads as the binary number 5", ""),
    ("{duration: 1:30}", "override:1: duration: 1:30 reads as the base-60 number 90", "write 90"),
    ("{random_seed: 1:30}", "override:1: random_seed: 1:30 reads as the base-60 number 90", ""),
    ("{duration: 1:30.5}", "override:1: duration: 1:30.5 reads as the base-60 number 90.5", ""),
    ("{duration: 1_000}", "override:1: duration: 1_000 reads as 1000", "write 1000"),
    ("{random_seed: 1_000}", "override:1: random_seed: 1_000 reads as 1000", ""),
    ("{duration: 1_0.5}", "override:1: duration: 1_0.5 reads as 10.5", ""),
    ("{epm: {magnet: {dimensions: [0x10, 0.1]}}}",
     "override:1: epm.magnet.dimensions[0]: 0x10 reads as the hexadecimal number 16", ""),
    ("{duration: 01.5}", "override:1: duration: 01.5", "leading zero"),
    ("{duration: 08}", "override: duration: expected a number, got '08'", "leading zero"),
    # yes/no/on/off: booleans in YAML 1.1, text in YAML 1.2.
    ("{magnet_force: {apply: yes}}", "override:1: magnet_force.apply: yes reads as true",
     "write true"),
    ("{magnet_force: {apply: off}}", "override:1: magnet_force.apply: off reads as false",
     "write false"),
    ("{magnet_force: {apply: On}}", "override:1: magnet_force.apply: On reads as true", ""),
    ("{magnet_force: {field_model: no}}",
     "override:1: magnet_force.field_model: no reads as false", "quote it ('no')"),
    ("{duration: yes}", "override:1: duration: yes reads as true", ""),
    ("{epm: {on: 1}}", "override:1: epm: the key on reads as true", "quote it"),
    # Text where a number belongs.
    ("{duration: '5'}", "override: duration: expected a number, got the text '5'", "quotes"),
    ('{epm: {clearance: "0.03"}}', "override: epm.clearance: expected a number, got the "
                                   "text '0.03'", "quotes"),
    ("{duration: ' 5 '}", "override: duration: expected a number, got the text ' 5 '", ""),
    ("{duration: \u0663}", "override: duration: expected a number, got '\u0663'", "digits 0-9"),
    ("{duration: \uff15}", "override: duration: expected a number, got '\uff15'", "digits 0-9"),
    ("{duration: \uff11.\uff15}", "override: duration: expected a number", "digits 0-9"),
    ("{random_seed: \u0663}", "override: random_seed: expected an integer, got '\u0663'",
     "digits 0-9"),
    ("{duration: inf}", "override: duration: expected a number, got 'inf'", ""),
    ("{duration: Infinity}", "override: duration: expected a number, got 'Infinity'", ""),
]


@pytest.mark.parametrize("text,start,then", REFUSED, ids=[r[0] for r in REFUSED])
def test_a_form_read_otherwise_than_it_looks_is_refused(text, start, then):
    message = _refused(text)
    assert message.startswith(start), message
    assert then in message, message


# (override text, the field, the value it must read as)
READ_AS_IT_LOOKS = [
    ("{duration: 1e3}", "duration", 1000.0),
    ("{duration: 1E3}", "duration", 1000.0),
    ("{duration: 2.5e+1}", "duration", 25.0),
    ("{duration: 1.5e-3}", "duration", 0.0015),
    ("{duration: +5}", "duration", 5.0),
    ("{duration: 5.}", "duration", 5.0),
    ("{duration: .5}", "duration", 0.5),
    ("{duration: 0}", "duration", 0.0),
    ("{duration: 0.25}", "duration", 0.25),
    ("{random_seed: +7}", "random_seed", 7),
    ("{random_seed: 0}", "random_seed", 0),
    ("{magnet_force: {apply: false}}", "magnet_force.apply", False),
    ("{magnet_force: {apply: False}}", "magnet_force.apply", False),
    ("{magnet_force: {apply: TRUE}}", "magnet_force.apply", True),
    ("{magnet_force: {field_model: 'dipole'}}", "magnet_force.field_model", "dipole"),
    ("{magnet_force: {field_model: dipole}}", "magnet_force.field_model", "dipole"),
]


def _field(scenario, dotted: str):
    for part in dotted.split("."):
        scenario = getattr(scenario, part)
    return scenario


@pytest.mark.parametrize("text,field,value", READ_AS_IT_LOOKS,
                         ids=[r[0] for r in READ_AS_IT_LOOKS])
def test_a_form_a_reader_reads_as_a_number_is_read_so(text, field, value):
    got = _field(load_scenario(override=text), field)
    assert got == value and type(got) is type(value), (got, value)


def test_a_merge_key_is_not_a_key_given_twice(tmp_path):
    # A merge key lays a mapping under the keys written beside it, which override it.
    path = tmp_path / "s.yaml"
    path.write_text("_base: &b {clearance: 0.03, magnet: {remanence: 1.3}}\n"
                    "A:\n  epm: {<<: *b, clearance: 0.04}\n")
    scenario = load_scenario(path, "A")
    assert scenario.epm.clearance == 0.04 and scenario.epm.magnet.remanence == 1.3


def test_infinity_in_yamls_own_spelling_is_read_and_refused_as_not_finite():
    message = _refused("{duration: .inf}")
    assert message.startswith("scenario: duration must be in [0, "), message
    assert math.isinf(float(message.rsplit("got ", 1)[1]))


def test_in_a_file_the_line_and_the_scenario_are_named(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("A:\n  duration: 5\nB:\n  epm:\n    clearance: 0.03\n"
                    "    clearance: 0.04\n")
    with pytest.raises(ScenarioError) as info:
        load_scenario(path, "A")
    assert str(info.value) == (f"{path}:6: B.epm.clearance: given twice (also at line 5); "
                               "a key may appear once in a mapping")
    path.write_text("A: {duration: 5}\nB: {random_seed: 0x1F}\n")
    with pytest.raises(ScenarioError, match=rf"^{path}:2: B\.random_seed: 0x1F reads as the "
                                            r"hexadecimal number 31"):
        scenario_names(path)


def test_a_scenario_named_twice_is_refused(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("Default: {duration: 5}\nFast: {duration: 1}\nDefault: {duration: 9}\n")
    with pytest.raises(ScenarioError) as info:
        scenario_names(path)
    assert str(info.value).startswith(f"{path}:3: Default: given twice (also at line 1)")
    path.write_text("Yes: {duration: 5}\n")
    with pytest.raises(ScenarioError, match=r"the key Yes reads as true"):
        load_scenario(path)


@pytest.mark.parametrize("text", ["# no change", "\n\n", "   ", "\x85", "---\n...\n"])
def test_an_override_of_nothing_changes_nothing(text):
    # Before: "override: YAML root was a <class 'NoneType'> but should have been a dict".
    assert load_scenario(override=text).duration == load_scenario().duration


def test_an_override_that_is_not_utf8_is_one_line():
    # A command-line argument of bytes that are not UTF-8 reaches Python as surrogates.
    # Before: UnicodeEncodeError, an internal error.
    assert _refused("{duration: \udcff}") == ("override: not text (a byte that is not UTF-8 "
                                               "at character 11)")
