"""The one run loop: a scenario's station built, stepped, guarded and written (`Run`,
`simulate`), with the stages around it (the settled start, signals, the output folder,
progress)."""

from __future__ import annotations

import contextlib
import copy
import signal
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydrake.common import RandomGenerator
from pydrake.math import RigidTransform
from pydrake.systems.analysis import SimulatorConfig, SimulatorStatus
from pydrake.systems.framework import DiagramBuilder, EventStatus
from pydrake.systems.primitives import LogVectorOutput

from capsule_drake.anatomy import load_colon
from capsule_drake.anatomy.start_check import check_start
from capsule_drake.capsule.model import capsule_model
from capsule_drake.io.guard import ENDING_OF_KIND, RunGuard, parse_guard_reason
from capsule_drake.io.metrics import run_metrics
from capsule_drake.app.live.outputs import add_channel_outputs
from capsule_drake.app.live.pacing import PaceWatch
from capsule_drake.app.signals import DeferredSignals
from capsule_drake.app.log_spool import LOG_KEYS, LogSpool
from capsule_drake.physics.contact.tissue import tissue_metrics
from capsule_drake.physics.contact_monitor import ContactMonitor
from capsule_drake.physics.wall_pressure import (WALL_PRESSURE_SYSTEM, WallPressure,
                                                 WallPressureMap)
from capsule_drake.plugins import FAILURES, culprit, failure_text, noting_loads, what_it_did
from capsule_drake.scenario import Scenario, ScenarioError
from capsule_drake.station import make_station, station_value
from capsule_drake.app.start import settled_start, simulator_for, start_where_it_rests
from capsule_drake.app.run_outputs import _write_outputs, prepare_folder


@dataclass
class RunResult:
    """What `simulate` returns: metrics and the raw logs they were computed from."""

    metrics: dict
    times: np.ndarray          # (K,) s
    capsule_state: np.ndarray  # (13, K)
    contact_load: np.ndarray   # (K,) N
    contact_pressure: np.ndarray  # (K,) Pa, the contact's peak pressure (NaN: point contact)
    epm_pose: np.ndarray       # (6, K) EPM centre and moment direction
    out_dir: Path | None
    # The wall's patches: each one's peak pressure and longest spells above the thresholds
    # (physics/wall_pressure.py), or None (a run without loggers).
    wall_pressure: WallPressure | None = None
    diagram: object = None     # the simulated diagram ("station" inside), its final
    context: object = None     # context (for the loggers an `extend` added), and the
    station: object = None     # station
    channel_logger: object = None   # the MCAP file's and live outputs' (app/mcap_log.py)
    # How the run ended: "completed" (its duration), "goal" (stop_when), "diverged",
    # "left_colon" or "perforated" (the run guard), "epm_clearance" (the EPM's clearance
    # watch), "error" (inside the simulation), "interrupted".
    status: str = "completed"


class Interrupted(KeyboardInterrupt):
    """A termination signal (SIGTERM, SIGHUP) turned into an interrupt, so that a run ends
    as it does on Ctrl-C: outputs written, then the process exits 128 + the signal."""

    def __init__(self, signal_number: int):
        super().__init__(signal.Signals(signal_number).name)
        self.signal_number = signal_number
        self.signal_name = signal.Signals(signal_number).name


class Progress:
    """A one-line progress bar on stderr (plain lines every 10 % when not a terminal)."""

    def __init__(self, total: float, enabled: bool = True, stream=None):
        self.total = max(total, 1e-9)
        self.enabled = enabled
        # sys.stderr as it is now (not when this module was imported: a test's capture,
        # since closed, may have been stderr then).
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
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

    def __init__(self, total: int, enabled: bool = True, unit: str = "runs", stream=None):
        self.total, self.enabled, self.unit = total, enabled, unit
        self.stream = stream or sys.stderr
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


CONTACT_MONITOR = "contact_monitor"
"""The run's contact monitor (the capsule's contact load), beside the station."""


def paced(scenario: Scenario) -> SimulatorConfig:
    """The scenario's SimulatorConfig, paced to real time when an output is watched live
    (outputs.meshcat, foxglove, ros2) and the scenario set no pace of its own."""
    config = scenario.simulator
    if scenario.outputs.live() and config.target_realtime_rate == 0.0:
        config = copy.copy(config)
        config.target_realtime_rate = 1.0
    return config


@dataclass
class Ending:
    """How a run ended before its time was up (or None from `Run.advance_to`: it was not)."""

    # "goal" (stop_when), "diverged", "left_colon" or "perforated" (the run guard),
    # "epm_clearance" (the EPM's clearance watch), "error" (inside the simulation),
    # "interrupted" (a signal).
    status: str
    text: str                  # one line: the goal's text, or what stopped it and when
    traceback: str | None = None   # an error's
    signal: str | None = None      # an interruption's: "SIGINT", "SIGTERM", "SIGHUP"


def _error_ending(e: BaseException, t: float, plugins=()) -> Ending:
    """An error that ended the run: one line, naming the plug-in (of `plugins`, those the run
    loaded) whose code raised or exited, if one did."""
    return Ending("error", f"simulation error at t = {t:.3f} s: {failure_text(e, plugins)}",
                  traceback.format_exc())


@contextlib.contextmanager
def _plugins_as_bad_input(plugins):
    """Within the block (a run's build), an error that the code of one of `plugins` (those
    the run loaded) raises or exits with is a bad input: ScenarioError, one line naming it,
    and nothing is simulated (e.g. Drake allocating a value of a navigator's port as the
    run's context is made)."""
    try:
        yield
    except FAILURES as e:
        plugin = culprit(e, plugins)
        if plugin is None or isinstance(e, ScenarioError):
            raise
        raise ScenarioError(f"scenario: {plugin} {what_it_did(e)} as the run was built") \
            from None


def _interrupted(name: str, t: float) -> Ending:
    return Ending("interrupted", f"interrupted ({name}) at t = {t:.3f} s", signal=name)


class Run:
    """One scenario's station, built and stepped: the one run loop that `simulate` (the
    CLI's verbs, the benchmark's runs) and the Gymnasium environment all step.

    The stages, in order: the settling of the capsule's start (capsule.settle: see
    `settled_start`), the build (the station with the contact monitor and the run guard,
    `add_guarded_station`; the loggers; the caller's `extend`), the Simulator
    (scenario.simulator applied, the random context seeded with scenario.random_seed).
    Then `advance_to(t)` as often as the caller likes: each returns None, or the `Ending`
    that stopped it (the guard, a goal, an error inside the simulation, a signal noted by
    `signals`). `close()` frees what the run holds (the extensions' close hooks, the
    camera's render worker, the simulator's monitor) and must be called; a `with` block
    does it.

    Args:
        meshcat: a pydrake Meshcat the station draws into, or None.
        extend: optional `extend(builder, station) -> close()`: adds systems around the
            station before the diagram is built; the returned callable, if any, runs in
            `finish_extensions()` (or `close()`).
        stop_when: optional `stop_when(station, station_context) -> str | None`, asked every
            simulated half second: a text ends the run there (Ending "goal").
        log: add the loggers of the capsule's state, contact load and EPM pose (every
            scenario.outputs.log_period), which `drain()` empties, and the map of the
            wall's pressure (`add_wall_pressure`, read by `wall_pressure()`).
        signals: a DeferredSignals whose noted signal ends the run at its next step.
    """

    def __init__(self, scenario: Scenario, *, meshcat=None, extend=None, stop_when=None,
                 log: bool = True, signals: DeferredSignals | None = None):
        self.scenario = scenario
        capsule_start = settled_start(scenario) if scenario.capsule.settle > 0.0 else None
        builder = DiagramBuilder()
        self._finish = self.channel_logger = None
        # The plug-ins the station and the extensions load: an error they raise names them.
        with noting_loads() as self.plugins, _plugins_as_bad_input(self.plugins):
            station, colon, monitor = add_guarded_station(builder, scenario, meshcat,
                                                          capsule_start)
            try:  # a build that fails closes what the station and the extensions opened
                period = scenario.outputs.log_period
                self._loggers = (
                    LogVectorOutput(station.GetOutputPort("capsule.state"), builder, period),
                    LogVectorOutput(monitor.GetOutputPort("contact_load"), builder, period),
                    LogVectorOutput(monitor.GetOutputPort("peak_pressure"), builder, period),
                    LogVectorOutput(station.GetOutputPort("epm.pose"), builder, period)
                ) if log else ()
                self._wall_map = (add_wall_pressure(builder, station, colon,
                                                    scenario.contact.pressure_field)
                                  if log else None)
                # The scenario's channel outputs (MCAP, Foxglove, ROS 2: app/live/outputs.py)
                # first, then the caller's.
                logger = add_channel_outputs(builder, station, scenario, self._wall_map)
                self.channel_logger = logger
                extend = chain_extends(None if logger is None else lambda b, s: logger.close,
                                       extend)
                self._finish = extend(builder, station) if extend is not None else None
                diagram = builder.Build()
                simulator = simulator_for(diagram, paced(scenario), scenario.random_seed)
            except BaseException:
                _close_quietly(self._finish)
                close_render_worker(station)
                raise
        self.station, self.colon, self.contact_monitor = station, colon, monitor
        self.diagram, self.simulator = diagram, simulator
        self.context = simulator.get_mutable_context()
        self._stop_when, self._signals = stop_when, signals
        self._last_check = -np.inf
        self._closed = False
        if stop_when is not None or signals is not None:
            simulator.set_monitor(self._monitor)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    @property
    def time(self) -> float:
        return self.context.get_time()

    def reset(self, random_seed: int) -> None:
        """Back to time 0 with the default state, the random context seeded anew (an
        episode of the Gymnasium environment); `initialize()` after fixing the inputs."""
        self.context.SetTime(0.0)
        self.diagram.SetRandomContext(self.context, RandomGenerator(random_seed))
        self._last_check = -np.inf

    def initialize(self) -> None:
        self.simulator.Initialize()

    def _monitor(self, root_context):
        if self._signals is not None and self._signals.pending is not None:
            return EventStatus.ReachedTermination(self.diagram, "interrupted")
        if self._stop_when is None:
            return EventStatus.DidNothing()
        t = root_context.get_time()
        if t - self._last_check < 0.5:
            return EventStatus.DidNothing()
        self._last_check = t
        reason = self._stop_when(self.station, self.station.GetMyContextFromRoot(root_context))
        if reason:
            return EventStatus.ReachedTermination(self.diagram, reason)
        return EventStatus.DidNothing()

    def advance_to(self, t: float) -> Ending | None:
        """Simulates up to time t. Returns None if it got there, else how the run ended:
        the run guard (io/guard.py), `stop_when`'s goal, an error inside the simulation
        (Drake's, including its failed assertions, or a plug-in's: one that raised, exited
        or raised KeyboardInterrupt itself), or a signal. A second signal before the first
        was acted on raises (KeyboardInterrupt, or the CLI's `Interrupted`)."""
        try:
            result = self.simulator.AdvanceTo(t)
        except KeyboardInterrupt as e:
            if not self.raised_by_plugin(e):
                raise
            return _error_ending(e, self.time, self.plugins)
        except (Exception, SystemExit) as e:  # Drake's errors; its failed assertions exit
            return _error_ending(e, self.time, self.plugins)
        if self._signals is not None and self._signals.pending is not None:
            return _interrupted(signal.Signals(self._signals.pending).name, self.time)
        if result.reason() != SimulatorStatus.ReturnReason.kReachedTerminationCondition:
            return None
        found = parse_guard_reason(result.message())
        if found is None:
            return Ending("goal", result.message())
        kind, text = found
        if kind == "epm_clearance":
            return Ending(ENDING_OF_KIND[kind], f"stopped by the EPM's clearance watch at {text}")
        return Ending(ENDING_OF_KIND[kind], f"stopped by the run guard at {text}")

    def raised_by_plugin(self, interrupt: KeyboardInterrupt) -> bool:
        """Whether a KeyboardInterrupt out of the simulation was raised by a plug-in's code
        itself, not by a signal: while `signals` are noted, a signal raises only when one is
        pending already (the second)."""
        return (self._signals is not None and self._signals.pending is None
                and culprit(interrupt, self.plugins) is not None)

    def drain(self) -> dict | None:
        """Moves the loggers' samples out (the LOG_KEYS of app/outputs.py), or None without
        loggers."""
        if not self._loggers:
            return None
        logs = [logger.FindMutableLog(self.context) for logger in self._loggers]
        # A run cut short may stop between two loggers' samples: keep the common part.
        k = min(log.num_samples() for log in logs)
        # Copies: the logs' arrays are views of storage that Clear() hands back.
        chunk = dict(zip(LOG_KEYS, (np.array(logs[0].sample_times()[:k]),
                                    np.array(logs[0].data()[:, :k]),
                                    np.array(logs[1].data()[0, :k]),
                                    np.array(logs[2].data()[0, :k]),
                                    np.array(logs[3].data()[:, :k]))))
        for log in logs:
            log.Clear()
        return chunk

    def wall_pressure(self) -> WallPressure | None:
        """The map of the wall's pressure now (`add_wall_pressure`), or None: a run without
        loggers, or a diagram that failed mid-step."""
        if self._wall_map is None:
            return None
        try:
            return self._wall_map.wall_pressure(self.context)
        except Exception:
            return None

    def epm_guard_counts(self) -> np.ndarray | None:
        """The EPM guard's counts now (the station's `epm.guard_counts`: epm/guard.py
        GUARD_COUNTS), or None if they cannot be read (a diagram that failed mid-step)."""
        try:
            return np.array(self.station.GetOutputPort("epm.guard_counts").Eval(
                self.station.GetMyContextFromRoot(self.context)))
        except Exception:
            return None

    def finish_extensions(self) -> None:
        """Runs the extensions' close hook (once); its error is raised."""
        finish, self._finish = self._finish, None
        if finish is not None:
            finish()

    def close(self) -> None:
        """Frees what the run holds: the extensions' close hook (its error dropped: call
        `finish_extensions` first to see it), the camera's render worker, the simulator's
        monitor (a Python callable inside the C++ simulator, which Python's garbage
        collector cannot see through)."""
        if self._closed:
            return
        self._closed = True
        finish, self._finish = self._finish, None
        _close_quietly(finish)
        close_render_worker(self.station)
        self.simulator.clear_monitor()
        self._stop_when = None


def simulate(scenario: Scenario, *, meshcat=None, out_dir: Path | str | None = None,
             progress: bool = True, live_meshcat: bool = False, extend=None,
             stop_when=None, recording: bool = True) -> RunResult:
    """Builds the station for `scenario`, runs it for `scenario.duration` and scores it:
    `run`, `record`, `teleop` and the benchmark's runs, on the one run loop (`Run`).

    It applies `scenario.simulator` (Drake's SimulatorConfig: target_realtime_rate 1 paces
    the run to the wall clock), seeds the diagram's random context with
    `scenario.random_seed`, logs the capsule's state, the contact load and the EPM's pose
    every `scenario.outputs.log_period`, shows progress, and guards the run
    (io/guard.py: a state that stops being physical ends it).

    However the run ends (its duration, a goal, the guard, an error inside the simulation,
    Ctrl-C or a termination signal, during the build as well), what was logged is kept and
    written; `status` in the result and in metrics.json says which it was.

    Args:
        meshcat: a pydrake Meshcat to draw into and record, or None.
        out_dir: if given, a folder (created if need be) that is checked for room, then
            gets scenario.yaml at once, the logs every few simulated seconds (logs.parts/,
            see app/outputs.py), and at the end metrics.json, logs.npz,
            wall_pressure.npz and (when the contact has a pressure field)
            wall_pressure.png (the map of the wall's pressure: `add_wall_pressure`), (with
            meshcat) recording.html (the replay page: run_outputs.py `replay_html`) and (after an error)
            error.txt with the traceback.
        progress: show a progress bar on stderr.
        live_meshcat: keep drawing while recording (for a user watching the live page).
        recording: with `meshcat`, record the run into recording.html (False: the page
            is only drawn live).
        extend: see `Run`.
        stop_when: see `Run`; its text becomes the metrics' "stopped_at".

    Raises:
        OutputError: `out_dir` cannot be written or has no room (before simulating), or
            the outputs could not be written at the end (WriteError; what was written as
            the run went stays on disk).
    """
    out = Path(out_dir) if out_dir is not None else None
    recorded = meshcat if recording else None  # the Meshcat the run is recorded in
    signals = DeferredSignals()
    ending, built = None, False
    try:
        # From here on a signal is noted, not raised: the run stops at its next step, at
        # t = 0 if the signal came while the run was being set up.
        with signals:  # on leaving, the signals are held until `signals.held()` ends
            try:
                scenario = start_where_it_rests(scenario)   # what scenario.yaml says
                if out is not None:  # before the build, which can take a while
                    prepare_folder(out, scenario, recorded is not None)
                run = Run(scenario, meshcat=meshcat, extend=extend, stop_when=stop_when,
                          signals=signals)
            except BaseException as e:  # nothing was run: leave no outputs of it
                signals.restore()
                if out is not None and isinstance(e, (ScenarioError, KeyboardInterrupt)):
                    (out / "scenario.yaml").unlink(missing_ok=True)
                raise
            built = True
            if recorded is not None:
                meshcat.StartRecording(frames_per_second=1.0 / scenario.outputs.visual_period,
                                       set_visualizations_while_recording=live_meshcat)
            spool = LogSpool(out)
            bar = Progress(scenario.duration, enabled=progress)
            pace = PaceWatch(paced(scenario).target_realtime_rate if scenario.outputs.live()
                             else 0.0)
            wall_start = time.perf_counter()
            run.initialize()
            chunk = max(scenario.duration / 200.0, 0.05)
            t = 0.0
            while ending is None and t < scenario.duration:
                if signals.pending is not None:  # during the set-up, or the last chunk
                    ending = run.advance_to(run.time)
                    break
                t = t + chunk
                if t > scenario.duration - 1e-9:  # end on the duration, not an ulp short
                    t = scenario.duration
                ending = run.advance_to(t)
                bar.update(run.time)
                pace.update(run.time)
                spool.add(run.drain(), run.time)
    except KeyboardInterrupt as e:  # a second signal: Ctrl-C, or the CLI's `Interrupted`
        if not built:
            raise
        if run.raised_by_plugin(e):  # as the run initialises
            ending = _error_ending(e, run.time, run.plugins)
        else:
            ending = _interrupted(getattr(e, "signal_name", "SIGINT"), run.time)
    except (Exception, SystemExit) as e:  # e.g. a plug-in's error as the run initialises
        if not built:
            raise
        ending = _error_ending(e, run.time, run.plugins)
    # However it ended: close what the run opened, score it, write it, with Ctrl-C and the
    # termination signals held until the files are whole.
    with signals.held():
        wall_time = time.perf_counter() - wall_start
        bar.close()
        status = ending.status if ending is not None else "completed"
        error = ending.traceback if ending is not None else None
        stopped_at = ending.text if status == "goal" else None
        stopped_early = ending.text if ending is not None and status != "goal" else None
        try:
            spool.add(run.drain(), run.time)
        except Exception:  # the loggers of a diagram that failed mid-publish
            pass
        try:
            run.finish_extensions()
        except Exception as e:  # e.g. a dataset writer on a full disk
            if status in ("completed", "goal"):
                status, error = "error", traceback.format_exc()
                stopped_early = f"could not finish the run's extension: {e}"
        wall_pressure = run.wall_pressure()
        run.close()
        logs = spool.joined()
        result = RunResult(metrics={}, times=logs["times"], capsule_state=logs["capsule_state"],
                           contact_load=logs["contact_load"],
                           contact_pressure=logs["contact_pressure"], epm_pose=logs["epm_pose"],
                           out_dir=out, wall_pressure=wall_pressure, diagram=run.diagram,
                           context=run.context, station=run.station, status=status,
                           channel_logger=run.channel_logger)
        model = capsule_model()
        result.metrics = run_metrics(
            run.colon, result.times, result.capsule_state, result.contact_load,
            result.epm_pose, capsule_radius=model.radius, capsule_length=model.length,
            epm_geometry=scenario.epm.magnet, start_s=scenario.capsule.start_s,
            sim_time=run.time, wall_time=wall_time, stopped_early=stopped_early,
            diverged=status == "diverged", epm_guard_counts=run.epm_guard_counts(),
            contact_pressure=result.contact_pressure, wall_pressure=wall_pressure)
        result.metrics["status"] = status
        if pace.target > 0.0:   # a paced run: how far from its pace it fell
            result.metrics["pace_target"] = pace.target
            result.metrics["pace_slowest"] = pace.slowest
        # The model every contact figure comes from (physics/contact/): printed with them.
        result.metrics["contact_model"] = scenario.contact.label()
        # The patient's wall (physics/contact/tissue.py): its figures and how they were chosen.
        result.metrics.update(tissue_metrics(scenario.contact, scenario.colon))
        if status == "interrupted":
            result.metrics["signal"] = ending.signal
        if stopped_at:
            result.metrics["stopped_at"] = stopped_at
        if recorded is not None:
            flush_trail = station_value(run.station, "meshcat.flush_trail", None)
            if flush_trail is not None:  # the trail up to the end
                flush_trail(run.time)
            meshcat.StopRecording()
            meshcat.PublishRecording()
        if out is not None:
            _write_outputs(result, spool, recorded, error, run.colon)
    return result


def chain_extends(*extends):
    """One `extend` for `simulate` that runs each given one (None ones skipped) in turn; its
    close hook closes every one's, in reverse order, each even if another failed (the
    first failure is raised after)."""
    extends = [e for e in extends if e is not None]
    if not extends:
        return None

    def extend(builder, station):
        closers = []
        try:
            for e in extends:
                closer = e(builder, station)
                if closer is not None:
                    closers.append(closer)
        except BaseException:  # the ones already added are closed; the failure is raised
            for closer in reversed(closers):
                _close_quietly(closer)
            raise

        def close():
            failure = None
            for closer in reversed(closers):
                try:
                    closer()
                except Exception as e:
                    failure = failure or e
            if failure is not None:
                raise failure
        return close
    return extend


def add_guarded_station(builder: DiagramBuilder, scenario: Scenario, meshcat=None,
                        capsule_start: RigidTransform | None = None):
    """Adds what every run simulates to `builder`: the station ("station"), the contact
    monitor ("contact_monitor": the capsule's contact load) and the run guard ("run_guard",
    io/guard.py: it ends a simulation whose state stops being physical). Returns (station,
    colon, contact monitor). `Run` builds every run's diagram with it.

    Raises:
        ScenarioError: the colon cannot be loaded, or the capsule does not fit where it
            starts.
    """
    model = capsule_model()
    # The station first: it reports a colon source that cannot be loaded as a ScenarioError.
    station = builder.AddNamedSystem("station", make_station(scenario, meshcat=meshcat,
                                                             capsule_start=capsule_start))
    colon, _ = load_colon(scenario.colon)   # cached: the station's own
    try:  # the capsule fits where it starts (an imported colon's ends may be open)
        check_start(colon, scenario.capsule.start_s, model.radius,
                    model.length + 2.0 * model.radius)
    except ValueError as e:
        close_render_worker(station)
        raise ScenarioError(f"scenario: {e}") from None
    monitor = add_contact_monitor(builder, station)
    guard = builder.AddNamedSystem("run_guard", RunGuard(
        colon, model.radius, model.length, scenario.guard,
        wall_allowance=scenario.contact.wall_allowance(model.radius, colon),
        wall_tears=scenario.contact.wall_tears()))
    builder.Connect(station.GetOutputPort("capsule.state"), guard.get_input_port())
    return station, colon, monitor


def add_contact_monitor(builder: DiagramBuilder, station, name: str = CONTACT_MONITOR):
    """Adds a ContactMonitor (the capsule's contact load and peak pressure) named `name`
    beside `station`, reading its contact results and, on the compliant wall's foundation
    route, its own contact (`contact.wall`)."""
    wall = station.HasOutputPort("contact.wall")
    monitor = builder.AddNamedSystem(name, ContactMonitor(wall=wall))
    builder.Connect(station.GetOutputPort("contact_results"),
                    monitor.GetInputPort("contact_results"))
    if wall:
        builder.Connect(station.GetOutputPort("contact.wall"), monitor.GetInputPort("wall_contact"))
    return monitor


def add_wall_pressure(builder: DiagramBuilder, station, colon,
                      pressure_field: bool) -> WallPressureMap:
    """Adds the map of the wall's pressure ("wall_pressure", physics/wall_pressure.py) beside
    `station`, reading its contact results; it samples them only when the contact model has
    a pressure field (`pressure_field`: the scenario's contact's), and otherwise says it has
    none."""
    wall = station.HasOutputPort("contact.wall")
    system = builder.AddNamedSystem(WALL_PRESSURE_SYSTEM, WallPressureMap(
        colon.centerline, pressure_field=pressure_field, wall=wall))
    builder.Connect(station.GetOutputPort("contact_results"),
                    system.GetInputPort("contact_results"))
    if wall:
        builder.Connect(station.GetOutputPort("contact.wall"), system.GetInputPort("wall_contact"))
    return system


def _close_quietly(close) -> None:
    """Runs a close hook (if any) on the way out of a failure: its own error is dropped, the
    failure being handled is the one to report."""
    if close is None:
        return
    try:
        close()
    except Exception:
        pass


def close_render_worker(station) -> None:
    """Ends the station camera's render worker, if it has one. The worker is a process: end
    it with the run, not when a pool process that runs the next run gets round to
    collecting the diagram."""
    worker = station_value(station, "capsule.camera.render_worker", None)
    if worker is not None:
        worker.close()
