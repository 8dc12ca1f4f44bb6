"""Which polyps a run showed: each camera frame's label image read for the polyps in view.

A polyp counts as seen when the camera showed it for at least SEEN_SECONDS (summed over its
frames; each frame counts for the time to the next) with at least SEEN_AREA of the lens's
field and some of it within SEEN_RANGE of the camera:
- SEEN_SECONDS 0.2 s: the six frames at 30 frames/s below which a computer-aided
  detector's alarms are withheld in the GI Genius frame-by-frame analysis (most false
  alarms last under three frames; withholding up to six removed 88 % of them and no
  polyp; docs/sources.md section 3.4, V abstract);
- SEEN_AREA 0.5 % of the field: a tenth of the SUN-SEG database's "small object" (under 5 %
  of the image; V), so that a polyp seen only as a speck does not count (U);
- SEEN_RANGE 30 mm: the depth of field of colon capsule cameras (PillCam COLON: 0-30 mm;
  S, product summaries).
A clinical study counts a polyp found if a detector flags it in one frame; these
thresholds ask more of the view, and each is a parameter of `LesionViews`.
"""

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

SEEN_SECONDS = 0.2
SEEN_AREA = 0.005
SEEN_RANGE = 0.03


class LesionViews(LeafSystem):
    """Per polyp, how long the camera has shown it well enough to count (module docstring).

    .. pydrake_system::

        name: LesionViews
        input_ports:
        - label_image
        - depth_image
        - frame_info
        output_ports:
        - shown_s

    label_image, depth_image, frame_info: the CapsuleCamera's. shown_s: per polyp (by
    index), the seconds of frames that showed it with at least `area` of the field within
    `max_range`; a frame counts from its exposure to the next frame's (the last for one
    camera period). Also kept per polyp: frames in view at all, largest area (px), nearest
    range (m): `views(context)`.

    Args:
        labels: {render label: polyp index}. count: the number of polyps.
        field_pixels: the pixels of the lens's field. period, delay: when to look for a new
            frame (the camera's tick and latency).
    """

    def __init__(self, labels: dict[int, int], count: int, field_pixels: int, period: float,
                 delay: float = 1e-6, area: float = SEEN_AREA, max_range: float = SEEN_RANGE):
        super().__init__()
        self._labels = dict(labels)
        self._count = int(count)
        self._min_pixels = area * field_pixels
        self._max_range = float(max_range)
        self._period = float(period)
        self._label = self.DeclareAbstractInputPort("label_image",
                                                    AbstractValue.Make(ImageLabel16I()))
        self._depth = self.DeclareAbstractInputPort("depth_image",
                                                    AbstractValue.Make(ImageDepth32F()))
        self._info = self.DeclareVectorInputPort("frame_info", 4)
        # [last frame count, last exposure time, last frame's qualifying (count)...,
        #  shown_s (count), frames in view (count), largest area (count), nearest (count)]
        n = self._count
        initial = np.concatenate([[-1.0, np.nan], np.zeros(n), np.zeros(n), np.zeros(n),
                                  np.zeros(n), np.full(n, np.inf)])
        self._state = self.DeclareDiscreteState(BasicVector(initial))
        self.DeclareVectorOutputPort(
            "shown_s", max(n, 1), lambda context, output: output.SetFromVector(
                self._shown(context)), {self.xd_ticket()})
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, delay, self._update)

    def _shown(self, context):
        values = context.get_discrete_state(self._state).value()
        n = self._count
        return values[2 + n:2 + 2 * n] if n else np.zeros(1)

    def views(self, context) -> dict:
        """Per polyp: shown_s, frames in view, largest area (px), nearest range (m)."""
        v = context.get_discrete_state(self._state).value()
        n = self._count
        return {"shown_s": v[2 + n:2 + 2 * n].copy(), "frames": v[2 + 2 * n:2 + 3 * n].copy(),
                "largest_px": v[2 + 3 * n:2 + 4 * n].copy(),
                "nearest_m": v[2 + 4 * n:2 + 5 * n].copy()}

    def _update(self, context, state):
        info = self._info.Eval(context)
        values = context.get_discrete_state(self._state).value().copy()
        if info[1] == values[0] or self._count == 0:
            return EventStatus.DidNothing()
        n = self._count
        qualifying = values[2:2 + n]
        if np.isfinite(values[1]):   # the last frame counts up to this one
            values[2 + n:2 + 2 * n] += qualifying * max(info[0] - values[1], 0.0)
        labels = self._label.Eval(context).data[..., 0]
        depth = self._depth.Eval(context).data[..., 0]
        qualifying[:] = 0.0
        present, pixels = np.unique(labels, return_counts=True)
        for label, count in zip(present, pixels):
            k = self._labels.get(int(label))
            if k is None:
                continue
            nearest = float(np.min(depth[labels == label]))
            values[2 + 2 * n + k] += 1.0
            values[2 + 3 * n + k] = max(values[2 + 3 * n + k], float(count))
            values[2 + 4 * n + k] = min(values[2 + 4 * n + k], nearest)
            qualifying[k] = float(count >= self._min_pixels and nearest <= self._max_range)
        values[2:2 + n] = qualifying
        values[0], values[1] = info[1], info[0]
        state.get_mutable_discrete_state(self._state).set_value(values)
        return EventStatus.Succeeded()

    def final_shown(self, context) -> np.ndarray:
        """shown_s with the last frame counted for one camera period."""
        v = context.get_discrete_state(self._state).value()
        n = self._count
        return v[2 + n:2 + 2 * n] + v[2:2 + n] * self._period
