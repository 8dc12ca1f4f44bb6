"""The documentation's Reference pages (app/reference.py) list everything the code has.

The pages are generated from the code, so each is checked against a second route to the same
facts, not against the generator's own walk:
- scenario.md: every leaf key of the Default, OneOfEverything and OneOfEverythingElse
  scenarios as the run writes them (scenario.yaml, `dump_scenario`), and every field of every
  config reachable from `Scenario` by `dataclasses.fields` (walked here); a field planted in
  a config appears with its unit, default and bound (the page is driven by the code); known
  bounds and sources.md statuses sit in their fields' rows.
- blocks.md (slow: it builds stations): every block of STATION_BLOCKS, and every system and
  port of the Default and WithSensors stations as Drake enumerates them.
- cli.md (slow: a subprocess per verb): every --flag `capsule-sim <verb> --help` prints.
- benchmark.md: every column of the newest benchmarks/results/compliant_population_*.csv,
  of COLUMNS and of a summary's rows, with a description and a unit.
Every page: its first line says it is generated; its tables are whole, with no raw `<` or
unescaped `|`, and its relative links reach pages and anchors that exist (sources.md's by
Python-Markdown's toc slugify, copied here).
"""

import dataclasses
import re
import subprocess
import sys
import typing
import unicodedata
from pathlib import Path

import pytest
import yaml

from capsule_drake.app import reference
from capsule_drake.app.benchmark.tables import summary
from capsule_drake.app.benchmark.task import COLUMNS, Task, failed_result
from capsule_drake.app.run import close_render_worker
from capsule_drake.scenario import STATION_BLOCKS, Scenario, dump_scenario, load_scenario
from capsule_drake.station import make_station

REPO = Path(__file__).resolve().parents[1]
FAST_PAGES = ("reference/scenario.md", "reference/scenarios.md", "reference/cli.md",
              "reference/benchmark.md")


@pytest.fixture(scope="module")
def pages():
    """The pages that build no station."""
    return reference.reference_pages(only=FAST_PAGES)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """Every page, as write_reference writes it."""
    out = tmp_path_factory.mktemp("docs")
    paths = reference.write_reference(out)
    assert sorted(p.relative_to(out).as_posix() for p in paths) == sorted(reference.PAGES)
    return {p.relative_to(out).as_posix(): p.read_text() for p in paths}


def _cells(line: str) -> list[str]:
    """The cells of a table row: split at the pipes outside code spans and not escaped."""
    return [c.strip() for c in re.findall(r"(?:`[^`]*`|\\\||[^|`])+", line.strip().strip("|"))]


def _rows(page: str, key: str) -> list[list[str]]:
    """The table rows whose first cell is `key` (in backticks)."""
    return [_cells(line) for line in page.splitlines()
            if line.startswith("|") and _cells(line)[0] == f"`{key}`"]


def _section(page: str, heading: str) -> str:
    return next(part for part in page.split("\n## ") if part.startswith(heading))


def _leaves(node, key=""):
    """The dotted keys of a YAML document's leaves (a list of mappings: key[].field)."""
    if isinstance(node, dict):
        for name, value in node.items():
            yield from _leaves(value, f"{key}.{name}" if key else name)
    elif isinstance(node, list) and node and all(isinstance(v, dict) for v in node):
        for item in node:
            yield from _leaves(item, key + "[]")
    else:
        yield key


class _TagLoader(yaml.SafeLoader):
    pass


_TagLoader.add_multi_constructor("!", lambda loader, tag, node: loader.construct_mapping(node))


@pytest.mark.slow
def test_every_key_a_run_writes_is_in_the_scenario_reference(pages):
    page = pages["reference/scenario.md"]
    for name in ("Default", "OneOfEverything", "OneOfEverythingElse"):
        written = yaml.load(dump_scenario(load_scenario(name=name)), Loader=_TagLoader)
        keys = set(_leaves(written))
        assert len(keys) > 150, name
        missing = [key for key in keys if not _rows(page, key)]
        assert not missing, f"{name}: keys not in reference/scenario.md: {missing}"


def _config_fields(cls, key=""):
    """(dotted key, field) of every field of `cls` and of every config under it, through
    unions, optional blocks and lists (walked with dataclasses.fields and Drake's
    __fields__)."""
    if dataclasses.is_dataclass(cls):
        hints = typing.get_type_hints(cls)
        fields = [(f.name, hints[f.name]) for f in dataclasses.fields(cls)]
    else:
        fields = [(f.name, f.type) for f in cls.__fields__]
    for name, hint in fields:
        where = f"{key}.{name}" if key else name
        yield where, name
        inner = typing.get_args(hint) if typing.get_args(hint) else (hint,)
        suffix = "[]" if typing.get_origin(hint) is list else ""
        for option in inner:
            if dataclasses.is_dataclass(option) or isinstance(
                    getattr(option, "__fields__", None), tuple):
                yield from _config_fields(option, where + suffix)


@pytest.mark.slow
def test_every_field_of_every_config_is_in_the_scenario_reference(pages):
    page = pages["reference/scenario.md"]
    fields = set(_config_fields(Scenario))
    assert len(fields) > 400
    missing = [key for key, _ in fields if not _rows(page, key)]
    assert not missing, f"fields not in reference/scenario.md: {missing}"
    # Every config has its section, every union member its tag.
    for member in ("contact: !CompliantWall", "contact: !RigidWall", "epm.mount: !Arm",
                   "epm.mount: !Stage", "colon.source: !Population", "epm.driver: !Plugin",
                   "epm.driver: !External", "epm.driver: !LumenFollower"):
        assert f"## `{member}`" in page, member


def test_a_field_added_to_the_code_appears_in_the_reference(monkeypatch):
    @dataclasses.dataclass
    class Planted:
        """A block planted by the test."""

        # How far the planted probe reaches (m); an assumption.
        reach: float = 0.25
        # Its gain [-] and count, the number of probes: a group (the second field has no
        # comment of its own).
        gain: float = 1.5
        count: int = 3

    @dataclasses.dataclass
    class PlantedScenario(Scenario):
        # A block the code does not have. Null: none.
        planted: Planted | None = None

    monkeypatch.setattr(reference, "Scenario", PlantedScenario)
    page, counts = reference._scenario_page({"Default": PlantedScenario()})
    assert "## `planted` (Planted)\n\nA block planted by the test." in page
    (row,) = _rows(page, "planted.reach")
    assert row[1:7] == ["float", "`0.25`", "m", "—", "U (its comment)",
                        "How far the planted probe reaches (m); an assumption."]
    assert _rows(page, "planted.gain")[0][2:4] == ["`1.5`", "1"]
    (row,) = _rows(page, "planted.count")   # the group's comment, not the gain's unit
    assert row[2:4] == ["`3`", ""] and row[6].startswith("Its gain [-] and count, the number")
    assert _rows(page, "planted")[0][2] == "`null` (absent)"


def test_known_bounds_and_sources_sit_in_their_fields_rows(pages):
    page = pages["reference/scenario.md"]
    (backlog,) = _rows(page, "outputs.foxglove.backlog")
    assert backlog[4] == "`[16, 1000000]`"
    (wait,) = _rows(page, "outputs.foxglove.wait_for_client")
    assert wait[3] == "s" and wait[4] == "`[0, 3600]` s"
    # Checks whose key holds an index (positions[2]) or a prefix (capsule.camera: fps).
    assert _rows(page, "capsule.magnetic_array.positions")[0][4] == "`[-0.1, 0.1]` m"
    assert _rows(page, "capsule.camera.fps")[0][4].startswith("`(0, ")
    # A union's members keep their own bounds: the stage's speed and the arm's.
    speeds = {row[4] for row in _rows(page, "epm.mount.max_speed")}
    assert speeds == {"`[0.001, 1]` m/s", "`[0.001, 2]` m/s"}
    wall = _section(page, "`contact: !CompliantWall`")
    (support,) = _rows(wall, "contact.support_stiffness")
    assert support[3] == "Pa/m" and support[4] == "`[0, 1e10]` Pa/m"
    assert support[5] == "U ([3.5](../sources.md#35-the-compliant-wall-physicscontactcompliantpy))"
    assert _rows(wall, "contact.thickness")[0][5].startswith("V ([3.5](")
    assert _rows(wall, "contact.stiffening")[0][5].startswith("S ([3.5](")
    # The rigid stand-in's friction is not the compliant wall's sourced figure.
    assert _rows(_section(page, "`contact: !RigidWall`"), "contact.friction")[0][5] == ""
    assert _rows(page, "duration")[0][2:5] == ["`60.0`", "s", "`[0, 1000000]` s"]


def test_the_named_scenarios_and_their_keys_are_in_the_reference(pages):
    page = pages["reference/scenarios.md"]
    names = list(yaml.load(reference.DEFAULT_SCENARIO_FILE.read_text(), Loader=_TagLoader))
    assert len(names) >= 10
    for name in names:
        assert f"\n## {name}\n" in page, name
    far = _section(page, "FarMagnet")
    assert "The EPM waits 50 cm above the capsule's start" in far
    assert _rows(far, "epm.driver")[0][1] == "`!HoldAbove {height: 0.5}`"
    assert _rows(_section(page, "OneOfEverythingElse"), "contact")[0][1] == (
        "`!CompliantWall {thickness: 0.003, support_stiffness: 1.0e6}`")


def test_every_benchmark_column_is_described(pages):
    page = pages["reference/benchmark.md"]
    results = sorted(REPO.glob("benchmarks/results/compliant_population_*.csv"),
                     key=lambda p: (re.findall(r"\d{4}-\d\d-\d\d", p.name), p.name))
    header = results[-1].read_text().splitlines()[0].split(",")
    rows = summary([failed_result(Task("autonomy-truth", 0), "test")])
    for column in {*header, *COLUMNS, *rows[0]}:
        described = _rows(page, column)
        assert described, f"column {column} not in reference/benchmark.md"
        assert all(row[1] and len(row[2]) > 10 for row in described), described


def _help_flags(verb: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "capsule_drake.app", verb, "--help"],
                            stdout=subprocess.PIPE, text=True, cwd=REPO)


@pytest.mark.slow
def test_every_flag_of_every_verb_is_in_the_cli_reference(pages):
    page = pages["reference/cli.md"]
    top = subprocess.run([sys.executable, "-m", "capsule_drake.app", "--help"],
                         capture_output=True, text=True, cwd=REPO, check=True).stdout
    verbs = re.search(r"\{([\w,-]+)\}", top).group(1).split(",")
    assert {"run", "record", "teleop", "benchmark"} <= set(verbs)
    helps = {verb: _help_flags(verb) for verb in verbs}   # the verbs' --help side by side
    for verb, process in helps.items():
        printed = process.communicate(timeout=120)[0]
        assert process.returncode == 0, verb
        flags = set(re.findall(r"(?<![\w-])(--[a-z][\w-]*)", printed)) - {"--help"}
        section = _section(page, f"`capsule-sim {verb}`")
        in_rows = {f for line in section.splitlines() if line.startswith("| `-")
                   for f in re.findall(r"`(--[\w-]+)`", _cells(line)[0])}
        assert flags <= in_rows, f"{verb}: flags not in reference/cli.md: {flags - in_rows}"


@pytest.mark.slow
@pytest.mark.parametrize("name", ["Default", "WithSensors"])
def test_every_block_system_and_port_of_a_station_is_in_the_blocks_reference(written, name):
    page, exported = written["reference/blocks.md"].split("\n## Exported ports\n")
    for block in STATION_BLOCKS:
        assert f"\n## `{block}`\n" in page, block
    station = make_station(load_scenario(name=name))
    try:
        for system in station.GetSystems():
            (row,) = _rows(page, system.get_name())
            ports = {system.get_input_port(i).get_name() for i in range(system.num_input_ports())}
            ports |= {system.get_output_port(i).get_name()
                      for i in range(system.num_output_ports())}
            listed = set(re.findall(r"`([^`]+)` \(", row[2] + " " + row[3]))
            assert ports <= listed, (system.get_name(), ports - listed)
            assert name in row[4]
        for i in range(station.num_output_ports()):
            port = station.get_output_port(i).get_name()
            assert any(name in r[4] for r in _rows(exported, port)), port
    finally:
        close_render_worker(station)
    # A scenario not built is one whose blocks the stations built all hold.
    for skipped in re.findall(r" (\w+) was not built", page):
        assert skipped in reference.COSTLY
        held = {b for built in re.search(r"named scenarios \(([^)]*)\)", page).group(1)
                .split(", ") for b in reference.station_blocks(load_scenario(name=built))}
        assert set(reference.station_blocks(load_scenario(name=skipped))) <= held


def _slugify(value: str) -> str:
    """Python-Markdown's toc slugify (markdown/extensions/toc.py, 3.x)."""
    value = unicodedata.normalize("NFKD", value).encode("ascii", "ignore").decode("ascii")
    value = re.sub(r"[^\w\s-]", "", value).strip().lower()
    return re.sub(r"[-\s]+", "-", value)


def _anchors(text: str) -> set[str]:
    seen = set()
    for title in re.findall(r"^#{1,6}\s+(.*?)\s*$", text, re.M):
        slug = _slugify(re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", title).replace("`", ""))
        n, unique = 0, slug
        while unique in seen:
            n += 1
            unique = f"{slug}_{n}"
        seen.add(unique)
    return seen


def _check_markdown(name: str, text: str, pages: dict) -> None:
    lines = text.splitlines()
    assert lines[0].startswith("# ") and lines[2].startswith("*Generated from the code")
    assert "do not edit" in lines[2]
    width = None
    for number, line in enumerate(lines, 1):
        outside = "".join(line.split("`")[::2])
        assert "<" not in outside, f"{name}:{number}: raw <"
        if line.startswith("|"):
            cells = _cells(line)
            width = len(cells) if width is None else width
            assert len(cells) == width, f"{name}:{number}: {len(cells)} cells, not {width}"
        else:
            width = None
    for target, anchor in re.findall(r"\]\(([^)#]*)(?:#([^)]*))?\)", text):
        path = (Path(name).parent / target).as_posix() if target else name
        path = re.sub(r"[^/]+/\.\./", "", path)
        body = (REPO / "docs" / path).read_text() if path == "sources.md" else pages.get(path)
        assert body is not None, f"{name}: link to {target}: no such page"
        assert not anchor or not body or anchor in _anchors(body), (    # "": not built here
            f"{name}: no anchor #{anchor} in {path}")


def test_the_pages_are_whole_markdown_with_working_links(pages):
    for name, text in pages.items():
        _check_markdown(name, text, {**pages, "reference/blocks.md": ""})


@pytest.mark.slow
def test_every_page_written_is_whole_markdown_with_working_links(written):
    for name, text in written.items():
        _check_markdown(name, text, written)
