"""A navigator that commands the EPM at the legal floor over one flank, then over the other
(tests/test_epm_clearance.py): every command is as low as the clearance allows, and the
straight way between two of them passes through the belly."""

import numpy as np
from pydrake.systems.framework import LeafSystem

FLANK_X = 0.2   # m: the default abdomen's dome falls to the flanks' 0.11 m there


class FlankSweep(LeafSystem):
    """Every `period` seconds the other flank: [+-FLANK_X, y of the start, the floor there],
    with the start's moment."""

    def __init__(self, context, period: float):
        super().__init__()
        start = np.array(context.start_command, dtype=float)
        self._m = start[3:] / np.linalg.norm(start[3:])
        self._y = start[1]
        self._floor = context.floor_height
        self._period = period
        self.DeclareVectorOutputPort("epm_command", 6, self._calc)

    def _calc(self, context, output):
        side = 1.0 if int(context.get_time() / self._period) % 2 == 0 else -1.0
        x = side * FLANK_X
        output.SetFromVector(np.concatenate([[x, self._y, self._floor(x, self._y, self._m)],
                                             self._m]))


def flanks(context):
    """Over the right flank from t = 0, the left from 2.5 s, and so on."""
    return FlankSweep(context, 2.5)
