"""PseudoForceField: the force the haptic stylus gives the operator's hand, sampled and held.

The physics is `capsule_drake.guidance.terms.pseudo_force` (lumen attraction, wall avoidance and a
potential field along the colon, in the device frame, saturated); this system samples it at
the device's servo period and holds it, so it adds no algebraic loop and costs one
evaluation per period (about 1.5 ms of Python, mostly the wall query `Colon.excursion`).
"""

import copy

import numpy as np
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from capsule_drake.blocks import block, checked, need
from capsule_drake.guidance.terms import (TERMS, PseudoForceConfig, check_pseudo_force_config,
                                          pseudo_force)


class PseudoForceField(LeafSystem):
    """Every ``config.update_period`` s (first at t = 0) evaluates the pseudo-force of the
    lumen seen by the camera, the wall's nearness and the potential along the colon
    (``guidance.pseudo_force``) and holds it.

    .. pydrake_system::

        name: PseudoForceField
        input_ports:
        - lumen_ray
        - lumen_visible
        - lumen_confidence
        - capsule_state
        output_ports:
        - F_D
        - terms_D
        - wall_distance
        - invalid_inputs

    - ``lumen_ray`` (3): unit direction of the lumen centre in the camera frame C (x right,
      y down, z forward).
    - ``lumen_visible`` (1): 1.0 if the lumen is seen, 0.0 if not.
    - ``lumen_confidence`` (1): the detector's confidence in [0, 1].
    - ``capsule_state`` (13): [q_WB (w, x, y, z), p_WB (m), w_WB (rad/s), v_WB (m/s)], world
      frame: the plant's ``get_state_output_port(capsule_instance)`` for the floating capsule.
    - ``F_D`` (3, N): the saturated total force in the haptic device frame D (x right, y up,
      z toward the operator).
    - ``terms_D`` (9, N): the lumen, wall and potential terms, weighted, in D, before
      saturation.
    - ``wall_distance`` (1, m): from the capsule's surface to the wall (< 0: pressed into
      it); NaN before the first sample, while the capsule's pose is not finite, and when
      the wall term's weight is 0 (the distance is then not computed).
    - ``invalid_inputs`` (3): per term (lumen, wall, potential), how many samples found its
      inputs not finite and set it to zero.

    An input port left unconnected carries no information: the lumen counts as not visible
    (confidence 1), and without ``capsule_state`` the wall and potential terms are zero.
    Neither counts as invalid.

    Args:
        colon: the scenario's Colon (wall and centreline).
        config: a ``PseudoForceConfig`` (copied; the scenario checked it).
        X_BC: the camera frame's pose in the capsule body (the ``camera`` frame of
            models/capsule.sdf: ``plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()``).
        capsule_radius, capsule_length: the capsule's collision shape (m).
    """

    def __init__(self, colon, config: PseudoForceConfig, X_BC: RigidTransform,
                 capsule_radius: float, capsule_length: float):
        LeafSystem.__init__(self)
        self._colon = colon
        self._config = copy.deepcopy(config)
        self._R_BC = X_BC.rotation().matrix()
        self._radius = float(capsule_radius)
        self._length = float(capsule_length)
        self._ray_port = self.DeclareVectorInputPort("lumen_ray", 3)
        self._visible_port = self.DeclareVectorInputPort("lumen_visible", 1)
        self._confidence_port = self.DeclareVectorInputPort("lumen_confidence", 1)
        self._state_port = self.DeclareVectorInputPort("capsule_state", 13)
        self._F_D_state = self.DeclareDiscreteState(3)
        self._terms_D_state = self.DeclareDiscreteState(3 * len(TERMS))
        self._distance_state = self.DeclareDiscreteState(np.array([np.nan]))
        self._invalid_state = self.DeclareDiscreteState(len(TERMS))
        self._F_D_port = self.DeclareStateOutputPort("F_D", self._F_D_state)
        self._terms_D_port = self.DeclareStateOutputPort("terms_D", self._terms_D_state)
        self._distance_port = self.DeclareStateOutputPort("wall_distance", self._distance_state)
        self._invalid_port = self.DeclareStateOutputPort("invalid_inputs", self._invalid_state)
        self.DeclarePeriodicDiscreteUpdateEvent(self._config.update_period, 0.0, self._update)

    def config(self) -> PseudoForceConfig:
        return copy.deepcopy(self._config)

    def get_lumen_ray_input_port(self):
        return self._ray_port

    def get_lumen_visible_input_port(self):
        return self._visible_port

    def get_lumen_confidence_input_port(self):
        return self._confidence_port

    def get_capsule_state_input_port(self):
        return self._state_port

    def get_F_D_output_port(self):
        return self._F_D_port

    def get_terms_D_output_port(self):
        return self._terms_D_port

    def get_wall_distance_output_port(self):
        return self._distance_port

    def get_invalid_inputs_output_port(self):
        return self._invalid_port

    def _update(self, context, discrete_state):
        ray = self._ray_port.Eval(context) if self._ray_port.HasValue(context) else np.zeros(3)
        visible = (self._visible_port.Eval(context)[0]
                   if self._visible_port.HasValue(context) else 0.0)
        confidence = (self._confidence_port.Eval(context)[0]
                      if self._confidence_port.HasValue(context) else 1.0)
        has_state = self._state_port.HasValue(context)
        state = self._state_port.Eval(context) if has_state else np.full(13, np.nan)
        result = pseudo_force(self._colon, self._config, self._R_BC, ray, visible, confidence,
                              state, self._radius, self._length)
        invalid = result.invalid if has_state else result.invalid & [True, False, False]
        counts = context.get_discrete_state(self._invalid_state).get_value() + invalid
        discrete_state.get_mutable_vector(self._F_D_state).SetFromVector(result.F_D)
        discrete_state.get_mutable_vector(self._terms_D_state).SetFromVector(
            result.terms_D.reshape(-1))
        discrete_state.get_mutable_vector(self._distance_state).SetAtIndex(
            0, result.wall_distance)
        discrete_state.get_mutable_vector(self._invalid_state).SetFromVector(counts)


def check_pseudo_force(config: PseudoForceConfig, scenario) -> None:
    checked("", check_pseudo_force_config, config)
    need(config.lumen_weight == 0 or scenario.capsule.lumen_tracker is not None,
         "pseudo_force.lumen_weight needs capsule.lumen_tracker (and a camera), or set "
         "lumen_weight: 0")


@block("pseudo_force", PseudoForceConfig, check=check_pseudo_force)
def add_pseudo_force(builder, parts, config: PseudoForceConfig):
    """`pseudo_force` from the capsule's state and, when there is one, the lumen tracker;
    exports pseudo_force.<signal> and shares the device's frame
    (`pseudo_force.device_from_camera_rpy_deg`)."""
    force = builder.AddNamedSystem("pseudo_force", PseudoForceField(
        parts.colon, config, parts.capsule.X_BC, capsule_radius=parts.capsule.radius,
        capsule_length=parts.capsule.length))
    builder.Connect(parts.capsule_state, force.GetInputPort("capsule_state"))
    if parts.has("capsule.lumen_tracker.lumen_ray"):
        for name in ("lumen_ray", "lumen_visible", "lumen_confidence"):
            builder.Connect(parts.output(f"capsule.lumen_tracker.{name}"),
                            force.GetInputPort(name))
    parts.export_outputs(force, "pseudo_force")
    parts.share("pseudo_force.device_from_camera_rpy_deg", config.device_from_camera_rpy_deg)
    return force
