"""The documentation site's Reference pages, generated from the code so that they cannot drift.

    python -m capsule_drake.app.reference OUT_DIR    # writes OUT_DIR/reference/*.md

`reference_pages()` gives {page path: Markdown} of the pages of PAGES:
- reference/scenario.md: every field of `Scenario`, through its nested configs, each member of
  its unions (by YAML tag) and its optional blocks (null: absent); a section per config in the
  scenario's order, a row per field: key, type, default, unit, bounds, source, description.
- reference/scenarios.md: the named scenarios of diagrams/default.yaml and what each changes.
- reference/blocks.md: the blocks of STATION_BLOCKS, the systems each adds with their ports,
  and the station's exported ports, read on stations built for the named scenarios.
- reference/cli.md: the verbs and flags of `capsule-sim`, walked from its argparse parser.
- reference/benchmark.md: the benchmark's columns (task.py COLUMN_DOCS, tables.py
  SUMMARY_COLUMN_DOCS).

Where a field's figures come from:
- description: the `#` comment lines directly above the field in its dataclass's source. A
  field without any belongs to the group above it (the fields on the lines directly after a
  commented one, no blank line between) and takes its comment, unless it holds a config,
  which its class docstring then describes. Drake's configs (plant, simulator): their docs.
- unit: a comment's "(m)" or "[m]": the first, for a field alone; in a group's comment, the
  one after the field's name, else one per field by position; else the unit of its bound.
- bounds: every `need_range` check (schema.py) run while validating each named scenario, and
  the Default scenario with each optional block or union member that no named scenario holds
  set to its defaults (`_probes`). A check's key, prefixed as `blocks.checked` prefixes its
  message, is resolved on the scenario checked to a field (list indices dropped).
- source: the rows of docs/sources.md's tables that name the field in backticks: by its dotted
  key, by a bare name after a dotted key in the row (read under that key's parent), or by its
  bare name in a section whose heading names the field's module; the status is the leading
  marker of the row's last cell (V, DS, S, U, M, S/U, ...). Without one, the markers of its
  comment ("(U)", "(S)", "assumption": U). Anchors follow Python-Markdown's toc slugify
  (MkDocs' default): NFKD to ASCII, characters other than word characters, spaces and hyphens
  dropped, lowercase, runs of spaces and hyphens one hyphen; a repeated anchor gets _1, _2.
"""

from __future__ import annotations

import argparse
import ast
import copy
import inspect
import io
import json
import re
import sys
import textwrap
import tokenize
import types
import typing
import unicodedata
from pathlib import Path

from pydrake.common import pretty_class_name
from pydrake.systems.framework import PortDataType

from capsule_drake import blocks, schema
from capsule_drake.app.benchmark.tables import SUMMARY_COLUMN_DOCS
from capsule_drake.app.benchmark.task import COLUMN_DOCS
from capsule_drake.app.cli_parser import _parser
from capsule_drake.app.run import close_render_worker
from capsule_drake.scenario import (DEFAULT_SCENARIO_FILE, REPO_ROOT, STATION_BLOCKS, Scenario,
                                    load_scenario, scenario_names, station_blocks, validate)
from capsule_drake.scene import StationParts
from capsule_drake.schema import ScenarioError, field_types, parse_yaml
from capsule_drake.station import make_station

SOURCES = REPO_ROOT / "docs" / "sources.md"
COSTLY = ("FastContact",)
"""Named scenarios not built for blocks.md when the stations built hold all their blocks (of
the same config types): FastContact's convex wall pieces take ~15 s and ~2 GB to build."""

_ATOM = (r"(?:%|m|mm|cm|s|ms|N|Pa|kPa|MPa|T|mT|J|kg|g|rad|deg|Hz|px|ml|A|min|sqrt_\w+)"
         r"(?:\^-?\d+)?")
_UNIT = re.compile(rf"-|(?:1/)?{_ATOM}(?:(?:[ /]| per ){_ATOM})*")
_MARKER = r"(?:DS|V|S|U|M)(?:\s*/\s*(?:DS|V|S|U|M))*(?!\w)"
_HEADER = ["Key", "Type", "Default", "Unit", "Bounds", "Source", "Description"]


def _banner(what: str, title: str) -> str:
    return (f"# {title}\n\n*Generated from the code ({what}) by `python -m "
            f"capsule_drake.app.reference` (capsule_drake/app/reference.py) when the site is "
            f"built: do not edit by hand.*\n\n")


def _cell(text) -> str:
    """`text` on one line, `|`, `*` and `<` escaped outside code spans (a table cell)."""
    parts = " ".join(str(text).split()).split("`")
    parts = parts if len(parts) % 2 else ["'".join(parts)]    # an unpaired backtick
    return "`".join(p if i % 2 else p.replace("|", "\\|").replace("*", "\\*")
                    .replace("<", "&lt;") for i, p in enumerate(parts))


def _table(header, rows) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows])


def _slug(title: str, seen: set) -> str:
    """The anchor Python-Markdown's toc gives a heading (module docstring)."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", title).replace("`", "").replace("*", "")
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")
    slug = unique = re.sub(r"[-\s]+", "-", re.sub(r"[^\w\s-]", "", text).strip().lower())
    n = 0
    while unique in seen:
        n += 1
        unique = f"{slug}_{n}"
    seen.add(unique)
    return unique


def _flow(value) -> str:
    """`value` (a default, parsed YAML) in YAML's flow style."""
    if value is None or isinstance(value, bool):
        return {None: "null", True: "true", False: "false"}[value]
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):   # as written in a YAML file (1.0e6, unquoted: text), or text
        plain = (re.fullmatch(r"[A-Za-z_][\w./:-]*", value) and value.lower() not in (
            "true", "false", "null", "yes", "no", "on", "off")) or (
            not isinstance(value, schema._Text) and schema._DECIMAL.fullmatch(value))
        return value if plain else json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(map(_flow, value)) + "]"
    tag = f"!{value.tag} " if isinstance(value, schema._Tagged) else ""
    return tag + "{" + ", ".join(f"{k}: {_flow(v)}" for k, v in value.items()) + "}"


def _doc(obj) -> str:
    """The first paragraph of `obj`'s own docstring ("" for a dataclass's generated one)."""
    doc = inspect.getdoc(obj) or ""
    if inspect.isclass(obj) and ("__doc__" not in vars(obj) or doc.startswith(obj.__name__ + "(")):
        return ""
    return " ".join(doc.split("\n\n")[0].split())


# --- reference/scenario.md ----------------------------------------------------------------

def _parts(hint):
    """(config classes, nullable, a list) of a field's annotated type."""
    if typing.get_origin(hint) is list:
        return _parts(typing.get_args(hint)[0])[0], False, True
    union = typing.get_origin(hint) in (typing.Union, types.UnionType)
    args = typing.get_args(hint) if union else (hint,)
    return [a for a in args if field_types(a) is not None], type(None) in args, False


def _type_text(hint) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        tag = "!" if len(_parts(hint)[0]) > 1 else ""
        return " or ".join("null" if a is type(None) else (tag if field_types(a) else "")
                           + _type_text(a) for a in args)
    if origin in (list, dict):
        return f"{origin.__name__}[{', '.join(map(_type_text, args))}]"
    return getattr(hint, "__name__", str(hint))


def _comments(cls) -> dict[str, tuple[str, bool, list]]:
    """{field: (its comment, whether its own, its group's fields)} of a dataclass, read from
    its source and its bases' (module docstring)."""
    out = {}
    for owner in [c for c in reversed(cls.__mro__) if "__dataclass_fields__" in vars(c)]:
        source = textwrap.dedent(inspect.getsource(owner))
        comments = {t.start[0]: t.string.lstrip("#").strip() for t in
                    tokenize.generate_tokens(io.StringIO(source).readline)
                    if t.type == tokenize.COMMENT and t.line.lstrip().startswith("#")}
        above_end, group = None, []
        for node in ast.parse(source).body[0].body:
            if not isinstance(node, ast.AnnAssign):
                above_end = None
                continue
            line, lines, name = node.lineno - 1, [], node.target.id
            while line in comments:
                lines.insert(0, comments[line])
                line -= 1
            if lines or above_end != node.lineno - 1:
                group = [name]
                text = re.sub(r"(?<=\S)/ (?=\S)", "/", " ".join(lines))   # "epm/\nshaping.py"
                out[name] = (text, bool(lines), group)
            else:
                group.append(name)
                out[name] = (out[group[0]][0], False, group)
            above_end = node.end_lineno
    return out


def _units(text: str) -> list[str]:
    """The units a comment gives, in order, in parentheses or brackets: "(m)", "[Pa/m]",
    "(s; 0: none)", "(the angle, deg)", "(N s/m, N m s/rad)"; "[-]" is 1."""
    found = []
    for content in re.findall(r"(?:^|\s)[(\[]([^()\[\]]*)[)\]]",
                              re.sub(r"sqrt\((\w+)\)", r"sqrt_\1", text)):
        pieces = [p.strip() for p in re.split(r"[,;]", content)]
        units = [p for p in pieces if _UNIT.fullmatch(p)]
        found += pieces if units == pieces else [p for p in (pieces[0], pieces[-1])
                                                 if p in units][:1]
    return ["1" if p == "-" else re.sub(r"sqrt_(\w+)", r"sqrt(\1)", p) for p in found]


def _unit(text: str, group: list, name: str, checks) -> str:
    """A field's unit (module docstring): its comment's, else its bound's."""
    units, bound = _units(text), next((unit for _, unit in checks if unit), "")
    if len(group) == 1:
        return (units or [bound])[0]
    after_name = {n: _units(m.group(1)) for n in group for m in [re.search(
        rf"\b{n}\b\s*([(\[][^)\]]*[)\]])", text)] if m and _units(m.group(1))}
    if after_name:                      # "... push_after (s) ...": the unit after each name
        return after_name.get(name, [bound])[0]
    return units[group.index(name)] if len(units) == len(group) else bound


def _at(obj, key: str):
    for name in key.split(".") if key else ():
        obj = getattr(obj, name, None)
    return obj


def _probes(named: dict) -> list:
    """The Default scenario with each optional block, and each union member, that no named
    scenario holds at its key set to its defaults (a block inside another: in that one's)."""
    out = []

    def walk(base, obj, key):
        for name, hint in (field_types(type(obj)) or {}).items():
            where = f"{key}.{name}" if key else name
            configs, _, is_list = _parts(hint)
            for cls in [] if is_list else configs:
                if isinstance(getattr(obj, name), cls):
                    walk(base, getattr(obj, name), where)
                    continue
                probe = copy.deepcopy(base)
                setattr(_at(probe, key), name, cls())
                if not any(isinstance(_at(s, where), cls) for s in named.values()):
                    out.append(probe)
                walk(probe, _at(probe, where), where)
    walk(Scenario(), Scenario(), "")
    return out


def _field_of(scenario, key: str):
    """(dotted key, owner class name) of the field a check's `key` names on `scenario`."""
    obj, names, out = scenario, re.findall(r"([^.\[\]\s]+)((?:\[\d+\])*)", key), []
    for i, (name, index) in enumerate(names):
        if name not in (field_types(type(obj)) or {}):
            return None
        owner, obj, inner = obj, getattr(obj, name), index and i < len(names) - 1
        out.append(name + ("[]" if inner else ""))
        obj = obj[int(index[1:].split("]")[0])] if inner else obj
    return ".".join(out), type(owner).__name__


def _bounds(named: dict) -> tuple[dict, list]:
    """{(key, owner class name): {(interval, unit): None}} of the range checks run validating
    the named scenarios and the probes (module docstring); the checked keys naming no field."""
    found, unmapped, prefix = {}, set(), [""]
    need_range, checked = schema.need_range, blocks.checked

    def noting_need_range(value, key, interval, unit="", why=""):
        where = re.sub(r"\s*\([^)]*\)", "", prefix[-1]).replace(": ", ".") + key
        field = _field_of(scenario, where)
        if field is None:
            unmapped.add(where)
        else:
            found.setdefault(field, {})[(interval, unit)] = None
        return need_range(value, key, interval, unit, why)

    def noting_checked(where, check, *args):
        prefix.append(where)
        try:
            return checked(where, check, *args)
        finally:
            prefix.pop()

    patched = [(m, a, f, new) for m in list(sys.modules.values())
               if getattr(m, "__name__", "").startswith("capsule_drake")
               for a, f, new in (("need_range", need_range, noting_need_range),
                                 ("checked", checked, noting_checked))
               if getattr(m, a, None) is f]
    try:
        for module, attr, _, new in patched:
            setattr(module, attr, new)
        for scenario in [*named.values(), *_probes(named)]:
            try:
                validate(scenario)
            except ScenarioError:
                pass    # a probe refused by a later check: the checks before it count
    finally:
        for module, attr, f, _ in patched:
            setattr(module, attr, f)
    return found, sorted(unmapped)


def _source_rows() -> list[tuple]:
    """(section number, anchor, modules its heading names, backticked names, status) of each
    table row of docs/sources.md whose last cell starts with a status."""
    rows, heading, seen, fenced = [], ("", "", ()), set(), False
    for line in SOURCES.read_text().splitlines():
        fenced ^= line.startswith("```")
        title = None if fenced else re.match(r"#{1,6}\s+(.*?)\s*#*$", line)
        if title:
            number = re.match(r"\d+(?:\.\d+)*", title.group(1))
            heading = (number.group().rstrip(".") if number else title.group(1),
                       _slug(title.group(1), seen), re.findall(r"[\w/]+\.py", title.group(1)))
        elif line.startswith("|") and not fenced:
            cells = re.findall(r"(?:`[^`]*`|\\\||[^|`])+", line.strip().strip("|"))
            status = re.match(rf"\s*({_MARKER})", cells[-1]) if cells else None
            if status:
                rows.append((*heading, re.findall(r"`([^`]+)`", line),
                             re.sub(r"\s", "", status.group(1))))
    return rows


def _source(key: str, name: str, module: str, rows) -> str:
    """The field's status and sources.md section(s) (module docstring), or ""."""
    plain, found = key.replace("[]", ""), {}
    for number, anchor, modules, names, status in rows:
        parent = None
        for token in names:
            if "." in token:
                parent = token.rsplit(".", 1)[0]
                hit = plain == token or plain.endswith("." + token)
            elif parent:
                hit = plain == f"{parent}.{token}"
            else:
                hit = token == name and module in modules
            if hit:
                found[f"{status} ([{number}](../sources.md#{anchor}))"] = None
    return ", ".join(found)


def _row(cls, default, key, name, hint, comment, checks, rows, anchors) -> list:
    """The table row of field `name` (annotated `hint`) of config `cls` at `key`."""
    text, own, group = comment
    configs, nullable, is_list = _parts(hint)
    where, value = f"{key}.{name}" if key else name, getattr(default, name)
    if "__dataclass_fields__" not in vars(cls):           # Drake's configs: the property's doc
        text = re.sub(r"^\(self\).*", "", _doc(getattr(cls, name))).replace("∷", "::")
    elif configs and not own and len(configs) == 1:
        text = _doc(configs[0]) or text
    unit = "" if configs else _unit(text, group, name, checks)
    owner = next((c for c in cls.__mro__ if name in vars(c).get("__annotations__", {})), cls)
    module = owner.__module__.replace(".", "/").removeprefix("capsule_drake/") + ".py"
    markers = dict.fromkeys(re.findall(rf"[(,;]\s*({_MARKER})\s*(?=[).;:]|$)", text)
                            + (["U"] if re.search(r"\bassumption\b", text, re.I) else []))
    source = _source(where, name, module, rows) or (
        f"{', '.join(markers)} (its comment)" if markers else "")
    kind = _type_text(hint)
    for c in configs:
        anchor = anchors[(where + "[]" * is_list, c)]
        kind = re.sub(rf"(!?)\b{c.__name__}\b", rf"[\1{c.__name__}](#{anchor})", kind)
    shown = ("`null` (absent)" if value is None else f"`!{type(value).__name__} {{}}`"
             if len(configs) > 1 else "its section" if configs and not is_list
             else f"`{_flow(value)}`")
    limits = "; ".join(f"`{i}`" + (f" {u}" if u else "") for i, u in checks) or "—"
    return [f"`{where}`", kind, shown, unit, limits, source, text]


def _sections(cls, default, key="", title="", within="") -> list[tuple]:
    """(heading, config class, default, key) of `cls` at `key` and of every config under it,
    in the scenario's order: nested configs, union members (by tag), optional blocks (their
    defaults), the items of lists."""
    out = [(title or "The scenario's top-level keys (Scenario)", cls, default, key)]
    for name, hint in field_types(cls).items():
        configs, _, is_list = _parts(hint)
        path = (f"{key}.{name}" if key else name) + "[]" * is_list
        for member in configs:
            value = getattr(default, name)
            tag = f": !{member.__name__}" if len(configs) > 1 else ""
            out += _sections(member, value if type(value) is member else member(), path,
                             f"`{path}{tag}` ({member.__name__}{within})",
                             within or (f", in !{member.__name__}" if tag else ""))
    return out


def _scenario_page(named: dict) -> tuple[str, dict]:
    bounds, unmapped = _bounds(named)
    rows, seen, parts, count = _source_rows(), set(), [], 0
    sections = _sections(Scenario, Scenario())
    anchors = {(key, cls): _slug(title, seen) for title, cls, _, key in sections}
    for title, cls, default, key in sections:
        comments = _comments(cls) if "__dataclass_fields__" in vars(cls) else {}
        table = [_row(cls, default, key, name, hint, comments.get(name, ("", False, [name])),
                      bounds.get(((f"{key}." if key else "") + name, cls.__name__), {}),
                      rows, anchors) for name, hint in field_types(cls).items()]
        count += len(table)
        parts.append(f"## {title}\n\n{_cell(_doc(cls))}\n\n" + (
            _table(_HEADER, table) if table else
            f"No fields: the tag alone selects it (`{key}: !{cls.__name__} {{}}`)."))
    return (_banner("capsule_drake/scenario.py and the config dataclasses it holds",
                    "Scenario fields")
            + "Every key a scenario file may set, a section per config in the scenario's "
            "order. A union's members are chosen by YAML tag (`epm: {mount: !Arm {}}`; an "
            "untagged mapping is the first member); an optional block is absent when null, "
            "and its section gives the defaults of `{}`. Unit 1: a plain number. Bounds: the "
            "ranges checked at load (any other number need only be finite). Source: the "
            "status in [sources.md](../sources.md) (V: checked in a primary source, S: "
            "secondary, U: assumption, M: measured here, DS: datasheet) and its section, or "
            "the status the field's comment gives.\n\n" + "\n\n".join(parts)
            + ("\n\nRange checks naming no field: " + ", ".join(f"`{k}`" for k in unmapped)
               + "." if unmapped else "") + "\n"), {"fields": count}


# --- reference/scenarios.md ---------------------------------------------------------------

def _scenarios_page(named: dict) -> tuple[str, dict]:
    text = DEFAULT_SCENARIO_FILE.read_text()
    document, lines, parts = parse_yaml(text, str(DEFAULT_SCENARIO_FILE)), text.splitlines(), []
    for name, scenario in named.items():
        at = next(i for i, line in enumerate(lines) if line.startswith(f"{name}:"))
        comment, changes = [], []
        while at > 0 and lines[at - 1].startswith("#"):
            at -= 1
            comment.insert(0, lines[at].lstrip("#").strip())

        def flatten(node, key, depth):
            for k, v in (node or {}).items():
                if isinstance(v, dict) and not isinstance(v, schema._Tagged) and v and depth < 2:
                    flatten(v, f"{key}{k}.", depth + 1)
                else:
                    changes.append([f"`{key}{k}`", f"`{_flow(v)}`"])
        flatten(document[name], "", 0)
        held = ", ".join(f"[`{b}`](blocks.md#{_slug(f'`{b}`', set())})"
                         for b in station_blocks(scenario))
        parts.append(f"## {name}\n\n{_cell(' '.join(comment))}\n\nBlocks: {held}.\n\n"
                     + (_table(["Key", "Value"], changes) if changes else "The defaults."))
    return (_banner("diagrams/default.yaml", "Named scenarios") + "The scenarios of "
            "diagrams/default.yaml (`capsule-sim run --scenario NAME`), each with the keys "
            "it sets ([scenario fields](scenario.md)) and the [blocks](blocks.md) its station "
            "holds.\n\n" + "\n\n".join(parts) + "\n"), {"scenarios": len(named)}


# --- reference/blocks.md ------------------------------------------------------------------

def _port(port) -> str:
    if port.get_data_type() == PortDataType.kVectorValued:
        return str(port.size())
    return re.sub(r"^Value\[(.*)\]$", r"\1", pretty_class_name(type(port.Allocate())))


def _station(scenario) -> tuple[dict, dict]:
    """({block: {system: (type, inputs, outputs)}}, {(port, direction): (size or type,
    block)}) of a station built for `scenario`; a port's block is the one whose add or
    models exported it (read on the call stack of `parts.export`)."""
    codes = {f.__code__: item.name for item in blocks.all_blocks()
             for f in (item.add, item.models) if f is not None}
    exporter, original, systems_of = {}, (StationParts.export, StationParts.export_input), {}

    def noting(method):
        def export(self, port, name):
            frame = inspect.currentframe()
            while frame is not None and frame.f_code not in codes:
                frame = frame.f_back
            exporter[name] = codes[frame.f_code] if frame is not None else ""
            return method(self, port, name)
        return export

    StationParts.export, StationParts.export_input = map(noting, original)
    try:
        station = make_station(scenario, systems_of=systems_of)
    finally:
        StationParts.export, StationParts.export_input = original
    try:
        block_of, systems = {s: b for b, names in systems_of.items() for s in names}, {}
        for system in station.GetSystems():
            systems.setdefault(block_of[system.get_name()], {})[system.get_name()] = (
                pretty_class_name(type(system)),
                *([(p.get_name(), _port(p)) for p in map(get, range(count()))] for get, count in
                  ((system.get_input_port, system.num_input_ports),
                   (system.get_output_port, system.num_output_ports))))
        ports = {(p.get_name(), direction): (_port(p), exporter.get(p.get_name(), ""))
                 for direction, get, count in (
                     ("output", station.get_output_port, station.num_output_ports),
                     ("input", station.get_input_port, station.num_input_ports))
                 for p in map(get, range(count()))}
        return systems, ports
    finally:
        close_render_worker(station)


def _listed(ports: dict) -> str:
    return ", ".join(f"`{p}` ({', '.join(sizes)})" for p, sizes in ports.items()) or "—"


def _blocks_page(named: dict) -> tuple[str, dict]:
    built, skipped, held = {}, {}, set()
    for name in sorted(named, key=lambda n: n in COSTLY):
        pairs = {(b.name, type(c)) for b, c in blocks.present(STATION_BLOCKS, named[name])}
        if name in COSTLY and pairs <= held:
            skipped[name] = sorted(b for b, _ in pairs)
        else:
            built[name], held = _station(named[name]), held | pairs
    parts, exports = [], {}
    for block in STATION_BLOCKS:
        lines = [f"## `{block}`\n"]
        for item in blocks.registered(block):
            what = (f"config `{item.config_type.__name__}` at `{item.key}`" if item.key
                    else "in every station, given the whole scenario")
            hooks = ", ".join(f"`{f.__module__}.{f.__name__}`" for f in (item.models, item.add)
                              if f is not None)
            holding = [n for n, s in named.items()
                       if any(b is item for b, _ in blocks.present(STATION_BLOCKS, s))]
            held_by = ("every named scenario" if len(holding) == len(named) else
                       ", ".join(holding) or "no named scenario")
            lines.append(f"- {what}: {hooks}. {_cell(_doc(item.add or item.models))} "
                         f"Held by: {held_by}.")
        lines.append("")
        rows = {}
        for name, (systems, _) in built.items():
            for system, (kind, *ports) in systems.get(block, {}).items():
                row = rows.setdefault(system, [f"`{system}`", kind, {}, {}, []])
                for listed, seen in zip(ports, row[2:4]):
                    for port, size in listed:
                        seen.setdefault(port, {})[size] = None
                row[4].append(name)
        lines.append(_table(["System", "Type", "Inputs", "Outputs", "In the stations of"],
                            [[s, k, _listed(i), _listed(o), ", ".join(n)]
                             for s, k, i, o, n in rows.values()]) if rows else
                     "Adds no system to the stations built" + (
                         " (it draws only in a station built with a Meshcat)."
                         if block == "meshcat" else ": models, geometry or contact only."))
        parts.append("\n".join(lines))
    for name, (_, ports) in built.items():
        for (port, direction), (size, block) in ports.items():
            sizes, names = exports.setdefault((port, direction, block), ({}, []))
            sizes[size] = None
            names.append(name)
    table = _table(["Port", "Direction", "Size or type", "Exported by block",
                    "In the stations of"],
                   [[f"`{p}`", d, ", ".join(s), f"`{b}`", ", ".join(n)]
                    for (p, d, b), (s, n) in exports.items()])
    note = "".join(f" {n} was not built: its blocks ({', '.join(b)}), of their config types, "
                   "are all in the stations built." for n, b in skipped.items())
    return (_banner("STATION_BLOCKS of capsule_drake/scenario.py, the registry of "
                    "capsule_drake/blocks.py, stations built by capsule_drake/station.py",
                    "Blocks and ports")
            + "The station's blocks in the order they are checked and added, and the systems "
            "each adds with their ports (a vector port: its size; an abstract one: its type), "
            f"read on the stations of the named scenarios ({', '.join(built)}).{note}\n\n"
            + "\n\n".join(parts) + "\n\n## Exported ports\n\nThe station's ports, by the name "
            "a block exports them as (`parts.export`).\n\n" + table + "\n"), {
        "blocks": len(STATION_BLOCKS), "ports": len({p for p, _, _ in exports})}


# --- reference/cli.md ---------------------------------------------------------------------

def _cli_page(named=None) -> tuple[str, dict]:
    parser = _parser()
    verbs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    helps, parts, count = {a.dest: a.help for a in verbs._choices_actions}, [], 0
    for verb, sub in verbs.choices.items():
        rows = []
        for action in sub._actions:
            if action.help == argparse.SUPPRESS or isinstance(action, argparse._HelpAction):
                continue
            count += bool(action.option_strings)
            values = {**vars(action), "prog": sub.prog}
            if action.choices is not None:
                values["choices"] = ", ".join(map(str, action.choices))
            default = action.default
            if isinstance(default, Path) and default.is_relative_to(REPO_ROOT):
                default = default.relative_to(REPO_ROOT)
            rows.append([
                ", ".join(f"`{o}`" for o in action.option_strings)
                or f"`{action.dest}` (positional)",
                "—" if action.nargs == 0 else "one of " + ", ".join(
                    f"`{c}`" for c in action.choices) if action.choices
                else f"`{action.metavar or action.dest.upper()}`",
                "—" if default in (None, False, argparse.SUPPRESS) or action.nargs == 0
                else f"`{_flow(default) if default == '' else default}`",
                (action.help or "") % values])
        parts.append(f"## `capsule-sim {verb}`\n\n{_cell(sub.description or helps.get(verb))}"
                     "\n\n" + _table(["Flag", "Argument", "Default", "Help"], rows))
    return (_banner("the argparse parser of capsule_drake/app/cli_parser.py",
                    "The `capsule-sim` command") + f"{_cell(parser.description)} Every verb "
            "also takes `-h`, `--help`.\n\n" + "\n\n".join(parts) + "\n"), {"flags": count}


# --- reference/benchmark.md ---------------------------------------------------------------

def _benchmark_page(named=None) -> tuple[str, dict]:
    def table(docs):
        return _table(["Column", "Unit", "What it is"], [
            [f"`{column}`", *re.fullmatch(r"(.*) \(([^()]*)\)", doc, re.S).groups()[::-1]]
            for column, doc in docs.items()])
    return (_banner("COLUMN_DOCS of capsule_drake/app/benchmark/task.py, SUMMARY_COLUMN_DOCS "
                    "of capsule_drake/app/benchmark/tables.py", "Benchmark columns")
            + "`capsule-sim benchmark` writes a row per run to runs.csv and a row per "
            "navigator to summary.csv. Unit 1: a plain number or fraction.\n\n## runs.csv\n\n"
            + table(COLUMN_DOCS) + "\n\n## summary.csv\n\n" + table(SUMMARY_COLUMN_DOCS)
            + "\n"), {"columns": len(COLUMN_DOCS) + len(SUMMARY_COLUMN_DOCS)}


# --- the pages ----------------------------------------------------------------------------

PAGES = {"reference/scenario.md": _scenario_page, "reference/scenarios.md": _scenarios_page,
         "reference/blocks.md": _blocks_page, "reference/cli.md": _cli_page,
         "reference/benchmark.md": _benchmark_page}
"""Each page (its path under docs/) and what writes it, given the named scenarios; only
blocks.md builds stations (~30 s)."""


def _build(only=None) -> tuple[dict[str, str], dict[str, int]]:
    named = {name: load_scenario(name=name) for name in scenario_names(DEFAULT_SCENARIO_FILE)}
    pages, counts = {}, {}
    for path, page in PAGES.items():
        if only is None or path in only:
            pages[path], count = page(named)
            counts.update(count)
    return pages, counts


def reference_pages(only=None) -> dict[str, str]:
    """{page path (under docs/): Markdown} of the Reference pages (PAGES; `only`: these)."""
    return _build(only)[0]


def write_reference(out_dir: Path, pages: dict[str, str] | None = None) -> list[Path]:
    """Writes the Reference pages (`pages`, by default all) under `out_dir` (e.g. docs/)."""
    paths = []
    for name, text in (reference_pages() if pages is None else pages).items():
        paths.append(Path(out_dir) / name)
        paths[-1].parent.mkdir(parents=True, exist_ok=True)
        paths[-1].write_text(text)
    return paths


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m capsule_drake.app.reference",
                                     description="Write the documentation's Reference pages.")
    parser.add_argument("out_dir", type=Path, help="folder to write reference/*.md under (docs)")
    out_dir = parser.parse_args(argv).out_dir
    pages, counts = _build()
    paths = write_reference(out_dir, pages)
    print(f"wrote {len(paths)} pages under {out_dir}: "
          + ", ".join(f"{n} {what}" for what, n in counts.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
