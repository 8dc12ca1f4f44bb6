"""The documentation site's parts that are made from the code: `capsule-sim docs` (the
command it hands to MkDocs, and one line when MkDocs is missing), the results pages' tables
made from the benchmark's result files (against a Wilson interval computed here and the
rows read here), and the diagram's picture (every wire and exported port of a built
station drawn, no two boxes on top of each other). The strict build itself runs in
`.ci/run` (`./capsule-sim docs --build`), as a user builds it."""

import csv
import math
import re
import sys
import tomllib
from pathlib import Path

import pytest

from capsule_drake.app.benchmark import result_tables

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted((ROOT / "docs").rglob("*.md"))


def test_the_docs_verb_builds_strictly_or_serves_on_the_loopback(monkeypatch, tmp_path):
    from capsule_drake.app import cli
    from capsule_drake.app.commands import docs
    started = []
    monkeypatch.setattr(docs.importlib.util, "find_spec", lambda name: object())
    monkeypatch.setattr(docs.os, "execv", lambda path, argv: started.append(argv))
    monkeypatch.setattr(docs.os, "chdir", lambda path: None)
    assert cli.main(["docs", "--build", "--out", str(tmp_path / "site")]) == 0
    assert cli.main(["docs", "--port", "8123"]) == 0
    build, serve = started
    assert build[:4] == [sys.executable, "-m", "mkdocs", "build"] and "--strict" in build
    assert build[build.index("--config-file") + 1] == str(ROOT / "mkdocs.yml")
    assert build[build.index("--site-dir") + 1] == str(tmp_path / "site")
    assert serve[3] == "serve" and "--strict" in serve
    assert serve[serve.index("--dev-addr") + 1] == "127.0.0.1:8123"


def test_without_mkdocs_the_docs_verb_says_how_to_install_it(monkeypatch, capsys):
    from capsule_drake.app import cli
    from capsule_drake.app.commands import docs
    monkeypatch.setattr(docs.importlib.util, "find_spec", lambda name: None)
    monkeypatch.setattr(docs.os, "execv", lambda *a: pytest.fail("nothing to start"))
    assert cli.main(["docs"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install -e '.[docs]'" in err, err
    with open(ROOT / "pyproject.toml", "rb") as f:
        extra = tomllib.load(f)["project"]["optional-dependencies"]["docs"]
    assert {re.split(r"[<>=\[ ]", r)[0] for r in extra} >= {"mkdocs", "mkdocs-material",
                                                            "mkdocs-jupyter"}
    # ... and the command that sets up .venv installs it for this verb.
    assert "[test,docs]" in (ROOT / "capsule-sim").read_text()


def _write_runs(path: Path, rows):
    columns = ["navigator", "seed", "colon_cm", "patient", "reached_cecum", "time_to_cecum_s",
               "progress", "progress_cm", "stuck_in", "wall_contact_s", "peak_contact_force_N",
               "peak_contact_pressure_kPa", "coverage", "sim_time_s", "status"]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({c: row.get(c, "") for c in columns})


def _wilson(k: int, n: int, z: float = 1.959964):
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return centre - half, centre + half


def test_a_results_table_is_made_from_its_file_in_place_of_what_was_typed(tmp_path):
    runs = tmp_path / "runs.csv"
    common = dict(navigator="autonomy-truth", colon_cm=150, patient="", progress=1.0,
                  wall_contact_s=10, peak_contact_force_N=0.5, peak_contact_pressure_kPa=20,
                  coverage=0.8, sim_time_s=100, status="finished")
    _write_runs(runs, [
        {**common, "seed": 0, "reached_cecum": True, "time_to_cecum_s": 100, "progress_cm": 150},
        {**common, "seed": 1, "reached_cecum": True, "time_to_cecum_s": 200, "progress_cm": 150,
         "wall_contact_s": 30},
        {**common, "seed": 2, "reached_cecum": False, "time_to_cecum_s": "nan",
         "progress_cm": 80, "stuck_in": "transverse"},
        {**common, "seed": 3, "status": "failed"}])
    page = ("Before.\n\n<!-- results-table: runs.csv -->\n| typed | table |\n|---|---|\n"
            "| 9/9 | wrong |\n\n<!-- results-stops: runs.csv -->\n- a stale line\n\nAfter.\n")
    made = result_tables.expand(page, tmp_path)
    assert "wrong" not in made and "stale" not in made and made.endswith("After.\n")
    header, rule, row = [line for line in made.splitlines() if line.startswith("|")]
    cells = dict(zip([c.strip() for c in header.strip("|").split("|")],
                     [c.strip() for c in row.strip("|").split("|")]))
    low, high = _wilson(2, 3)
    assert cells["cecum"] == "2/3" and cells["runs"] == "3"      # the failed run left out
    assert cells["95 % interval"] == f"{low:.2f}-{high:.2f}"
    assert cells["time to cecum (s)"] == "150.0"                  # of the two that arrived
    assert cells["speed (mm/s)"] == f"{(1500 / 100 + 1500 / 200) / 2:.1f}"
    assert cells["wall contact (s)"] == f"{(10 + 30 + 10) / 3:.1f}"
    assert "- autonomy-truth seed 2 (150 cm): 80 cm in, transverse" in made


def test_every_results_marker_names_files_that_are_there_and_nothing_typed_follows():
    """A results page holds the marker only: the table is made at build time, so a figure
    typed after it would be a second copy that can drift."""
    markers = 0
    for page in PAGES:
        lines = page.read_text().splitlines()
        for k, line in enumerate(lines):
            match = result_tables.MARKER.match(line.strip())
            if not match:
                continue
            markers += 1
            for name in result_tables.parse(match.group(2))[0]:
                assert (ROOT / name).is_file(), f"{page}:{k + 1}: no {name}"
            following = next((x for x in lines[k + 1:] if x.strip()), "")
            assert not following.startswith(("|", "- ")), (
                f"{page}:{k + 1}: a typed table or list after the marker")
            assert result_tables.block(match.group(1), match.group(2), ROOT)


@pytest.mark.slow
def test_the_diagram_picture_draws_every_wire_and_exported_port_of_a_built_station(tmp_path):
    from capsule_drake.app.diagram_picture import draw, station_graph
    from capsule_drake.scenario import load_scenario
    from capsule_drake.station import make_station
    systems_of = {}
    station = make_station(load_scenario(name="WithSensors"), systems_of=systems_of)
    graph = station_graph(station, systems_of)
    assert len(graph.wires) == len(station.connection_map())
    assert len(graph.boxes) == len(station.GetSystems())
    exported = sorted(graph.exported.values())
    assert exported == sorted([station.get_output_port(k).get_name()
                               for k in range(station.num_output_ports())]
                              + [station.get_input_port(k).get_name()
                                 for k in range(station.num_input_ports())])
    for a, out, b, inp in graph.wires:       # each end drawn on its box
        assert out in graph.boxes[a].outputs and inp in graph.boxes[b].inputs
    assert systems_of["capsule.imu"] == ["capsule.imu"]
    assert graph.boxes["capsule.imu"].block == "capsule.imu"
    path = draw(graph, tmp_path / "diagram.svg")
    assert path.stat().st_size > 10_000 and "<svg" in path.read_text()[:500]
    boxes = list(graph.boxes.values())
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            apart = (a.x + a.width <= b.x or b.x + b.width <= a.x
                     or a.y + a.height <= b.y or b.y + b.height <= a.y)
            assert apart, f"{a.name} and {b.name} overlap"
