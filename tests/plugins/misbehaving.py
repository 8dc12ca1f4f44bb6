"""Navigators whose code misbehaves as a user's might, for the benchmark's tests
(tests/test_benchmark.py): each creeps like `navigators.creep`, then, at 0.5 s simulated,
takes its process down or never returns."""

import os
import signal
import time

from plugins.navigators import Creep

# The simulated time at which these navigators misbehave (s).
WHEN = 0.5


class _Crashes(Creep):
    """Kills its own process (as a segfault in a user's extension would end it)."""

    def _calc(self, context, output):
        if context.get_time() >= WHEN:
            os.kill(os.getpid(), signal.SIGKILL)
        super()._calc(context, output)


class _Hangs(Creep):
    """Never returns from computing its command (a user's endless loop)."""

    def _calc(self, context, output):
        if context.get_time() >= WHEN:
            while True:
                time.sleep(0.2)
        super()._calc(context, output)


def crashes(context):
    return _Crashes(context)


def hangs(context):
    return _Hangs(context)
