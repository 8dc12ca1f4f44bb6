"""The mucosal wall as an analytic surface r = wall_radius(s, theta) around the centreline.

wall radius = nominal segment radius (blended between segments)
              - haustral folds   (raised-cosine ridges across the lumen, crescent-shaped
                                  between the three taeniae: zero at the bands, highest
                                  midway; the three sectors are slightly staggered)
              - taenia ridges    (low Gaussian ridges along the bands)
              - rectal valves    (three half-circumference folds, alternating sides)
theta is measured in the centreline's rotation-minimising frame.
"""

from dataclasses import dataclass

import numpy as np

from .centerline import Centerline
from .params import SEGMENT_NAMES, ColonParams

TWO_PI = 2.0 * np.pi
SECTOR = TWO_PI / 3.0


@dataclass
class Folds:
    """Fold centres [m of arc], peak heights [m] and, for valves, the side angle [rad]."""

    s: np.ndarray
    height: np.ndarray
    angle: np.ndarray | None = None


def _raised_cosine(d: np.ndarray, half_width: float) -> np.ndarray:
    x = np.clip(np.abs(d) / half_width, 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * x))


def _nearest_two(centers: np.ndarray, s: np.ndarray):
    """Indices of the fold centres just below and just above each s (clipped)."""
    hi = np.searchsorted(centers, s)
    lo = np.clip(hi - 1, 0, len(centers) - 1)
    return lo, np.clip(hi, 0, len(centers) - 1)


class HaustralWall:
    """Seeded folds and taeniae on a centreline; evaluates the wall radius anywhere."""

    def __init__(self, params: ColonParams, centerline: Centerline, rng: np.random.Generator):
        self.params = params
        self.centerline = centerline
        ranges = centerline.segment_ranges()
        hw = params.fold_half_width
        sectors = [([], []) for _ in range(3)]
        for name in SEGMENT_NAMES:
            seg = params.segment(name)
            if seg.fold_height <= 0.0:
                continue
            s0, s1 = ranges[name]
            pos = s0 + rng.uniform(0.5, 1.0) * seg.fold_spacing_min
            while pos < s1 - 0.5 * seg.fold_spacing_min:
                for j in range(3):
                    c = pos + rng.uniform(-1.0, 1.0) * params.fold_stagger
                    h = (seg.fold_height * params.fold_height_scale
                         * rng.uniform(1.0 - params.fold_height_jitter,
                                       1.0 + params.fold_height_jitter))
                    if hw < c < centerline.length - hw:
                        sectors[j][0].append(c)
                        sectors[j][1].append(h)
                pos += rng.uniform(seg.fold_spacing_min, seg.fold_spacing_max)
        self.haustra = []
        for centers, heights in sectors:
            order = np.argsort(centers)
            self.haustra.append(Folds(np.asarray(centers)[order],
                                      np.asarray(heights)[order]))
        self.valves = self._rectal_valves(ranges["rectum"])
        # Taeniae run wherever the segment has them; blend like the radius does.
        has = np.array([1.0 if params.segment(n).has_taeniae else 0.0 for n in SEGMENT_NAMES])
        self._taenia_samples = has[centerline.segment]

    def _rectal_valves(self, rectum_range) -> Folds:
        p = self.params
        cl = self.centerline
        s = np.array([x for x in p.rectal_valve_positions
                      if rectum_range[0] < x < rectum_range[1]])
        # Alternate left (+x), right, left: the middle valve (Kohlrausch) is on the right.
        side = np.array([1.0 if k % 2 == 0 else -1.0 for k in range(len(s))])
        _, n, b = cl.frame_at(s)
        angle = np.arctan2(side * b[:, 0], side * n[:, 0])  # theta of the +-x direction
        height = np.full(len(s), p.rectal_valve_height * p.fold_height_scale)
        return Folds(s, height, angle)

    def fold_depth(self, s: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Inward height [m] of haustral folds and rectal valves at (s, theta)."""
        p = self.params
        hw = p.fold_half_width
        x = np.mod(theta - p.taenia_angle, TWO_PI)
        sector = np.minimum((x // SECTOR).astype(int), 2)
        crescent = np.sin(1.5 * x) ** 2  # 0 at the bands, 1 midway between them
        depth = np.zeros_like(s)
        for j, folds in enumerate(self.haustra):
            if len(folds.s) == 0:
                continue
            mask = sector == j
            sj = s[mask]
            lo, hi = _nearest_two(folds.s, sj)
            axial = (folds.height[lo] * _raised_cosine(sj - folds.s[lo], hw)
                     + np.where(hi != lo,
                                folds.height[hi] * _raised_cosine(sj - folds.s[hi], hw), 0.0))
            depth[mask] = axial * crescent[mask]
        for c, h, a in zip(self.valves.s, self.valves.height, self.valves.angle):
            lobe = np.maximum(np.cos(theta - a), 0.0) ** 2
            depth += h * _raised_cosine(s - c, hw) * lobe
        return depth

    def taenia_depth(self, s: np.ndarray, theta: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """Inward height [m] of the three taenia ridges."""
        p = self.params
        amp = p.taenia_height * np.interp(s, self.centerline.s, self._taenia_samples)
        out = np.zeros_like(s)
        for k in range(3):
            d = np.mod(theta - p.taenia_angle - k * SECTOR + np.pi, TWO_PI) - np.pi
            out += np.exp(-0.5 * (radius * d / p.taenia_width) ** 2)
        return amp * out

    def wall_radius(self, s, theta) -> np.ndarray:
        """Distance [m] from the centreline to the mucosa at arc length s, angle theta."""
        s, theta = np.broadcast_arrays(np.asarray(s, dtype=float),
                                       np.asarray(theta, dtype=float))
        shape = s.shape
        s = np.clip(s.ravel(), 0.0, self.centerline.length)
        theta = theta.ravel()
        r = self.centerline.radius_at(s)
        w = r - self.fold_depth(s, theta) - self.taenia_depth(s, theta, r)
        return w.reshape(shape)
