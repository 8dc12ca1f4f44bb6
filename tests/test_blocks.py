"""The station is its registered blocks (blocks.py, station.py): every system of a built
station belongs to one, blocks reach each other only by the station's names, and the EPM's
start is decided in one place."""

import ast
import inspect
import textwrap

import numpy as np
import pytest

from capsule_drake import blocks
from capsule_drake.anatomy import load_colon
from capsule_drake.app.run import close_render_worker
from capsule_drake.epm.paths import (AlongColon, External, HoldAbove, epm_start,
                                     path_trajectory, start_over_capsule)
from capsule_drake.scenario import EpmConfig, load_scenario
from capsule_drake.station import make_station
from capsule_drake.scenario import STATION_BLOCKS, station_blocks


def test_every_registered_block_has_its_place_in_the_station_order():
    names = {item.name for item in blocks.all_blocks()}
    assert names == set(STATION_BLOCKS)
    assert len(STATION_BLOCKS) == len(set(STATION_BLOCKS))
    for item in blocks.all_blocks():
        assert item.add is not None or item.models is not None, item.name


def _functions_given_parts(module):
    """The functions (and methods) of `module` that take the station's `parts`: what a
    block runs when the station is built."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(module)))
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef) and any(a.arg == "parts" for a in node.args.args):
            yield node


def test_blocks_reach_each_other_only_through_the_station_names():
    modules = {inspect.getmodule(f) for item in blocks.all_blocks()
               for f in (item.add, item.models, item.check) if f is not None}
    assert len(modules) >= 15
    seen = 0
    for module in modules:
        for function in _functions_given_parts(module):
            seen += 1
            for node in ast.walk(function):
                if isinstance(node, ast.Attribute):
                    assert node.attr not in ("GetSubsystemByName", "ExportOutput"), (
                        f"{module.__name__}.{function.name} calls {node.attr}: a block "
                        "connects by parts.output(name) and exports by parts.export")
    assert seen >= 25


def test_the_application_reads_the_station_by_its_ports_and_shared_values_only():
    """The app layer (app/) never looks a system up by name: it connects to the station's
    exported ports and reads its build-time values (station.py `station_value`), and keeps
    the systems it adds itself."""
    import pathlib

    import capsule_drake.app as app
    files = sorted(pathlib.Path(app.__file__).parent.rglob("*.py"))
    assert len(files) >= 30
    for path in files:
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute):
                assert node.attr not in ("GetSubsystemByName", "HasSubsystemNamed"), (
                    f"{path.name}:{node.lineno} calls {node.attr}: use the station's ports "
                    "or station_value")


def test_a_built_station_carries_the_values_its_blocks_shared():
    from capsule_drake.station import station_value
    station = make_station(load_scenario(name="WithSensors"))
    try:
        plant = station_value(station, "scene.plant")
        assert plant.HasBodyNamed("capsule")
        lens = station_value(station, "capsule.camera.lens")
        assert lens.width > 0 and station_value(station, "capsule.camera.tick") > 0
        assert callable(station_value(station, "capsule.lumen.truth_at"))
        assert station_value(station, "teleop.device.address", None) is None
        with pytest.raises(KeyError, match="shared no 'no.such'"):
            station_value(station, "no.such")
    finally:
        close_render_worker(station)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["OneOfEverything", "OneOfEverythingElse"])
def test_every_system_of_a_station_belongs_to_one_registered_block(name):
    scenario = load_scenario(name=name)
    systems_of = {}
    station = make_station(scenario, systems_of=systems_of)
    try:
        assert list(systems_of) == [n for n in station_blocks(scenario) if n in systems_of]
        owned = [s for names in systems_of.values() for s in names]
        built = [s.get_name() for s in station.GetSystems()]
        assert sorted(owned) == sorted(built)
        assert {"plant", "scene_graph"} <= set(systems_of["scene"])
        assert "capsule.camera" in systems_of["capsule.camera"]
        assert any(s.startswith(("epm_", "lumen_follower", "teleop.", "navigator"))
                   for s in systems_of["epm.driver"])
    finally:
        close_render_worker(station)


def test_the_epm_starts_where_its_driver_says_from_one_place():
    scenario = load_scenario(name="Default")
    colon, _ = load_colon(scenario.colon)
    start_s = scenario.capsule.start_s
    magnet, clearance = scenario.epm.magnet, scenario.epm.clearance
    # A path driver starts where its trajectory begins ...
    for path in (AlongColon(), AlongColon(lead=0.03), HoldAbove(height=0.3)):
        trajectory = path_trajectory(path, colon, start_s, magnet, clearance)
        q0 = epm_start(EpmConfig(magnet=magnet, clearance=clearance, driver=path),
                       colon, start_s)
        np.testing.assert_array_equal(q0, trajectory.value(trajectory.start_time()).ravel())
    # ... every other driver over the capsule's start, as low as the clearance allows.
    q0 = epm_start(EpmConfig(magnet=magnet, clearance=clearance, driver=External()),
                   colon, start_s)
    np.testing.assert_array_equal(q0, start_over_capsule(colon, start_s, magnet, clearance))
    np.testing.assert_allclose(q0[:2], colon.centerline.point_at(start_s)[:2], atol=1e-12)
