"""A run's outputs (io/outputs.py, io/run.py): never overwritten silently, checked before the
run, spooled as it goes, whole on every way a run ends (signals, errors, a full disk)."""

import collections
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from pydrake.systems.framework import LeafSystem

from capsule_drake.cli import main as cli_main
from capsule_drake.io import outputs
from capsule_drake.io.outputs import (LogSpool, OutputError, check_room, claim_folder,
                                      load_logs, new_run_folder, write_atomic)
from capsule_drake.io.run import simulate
from capsule_drake.scenario import load_scenario

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "capsule_drake.cli"]


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def test_new_runs_get_their_own_folders_even_in_the_same_second(tmp_path):
    folders = {new_run_folder(tmp_path, "Default") for _ in range(5)}
    assert len(folders) == 5 and all(f.is_dir() and not any(f.iterdir()) for f in folders)


def test_an_existing_folder_is_refused_unless_forced(tmp_path):
    old = tmp_path / "old"
    old.mkdir()
    (old / "metrics.json").write_text("{}")
    (old / "recording.html").write_text("old")
    (old / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="folder exists and holds metrics.json, notes.txt"):
        claim_folder(old)
    # --force removes a previous run's outputs (no stale recording beside new metrics),
    # and leaves the user's own files.
    assert claim_folder(old, force=True) == old
    assert sorted(p.name for p in old.iterdir()) == ["notes.txt"]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert claim_folder(empty) == empty  # an empty folder loses nothing
    with pytest.raises(OutputError, match="--out: empty path"):
        claim_folder("")
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="exists and is not a folder"):
        claim_folder(tmp_path / "file")


def test_the_cli_refuses_to_overwrite_a_run(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["run", "--duration", "0.05", "--no-recording", "--quiet", "--out", str(out)]
    assert cli_main(args) == 0
    first = (out / "metrics.json").read_text()
    capsys.readouterr()
    assert cli_main(args) == 2
    assert "folder exists and holds" in _one_line(capsys.readouterr().err)
    assert (out / "metrics.json").read_text() == first
    assert cli_main(args + ["--force"]) == 0
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["run", "--duration", "0.05", "--no-recording", "--out", ""])
    assert exit_info.value.code == 2
    assert "argument --out: empty path" in _one_line(capsys.readouterr().err)


def test_no_room_is_found_before_the_run(tmp_path):
    with pytest.raises(OutputError, match="MB free, but the run will write about"):
        check_room(tmp_path, 50e6, free_bytes=10e6)
    check_room(tmp_path, 50e6, free_bytes=1e9)


def test_an_atomic_write_that_fails_leaves_the_old_file_and_no_partial(tmp_path):
    path = tmp_path / "metrics.json"
    path.write_text("old")

    def failing(temporary):
        Path(temporary).write_text("half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        write_atomic(path, writer=failing)
    assert path.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]


def test_logs_are_spooled_in_parts_and_joined(tmp_path):
    spool = LogSpool(tmp_path, period=1.0, wall_period=1e9)
    for k in range(5):
        t = np.arange(10) * 0.1 + k
        spool.add({"times": t, "capsule_state": np.tile(t, (13, 1)), "contact_load": t,
                   "epm_pose": np.tile(t, (6, 1))}, t=k + 1.0)
    parts = sorted((tmp_path / "logs.parts").glob("part-*.npz"))
    assert len(parts) == 5
    logs = load_logs(tmp_path)  # what a killed run left
    np.testing.assert_allclose(logs["times"], np.arange(50) * 0.1, atol=1e-12)
    spool.finish()
    assert not (tmp_path / "logs.parts").exists()
    np.testing.assert_allclose(load_logs(tmp_path)["capsule_state"][4], np.arange(50) * 0.1,
                               atol=1e-12)


class _Fails(LeafSystem):
    """Raises `error` from a publish event at t = 0.3 s (as Drake's failed assertions do:
    they arrive in Python as SystemExit)."""

    def __init__(self, error):
        super().__init__()
        self._error = error
        self.DeclarePeriodicPublishEvent(0.3, 0.3, self._fail)

    def _fail(self, context):
        raise self._error


@pytest.mark.parametrize("error", [SystemExit("Failure at multibody/plant.cc: condition "
                                              "'mu >= 0' failed."),
                                   RuntimeError("solver failed\nsecond line")])
def test_an_error_inside_the_simulation_keeps_what_was_logged(tmp_path, error):
    scenario = load_scenario(override="{duration: 2.0}")
    result = simulate(scenario, out_dir=tmp_path, progress=False,
                      extend=lambda builder, station: builder.AddSystem(_Fails(error)) and None)
    assert result.status == "error"
    assert result.metrics["stopped_early"].startswith("simulation error at t = 0.300 s: ")
    assert "\n" not in result.metrics["stopped_early"]
    assert {"metrics.json", "logs.npz", "scenario.yaml", "error.txt"} <= {
        p.name for p in tmp_path.iterdir()}
    assert "Traceback" in (tmp_path / "error.txt").read_text()
    assert load_logs(tmp_path)["times"][-1] == pytest.approx(0.3)
    assert json.loads((tmp_path / "metrics.json").read_text())["status"] == "error"


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


def test_a_read_only_folder_is_found_before_the_run(tmp_path, capsys):
    with _tmpfs(tmp_path / "ro", "1m", read_only=True) as ro:
        if ro is None:  # not root: a folder without write permission instead
            ro = tmp_path / "ro"
            ro.chmod(0o555)
        start = time.perf_counter()
        code = cli_main(["run", "--duration", "30", "--no-recording", "--quiet",
                         "--out", str(ro / "run")])
        line = _one_line(capsys.readouterr().err)
        assert code == 2 and "cannot create the output folder" in line and str(ro) in line
        assert time.perf_counter() - start < 20  # refused before 30 s of simulation


def test_a_disk_that_fills_during_the_run_loses_no_logs(tmp_path, capsys, monkeypatch):
    # 4 MB: room for the logs, not for the 16 MB recording. The room check is told there
    # is plenty, as if another program filled the disk during the run.
    Usage = collections.namedtuple("Usage", "total used free")
    monkeypatch.setattr(outputs.shutil, "disk_usage", lambda path: Usage(1e12, 0, 1e12))
    with _tmpfs(tmp_path / "small", "4m") as small:
        if small is None:
            pytest.skip("needs root to mount a small tmpfs (a real full disk)")
        code = cli_main(["run", "--duration", "0.5", "--quiet", "--out", str(small / "run")])
        line = _one_line(capsys.readouterr().err)
        assert code == 1
        assert "could not write recording.html (No space left on device)" in line
        names = sorted(p.name for p in (small / "run").iterdir())
        # Everything before the recording is whole; no partial file is left.
        assert names == ["logs.npz", "metrics.json", "scenario.yaml"], names
        assert load_logs(small / "run")["times"][-1] == pytest.approx(0.5)


def _start(tmp_path, duration="60"):
    out = tmp_path / "run"
    process = subprocess.Popen(CLI + ["run", "--duration", duration, "--no-recording",
                                      "--out", str(out)],
                               cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    return process, out


def _wait_for_simulation(out: Path, process, timeout=120):
    """Until the run has spooled its first logs (it is simulating)."""
    start = time.monotonic()
    while not (out / "logs.parts").is_dir():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() - start < timeout
        time.sleep(0.2)


@pytest.mark.slow
@pytest.mark.parametrize("sig,code", [(signal.SIGTERM, 143), (signal.SIGINT, 130),
                                      (signal.SIGHUP, 129)])
def test_a_signal_ends_the_run_with_its_outputs_written(tmp_path, sig, code):
    process, out = _start(tmp_path)
    _wait_for_simulation(out, process)
    time.sleep(8.0 if sig == signal.SIGTERM else 1.0)
    process.send_signal(sig)
    _, err = process.communicate(timeout=120)
    assert process.returncode == code, err
    assert "Traceback" not in err
    assert f"interrupted ({sig.name})" in err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "interrupted" and metrics["signal"] == sig.name
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
    logs = load_logs(out)  # from logs.parts/
    assert logs["times"][0] == 0.0 and logs["times"][-1] >= 5.0
    assert (out / "scenario.yaml").is_file()
