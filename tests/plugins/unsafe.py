"""Navigators that command the EPM where it must not go (tests/test_epm_guard.py): into the
patient, a kilometre up, not a number. The station's EPM guard must make every such command
safe, whoever sends it."""

import math

import numpy as np
from pydrake.systems.framework import LeafSystem


class Height(LeafSystem):
    """Commands the EPM's start pose with its centre at height `z` (m, world)."""

    def __init__(self, context, z):
        super().__init__()
        self._command = np.array(context.start_command, dtype=float)
        self._command[2] = z
        self.DeclareVectorOutputPort("epm_command", 6, self._calc)

    def _calc(self, context, output):
        output.SetFromVector(self._command)


class Flicker(Height):
    """Every `period` seconds, by turns: a command of all NaN (from t = 0) and the start pose
    at height `z`."""

    def __init__(self, context, z, period):
        super().__init__(context, z)
        self._period = period

    def _calc(self, context, output):
        if math.floor(context.get_time() / self._period) % 2 == 0:
            output.SetFromVector(np.full(6, np.nan))
        else:
            output.SetFromVector(self._command)


def into_the_table(context):
    """Half a metre below the table top, through the patient."""
    return Height(context, -0.5)


def kilometre_up(context):
    """A thousand kilometres up (1e6 m)."""
    return Height(context, 1.0e6)


def flicker(context):
    """NaN and half a metre below the table, by turns every 0.15 s."""
    return Flicker(context, -0.5, 0.15)
