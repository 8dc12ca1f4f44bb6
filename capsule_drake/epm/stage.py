"""PoseToStage: an EPM pose command [p_WE, m_hat_W] as the five-axis stage's desired state."""

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from capsule_drake.epm.poses import stage_joint_positions


class PoseToStage(LeafSystem):
    """[p_WE, m_hat_W] -> stage desired state [x, y, z, yaw, pitch, zero rates], the yaw
    unwrapped against the previous sample (so the servo never turns the long way round).

    .. pydrake_system::

        name: PoseToStage
        input_ports:
        - epm_command
        output_ports:
        - desired_state

    A non-finite command holds the last state. Samples every `period` (s).
    """

    def __init__(self, initial_stage_q, period: float = 0.001):
        super().__init__()
        self._command = self.DeclareVectorInputPort("epm_command", 6)
        initial = np.concatenate([np.asarray(initial_stage_q, dtype=float)[:5], np.zeros(5)])
        self._state = self.DeclareDiscreteState(BasicVector(initial))
        self.DeclareStateOutputPort("desired_state", self._state)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)

    def _update(self, context, discrete_state):
        command = np.asarray(self._command.Eval(context), dtype=float)
        x = context.get_discrete_state(self._state).value().copy()
        if np.all(np.isfinite(command)) and np.linalg.norm(command[3:]) > 1e-9:
            q = stage_joint_positions(command[:3], command[3:] / np.linalg.norm(command[3:]))
            q[3] = x[3] + np.angle(np.exp(1j * (q[3] - x[3])))
            x[:5] = q
        discrete_state.set_value(self._state, x)
