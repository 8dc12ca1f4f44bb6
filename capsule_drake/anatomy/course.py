"""The 3D course of the colon in a supine abdomen, from seeded landmarks.

World frame: table top z = 0, +z anterior (up), +x to the patient's left, +y toward the head,
spine along x = 0, origin at the level of the umbilicus. Units: metres.

Landmarks follow the course described in the project reference (S/U): anus low and
posterior, rectum along the sacral hollow, sigmoid looping in the pelvis, descending colon
posterior in the left flank, splenic flexure high in the left upper quadrant, transverse
colon anterior and sagging toward the feet, hepatic flexure (lower than the splenic) under
the liver on the right, ascending colon posterior in the right flank, cecum in the right
iliac fossa. Each segment has one free shape parameter (the rectosigmoid height, sigmoid
loop size, splenic flexure height, transverse sag, ileocecal height, cecal pole height),
solved by bisection so that the segment's arc length matches its sampled target.
A C2 interpolating cubic spline (centripetal knots) runs through all landmarks.
"""

import numpy as np
from scipy.interpolate import make_interp_spline

from .params import SEGMENT_NAMES, ColonParams

# Fixed anatomical anchors [m] (U, chosen to match the reference's course and depths).
_ANUS = np.array([0.0, -0.205, 0.085])
_DESCENDING_SIGMOID = np.array([0.115, -0.045, 0.08])   # left pelvic brim
_HEPATIC_FLEXURE = np.array([-0.105, 0.13, 0.10])       # under the liver, right

# Per segment: bracket of the free shape parameter [m] for the length solve.
_SHAPE_BRACKETS = {
    "rectum": (0.06, 0.16),       # height of the rectosigmoid junction above the anus
    "sigmoid": (0.0, 0.12),       # cranial reach of the sigmoid loop
    "descending": (0.08, 0.30),   # height of the splenic flexure above the junction
    "transverse": (0.0, 0.22),    # sag of the transverse colon toward the feet
    "ascending": (0.06, 0.26),    # drop from the hepatic flexure to the ileocecal valve
    "cecum": (0.02, 0.12),        # drop from the ileocecal valve to the cecal pole
}
_SHAPE_START = {"rectum": 0.11, "sigmoid": 0.05, "descending": 0.22,
                "transverse": 0.10, "ascending": 0.17, "cecum": 0.06}


def _landmarks(shape: dict[str, float]) -> tuple[np.ndarray, list[int]]:
    """Unjittered landmarks and the landmark index where each segment ends.

    Returns:
        (K, 3) landmarks from the anus to the cecal pole, and 7 landmark indices: the start
        of the rectum followed by the end of each segment in SEGMENT_NAMES order.
    """
    pts = [_ANUS]
    ends = [0]
    # Rectum: up the sacral hollow (posterior, z low), small lateral curves.
    h = shape["rectum"]
    pts += [_ANUS + [-0.008, 0.40 * h, -0.030], _ANUS + [0.010, 0.72 * h, -0.027],
            _ANUS + [0.012, h, -0.012]]
    ends.append(len(pts) - 1)
    rs = pts[-1]
    # Sigmoid: from the rectosigmoid junction to the right and up, over a loop whose apex
    # rises by `a`, then down into the left pelvis and up to the pelvic brim.
    a = shape["sigmoid"]
    pts += [rs + [-0.040, 0.012, 0.012], rs + [-0.045, 0.02 + 0.55 * a, 0.028],
            rs + [-0.008, 0.03 + a, 0.040], rs + [0.040, 0.02 + 0.55 * a, 0.033],
            np.array([0.070, -0.125, 0.095]), np.array([0.105, -0.105, 0.085]),
            _DESCENDING_SIGMOID]
    ends.append(len(pts) - 1)
    # Descending: straight up the left flank, posterior; ends at the splenic flexure.
    d = shape["descending"]
    ds = _DESCENDING_SIGMOID
    pts += [ds + [0.010, 0.35 * d, -0.006], ds + [0.012, 0.72 * d, -0.006],
            ds + [-0.005, d, 0.012]]
    ends.append(len(pts) - 1)
    sf = pts[-1]
    # Transverse: turns anterior and caudal from the splenic flexure, sags by `g` toward
    # the feet, rises again on the right to the hepatic flexure.
    g = shape["transverse"]
    bottom_y = 0.10 - g
    hf = _HEPATIC_FLEXURE
    pts += [sf + [-0.018, -0.03, 0.055],
            np.array([0.060, 0.5 * (sf[1] - 0.03) + 0.5 * (bottom_y + 0.035), 0.165]),
            np.array([0.030, bottom_y + 0.008, 0.175]),
            np.array([-0.020, bottom_y, 0.175]),
            np.array([-0.060, 0.5 * (bottom_y + 0.01) + 0.5 * (hf[1] - 0.035), 0.165]),
            hf + [0.020, -0.035, 0.050], hf]
    ends.append(len(pts) - 1)
    # Ascending: down the right flank, posterior, to the ileocecal valve.
    c = shape["ascending"]
    pts += [hf + [-0.018, -0.35 * c, -0.018], hf + [-0.020, -0.72 * c, -0.022],
            hf + [-0.015, -c, -0.020]]
    ends.append(len(pts) - 1)
    icv = pts[-1]
    # Cecum: a short blind pouch hanging into the right iliac fossa.
    e = shape["cecum"]
    pts += [icv + [0.004, -0.5 * e, 0.004], icv + [0.010, -e, 0.010]]
    ends.append(len(pts) - 1)
    return np.array(pts, dtype=float), ends


class _Course:
    """Landmark spline evaluated on a dense grid that contains every landmark."""

    SAMPLES_PER_SPAN = 60

    def __init__(self, landmarks: np.ndarray):
        chords = np.linalg.norm(np.diff(landmarks, axis=0), axis=1)
        self.knots = np.concatenate([[0.0], np.cumsum(np.sqrt(chords))])
        self.spline = make_interp_spline(self.knots, landmarks, k=3)
        u = [np.linspace(self.knots[i], self.knots[i + 1], self.SAMPLES_PER_SPAN,
                         endpoint=False) for i in range(len(landmarks) - 1)]
        self.u = np.concatenate(u + [self.knots[-1:]])
        p = self.spline(self.u)
        self.s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0),
                                                                 axis=1))])
        self.s_knots = self.s[::self.SAMPLES_PER_SPAN]

    def resample(self, step: float) -> tuple[np.ndarray, np.ndarray]:
        """Points every ~`step` metres of arc length, including both ends."""
        n = int(np.ceil(self.s[-1] / step)) + 1
        s = np.linspace(0.0, self.s[-1], n)
        return s, self.spline(np.interp(s, self.s, self.u))


def _jitter(rng: np.random.Generator, count: int, sigma: float) -> np.ndarray:
    j = rng.normal(0.0, sigma, size=(count, 3))
    j[0] = 0.0  # the anus stays where it is
    return j


def solve_course(params: ColonParams, rng: np.random.Generator):
    """Landmark spline whose segments have seeded lengths.

    Returns:
        (course, target_lengths, boundaries): the solved `_Course`, the sampled target
        length of each segment [m] and the arc length of the 7 segment boundaries [m].
    """
    targets = {name: rng.uniform(params.segment(name).length_min,
                                 params.segment(name).length_max)
               for name in SEGMENT_NAMES}
    shape = dict(_SHAPE_START)
    jitter = _jitter(rng, len(_landmarks(shape)[0]), params.landmark_jitter)

    def build(sh):
        pts, ends = _landmarks(sh)
        course = _Course(pts + jitter)
        return course, course.s_knots[ends]

    def segment_length(sh, k):
        b = build(sh)[1]
        return b[k + 1] - b[k]

    for _ in range(4):  # Gauss-Seidel sweeps: each parameter mostly moves its own segment
        for k, name in enumerate(SEGMENT_NAMES):
            lo, hi = _SHAPE_BRACKETS[name]

            def residual(x, k=k, name=name):
                trial = dict(shape)
                trial[name] = x
                return segment_length(trial, k) - targets[name]

            f_lo, f_hi = residual(lo), residual(hi)
            if f_lo > 0.0 or f_hi < 0.0:
                # Out of reach: take the closer end; the anatomy tests catch a bad bracket.
                shape[name] = lo if f_lo > 0.0 else hi
                continue
            for _ in range(40):
                mid = 0.5 * (lo + hi)
                if residual(mid) > 0.0:
                    hi = mid
                else:
                    lo = mid
                if hi - lo < 1e-6:
                    break
            shape[name] = 0.5 * (lo + hi)
    course, boundaries = build(shape)
    return course, targets, boundaries
