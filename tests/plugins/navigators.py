"""Navigators a user might plug into the benchmark (tests/test_benchmark.py)."""

import numpy as np
from pydrake.systems.framework import LeafSystem


class Creep(LeafSystem):
    """A trivial navigator: the EPM starts over the capsule's start and creeps along +y
    (roughly up the rectum) at `speed`, at the floor height the clearance allows."""

    def __init__(self, context, speed=0.01):
        super().__init__()
        self._start = np.asarray(context.start_command, dtype=float)
        self._floor = context.floor_height
        self._speed = speed
        self.DeclareVectorInputPort("capsule_state", 13)
        self.DeclareVectorOutputPort("epm_command", 6, self._calc)

    def _calc(self, context, output):
        p = self._start[:3] + [0.0, self._speed * context.get_time(), 0.0]
        m = self._start[3:]
        p[2] = max(p[2], self._floor(p[0], p[1], m))
        output.SetFromVector(np.concatenate([p, m]))


def creep(context):
    return Creep(context)


def bad_port(context):
    system = Creep(context)
    system.DeclareVectorInputPort("colon_centerline", 3)
    return system


class _FailsLater(Creep):
    """Creeps, then raises inside the simulation at t = 0.5 s (a user's bug)."""

    def _calc(self, context, output):
        if context.get_time() >= 0.5:
            raise ZeroDivisionError("the navigator divided by zero")
        super()._calc(context, output)


def fails_later(context):
    return _FailsLater(context)


def not_a_system(context):
    return 42


def fails_to_build(context):
    raise KeyError("no such parameter")
