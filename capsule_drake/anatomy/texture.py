"""Seeded procedural texture of the colonic mucosa (the visual wall's diffuse map).

Layers, bottom to top:
  - base colour with low-frequency patches, paler or redder (a smooth random field);
  - deep submucosal vessels: bluish purple, blurred by the tissue above them;
  - superficial vessels: darker red, sharp;
  - fine granular grain (the crypt openings' stipple), multiplying everything.
Vessels are trees grown by a correlated random walk: trunks wander, fork at random into
thinner children and taper until they fade out at capillary size.

The image is periodic in both directions (the fields are filtered in Fourier space and the
vessels are drawn wrapped around the edges), so it repeats without a seam around the lumen
(u) and along the axis (v). Image columns follow u = theta / 2 pi, rows the arc length at
`texels_per_metre`; all sizes below are converted to texels with that density.
"""

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .params import MucosaParams

SUPERSAMPLE = 2
"""Vessels are drawn at this multiple of the texture resolution, then averaged down, so
sub-texel widths come out as partial coverage instead of jagged one-pixel lines."""

VESSEL_ALPHA = 0.2
"""A texel counts as vessel where a vessel layer covers at least this fraction of it."""

# Colours the low-frequency variation pulls toward: paler (less blood in the lamina propria)
# and redder (hyperaemic); the amplitude sets how far.
_PALE = np.array([0.96, 0.72, 0.64])
_RED = np.array([0.78, 0.24, 0.22])

# Vessel growth in texel units (converted from metres by texels_per_metre) and per step.
_STEP_M = 0.00025          # random-walk step [m]
_MIN_WIDTH_M = 0.00010     # a branch ends where it has thinned to capillary size [m]
_TAPER = 0.998             # width factor per step
_BRANCH_P = 0.02           # chance of a fork per step
_END_P = 0.002             # chance a branch just ends (leaves the submucosa) per step
_MAX_STEPS = 400           # longest single branch [steps] (0.1 m)


@dataclass
class MucosaTexture:
    """The texture image and where its vessels are.

    Attributes:
        rgb: (texels_along, texels_around, 3) uint8, row 0 at v = 0 (image top).
        vessel_alpha: (texels_along, texels_around) float32 in [0, 1], the larger of the
            two vessel layers' coverage of each texel.
    """

    rgb: np.ndarray
    vessel_alpha: np.ndarray

    def vessel_fraction(self) -> float:
        """Fraction of texels that count as vessel (coverage >= VESSEL_ALPHA)."""
        return float(np.mean(self.vessel_alpha >= VESSEL_ALPHA))


def periodic_field(rng: np.random.Generator, shape, sigma: float) -> np.ndarray:
    """Gaussian random field of unit standard deviation, periodic in both directions.

    White noise low-passed by a Gaussian of `sigma` texels (its correlation length).
    """
    white = rng.standard_normal(shape)
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    kernel = np.exp(-2.0 * (np.pi * sigma) ** 2 * (fx**2 + fy**2))
    field = np.fft.irfft2(np.fft.rfft2(white) * kernel, s=shape)
    return field / max(float(field.std()), 1e-12)


def _grow_tree(rng: np.random.Generator, start, angle: float, width: float,
               min_width: float, step: float) -> np.ndarray:
    """Segments (K, 5): x0, y0, x1, y1, width [texels] of one branching vessel tree."""
    segments = []
    stack = [(start[0], start[1], angle, width)]
    while stack:
        x, y, heading, w = stack.pop()
        # Random numbers for the whole branch at once (a Python loop per step is the cost).
        turn = rng.normal(0.0, 0.04, _MAX_STEPS)
        bend = rng.normal(0.0, 0.004, _MAX_STEPS)
        fork = rng.random(_MAX_STEPS) < _BRANCH_P
        end = rng.random(_MAX_STEPS) < _END_P
        curvature = rng.normal(0.0, 0.01)
        for k in range(_MAX_STEPS):
            # Smoothly varying curvature: tortuous but not jittery.
            curvature = 0.97 * curvature + bend[k]
            heading += curvature + turn[k]
            nx, ny = x + step * np.cos(heading), y + step * np.sin(heading)
            segments.append((x, y, nx, ny, w))
            x, y = nx, ny
            w *= _TAPER
            if fork[k]:
                side = rng.choice((-1.0, 1.0))
                child = w * rng.uniform(0.6, 0.85)
                if child >= min_width:
                    stack.append((x, y, heading + side * rng.uniform(0.4, 1.1), child))
                w *= 0.88
                heading -= side * rng.uniform(0.05, 0.3)
            if w < min_width or end[k]:
                break
    return np.array(segments).reshape(-1, 5)


def _wrapped_copies(segments: np.ndarray, width: int, height: int) -> np.ndarray:
    """Segments moved into the image, plus shifted copies of those that cross an edge."""
    seg = segments.copy()
    shift_x = np.floor(seg[:, 0] / width) * width
    shift_y = np.floor(seg[:, 1] / height) * height
    seg[:, [0, 2]] -= shift_x[:, None]
    seg[:, [1, 3]] -= shift_y[:, None]
    reach = seg[:, 4] + 2.0
    lo_x = np.minimum(seg[:, 0], seg[:, 2]) - reach
    hi_x = np.maximum(seg[:, 0], seg[:, 2]) + reach
    lo_y = np.minimum(seg[:, 1], seg[:, 3]) - reach
    hi_y = np.maximum(seg[:, 1], seg[:, 3]) + reach
    out = []
    for ox in (-1, 0, 1):
        need_x = {0: np.ones(len(seg), bool), 1: lo_x < 0, -1: hi_x > width}[ox]
        for oy in (-1, 0, 1):
            need_y = {0: np.ones(len(seg), bool), 1: lo_y < 0, -1: hi_y > height}[oy]
            copy = seg[need_x & need_y].copy()
            copy[:, [0, 2]] += ox * width
            copy[:, [1, 3]] += oy * height
            out.append(copy)
    return np.concatenate(out)


def _draw_layer(segments: np.ndarray, opacity: np.ndarray, width: int, height: int,
                blur: float) -> np.ndarray:
    """Coverage (height, width) float32 in [0, 1] of anti-aliased, wrapped segments."""
    ss = SUPERSAMPLE
    shift = 3
    canvas = np.zeros((height * ss, width * ss), np.uint8)
    if len(segments):
        seg = _wrapped_copies(np.column_stack([segments, opacity]), width, height)
        # Sub-texel vessels: a one-pixel line whose opacity falls with its width.
        thickness = np.maximum(1, np.round(seg[:, 4] * ss)).astype(int)
        value = np.round(255 * seg[:, 5] * np.clip(seg[:, 4] * ss, 0.3, 1.0)).astype(int)
        points = np.round(seg[:, :4] * ss * (1 << shift)).astype(np.int32).reshape(-1, 2, 2)
        # Faint lines first: where vessels meet, the stronger one is drawn over.
        for v in np.unique(value):
            for t in np.unique(thickness[value == v])[::-1]:
                pick = (value == v) & (thickness == t)
                cv2.polylines(canvas, list(points[pick]), False, int(v), int(t),
                              cv2.LINE_AA, shift)
    layer = cv2.resize(canvas, (width, height), interpolation=cv2.INTER_AREA)
    layer = layer.astype(np.float32) / 255.0
    if blur > 0:
        pad = int(np.ceil(3 * blur))
        padded = np.pad(layer, pad, mode="wrap")
        layer = cv2.GaussianBlur(padded, (0, 0), blur)[pad:-pad, pad:-pad]
    return layer


def _vessel_layers(rng: np.random.Generator, params: MucosaParams):
    """Deep and superficial vessel coverage, grown until the vessel fraction is reached."""
    w, h = params.texels_around, params.texels_along
    tpm = params.texels_per_metre
    step = _STEP_M * tpm
    min_width = _MIN_WIDTH_M * tpm
    trees = []  # (segments, deep?, opacity)
    drawn_area = 0.0
    target_area = params.vessel_density * w * h
    for _ in range(6):
        # The drawn area (length x width) overestimates the coverage where branches overlap
        # and underestimates it where blur widens thin vessels: grow, measure, top up.
        while drawn_area < target_area:
            trunk = params.vessel_width * tpm * rng.uniform(0.6, 1.0)
            segments = _grow_tree(rng, rng.uniform(0, [w, h]), rng.uniform(0, 2 * np.pi),
                                  trunk, min_width, step)
            deep = rng.random() < params.deep_fraction
            trees.append((segments, deep, rng.uniform(0.75, 1.0) * (0.7 if deep else 0.95)))
            drawn_area += float(np.sum(segments[:, 4])) * step
        layers = []
        for deep, blur in ((True, 1.4), (False, 0.5)):
            chosen = [t for t in trees if t[1] == deep]
            segments = (np.concatenate([t[0] for t in chosen]) if chosen
                        else np.zeros((0, 5)))
            opacity = (np.concatenate([np.full(len(t[0]), t[2]) for t in chosen]) if chosen
                       else np.zeros(0))
            layers.append(_draw_layer(segments, opacity, w, h, blur))
        fraction = float(np.mean(np.maximum(*layers) >= VESSEL_ALPHA))
        if params.vessel_density == 0 or abs(fraction / params.vessel_density - 1.0) < 0.05:
            break
        if fraction > params.vessel_density:
            # Overshot (a large last tree): drop trees from the end and redraw.
            while trees and drawn_area > target_area * params.vessel_density / fraction:
                segments = trees.pop()[0]
                drawn_area -= float(np.sum(segments[:, 4])) * step
            target_area = drawn_area
            continue
        target_area *= params.vessel_density / max(fraction, 1e-3)
    return layers


def mucosa_texture(params: MucosaParams, seed) -> MucosaTexture:
    """The texture for `params`; `seed` (anything `numpy.random.default_rng` takes) fixes it."""
    rng = np.random.default_rng(seed)
    w, h = params.texels_around, params.texels_along
    tpm = params.texels_per_metre
    base = np.asarray(params.base_color, dtype=float)

    # Patches: about +-2 sigma of the field reaches the full amplitude.
    patches = 0.5 * params.variation_amplitude * periodic_field(
        rng, (h, w), params.variation_scale * tpm)
    toward_pale = np.clip(patches, 0.0, 1.0)[..., None]
    toward_red = np.clip(-patches, 0.0, 1.0)[..., None]
    color = base + toward_pale * (_PALE - base) + toward_red * (_RED - base)
    # A finer, weaker brightness mottle breaks up the smooth patches.
    mottle = periodic_field(rng, (h, w), 0.25 * params.variation_scale * tpm)
    color *= (1.0 + 0.1 * params.variation_amplitude * mottle)[..., None]

    deep, superficial = _vessel_layers(rng, params)
    for layer, tint in ((deep, params.deep_vessel_color), (superficial, params.vessel_color)):
        color += layer[..., None] * (np.asarray(tint, dtype=float) - color)

    grain = periodic_field(rng, (h, w), 0.7)
    color *= (1.0 + params.grain_amplitude * grain)[..., None]
    rgb = np.round(np.clip(color, 0.0, 1.0) * 255.0).astype(np.uint8)
    return MucosaTexture(rgb=rgb, vessel_alpha=np.maximum(deep, superficial))


def write_mucosa_texture(path, params: MucosaParams, seed) -> MucosaTexture:
    """Writes the texture as an RGB PNG at `path` and returns it."""
    texture = mucosa_texture(params, seed)
    if not cv2.imwrite(str(Path(path)), cv2.cvtColor(texture.rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write the mucosa texture to {path}")
    return texture
