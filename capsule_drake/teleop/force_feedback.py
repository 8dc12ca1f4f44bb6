"""ForceFeedback: what the operator's hand feels, in the haptic device's frame.

The pseudo-force (guidance: lumen, wall, potential; already in the device frame D) plus the
environment: the capsule's contact force with the colon wall, scaled to the device and
turned into D through the camera view (D x right, y up, z toward the operator; the same
R_DC as the pseudo-force), the sum saturated by norm to the device's limit.
"""

import math

import numpy as np
from pydrake.systems.framework import LeafSystem

from capsule_drake.capsule.model import rotation_from_quaternion
from capsule_drake.guidance.terms import rotation_from_rpy_deg, saturate


def contact_force_D(F_W, R_WB, R_BC, R_DC, gain: float) -> np.ndarray:
    """The capsule's contact force (world) as felt at the device: gain * R_DC R_CW F_W."""
    R_WC = np.asarray(R_WB) @ np.asarray(R_BC)
    return gain * (np.asarray(R_DC) @ (R_WC.T @ np.asarray(F_W, dtype=float)))


class ForceFeedback(LeafSystem):
    """pseudo-force + scaled contact force, saturated (module docstring).

    .. pydrake_system::

        name: ForceFeedback
        input_ports:
        - pseudo_force_D (optional)
        - capsule_force_W
        - capsule_state
        output_ports:
        - F_D

    Unconnected or non-finite inputs count as zero. Direct feedthrough (no state).

    Args:
        X_BC: the camera's pose in the capsule body.
        contact_gain: device newtons per newton of contact force on the capsule.
        force_limit: the device's peak force (N).
        device_from_camera_rpy_deg: R_DC as roll-pitch-yaw (deg), as the pseudo-force's.
    """

    def __init__(self, X_BC, contact_gain: float = 1.0, force_limit: float = 3.3,
                 device_from_camera_rpy_deg=(180.0, 0.0, 0.0)):
        super().__init__()
        if not contact_gain >= 0.0 or not force_limit > 0.0:
            raise ValueError("force feedback contact_gain must be >= 0, force_limit > 0")
        self._R_BC = np.asarray(X_BC.rotation().matrix())
        self._R_DC = rotation_from_rpy_deg(device_from_camera_rpy_deg)
        self._gain = contact_gain
        # contact_force_D's product with the capsule's orientation factored out.
        self._contact_to_D = contact_gain * (self._R_DC @ self._R_BC.T)
        self._limit = force_limit
        self._pseudo = self.DeclareVectorInputPort("pseudo_force_D", 3)
        self._contact = self.DeclareVectorInputPort("capsule_force_W", 3)
        self._state = self.DeclareVectorInputPort("capsule_state", 13)
        self.DeclareVectorOutputPort("F_D", 3, self._calc)

    def _calc(self, context, output):
        # Evaluated at the device's servo rate (1 kHz): kept lean.
        total = np.zeros(3)
        if self._pseudo.HasValue(context):
            pseudo = self._pseudo.Eval(context)
            if math.isfinite(pseudo.sum()):
                total += pseudo
        if self._gain > 0.0:
            F_W = self._contact.Eval(context)
            if F_W.any() and math.isfinite(F_W.sum()):
                q = self._state.Eval(context)[:4]
                if math.isfinite(q.sum()):
                    R_WB = rotation_from_quaternion(q)
                    total += self._contact_to_D @ (R_WB.T @ F_W)
        output.SetFromVector(saturate(total, self._limit))
