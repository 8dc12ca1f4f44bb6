"""The navigation benchmark: seeded random colons x navigators, one table.

A run puts the capsule in the rectum of one seeded random colon (`colon.seed`) and lets one
navigator drive the EPM for up to `duration` simulated seconds, stopping early when the
capsule reaches the cecum (its centreline station within `CECUM_MARGIN` of the end). The
suite runs in parallel processes on this machine (`engine="local"`) or on a Dask cluster
(`engine="dask"`: a local cluster of `workers` processes, or an existing scheduler's
address), with a progress line, and gives the same table for the same seeds either way.

Navigators:
- "autonomy-truth", "autonomy-detected": the lumen follower (navigation/autonomy.py),
  steering from the lumen truth or from the lumen tracker on the camera's frames;
- "teleop-guided", "teleop-unguided": the simulated operator at the haptic device
  (teleop/), with and without the pseudo-force on the hand (the `Teleop` scenario);
- "package.module:function": a user's navigator (the plug-in interface below).

Plug-in interface. `function(context: NavigatorContext) -> LeafSystem`. The system needs an
output port `epm_command` ([p_WE (3), m_hat_W (3)]: the EPM's centre and unit moment
direction, world frame), and may have any of these input ports, connected by name:
`capsule_state` (13: quaternion wxyz, position, angular and linear velocity; ground truth),
`epm_pose` (6), `rgb_image` and `frame_info` (the camera's), `lumen_ray`, `lumen_visible`,
`lumen_confidence` (the lumen tracker's; the tracker is switched on when asked for), and
`lumen_truth_ray`, `lumen_truth_visible` (the lumen truth, as a ray in the camera frame). A
user's lumen detector plugs into the tracker instead: `capsule: {lumen_tracker: {detector:
"package.module:function"}}` in the scenario text (see vision/lumen.py `load_detector`).
"""

from __future__ import annotations

import concurrent.futures
import csv
import dataclasses
import json
import multiprocessing
import time
from pathlib import Path

import numpy as np

from capsule_drake.plugins import load_function
from capsule_drake.scenario import layered

BUILT_IN = ("autonomy-truth", "autonomy-detected", "teleop-guided", "teleop-unguided")
# A run reaches the cecum when the capsule's centreline station is this close to the end (m).
CECUM_MARGIN = 0.04
# Contact counts as wall contact above this load (N).
CONTACT_THRESHOLD = 0.05
PLUGIN_INPUTS = ("capsule_state", "epm_pose", "rgb_image", "frame_info", "lumen_ray",
                 "lumen_visible", "lumen_confidence", "lumen_truth_ray",
                 "lumen_truth_visible")
# The columns of the table, CSV and summary (per run; the summary averages or counts them).
COLUMNS = ("navigator", "seed", "reached_cecum", "time_to_cecum_s", "progress",
           "progress_cm", "stuck_in", "wall_contact_s", "peak_contact_force_N",
           "centring_error_deg", "epm_path_m", "coverage", "sim_time_s", "wall_time_s")


@dataclasses.dataclass(frozen=True)
class Task:
    """One run: a navigator on a seeded colon."""

    navigator: str
    seed: int
    duration: float = 600.0
    # The scenario the autonomous and user navigators start from, and text laid over it
    # (YAML); teleop navigators use `Teleop` with the same text.
    scenario: str = "Navigation"
    scenario_text: str = ""
    log_period: float = 0.1


@dataclasses.dataclass
class NavigatorContext:
    """What a user's navigator factory is given.

    scenario: the run's Scenario. colon_length: the colon's centreline length (m; the goal
    is its end: the navigator is not given the centreline itself). lens: the camera's Lens
    (None without a camera). X_BC: the camera's pose in the capsule body. floor_height:
    function (x, y, m_hat) -> the lowest EPM centre height the clearance allows.
    start_command: the EPM's pose at the start, [p_WE, m_hat_W].
    """

    scenario: object
    colon_length: float
    lens: object
    X_BC: object
    floor_height: object
    start_command: np.ndarray


def load_navigator(name: str):
    """The factory of a user's navigator "package.module:function"; ValueError (one line)
    when it cannot be found."""
    return load_function("navigator", name, f"one of {', '.join(BUILT_IN)}")


def task_scenario(task: Task):
    """The Scenario of a task (its colon seed, duration and navigator's needs)."""
    import yaml

    from capsule_drake.scenario import load_scenario

    extra = yaml.safe_load(task.scenario_text) or {}
    if not isinstance(extra, dict):
        raise ValueError("benchmark scenario text must be a YAML mapping")
    override = layered(extra, {"duration": task.duration, "colon": {"seed": task.seed}})
    name = task.scenario
    if task.navigator.startswith("teleop-"):
        name = "Teleop"
        if task.navigator == "teleop-unguided":
            override["pseudo_force"] = None
    elif task.navigator == "autonomy-detected":
        override = layered({"capsule": {"lumen_tracker": {}}}, override)
    return load_scenario(name=name, override=yaml.safe_dump(override, default_flow_style=True))


def _connect_navigator(builder, station, scenario, navigator_name, colon):
    """Adds the navigator of a task to `builder` and connects it; returns it."""
    if navigator_name in ("autonomy-truth", "autonomy-detected"):
        from capsule_drake.navigation.autonomy import LumenFollowerConfig, add_lumen_follower
        lumen = "truth" if navigator_name == "autonomy-truth" else "detected"
        return add_lumen_follower(builder, station, scenario, LumenFollowerConfig(), lumen)
    factory = load_navigator(navigator_name)
    context = _navigator_context(station, scenario, colon)
    system = builder.AddNamedSystem("navigator", factory(context))
    sources = {
        "capsule_state": "capsule.state", "epm_pose": "epm.pose",
        "rgb_image": "capsule.camera.rgb_image", "frame_info": "capsule.camera.frame_info",
        "lumen_ray": "capsule.lumen_tracker.lumen_ray",
        "lumen_visible": "capsule.lumen_tracker.lumen_visible",
        "lumen_confidence": "capsule.lumen_tracker.lumen_confidence",
    }
    truth = None
    for i in range(system.num_input_ports()):
        port = system.get_input_port(i)
        name = port.get_name()
        if name not in PLUGIN_INPUTS:
            raise ValueError(f"navigator {navigator_name!r}: input port {name!r} is not one "
                             f"of {', '.join(PLUGIN_INPUTS)}")
        if name.startswith("lumen_truth_"):
            if truth is None:
                truth = _add_truth_ray(builder, station, scenario, navigator_name)
            builder.Connect(truth.GetOutputPort(name.removeprefix("lumen_truth_")), port)
            continue
        if not station.HasOutputPort(sources[name]):
            raise ValueError(f"navigator {navigator_name!r}: input {name!r} needs "
                             f"{sources[name]!r}, which this scenario does not have (switch "
                             "on the camera or the lumen tracker)")
        builder.Connect(station.GetOutputPort(sources[name]), port)
    if not system.HasOutputPort("epm_command"):
        raise ValueError(f"navigator {navigator_name!r} has no output port 'epm_command'")
    builder.Connect(system.GetOutputPort("epm_command"), station.GetInputPort("epm.command"))
    return system


def _add_truth_ray(builder, station, scenario, navigator_name):
    from capsule_drake.teleop.operator import LumenRayFromTruth
    if not station.HasOutputPort("capsule.lumen.lumen_pixel"):
        raise ValueError(f"navigator {navigator_name!r}: the lumen truth needs the camera")
    camera = station.GetSubsystemByName("capsule.camera")
    truth = builder.AddNamedSystem("lumen_truth_ray", LumenRayFromTruth(camera.lens))
    builder.Connect(station.GetOutputPort("capsule.lumen.lumen_pixel"),
                    truth.GetInputPort("pixel"))
    builder.Connect(station.GetOutputPort("capsule.lumen.lumen_visible"),
                    truth.GetInputPort("visible"))
    return truth


def _navigator_context(station, scenario, colon) -> NavigatorContext:
    from capsule_drake.epm.poses import epm_pose_over
    from capsule_drake.epm.arm import EpmGuard

    plant = station.GetSubsystemByName("plant")
    capsule = plant.GetModelInstanceByName("capsule")
    X_BC = plant.GetFrameByName("camera", capsule).GetFixedPoseInBodyFrame()
    lens = (station.GetSubsystemByName("capsule.camera").lens
            if station.HasOutputPort("capsule.camera.rgb_image") else None)
    guard = EpmGuard(colon.abdomen, scenario.epm.magnet, scenario.epm.clearance,
                     np.zeros(3), np.inf)
    p, m = epm_pose_over(colon, scenario.capsule.start_s, scenario.epm.clearance,
                         scenario.epm.magnet)
    return NavigatorContext(scenario, colon.centerline.length, lens, X_BC,
                            guard.lowest_centre_height, np.concatenate([p, m]))


def run_task(task: Task) -> dict:
    """Simulates one task; returns its row (COLUMNS) and its progress curve."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder, EventStatus
    from pydrake.systems.primitives import LogVectorOutput

    from capsule_drake.navigation.coverage import MucosaCoverage
    from capsule_drake.station import colon_for, make_station
    from capsule_drake.physics.contact_monitor import ContactMonitor

    scenario = task_scenario(task)
    colon = colon_for(scenario)
    builder = DiagramBuilder()
    teleop = task.navigator.startswith("teleop-")
    station = builder.AddNamedSystem("station", make_station(
        scenario, external_epm_command=not teleop))
    if not teleop:
        _connect_navigator(builder, station, scenario, task.navigator, colon)
    monitor = builder.AddNamedSystem("contact", ContactMonitor())
    builder.Connect(station.GetOutputPort("contact_results"), monitor.get_input_port())
    period = task.log_period
    logs = {"state": LogVectorOutput(station.GetOutputPort("capsule.state"), builder, period),
            "epm": LogVectorOutput(station.GetOutputPort("epm.pose"), builder, period),
            "load": LogVectorOutput(monitor.GetOutputPort("contact_load"), builder, period)}
    camera = None
    if station.HasOutputPort("capsule.camera.rgb_image"):
        camera = station.GetSubsystemByName("capsule.camera")
        coverage = builder.AddNamedSystem("coverage", MucosaCoverage(
            colon, camera.lens, scenario.capsule.camera.far))
        for name in ("depth_image", "frame_info", "frame_pose"):
            builder.Connect(station.GetOutputPort(f"capsule.camera.{name}"),
                            coverage.GetInputPort(name))
        logs["coverage"] = LogVectorOutput(coverage.GetOutputPort("coverage"), builder, 1.0)
        for name in ("lumen_pixel", "lumen_visible"):
            logs[name] = LogVectorOutput(station.GetOutputPort(f"capsule.lumen.{name}"),
                                         builder, period)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    length = colon.centerline.length
    last_check = [-np.inf]

    def at_cecum(root_context):
        t = root_context.get_time()
        if t - last_check[0] < 0.5:
            return EventStatus.DidNothing()
        last_check[0] = t
        state = station.GetOutputPort("capsule.state").Eval(
            station.GetMyContextFromRoot(root_context))
        s = float(colon.centerline.closest(state[4:7])[0])
        if s >= length - CECUM_MARGIN:
            return EventStatus.ReachedTermination(diagram, "reached the cecum")
        return EventStatus.DidNothing()

    simulator.set_monitor(at_cecum)
    start = time.perf_counter()
    stopped = None
    try:
        simulator.Initialize()
        simulator.AdvanceTo(task.duration)
    except RuntimeError as e:  # a run that fails is a result, not the end of the suite
        stopped = f"simulation error: {str(e).splitlines()[0]}"
    finally:
        # The render worker is a process: end it with the run, not when a pool process
        # that runs the next task gets round to collecting this diagram.
        if camera is not None and camera.worker is not None:
            camera.worker.close()
    wall_time = time.perf_counter() - start
    context = simulator.get_context()
    data = {name: log.FindLog(context) for name, log in logs.items()}
    row = _metrics(task, colon, data, camera, stopped)
    row["sim_time_s"] = round(float(context.get_time()), 3)
    row["wall_time_s"] = round(wall_time, 1)
    times = data["state"].sample_times()
    s = colon.centerline.closest(data["state"].data()[4:7].T)[0]
    step = max(1, int(round(1.0 / period)))
    return {"row": row, "curve": (times[::step].tolist(), s[::step].tolist()),
            "segments": colon.centerline.segment_ranges()}


def _metrics(task, colon, data, camera, stopped) -> dict:
    length = colon.centerline.length
    times = data["state"].sample_times()
    state = data["state"].data()
    s = colon.centerline.closest(state[4:7].T)[0]
    start_s = s[0] if len(s) else 0.0
    reached = np.flatnonzero(s >= length - CECUM_MARGIN)
    furthest = float(s.max()) if len(s) else 0.0
    load = data["load"].data()[0]
    dt = np.diff(times, append=times[-1]) if len(times) else np.zeros(0)
    epm = data["epm"].data()[:3]
    centring = np.nan
    if camera is not None and "lumen_pixel" in data:
        pixel = data["lumen_pixel"].data().T
        visible = (data["lumen_visible"].data()[0] > 0.5) & np.all(np.isfinite(pixel), axis=1)
        if visible.any():
            rays = camera.lens.unproject(pixel[visible])
            angles = np.degrees(np.arccos(np.clip(rays[:, 2] / np.linalg.norm(rays, axis=1),
                                                  -1.0, 1.0)))
            centring = float(np.median(angles))
    coverage = float(data["coverage"].data()[0, -1]) if "coverage" in data and \
        data["coverage"].data().size else np.nan
    segments = colon.centerline.segment_ranges()
    stuck = "" if len(reached) else colon.centerline.segment_at(furthest)
    return {
        "navigator": task.navigator, "seed": task.seed,
        "reached_cecum": bool(len(reached)),
        "time_to_cecum_s": round(float(times[reached[0]]), 2) if len(reached) else np.nan,
        "progress": round(float((furthest - start_s) / (length - start_s)), 4),
        "progress_cm": round(float(100.0 * (furthest - start_s)), 1),
        "stuck_in": stopped or stuck,
        "wall_contact_s": round(float(np.sum(dt[load > CONTACT_THRESHOLD])), 2),
        "peak_contact_force_N": round(float(load.max()) if load.size else 0.0, 3),
        "centring_error_deg": round(centring, 1) if np.isfinite(centring) else np.nan,
        "epm_path_m": round(float(np.sum(np.linalg.norm(np.diff(epm, axis=1), axis=0))), 3),
        "coverage": round(coverage, 4) if np.isfinite(coverage) else np.nan,
        # Through each segment; the cecum, a blind end, counts when the run reached it.
        "segments_passed": [name for name, (_, end) in segments.items()
                            if furthest >= end or (name == list(segments)[-1] and len(reached))],
    }


def run_suite(tasks: list[Task], workers: int = 2, engine: str = "local",
              address: str | None = None, progress: bool = True,
              on_result=None) -> list[dict]:
    """Runs the tasks in parallel; returns their results in the tasks' order.

    engine "local": a pool of `workers` processes on this machine. "dask": a Dask cluster,
    `address` of an existing scheduler or else a local cluster of `workers` processes.
    on_result: called with each result as its run finishes (e.g. `RowWriter`), so a long
    suite that is interrupted keeps the runs it finished.
    """
    if engine not in ("local", "dask"):
        raise ValueError(f"benchmark engine {engine!r} is not 'local' or 'dask'")
    from capsule_drake.io.run import StepBar

    bar = StepBar(len(tasks), progress)
    results: list[dict | None] = [None] * len(tasks)
    if engine == "local":
        with concurrent.futures.ProcessPoolExecutor(
                max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(run_task, task): k for k, task in enumerate(tasks)}
            for future in concurrent.futures.as_completed(futures):
                k = futures[future]
                results[k] = future.result()
                if on_result is not None:
                    on_result(results[k])
                bar.step(f"{tasks[k].navigator} seed {tasks[k].seed}")
        return results
    from dask.distributed import Client, LocalCluster, as_completed
    cluster = None
    if address is None:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)
    try:
        with Client(address or cluster) as client:
            futures = client.map(run_task, tasks, pure=False)
            index = {future.key: k for k, future in enumerate(futures)}
            for future in as_completed(futures):
                k = index[future.key]
                results[k] = future.result()
                if on_result is not None:
                    on_result(results[k])
                bar.step(f"{tasks[k].navigator} seed {tasks[k].seed}")
    finally:
        if cluster is not None:
            cluster.close()
    return results


def _json_default(value):
    """numpy scalars and arrays in results as plain JSON."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


class RowWriter:
    """Appends each finished run's row to a CSV file at once (header first)."""

    def __init__(self, path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "w", newline="") as f:
            csv.DictWriter(f, fieldnames=COLUMNS).writeheader()

    def __call__(self, result: dict) -> None:
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore").writerow(result["row"])


def summary(results: list[dict]) -> list[dict]:
    """Per navigator: runs, cecal intubation rate, mean time to cecum (of those that
    reached it), mean progress, and the means of the other columns."""
    out = []
    for navigator in dict.fromkeys(r["row"]["navigator"] for r in results):
        rows = [r["row"] for r in results if r["row"]["navigator"] == navigator]

        def mean(key):
            values = np.array([row[key] for row in rows], dtype=float)
            values = values[np.isfinite(values)]
            return round(float(values.mean()), 3) if len(values) else np.nan

        out.append({"navigator": navigator, "runs": len(rows),
                    "reached_cecum": f"{sum(row['reached_cecum'] for row in rows)}/{len(rows)}",
                    "time_to_cecum_s": mean("time_to_cecum_s"), "progress": mean("progress"),
                    "wall_contact_s": mean("wall_contact_s"),
                    "peak_contact_force_N": mean("peak_contact_force_N"),
                    "centring_error_deg": mean("centring_error_deg"),
                    "epm_path_m": mean("epm_path_m"), "coverage": mean("coverage")})
    return out


def segment_table(results: list[dict]) -> list[dict]:
    """Per navigator, the share of runs that got through each colon segment."""
    names = list(results[0]["segments"])
    out = []
    for navigator in dict.fromkeys(r["row"]["navigator"] for r in results):
        rows = [r["row"] for r in results if r["row"]["navigator"] == navigator]
        out.append({"navigator": navigator, **{
            name: f"{sum(name in row['segments_passed'] for row in rows)}/{len(rows)}"
            for name in names}})
    return out


def format_table(rows: list[dict], columns) -> str:
    cells = [[str(row.get(c, "")) for c in columns] for row in rows]
    widths = [max(len(c), *(len(r[k]) for r in cells)) for k, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths))]
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths)) for r in cells]
    return "\n".join(lines)


def write_outputs(results: list[dict], out_dir: Path) -> dict[str, Path]:
    """runs.csv (one row per run), summary.csv, progress.png (progress against time) and
    segments.png (share of runs through each colon segment, per navigator)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"runs": out_dir / "runs.csv", "summary": out_dir / "summary.csv",
             "progress": out_dir / "progress.png", "segments": out_dir / "segments.png",
             "results": out_dir / "results.json"}
    # Everything the table and plots are made from (rows, progress curves, segments), so
    # they can be redrawn or analysed further without rerunning the suite.
    with open(paths["results"], "w") as f:
        json.dump(results, f, default=_json_default)
    with open(paths["runs"], "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for r in results:
            writer.writerow(r["row"])
    rows = summary(results)
    with open(paths["summary"], "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    navigators = list(dict.fromkeys(r["row"]["navigator"] for r in results))
    colours = {n: plt.cm.tab10(k % 10) for k, n in enumerate(navigators)}
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for r in results:
        t, s = r["curve"]
        navigator = r["row"]["navigator"]
        ax.plot(t, 100.0 * np.asarray(s), color=colours[navigator], lw=1.0, alpha=0.8)
    for n in navigators:
        ax.plot([], [], color=colours[n], label=n)
    ax.set_xlabel("simulated time (s)")
    ax.set_ylabel("centreline station of the capsule (cm)")
    ax.set_title("progress toward the cecum, one line per run")
    ax.legend(loc="upper left", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(paths["progress"], dpi=120)
    plt.close(fig)
    names = list(results[0]["segments"])
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / max(len(navigators), 1)
    for k, n in enumerate(navigators):
        rows = [r["row"] for r in results if r["row"]["navigator"] == n]
        share = [np.mean([name in row["segments_passed"] for row in rows]) for name in names]
        ax.bar(np.arange(len(names)) + k * width, share, width, color=colours[n], label=n)
    ax.set_xticks(np.arange(len(names)) + 0.4 - width / 2, names, rotation=20, fontsize=8)
    ax.set_ylabel("share of runs through the segment")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(paths["segments"], dpi=120)
    plt.close(fig)
    return paths
