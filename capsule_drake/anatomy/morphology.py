"""Measures of a colon's course as CT colonography studies report them.

`acute_flexures` counts the places where the centreline turns through more than 90 degrees
within 10 cm: its direction 5 cm before a point and 5 cm after it differ by more than 90
degrees (the bend's interior angle is acute). Khashab et al. (Endoscopy 2009) count 10.9 +- 2.4 "acute-angle flexures"
per colon on CT colonography's 3D maps, and Hanson et al. (AJR 2007) 9.6 (completed
colonoscopies) and 11.9 (failed ones); their exact rule is not in their abstracts, so this
one is ours, written down here (docs/sources.md section 3.2).
"""

from __future__ import annotations

import numpy as np

FLEXURE_ARC = 0.05
"""Arc length (m) before and after a point over which its turn is measured."""
FLEXURE_ANGLE = 90.0
"""Turning angle (degrees) beyond which a bend is an acute-angle flexure (its interior
angle below 90 degrees)."""


def turning_angles(s, points, arc: float = FLEXURE_ARC) -> np.ndarray:
    """Angle (degrees) through which the centreline's direction turns from s - arc to
    s + arc (between its unit tangents there), at every sample at least `arc` from either
    end; NaN nearer the ends."""
    s, points = np.asarray(s, dtype=float), np.asarray(points, dtype=float)
    tangents = np.gradient(points, s, axis=0)
    tangents /= np.maximum(np.linalg.norm(tangents, axis=1, keepdims=True), 1e-12)

    def tangent_at(t):
        out = np.column_stack([np.interp(t, s, tangents[:, k]) for k in range(3)])
        return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)

    cos = np.einsum("ij,ij->i", tangent_at(s - arc), tangent_at(s + arc))
    angles = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    angles[(s < s[0] + arc) | (s > s[-1] - arc)] = np.nan
    return angles


def acute_flexures(s, points, arc: float = FLEXURE_ARC,
                   angle: float = FLEXURE_ANGLE) -> np.ndarray:
    """Arc lengths (m) of the acute-angle flexures of a centreline: each run of samples
    turning more than `angle` degrees within +-`arc` is one flexure, at its sharpest."""
    s = np.asarray(s, dtype=float)
    turns = turning_angles(s, points, arc)
    with np.errstate(invalid="ignore"):
        sharp = turns > angle
    edges = np.flatnonzero(np.diff(np.concatenate([[0], sharp.astype(int), [0]])))
    return np.array([s[start + int(np.nanargmax(turns[start:end]))]
                     for start, end in zip(edges[::2], edges[1::2])])
