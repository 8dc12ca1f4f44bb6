"""The 3D course of the colon in a supine abdomen, from seeded landmarks.

World frame: table top z = 0, +z anterior (up), +x to the patient's left, +y toward the head,
spine along x = 0, origin at the level of the umbilicus. Units: metres.

Landmarks follow the course described in docs/sources.md section 3 (S/U): anus low and
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
from scipy.interpolate import CubicSpline, make_interp_spline
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree

from .params import SEGMENT_NAMES, ColonParams

# Fixed anatomical anchors [m] (U, chosen to match the reference's course and depths).
_ANUS = np.array([0.0, -0.205, 0.085])
_DESCENDING_SIGMOID = np.array([0.130, -0.065, 0.08])   # left pelvic brim
_HEPATIC_FLEXURE = np.array([-0.105, 0.105, 0.12])       # under the liver, right
_FLEXURE_RADIUS = 0.042   # half the front-to-back span of the flexure hairpins (U)
_FLEXURE_Z = 0.12         # height of the flexures' centre above the table (U)

# Per segment: bracket of the free shape parameter [m] for the length solve.
_SHAPE_BRACKETS = {
    "rectum": (0.06, 0.16),       # height of the rectosigmoid junction above the anus
    "sigmoid": (-0.02, 0.14),       # cranial reach of the sigmoid loop
    "descending": (0.10, 0.34),   # height of the splenic flexure above the junction
    "transverse": (0.02, 0.22),    # sag of the transverse colon toward the feet
    "ascending": (0.06, 0.26),    # drop from the hepatic flexure to the ileocecal valve
    "cecum": (0.02, 0.12),        # drop from the ileocecal valve to the cecal pole
}
_SHAPE_START = {"rectum": 0.11, "sigmoid": 0.05, "descending": 0.22,
                "transverse": 0.10, "ascending": 0.17, "cecum": 0.06}
# Farther ends of two brackets, searched only when a segment is longer than the bracket
# reaches (so a colon within it is solved as before): a redundant sigmoid whose loop rises
# toward the umbilicus (to ~80 cm), a long transverse colon sagging into the pelvis (to
# ~80 cm; anatomy/population.py samples both).
_SHAPE_EXTENDED = {"sigmoid": 0.30, "transverse": 0.32}
# ... and nearer ends: a short sigmoid (to ~20 cm) whose loop barely rises.
_SHAPE_EXTENDED_LOW = {"sigmoid": -0.06}


def _hairpin(start_center: np.ndarray, end_center: np.ndarray, radius: float,
             up: bool) -> list[np.ndarray]:
    """Five points on a half circle in a sagittal plane, apex toward the head.

    `up` runs from the posterior leg to the anterior one (splenic flexure); otherwise from
    anterior to posterior (hepatic flexure). x moves linearly from start to end center.
    """
    out = []
    for k in range(5):
        phi = np.pi * k / 4
        x = start_center[0] + (end_center[0] - start_center[0]) * k / 4
        dz = -np.cos(phi) if up else np.cos(phi)
        out.append(np.array([x, start_center[1] + radius * np.sin(phi),
                             start_center[2] + radius * dz]))
    return out


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
    pts += [rs + [-0.035, 0.025, 0.010], rs + [-0.048, 0.040 + 0.5 * a, 0.020],
            rs + [-0.025, 0.055 + a, 0.025], rs + [0.015, 0.055 + a, 0.025],
            rs + [0.040, 0.035 + 0.5 * a, 0.025],
            np.array([0.065, -0.100, 0.090]), np.array([0.100, -0.118, 0.088]),
            _DESCENDING_SIGMOID]
    ends.append(len(pts) - 1)
    # Descending: straight up the left flank, posterior, into the splenic flexure: a
    # round hairpin (in the sagittal plane) that turns the colon anterior and caudal.
    d = shape["descending"]
    ds = _DESCENDING_SIGMOID
    top = ds[1] + d
    r = _FLEXURE_RADIUS
    sf_arc = _hairpin(np.array([ds[0] + 0.010, top - r, _FLEXURE_Z]),
                      np.array([ds[0] - 0.015, top - r, _FLEXURE_Z]), r, up=True)
    pts += [ds + [0.010, 0.45 * (d - r), -0.004]] + sf_arc[:3]
    ends.append(len(pts) - 1)
    # Transverse: leaves the splenic flexure anterior, sags by `g` toward the feet, rises
    # on the right into the hepatic flexure (a hairpin turning posterior and caudal).
    g = shape["transverse"]
    bottom_y = 0.10 - g
    hf = _HEPATIC_FLEXURE
    hf_arc = _hairpin(np.array([hf[0] + 0.020, hf[1] - r, _FLEXURE_Z]),
                      np.array([hf[0] - 0.015, hf[1] - r, _FLEXURE_Z]), r, up=False)
    pts += sf_arc[3:] + [
        np.array([0.065, bottom_y + 0.035, 0.162]),
        np.array([0.022, bottom_y, 0.168]),
        np.array([-0.028, bottom_y, 0.168]),
        np.array([-0.068, bottom_y + 0.035, 0.162])] + hf_arc[:3]
    ends.append(len(pts) - 1)
    # Ascending: down the right flank, posterior, to the ileocecal valve.
    c = shape["ascending"]
    pts += hf_arc[3:] + [hf + [-0.022, -0.72 * c, -0.040], hf + [-0.020, -c, -0.038]]
    ends.append(len(pts) - 1)
    icv = pts[-1]
    # Cecum: a short blind pouch hanging into the right iliac fossa.
    e = shape["cecum"]
    pts += [icv + [0.003, -0.5 * e, 0.002], icv + [0.006, -e, 0.004]]
    ends.append(len(pts) - 1)
    return np.array(pts, dtype=float), ends


class _Course:
    """Landmark spline, smoothed with a Gaussian along its arc length.

    The interpolating spline alone bends sharply at landmarks where the course turns; the
    Gaussian (odd-reflected at the ends so the end directions survive) bounds the curvature
    so the lumen tube never folds onto itself.
    """

    SAMPLES_PER_SPAN = 40
    STEP = 0.002  # [m] spacing of the smoothed polyline

    def __init__(self, landmarks: np.ndarray, smoothing: float):
        chords = np.linalg.norm(np.diff(landmarks, axis=0), axis=1)
        knots = np.concatenate([[0.0], np.cumsum(chords)])
        spline = make_interp_spline(knots, landmarks, k=3)
        u = [np.linspace(knots[i], knots[i + 1], self.SAMPLES_PER_SPAN, endpoint=False)
             for i in range(len(landmarks) - 1)]
        u = np.concatenate(u + [knots[-1:]])
        p = spline(u)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        s_knots = s[::self.SAMPLES_PER_SPAN]
        n = int(np.ceil(s[-1] / self.STEP)) + 1
        s_even = np.linspace(0.0, s[-1], n)
        q = spline(np.interp(s_even, s, u))
        if smoothing > 0.0:
            sigma = smoothing / (s_even[1] - s_even[0])
            pad = min(int(4 * sigma) + 1, n - 1)
            head = 2.0 * q[0] - q[pad:0:-1]
            tail = 2.0 * q[-1] - q[-2:-pad - 2:-1]
            q = gaussian_filter1d(np.concatenate([head, q, tail]), sigma, axis=0,
                                  mode="nearest")[pad:pad + n]
        self.points = q
        self.s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0),
                                                                 axis=1))])
        # A landmark keeps its (pre-smoothing) sample index: that is where its segment ends.
        self.s_knots = np.interp(s_knots, s_even, self.s)

    def resample(self, step: float) -> tuple[np.ndarray, np.ndarray]:
        """Points every ~`step` metres of arc length, including both ends."""
        n = int(np.ceil(self.s[-1] / step)) + 1
        s = np.linspace(0.0, self.s[-1], n)
        return s, CubicSpline(self.s, self.points, axis=0)(s)


def _jitter(rng: np.random.Generator, landmarks: np.ndarray, sigma: float) -> np.ndarray:
    """Random landmark offsets, smaller where landmarks are close (no kinks in short spans)."""
    span = np.linalg.norm(np.diff(landmarks, axis=0), axis=1)
    nearest = np.minimum(np.concatenate([[np.inf], span]), np.concatenate([span, [np.inf]]))
    scale = np.clip(nearest / 0.06, 0.2, 1.0)
    j = rng.normal(0.0, sigma, size=landmarks.shape) * scale[:, None]
    j[0] = 0.0  # the anus stays where it is
    return j


def nominal_radius(s: np.ndarray, boundaries: np.ndarray, params: ColonParams) -> np.ndarray:
    """Nominal lumen radius [m] along the arc, blended between segments (smoothstep)."""
    radii = [0.5 * params.segment(name).diameter for name in SEGMENT_NAMES]
    r = np.full_like(np.asarray(s, dtype=float), radii[0])
    half = 0.5 * params.radius_blend_length
    for k in range(1, len(radii)):
        x = np.clip((s - boundaries[k] + half) / (2.0 * half), 0.0, 1.0)
        r += (radii[k] - radii[k - 1]) * x * x * (3.0 - 2.0 * x)
    return r


# Acceptance of a sampled course: radius of curvature / lumen radius, and clearance
# between non-neighbouring parts of the tube beyond twice the larger radius [m] (so every
# wall point is nearest to its own stretch of centreline).
MIN_CURVATURE_RATIO = 1.2
MIN_CLEARANCE = 0.003
_NEIGHBOUR_ARC = 0.10
_MAX_ATTEMPTS = 40


def course_defects(s: np.ndarray, points: np.ndarray, radius: np.ndarray) -> tuple[float, float]:
    """(smallest curvature radius / lumen radius, smallest clearance [m]) of a course."""
    spline = CubicSpline(s, points, axis=0)
    d1, d2 = spline(s, 1), spline(s, 2)
    kappa = np.linalg.norm(np.cross(d1, d2), axis=1) / np.linalg.norm(d1, axis=1) ** 3
    ratio = float(np.min(1.0 / np.maximum(kappa * radius, 1e-12)))
    reach = 2.0 * radius.max() + MIN_CLEARANCE + 0.01
    pairs = cKDTree(points).query_pairs(reach, output_type="ndarray")
    pairs = pairs[np.abs(s[pairs[:, 0]] - s[pairs[:, 1]]) > _NEIGHBOUR_ARC]
    if len(pairs) == 0:
        return ratio, reach
    gap = (np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
           - 2.0 * np.maximum(radius[pairs[:, 0]], radius[pairs[:, 1]]))
    return ratio, float(gap.min())


def solve_course(params: ColonParams, rng: np.random.Generator):
    """Seeded course whose segments have seeded lengths, free of kinks and overlaps.

    Landmark jitter is redrawn (from the same generator, so still deterministic) until the
    course passes `course_defects`.

    Returns:
        (s, points, boundaries, targets): arc length samples every `centerline_step` [m],
        (N, 3) points [m], arc length of the 7 segment boundaries [m] and the sampled
        target length of each segment [m].
    """
    targets = {name: rng.uniform(params.segment(name).length_min,
                                 params.segment(name).length_max)
               for name in SEGMENT_NAMES}
    for _ in range(_MAX_ATTEMPTS):
        course, boundaries = _solve_lengths(params, rng, targets)
        s, points = course.resample(params.centerline_step)
        radius = nominal_radius(s, boundaries, params)
        ratio, clearance = course_defects(s, points, radius)
        if ratio >= MIN_CURVATURE_RATIO and clearance >= MIN_CLEARANCE:
            return s, points, boundaries, targets
    raise RuntimeError(f"no valid colon course for seed {params.seed}; "
                       "the landmark jitter is probably too large")


def _solve_lengths(params: ColonParams, rng: np.random.Generator, targets):
    shape = dict(_SHAPE_START)
    jitter = _jitter(rng, _landmarks(shape)[0], params.landmark_jitter)

    def build(sh):
        pts, ends = _landmarks(sh)
        course = _Course(pts + jitter, params.course_smoothing)
        return course, course.s_knots[ends]

    for _ in range(3):  # Gauss-Seidel sweeps: each parameter mostly moves its own segment
        for k, name in enumerate(SEGMENT_NAMES):
            lo, hi = _SHAPE_BRACKETS[name]

            def residual(x, k=k, name=name):
                trial = dict(shape)
                trial[name] = x
                b = build(trial)[1]
                return b[k + 1] - b[k] - targets[name]

            f_lo, f_hi = residual(lo), residual(hi)
            if f_hi < 0.0 and name in _SHAPE_EXTENDED:
                lo, hi = hi, _SHAPE_EXTENDED[name]
                f_lo, f_hi = f_hi, residual(hi)
            elif f_lo > 0.0 and name in _SHAPE_EXTENDED_LOW:
                lo, hi = _SHAPE_EXTENDED_LOW[name], lo
                f_lo, f_hi = residual(lo), f_lo
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
                if hi - lo < 1e-5:
                    break
            shape[name] = 0.5 * (lo + hi)
    return build(shape)
