"""What a run leaves in its folder (`simulate`, app/run.py): the folder prepared before,
the logs, metrics, the wall's pressure map and the replay written after, each whole or
not at all."""

from __future__ import annotations

import json
from pathlib import Path


from capsule_drake.app.outputs import (OutputError, check_room, run_output_bytes, save_npz,
                                       write_atomic)
from capsule_drake.app.log_spool import LogSpool
from capsule_drake.io.replay import replay_page, run_plots, wall_map_panel
from capsule_drake.io.wall_map import wall_map_png, write_wall_map
from capsule_drake.scenario import Scenario, dump_scenario
from capsule_drake.station import station_value


class WriteError(OutputError):
    """A run's outputs could not be written after the run (one line; what had been written
    as the run went stays on disk)."""


def prepare_folder(out: Path, scenario: Scenario, recording: bool) -> None:
    """Creates `out` if need be, checks it can take the run's outputs, writes scenario.yaml
    (removed again if the station cannot be built: see `simulate`)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{out}: cannot create the output folder "
                          f"({e.strerror or e})") from None
    check_room(out, run_output_bytes(scenario.duration, scenario.outputs.log_period, recording))
    try:
        write_atomic(out / "scenario.yaml", dump_scenario(scenario))
    except OSError as e:
        raise OutputError(f"{out}: cannot write scenario.yaml ({e.strerror or e})") from None


def _write_outputs(result, spool: LogSpool, meshcat, error: str | None, colon):
    """The run's outputs, each written whole or not at all; WriteError names the first
    that could not be written (what is on disk already stays)."""
    out = result.out_dir
    wall = result.wall_pressure
    steps = [("logs.npz", spool.finish),
             ("metrics.json", lambda: write_atomic(
                 out / "metrics.json", json.dumps(result.metrics, indent=2) + "\n"))]
    if wall is not None:  # the map of the wall's pressure, and its picture when it has one
        steps.append(("wall_pressure.npz", lambda: save_npz(out / "wall_pressure.npz",
                                                            wall.arrays())))
        if wall.has_pressure:
            steps.append(("wall_pressure.png", lambda: write_atomic(
                out / "wall_pressure.png",
                writer=lambda path: write_wall_map(path, wall, colon.centerline))))
    if error is not None:
        steps.append(("error.txt", lambda: write_atomic(out / "error.txt", error)))
    if meshcat is not None:
        steps.append(("recording.html", lambda: write_atomic(
            out / "recording.html", replay_html(result, meshcat, colon))))
    for name, write in steps:
        try:
            write()
        except OSError as e:
            kept = ("; the logs written during the run are in logs.parts/"
                    if (out / "logs.parts").is_dir() else "")
            raise WriteError(f"{out}: could not write {name} ({e.strerror or e}){kept}") from None


def replay_html(result, meshcat, colon) -> str:
    """recording.html: Meshcat's replay of the run with, beside it, the capsule camera's
    frames (when the station has a camera) and the run's progress and contact load
    (io/replay.py)."""
    station = result.station
    frames = station_value(station, "meshcat.replay_frames", list)() if station else []
    plots = run_plots(colon, result.times, result.capsule_state, result.contact_load)
    return replay_page(meshcat.StaticHtml(), frames, plots,
                       replay_wall_map(result.wall_pressure, colon, plots))


def replay_wall_map(wall, colon, plots) -> dict | None:
    """The replay's section of the wall's pressure map (io/replay.py `wall_map_panel`: the
    compact picture of io/wall_map.py, the capsule's track from the plot of its place along
    the colon), or None for a map without pressures."""
    if wall is None or not wall.has_pressure:
        return None
    png, boxes = wall_map_png(wall, colon.centerline, width=3.2, height=2.7, dpi=100,
                              compact=True)
    track = next((p for p in plots if p["unit"] == "cm"), {"t": [], "y": []})
    longest = wall.longest_above.get("ischaemia")
    title = (f"wall pressure per patch: peak {wall.peak.max() / 1000:.0f} kPa"
             + (f"; longest above {wall.thresholds['ischaemia'] / 1000:.1f} kPa "
                f"{longest.max():.1f} s" if longest is not None else ""))
    return wall_map_panel(png, boxes, (0.0, 100.0 * wall.grid.s_edges[-1]), track["t"],
                          track["y"], title)
