"""A run's outputs (app/outputs.py, app/run.py): never overwritten silently, checked before the
run, spooled as it goes, whole on every way a run ends. Signals, disks and bad inputs
through the command line: tests/test_bad_inputs.py."""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from pydrake.systems.framework import LeafSystem

from capsule_drake.app.cli import main as cli_main
from capsule_drake.app.outputs import (OutputError, check_room, claim_folder, new_run_folder,
                                       plan_outputs, release_claims, write_atomic)
from capsule_drake.app.log_spool import LogSpool, load_logs
from capsule_drake.app.run import Interrupted, chain_extends, simulate
from capsule_drake.app.signals import DeferredSignals
from capsule_drake.scenario import load_scenario

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


@pytest.mark.slow
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
                   "contact_pressure": t,
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


class _Signals(LeafSystem):
    """Sends this process `number` from a publish event at t = 0.3 s: the signal arrives
    while Drake is calling Python, as a real one does at any moment of a run."""

    def __init__(self, number):
        super().__init__()
        self._number = number
        self.DeclarePeriodicPublishEvent(0.3, 0.3, self._send)

    def _send(self, context):
        if context.get_time() < 0.35:
            os.kill(os.getpid(), self._number)


def _raise_interrupted(number, frame):  # the command line's handler
    raise Interrupted(number)


@pytest.fixture
def cli_handlers():
    names = ("SIGINT", "SIGTERM", "SIGHUP")
    previous = {name: signal.signal(getattr(signal, name), _raise_interrupted)
                for name in names}
    yield
    for name, handler in previous.items():
        signal.signal(getattr(signal, name), handler)


def test_a_signal_during_the_simulation_is_noted_and_the_run_ends_at_its_next_step(
        tmp_path, cli_handlers):
    # The handler is not run inside Drake's calls into Python, where an exception can turn
    # into a TypeError (pybind11 converting an argument): the run ends at the next step.
    scenario = load_scenario(override="{duration: 2.0}")
    result = simulate(scenario, out_dir=tmp_path, progress=False,
                      extend=lambda builder, station: builder.AddSystem(
                          _Signals(signal.SIGHUP)) and None)
    assert result.status == "interrupted" and result.metrics["signal"] == "SIGHUP"
    assert result.metrics["stopped_early"] == "interrupted (SIGHUP) at t = 0.300 s"
    assert {"metrics.json", "logs.npz", "scenario.yaml"} <= {p.name for p in tmp_path.iterdir()}
    assert load_logs(tmp_path)["times"][-1] == pytest.approx(0.3)
    assert signal.getsignal(signal.SIGHUP) is _raise_interrupted  # handlers put back


def test_a_signal_while_the_run_is_set_up_stops_it_at_its_start_with_its_outputs(
        tmp_path, cli_handlers):
    # Before: a signal noted during the build was forgotten when the simulation began, and
    # the run went on to its end with exit 0.
    def extend(builder, station):   # runs while the station is built
        os.kill(os.getpid(), signal.SIGHUP)   # noted, not raised

    scenario = load_scenario(override="{duration: 5.0}")
    result = simulate(scenario, out_dir=tmp_path, progress=False, extend=extend)
    assert result.status == "interrupted" and result.metrics["signal"] == "SIGHUP"
    assert result.metrics["sim_time_s"] == 0.0
    assert result.metrics["stopped_early"] == "interrupted (SIGHUP) at t = 0.000 s"
    assert {"metrics.json", "logs.npz", "scenario.yaml"} <= {p.name for p in tmp_path.iterdir()}
    assert signal.getsignal(signal.SIGHUP) is _raise_interrupted  # handlers put back


def test_deferred_signals_note_one_raise_a_second_and_hold_until_written(cli_handlers):
    with DeferredSignals() as signals:
        os.kill(os.getpid(), signal.SIGTERM)       # noted, not raised
        assert signals.pending == signal.SIGTERM
        with pytest.raises(Interrupted):           # a second: the run is stuck, raise
            os.kill(os.getpid(), signal.SIGINT)
    arrived = []
    with pytest.raises(Interrupted) as raised:
        with signals.held():
            os.kill(os.getpid(), signal.SIGHUP)    # noted while the outputs are written
            time.sleep(0.05)
            arrived.append("the block went on")
    assert arrived and raised.value.signal_name == "SIGHUP"  # raised as the block ended
    assert signal.getsignal(signal.SIGHUP) is _raise_interrupted


def _render_workers() -> list[int]:
    """This process's children that are camera render workers (capsule/render_worker.py)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            command = (entry / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if ppid == os.getpid() and b"render_process" in command:
            found.append(int(entry.name))
    return found


@pytest.mark.slow
def test_a_failed_build_closes_the_render_worker_and_the_extensions_already_added(tmp_path):
    # A camera with latency draws in a worker process; an extension that fails after another
    # was added: the run is not started, the worker has ended and the first one is closed.
    scenario = load_scenario(override="{duration: 0.5, capsule: {camera: {fps: 5.0, "
                                      "latency: 0.05}}}")
    closed = []
    # Workers of stations that earlier tests in this process still hold are not this build's.
    before = set(_render_workers())
    started = []

    def first(builder, station):
        started.extend(set(_render_workers()) - before)
        assert started  # the station's camera started its worker
        return lambda: closed.append("first")

    def second(builder, station):
        raise RuntimeError("cannot open the dataset folder")

    with pytest.raises(RuntimeError, match="dataset folder"):
        simulate(scenario, progress=False, extend=chain_extends(first, second))
    assert closed == ["first"]
    assert not set(started) & set(_render_workers())


# --- Claiming a folder: one command at a time ------------------------------------------

# A process that claims a folder as a command does (plan, then claim) and holds it until
# it is killed; it prints "claimed" once it holds it.
_HOLDER = """
import sys, time
from capsule_drake.app.outputs import plan_outputs
plan_outputs(sys.argv[1], force=True).claim()
print("claimed", flush=True)
time.sleep(600)
"""


def _hold(folder: Path):
    """A process holding the claim on `folder` (killed by the caller)."""
    process = subprocess.Popen([sys.executable, "-c", _HOLDER, str(folder)],
                               stdout=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "claimed"
    return process


def test_two_commands_that_check_a_folder_at_once_cannot_both_claim_it(tmp_path):
    # Two runs started at the same moment both find the folder free (the plan); only the
    # first claim wins, the second is refused in one line and removes nothing. Before: both
    # claims succeeded and the runs overwrote each other's files.
    out = tmp_path / "run"
    out.mkdir()   # an empty folder a user made for the run
    first, second = plan_outputs(out, force=True), plan_outputs(out, force=True)
    try:
        assert first.claim() == out
        (out / "metrics.json").write_text("first")
        with pytest.raises(OutputError, match=re.escape(f"--out {out}: another capsule-sim "
                                                        "command is writing into this folder")):
            second.claim()
        assert (out / "metrics.json").read_text() == "first"
        # A folder the first made for itself: the same.
        new = tmp_path / "new"
        first, second = plan_outputs(new), plan_outputs(new)
        assert first.claim() == new
        with pytest.raises(OutputError, match="another capsule-sim command is writing"):
            second.claim()
        # A run's own new folder (no --out) is held too: --out naming it is refused.
        mine = plan_outputs(None, parent=tmp_path / "runs", name="Default").claim()
        with pytest.raises(OutputError, match="another capsule-sim command is writing"):
            plan_outputs(mine, force=True)
    finally:
        release_claims()
    assert plan_outputs(out, force=True).claim() == out  # released: free again
    release_claims()


def test_a_folder_in_use_is_refused_even_with_force_and_freed_when_its_holder_dies(tmp_path):
    out = tmp_path / "run"
    holder = _hold(out)
    try:
        (out / "scenario.yaml").write_text("the running command's")
        with pytest.raises(OutputError, match=re.escape(f"--out {out}: another capsule-sim "
                                                        "command is writing into this folder")):
            plan_outputs(out, force=True)
        assert (out / "scenario.yaml").read_text() == "the running command's"
    finally:
        holder.kill()
        holder.wait()
    # A command killed outright leaves no claim behind: the folder is free for --force.
    try:
        assert plan_outputs(out, force=True).claim() == out
        assert not (out / "scenario.yaml").exists()
    finally:
        release_claims()


def test_the_cli_refuses_a_folder_another_run_writes_into(tmp_path, capsys):
    out = tmp_path / "run"
    holder = _hold(out)
    try:
        (out / "scenario.yaml").write_text("the running command's")
        code = cli_main(["run", "--duration", "0.05", "--no-recording", "--quiet", "--out",
                         str(out), "--force"])
        line = _one_line(capsys.readouterr().err)
        assert code == 2, line
        assert "another capsule-sim command is writing into this folder" in line
        assert (out / "scenario.yaml").read_text() == "the running command's"
    finally:
        holder.kill()
        holder.wait()
    # The claim is released when the command ends: the same process can claim it again.
    assert cli_main(["run", "--duration", "0.05", "--no-recording", "--quiet", "--out",
                     str(out), "--force"]) == 0
    assert plan_outputs(out, force=True).claim() == out
    release_claims()


# --- Disks that fill: nothing left behind that blocks the retry ----------------------------

# A process that writes nothing more than `limit` bytes long (a disk that fills, without
# root or a mount: the write fails with EFBIG) and runs the room check in `folder`.
_PROBE = """
import resource, sys
from pathlib import Path
from capsule_drake.app.outputs import OutputError, check_room
resource.setrlimit(resource.RLIMIT_FSIZE, (4, 4))
try:
    check_room(Path(sys.argv[1]), 1.0)
except OutputError as e:
    print(e)
"""


def test_a_probe_that_cannot_be_written_is_removed(tmp_path):
    # The room check's probe is created, then its write fails: before, the probe stayed,
    # and the retry was refused for the file it found in the folder.
    done = subprocess.run([sys.executable, "-c", _PROBE, str(tmp_path)], capture_output=True,
                          text=True, timeout=60)
    assert "cannot write to the output folder (File too large)" in done.stdout, done
    assert list(tmp_path.iterdir()) == []


def test_what_a_failed_write_leaves_does_not_block_the_retry(tmp_path):
    # What a run killed (or out of room) while writing can leave: a probe, the temporary
    # files of write_atomic. A folder holding only those is free (they are removed); with
    # --force they go with the previous run's outputs; a user's own files stay.
    out = tmp_path / "run"
    out.mkdir()
    (out / ".write-check").write_bytes(b"")
    (out / ".metrics.json.partial").write_text('{"half')
    try:
        assert claim_folder(out) == out
        assert list(out.iterdir()) == []
    finally:
        release_claims()
    (out / "metrics.json").write_text("{}")
    (out / ".logs.npz.partial").write_bytes(b"PK")
    (out / ".notes.txt.partial").write_text("mine")
    with pytest.raises(OutputError, match="folder exists and holds"):
        claim_folder(out)
    try:
        assert claim_folder(out, force=True) == out
        assert sorted(p.name for p in out.iterdir()) == [".notes.txt.partial"]
    finally:
        release_claims()
