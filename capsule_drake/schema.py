"""Checks a YAML document against a dataclass schema and names what is wrong.

`pydrake.common.yaml.yaml_load_typed` already rejects unknown keys and wrong types, but its
messages do not say where in a nested scenario the bad key sits. This module walks the raw
document first and raises `SchemaError` with a dotted path (`epm.path.speed`), so that a user's
mistake costs one line of output, not a traceback.
"""

from __future__ import annotations

import dataclasses
import types
import typing

import yaml


class ScenarioError(ValueError):
    """A scenario file, override or value is wrong; the message is one line naming where."""


class SchemaError(ScenarioError):
    """A scenario document does not match its schema; the message names the key."""


class _Tagged(dict):
    """A YAML mapping that carried a `!Tag`, as the union-typed fields use."""

    def __init__(self, tag: str, mapping: dict):
        super().__init__(mapping)
        self.tag = tag


class _Loader(yaml.SafeLoader):
    pass


def _construct_tagged(loader, tag_suffix, node):
    if isinstance(node, yaml.MappingNode):
        return _Tagged(tag_suffix, loader.construct_mapping(node, deep=True))
    raise yaml.constructor.ConstructorError(
        None, None, f"tag !{tag_suffix} must be followed by a mapping", node.start_mark)


_Loader.add_multi_constructor("!", _construct_tagged)


def parse_yaml(text: str, source: str) -> typing.Any:
    """Parses YAML text; syntax errors become a `SchemaError` naming `source` and the line."""
    try:
        return yaml.load(text, Loader=_Loader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"{source}:{mark.line + 1}" if mark else source
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise SchemaError(f"{where}: YAML syntax error: {problem}") from None


def _is_float_text(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _type_name(t) -> str:
    return getattr(t, "__name__", str(t))


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
        # An untagged mapping means the first alternative (as yaml_load_typed reads it).
        check(options[0], node, path)
        return
    if dataclasses.is_dataclass(schema):
        if not isinstance(node, dict):
            raise SchemaError(f"{path}: expected a mapping for {_type_name(schema)}, "
                              f"got {type(node).__name__}")
        if isinstance(node, _Tagged) and node.tag != _type_name(schema):
            raise SchemaError(f"{path}: tag !{node.tag} does not fit {_type_name(schema)}")
        hints = typing.get_type_hints(schema)
        known = {f.name for f in dataclasses.fields(schema)}
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
        if isinstance(node, str) and _is_float_text(node):
            return  # YAML 1.1 reads 1.0e4 (no exponent sign) as text; Drake converts it.
        if isinstance(node, bool) or not isinstance(node, (int, float)):
            raise SchemaError(f"{path}: expected a number, got {node!r}")
        return
    if schema is int:
        if isinstance(node, bool) or not isinstance(node, int):
            raise SchemaError(f"{path}: expected an integer, got {node!r}")
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
