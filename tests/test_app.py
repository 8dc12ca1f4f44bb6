"""The application layer (capsule_drake/app/): the one run loop every caller steps, its
stages, and the command's start-up."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from capsule_drake.app.run import Run, simulate
from capsule_drake.scenario import load_scenario

REPO = Path(__file__).resolve().parents[1]
COMMAND = [sys.executable, "-m", "capsule_drake.app"]   # what the capsule-sim script runs


def caught_signals(pid: int) -> int:
    """The mask of signals process `pid` has handlers for (Linux: SigCgt in /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigCgt:"):
            return int(line.split()[1], 16)
    return 0


def wait_for_handlers(process, timeout: float = 30.0) -> None:
    """Until the command's first statements have run (app/entry.py takes SIGTERM, which
    the interpreter leaves to the system): before that, only the interpreter's own start-up
    runs, the same for every Python program."""
    deadline = time.monotonic() + timeout
    while not caught_signals(process.pid) & (1 << (signal.SIGTERM - 1)):
        assert process.poll() is None and time.monotonic() < deadline
        time.sleep(0.002)


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc (Linux)")
@pytest.mark.parametrize("delay", [0.0, 0.5, 1.5, 3.0])
def test_ctrl_c_at_start_up_ends_the_command_in_one_line(tmp_path, delay):
    """SIGINT while the libraries are imported (the first second or two after the command
    starts), while the scenario loads, or while the station is built: exit 130 and one
    line, no traceback, and no run that goes on as if nothing happened. A run folder, if
    one was begun, holds the run's metrics (status interrupted), not a lone
    scenario.yaml. (Measured before: a traceback or a run that completed with exit 0
    within the first 1.2 s, a lone scenario.yaml at 1.5-2.5 s.)"""
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    process = subprocess.Popen(
        COMMAND + ["run", "--duration", "60", "--no-recording", "--quiet", "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path, env=env)
    wait_for_handlers(process)
    time.sleep(delay)
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=120)
    assert "Traceback" not in stderr, stderr
    assert process.returncode == 130, (process.returncode, stdout, stderr)
    assert stderr.strip().splitlines()[-1].startswith("capsule-sim: interrupted (SIGINT)") \
        or "stopped early: interrupted (SIGINT)" in stdout + stderr, (stdout, stderr)
    if out.is_dir() and (out / "scenario.yaml").exists():
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["status"] == "interrupted" and metrics["signal"] == "SIGINT"


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="reads /proc (Linux)")
def test_the_command_takes_its_signals_before_it_loads_drake(tmp_path):
    """The handlers are in place before Drake's library is loaded (the second or two of
    start-up that a Ctrl-C used to hit with a traceback)."""
    process = subprocess.Popen(COMMAND + ["run", "--duration", "60", "--no-recording",
                                          "--quiet", "--out", str(tmp_path / "run")],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for_handlers(process)
        loaded = Path(f"/proc/{process.pid}/maps").read_text()
    finally:
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=120)
    assert "libdrake" not in loaded
    assert process.returncode == 130 and "Traceback" not in stderr, stderr
