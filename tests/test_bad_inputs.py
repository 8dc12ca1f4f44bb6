"""Bad inputs and faults, as a careless user or a hostile environment produces them.

Every case asserts what docs/runs.md promises ("Bad inputs get one line", "Exit status"): a
non-zero exit, one line on stderr naming the culprit, no Python traceback, no hang, and
whatever had been logged on disk. The categories: scenario values, scenario files,
command-line flags, plug-ins, output folders and disks, signals, the run guard and errors
inside a simulation, and mesh import.
"""

import collections
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from mcap.writer import Writer as McapWriter

from capsule_drake.anatomy import importer
from capsule_drake.anatomy.imported import import_colon_mesh, write_import
from capsule_drake.app.cli import main as cli_main
from capsule_drake.app import outputs
from capsule_drake.app.mcap_file import Ros2McapFile
from capsule_drake.app.log_spool import load_logs
from tube_set import straight_tube

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "capsule_drake.app.cli"]
RUN = ["run", "--no-recording", "--quiet", "--duration", "0.2"]


def _text(yaml_text):
    """A short run with `yaml_text` laid over the Default scenario (--duration would
    override a duration in the text, so it is left out then)."""
    return (RUN[:-2] if "duration" in yaml_text else RUN) + ["--scenario-text", yaml_text]


# (id, arguments, the culprit the one line must name). {tmp} is a folder of bad files.
SCENARIO_VALUES = [
    ("time step 0.1 s", _text("{plant: {time_step: 0.1}}"), r"plant\.time_step"),
    ("time step 1 s", _text("{plant: {time_step: 1.0}}"), r"plant\.time_step"),
    ("time step 0", _text("{plant: {time_step: 0}}"), r"time_step"),
    ("NaN magnet dimension", _text("{epm: {magnet: {dimensions: [.nan, 0.1]}}}"),
     r"epm\.magnet\.dimensions"),
    ("negative remanence", _text("{capsule: {ipm: {remanence: -1.48}}}"),
     r"capsule\.ipm.*remanence"),
    ("zero EPM moment", _text("{epm: {magnet: {remanence: 0.0}}}"), r"epm\.magnet"),
    ("infinite colon diameter", _text("{colon: {sigmoid: {diameter: .inf}}}"),
     r"colon\.sigmoid\.diameter"),
    ("10 m colon diameter", _text("{colon: {sigmoid: {diameter: 10.0}}}"),
     r"colon\.sigmoid\.diameter"),
    ("clearance 1e6", _text("{epm: {clearance: 1.0e+6}}"), r"epm\.clearance"),
    ("random_seed -1", _text("{random_seed: -1}"), r"random_seed"),
    ("colon seed -5", _text("{colon: {seed: -5}}"), r"colon\.seed"),
    ("visual_period 0", _text("{outputs: {visual_period: 0}}"), r"outputs\.visual_period"),
    ("log_period 1e-7", _text("{outputs: {log_period: 1.0e-7}}"), r"outputs\.log_period"),
    ("duration NaN", _text("{duration: .nan}"), r"duration"),
    ("duration inf", _text("{duration: .inf}"), r"duration"),
    ("duration negative", _text("{duration: -1}"), r"duration"),
    ("friction inf", _text("{contact: {friction: .inf}}"), r"contact\.friction"),
    ("friction negative", _text("{contact: {friction: -0.1}}"), r"contact\.friction"),
    ("unknown tissue corner", _text("{colon: {source: !Population {tissue: mushy}}}"),
     r"colon\.source\.tissue must be one of drawn, nominal, soft, .*stiff_sticky, got 'mushy'"),
    ("tissue percentile 100", _text("{colon: {source: !Population {tissue_percentile: 100}}}"),
     r"colon\.source\.tissue_percentile must be in \(0, 100\)"),
    ("100000 px camera", _text("{capsule: {camera: {lens: {width: 100000}}}}"),
     r"width"),
    ("start before the colon", _text("{capsule: {start_s: -1}}"), r"capsule\.start_s"),
    ("start beyond the colon", _text("{capsule: {start_s: 100}}"), r"start_s"),
    ("unknown key", _text("{colon: {sead: 1}}"), r"colon\.sead: unknown key"),
    ("wrong type", _text("{duration: long}"), r"duration: expected a number"),
    ("moved key", _text("{time_step: 0.001}"), r"time_step: moved to plant\.time_step"),
    ("unknown tag", _text("{epm: {driver: !Fly {}}}"), r"unknown tag !Fly"),
    ("YAML syntax", _text("{duration: [1"), r"YAML syntax error"),
    ("nesting 20000 deep", _text("{colon: {rectal_valve_positions: "
                                 + "[" * 20000 + "]" * 20000 + "}}"), r"nest"),
    ("alias bomb", _text("{a: &a [x, x, x, x, x, x, x, x, x], "
                         + ", ".join(f"{k}: &{k} [" + ", ".join([f"*{p}"] * 9) + "]"
                                     for p, k in zip("abcdefgh", "bcdefghi"))
                         + "}"), r"alias"),
    ("guard off", _text("{guard: {max_speed: 0}}"), r"guard\.max_speed"),
    ("field model", _text("{magnet_force: {field_model: nonsense}}"),
     r"magnet_force\.field_model"),
    ("contact approximation", _text("{plant: {discrete_contact_approximation: tamsi}}"),
     r"plant"),
    ("IMU rate 0", _text("{capsule: {imu: {sample_rate: 0}}}"), r"capsule\.imu\.sample_rate"),
    ("tracker without camera", _text("{capsule: {lumen_tracker: {}}}"),
     r"needs capsule\.camera"),
    ("colon source missing", _text("{colon: {source: !Imported {path: /no/such/colon}}}"), r"/no/such/colon"),
    ("colon source a picture", _text("{colon: {source: !Imported {path: '{tmp}/photo.obj'}}}"),
     r"photo\.obj: a PNG image, not a mesh(?!.*module)"),
    ("colon source a triangle soup",
     _text("{colon: {source: !Imported {path: '{tmp}/soup.obj'}}}"),
     r"soup\.obj: not a tube: its 20,000 triangles fall apart .*\(a triangle soup\)"),
    ("unresolvable UDP host", _text("{epm: {driver: !Teleop {operator: udp, udp: "
                                    "{host: no.such.host.invalid}}}}"),
     r"no\.such\.host\.invalid"),
    ("start at an open end", _text("{colon: {source: !Imported {path: '{tmp}/imported'}}, "
                                   "capsule: {start_s: 0.018}}"),
     r"capsule\.start_s 0\.018 m: the capsule would stick out of the colon's open end"),
    ("realtime rate negative", _text("{simulator: {target_realtime_rate: -1}}"),
     r"target_realtime_rate"),
    # Text read otherwise than it looks (docs/runs.md: the last of a key given twice won; YAML
    # 1.1 read these forms as other numbers or booleans; Python's float() reads other digits).
    ("key given twice", _text("{epm: {clearance: 0.03, clearance: 0.04}}"),
     r"override:1: epm\.clearance: given twice"),
    ("hexadecimal number", _text("{colon: {seed: 0x10}}"),
     r"colon\.seed: 0x10 reads as the hexadecimal number 16"),
    ("base-60 number", _text("{random_seed: 1:30}"),
     r"random_seed: 1:30 reads as the base-60 number 90"),
    ("yes for true", _text("{magnet_force: {apply: yes}}"),
     r"magnet_force\.apply: yes reads as true"),
    ("number in quotes", _text("{epm: {clearance: '0.03'}}"),
     r"epm\.clearance: expected a number, got the text '0\.03' \(in quotes\)"),
    ("Arabic-Indic digits", _text("{colon: {seed: \u0663}}"),
     r"colon\.seed: expected an integer, got .*digits 0-9"),
    ("full-width digits", _text("{epm: {clearance: \uff10.\uff10\uff13}}"),
     r"epm\.clearance: expected a number, got .*digits 0-9"),
]

SCENARIO_FILES = [
    ("missing file", ["run", "{tmp}/none.yaml"], r"none\.yaml: scenario file not found"),
    ("device /dev/zero", ["run", "/dev/zero"], r"/dev/zero: not a regular file"),
    ("a folder", ["run", "{tmp}"], r"not a regular file"),
    ("binary file", ["run", "{tmp}/binary.yaml"], r"binary\.yaml: not text"),
    ("2 MB file", ["run", "{tmp}/huge.yaml"], r"huge\.yaml: .*MB"),
    ("named pipe", ["run", "{tmp}/fifo.yaml"], r"fifo\.yaml: not a regular file"),
    ("empty file", ["run", "{tmp}/empty.yaml"], r"empty\.yaml"),
    ("a list, not scenarios", ["run", "{tmp}/list.yaml"], r"list\.yaml: expected a mapping"),
    ("no such scenario", ["run", "--scenario", "NoSuch"], r"no scenario named 'NoSuch'"),
    ("alias bomb file", ["run", "{tmp}/bomb.yaml"], r"bomb\.yaml.*alias"),
    ("latin-1 text", ["run", "{tmp}/latin1.yaml"], r"latin1\.yaml: not text"),
]

FLAGS = [
    ("--duration nan", ["run", "--duration", "nan"], r"duration"),
    ("--duration inf", ["run", "--duration", "inf"], r"duration"),
    ("--duration -5", ["run", "--duration=-5"], r"duration"),
    ("--duration text", ["run", "--duration", "abc"], r"argument --duration"),
    ("--port 99999", ["run", "--port", "99999"], r"argument --port: 99999 is not a port"),
    ("--port -1", ["run", "--port=-1"], r"argument --port"),
    ("teleop --delay 1e9", ["teleop", "--delay", "1e9", "--duration", "0.1"], r"delay"),
    ("teleop --delay nan", ["teleop", "--delay", "nan", "--duration", "0.1"], r"delay"),
    ("teleop --delay -1", ["teleop", "--delay=-1", "--duration", "0.1"], r"delay"),
    ("--out empty", RUN + ["--out", ""], r"argument --out: empty path"),
    ("--out a run", RUN + ["--out", "{tmp}/previous_run"], r"folder exists and holds"),
    ("--out a file", RUN + ["--out", "{tmp}/binary.yaml"], r"exists and is not a folder"),
    ("--host unresolvable", RUN + ["--meshcat", "--port", "0",
                                        "--host", "no.such.host.invalid"],
     r"no\.such\.host\.invalid"),
    ("unknown flag", ["run", "--durationx", "3"], r"unrecognized arguments: --durationx"),
    ("unknown verb", ["fly"], r"invalid choice: 'fly'"),
    ("benchmark --seeds a-b", ["benchmark", "--seeds", "a-b"], r"--seeds 'a-b'"),
    ("benchmark --seeds negative", ["benchmark", "--seeds=-3"], r"--seeds"),
    ("benchmark --seeds 0-1e9", ["benchmark", "--seeds", "0-999999999"], r"at most 10,000"),
    ("benchmark --seeds 9-3", ["benchmark", "--seeds", "9-3"], r"low to high"),
    ("benchmark --workers 0", ["benchmark", "--workers", "0"], r"--workers"),
    ("benchmark --workers 10000", ["benchmark", "--workers", "10000"], r"--workers"),
    ("benchmark --duration nan", ["benchmark", "--duration", "nan"], r"--duration"),
    ("benchmark navigator", ["benchmark", "--navigators", "nonsense"], r"nonsense"),
    ("benchmark scenario", ["benchmark", "--scenario", "NoSuch"], r"--scenario 'NoSuch'"),
    ("benchmark live output", ["benchmark", "--seeds", "0", "--scenario-text",
                               "{outputs: {foxglove: {}}}"], r"outputs.foxglove is for one run"),
    ("run foxglove port", ["run", "--foxglove", "70000"], r"--foxglove: .*70000"),
    ("run ros2 goal without External", ["run", "--scenario-text",
                                        "{outputs: {ros2: {epm_command: true}}}"],
     r"outputs.ros2.epm_command needs epm.driver !External"),
    ("eval-lumen --frames 0", ["eval-lumen", "--frames", "0"], r"--frames"),
    ("eval-lumen --frames 1e9", ["eval-lumen", "--frames", "1000000000"], r"--frames"),
    ("eval-lumen --seed -1", ["eval-lumen", "--seed=-1"], r"--seed"),
    ("eval-lumen --wall-fraction 2", ["eval-lumen", "--wall-fraction", "2"],
     r"--wall-fraction"),
    ("eval-lumen detector", ["eval-lumen", "--detector", "nosuch"], r"--detector"),
    ("import --scale 0", ["import-colon", "{tmp}/tube.obj", "--out", "{tmp}/i1",
                          "--scale", "0"], r"--scale"),
    ("import --scale nan", ["import-colon", "{tmp}/tube.obj", "--out", "{tmp}/i2",
                            "--scale", "nan"], r"--scale"),
    ("import --max-faces 10", ["import-colon", "{tmp}/tube.obj", "--out", "{tmp}/i3",
                               "--max-faces", "10"], r"--max-faces"),
    ("record into a used folder", ["record", "--duration", "0.1", "--quiet", "--out",
                                   "{tmp}/previous_run"], r"folder exists and holds"),
]

PLUGINS = [
    ("navigator module missing", _text("{epm: {driver: !Plugin {factory: 'nosuch_mod:f'}}}"),
     r"no module 'nosuch_mod'"),
    ("navigator function missing", _text("{epm: {driver: !Plugin {factory: "
                                         "'plugins.navigators:nothing'}}}"),
     r"has no function 'nothing'"),
    ("navigator not a system", _text("{epm: {driver: !Plugin {factory: "
                                     "'plugins.navigators:not_a_system'}}}"),
     r"returned a int, not a Drake LeafSystem"),
    ("navigator fails to build", _text("{epm: {driver: !Plugin {factory: "
                                       "'plugins.navigators:fails_to_build'}}}"),
     r"failed to build its system \(KeyError"),
    ("navigator malformed name", _text("{epm: {driver: !Plugin {factory: 'justaname'}}}"),
     r"'justaname' is not"),
    ("detector missing", _text("{capsule: {camera: {}, lumen_tracker: "
                               "{detector: 'nosuch_mod:f'}}}"), r"no module 'nosuch_mod'"),
    # Before: a module that exits as it is imported, or a factory that exits, ended the
    # command with status 0, no outputs and no message.
    ("navigator exits at import", _text("{epm: {driver: !Plugin {factory: "
                                        "'plugins.exits_on_import:make'}}}"),
     r"navigator 'plugins\.exits_on_import:make': importing 'plugins\.exits_on_import' "
     r"failed \(SystemExit: 0\)"),
    ("detector exits at import", _text("{capsule: {camera: {}, lumen_tracker: {detector: "
                                       "'plugins.exits_on_import:detect'}}}"),
     r"lumen detector 'plugins\.exits_on_import:detect': importing "
     r"'plugins\.exits_on_import' failed \(SystemExit: 0\)"),
    ("benchmark navigator exits at import",
     ["benchmark", "--seeds", "0", "--duration", "1", "--out", "{out}", "--navigators",
      "plugins.exits_on_import:make"], r"importing 'plugins\.exits_on_import' failed "
                                       r"\(SystemExit: 0\)"),
    ("eval-lumen detector exits at import",
     ["eval-lumen", "--out", "{out}", "--detector", "plugins.exits_on_import:detect"],
     r"--detector: lumen detector 'plugins\.exits_on_import:detect': importing "
     r"'plugins\.exits_on_import' failed \(SystemExit: 0\)"),
    ("navigator exits in its factory", _text("{epm: {driver: !Plugin {factory: "
                                             "'plugins.misbehaving:exits_in_factory'}}}"),
     r"navigator 'plugins\.misbehaving:exits_in_factory' failed to build its system "
     r"\(SystemExit: 0\)"),
    ("navigator exits as the run is built", _text("{epm: {driver: !Plugin {factory: "
                                                  "'plugins.misbehaving:exits_as_it_is_built'"
                                                  "}}}"),
     r"scenario: navigator 'plugins\.misbehaving:exits_as_it_is_built' exited "
     r"\(SystemExit: 0\) as the run was built"),
    # Ports that do not fit the station: before, Drake's connection error, reported as an
    # internal error (status 70, "please report it").
    ("navigator command of 3", _text("{epm: {driver: !Plugin {factory: "
                                     "'plugins.misbehaving:short_command'}}}"),
     r"navigator 'plugins\.misbehaving:short_command': output port 'epm_command' is a vector "
     r"of size 3; the station needs a vector of size 6"),
    ("navigator command not a vector", _text("{epm: {driver: !Plugin {factory: "
                                             "'plugins.misbehaving:abstract_command'}}}"),
     r"navigator 'plugins\.misbehaving:abstract_command': output port 'epm_command' is an "
     r"abstract value \(float\); the station needs a vector of size 6"),
    ("navigator state of 7", _text("{epm: {driver: !Plugin {factory: "
                                   "'plugins.misbehaving:long_state'}}}"),
     r"navigator 'plugins\.misbehaving:long_state': input port 'capsule_state' is a vector "
     r"of size 7; the station gives it a vector of size 13"),
    ("navigator image as a vector", _text("{capsule: {camera: {latency: 0.0}}, epm: {driver: "
                                          "!Plugin {factory: "
                                          "'plugins.misbehaving:image_as_vector'}}}"),
     r"navigator 'plugins\.misbehaving:image_as_vector': input port 'rgb_image' is a vector "
     r"of size 3; the station gives it an abstract value \(Image\[PixelType\.kRgba8U\]\)"),
    ("navigator grey image", _text("{capsule: {camera: {latency: 0.0}}, epm: {driver: "
                                   "!Plugin {factory: 'plugins.misbehaving:grey_image'}}}"),
     r"navigator 'plugins\.misbehaving:grey_image': input port 'rgb_image' is an abstract "
     r"value \(Image\[PixelType\.kGrey8U\]\); the station gives it an abstract value "
     r"\(Image\[PixelType\.kRgba8U\]\)"),
]

# Output paths, all checked together before anything is built (app/outputs.py's
# plan_outputs): {out} is the test's own --out folder (not made beforehand).
OUTPUT_PATHS = [
    ("--mcap the run's scenario.yaml", RUN + ["--out", "{tmp}/previous_run", "--force",
                                              "--mcap", "{tmp}/previous_run/scenario.yaml"],
     r"previous_run/scenario\.yaml: scenario\.yaml in --out .* own outputs"),
    ("--mcap the run's logs.npz", RUN + ["--out", "{tmp}/empty_folder",
                                         "--mcap", "{tmp}/empty_folder/logs.npz"],
     r"logs\.npz in --out .* own outputs"),
    ("--mcap the --out folder", RUN + ["--out", "{out}", "--mcap", "{out}"],
     r"--mcap .*out: is the --out folder"),
    ("--out inside --mcap's path", RUN + ["--out", "{out}/inner", "--mcap", "{out}"],
     r"--out .*out/inner: lies inside --mcap's path"),
    ("--mcap an unrelated file, --force", RUN + ["--mcap", "{tmp}/binary.yaml", "--force"],
     r"binary\.yaml: file exists and is not an MCAP log written by capsule-sim"),
    ("--mcap another program's MCAP, --force", RUN + ["--mcap", "{tmp}/foreign.mcap",
                                                      "--force"],
     r"foreign\.mcap: file exists and is not an MCAP log written by capsule-sim"),
    ("--mcap a named pipe, --force", RUN + ["--mcap", "{tmp}/fifo.yaml", "--force"],
     r"fifo\.yaml: not a regular file \(a named pipe\)"),
    ("--mcap /dev/full, --force", RUN + ["--mcap", "/dev/full", "--force"],
     r"/dev/full: not a regular file \(a character device\)"),
    ("--mcap a link to an MCAP, --force", RUN + ["--mcap", "{tmp}/link.mcap", "--force"],
     r"link\.mcap: is a symbolic link \(to .*ours\.mcap\)"),
    ("--mcap a dangling link", RUN + ["--mcap", "{tmp}/dangling.mcap"],
     r"dangling\.mcap: is a symbolic link"),
    ("--force on a folder named metrics.json", RUN + ["--out", "{tmp}/odd_run", "--force"],
     r"odd_run: its metrics\.json is a folder, not a previous run's output"),
    ("--out holds the scenario file, --force", ["run", "{tmp}/scenario_here/scenario.yaml"]
     + RUN[1:] + ["--out", "{tmp}/scenario_here", "--force"],
     r"--out .*scenario_here: would replace .*scenario\.yaml, which this command reads"),
    ("record --mcap a dataset file", ["record", "--duration", "0.1", "--quiet", "--out",
                                      "{tmp}/empty_dataset", "--mcap",
                                      "{tmp}/empty_dataset/frames.csv"],
     r"frames\.csv in --out .* own outputs"),
    ("record --seeds --mcap", ["record", "--seeds", "0-1", "--duration", "0.1", "--quiet",
                               "--mcap", "{tmp}/seeds.mcap"], r"--mcap: not with --seeds"),
    ("import over its own mesh", ["import-colon", "{tmp}/own_mesh/wall.obj", "--out",
                                  "{tmp}/own_mesh", "--force", "--quiet"],
     r"--out .*own_mesh: would replace .*wall\.obj, which this command reads"),
]

IMPORT = [
    ("mesh missing", ["import-colon", "{tmp}/none.obj", "--out", "{tmp}/m1", "--quiet"],
     r"none\.obj: no such file"),
    ("mesh format", ["import-colon", "{tmp}/list.yaml", "--out", "{tmp}/m2", "--quiet"],
     r"unsupported format"),
    ("mesh garbage", ["import-colon", "{tmp}/garbage.obj", "--out", "{tmp}/m3", "--quiet"],
     r"garbage\.obj"),
    ("closed sphere", ["import-colon", "{tmp}/sphere.obj", "--out", "{tmp}/m4", "--quiet"],
     r"sphere\.obj.*(closed|not a tube|blob)"),
    ("wavy sheet", ["import-colon", "{tmp}/sheet.obj", "--out", "{tmp}/m5", "--quiet"],
     r"sheet\.obj: not a tube"),
    ("branching", ["import-colon", "{tmp}/branch.obj", "--out", "{tmp}/m6", "--quiet"],
     r"branch\.obj.*(branch|ends)"),
    ("point cloud", ["import-colon", "{tmp}/cloud.ply", "--out", "{tmp}/m7", "--quiet"],
     r"point cloud"),
    ("mesh in millimetres", ["import-colon", "{tmp}/tube_mm.obj", "--out", "{tmp}/m8", "--quiet"],
     r"tube_mm\.obj: 300 units across.*scale it by 0\.001"),
    ("empty mesh", ["import-colon", "{tmp}/empty.obj", "--out", "{tmp}/m9", "--quiet"], r"empty\.obj"),
    # A picture given for a mesh: its kind named, not what trimesh's text decoder lacked.
    ("PNG named .obj", ["import-colon", "{tmp}/photo.obj", "--out", "{tmp}/m10", "--quiet"],
     r"photo\.obj: a PNG image, not a mesh(?!.*module)"),
    ("JPEG named .obj", ["import-colon", "{tmp}/snapshot.obj", "--out", "{tmp}/m11",
                         "--quiet"], r"snapshot\.obj: a JPEG image, not a mesh(?!.*module)"),
    ("PNG named .stl", ["import-colon", "{tmp}/photo.stl", "--out", "{tmp}/m12", "--quiet"],
     r"photo\.stl: a PNG image, not a mesh(?!.*module)"),
    ("JPEG named .ply", ["import-colon", "{tmp}/snapshot.ply", "--out", "{tmp}/m13",
                         "--quiet"], r"snapshot\.ply: a JPEG image, not a mesh"),
    ("triangle soup", ["import-colon", "{tmp}/soup.obj", "--out", "{tmp}/m15", "--quiet"],
     r"soup\.obj: not a tube: its 20,000 triangles fall apart into 20,000 separate pieces"),
    ("mesh over the import's limit", ["import-colon", "{tmp}/huge.obj", "--out", "{tmp}/m16",
                                      "--quiet"],
     r"huge\.obj: [\d,]+ triangles, more than the [\d,]+ the import handles.*simplify"),
    ("binary bytes named .obj", ["import-colon", "{tmp}/noise.obj", "--out", "{tmp}/m14",
                                 "--quiet"],
     r"noise\.obj: not text \(an OBJ file is text(?!.*module)"),
    ("import into a used folder", ["import-colon", "{tmp}/tube.obj", "--out",
                                   "{tmp}/previous_run", "--quiet"], r"folder exists and holds"),
]

CASES = SCENARIO_VALUES + SCENARIO_FILES + FLAGS + PLUGINS + OUTPUT_PATHS + IMPORT


def _tube(length=0.3, radius=0.02, rings=60, around=32):
    """An open straight tube (the valid mesh the flag cases import)."""
    return straight_tube(length, radius, rings, around)


def _branch():
    """Three open tubes meeting at the origin: a Y."""
    parts = []
    for angle in (0.0, 2.1, 4.2):
        tube = _tube(length=0.15)
        direction = np.array([np.cos(angle), np.sin(angle), 0.0])
        rotation = trimesh.geometry.align_vectors([0, 0, 1], direction)
        tube.apply_transform(rotation)
        parts.append(tube)
    return trimesh.util.concatenate(parts)


@pytest.fixture(scope="module")
def bad_files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bad_inputs")
    rng = np.random.default_rng(0)
    (tmp / "binary.yaml").write_bytes(bytes(rng.integers(0, 256, 4096, dtype=np.uint8)))
    (tmp / "huge.yaml").write_text("Default: {}\n" + "# padding\n" * 220_000)
    os.mkfifo(tmp / "fifo.yaml")
    (tmp / "empty.yaml").write_text("")
    (tmp / "list.yaml").write_text("- a\n- b\n")
    lines = ["a: &a [x, x, x, x, x, x, x, x, x]"] + [
        f"{k}: &{k} [{', '.join([f'*{p}'] * 9)}]" for p, k in zip("abcdefgh", "bcdefghi")]
    (tmp / "bomb.yaml").write_text("\n".join(lines) + "\nDefault: {duration: 1}\n")
    (tmp / "latin1.yaml").write_bytes("Default: {}  # caf\xe9\n".encode("latin-1"))
    previous = tmp / "previous_run"
    previous.mkdir()
    (previous / "metrics.json").write_text("{}")
    _tube().export(tmp / "tube.obj")
    write_import(import_colon_mesh(tmp / "tube.obj"), tmp / "imported")
    (tmp / "garbage.obj").write_text("v 1 2\nf 1 2 x\nthis is not a mesh\n")
    trimesh.creation.icosphere(subdivisions=3, radius=0.05).export(tmp / "sphere.obj")
    x, y = np.meshgrid(np.linspace(0, 0.3, 40), np.linspace(0, 0.2, 30))
    z = 0.01 * np.sin(20 * x) * np.cos(15 * y)
    vertices = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    faces = []
    for i in range(29):
        for j in range(39):
            k = i * 40 + j
            faces += [[k, k + 1, k + 40], [k + 1, k + 41, k + 40]]
    sheet = trimesh.Trimesh(vertices, faces, process=False)
    sheet.export(tmp / "sheet.obj")
    _branch().export(tmp / "branch.obj")
    trimesh.PointCloud(rng.normal(size=(100, 3))).export(tmp / "cloud.ply")
    _tube().apply_scale(1000.0).export(tmp / "tube_mm.obj")
    (tmp / "empty.obj").write_text("")
    picture = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    for name, ext in (("photo", ".png"), ("snapshot", ".jpg")):
        ok, encoded = cv2.imencode(ext, picture)
        for suffix in (".obj", ".stl", ".ply"):
            (tmp / f"{name}{suffix}").write_bytes(encoded.tobytes())
    (tmp / "noise.obj").write_bytes(bytes(rng.integers(0, 256, 4096, dtype=np.uint8)))
    corners = rng.uniform(0.0, 0.3, (20_000, 1, 3)) + rng.normal(0.0, 0.002, (20_000, 3, 3))
    trimesh.Trimesh(corners.reshape(-1, 3), np.arange(60_000).reshape(-1, 3),
                    process=False).export(tmp / "soup.obj")
    with open(tmp / "huge.obj", "wb") as f:  # one face more than the import takes
        f.write(b"v 0 0 0\nv 0.1 0 0\nv 0 0.1 0.05\n")
        f.write(b"f 1 2 3\n" * (importer.MAX_IMPORT_FACES + 1))
    # Output paths: empty folders, an MCAP of this simulator's and one of another program's,
    # links, a folder with a folder where a run's file goes, inputs inside an --out folder.
    (tmp / "empty_folder").mkdir()
    (tmp / "empty_dataset").mkdir()
    ours = Ros2McapFile(tmp / "ours.mcap")
    ours.write("/tf", "tf2_msgs/msg/TFMessage", {"transforms": []}, 0)
    ours.close()
    with open(tmp / "foreign.mcap", "wb") as f:
        writer = McapWriter(f)
        writer.start(profile="ros2", library="another-recorder")
        writer.finish()
    (tmp / "link.mcap").symlink_to(tmp / "ours.mcap")
    (tmp / "dangling.mcap").symlink_to(tmp / "nowhere.mcap")
    (tmp / "odd_run" / "metrics.json").mkdir(parents=True)
    (tmp / "odd_run" / "metrics.json" / "notes.txt").write_text("mine")
    (tmp / "scenario_here").mkdir()
    (tmp / "scenario_here" / "scenario.yaml").write_text("Default: {duration: 0.1}\n")
    (tmp / "own_mesh").mkdir()
    (tmp / "own_mesh" / "wall.obj").write_bytes((tmp / "tube.obj").read_bytes())
    return tmp


def _argv(args, tmp, out=None):
    return [a.replace("{tmp}", str(tmp)).replace("{out}", str(out)) for a in args]


def _error_lines(err: str) -> list[str]:
    """stderr's lines, without the announcement of a plug-in being loaded (not an error)."""
    return [line for line in err.splitlines() if line.strip() and not line.startswith("plug-in ")]


def _assert_one_line(code, err, culprit):
    assert code != 0, err
    assert "Traceback" not in err, err
    lines = _error_lines(err)
    assert len(lines) == 1, err
    assert re.search(culprit, lines[0]), lines[0]
    assert "internal error" not in lines[0], lines[0]
    return lines[0]


# Cases that could hang if their check regressed run in a subprocess with a time limit.
HANG_PRONE = {"device /dev/zero", "named pipe", "nesting 20000 deep", "alias bomb",
              "alias bomb file", "100000 px camera", "teleop --delay 1e9", "log_period 1e-7",
              "duration inf", "--duration inf", "--mcap a named pipe, --force",
              "--mcap /dev/full, --force"}


# The hang-prone cases run in a process of their own (3-4 s each, most of it the import):
# the full suite's, not the fast loop's.
@pytest.mark.parametrize("name,args,culprit", [
    pytest.param(*c, marks=pytest.mark.slow) if c[0] in HANG_PRONE else c for c in CASES],
    ids=[c[0] for c in CASES])
def test_a_bad_input_gives_one_line(name, args, culprit, bad_files, tmp_path, capsys):
    argv = _argv(args, bad_files, tmp_path / "out")
    if argv[0] in ("run", "teleop", "record") and "--out" not in argv:
        argv += ["--out", str(tmp_path / "out")]
    if name in HANG_PRONE:
        done = subprocess.run(CLI + argv, cwd=REPO, capture_output=True, text=True, timeout=120)
        code, err = done.returncode, done.stderr
    else:
        try:
            code = cli_main(argv)
        except SystemExit as e:  # argparse
            code = e.code
        err = capsys.readouterr().err
    _assert_one_line(code, err, culprit)
    # Nothing was simulated: no output folder left behind, or (if the run had started) one
    # holding what it logged.
    out = tmp_path / "out"
    if name in {c[0] for c in PLUGINS}:  # a plug-in that cannot be used is a bad input
        assert code == 2, err
        assert not out.exists() or not any(out.iterdir())
    if out.exists() and any(out.iterdir()):
        assert (out / "metrics.json").is_file() and (out / "logs.npz").is_file()
    if name in {c[0] for c in OUTPUT_PATHS}:  # refused before anything was made or changed
        assert not out.exists()
        assert (bad_files / "previous_run" / "metrics.json").read_text() == "{}"
        assert not any((bad_files / "empty_folder").iterdir())
        assert not any((bad_files / "empty_dataset").iterdir())
        assert (bad_files / "binary.yaml").stat().st_size == 4096
        assert (bad_files / "odd_run" / "metrics.json" / "notes.txt").read_text() == "mine"
        assert "duration" in (bad_files / "scenario_here" / "scenario.yaml").read_text()
        assert (bad_files / "own_mesh" / "wall.obj").stat().st_size > 1000


# Flags that would do nothing in the combination given: refused in one line, exit 2, before
# anything is written (the commands run in an empty folder, where a run without --out would
# make its own). Before, each was accepted and ignored.
BENCH = ["benchmark", "--seeds", "0", "--navigators", "autonomy-truth", "--duration", "0.1",
         "--quiet"]
EVAL_ONE = ["eval-lumen", "--frames", "1", "--colons", "1", "--renderer", "raycast", "--lens",
            "fisheye", "--conditions", "nominal", "--detector", "core", "--quiet"]
IDLE_FLAGS = [
    ("run --force without --out", RUN + ["--force"],
     r"--force: only with --out or --mcap \(it replaces a previous run's outputs there\)"),
    ("teleop --force without --out", ["teleop", "--duration", "0.1", "--quiet", "--force"],
     r"--force: only with --out or --mcap"),
    ("benchmark --force without --out", BENCH + ["--force"], r"--force: only with --out"),
    ("eval-lumen --force without --out", EVAL_ONE + ["--force"], r"--force: only with --out"),
    ("--address without --engine dask", BENCH + ["--address", "127.0.0.1:8786"],
     r"--address: only with --engine dask"),
    ("--workers with --address", BENCH + ["--engine", "dask", "--address", "127.0.0.1:1",
                                          "--workers", "3"],
     r"--workers: not with --address \(the scheduler's own workers run the benchmark\)"),
    ("benchmark --scenario for built-in navigators", BENCH + ["--scenario", "Default"],
     r"--scenario: only with a user's navigator"),
    ("run --port without --meshcat", RUN + ["--port", "7123"], r"--port: only with --meshcat"),
    ("teleop --port, simulated operator", ["teleop", "--duration", "0.1", "--quiet",
                                           "--operator", "simulated", "--port", "7123"],
     r"--port: the simulated operator"),
    ("eval-lumen light conditions with vtk", EVAL_ONE[:5] + ["--renderer", "vtk", "--lens",
                                                              "fisheye", "--conditions",
                                                              "light_all", "--quiet"],
     r"--conditions light_all: .*only with the ray caster"),
]


@pytest.mark.parametrize("name,args,culprit", IDLE_FLAGS, ids=[c[0] for c in IDLE_FLAGS])
def test_a_flag_that_would_do_nothing_is_refused(name, args, culprit, tmp_path, monkeypatch,
                                                capsys):
    monkeypatch.chdir(tmp_path)
    code, err = cli_main(args), capsys.readouterr().err
    _assert_one_line(code, err, culprit)
    assert code == 2
    assert not any(tmp_path.iterdir())


@pytest.mark.slow
def test_no_recording_with_a_live_page_writes_no_recording(tmp_path):
    # Before, --no-recording did nothing with --meshcat: the run still wrote recording.html.
    out = tmp_path / "run"
    process = subprocess.Popen(CLI + ["run", "--duration", "0.1", "--quiet", "--meshcat",
                                      "--port", "0", "--no-recording", "--out", str(out)],
                               cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    try:
        for line in process.stderr:  # it serves the page after the run, until Ctrl-C
            if line.startswith("serving Meshcat"):
                break
        process.send_signal(signal.SIGINT)
        stdout, _ = process.communicate(timeout=60)
    finally:
        process.kill()
    assert "outputs in " in stdout and "recording.html" not in stdout, stdout
    assert sorted(p.name for p in out.iterdir()) == ["logs.npz", "metrics.json",
                                                     "scenario.yaml", "wall_pressure.npz",
                                                     "wall_pressure.png"]


@pytest.mark.slow
def test_a_foxglove_port_in_use_is_one_line_and_nothing_runs(tmp_path, capsys):
    import socket
    with socket.socket() as held:   # another server on the port
        held.bind(("127.0.0.1", 0))
        held.listen(1)
        port = held.getsockname()[1]
        code = cli_main(["run", "--duration", "0.1", "--foxglove", str(port), "--no-recording",
                         "--quiet", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error" in line]
    assert code == 2 and len(errors) == 1 and "Traceback" not in err, err
    assert f"127.0.0.1:{port}" in errors[0] and "in use" in errors[0], errors[0]
    assert not (tmp_path / "run" / "metrics.json").exists()


@pytest.mark.slow
def test_force_without_out_replaces_a_previous_mcap_log(tmp_path, monkeypatch, capsys):
    # --force does something without --out when there is an --mcap to replace.
    monkeypatch.chdir(tmp_path)
    args = RUN[:-1] + ["0.05", "--mcap", str(tmp_path / "run.mcap")]
    assert cli_main(args) == 0
    assert cli_main(args + ["--force"]) == 0, capsys.readouterr().err
    assert len(list((tmp_path / "runs").iterdir())) == 2


def test_there_are_at_least_60_cases():
    assert len(CASES) >= 60
    assert len({name for name, *_ in CASES}) == len(CASES)


# --- Faults during a run: what was logged is on disk ---------------------------------------

def test_a_diverging_run_stops_in_one_line_with_its_logs(tmp_path, capsys):
    # A guard that the capsule's starting drop trips: the run guard's stop, end to end.
    out = tmp_path / "run"
    code = cli_main(RUN[:-1] + ["2", "--scenario-text", "{guard: {max_speed: 0.05}}",
                                "--out", str(out)])
    line = _assert_one_line(code, capsys.readouterr().err, r"run guard at t = ")
    assert "no distance" in line
    assert load_logs(out)["times"].size >= 2
    assert json.loads((out / "metrics.json").read_text())["advance_m"] is None


# Plug-ins that break inside the simulation, and the one line that names each. Before: the
# line did not name the navigator; one that exited was reported as such a line too, and one
# that raised KeyboardInterrupt itself as a Ctrl-C (status 130).
BROKEN_IN_THE_RUN = [
    ("plugins.navigators:fails_later", "ZeroDivisionError",
     r"navigator 'plugins\.navigators:fails_later' raised ZeroDivisionError: the navigator "
     r"divided by zero"),
    ("plugins.misbehaving:exits_later", "SystemExit",
     r"navigator 'plugins\.misbehaving:exits_later' exited \(SystemExit: 0\)"),
    ("plugins.misbehaving:interrupts_later", "KeyboardInterrupt",
     r"navigator 'plugins\.misbehaving:interrupts_later' raised KeyboardInterrupt"),
    ("plugins.misbehaving:shrinks_later", "size",
     r"navigator 'plugins\.misbehaving:shrinks_later' raised \w+: .*size"),
]


@pytest.mark.parametrize("navigator,error,culprit", BROKEN_IN_THE_RUN,
                         ids=[n.split(":")[1] for n, *_ in BROKEN_IN_THE_RUN])
def test_an_error_inside_the_simulation_is_one_line_with_its_logs(navigator, error, culprit,
                                                                   tmp_path, capsys):
    out = tmp_path / "run"
    code = cli_main(RUN[:-1] + ["2", "--scenario-text",
                                f"{{epm: {{driver: !Plugin {{factory: '{navigator}'}}}}}}",
                                "--out", str(out)])
    line = _assert_one_line(code, capsys.readouterr().err,
                            r"simulation error at t = 0\.5\d* s: " + culprit)
    assert code == 1, line
    assert json.loads((out / "metrics.json").read_text())["status"] == "error"
    assert load_logs(out)["times"][-1] >= 0.4
    assert error in (out / "error.txt").read_text()


# A user's lumen detector in the tracker that ends the program or returns what is not a
# result. Before: the one that exited was reported without its name; the others were
# counted as the tracker's failures, a warning each frame, and the run exited 0.
TRACKER = ("{capsule: {camera: {fps: 10.0, latency: 0.0}, lumen_tracker: {detector: "
           "'plugins.detectors:%s'}}}")
BROKEN_DETECTORS = [
    ("exits", r"lumen detector 'plugins\.detectors:exits' exited \(SystemExit: 0\)"),
    ("wrong_shape", r"lumen detector 'plugins\.detectors:wrong_shape' returned pixel = "
                    r"\[10, 20, 1\] of shape \(3,\), not a pair \(u, v\)"),
    ("returns_none", r"lumen detector 'plugins\.detectors:returns_none' returned None, which "
                     r"is not a result"),
]


@pytest.mark.parametrize("detector,culprit", BROKEN_DETECTORS,
                         ids=[d for d, _ in BROKEN_DETECTORS])
def test_a_detector_that_breaks_in_the_run_fails_it_in_one_line(detector, culprit, tmp_path,
                                                                 capsys):
    out = tmp_path / "run"
    code = cli_main(RUN[:-1] + ["0.5", "--scenario-text", TRACKER % detector,
                                "--out", str(out)])
    line = _assert_one_line(code, capsys.readouterr().err,
                            r"simulation error at t = 0\.\d+ s: " + culprit)
    assert code == 1, line
    assert json.loads((out / "metrics.json").read_text())["status"] == "error"
    assert load_logs(out)["times"].size >= 1 and (out / "error.txt").is_file()


@contextlib.contextmanager
def _tmpfs(path: Path, size: str, read_only: bool = False):
    """A small tmpfs at `path` (a real full or read-only disk), or None where this process
    may not mount one."""
    path.mkdir()
    options = f"size={size}" + (",ro" if read_only else "")
    mounted = os.geteuid() == 0 and subprocess.run(
        ["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)],
        capture_output=True).returncode == 0
    try:
        yield path if mounted else None
    finally:
        if mounted:
            subprocess.run(["umount", str(path)], check=False)


def test_a_read_only_disk_is_found_before_the_run(tmp_path, capsys):
    with _tmpfs(tmp_path / "ro", "1m", read_only=True) as ro:
        if ro is None:  # not root: a folder without write permission instead
            ro = tmp_path / "ro"
            ro.chmod(0o555)
        start = time.perf_counter()
        code = cli_main(["run", "--duration", "30", "--no-recording", "--quiet",
                         "--out", str(ro / "run")])
        _assert_one_line(code, capsys.readouterr().err,
                         re.escape(str(ro)) + r".*cannot create the output folder")
        assert time.perf_counter() - start < 20  # refused before 30 s of simulation


def test_a_full_disk_is_found_before_the_run(tmp_path, capsys):
    with _tmpfs(tmp_path / "full", "2m") as full:
        if full is None:
            pytest.skip("needs root to mount a small tmpfs (a real full disk)")
        code = cli_main(["run", "--duration", "30", "--quiet", "--out", str(full / "run")])
        _assert_one_line(code, capsys.readouterr().err, r"MB free, but the run will write")


def test_a_full_disk_leaves_nothing_that_blocks_the_retry(tmp_path, capsys):
    # A real full disk: the run is refused in one line and leaves no folder; once there is
    # room, the same --out (without --force) runs.
    with _tmpfs(tmp_path / "disk", "40m") as disk:
        if disk is None:
            pytest.skip("needs root to mount a small tmpfs (a real full disk)")
        filler = disk / "filler"
        with open(filler, "wb", buffering=0) as f, contextlib.suppress(OSError):
            while True:
                f.write(b"\0" * (1 << 20))
        args = ["run", "--duration", "0.05", "--no-recording", "--quiet",
                "--out", str(disk / "run")]
        code = cli_main(args)
        _assert_one_line(code, capsys.readouterr().err, re.escape(
            f"{disk / 'run'}: cannot write to the output folder (No space left on device)"))
        assert code == 2
        assert not (disk / "run").exists()
        filler.unlink()
        assert cli_main(args) == 0, capsys.readouterr().err
        assert sorted(p.name for p in (disk / "run").iterdir()) == [
            "logs.npz", "metrics.json", "scenario.yaml", "wall_pressure.npz",
            "wall_pressure.png"]


@pytest.mark.slow
def test_an_mcap_log_a_full_disk_cut_short_does_not_block_the_retry(tmp_path, capsys,
                                                                    monkeypatch):
    # The MCAP log's disk is full when its first chunk is written (the room check is told
    # there is room, as if another program filled the disk during the run). Before, an
    # empty run.mcap stayed, which the retry refused even with --force (not an MCAP log of
    # this simulator).
    real_statvfs = os.statvfs

    class Roomy:
        def __init__(self, real):
            self._real = real

        def __getattr__(self, name):
            return 10 ** 9 if name == "f_bavail" else getattr(self._real, name)

    monkeypatch.setattr(outputs.os, "statvfs", lambda path: Roomy(real_statvfs(path)))
    with _tmpfs(tmp_path / "disk", "1m") as disk:
        if disk is None:
            pytest.skip("needs root to mount a small tmpfs (a real full disk)")
        filler = disk / "filler"
        with open(filler, "wb", buffering=0) as f, contextlib.suppress(OSError):
            while True:
                f.write(b"\0" * 4096)
        mcap = disk / "run.mcap"
        args = RUN + ["--scenario-text", "{capsule: {imu: {}}}", "--mcap", str(mcap)]
        code = cli_main(args + ["--out", str(tmp_path / "a")])
        line = _assert_one_line(code, capsys.readouterr().err,
                                re.escape(f"--mcap {mcap}: could not write the MCAP log (No "
                                          "space left on device)"))
        assert code == 1, line
        assert not mcap.exists()   # it held nothing: removed
        filler.unlink()
        assert cli_main(args + ["--out", str(tmp_path / "b")]) == 0, capsys.readouterr().err
        assert "MCAP log: " in capsys.readouterr().out


@pytest.mark.slow
def test_a_disk_that_fills_during_the_run_loses_no_logs(tmp_path, capsys, monkeypatch):
    # 4 MB: room for the logs, not for the 16 MB recording. The room check is told there
    # is plenty, as if another program filled the disk during the run.
    Usage = collections.namedtuple("Usage", "total used free")
    monkeypatch.setattr(outputs.shutil, "disk_usage", lambda path: Usage(1e12, 0, 1e12))
    with _tmpfs(tmp_path / "small", "4m") as small:
        if small is None:
            pytest.skip("needs root to mount a small tmpfs (a real full disk)")
        code = cli_main(["run", "--duration", "0.5", "--quiet", "--out", str(small / "run")])
        _assert_one_line(code, capsys.readouterr().err,
                         r"could not write recording\.html \(No space left on device\)")
        assert code == 1
        names = sorted(p.name for p in (small / "run").iterdir())
        # Everything before the recording is whole; no partial file is left.
        assert names == ["logs.npz", "metrics.json", "scenario.yaml", "wall_pressure.npz",
                         "wall_pressure.png"], names
        assert load_logs(small / "run")["times"][-1] == pytest.approx(0.5)


def _file_size_limit(size):
    """A child's preexec_fn: files it writes may not grow past `size` bytes (a write beyond
    fails with EFBIG: Python ignores SIGXFSZ), a disk that fills without root or a mount."""
    import resource
    return lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))


@pytest.mark.slow
def test_an_mcap_log_that_cannot_be_written_is_reported_as_failed(tmp_path):
    # The run's own files (for 3 s: logs.npz ~44 kB, wall_pressure.png ~31 kB) fit under
    # 60 kB; the MCAP log does not (its first chunk holds the scene's colon, ~2 MB): writing
    # it fails, and the run stops there. It must not be reported as written: one line naming
    # it, exit 1, the run's outputs on disk.
    out, mcap = tmp_path / "run", tmp_path / "run.mcap"
    done = subprocess.run(CLI + ["run", "--duration", "3", "--no-recording", "--quiet",
                                 "--scenario-text", "{capsule: {imu: {}}}", "--out", str(out),
                                 "--mcap", str(mcap)],
                          cwd=REPO, capture_output=True, text=True, timeout=300,
                          preexec_fn=_file_size_limit(60_000))
    _assert_one_line(done.returncode, done.stderr, re.escape(f"--mcap {mcap}: could not write "
                                                             "the MCAP log (File too large)"))
    assert done.returncode == 1
    assert "MCAP log:" not in done.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "error" and "MCAP" in metrics["stopped_early"]
    assert load_logs(out)["times"][-1] < 0.1   # stopped at the MCAP's first chunk


@pytest.mark.slow
def test_force_replaces_a_previous_mcap_log_only(tmp_path, capsys):
    mcap = tmp_path / "run.mcap"
    args = RUN[:-1] + ["0.05", "--mcap", str(mcap)]
    assert cli_main(args + ["--out", str(tmp_path / "a")]) == 0
    first = mcap.read_bytes()
    capsys.readouterr()
    code = cli_main(args + ["--out", str(tmp_path / "b")])
    _assert_one_line(code, capsys.readouterr().err,
                     r"run\.mcap: file exists \(an MCAP log written by capsule-sim\); choose "
                     r"another name, or add --force")
    assert mcap.read_bytes() == first and not (tmp_path / "b").exists()
    assert cli_main(args + ["--out", str(tmp_path / "c"), "--force"]) == 0
    assert "MCAP log: " in capsys.readouterr().out


# --- A user's lumen detector that fails in eval-lumen ------------------------------------

EVAL = ["eval-lumen", "--frames", "1", "--colons", "1", "--seed", "20", "--quiet",
        "--renderer", "raycast", "--lens", "fisheye", "--conditions", "nominal",
        "--detector", "core"]
FAILING_DETECTORS = [
    ("raises", r"lumen detector plugins\.detectors:raises raised ZeroDivisionError: the "
               r"detector divided by zero on frame 0 of 1 \(raycast, fisheye, nominal: \w+ "
               r"view, colon seed 20, s = [\d.]+ cm\); the traceback is in .*error\.txt"),
    ("returns_none", r"plugins\.detectors:returns_none returned None, which is not a result: "
                     r"a detector reports no lumen with visible False .* on frame 0 of 1 "
                     r"\(raycast, fisheye, nominal"),
    ("returns_nan", r"plugins\.detectors:returns_nan returned nan \(float\), not a result "
                    r".* on frame 0 of 1"),
    ("nan_pixel", r"plugins\.detectors:nan_pixel returned pixel = \[nan, nan\] with visible "
                  r"True: a lumen it sees needs a finite \(u, v\), on frame 0 of 1"),
    ("wrong_shape", r"plugins\.detectors:wrong_shape returned pixel = \[10, 20, 1\] "
                    r"of shape \(3,\), not a pair \(u, v\), on frame 0"),
    # Before: the exit ended eval-lumen with status 0, taking the core detector's scores.
    ("exits", r"lumen detector plugins\.detectors:exits exited \(SystemExit: 0\) on frame 0 "
              r"of 1 \(raycast, fisheye, nominal"),
    # Before: it wrote into the frames the next detectors score, with status 0.
    ("scribbles", r"lumen detector plugins\.detectors:scribbles raised ValueError: "
                  r"assignment destination is read-only \(a detector is given a read-only "
                  r"frame and field mask: copy them to change them\) on frame 0 of 1"),
    ("clears_the_mask", r"lumen detector plugins\.detectors:clears_the_mask raised "
                        r"ValueError: .*read-only .* on frame 0 of 1"),
]


@pytest.mark.parametrize("detector,culprit", FAILING_DETECTORS,
                         ids=[d for d, _ in FAILING_DETECTORS])
def test_a_users_detector_that_fails_is_one_line_and_keeps_the_scores(detector, culprit,
                                                                     tmp_path, capsys):
    # The built-in detector is scored first, then the user's fails on the first frame: one
    # line naming it, the frame and what it did; what was scored is written; exit 1.
    out = tmp_path / "eval"
    code = cli_main(EVAL + ["--detector", f"plugins.detectors:{detector}", "--out", str(out)])
    _assert_one_line(code, capsys.readouterr().err, culprit)
    assert code == 1
    results = json.loads((out / "results.json").read_text())
    assert list(results) == ["core"] and results["core"]["raycast_fisheye"]["nominal"][
        "frames"] == 1
    assert f"Stopped: lumen detector plugins.detectors:{detector}" in (
        out / "tables.md").read_text()
    if detector in ("raises", "exits", "scribbles", "clears_the_mask"):  # its traceback
        details = (out / "error.txt").read_text()
        assert "Traceback" in details and ("the detector divided by zero" in details
                                           or detector != "raises")
    else:
        assert not (out / "error.txt").exists()


def _start(tmp_path, duration="60", preexec_fn=None):
    out = tmp_path / "run"
    process = subprocess.Popen(CLI + ["run", "--duration", duration, "--no-recording",
                                      "--quiet", "--out", str(out)],
                               cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, preexec_fn=preexec_fn)
    return process, out


@pytest.mark.slow
def test_sigint_ends_a_run_started_in_the_background(tmp_path):
    # A background job (nohup, `&` in a script) inherits SIGINT ignored; `kill -INT` must
    # still end the run with its outputs written.
    process, out = _start(tmp_path, preexec_fn=lambda: signal.signal(signal.SIGINT,
                                                                     signal.SIG_IGN))
    _wait_for_simulation(out, process)
    time.sleep(1.0)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    assert json.loads((out / "metrics.json").read_text())["status"] == "interrupted"


def _wait_for_simulation(out: Path, process, timeout=120):
    """Until the run has spooled its first logs (it is simulating)."""
    start = time.monotonic()
    while not (out / "logs.parts").is_dir():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() - start < timeout
        time.sleep(0.2)


@pytest.mark.slow
@pytest.mark.parametrize("signal_name,code,after", [("SIGTERM", 143, 8.0),
                                                    ("SIGINT", 130, 1.0),
                                                    ("SIGHUP", 129, 1.0)])
def test_a_signal_ends_the_run_with_its_outputs_written(tmp_path, signal_name, code, after):
    # The acceptance line: SIGTERM 8 s into a 60 s run writes metrics, logs and scenario
    # and exits non-zero.
    process, out = _start(tmp_path)
    started = time.monotonic()
    _wait_for_simulation(out, process)
    time.sleep(max(0.0, after - (time.monotonic() - started)))
    process.send_signal(getattr(signal, signal_name))
    _, err = process.communicate(timeout=120)
    assert process.returncode == code, err
    _assert_one_line(process.returncode, err, rf"interrupted \({signal_name}\) at t = ")
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "interrupted" and metrics["signal"] == signal_name
    assert 0 < metrics["sim_time_s"] < 60
    logs = load_logs(out)
    assert logs["times"][-1] == pytest.approx(metrics["sim_time_s"], abs=0.011)
    assert (out / "scenario.yaml").is_file() and not (out / "logs.parts").exists()


@pytest.mark.slow
def test_a_killed_run_leaves_its_spooled_logs(tmp_path):
    process, out = _start(tmp_path)
    _wait_for_simulation(out, process)
    time.sleep(12.0)
    process.kill()
    process.communicate()
    logs = load_logs(out)  # from logs.parts/: at most ~5 simulated seconds are lost
    assert logs["times"][0] == 0.0 and logs["times"][-1] >= 5.0
    assert (out / "scenario.yaml").is_file()


@pytest.mark.slow
def test_a_second_run_into_the_folder_of_a_running_one_is_refused(tmp_path, capsys):
    # Before: the second run, with --force, removed the first one's outputs as it ran, and
    # both reported success with a folder of mixed files.
    process, out = _start(tmp_path)
    try:
        _wait_for_simulation(out, process)
        code = cli_main(RUN + ["--out", str(out), "--force"])
        _assert_one_line(code, capsys.readouterr().err,
                         re.escape(f"--out {out}: another capsule-sim command is writing into "
                                   "this folder"))
        assert code == 2
    finally:
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=120)
    assert process.returncode == 143, err
    assert json.loads((out / "metrics.json").read_text())["status"] == "interrupted"
    assert "duration: 60.0" in (out / "scenario.yaml").read_text()
    assert sorted(p.name for p in out.iterdir()) == ["logs.npz", "metrics.json",
                                                     "scenario.yaml", "wall_pressure.npz",
                                                     "wall_pressure.png"]
