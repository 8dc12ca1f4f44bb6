"""A closed-loop magnetic position controller designed from the linearisation.

The capsule hanging under the EPM is unstable (Earnshaw: the magnetic stiffness has a
positive eigenvalue; `analysis.magnetic_stiffness`). `design_hover_lqr` linearises the
capsule-magnet diagram (`linearization.capsule_magnet_diagram`) at a hover point with
Drake's `FirstOrderTaylorApproximation`, keeps the translational block (the capsule's
position and velocity, the EPM's position as input; its orientation follows the field on
its own, its roll about the magnet's axis is not actuated at all), and solves the
discrete-time LQR for it. `HoverController` closes the loop: the EPM moves by the target's
offset (a shifted hover is a hover: only the offset between the magnets counts) plus the
LQR correction, its moment held.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.systems.controllers import DiscreteTimeLinearQuadraticRegulator
from pydrake.systems.framework import LeafSystem
from pydrake.systems.primitives import FirstOrderTaylorApproximation


def _translation_indices(plant):
    """Indices in the plant's state [q, v] of the capsule's position and translational
    velocity (its floating joint: quaternion then position; angular then translational)."""
    joint = plant.GetJointByName("capsule_floating")
    return joint.position_start() + 4, plant.num_positions() + joint.velocity_start() + 3


@dataclasses.dataclass
class HoverDesign:
    """The LQR gain and the operating point it was designed at."""

    K: np.ndarray          # 3 x 9: EPM position correction from [integral of dp, dp, dv]
    p_WB0: np.ndarray      # the capsule body's position at the hover point
    epm_pose0: np.ndarray  # [p_WE, m_hat_W] at the hover point
    A: np.ndarray          # the translational block of the linearisation (6 x 6)
    B: np.ndarray          # (6 x 3)
    period: float          # the plant's time step: the controller's period (s)
    closed_loop_eigenvalues: np.ndarray  # of the augmented system (9)


def design_hover_lqr(diagram, plant, context, epm_pose, position_weight: float = 400.0,
                     velocity_weight: float = 1.0, integral_weight: float = 100.0,
                     input_weight=(1.0, 1.0, 30.0)) -> HoverDesign:
    """LQR with integral action for the capsule's translation at the hover point `context`
    (state) / `epm_pose` (input). The integral of the position error removes the offset a
    proportional law leaves: the hover point is an equilibrium of the translation only (the
    magnet's force acts 3 mm from the centre of mass, so the capsule tilts a little and the
    pull changes). Weights: Q = diag(integral_weight I, position_weight I,
    velocity_weight I) on [integral of dp (m s), dp (m), dv (m/s)], R = diag(input_weight)
    on the EPM's position (m). The vertical input costs more: the pull grows as 1/r^4, so the
    linearisation holds for a few centimetres of the EPM's height but for ~20 cm sideways,
    where the pull's horizontal part saturates."""
    linear = FirstOrderTaylorApproximation(
        diagram, context, input_port_index=diagram.GetInputPort("epm_pose").get_index(),
        output_port_index=diagram.GetOutputPort("state").get_index())
    q0, v0 = _translation_indices(plant)
    rows = list(range(q0, q0 + 3)) + list(range(v0, v0 + 3))
    A = linear.A()[np.ix_(rows, rows)]
    B = linear.B()[rows, 0:3]
    h = plant.time_step()
    # z = [integral of dp, dp, dv]; the integral advances by h dp each step.
    A_aug = np.block([[np.eye(3), h * np.eye(3), np.zeros((3, 3))],
                      [np.zeros((6, 3)), A]])
    B_aug = np.vstack([np.zeros((3, 3)), B])
    Q = np.diag([integral_weight] * 3 + [position_weight] * 3 + [velocity_weight] * 3)
    R = np.diag(np.broadcast_to(np.asarray(input_weight, dtype=float), (3,)))
    K, _ = DiscreteTimeLinearQuadraticRegulator(A_aug, B_aug, Q, R)
    x0 = context.get_discrete_state_vector().CopyToVector()
    return HoverDesign(K, x0[q0:q0 + 3].copy(), np.asarray(epm_pose, dtype=float).copy(), A, B,
                       h, np.linalg.eigvals(A_aug - B_aug @ K))


class HoverController(LeafSystem):
    """Holds the capsule at a target position with the EPM (state feedback, 1 per step).

    .. pydrake_system::

        name: HoverController
        input_ports:
        - state
        - target
        output_ports:
        - epm_pose

    state: the plant's state [q, v] (the capsule's floating joint: quaternion, position,
    angular and translational velocity). target: the capsule body's wanted position (3).
    epm_pose: [p_WE, m_hat_W]: the hover pose shifted by target - p_WB0, minus K times
    [integral of the error, p_WB - target, v_WB]; the moment as at the hover point. The
    integral (discrete state) advances every `design.period`.
    """

    def __init__(self, design: HoverDesign, plant):
        super().__init__()
        self._design = design
        q, v = _translation_indices(plant)
        self._q, self._v = slice(q, q + 3), slice(v, v + 3)
        self._state = self.DeclareVectorInputPort(
            "state", plant.num_positions() + plant.num_velocities())
        self._target = self.DeclareVectorInputPort("target", 3)
        self._integral = self.DeclareDiscreteState(3)
        self.DeclarePeriodicDiscreteUpdateEvent(design.period, 0.0, self._integrate)
        self.DeclareVectorOutputPort("epm_pose", 6, self._calc)

    def _error(self, context):
        return np.asarray(self._state.Eval(context))[self._q] - self._target.Eval(context)

    def _integrate(self, context, discrete_state):
        integral = context.get_discrete_state(self._integral).get_value()
        discrete_state.set_value(self._integral,
                                 integral + self._design.period * self._error(context))

    def _calc(self, context, output):
        x = np.asarray(self._state.Eval(context))
        target = self._target.Eval(context)
        d = self._design
        z = np.concatenate([context.get_discrete_state(self._integral).get_value(),
                            x[self._q] - target, x[self._v]])
        p_E = d.epm_pose0[:3] + (target - d.p_WB0) - d.K @ z
        output.SetFromVector(np.concatenate([p_E, d.epm_pose0[3:]]))
