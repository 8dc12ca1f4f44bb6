"""The colon's centreline: an arc-length sampled curve with a rotation-minimising frame."""

import math
from pathlib import Path

import numpy as np
from numba import njit
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree


def rotation_minimising_frame(points: np.ndarray, tangents: np.ndarray,
                              first_normal: np.ndarray) -> np.ndarray:
    """Normals of the double-reflection rotation-minimising frame (Wang et al., ACM TOG 2008).

    Args:
        points: (N, 3) samples of the curve.
        tangents: (N, 3) unit tangents at the samples.
        first_normal: a vector not parallel to tangents[0]; its part normal to it starts
            the frame.

    Returns:
        (N, 3) unit normals; binormals are tangents x normals.
    """
    n = np.empty_like(points)
    r = first_normal - np.dot(first_normal, tangents[0]) * tangents[0]
    n[0] = r / np.linalg.norm(r)
    for i in range(len(points) - 1):
        v1 = points[i + 1] - points[i]
        c1 = v1 @ v1
        r_l = n[i] - (2.0 / c1) * (v1 @ n[i]) * v1
        t_l = tangents[i] - (2.0 / c1) * (v1 @ tangents[i]) * v1
        v2 = tangents[i + 1] - t_l
        c2 = v2 @ v2
        r_next = r_l - (2.0 / c2) * (v2 @ r_l) * v2 if c2 > 1e-30 else r_l
        n[i + 1] = r_next / np.linalg.norm(r_next)
    return n


class Centerline:
    """Arc-length parametrised centreline of the colon, from the anus (s = 0) to the cecal pole.

    Arrays (sampled every ~1 mm):
        s (N,): arc length [m]; points (N, 3) [m] in the world frame; tangents, normals,
        binormals (N, 3): unit, rotation-minimising frame (normal x binormal = tangent);
        radius (N,): nominal lumen radius [m]; segment (N,): index into `segment_names`.

    Between samples the position is a C2 cubic spline in s; the frame is interpolated and
    re-orthonormalised. The wall angle theta is measured from the normal toward the binormal.
    """

    def __init__(self, s, points, normals, radius, segment, segment_names):
        self.s = np.asarray(s, dtype=float)
        self.points = np.asarray(points, dtype=float)
        self.radius = np.asarray(radius, dtype=float)
        self.segment = np.asarray(segment, dtype=np.int32)
        self.segment_names = tuple(str(name) for name in segment_names)
        self._spline = CubicSpline(self.s, self.points, axis=0)
        self._spline.c = np.ascontiguousarray(self._spline.c)   # (4, N - 1, 3), compiled reads
        self._dspline = self._spline.derivative(1)
        self._ddspline = self._spline.derivative(2)
        self.tangents = self._unit(self._dspline(self.s))
        self._normal_samples = np.asarray(normals, dtype=float)
        self.normals, self.binormals = self._orthonormal(self.tangents, self._normal_samples)
        self._tree = cKDTree(self.points)

    @staticmethod
    def _unit(v):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    @classmethod
    def _orthonormal(cls, t, n_raw):
        n = cls._unit(n_raw - np.sum(n_raw * t, axis=-1, keepdims=True) * t)
        return n, np.cross(t, n)

    @property
    def length(self) -> float:
        """Total arc length [m]."""
        return float(self.s[-1])

    def _clip(self, s):
        return np.clip(np.asarray(s, dtype=float), 0.0, self.s[-1])

    def point_at(self, s) -> np.ndarray:
        """Centreline position(s) at arc length s [m] -> (..., 3)."""
        return self._spline(self._clip(s))

    def tangent_at(self, s) -> np.ndarray:
        """Unit tangent(s) at arc length s -> (..., 3)."""
        return self._unit(self._dspline(self._clip(s)))

    def frame_at(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(tangent, normal, binormal) at arc length s, each (..., 3)."""
        s = self._clip(s)
        t = self._unit(self._dspline(s))
        raw = np.stack([np.interp(s, self.s, self._normal_samples[:, k]) for k in range(3)],
                       axis=-1)
        n, b = self._orthonormal(t, raw)
        return t, n, b

    def curvature_at(self, s) -> np.ndarray:
        """Curvature [1/m] at arc length s (the spline is arc-length parametrised)."""
        s = self._clip(s)
        d1 = self._dspline(s)
        d2 = self._ddspline(s)
        speed = np.linalg.norm(d1, axis=-1)
        return np.linalg.norm(np.cross(d1, d2), axis=-1) / speed**3

    def radius_at(self, s) -> np.ndarray:
        """Nominal lumen radius [m] at arc length s (blended between segments)."""
        return np.interp(self._clip(s), self.s, self.radius)

    def segment_index_at(self, s) -> np.ndarray:
        """Index into `segment_names` of the segment containing arc length s."""
        idx = np.searchsorted(self.s, self._clip(s), side="right") - 1
        return self.segment[np.clip(idx, 0, len(self.s) - 1)]

    def segment_at(self, s: float) -> str:
        """Name of the segment containing arc length s."""
        return self.segment_names[int(self.segment_index_at(float(s)))]

    def segment_ranges(self) -> dict[str, tuple[float, float]]:
        """name -> (s_start, s_end) [m] for each segment, in order from the anus."""
        ranges = {}
        for k, name in enumerate(self.segment_names):
            idx = np.flatnonzero(self.segment == k)
            s1 = self.s[idx[-1] + 1] if idx[-1] + 1 < len(self.s) else self.s[-1]
            ranges[name] = (float(self.s[idx[0]]), float(s1))
        return ranges

    def closest(self, points, iterations: int = 4):
        """Closest centreline station of each world point.

        Args:
            points: (K, 3) or (3,) world points [m].
            iterations: Newton steps after the nearest-sample lookup.

        Returns:
            (s, distance, theta): arc length of the foot point (clamped to [0, L]); distance
            from the centreline in the normal plane [m]; angle [rad] in the frame at s,
            from the normal toward the binormal. Each (K,) (or scalars for one point).
        """
        p = np.ascontiguousarray(np.atleast_2d(np.asarray(points, dtype=float)))
        single = np.ndim(points) == 1
        _, idx = self._tree.query(p)
        s, dist, theta = _closest_stations(p, self.s[idx], self.s, self._spline.c,
                                           self._normal_samples, iterations)
        if single:
            return float(s[0]), float(dist[0]), float(theta[0])
        return s, dist, theta

    def save(self, path) -> None:
        """Write the samples to an .npz file."""
        np.savez(Path(path), s=self.s, points=self.points, normals=self._normal_samples,
                 radius=self.radius, segment=self.segment,
                 segment_names=np.array(self.segment_names))

    @classmethod
    def load(cls, path) -> "Centerline":
        """Read a centreline written by `save`."""
        with np.load(Path(path)) as data:
            return cls(data["s"], data["points"], data["normals"], data["radius"],
                       data["segment"], [str(x) for x in data["segment_names"]])


@njit(cache=True)
def _closest_stations(p, start, knots, c, normals, iterations):
    """Centerline.closest's Newton steps and frame, compiled: for each point p[k] (K, 3)
    from the station start[k], `iterations` Newton steps on (P(s) - p) . P'(s) = 0 over the
    cubic spline with breakpoints `knots` and coefficients c (4, N - 1, 3, highest power
    first), s kept in [0, L], a first-order step where the curve's second-order term makes
    the slope small or negative; then the tangent P', the normal interpolated linearly
    between the samples `normals` and made normal to it, and the point's distance and
    angle in that frame. Returns (s, distance, theta), each (K,)."""
    count = p.shape[0]
    last = knots.shape[0] - 2
    length = knots[-1]
    s_out = np.empty(count)
    dist_out = np.empty(count)
    theta_out = np.empty(count)
    P = np.empty(3)
    d1 = np.empty(3)
    d2 = np.empty(3)
    for k in range(count):
        s = start[k]
        for it in range(iterations + 1):
            i = min(max(np.searchsorted(knots, s, side="right") - 1, 0), last)
            dx = s - knots[i]
            for a in range(3):
                c0, c1, c2, c3 = c[0, i, a], c[1, i, a], c[2, i, a], c[3, i, a]
                P[a] = ((c0 * dx + c1) * dx + c2) * dx + c3
                d1[a] = (3.0 * c0 * dx + 2.0 * c1) * dx + c2
                d2[a] = 6.0 * c0 * dx + 2.0 * c1
            if it == iterations:
                break
            f = 0.0
            df = 0.0
            for a in range(3):
                d = P[a] - p[k, a]
                f += d * d1[a]
                df += d1[a] * d1[a] + d * d2[a]
            if not df > 0.2:
                df = 1.0
            s = min(max(s - f / df, 0.0), length)
        w = (s - knots[i]) / (knots[i + 1] - knots[i])
        norm_t = math.sqrt(d1[0] * d1[0] + d1[1] * d1[1] + d1[2] * d1[2])
        t0, t1, t2 = d1[0] / norm_t, d1[1] / norm_t, d1[2] / norm_t
        r0 = normals[i, 0] + w * (normals[i + 1, 0] - normals[i, 0])
        r1 = normals[i, 1] + w * (normals[i + 1, 1] - normals[i, 1])
        r2 = normals[i, 2] + w * (normals[i + 1, 2] - normals[i, 2])
        along = r0 * t0 + r1 * t1 + r2 * t2
        n0, n1, n2 = r0 - along * t0, r1 - along * t1, r2 - along * t2
        norm_n = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        n0, n1, n2 = n0 / norm_n, n1 / norm_n, n2 / norm_n
        b0, b1, b2 = t1 * n2 - t2 * n1, t2 * n0 - t0 * n2, t0 * n1 - t1 * n0
        e0, e1, e2 = p[k, 0] - P[0], p[k, 1] - P[1], p[k, 2] - P[2]
        along = e0 * t0 + e1 * t1 + e2 * t2
        e0, e1, e2 = e0 - along * t0, e1 - along * t1, e2 - along * t2
        s_out[k] = s
        dist_out[k] = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        theta_out[k] = math.atan2(e0 * b0 + e1 * b1 + e2 * b2, e0 * n0 + e1 * n1 + e2 * n2)
    return s_out, dist_out, theta_out
