"""What the suite shows and keeps while it runs: the progress line and the rows written as
the runs finish."""

from __future__ import annotations

import csv
import shutil
import sys
import threading
import time
from pathlib import Path

import numpy as np

from capsule_drake.app.benchmark.task import COLUMNS, FAILED


class RunsProgress:
    """Each run's progress on stderr while a suite goes: per run, its simulated time and
    where the capsule is (colon segment, centreline station in cm from the anal end); a line
    per finished run with how it ended.

    On a terminal, a block of one line per running run under a bar of the runs done, redrawn
    in place; otherwise (a log file, a pipe) plain lines: a run's start, then its progress
    every `line_period` s of wall time, then its end. Thread-safe (updates arrive from a
    queue-draining thread or Dask's event loop).
    """

    def __init__(self, tasks, enabled: bool = True, stream=None, line_period: float = 10.0):
        self.tasks, self.enabled = tasks, enabled
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.line_period = line_period
        self.start = time.perf_counter()
        self.running: dict[int, dict] = {}
        self.last_line: dict[int, float] = {}
        self.done = 0
        self._drawn = 0
        self._last_draw = -np.inf
        self._shown_running: set[int] = set()
        self._lock = threading.Lock()
        self._closed = threading.Event()
        if self.enabled and self.tty:  # the clock and bar move even while no run reports
            threading.Thread(target=self._heartbeat, daemon=True).start()

    def _heartbeat(self) -> None:
        while not self._closed.wait(1.0):
            with self._lock:
                if not self._closed.is_set():
                    self._draw()

    def _name(self, k) -> str:
        return f"{self.tasks[k].navigator} seed {self.tasks[k].seed}"

    def _clock(self) -> str:
        return f"[{time.perf_counter() - self.start:6.0f} s]"

    def starting(self, workers, engine: str) -> None:
        """The suite's first line, at once (a worker process takes a few seconds to start
        Python and Drake before its first run reports)."""
        if not self.enabled:
            return
        where = (f"{workers} local worker processes" if engine == "local" else
                 f"a local Dask cluster of {workers} processes" if workers else
                 "the Dask scheduler's workers")
        line = (f"{len(self.tasks)} runs on {where}; each reports once its process has "
                "started Python and Drake")
        with self._lock:
            if self.tty:
                self._write(line + "\n")
                self._draw()
            else:
                self._write(f"{self._clock()} {line}\n")

    def describe(self, k, info) -> str:
        if info.get("phase") != "running":
            return f"{self._name(k)}: building the station"
        rate = info.get("rate", 0.0)
        return (f"{self._name(k)}: {info['t']:6.1f} / {info['duration']:g} s simulated, "
                f"{info['segment']} at {info['s_cm']:.0f} cm"
                + (f" (x{rate:.2f} real time)" if rate > 0 else ""))

    def update(self, k, info: dict) -> None:
        if not self.enabled:
            return
        with self._lock:
            if k not in self.running and self.last_line.get(k) == np.inf:
                return  # a late report of a run that has finished
            self.running[k] = info
            now = time.perf_counter()
            if self.tty:
                if now - self._last_draw >= 0.2:
                    self._draw()
            elif (k not in self.last_line or info.get("phase") == "building"
                  or k not in self._shown_running
                  or now - self.last_line[k] >= self.line_period):
                self.last_line[k] = now
                if info.get("phase") == "running":
                    self._shown_running.add(k)
                self._write(f"{self._clock()} {self.describe(k, info)}\n")

    def finished(self, k, result: dict) -> None:
        with self._lock:
            self.done += 1
            self.running.pop(k, None)
            self.last_line[k] = np.inf
            if not self.enabled:
                return
            row = result["row"]
            line = f"{self._clock()} done {self.done}/{len(self.tasks)}: {self._name(k)}: "
            if row.get("status") == FAILED:
                line += f"failed: {row['error']}"
            else:
                ending = (f"reached the cecum at {row['time_to_cecum_s']:.1f} s"
                          if row["reached_cecum"] else f"ended: {row['stuck_in']}")
                line += (f"{ending}; {row['sim_time_s']:.1f} s simulated in "
                         f"{row['wall_time_s']:.0f} s")
            if self.tty:
                self._clear()
                self._write(line + "\n")
                self._draw()
            else:
                self._write(line + "\n")

    def close(self) -> None:
        with self._lock:
            self._closed.set()
            if self.enabled and self.tty:
                self._clear()

    def _write(self, text: str) -> None:
        self.stream.write(text)
        self.stream.flush()

    def _clear(self) -> None:
        if self._drawn:
            self._write(f"\x1b[{self._drawn}F\x1b[J")
            self._drawn = 0

    def _draw(self) -> None:
        width = max(20, shutil.get_terminal_size((100, 20)).columns - 1)
        total = len(self.tasks)
        bar = "#" * int(30 * self.done / max(total, 1))
        lines = [f"[{bar:<30}] {self.done}/{total} runs  "
                 f"{time.perf_counter() - self.start:6.0f} s"]
        lines += [f"  {self.describe(k, info)}" for k, info in sorted(self.running.items())]
        self._clear()
        self._write("".join(line[:width] + "\n" for line in lines))
        self._drawn = len(lines)
        self._last_draw = time.perf_counter()


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


