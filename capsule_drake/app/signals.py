"""Ctrl-C and the termination signals while a run writes what must stay whole.

Two mechanisms, for two situations:
- `DeferredSignals` (the run loop, app/run.py): while a run simulates, a signal is noted and
  ends the run at its next step; while its outputs are written, noted and raised after.
- `signals_held` (the MCAP writer, app/mcap_log.py): a block during which the signals are
  masked, so that none lands inside a record halfway through; they are delivered as the
  block ends.
"""

from __future__ import annotations

import contextlib
import signal
import threading


@contextlib.contextmanager
def signals_held():
    """Ctrl-C and the termination signals wait until the block is done (main thread only):
    an interrupt never lands inside the MCAP writer, halfway through a record."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK,
                                      {signal.SIGINT, signal.SIGTERM, signal.SIGHUP})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


class DeferredSignals:
    """While a run simulates, Ctrl-C and the termination signals whose handler is Python's
    (Ctrl-C's KeyboardInterrupt, the CLI's `Interrupted`) are noted, not raised: the
    simulator's monitor ends the run at its next step, and the run's outputs are written.

    An exception raised by a signal handler lands in whatever Python code runs at that
    moment, and inside Drake that may be pybind11 converting a callback's argument, which
    reports it as a TypeError ("incompatible function arguments") instead of the interrupt.
    A second signal before the first has been acted on is raised at once (a stuck step).
    After the `with`, until `held()` ends, signals are only noted (the outputs are being
    written); the first of them is raised as `held()` ends. Python runs signal handlers
    in the main thread whichever thread the signal reached, so this holds where a signal
    mask (per thread) would not. Outside the main thread, or for a signal left to the
    system (SIG_DFL, SIG_IGN), nothing changes."""

    NAMES = ("SIGINT", "SIGTERM", "SIGHUP")

    def __init__(self):
        self.pending: int | None = None      # the signal that ended the simulation
        self._later: int | None = None       # the first one while the outputs are written
        self._simulating = False
        self._previous: dict[int, object] = {}

    def __enter__(self):
        self.pending, self._later, self._simulating = None, None, True
        if threading.current_thread() is threading.main_thread():
            for name in self.NAMES:
                number = getattr(signal, name, None)
                handler = signal.getsignal(number) if number is not None else None
                if callable(handler) and handler != self._note:
                    self._previous[number] = handler
                    signal.signal(number, self._note)
        return self

    def _note(self, number, frame):
        if not self._simulating:
            self._later = self._later or number
        elif self.pending is None:
            self.pending = number
        else:
            self._previous[number](number, frame)  # raises (KeyboardInterrupt, Interrupted)

    def __exit__(self, *exc):
        self._simulating = False
        return False

    def restore(self) -> dict:
        """Puts the handlers back (and returns them, by signal), dropping what was noted."""
        previous, self._previous = self._previous, {}
        for number, handler in previous.items():
            signal.signal(number, handler)
        self.pending = self._later = None
        return previous

    @contextlib.contextmanager
    def held(self):
        """Signals are noted until this block is done; then the handlers are put back and
        the first signal that arrived meanwhile is raised (a second Ctrl-C arrives after
        the files are whole)."""
        try:
            yield
        finally:
            later = self._later
            previous = self.restore()
            if later is not None and later in previous:
                previous[later](later, None)
