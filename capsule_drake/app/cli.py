"""capsule-sim: the command line. Parses arguments and calls `station` and `run`; nothing else."""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import logging
import os
import signal
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path

import numpy as np
import yaml
from pydrake.geometry import Meshcat, MeshcatParams

from capsule_drake.anatomy.cache import CacheError, cache_base
from capsule_drake.anatomy.imported import import_colon_mesh, write_import
from capsule_drake.app.eval_lumen import OUTPUTS as EVAL_OUTPUTS
from capsule_drake.app.eval_lumen import EvaluationStopped, evaluate_paths
from capsule_drake.app.mcap_log import add_mcap_logger, expected_mcap_bytes
from capsule_drake.app.record import record, record_seeds, with_all_sensors
from capsule_drake.app.outputs import (DATASET_OUTPUTS, RUN_OUTPUTS, SEED_PREFIX, SEEDS_OUTPUTS,
                                      OutputError, plan_outputs, release_claims)
from capsule_drake.app.run import Interrupted, StepBar, WriteError, chain_extends, simulate
from capsule_drake.app.benchmark import (FAILED, NAVIGATORS, TIERS, EngineError, NotedSignals,
                                         RowWriter, Task, default_run_timeout, report,
                                         run_suite, task_scenario)
from capsule_drake.perception.evaluation import IMAGE_CONDITIONS, LIGHT_CONDITIONS, RENDERERS
from capsule_drake.physics.tissue import INJURY_PRESSURE, ISCHAEMIA_PRESSURE
from capsule_drake.perception.lumen import load_detector
from capsule_drake.plugins import load_function
from capsule_drake.scenario import (DEFAULT_SCENARIO_FILE, ScenarioError, load_scenario,
                                    scenario_names)

# Servers (Meshcat, the UDP bridge) listen on this machine only unless --host says otherwise.
LOOPBACK = "127.0.0.1"
# The port of the live Meshcat page (run --meshcat, teleop --operator browser) and of the
# UDP bridge (teleop --operator udp) unless --port says otherwise.
DEFAULT_PORT = 7000
# What a benchmark and an import write (a previous one's are replaced by --force).
BENCHMARK_OUTPUTS = ("runs.csv", "summary.csv", "progress.png", "segments.png", "results.json",
                     "runs-as-finished.csv")
IMPORT_OUTPUTS = ("wall.obj", "centerline.npz", "wall_radius.npz", "import.json")
# The commands that build colons, in the cache (anatomy/cache.py).
COLON_VERBS = ("run", "record", "teleop", "benchmark", "eval-lumen")


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="capsule-sim",
        description="Magnetically actuated endoscopic capsule simulator (Drake).")
    verbs = parser.add_subparsers(dest="verb", required=True, parser_class=_Parser)
    run = verbs.add_parser(
        "run", help="simulate a scenario and write its metrics and Meshcat recording",
        description="Simulate a scenario. Writes metrics.json, scenario.yaml, logs.npz and "
                    "recording.html (a self-contained Meshcat replay) into the output folder.")
    _scenario_arguments(run)
    run.add_argument("--meshcat", action="store_true",
                     help="serve a live Meshcat page, pace the run to real time, and keep "
                          "serving after the run until Ctrl-C")
    run.add_argument("--port", type=_port,
                     help=f"Meshcat port with --meshcat (default {DEFAULT_PORT})")
    _host_argument(run, "Meshcat")
    _out_arguments(run, "runs/<scenario>-<date-time>", mcap=True)
    run.add_argument("--no-recording", action="store_true",
                     help="skip the Meshcat recording (a little faster; with --meshcat the "
                          "page is drawn live only)")
    _mcap_argument(run)
    run.add_argument("--quiet", action="store_true", help="no progress bar")

    rec = verbs.add_parser(
        "record", help="simulate a scenario with the capsule camera and write a dataset",
        description="Simulate a scenario with the capsule's camera (the scenario's, or the "
                    "default 172-degree fisheye) and sensors, writing RGB and 16-bit depth "
                    "frames, a field-of-view mask, camera poses, IMU, AHRS, magnetometer and "
                    "lumen ground truth into a folder laid out like SimCol3D's (README.md "
                    "written there describes every file). With --seeds, one such folder per "
                    "colon seed (seed_XXXX/) and splits.csv assigning each seed to train, val "
                    "or test.")
    _scenario_arguments(rec)
    _out_arguments(rec, "datasets/<scenario>-<date-time>", force=False)
    _mcap_argument(rec)
    rec.add_argument("--seeds", metavar="SEEDS",
                     help="record one dataset per colon seed: '0-99', '0,3,7' or '5' (each "
                          "seed also seeds the sensors' noise unless --scenario-text sets "
                          "random_seed)")
    rec.add_argument("--split", metavar="TRAIN,VAL,TEST", default=None,
                     help="with --seeds: the expected shares of train, val and test seeds "
                          "(default 0.7,0.15,0.15); a seed's split is a fixed function of "
                          "the seed and these shares (README.md at the top of --out)")
    rec.add_argument("--quiet", action="store_true", help="no progress bar")

    tel = verbs.add_parser(
        "teleop", help="haptic teleoperation: a simulated operator, the browser, or a device",
        description="Teleoperate the capsule (scenario 'Teleop' unless --scenario says "
                    "otherwise): the operator moves the stylus, the EPM follows, the operator "
                    "feels the pseudo-force and the capsule's contact. --operator simulated "
                    "runs a model of a hand (as fast as it computes); browser serves a Meshcat "
                    "page with keyboard, gamepad and sliders, paced in real time; udp listens "
                    "for a real device (docs/udp_protocol.md), paced in real time.")
    _scenario_arguments(tel)
    tel.add_argument("--operator", choices=("simulated", "browser", "udp"),
                     help="who holds the stylus (default: the scenario's)")
    tel.add_argument("--guidance", choices=("on", "off"), default="on",
                     help="the pseudo-force on the operator's hand (default on)")
    tel.add_argument("--delay", type=float, metavar="S",
                     help="one-way delay of the channel, both ways (s)")
    tel.add_argument("--port", type=_port,
                     help="Meshcat port (browser) or UDP port (udp; 0 = any free one; default "
                          f"{DEFAULT_PORT}); the simulated operator has none")
    _host_argument(tel, "Meshcat and the UDP bridge")
    _out_arguments(tel, "runs/teleop-<operator>-<date-time>", mcap=True)
    _mcap_argument(tel)
    tel.add_argument("--quiet", action="store_true", help="no progress bar")

    ev = verbs.add_parser(
        "eval-lumen", help="score a lumen detector against the ground truth on rendered frames",
        description="Render seeded frames at random poses in random colons (looking along the "
                    "lumen, and facing the wall) with the simulator's camera (vtk) and with an "
                    "independent ray caster (its own light, texture and shading), through a "
                    "fisheye and a pinhole lens, under each condition (nominal; exposure, "
                    "gamma, noise, motion blur, vignetting, colour cast, compression, bubbles, "
                    "everything at once; with the ray caster also random light fall-off, spot, "
                    "ambient, specular, texture, sensor and all of them), run each lumen "
                    "detector and compare it with the lumen truth. Prints per condition the "
                    "median and 90th-percentile error (fraction of the image diagonal), "
                    "detection rate where the lumen is in view, false-positive rate where it "
                    "is not, milliseconds per frame, and whether the condition meets the "
                    "targets; saves results.json, tables.md and contact sheets.")
    ev.add_argument("--frames", type=int, default=200, help="frames to render (default 200)")
    ev.add_argument("--colons", type=int, default=5, help="random colons (default 5)")
    ev.add_argument("--seed", type=int, default=100,
                    help="seed of the colons and poses (default 100)")
    ev.add_argument("--wall-fraction", type=float, default=0.25,
                    help="share of frames facing the wall (default 0.25)")
    ev.add_argument("--detector", action="append", metavar="NAME",
                    help="'net', 'core', 'gaussian', 'median' or "
                         "'package.module:function' (repeatable; default: net, core and "
                         "gaussian)")
    ev.add_argument("--renderer", choices=("vtk", "raycast", "both"), default="both",
                    help="image path: the simulator's camera, the ray caster, or both "
                         "(default)")
    ev.add_argument("--lens", choices=("fisheye", "pinhole", "both"), default="both",
                    help="the default 172-degree fisheye, a 120-degree pinhole, or both "
                         "(default)")
    ev.add_argument("--conditions", default="all",
                    help="comma-separated conditions, or 'all' (default)")
    _out_arguments(ev, "eval_lumen/<date-time>")
    ev.add_argument("--quiet", action="store_true", help="no progress")

    bench = verbs.add_parser(
        "benchmark", help="navigators on seeded random colons: a table, CSV and plots",
        description="Run each navigator on each seeded random colon (from the rectum, up to "
                    "--duration simulated seconds, stopping at the cecum) in parallel "
                    "processes, print a table per run and per navigator, and write runs.csv, "
                    "summary.csv, progress.png and segments.png. Navigators: autonomy-truth, "
                    "autonomy-detected, autonomy-sensors, teleop-guided, teleop-unguided, or "
                    "a user's "
                    "'package.module:function' (the plug-in interface in "
                    "capsule_drake/navigation/plugin.py).")
    bench.add_argument("--tier", choices=tuple(TIERS), default="standard",
                       help="standard: the ten procedural colons (seeds 0-9); population: "
                            "30 patients drawn from the population model (seeds 1000-1029)")
    bench.add_argument("--seeds", default=None,
                       help="colon seeds: '0-9', '0,3,7' or '5' (default: the tier's)")
    bench.add_argument("--navigators", default="autonomy-truth,autonomy-detected",
                       help="comma-separated (default autonomy-truth,autonomy-detected)")
    bench.add_argument("--duration", type=float, default=600.0, metavar="S",
                       help="simulated seconds per run at most (default 600)")
    bench.add_argument("--scenario", metavar="NAME",
                       help="the scenario a user's navigator drives (default Navigation); "
                            "the built-in navigators are named scenarios of their own, so "
                            "it is refused without a user's navigator")
    bench.add_argument("--scenario-text", default="", metavar="YAML",
                       help="YAML layered on every run's scenario")
    bench.add_argument("--polyp-detector", default="", metavar="MODULE:FUNCTION",
                       help="a polyp detector (a function of the RGB frame returning points "
                            "(u, v) or boxes (x, y, w, h)) scored on every frame: per polyp "
                            "seen and false positives per minute")
    bench.add_argument("--workers", type=int,
                       help="parallel runs (default 2; not with --address, whose scheduler "
                            "has workers of its own)")
    bench.add_argument("--run-timeout", type=float, metavar="S",
                       help="wall seconds a run may take before it is stopped and marked "
                            "failed (default 300 + 3 x --duration)")
    bench.add_argument("--engine", choices=("local", "dask"), default="local",
                       help="local process pool, or a Dask cluster (default local)")
    bench.add_argument("--address", metavar="HOST:PORT",
                       help="an existing Dask scheduler (only with --engine dask; default: a "
                            "local cluster of --workers processes)")
    _out_arguments(bench, "runs/benchmark-<date-time>")
    bench.add_argument("--quiet", action="store_true",
                       help="no progress (otherwise each run's simulated time and where the "
                            "capsule is, on stderr, as the runs go)")

    nb = verbs.add_parser(
        "notebooks", help="open the example notebooks (notebooks/) in JupyterLab",
        description="Start JupyterLab on the repository's notebooks/ folder, with this "
                    "Python (and so this installation of capsule_drake) as the kernel. Needs "
                    "the notebooks extra: ./capsule-sim notebooks installs it into .venv the "
                    "first time; elsewhere pip install -e '.[notebooks]'.")
    nb.add_argument("--port", type=_port, default=8888,
                    help="JupyterLab's port (default 8888; 0 = any free one)")
    _host_argument(nb, "JupyterLab")
    nb.add_argument("--no-browser", action="store_true",
                    help="do not open a browser (the address to open is printed)")

    imp = verbs.add_parser(
        "import-colon", help="a user's colon mesh: check, repair, extract its centreline",
        description="Read a colon mesh (OBJ, STL, PLY, GLB; metres), refuse with one line what "
                    "cannot be a colon, repair what can be repaired (duplicate and degenerate "
                    "faces, winding, small holes, normals toward the lumen, decimation to a "
                    "triangle budget; a texture is kept), extract its centreline with arc "
                    "length and local radius (s = 0 at the narrower end), tabulate the wall "
                    "around it, and write DIR/wall.obj, DIR/centerline.npz, "
                    "DIR/wall_radius.npz and DIR/import.json with a summary of the repairs. "
                    "A scenario runs on it with colon: {source: !Imported {path: DIR}}.")
    imp.add_argument("mesh", type=_path, help="the mesh file")
    imp.add_argument("--out", type=_path, required=True, metavar="DIR", help="output folder")
    imp.add_argument("--force", action="store_true",
                     help="replace a previous import's files in --out")
    imp.add_argument("--scale", type=float, default=1.0,
                     help="multiply the coordinates by this first (e.g. 0.001 from mm)")
    imp.add_argument("--max-faces", type=int, default=150000, metavar="N",
                     help="decimate to at most N triangles (default 150000)")
    imp.add_argument("--reverse", action="store_true",
                     help="start the centreline at the wider end instead of the narrower")
    imp.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


class _Parser(argparse.ArgumentParser):
    """argparse, with a wrong flag reported in one line (and where to find the usage)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _path(text: str) -> Path:
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path")
    if "\0" in text:
        raise argparse.ArgumentTypeError("a path cannot hold a NUL character")
    return Path(text)


def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{port} is not a port (0-65535; 0 = any free one)")
    return port


def _host_argument(parser, what: str):
    parser.add_argument("--host", metavar="ADDRESS",
                        help=f"address {what} listen on (default {LOOPBACK}: this machine "
                             "only; 0.0.0.0 opens it to the network, which has no "
                             "authentication: only on a network you trust)")


def _mcap_argument(parser):
    parser.add_argument("--mcap", type=_path, metavar="FILE",
                        help="also write the run as ROS 2 messages (camera, depth, IMU, "
                             "magnetic field, tf, contact wrench, lumen) into an MCAP file, "
                             "as it goes, for Foxglove or `ros2 bag` (README, \"ROS 2 and "
                             "Foxglove: MCAP logs\")")


def _mcap_extend(path, scenario):
    """simulate's `extend` that adds the MCAP logger, or None."""
    if path is None:
        return None
    return lambda builder, station: add_mcap_logger(builder, station, scenario, path).close


def _report_mcap(result) -> str | None:
    """Prints where the MCAP log is; or, when writing it failed, prints nothing and returns
    the failure (one line: `_finish` reports it)."""
    diagram = result.diagram
    if diagram is None or not diagram.HasSubsystemNamed("mcap_logger"):
        return None
    log = diagram.GetSubsystemByName("mcap_logger").log
    if log.error is not None:
        return f"--mcap {log.error}"
    print(f"MCAP log: {log.messages} ROS 2 messages in {log.path} (open it in Foxglove, "
          "or `ros2 bag info` it)")
    return None


def _finish(result, mcap_failure: str | None) -> int:
    """The run's stop, if it stopped early, and a failed MCAP log, on stderr (one line each;
    a run that stopped because the MCAP could not be written: one line); the exit status
    (`_exit_code`, and at least 1 when the MCAP log failed)."""
    stopped = result.metrics.get("stopped_early") or ""
    if mcap_failure is None or mcap_failure.removeprefix("--mcap ") not in stopped:
        _report_stop(result)
    code = _exit_code(result)
    if mcap_failure is not None:
        print(f"capsule-sim: error: {mcap_failure}", file=sys.stderr)
        code = code or 1
    return code


def _out_arguments(parser, default: str, force: bool = True, mcap: bool = False):
    parser.add_argument("--out", type=_path, metavar="DIR",
                        help=f"output folder (default: {default}, a new folder each run); "
                             "an existing folder that holds files is refused"
                             + (" unless --force" if force else ""))
    if force:
        parser.add_argument("--force", action="store_true",
                            help="write into an existing --out folder, replacing a previous "
                                 "run's outputs there (refused without --out"
                                 + (" or --mcap" if mcap else "") + ")")


def _check_flag_combinations(args) -> None:
    """Refuses (ScenarioError: one line, exit 2) a flag that would do nothing in the
    combination given, before anything is loaded or written. What depends on the scenario
    (teleop's --port with the simulated operator) and on other flags' values (benchmark's
    --scenario, eval-lumen's light conditions) is checked where those are known."""
    if getattr(args, "force", False) and args.out is None and args.verb != "import-colon":
        has_mcap = hasattr(args, "mcap")
        if getattr(args, "mcap", None) is None:
            raise ScenarioError("--force: only with --out" + (" or --mcap" if has_mcap else "")
                                + " (it replaces a previous run's outputs there); without "
                                "--out, each run writes into a new folder")
    if args.verb == "run":
        if args.port is not None and not args.meshcat:
            raise ScenarioError("--port: only with --meshcat (the port of the live page; the "
                                "recording's own server takes any free port)")
    if args.verb == "benchmark":
        if args.address is not None and args.engine != "dask":
            raise ScenarioError("--address: only with --engine dask (the Dask scheduler the "
                                "benchmark runs on)")
        if args.workers is not None and args.address is not None:
            raise ScenarioError("--workers: not with --address (the scheduler's own workers "
                                "run the benchmark)")


def _plan(args, parent: str, name: str, outputs=RUN_OUTPUTS, *, mcap_bytes: float = 0.0,
          prefixes=(), inputs=()):
    """Every output path of the command, checked together before anything is built or run
    (app/outputs.py's `plan_outputs`): --out (refused if it holds files, unless --force) or
    a new folder parent/name-<date-time>, the --mcap file, and the `inputs` it reads."""
    return plan_outputs(args.out, getattr(args, "force", None), parent=parent, name=name,
                        outputs=outputs, prefixes=prefixes, mcap=getattr(args, "mcap", None),
                        mcap_bytes=mcap_bytes, inputs=inputs)


def _claim(plan) -> Path:
    """The planned folder, made (or a previous run's outputs removed from it, --force), and
    held by this command until it ends (another command naming it is refused)."""
    folder = plan.claim()
    if not plan.existed:
        _created_folders.append(folder)
    return folder


def _output_folder(args, parent: str, name: str, outputs=RUN_OUTPUTS) -> Path:
    """The folder a command writes into: --out (refused if it holds files, unless --force),
    or a new folder parent/name-<date-time> that no other run uses; checked (`_plan`), then
    made."""
    return _claim(_plan(args, parent, name, outputs))


# Output folders this command created: removed again if it fails before writing into them.
_created_folders: list[Path] = []


def _remove_unused_folders():
    release_claims()
    for folder in _created_folders:
        with contextlib.suppress(OSError):
            folder.rmdir()  # only if empty
    _created_folders.clear()


def _meshcat(host: str, port: int, announce: bool) -> Meshcat:
    """A Meshcat server on (host, port); its address printed when `announce` (a person will
    open it), Drake's own line silenced otherwise (a recording's server is noise)."""
    drake_log = logging.getLogger("drake")
    level = drake_log.level
    if not announce:
        drake_log.setLevel(logging.WARNING)
    try:
        meshcat = Meshcat(MeshcatParams(host=host, port=port))
    except RuntimeError as e:
        raise ScenarioError(f"--host {host} --port {port}: cannot start Meshcat "
                            f"({str(e).splitlines()[0]})") from None
    finally:
        drake_log.setLevel(level)
    if announce:
        print(f"Meshcat: {meshcat.web_url()}", file=sys.stderr)
    return meshcat


def _exit_code(result) -> int:
    """0 for a run that ran its course (or reached its goal); 128 + the signal for an
    interrupted one; 1 for one the guard stopped or an error ended."""
    if result.status in ("completed", "goal"):
        return 0
    if result.status == "interrupted":
        return 128 + signal.Signals[result.metrics.get("signal", "SIGINT")].value
    return 1


def _report_stop(result) -> None:
    m = result.metrics
    if m.get("stopped_early"):
        print(f"stopped early: {m['stopped_early']}"
              + ("; the simulation diverged, so no distance or force is reported from it"
                 if result.status == "diverged" else ""), file=sys.stderr)


MAX_SEEDS = 10_000  # a benchmark of more runs than this is a typing mistake


def parse_seeds(text: str, flag: str = "--seeds") -> list[int]:
    """Seeds from '0-9', '0,3,7' or '5'; ScenarioError (one line) on anything else."""
    ranges = []
    try:
        for part in text.split(","):
            first, _, last = part.strip().partition("-")
            ranges.append((int(first), int(last) if last else int(first)))
    except ValueError:
        raise ScenarioError(f"{flag} {text!r}: expected e.g. '0-9', '0,3,7' or '5'") from None
    if not all(0 <= first <= last < 2**32 for first, last in ranges):
        raise ScenarioError(f"{flag} {text!r}: expected seeds in [0, 2^32), each range from "
                            "low to high")
    if sum(last - first + 1 for first, last in ranges) > MAX_SEEDS:
        raise ScenarioError(f"{flag} {text!r}: at most {MAX_SEEDS:,} seeds")
    seeds = [seed for first, last in ranges for seed in range(first, last + 1)]
    if len(set(seeds)) != len(seeds):
        raise ScenarioError(f"{flag} {text!r}: a seed is given twice")
    return seeds


def _benchmark(args) -> int:
    tier_seeds, tier_text = TIERS[args.tier]
    seeds = parse_seeds(args.seeds if args.seeds is not None else tier_seeds)
    navigators = [n.strip() for n in args.navigators.split(",") if n.strip()]
    if not navigators:
        raise ScenarioError("--navigators: none given")
    if not (np.isfinite(args.duration) and 0 < args.duration <= 1e5):
        raise ScenarioError(f"--duration must be > 0 and <= 1e5 s, got {args.duration}")
    workers = 2 if args.workers is None else args.workers
    if not 1 <= workers <= 64:
        raise ScenarioError(f"--workers must be 1-64, got {workers}")
    scenario = "Navigation" if args.scenario is None else args.scenario
    run_timeout = (default_run_timeout(args.duration) if args.run_timeout is None
                   else args.run_timeout)
    if not (np.isfinite(run_timeout) and 0 < run_timeout <= 1e7):
        raise ScenarioError(f"--run-timeout must be > 0 and <= 1e7 s, got {run_timeout}")
    if args.polyp_detector:
        try:
            load_function("polyp detector", args.polyp_detector, "a function")
        except ValueError as e:
            raise ScenarioError(f"--polyp-detector: {e}") from None
    tasks = [Task(n, seed, args.duration, scenario, args.scenario_text,
                  tier_text=tier_text, polyp_detector=args.polyp_detector)
             for n in navigators for seed in seeds]
    # Fail on a bad navigator or scenario here, with one line, not in a worker.
    names = scenario_names(DEFAULT_SCENARIO_FILE)
    if scenario not in names:
        raise ScenarioError(f"--scenario {scenario!r}: no scenario of that name in "
                            f"{DEFAULT_SCENARIO_FILE.name} (it has: {', '.join(names)})")
    for navigator in navigators:
        try:
            task_scenario(Task(navigator, seeds[0], args.duration, scenario,
                               args.scenario_text, tier_text=tier_text))
        except ValueError as e:
            raise ScenarioError(str(e)) from None
    if args.scenario is not None and all(n in NAVIGATORS for n in navigators):
        raise ScenarioError("--scenario: only with a user's navigator (package.module:function); "
                            f"the built-in ones ({', '.join(navigators)}) are named scenarios "
                            "of their own")
    out_dir = _output_folder(args, "runs", "benchmark", outputs=BENCHMARK_OUTPUTS)
    # Rows as the runs finish, in the order they finish; runs.csv is written at the end.
    partial = RowWriter(out_dir / "runs-as-finished.csv")
    finished = []

    def keep(result):
        partial(result)
        finished.append(result)

    try:
        results = run_suite(tasks, workers=workers, engine=args.engine,
                            address=args.address, progress=not args.quiet, on_result=keep,
                            run_timeout=run_timeout)
    except EngineError as e:
        partial.path.unlink(missing_ok=True)
        raise ScenarioError(f"--address: {e}") from None
    except KeyboardInterrupt:
        # The runs have been stopped: the table and outputs of those that finished.
        order = {(task.navigator, task.seed): k for k, task in enumerate(tasks)}
        finished.sort(key=lambda r: order.get((r["row"]["navigator"], r["row"]["seed"]), 0))
        with NotedSignals():  # a second signal waits until the files are whole
            report(finished, out_dir)
        raise
    with NotedSignals() as signals:
        report(results, out_dir)
    signals.raise_noted()
    failed = [r["row"] for r in results if r["row"].get("status") == FAILED]
    if failed:
        print(f"capsule-sim: {len(failed)} of {len(results)} runs failed (the error column "
              f"says why): {', '.join(f'{r['navigator']} seed {r['seed']}' for r in failed)}",
              file=sys.stderr)
    return 1 if failed else 0


def _scenario_arguments(parser):
    parser.add_argument("scenario_file", nargs="?", type=_path, default=DEFAULT_SCENARIO_FILE,
                        help="YAML file of named scenarios (default: diagrams/default.yaml)")
    parser.add_argument("--scenario", metavar="NAME",
                        help="which scenario in the file (default: the only one, or 'Default')")
    parser.add_argument("--scenario-text", metavar="YAML",
                        help="YAML layered on top of the scenario, e.g. '{colon: {seed: 3}}'")
    parser.add_argument("--duration", type=float, metavar="S", help="simulated seconds")


def _flags(**values) -> str:
    """YAML text of a command's flags, layered on the scenario before it is checked."""
    return yaml.safe_dump(values, default_flow_style=True, width=1 << 20).strip()


def _load(args, *flags: str):
    """The scenario of the command line: the file's named scenario, the user's
    --scenario-text over it, then the command's own flags (YAML texts), then checked once."""
    overrides = [args.scenario_text]
    if args.duration is not None:
        overrides.append(_flags(duration=args.duration))
    return load_scenario(args.scenario_file, args.scenario, overrides + list(flags))


def _record(args) -> int:
    if args.seeds is not None:
        return _record_seeds(args)
    if args.split is not None:
        raise ScenarioError("--split: only with --seeds (it splits the seeds recorded)")
    scenario = _load(args)
    plan = _plan(args, "datasets", args.scenario or "Default", DATASET_OUTPUTS,
                 mcap_bytes=expected_mcap_bytes(with_all_sensors(scenario)),
                 inputs=[args.scenario_file])
    out_dir = _claim(plan)
    result = record(scenario, out_dir, progress=not args.quiet, mcap=plan.mcap,
                    scenario_name=args.scenario or "Default")
    frames = len(list((out_dir / "Frames").glob("FrameBuffer_*.png")))
    m = result.metrics
    print(f"recorded {frames} frames over {m.get('sim_time_s', 0.0):.2f} s into {out_dir}/ "
          f"(README.md there describes every file)")
    return _finish(result, _report_mcap(result))


def _split_fractions(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if (len(values) != 3 or not all(np.isfinite(v) and 0.0 <= v <= 1.0 for v in values)
            or abs(sum(values) - 1.0) > 1e-6):
        raise ScenarioError(f"--split {text!r}: expected three shares TRAIN,VAL,TEST in "
                            "[0, 1] that add up to 1, e.g. 0.7,0.15,0.15")
    return values


def _record_seeds(args) -> int:
    """One dataset per colon seed into --out/seed_XXXX/, with splits.csv and README.md."""
    if args.mcap is not None:
        raise ScenarioError("--mcap: not with --seeds (an MCAP log holds one recording; "
                            "record a seed on its own to log it)")
    seeds = parse_seeds(args.seeds, "--seeds")
    fractions = _split_fractions(args.split or "0.7,0.15,0.15")
    name = args.scenario or "Default"
    # Each seed is its own patient and its own noise; the user's --scenario-text comes after,
    # so it may fix random_seed (or anything else), but not the colon seed.
    def scenario_of(seed):
        scenario = load_scenario(args.scenario_file, args.scenario, [
            _flags(colon={"seed": seed}, random_seed=seed), args.scenario_text,
            *([_flags(duration=args.duration)] if args.duration is not None else [])])
        if getattr(scenario.colon, "seed", seed) != seed:
            raise ScenarioError("--seeds: --scenario-text sets colon.seed, which --seeds sets "
                                "for each recording")
        return scenario

    scenario_of(seeds[0])  # a bad scenario: one line before anything is written
    out_dir = _claim(_plan(args, "datasets", f"{name}-seeds", SEEDS_OUTPUTS,
                           prefixes=(SEED_PREFIX,), inputs=[args.scenario_file]))
    batch = record_seeds(scenario_of, seeds, fractions, out_dir, name, quiet=args.quiet,
                         on_stop=_report_stop)
    if batch.interrupted is not None:
        return _exit_code(batch.interrupted)
    print(f"recorded {len(batch.recorded)} of {len(seeds)} seeds into {out_dir}/ ("
          + ", ".join(f"{split} {n}" for split, n in batch.counts.items())
          + "; splits.csv and README.md there)"
          + (f"; failed: {', '.join(map(str, batch.failed))}" if batch.failed else ""))
    return 1 if batch.failed else 0


def _teleop(args) -> int:
    if args.scenario is None and args.scenario_file == DEFAULT_SCENARIO_FILE:
        args.scenario = "Teleop"
    # The verb makes the operator drive the EPM: `!Teleop` merges into the scenario's own
    # Teleop driver (or replaces another driver with the default one).
    # The UDP bridge's host: --host, else the scenario's (127.0.0.1 by default).
    port = DEFAULT_PORT if args.port is None else args.port
    teleop = {"udp": {"port": port, **({"host": args.host} if args.host else {})}}
    if args.operator is not None:
        teleop["operator"] = args.operator
    if args.delay is not None:
        teleop["channel"] = {"forward": {"delay": args.delay},
                             "backward": {"delay": args.delay}}
    flags = ["{epm: {driver: !Teleop " + _flags(**teleop) + "}}"]
    if args.guidance == "off":
        flags.append("{pseudo_force: null}")
    scenario = _load(args, *flags)
    teleop = scenario.epm.driver
    if args.port is not None and teleop.operator == "simulated":
        raise ScenarioError("--port: the simulated operator listens on no port (--port is the "
                            "page's with --operator browser, the device's with udp)")
    live = teleop.operator in ("browser", "udp")
    if live and scenario.simulator.target_realtime_rate == 0.0:
        # A person at the device: paced to the wall clock.
        scenario = _load(args, *flags, "{simulator: {target_realtime_rate: 1.0}}")
    plan = _plan(args, "runs", f"teleop-{teleop.operator}",
                 mcap_bytes=expected_mcap_bytes(scenario), inputs=[args.scenario_file])
    out_dir = _claim(plan)
    meshcat = _meshcat(args.host or LOOPBACK, port if teleop.operator == "browser" else 0,
                       announce=live)

    def announce(builder, station):
        if teleop.operator == "udp":
            device = station.GetSubsystemByName("teleop.device")
            print(f"listening for the haptic device on udp://{device.address()[0]}:"
                  f"{device.port()} (docs/udp_protocol.md)", file=sys.stderr)
        return None

    result = simulate(scenario, meshcat=meshcat, out_dir=out_dir, progress=not args.quiet,
                      live_meshcat=live,
                      extend=chain_extends(announce, _mcap_extend(plan.mcap, scenario)))
    m = result.metrics
    if m.get("advance_m") is not None:
        print(f"advanced {m['advance_m'] * 100:.1f} cm along the centerline in "
              f"{m['sim_time_s']:.1f} s (x{m['real_time_factor']:.2f} real time); peak "
              f"contact force {m['peak_contact_force_N']:.2f} N; closest EPM to skin "
              f"{m['min_epm_skin_gap_m'] * 1000:.0f} mm")
    mcap_failure = _report_mcap(result)
    print(f"outputs in {out_dir}/ (metrics.json, recording.html)")
    return _finish(result, mcap_failure)


def _eval_lumen(args) -> int:
    # Bounds: a frame takes ~0.1 s to render and each colon ~5 s to build.
    if not (1 <= args.frames <= 100_000 and 1 <= args.colons <= 1000):
        raise ScenarioError(f"--frames must be 1-100000 and --colons 1-1000, got "
                            f"{args.frames} and {args.colons}")
    if not 0 <= args.seed < 2**32:
        raise ScenarioError(f"--seed must be in [0, 2^32), got {args.seed}")
    if not 0.0 <= args.wall_fraction <= 1.0:
        raise ScenarioError(f"--wall-fraction must be in [0, 1], got {args.wall_fraction}")

    names = args.detector or ["net", "core", "gaussian"]
    try:
        detectors = {name: load_detector(name) for name in names}
    except ValueError as e:
        raise ScenarioError(f"--detector: {e}") from None
    renderers = RENDERERS if args.renderer == "both" else (args.renderer,)
    lenses = ("fisheye", "pinhole") if args.lens == "both" else (args.lens,)
    wanted = None if args.conditions == "all" else [c.strip() for c in
                                                     args.conditions.split(",") if c.strip()]
    known = IMAGE_CONDITIONS + LIGHT_CONDITIONS
    if wanted is not None and (not wanted or any(c not in known for c in wanted)):
        raise ScenarioError(f"--conditions: expected 'all' or a comma-separated list of "
                            f"{', '.join(known)}; got {args.conditions!r}")
    light = [c for c in wanted or () if c in LIGHT_CONDITIONS]
    if light and args.renderer == "vtk":
        raise ScenarioError(f"--conditions {','.join(light)}: the light conditions are only "
                            "with the ray caster (--renderer raycast or both)")
    out_dir = _output_folder(args, "eval_lumen", "eval", outputs=EVAL_OUTPUTS)
    try:
        failing = evaluate_paths(detectors, renderers, lenses, wanted or known, out_dir,
                                 frames=args.frames, colons=args.colons, seed=args.seed,
                                 wall_fraction=args.wall_fraction, quiet=args.quiet)
    except EvaluationStopped as e:   # a detector failed: what was scored is on disk
        print(f"capsule-sim: error: {e}", file=sys.stderr)
        return 1
    print(f"{'every condition meets' if not failing else f'{len(failing)} condition(s) miss'}"
          f" the targets (against the far region: median <= 1.5 %, p90 <= 4 %, detected >= "
          f"95 %, false positives <= 10 %; against the point 5 cm ahead: median / p90 <= "
          f"1.5 / 5 % fisheye, 3 / 8 % pinhole); tables.md, results.json and contact sheets "
          f"in {out_dir}/")
    return 0


def _run(args) -> int:
    # A live page is paced to the wall clock.
    scenario = _load(args, *(["{simulator: {target_realtime_rate: 1.0}}"] if args.meshcat else []))
    plan = _plan(args, "runs", args.scenario or "Default",
                 mcap_bytes=expected_mcap_bytes(scenario), inputs=[args.scenario_file])
    out_dir = _claim(plan)
    meshcat = None
    if args.meshcat:
        meshcat = _meshcat(args.host or LOOPBACK,
                           DEFAULT_PORT if args.port is None else args.port, announce=True)
    elif not args.no_recording:  # only for the recording
        meshcat = _meshcat(args.host or LOOPBACK, 0, announce=False)
    result = simulate(scenario, meshcat=meshcat, out_dir=out_dir,
                      progress=not args.quiet, live_meshcat=args.meshcat,
                      extend=_mcap_extend(plan.mcap, scenario),
                      recording=not args.no_recording)
    m = result.metrics
    if m.get("advance_m") is not None:
        print(f"advanced {m['advance_m'] * 100:.1f} cm along the centerline, from s = "
              f"{m['start_s_m'] * 100:.1f} cm to s = {m['final_s_m'] * 100:.1f} cm of "
              f"{m['colon_length_m'] * 100:.1f} cm; stopped in the {m['stop_segment']}")
        print(f"simulated {m['sim_time_s']:.2f} s in {m['wall_time_s']:.2f} s "
              f"(x{m['real_time_factor']:.2f} real time); {contact_words(m)}: peak contact "
              f"force {m['peak_contact_force_N']:.2f} N, largest excursion beyond the wall "
              f"{m['max_wall_excursion_m'] * 1000:.2f} mm; closest EPM to skin "
              f"{m['min_epm_skin_gap_m'] * 1000:.0f} mm")
    _report_pressure(m)
    _report_epm_guard(m)
    mcap_failure = _report_mcap(result)
    print(f"outputs in {out_dir}/ (metrics.json"
          f"{', wall_pressure.png' if (out_dir / 'wall_pressure.png').is_file() else ''}"
          f"{', recording.html' if not args.no_recording else ''})")
    code = _finish(result, mcap_failure)
    if args.meshcat:
        print("serving Meshcat; Ctrl-C to quit", file=sys.stderr)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
    return code


def contact_words(m: dict) -> str:
    """How a printed contact figure names the model it comes from (metrics' contact_model,
    physics/contact/), and, for the rigid stand-in, that its figures are the stand-in's."""
    model = m.get("contact_model")
    if model is None:   # metrics of a run before the models were named
        return "contact"
    if model.startswith("rigid"):
        return f"contact on the {model}, not a tissue figure"
    return f"contact on the {model}"


def pressure_summary(m: dict) -> str | None:
    """The run's pressure on the colon wall as one line, from its metrics' per-patch figures
    (io/metrics.py `site_pressure_metrics`): the highest pressure any patch of the wall felt
    and where, and the longest time ONE patch spent above each threshold (physics/tissue.py:
    330 kPa, mucosal injury; 4.0 kPa, blood flow falls) and where. "none" when the contact
    has no pressure field; None (nothing to say) for a run without the map or whose figures
    are null (it diverged, or ended before a sample)."""
    if "wall_pressure_field" not in m:
        return None
    patch = f"{m['wall_patch_length_m'] * 100:.0f} cm x {m['wall_patch_angle_deg']:.0f} deg"
    patch = f"{patch} patch" + (f", {contact_words(m)}" if "contact_model" in m else "")
    if not m["wall_pressure_field"]:
        return f"wall pressure per {patch}: none (the contact has no pressure field)"
    if m.get("site_peak_pressure_kPa") is None:
        return None

    def where(prefix):
        s = m.get(f"{prefix}_at_s_m")
        return f" ({m[f'{prefix}_segment']}, {s * 100:.1f} cm)" if s is not None else ""

    return (f"wall pressure per {patch}: peak {m['site_peak_pressure_kPa']:.0f} kPa"
            f"{where('site_peak')}; longest on one patch above {INJURY_PRESSURE / 1000:.0f} "
            f"kPa (mucosal injury) {m['site_longest_above_injury_s']:.2f} s, above "
            f"{ISCHAEMIA_PRESSURE / 1000:.1f} kPa (blood flow falls) "
            f"{m['site_longest_above_ischaemia_s']:.2f} s"
            f"{where('site_longest_above_ischaemia')}")


def _report_pressure(m: dict) -> None:
    """Prints `pressure_summary`'s line, if it has one."""
    line = pressure_summary(m)
    if line is not None:
        print(line)


def _report_epm_guard(metrics) -> None:
    """One line when the EPM guard (epm/guard.py) had to change the driver's commands."""
    changed = {name: metrics.get(f"epm_commands_{name}", 0)
               for name in ("raised", "clamped", "rejected")}
    if any(changed.values()):
        print(f"EPM guard: of {metrics.get('epm_commands', 0)} pose commands, "
              f"{changed['raised']} raised to the clearance, {changed['clamped']} clamped "
              f"to the workspace, {changed['rejected']} rejected (not finite: the last safe "
              f"one held)")


def _import_colon(args) -> int:
    stages = ["reading", "repairing", "centreline", "wall table"]
    bar = StepBar(len(stages), enabled=not args.quiet, unit="stages")

    def say(text):  # the stages before this one are done
        bar.show(next((k for k, name in enumerate(stages) if text.startswith(name)), 0), text)

    if not (args.scale > 0.0 and np.isfinite(args.scale)):
        raise ScenarioError(f"--scale must be > 0, got {args.scale}")
    if not 1000 <= args.max_faces <= 10_000_000:
        raise ScenarioError(f"--max-faces must be 1000-10000000, got {args.max_faces}")
    _claim(plan_outputs(args.out, args.force, outputs=IMPORT_OUTPUTS, inputs=[args.mesh]))
    try:
        wall = import_colon_mesh(args.mesh, args.scale, args.max_faces, args.reverse,
                                 progress=say)
    except ValueError as e:  # MeshImportError, or a mesh with no tube to follow
        if not args.quiet:
            print(file=sys.stderr)
        raise ScenarioError(str(e).splitlines()[0]) from None
    summary = write_import(wall, args.out)
    bar.show(len(stages), "done")
    radius = summary["radius_m"]
    print(f"imported {args.mesh}: {summary['faces']} faces"
          f"{' (textured)' if summary['textured'] else ''}; centreline "
          f"{100 * summary['centreline_length_m']:.1f} cm, radius {1000 * radius['min']:.1f}-"
          f"{1000 * radius['max']:.1f} mm (median {1000 * radius['median']:.1f})")
    for line in wall.report.lines():
        print(f"  repaired: {line}")
    print(f"wrote {args.out}/: wall.obj, centerline.npz, wall_radius.npz, import.json; "
          f"use it with colon: {{source: !Imported {{path: {args.out}}}}}")
    return 0


NOTEBOOKS_DIR = Path(__file__).resolve().parents[2] / "notebooks"


def _notebooks(args) -> int:
    """Replaces this process with JupyterLab on notebooks/ (it returns only on an error)."""
    if importlib.util.find_spec("jupyterlab") is None:
        raise ScenarioError("JupyterLab is not installed: ./capsule-sim notebooks installs it "
                            "into .venv; elsewhere run pip install -e '.[notebooks]' in the "
                            "repository")
    if not NOTEBOOKS_DIR.is_dir():
        raise ScenarioError(f"no notebooks folder at {NOTEBOOKS_DIR} (the notebooks come with "
                            "the repository: install it with pip install -e)")
    command = [sys.executable, "-m", "jupyterlab", f"--ServerApp.root_dir={NOTEBOOKS_DIR}",
               f"--ServerApp.ip={args.host or LOOPBACK}", f"--ServerApp.port={args.port}"]
    if args.no_browser:
        command.append("--no-browser")
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        command.append("--allow-root")  # a container's user (JupyterLab refuses root else)
    sys.stdout.flush()
    os.execv(sys.executable, command)
    return 0


def _raise_interrupted(signal_number, frame):
    raise Interrupted(signal_number)


def main(argv=None, noted=None) -> int:
    """The command. `noted`: signals that arrived before it (app/entry.py notes them while
    the libraries are imported); the first ends the command at once, as it would have."""
    noted = noted if noted is not None else []
    # A termination signal (kill, timeout, a closed terminal) ends a run as Ctrl-C does:
    # what was logged is written, then the exit status says which signal it was. SIGINT
    # too: a process started in the background (nohup, `&` in a script) inherits it ignored,
    # and Python then installs no Ctrl-C handler of its own.
    if threading.current_thread() is threading.main_thread():
        for number in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(number, _raise_interrupted)
    try:
        if noted:  # before anything ran
            raise Interrupted(noted[0])
        args = _parser().parse_args(argv)
        _created_folders.clear()
        _check_flag_combinations(args)
        if args.verb in COLON_VERBS:
            cache_base()  # a cache variable naming a file: one line, before anything is made
        if args.verb == "run":
            return _run(args)
        if args.verb == "record":
            return _record(args)
        if args.verb == "eval-lumen":
            return _eval_lumen(args)
        if args.verb == "teleop":
            return _teleop(args)
        if args.verb == "benchmark":
            return _benchmark(args)
        if args.verb == "import-colon":
            return _import_colon(args)
        if args.verb == "notebooks":
            return _notebooks(args)
    except (ScenarioError, WriteError, CacheError) as e:  # WriteError: after the run
        _remove_unused_folders()
        print(f"capsule-sim: error: {e}", file=sys.stderr)
        return 1 if isinstance(e, WriteError) else 2
    except OutputError as e:
        _remove_unused_folders()
        print(f"capsule-sim: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        name = getattr(e, "signal_name", "SIGINT")
        print(f"capsule-sim: interrupted ({name})", file=sys.stderr)
        return 128 + signal.Signals[name].value
    except BrokenPipeError:  # the output piped into a command that stopped reading
        sys.stderr.close()
        return 1
    except Exception as e:  # a defect, not the user's mistake: one line, the details on disk
        return _internal_error(e)
    finally:
        release_claims()  # the output folders this command held (the system would, at exit)
    return 0


def _internal_error(e: Exception) -> int:
    """An unexpected error: one line, and the traceback in a file for a bug report."""
    details = "".join(traceback.format_exception(e))
    try:
        handle, path = tempfile.mkstemp(prefix="capsule-sim-error-", suffix=".txt")
        with os.fdopen(handle, "w") as f:
            f.write(details)
        where = f"the traceback is in {path}"
    except OSError:
        where = "no file could be written for the traceback"
    text = str(e).strip().splitlines()[0] if str(e).strip() else ""
    print(f"capsule-sim: internal error: {type(e).__name__}: {text} ({where}; please report "
          "it with the command that caused it)", file=sys.stderr)
    return 70


if __name__ == "__main__":
    sys.exit(main())
