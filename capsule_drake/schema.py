"""Checks a YAML document against a dataclass schema and names what is wrong.

`pydrake.common.yaml.yaml_load_typed` already rejects unknown keys and wrong types, but its
messages do not say where in a nested scenario the bad key sits. This module walks the raw
document first and raises `SchemaError` with a dotted path (`epm.path.speed`), so that a user's
mistake costs one line of output, not a traceback.

Both read YAML by PyYAML's YAML 1.1 rules, where some text reads otherwise than it looks.
`parse_yaml` refuses, with the line and the dotted path, what would be read so (`_check_forms`):
a key given twice in a mapping (the last one would win silently), and the plain scalars
YAML 1.1 reads as numbers or booleans that a reader (or YAML 1.2) reads otherwise:
hexadecimal 0x10, octal 010, binary 0b101, base-60 1:30, digit separators 1_000, numbers
with a leading zero, and yes/no/on/off (true and false are the booleans). Where a number
belongs, `check` takes it written plainly in the digits 0-9 (5, -2, 0.5, 5., .5, 1e3,
1.5e-3, +5; .inf and .nan are read, then refused as not finite): text in quotes ('5'),
digits of other scripts (which Python's float() reads) and words (inf) are refused.
"""

from __future__ import annotations

import dataclasses
import math
import re
import sys
import types
import typing

import yaml


_LARGEST_FLOAT = sys.float_info.max


class ScenarioError(ValueError):
    """A scenario file, override or value is wrong; the message is one line naming where."""


class SchemaError(ScenarioError):
    """A scenario document does not match its schema; the message names the key."""


class _Tagged(dict):
    """A YAML mapping that carried a `!Tag`, as the union-typed fields use."""

    def __init__(self, tag: str, mapping: dict):
        super().__init__(mapping)
        self.tag = tag


# What a scenario document may cost to read. A scenario has ~300 fields, at most ~6 levels
# deep, and no field takes a list longer than a handful of numbers; these bounds are far
# above any real scenario file (diagrams/default.yaml: 9.5 kB, 1,700 nodes, 5 levels) and far
# below what would exhaust the parser (Python's recursion, or memory).
MAX_TEXT_BYTES = 1_000_000
"""Largest scenario text (a file, or an override), in bytes."""
MAX_DEPTH = 50
"""Deepest nesting of lists and mappings."""
MAX_NODES = 100_000
"""Most nodes (scalars, lists, mappings) a document may hold once every alias is expanded:
a document of a few hundred bytes whose anchors refer to each other can otherwise expand
to billions (the "billion laughs")."""


MIN_PERIOD = 1e-4
"""Shortest period (s) of any periodic block (sensors, controllers, channels, logs): the
fastest loop of the system is the haptic device's 1 kHz servo; every period is an event
of the simulator, so a period far below that does nothing but make a run crawl (1 ns would
be 60 billion events in a one-minute run). Sample rates are bounded by its inverse."""
MAX_RATE = 1.0 / MIN_PERIOD


class _Loader(yaml.CSafeLoader if yaml.__with_libyaml__ else yaml.SafeLoader):
    pass


class _Text(str):
    """A scalar written as text (in quotes, or a block): never read as a number."""


def _construct_tagged(loader, tag_suffix, node):
    if isinstance(node, yaml.MappingNode):
        return _Tagged(tag_suffix, loader.construct_mapping(node, deep=True))
    raise yaml.constructor.ConstructorError(
        None, None, f"tag !{tag_suffix} must be followed by a mapping", node.start_mark)


def _construct_str(loader, node):
    text = loader.construct_scalar(node)
    return _Text(text) if node.style in ("'", '"', "|", ">") else text


_Loader.add_multi_constructor("!", _construct_tagged)
_Loader.add_constructor("tag:yaml.org,2002:str", _construct_str)

# A number as it is written where one belongs: an optional sign, the digits 0-9 without a
# leading zero, a fraction, an exponent. YAML 1.1 reads some of these as text (1e3, 5e6:
# its floats need a point and a signed exponent), which Drake's loader converts.
_DECIMAL = re.compile(r"[-+]?(?:(?:0|[1-9][0-9]*)(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
_INTEGER = re.compile(r"[-+]?(?:0|[1-9][0-9]*)")
# YAML's own spelling of the infinities and NaN (read as such, then refused as not finite).
_NOT_FINITE = re.compile(r"[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)")
_BOOLEANS = ("true", "True", "TRUE", "false", "False", "FALSE")
_INT_TAG, _FLOAT_TAG = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"
_BOOL_TAG, _MERGE_TAG = "tag:yaml.org,2002:bool", "tag:yaml.org,2002:merge"


def _number_text(value: float | int) -> str:
    return f"{value:g}" if isinstance(value, float) and not value.is_integer() else (
        str(int(value)))


def _misread(loader, node, key: bool = False) -> str | None:
    """What YAML 1.1 reads the plain scalar `node` (a mapping's key: `key`) as, in words,
    when a reader would read it otherwise ("reads as the hexadecimal number 16 ..."), with
    what to write instead; None when it reads as it looks."""
    if not isinstance(node, yaml.ScalarNode) or node.style:  # quoted or a block: text
        return None
    text = node.value
    if node.tag == _BOOL_TAG:
        if text in _BOOLEANS:
            return None
        value = "true" if loader.construct_yaml_bool(node) else "false"
        return (f"reads as {value} in YAML 1.1 (and as text in YAML 1.2); "
                + (f"quote it ('{text}')" if key else
                   f"write {value}, or quote it ('{text}') if it is meant as text"))
    if node.tag == _INT_TAG and not _INTEGER.fullmatch(text):
        value = loader.construct_yaml_int(node)
    elif node.tag == _FLOAT_TAG and not (_DECIMAL.fullmatch(text)
                                         or _NOT_FINITE.fullmatch(text)):
        value = loader.construct_yaml_float(node)
    else:
        return None
    digits = text.lstrip("+-")
    if "_" in text:
        what = _number_text(value)
    elif ":" in text:
        what = f"the base-60 number {_number_text(value)}"
    elif digits[:2] in ("0x", "0X"):
        what = f"the hexadecimal number {value}"
    elif digits[:2] in ("0b", "0B"):
        what = f"the binary number {value}"
    elif node.tag == _INT_TAG:
        what = f"the octal number {value}"
    else:
        return (f"is a number with a leading zero (YAML 1.1 reads 010 as the octal number "
                f"8); write {_number_text(value)}")
    return (f"reads as {what} in YAML 1.1 (and as text in YAML 1.2); "
            + (f"quote it ('{text}')" if key else
               f"write {_number_text(value)}, or quote it ('{text}') if it is meant as text"))


def _check_forms(loader, node, source: str, path: str = "", seen=None) -> None:
    """Raises SchemaError ("<source>:<line>: <path>: ...") at the first key given twice in a
    mapping, and the first plain scalar (a value or a key) that YAML 1.1 reads otherwise than
    it looks (`_misread`). A merge key (<<) lays its mappings under the keys beside it, which
    override them: that is no key given twice. `seen`: the nodes walked (an alias is walked
    once)."""
    seen = set() if seen is None else seen
    if id(node) in seen:
        return
    seen.add(id(node))

    def fail(at, what: str):
        where = f"{path}: " if path else ""
        raise SchemaError(f"{source}:{at.start_mark.line + 1}: {where}{what}")

    if isinstance(node, yaml.ScalarNode):
        problem = _misread(loader, node)
        if problem:
            fail(node, f"{node.value} {problem}")
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _check_forms(loader, item, source, f"{path}[{i}]", seen)
    elif isinstance(node, yaml.MappingNode):
        first_at = {}
        for key, value in node.value:
            if key.tag == _MERGE_TAG:
                _check_forms(loader, value, source, path, seen)
                continue
            if isinstance(key, yaml.ScalarNode):
                problem = _misread(loader, key, key=True)
                if problem:
                    fail(key, f"the key {key.value} {problem}")
                where = f"{path}.{key.value}" if path else key.value
                identity = (key.tag, loader.construct_object(key))
                if identity in first_at:
                    raise SchemaError(
                        f"{source}:{key.start_mark.line + 1}: {where}: given twice (also at "
                        f"line {first_at[identity]}); a key may appear once in a mapping")
                first_at[identity] = key.start_mark.line + 1
            else:
                where = path
            _check_forms(loader, value, source, where, seen)


def _check_size(text: str, source: str) -> None:
    """Raises SchemaError when `text` is too large, too deep, or expands (through its
    aliases) to too many nodes. Reads the YAML's events, which takes no recursion and no
    memory beyond the open collections, before anything builds the document."""
    size = len(text.encode("utf-8", "surrogatepass"))
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as e:  # an argument that is not UTF-8 (Python's surrogateescape)
        raise SchemaError(f"{source}: not text (a byte that is not UTF-8 at character "
                          f"{e.start})") from None
    if size > MAX_TEXT_BYTES:
        raise SchemaError(f"{source}: {size / 1e6:.1f} MB, larger than the "
                          f"{MAX_TEXT_BYTES / 1e6:g} MB a scenario may be")
    # Per open collection: [expanded node count, its anchor]; anchors of closed nodes ->
    # their expanded node counts.
    stack, anchors, total = [], {}, 0

    def add(count: int, line: int):
        nonlocal total
        if stack:
            stack[-1][0] += count
        else:
            total += count
        if total + sum(item[0] for item in stack) > MAX_NODES:
            raise SchemaError(f"{source}:{line}: the document expands (through its aliases) "
                              f"to more than {MAX_NODES:,} nodes")

    try:
        for event in yaml.parse(text, Loader=_Loader):
            line = event.start_mark.line + 1 if event.start_mark else 0
            if isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
                if len(stack) >= MAX_DEPTH:
                    raise SchemaError(f"{source}:{line}: nested deeper than {MAX_DEPTH} levels")
                stack.append([1, event.anchor])
            elif isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
                count, anchor = stack.pop()
                if anchor is not None:
                    anchors[anchor] = count
                add(count, line)
            elif isinstance(event, yaml.ScalarEvent):
                if event.anchor is not None:
                    anchors[event.anchor] = 1
                add(1, line)
            elif isinstance(event, yaml.AliasEvent):
                if event.anchor not in anchors and any(a == event.anchor for _, a in stack):
                    raise SchemaError(f"{source}:{line}: alias *{event.anchor} refers to a "
                                      "node that contains it")
                add(anchors.get(event.anchor, 1), line)
    except yaml.YAMLError as e:
        if "nesting depth" in str(e):  # libyaml's own limit, met while it reads ahead
            mark = getattr(e, "problem_mark", None)
            where = f"{source}:{mark.line + 1}" if mark else source
            raise SchemaError(f"{where}: nested deeper than {MAX_DEPTH} levels") from None
        # any other syntax error: parse_yaml reports it, with its line


def parse_yaml(text: str, source: str) -> typing.Any:
    """Parses YAML text; syntax errors become a `SchemaError` naming `source` and the line,
    and so does a document too large, too deep or expanding to too many nodes (MAX_*), a key
    given twice, and a scalar YAML 1.1 reads otherwise than it looks (`_check_forms`)."""
    _check_size(text, source)
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_forms(loader, node, source)
        return loader.construct_document(node)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"{source}:{mark.line + 1}" if mark else source
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise SchemaError(f"{where}: YAML syntax error: {problem}") from None
    finally:
        loader.dispose()


def _not_a_number(path: str, node: str, expected: str) -> SchemaError:
    """The error for text where a number belongs, saying what is wrong with it."""
    if isinstance(node, _Text):
        return SchemaError(f"{path}: expected {expected}, got the text {node!r} (in quotes); "
                           "write a number without quotes")
    if any(c.isdigit() and not "0" <= c <= "9" for c in node):
        return SchemaError(f"{path}: expected {expected}, got {node!r}; write numbers with the "
                           "digits 0-9")
    if _DECIMAL.fullmatch(node.lstrip("+-").lstrip("0") or "0") and re.match(
            r"[-+]?0[0-9]", node):
        return SchemaError(f"{path}: expected {expected}, got {node!r}, a number with a "
                           "leading zero (YAML 1.1 reads 010 as the octal number 8); write it "
                           "without")
    return SchemaError(f"{path}: expected {expected}, got {node!r}")


def _type_name(t) -> str:
    return getattr(t, "__name__", str(t))


def field_types(schema) -> dict | None:
    """{field name: annotated type} of a dataclass or of one of Drake's configs (their
    `__fields__`: the plant's, the simulator's), in declaration order; None for any other
    type. The one walk over a config's fields: the schema check here, the scenario's
    number check (scenario.py)."""
    if dataclasses.is_dataclass(schema):
        hints = typing.get_type_hints(schema)
        return {f.name: hints[f.name] for f in dataclasses.fields(schema)}
    drake_fields = getattr(schema, "__fields__", None)
    if isinstance(drake_fields, tuple):
        return {f.name: f.type for f in drake_fields}
    return None


def check(schema, node, path: str) -> None:
    """Raises SchemaError if `node` (parsed YAML) does not fit the type `schema`."""
    origin = typing.get_origin(schema)
    args = typing.get_args(schema)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in args if a is not type(None)]
        if node is None and type(None) in args:
            return
        if isinstance(node, _Tagged):
            for option in options:
                if _type_name(option) == node.tag:
                    check(option, dict(node), path)
                    return
            names = ", ".join("!" + _type_name(o) for o in options)
            raise SchemaError(f"{path}: unknown tag !{node.tag} (expected one of {names})")
        if not isinstance(node, dict) and all(dataclasses.is_dataclass(o) for o in options):
            names = ", ".join("!" + _type_name(o) + " {...}" for o in options)
            raise SchemaError(f"{path}: expected one of {names}, got {node!r}")
        # An untagged mapping means the first alternative (as yaml_load_typed reads it).
        check(options[0], node, path)
        return
    hints = field_types(schema)   # a dataclass, or Drake's configs (plant, simulator)
    if hints is not None:
        if not isinstance(node, dict):
            raise SchemaError(f"{path}: expected a mapping for {_type_name(schema)}, "
                              f"got {type(node).__name__}")
        if isinstance(node, _Tagged) and node.tag != _type_name(schema):
            raise SchemaError(f"{path}: tag !{node.tag} does not fit {_type_name(schema)}")
        known = set(hints)
        for key, value in node.items():
            where = f"{path}.{key}" if path else str(key)
            if key not in known:
                raise SchemaError(f"{where}: unknown key (known keys: {', '.join(sorted(known))})")
            check(hints[key], value, where)
        return
    if origin in (list, typing.List):
        if not isinstance(node, list):
            raise SchemaError(f"{path}: expected a list, got {type(node).__name__}")
        for i, item in enumerate(node):
            check(args[0], item, f"{path}[{i}]")
        return
    if origin in (dict, typing.Dict):
        if not isinstance(node, dict):
            raise SchemaError(f"{path}: expected a mapping, got {type(node).__name__}")
        for key, item in node.items():
            check(args[1], item, f"{path}.{key}")
        return
    if schema is float:
        if isinstance(node, str):
            if not isinstance(node, _Text) and _DECIMAL.fullmatch(node):
                return  # YAML 1.1 reads 1.0e4 (no exponent sign) as text; Drake converts it.
            raise _not_a_number(path, node, "a number")
        if isinstance(node, bool) or not isinstance(node, (int, float)):
            raise SchemaError(f"{path}: expected a number, got {node!r}")
        if isinstance(node, int) and abs(node) > _LARGEST_FLOAT:
            raise SchemaError(f"{path}: expected a number, got an integer of {len(str(node))} "
                              "digits, beyond a float's range")
        return
    if schema is int:
        if isinstance(node, str):
            raise _not_a_number(path, node, "an integer")
        if isinstance(node, bool) or not isinstance(node, int):
            raise SchemaError(f"{path}: expected an integer, got {node!r}")
        if not -2 ** 63 <= node < 2 ** 64:
            raise SchemaError(f"{path}: expected an integer of at most 64 bits, got one of "
                              f"{len(str(abs(node)))} digits")
        return
    if schema is bool:
        if not isinstance(node, bool):
            raise SchemaError(f"{path}: expected true or false, got {node!r}")
        return
    if schema is str:
        if not isinstance(node, str):
            raise SchemaError(f"{path}: expected a string, got {node!r}")
        return
    # Any other annotation is left to yaml_load_typed.


def _bounds(interval: str):
    """(low, high, low_open, high_open) of "[a, b]", "(a, b]", "> a", ">= a", "<= b"."""
    text = interval.strip()
    if text[0] in "[(":
        low, high = (float(part) for part in text[1:-1].split(","))
        return low, high, text[0] == "(", text[-1] == ")"
    op, number = text.split()
    return {">": (float(number), math.inf, True, True),
            ">=": (float(number), math.inf, False, True),
            "<": (-math.inf, float(number), True, True),
            "<=": (-math.inf, float(number), True, False)}[op]


def need_range(value, key: str, interval: str, unit: str = "", why: str = "") -> None:
    """Raises ValueError "<key> must be finite and <interval> [unit] [(why)], got <value>"
    unless `value` (a number, or each number of a list) is finite and inside `interval`
    ("[a, b]", "(a, b]", "> a", ">= a", "<= b"; see `_bounds`)."""
    low, high, low_open, high_open = _bounds(interval)
    values = value if isinstance(value, (list, tuple)) else [value]

    def inside(v) -> bool:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return False
        if isinstance(v, float) and not math.isfinite(v):
            return False
        return ((v > low if low_open else v >= low) and (v < high if high_open else v <= high))

    if not all(inside(v) for v in values):
        bounded = interval.strip()[0] in "[("
        constraint = f"in {interval}" if bounded else f"finite and {interval}"
        unit = f" {unit}" if unit else ""
        why = f" ({why})" if why else ""
        raise ValueError(f"{key} must be {constraint}{unit}{why}, got {value!r}")
