"""Whether a paced run keeps the pace it was asked for, said when it does not.

A run with a live output is paced (Drake's Simulator, target_realtime_rate: app/run.py
`paced`); a step that costs more than its share of the wall clock cannot be paced faster.
`PaceWatch` compares the simulated time with the wall clock over windows of `window`
seconds and prints one line when a window falls below `tolerance` of the target, and one
when the run is back at pace, so a viewer knows the picture is slower than life.
"""

from __future__ import annotations

import sys
import time


class PaceWatch:
    def __init__(self, target: float, window: float = 5.0, tolerance: float = 0.9,
                 stream=None, clock=time.perf_counter):
        self.target = float(target)
        self.window = window
        self.tolerance = tolerance
        self._stream = stream
        self._clock = clock
        self._start = None
        self.behind = False
        self.slowest = None      # the lowest real-time factor of a window
        self.lines: list[str] = []

    def _say(self, line: str) -> None:
        self.lines.append(line)
        print(f"capsule-sim: {line}", file=self._stream or sys.stderr, flush=True)

    def update(self, sim_time: float) -> None:
        if self.target <= 0.0:
            return
        now = self._clock()
        if self._start is None:
            self._start = (now, sim_time)
            return
        wall0, sim0 = self._start
        if now - wall0 < self.window:
            return
        rate = (sim_time - sim0) / (now - wall0)
        self._start = (now, sim_time)
        self.slowest = rate if self.slowest is None else min(self.slowest, rate)
        if rate < self.tolerance * self.target and not self.behind:
            self.behind = True
            self._say(f"the run cannot keep the pace asked (x{self.target:g} real time): "
                      f"x{rate:.2f} over the last {self.window:g} s at t = {sim_time:.1f} s; "
                      "live outputs show it slower than life")
        elif rate >= self.tolerance * self.target and self.behind:
            self.behind = False
            self._say(f"back at pace (x{rate:.2f} real time) at t = {sim_time:.1f} s")
