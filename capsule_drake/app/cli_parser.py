"""The command line's arguments: the verbs, their flags and what each flag accepts."""

from __future__ import annotations

import argparse
from pathlib import Path

from capsule_drake.app.benchmark import TIERS
from capsule_drake.scenario import DEFAULT_SCENARIO_FILE


# Servers (Meshcat, the UDP bridge) listen on this machine only unless --host says otherwise.
LOOPBACK = "127.0.0.1"


# The port of the live Meshcat page (run --meshcat, teleop --operator browser) and of the
# UDP bridge (teleop --operator udp) unless --port says otherwise.
DEFAULT_PORT = 7000


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
    _live_arguments(run)
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
    _live_arguments(tel)
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

    doc = verbs.add_parser(
        "docs", help="the documentation site: serve it here, or build it (--build)",
        description="Serve the documentation site (docs/, mkdocs.yml) on this machine with "
                    "live reload, or with --build write it as a static site. Strict either "
                    "way: a broken link, anchor or reference is an error. The reference pages "
                    "and the diagram's picture are made from the code as it builds. Needs the "
                    "docs extra: ./capsule-sim docs installs it into .venv the first time; "
                    "elsewhere pip install -e '.[docs]'.")
    doc.add_argument("--build", action="store_true",
                     help="write the static site (to site/, or --out) and exit")
    doc.add_argument("--out", type=_path, metavar="DIR",
                     help="with --build: the folder to write the site to (default site/)")
    doc.add_argument("--port", type=_port, default=8000,
                     help="the server's port (default 8000)")
    _host_argument(doc, "the documentation server")

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
                             "as it goes, for Foxglove or `ros2 bag` (docs/guides/live.md, "
                             "\"MCAP logs\")")


def _live_arguments(parser):
    parser.add_argument("--foxglove", type=_port, nargs="?", const=8765, metavar="PORT",
                        help="stream the run's channels live to Foxglove (a WebSocket server "
                             "on --host, port 8765 unless given; 0: any free port), paced "
                             "to real time: outputs.foxglove")
    parser.add_argument("--ros2", type=int, nargs="?", const=0, metavar="DOMAIN",
                        help="publish the run's channels as ROS 2 topics over DDS (domain 0 "
                             "unless given; this machine only unless --host 0.0.0.0), paced "
                             "to real time: outputs.ros2")


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


def _scenario_arguments(parser):
    parser.add_argument("scenario_file", nargs="?", type=_path, default=DEFAULT_SCENARIO_FILE,
                        help="YAML file of named scenarios (default: diagrams/default.yaml)")
    parser.add_argument("--scenario", metavar="NAME",
                        help="which scenario in the file (default: the only one, or 'Default')")
    parser.add_argument("--scenario-text", metavar="YAML",
                        help="YAML layered on top of the scenario, e.g. '{colon: {seed: 3}}'")
    parser.add_argument("--duration", type=float, metavar="S", help="simulated seconds")
