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

A user's polyp detector (a function of the RGB frame returning detections, each a point
(u, v) or a box (x, y, width, height) whose centre counts) is scored on every frame the way
the MICCAI 2015 polyp-detection challenge scores one (docs/sources.md section 3.4): a
detection whose point falls on a polyp's pixels of the label image is a true positive of
that polyp (several on one polyp count once), one that falls on none is a false positive.
A polyp is detected when it had a true positive in any frame (the clinical rule);
sensitivity is over the polyps seen, false positives are per minute of frames. A detector
that raises or returns something malformed counts a failure for that frame; the run goes on.
"""

import logging


import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I, ImageRgba8U

log = logging.getLogger(__name__)

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
                 delay: float = 1e-6, area: float = SEEN_AREA, max_range: float = SEEN_RANGE,
                 detector=None):
        super().__init__()
        self._detector = detector
        # The detector's score: [frames, failures, false positives, first and last frame's
        # time] and per polyp the frames it was detected in.
        self._score = np.array([0.0, 0.0, 0.0, np.nan, np.nan])
        self._detected = np.zeros(int(count))
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
        self._rgb = (self.DeclareAbstractInputPort("rgb_image", AbstractValue.Make(
            ImageRgba8U())) if detector is not None else None)
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
        if info[1] == values[0]:
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
        if self._detector is not None:
            self._score_detector(self._rgb.Eval(context).data[..., :3], labels, info[0])
        state.get_mutable_discrete_state(self._state).set_value(values)
        return EventStatus.Succeeded()

    def _score_detector(self, rgb, labels, t: float) -> None:
        score = self._score
        score[0] += 1.0
        score[3] = t if not np.isfinite(score[3]) else score[3]
        score[4] = t
        try:
            points = detection_points(self._detector(rgb.copy()))
        except Exception as e:   # a user's detector must not stop the simulation
            log.warning("polyp detector failed on a frame: %s: %s", type(e).__name__, e)
            score[1] += 1.0
            return
        height, width = labels.shape
        hit = set()
        for u, v in points:
            col, row = int(round(u)), int(round(v))
            k = (self._labels.get(int(labels[row, col]))
                 if 0 <= row < height and 0 <= col < width else None)
            if k is None:
                score[2] += 1.0
            else:
                hit.add(k)
        for k in hit:
            self._detected[k] += 1.0

    def detector_score(self, seen=None) -> dict:
        """The detector's score so far: frames, failures, false positives and their rate
        per minute of frames (over the time from the first frame to the last plus one
        period), frames detected per polyp, and (given `seen`, per polyp bools) the polyps
        seen and the seen ones detected."""
        frames, failures, false_positives, first, last = self._score
        minutes = ((last - first) + self._period) / 60.0 if frames else np.nan
        out = {"frames": int(frames), "failures": int(failures),
               "false_positives": int(false_positives),
               "fp_per_min": false_positives / minutes if frames else np.nan,
               "detected_frames": self._detected.copy()}
        if seen is not None:
            seen = np.asarray(seen, dtype=bool)
            out["seen"] = int(seen.sum())
            out["seen_detected"] = int((seen & (self._detected > 0)).sum())
        return out

    def final_shown(self, context) -> np.ndarray:
        """shown_s with the last frame counted for one camera period."""
        v = context.get_discrete_state(self._state).value()
        n = self._count
        return v[2 + n:2 + 2 * n] + v[2:2 + n] * self._period


def detection_points(detections) -> list[tuple[float, float]]:
    """The points (u, v) of a detector's answer: each detection a point (u, v) or a box
    (x, y, width, height), whose centre counts. ValueError for anything else."""
    points = []
    for detection in detections if detections is not None else ():
        values = np.asarray(detection, dtype=float).ravel()
        if values.size == 2:
            u, v = values
        elif values.size == 4:
            u, v = values[0] + 0.5 * values[2], values[1] + 0.5 * values[3]
        else:
            raise ValueError(f"a detection must be (u, v) or (x, y, w, h), not {detection!r}")
        if not (np.isfinite(u) and np.isfinite(v)):
            raise ValueError(f"a detection is not finite: {detection!r}")
        points.append((float(u), float(v)))
    return points
