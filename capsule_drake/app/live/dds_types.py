"""ROS 2 message types for DDS, made from the same field lists the MCAP logs use.

A ROS 2 node on Cyclone DDS (rmw_cyclonedds) publishes a topic `/a/b` as the DDS topic
`rt/a/b` whose type is the IDL struct `pkg::msg::dds_::Type_` that rosidl generates from
`pkg/msg/Type.msg`: the same fields in the same order, primitive types mapped one to one,
`T[]` a sequence, `T[N]` an array, a nested message its own struct. The structs here are
made at run time from `ros2_messages.DEFINITIONS` (no ROS installation, no generated code)
for cyclonedds's Python binding; their CDR (XCDR1, as ROS 2 exchanges) is byte for byte what
the MCAP writer encodes (tests/test_live_outputs.py checks it).
"""

from __future__ import annotations

import dataclasses
import functools
import types as pytypes

from capsule_drake.app.ros2_messages import DEFINITIONS, dependency, fields


@functools.cache
def _cyclonedds():
    """(cyclonedds.idl.types, IdlStruct, the ROS 2 primitives' IDL types), imported at the
    first use: a run without ROS 2 topics does not load Cyclone DDS."""
    import cyclonedds.idl.types as idl
    from cyclonedds.idl import IdlStruct
    primitive = {"bool": bool, "byte": idl.uint8, "char": idl.uint8, "float32": idl.float32,
                 "float64": idl.float64, "int8": idl.int8, "uint8": idl.uint8,
                 "int16": idl.int16, "uint16": idl.uint16, "int32": idl.int32,
                 "uint32": idl.uint32, "int64": idl.int64, "uint64": idl.uint64, "string": str}
    return idl, IdlStruct, primitive


_FLOATS = ("float32", "float64")
_INTEGERS = ("byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64",
             "uint64")


def dds_type_name(type_name: str) -> str:
    """`pkg/msg/Type` -> `pkg::msg::dds_::Type_` (rosidl's IDL name, rmw_cyclonedds's)."""
    package, kind, name = type_name.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def dds_topic_name(topic: str) -> str:
    """A ROS 2 topic's DDS name: `/a/b` -> `rt/a/b`."""
    return "rt" + (topic if topic.startswith("/") else "/" + topic)


def _annotation(type_name: str, field_type: str):
    idl, _, primitive = _cyclonedds()
    base, _, rest = field_type.partition("[")
    used = dependency(type_name, base)
    element = primitive[base] if used is None else idl_type(used)
    if not rest:
        return element
    size = rest.rstrip("]")
    return idl.array[element, int(size)] if size else idl.sequence[element]


@functools.cache
def idl_type(type_name: str) -> type:
    """The IdlStruct class of a ROS 2 message type (made once, then kept)."""
    if type_name not in DEFINITIONS:
        raise KeyError(f"{type_name}: no definition in ros2_messages.DEFINITIONS")
    annotations = {name: _annotation(type_name, field_type)
                   for field_type, name in fields(type_name)}

    def body(namespace):
        namespace["__annotations__"] = annotations
        namespace["__module__"] = __name__

    cls = pytypes.new_class(type_name.split("/")[-1] + "_", (_cyclonedds()[1],),
                            {"typename": dds_type_name(type_name)}, body)
    return dataclasses.dataclass(cls)


def _cast(base: str):
    return float if base in _FLOATS else (int if base in _INTEGERS else
                                          (bool if base == "bool" else str))


def _convert(type_name: str, field_type: str, value):
    base, _, rest = field_type.partition("[")
    used = dependency(type_name, base)
    if used is None:
        if rest and base in ("uint8", "byte", "char") and isinstance(value, (bytes, bytearray)):
            return value
        if rest:
            return [_cast(base)(v) for v in value]
        return _cast(base)(value)
    if rest:
        return [to_idl(used, v) for v in value]
    return to_idl(used, value)


def to_idl(type_name: str, message: dict):
    """The IdlStruct instance of a message given as the MCAP writer's dictionary (missing
    fields take their type's zero, as in the CDR encoder)."""
    cls = idl_type(type_name)
    values = {}
    for field_type, name in fields(type_name):
        if name in message:
            values[name] = _convert(type_name, field_type, message[name])
        else:
            values[name] = _zero(type_name, field_type)
    return cls(**values)


def _zero(type_name: str, field_type: str):
    base, _, rest = field_type.partition("[")
    used = dependency(type_name, base)
    if rest:
        size = rest.rstrip("]")
        if not size:
            return []
        return [_zero(type_name, base) for _ in range(int(size))]
    if used is not None:
        return to_idl(used, {})
    return _cast(base)()


def from_idl(sample) -> dict:
    """A received sample as a plain dictionary (nested messages as dictionaries)."""
    if dataclasses.is_dataclass(sample):
        return {f.name: from_idl(getattr(sample, f.name)) for f in dataclasses.fields(sample)}
    if isinstance(sample, list):
        return [from_idl(v) for v in sample]
    return sample
