"""Simulate a built station: logging, pacing, progress, and the run's output folder."""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydrake.common import RandomGenerator
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator, SimulatorStatus
from pydrake.systems.framework import DiagramBuilder, EventStatus
from pydrake.systems.primitives import LogVectorOutput

from capsule_drake.anatomy import load_colon
from capsule_drake.capsule.model import capsule_model
from capsule_drake.io.metrics import run_metrics
from capsule_drake.physics.contact_monitor import ContactMonitor
from capsule_drake.scenario import Scenario, dump_scenario
from capsule_drake.station import make_station


@dataclass
class RunResult:
    """What `simulate` returns: metrics and the raw logs they were computed from."""

    metrics: dict
    times: np.ndarray          # (K,) s
    capsule_state: np.ndarray  # (13, K)
    contact_load: np.ndarray   # (K,) N
    epm_pose: np.ndarray       # (6, K) EPM centre and moment direction
    out_dir: Path | None
    diagram: object = None     # the simulated diagram ("station" inside), its final
    context: object = None     # context (for the loggers an `extend` added), and the
    station: object = None     # station


class Progress:
    """A one-line progress bar on stderr (plain lines every 10 % when not a terminal)."""

    def __init__(self, total: float, enabled: bool = True, stream=sys.stderr):
        self.total = max(total, 1e-9)
        self.enabled = enabled
        self.stream = stream
        self.tty = stream.isatty()
        self.start = time.perf_counter()
        self._last_decile = -1

    def update(self, t: float):
        if not self.enabled:
            return
        fraction = min(1.0, t / self.total)
        elapsed = time.perf_counter() - self.start
        rate = t / elapsed if elapsed > 0 else 0.0
        line = f"{t:7.2f} / {self.total:.2f} s sim  {elapsed:6.1f} s wall  x{rate:4.1f} real time"
        if self.tty:
            bar = "#" * int(30 * fraction)
            self.stream.write(f"\r[{bar:<30}] {line}")
            self.stream.flush()
        elif int(fraction * 10) > self._last_decile:
            self._last_decile = int(fraction * 10)
            self.stream.write(f"[{int(fraction * 100):3d} %] {line}\n")

    def close(self):
        if self.enabled and self.tty:
            self.stream.write("\n")


class StepBar:
    """Steps done out of a total, with a label, on one line of stderr (the benchmark's runs,
    the import's stages); a new line once all are done."""

    def __init__(self, total: int, enabled: bool = True, unit: str = "runs",
                 stream=sys.stderr):
        self.total, self.enabled, self.unit, self.stream = total, enabled, unit, stream
        self.done = 0
        self.start = time.perf_counter()

    def step(self, label: str):
        self.show(self.done + 1, label)

    def show(self, done: int, label: str):
        self.done = done
        if self.enabled:
            bar = "#" * int(30 * done / self.total)
            self.stream.write(f"\r[{bar:<30}] {done}/{self.total} {self.unit}  "
                              f"{time.perf_counter() - self.start:6.0f} s  {label:<32}")
            if done == self.total:
                self.stream.write("\n")
            self.stream.flush()


def simulate(scenario: Scenario, *, meshcat=None, out_dir: Path | str | None = None,
             progress: bool = True, live_meshcat: bool = False, extend=None,
             stop_when=None) -> RunResult:
    """Builds the station for `scenario`, runs it for `scenario.duration` and scores it:
    the one run loop of `run`, `record`, `teleop` and `benchmark`.

    It applies `scenario.simulator` (Drake's SimulatorConfig: target_realtime_rate 1 paces
    the run to the wall clock), seeds the diagram's random context with
    `scenario.random_seed`, logs the capsule's state, the contact load and the EPM's pose
    every `scenario.outputs.log_period`, and shows progress.

    Args:
        meshcat: a pydrake Meshcat to draw into and record, or None.
        out_dir: if given, writes metrics.json, scenario.yaml, logs.npz and (with meshcat)
            recording.html there. A simulation error or Ctrl-C still writes what was logged.
        progress: show a progress bar on stderr.
        live_meshcat: keep drawing while recording (for a user watching the live page).
        extend: optional `extend(builder, station) -> close()`: adds systems (a dataset
            writer, loggers, a controller) around the station before the diagram is built;
            the returned callable, if any, runs after the simulation, however it ended.
        stop_when: optional `stop_when(station, station_context) -> str | None`, asked
            every simulated half second: a text ends the run there (a goal reached), and
            becomes the metrics' "stopped_at".
    """
    builder = DiagramBuilder()
    # The station first: it reports a colon source that cannot be loaded as a ScenarioError.
    station = builder.AddNamedSystem("station", make_station(scenario, meshcat=meshcat))
    colon, _ = load_colon(scenario.colon)   # cached: the station's own
    monitor = builder.AddNamedSystem("contact_monitor", ContactMonitor())
    builder.Connect(station.GetOutputPort("contact_results"), monitor.get_input_port())
    period = scenario.outputs.log_period
    capsule_log = LogVectorOutput(station.GetOutputPort("capsule.state"), builder, period)
    contact_log = LogVectorOutput(monitor.GetOutputPort("contact_load"), builder, period)
    epm_log = LogVectorOutput(station.GetOutputPort("epm.pose"), builder, period)
    finish = extend(builder, station) if extend is not None else None
    diagram = builder.Build()
    model = capsule_model()

    simulator = Simulator(diagram)
    ApplySimulatorConfig(scenario.simulator, simulator)
    diagram.SetRandomContext(simulator.get_mutable_context(),
                             RandomGenerator(scenario.random_seed))
    stopped_at = None
    if stop_when is not None:
        last_check = [-np.inf]

        def monitor_run(root_context):
            t = root_context.get_time()
            if t - last_check[0] < 0.5:
                return EventStatus.DidNothing()
            last_check[0] = t
            reason = stop_when(station, station.GetMyContextFromRoot(root_context))
            if reason:
                return EventStatus.ReachedTermination(diagram, reason)
            return EventStatus.DidNothing()

        simulator.set_monitor(monitor_run)
    if meshcat is not None:
        meshcat.StartRecording(frames_per_second=1.0 / scenario.outputs.visual_period,
                               set_visualizations_while_recording=live_meshcat)
    bar = Progress(scenario.duration, enabled=progress)
    stopped_early = None
    wall_start = time.perf_counter()
    try:
        simulator.Initialize()
        chunk = max(scenario.duration / 200.0, 0.05)
        t = 0.0
        while t < scenario.duration:
            t = t + chunk
            if t > scenario.duration - 1e-9:  # end on the duration, not an ulp short of it
                t = scenario.duration
            status = simulator.AdvanceTo(t)
            bar.update(simulator.get_context().get_time())
            if status.reason() == SimulatorStatus.ReturnReason.kReachedTerminationCondition:
                stopped_at = status.message()
                break
    except KeyboardInterrupt:
        stopped_early = f"interrupted at t = {simulator.get_context().get_time():.3f} s"
    except (RuntimeError, ValueError) as e:
        stopped_early = (f"simulation error at t = {simulator.get_context().get_time():.3f} s: "
                         f"{str(e).splitlines()[0]}")
    finally:
        bar.close()
        if finish is not None:
            finish()
        if station.HasSubsystemNamed("capsule.camera"):
            # The render worker is a process: end it with the run, not when a pool process
            # that runs the next run gets round to collecting this diagram.
            worker = station.GetSubsystemByName("capsule.camera").worker
            if worker is not None:
                worker.close()
    wall_time = time.perf_counter() - wall_start

    context = simulator.get_context()
    logs = [log.FindLog(context) for log in (capsule_log, contact_log, epm_log)]
    # A run cut short may stop between two loggers' samples: keep the common part.
    k = min(log.num_samples() for log in logs)
    times = logs[0].sample_times()[:k]
    result = RunResult(metrics={}, times=times, capsule_state=logs[0].data()[:, :k],
                       contact_load=logs[1].data()[0, :k], epm_pose=logs[2].data()[:, :k],
                       out_dir=Path(out_dir) if out_dir is not None else None,
                       diagram=diagram, context=context, station=station)
    if k > 0:
        result.metrics = run_metrics(
            colon, times, result.capsule_state, result.contact_load, result.epm_pose,
            capsule_radius=model.radius, capsule_length=model.length,
            epm_geometry=scenario.epm.magnet, start_s=scenario.capsule.start_s,
            sim_time=context.get_time(), wall_time=wall_time, stopped_early=stopped_early)
    else:
        result.metrics = {"stopped_early": stopped_early, "wall_time_s": wall_time}
    if stopped_at:
        result.metrics["stopped_at"] = stopped_at

    if meshcat is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()
    if result.out_dir is not None:
        _write_outputs(result, scenario, meshcat)
    return result


def _write_outputs(result: RunResult, scenario: Scenario, meshcat):
    out = result.out_dir
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / "logs.npz", times=result.times, capsule_state=result.capsule_state,
                        contact_load=result.contact_load, epm_pose=result.epm_pose)
    (out / "scenario.yaml").write_text(dump_scenario(scenario))
    (out / "metrics.json").write_text(json.dumps(result.metrics, indent=2) + "\n")
    if meshcat is not None:
        (out / "recording.html").write_text(meshcat.StaticHtml())
