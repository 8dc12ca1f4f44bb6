"""Lumen detection in a capsule image: the darkest region is the lumen when the light is at
the camera (docs/sources.md section 5). Pure OpenCV / numpy, independent of Drake.

Steps, as the seed paper's family of detectors has them, with the known flaws fixed:

1. pre-filter (Gaussian, as the seed; or median, as the STORM implementation) and take the
   red channel (mucosa reflects red most; vessels and texture show least there);
2. downsample to `work_size` pixels across;
3. histogram of the pixels the lens sees (a fisheye's black surround is excluded, and filled
   before filtering so it does not darken the rim);
4. a dark-biased, gradient-weighted Otsu threshold, vectorised over the histogram: maximise
   lambda(t) * eta(t), eta = between-class / total variance, lambda = ((L - t) / L) / g(t),
   g(t) = mean gradient of the pixels at level t relative to the image's (a threshold at
   the soft fall-off into the lumen beats one through sharp vessel edges);
5. connected regions of the dark class, scored S = I^2 * C * A (area A, compactness
   C = A / perimeter, I = 1 + (1 - normalised mean intensity), so darker scores higher:
   the public implementation forgets the normalisation, which inverts the preference);
6. centre = darkness-weighted centroid of the best region's core (its pixels within
   `core_fraction` of its range above its minimum; by default the whole region);
7. gates: a lumen is reported only with enough contrast between the region and the rest of
   the image, and not when the region hugs the edge of the field or its centre lies near
   that edge (the periphery of a view facing the wall is dark too).

`detect_lumen(rgb, field_mask, params) -> LumenDetection` is the detector signature; a user's
own detector with the same signature plugs in (see `load_detector`).
"""

import dataclasses
from typing import Callable

import cv2
import numpy as np

from capsule_drake.perception.lumen_net import DEFAULT_WEIGHTS, LumenNet
from capsule_drake.plugins import load_function
from capsule_drake.schema import need_range

PREFILTERS = ("gaussian", "median")
CORE_FEATURES = ("depth", "surround", "rim_fraction", "radius", "area_fraction")
"""What the core detector's confidence is a logistic function of (detect_lumen_core)."""
CORE_CONFIDENCE_WEIGHTS = (17.29, 4.932, -14.78, -9.916, -14.39, 1.843)


@dataclasses.dataclass
class LumenParams:
    """Detector settings. YAML-loadable; all fields default."""

    # "gaussian" (the seed paper) or "median" (the STORM implementation).
    prefilter: str = "gaussian"
    # Gaussian pre-filter sigma, in pixels of the input image.
    blur_sigma: float = 2.0
    # Median pre-filter aperture (odd), in pixels of the input image.
    median_size: int = 5
    # Longest side of the working image after downsampling (px).
    work_size: int = 128
    # Exponent of the dark bias (L - t) / L in the threshold criterion; 0 = plain Otsu.
    dark_bias: float = 2.0
    # Whether the threshold criterion divides by the mean gradient at the level (STORM's
    # weighting; off by default: on rendered frames it finds 31-95 % of visible lumens
    # against 96 % without, and it cuts synthetic blobs at their own sharp edges).
    gradient_weighted: bool = False
    # Radius (working pixels) of the morphological opening of the dark class; 0: none.
    opening: int = 1
    # The core whose darkness-weighted centroid is the centre: the region's pixels within
    # this fraction of its intensity range (threshold - minimum) above its minimum. 1, the
    # whole region, lies nearest the truth on rendered frames (median 1.3 % of the
    # diagonal, against 3.8 % for the darkest 20 %: the darkest pixels are the far end of
    # the lumen, which bends away).
    core_fraction: float = 1.0
    # Smallest region, as a fraction of the pixels the lens sees.
    min_area_fraction: float = 0.002
    # Gates (the periphery of a view facing the wall is dark too): least contrast
    # (bright-class mean - region mean) / bright-class mean; largest share of the region's
    # boundary on the edge of the field; largest distance of the centre from the field's
    # centre, relative to the field's radius (for a pinhole, of the circle of equal area).
    min_contrast: float = 0.5
    max_rim_fraction: float = 0.35
    max_radius: float = 0.85
    # Confidence at or above which the lumen is reported visible. "core": the fitted
    # probability that a lumen is in view (0.5 by default). "net": the network's, its 0.5
    # set at the operating point chosen on the validation seeds (lumen_net.py). "gaussian"
    # and "median": 0.5 means every gate passed, 1 contrast 1 and the region well inside
    # the field.
    min_confidence: float = 0.5
    # --- the "core" detector (detect_lumen_core) ---
    # Longest side of its working image (px).
    core_work_size: int = 64
    # Sigma of its masked Gaussian blur, as a fraction of the working image's longest side.
    core_sigma: float = 0.05
    # The core: connected to the darkest point of the blurred log intensity, the pixels
    # within this fraction of (field median - darkest) above the darkest.
    core_level: float = 0.6
    # ... and within this fraction of the field's radius of the darkest point (a dark
    # periphery joined to the lumen does not pull the centre outward).
    core_radius: float = 0.45
    # The darkest point is sought only this far inside the field's edge, as a share of the
    # image diagonal (0: anywhere but the edge's own pixels). A lumen whose centre lies
    # nearer the rim is, by the image-side truth's definition, not in view
    # (perception/lumen_truth.py, RIM_MARGIN, the same 8 %), and an unlit periphery is
    # darker than it.
    core_rim_margin: float = 0.08
    # The darkest point must be a basin: the lowest of the blurred log intensity within this
    # fraction of the working image's longest side around it (0: the darkest point
    # anywhere). Light falling off toward a wall-facing view's rim, or outside a narrow
    # spot, darkens toward the edge of the search without a basin; the lumen is one.
    core_basin: float = 0.0
    # The core as the image-side truth's far region is made (0: by `core_level`): the
    # darkest `core_quantile` of the field's blurred log intensity connected to the darkest
    # point, weighted by intensity^-1/2 (the range, were all light the lens's own falling
    # off as the inverse square).
    core_quantile: float = 0.0
    # Logistic confidence: bias, then the weights of CORE_FEATURES (fitted by
    # benchmarks/tune_lumen.py on colon seeds 0-4 only, against the image-side truth's
    # "lumen in view", with the 8 % rim margin: the simulator's frames under the nominal,
    # noise and exposure conditions and the ray caster's under its nominal light, through
    # the fisheye; scored on seeds 100-104 under every condition and both lenses,
    # docs/results/lumen.md).
    confidence_weights: list[float] = dataclasses.field(
        default_factory=lambda: list(CORE_CONFIDENCE_WEIGHTS))
    # --- the "net" detector (perception/lumen_net.py) ---
    # How many of the square frame's eight symmetries (flips and quarter turns, as trained)
    # the network reads each frame under, its answers moved back and averaged (1: the
    # frame alone). Each more costs about 0.4 ms (benchmarks/bench_lumen.py: 1.0-1.1 ms for
    # one, 2.3-2.4 ms for four).
    net_symmetries: int = 4


def check_lumen_params(params: LumenParams) -> None:
    """Raises ValueError naming the first impossible field."""
    if params.prefilter not in PREFILTERS:
        raise ValueError(f"lumen detector prefilter {params.prefilter!r} is not one of "
                         f"{PREFILTERS}")
    need_range(params.net_symmetries, "params.net_symmetries", "[1, 8]", "",
               "the square frame's flips and quarter turns")
    if params.median_size < 1 or params.median_size % 2 == 0:
        raise ValueError(f"lumen detector median_size {params.median_size} must be odd >= 1")
    if not params.blur_sigma >= 0.0:
        raise ValueError("lumen detector blur_sigma must be >= 0")
    if params.opening < 0:
        raise ValueError(f"lumen detector opening {params.opening} must be >= 0")
    if params.work_size < 16:
        raise ValueError(f"lumen detector work_size {params.work_size} must be >= 16")
    if not params.max_radius > 0.0:
        raise ValueError("lumen detector max_radius must be > 0")
    for name in ("core_fraction", "min_area_fraction", "min_contrast", "max_rim_fraction",
                 "min_confidence"):
        need_range(getattr(params, name), f"params.{name}", "[0, 1]")
    if not params.dark_bias >= 0.0:
        raise ValueError("lumen detector dark_bias must be >= 0")
    need_range(params.core_work_size, "params.core_work_size", "[16, 4096]", "px")
    need_range(params.core_sigma, "params.core_sigma", "(0, 0.5]")
    need_range(params.core_radius, "params.core_radius", "(0, 1]")
    need_range(params.core_quantile, "params.core_quantile", "[0, 0.5]")
    need_range(params.core_basin, "params.core_basin", "[0, 0.5]")
    need_range(params.core_rim_margin, "params.core_rim_margin", "[0, 0.3]")
    need_range(params.core_level, "params.core_level", "(0, 1]")
    if (len(params.confidence_weights) != len(CORE_FEATURES) + 1
            or not np.all(np.isfinite(params.confidence_weights))):
        raise ValueError(f"lumen detector confidence_weights must be {len(CORE_FEATURES) + 1}"
                         f" finite numbers (bias, then {', '.join(CORE_FEATURES)})")


@dataclasses.dataclass
class LumenDetection:
    """What a detector reports for one image.

    Attributes:
        visible: whether a lumen was found.
        pixel: (2,) its centre (u, v) in input-image pixels; NaN when not visible.
        confidence: in [0, 1].
        region: (H, W) uint8, 255 on the chosen dark region (input resolution), for overlays;
            all zero when nothing was found.
        threshold: the intensity threshold (0-255, red channel), NaN if none.
        features: the chosen region's measures behind the confidence (contrast, rim
            fraction, area fraction, compactness 4 pi A / P^2, normalised radius of the centre
            in the field), for analysis.
    """

    visible: bool
    pixel: np.ndarray
    confidence: float
    region: np.ndarray
    threshold: float = float("nan")
    features: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def nothing(cls, shape) -> "LumenDetection":
        return cls(False, np.full(2, np.nan), 0.0, np.zeros(shape[:2], dtype=np.uint8))


Detector = Callable[[np.ndarray, "np.ndarray | None"], LumenDetection]


def _shown(value, width: int = 60) -> str:
    """A value as a user would recognise it, cut to about `width` characters."""
    if isinstance(value, np.ndarray) and value.ndim == 1 and value.size <= 6:
        text = "[" + ", ".join(f"{x:.6g}" for x in value.tolist()) + "]"
    elif isinstance(value, np.ndarray):
        text = f"an array of shape {value.shape}"
    else:
        text = repr(value)
    text = " ".join(text.split())
    return text if len(text) <= width else text[:width - 3] + "..."


def detection_problem(result, shape) -> str | None:
    """Why `result`, a detector's return for an image of `shape` (H, W[, C]), breaks the
    detector contract (`load_detector`), in a phrase naming the value; None if it keeps it."""
    if result is None:
        return ("returned None, which is not a result: a detector reports no lumen with "
                "visible False (LumenDetection.nothing(rgb.shape))")
    missing = [a for a in ("visible", "pixel", "confidence") if not hasattr(result, a)]
    if missing:
        return (f"returned {_shown(result)} ({type(result).__name__}), not a result with "
                "visible, pixel and confidence (a LumenDetection)")
    visible = result.visible
    if not (isinstance(visible, (bool, np.bool_)) or (
            isinstance(visible, (int, np.integer)) and visible in (0, 1))):
        return f"returned visible = {_shown(visible)}, not True or False"
    try:
        pixel = np.asarray(result.pixel, dtype=float)
    except (TypeError, ValueError):
        return f"returned pixel = {_shown(result.pixel)}, not a pair of numbers (u, v)"
    if pixel.shape != (2,):
        return (f"returned pixel = {_shown(result.pixel)} of shape {pixel.shape}, not a "
                "pair (u, v)")
    if visible and not np.all(np.isfinite(pixel)):
        return (f"returned pixel = {_shown(pixel)} with visible True: a lumen it sees needs "
                "a finite (u, v)")
    confidence = result.confidence
    try:
        number = float(confidence)
    except (TypeError, ValueError):
        number = float("nan")
    if isinstance(confidence, (bool, np.bool_)) or not 0.0 <= number <= 1.0:
        return f"returned confidence = {_shown(confidence)}, not a number in [0, 1]"
    region = getattr(result, "region", None)
    if region is not None and np.shape(region) != tuple(shape[:2]):
        return (f"returned a region of shape {np.shape(region)}, not the image's "
                f"{tuple(shape[:2])}")
    return None


def dark_biased_threshold(values: np.ndarray, gradients: np.ndarray | None = None,
                          dark_bias: float = 1.0) -> int:
    """Threshold t (0-255) maximising ((L - t) / L)^dark_bias * eta(t) / g(t) over all levels
    at once (class 0 = values <= t). eta = between-class / total variance (Otsu);
    g(t) = mean of `gradients` over the pixels at level t, relative to their overall mean
    (smoothed over +-3 levels; 1 where no pixel has the level, or without gradients).

    Args: values: uint8 pixels (any shape); gradients: same shape, >= 0.
    """
    values = np.asarray(values).ravel()
    levels = np.arange(256, dtype=float)
    hist = np.bincount(values, minlength=256).astype(float)
    total = hist.sum()
    if total == 0:
        return 0
    p = hist / total
    w0 = np.cumsum(p)
    m0 = np.cumsum(p * levels)
    mean = m0[-1]
    variance = float(np.sum(p * (levels - mean) ** 2))
    if variance <= 0.0:
        return int(values[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (mean * w0 - m0) ** 2 / (w0 * (1.0 - w0))
    eta = np.where((w0 > 0.0) & (w0 < 1.0), between / variance, 0.0)
    criterion = eta * ((255.0 - levels) / 255.0) ** dark_bias
    if gradients is not None:
        g_sum = np.bincount(values, weights=np.asarray(gradients, dtype=float).ravel(),
                            minlength=256)
        kernel = np.ones(7)
        g_sum = np.convolve(g_sum, kernel, mode="same")
        counts = np.convolve(hist, kernel, mode="same")
        overall = max(float(g_sum.sum() / max(counts.sum(), 1.0)), 1e-9)
        with np.errstate(divide="ignore", invalid="ignore"):
            g = np.where(counts > 0, g_sum / counts / overall, 1.0)
        criterion = criterion / np.maximum(g, 0.05)
    return int(np.argmax(criterion))


def detect_lumen(rgb: np.ndarray, field_mask: np.ndarray | None = None,
                 params: LumenParams | None = None) -> LumenDetection:
    """Finds the lumen in an RGB(A) uint8 image (module docstring).

    Args:
        rgb: (H, W, 3 or 4) uint8, RGB channel order.
        field_mask: (H, W) bool, the pixels the lens sees (None: all).
        params: detector settings (default LumenParams()).
    """
    params = params or LumenParams()
    H, W = rgb.shape[:2]
    if field_mask is None:
        field_mask = np.ones((H, W), dtype=bool)
    red = np.ascontiguousarray(rgb[..., 0])
    if not field_mask.any():
        return LumenDetection.nothing(rgb.shape)
    # Fill the surround with the field's median so filtering does not darken the rim.
    red = red.copy()
    red[~field_mask] = np.uint8(np.median(red[field_mask]))
    if params.prefilter == "gaussian":
        if params.blur_sigma > 0.0:
            red = cv2.GaussianBlur(red, (0, 0), params.blur_sigma)
    else:
        red = cv2.medianBlur(red, params.median_size)

    scale = max(H, W) / params.work_size
    if scale > 1.0:
        size = (max(1, round(W / scale)), max(1, round(H / scale)))
        work = cv2.resize(red, size, interpolation=cv2.INTER_AREA)
        mask = cv2.resize(field_mask.astype(np.uint8), size,
                          interpolation=cv2.INTER_NEAREST).astype(bool)
    else:
        scale, work, mask = 1.0, red, field_mask
    # Keep a one-pixel margin inside the field: its edge pixels blend with the surround.
    mask = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    if mask.sum() < 16:
        return LumenDetection.nothing(rgb.shape)

    gx = cv2.Sobel(work, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(work, cv2.CV_32F, 0, 1, ksize=3)
    gradient = np.sqrt(gx * gx + gy * gy)
    values = work[mask]
    t = dark_biased_threshold(values, gradient[mask] if params.gradient_weighted else None,
                              params.dark_bias)
    dark = ((work <= t) & mask).astype(np.uint8)
    if params.opening > 0:
        # Detach thin dark lines (vessels, fold shadows) from the regions they cross.
        size = 2 * params.opening + 1
        dark = cv2.morphologyEx(dark, cv2.MORPH_OPEN,
                                cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(dark, connectivity=8)
    if count <= 1:
        return LumenDetection(False, np.full(2, np.nan), 0.0,
                              np.zeros((H, W), dtype=np.uint8), float(t))

    # Per-region area, mean intensity, boundary length and the boundary's share on the rim.
    flat = labels.ravel()
    area = np.bincount(flat, minlength=count).astype(float)
    intensity = np.bincount(flat, weights=work.ravel().astype(float), minlength=count)
    mean = intensity / np.maximum(area, 1.0)
    kernel = np.ones((3, 3), np.uint8)
    boundary = dark.astype(bool) & ~cv2.erode(dark, kernel, borderValue=0).astype(bool)
    perimeter = np.bincount(flat[boundary.ravel()], minlength=count).astype(float)
    outside = ~cv2.erode(mask.astype(np.uint8), kernel, borderValue=0).astype(bool)
    rim = np.bincount(flat[(boundary & outside).ravel()], minlength=count).astype(float)

    lo, hi = float(values.min()), float(values.max())
    normalised = (mean - lo) / max(hi - lo, 1.0)
    brightness = 1.0 + (1.0 - np.clip(normalised, 0.0, 1.0))
    compactness = area / np.maximum(perimeter, 1.0)
    score = brightness ** 2 * compactness * area
    score[0] = -np.inf  # the background label
    score[area < params.min_area_fraction * mask.sum()] = -np.inf
    best = int(np.argmax(score))
    if not np.isfinite(score[best]):
        return LumenDetection(False, np.full(2, np.nan), 0.0,
                              np.zeros((H, W), dtype=np.uint8), float(t))

    region = labels == best
    region_values = work[region].astype(float)
    floor = region_values.min()
    cut = floor + params.core_fraction * max(t - floor, 1.0)
    core = region & (work <= cut)
    v, u = np.nonzero(core)
    weight = cut - work[core].astype(float) + 1.0
    centre_work = np.array([np.sum(u * weight), np.sum(v * weight)]) / np.sum(weight)
    pixel = (centre_work + 0.5) * scale - 0.5

    bright = mask & (work > t)
    bright_mean = float(work[bright].mean()) if bright.any() else float(t)
    contrast = (bright_mean - mean[best]) / max(bright_mean, 1.0)
    rim_fraction = rim[best] / max(perimeter[best], 1.0)
    fv, fu = np.nonzero(mask)
    field_centre = np.array([fu.mean(), fv.mean()])
    radius = np.linalg.norm(centre_work - field_centre) / np.sqrt(mask.sum() / np.pi)
    # Each gate's margin in [-1, 1] (0 on the gate); confidence 0.5 + half the worst.
    margins = [(contrast - params.min_contrast) / max(1.0 - params.min_contrast, 1e-9),
               (params.max_rim_fraction - rim_fraction) / max(params.max_rim_fraction, 1e-9),
               (params.max_radius - radius) / params.max_radius]
    confidence = float(0.5 + 0.5 * np.clip(min(margins), -1.0, 1.0))
    visible = confidence >= params.min_confidence
    full_region = cv2.resize(region.astype(np.uint8) * 255, (W, H),
                             interpolation=cv2.INTER_NEAREST)
    features = {
        "contrast": float(contrast), "rim_fraction": float(rim_fraction),
        "area_fraction": float(area[best] / mask.sum()),
        "compactness": float(4 * np.pi * area[best] / max(perimeter[best], 1.0) ** 2),
        "radius": float(radius), "centre": pixel,
    }
    return LumenDetection(bool(visible), pixel if visible else np.full(2, np.nan),
                          confidence, full_region, float(t), features)


def inside_distance(field: np.ndarray) -> np.ndarray:
    """Each pixel's distance (px) to the nearest pixel outside `field` or the image (0
    outside the field): how far inside a lens's field it lies."""
    return cv2.distanceTransform(np.pad(np.asarray(field, dtype=np.uint8), 1), cv2.DIST_L2,
                                 cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]


def masked_blur(values, weight, sigma):
    """Gaussian blur of `values` over the pixels of `weight` only (normalised convolution),
    so the black surround of a fisheye's field does not darken its rim."""
    blurred = cv2.GaussianBlur(values * weight, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    total = cv2.GaussianBlur(weight, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    return blurred / np.maximum(total, 1e-6)


def detect_lumen_core(rgb: np.ndarray, field_mask: np.ndarray | None = None,
                      params: LumenParams | None = None) -> LumenDetection:
    """Finds the lumen's core: the darkest region of the image, light being at the lens,
    taken as the dark hole's centre rather than as the whole dark class.

    1. intensity = R + G + B (a colour cast moves no pixel's rank much), downsampled by area
       to `core_work_size` over the field;
    2. its logarithm, blurred over the field only (`core_sigma`): exposure becomes an offset
       and a tone curve nearly a scale, which the relative levels below do not see;
    3. the darkest point of the blurred field (one pixel inside its edge), and the core: the
       pixels connected to it within `core_level` of (field median - darkest) above it and
       within `core_radius` of the field's radius from it;
    4. centre: the core's centroid, weighted by how far below that level each pixel lies;
    5. confidence: a logistic function of the measures in CORE_FEATURES, fitted so that it
       estimates the probability that a lumen is in view (`benchmarks/tune_lumen.py`):
       depth, the log contrast between the field's median and the darkest point; surround,
       the core's log contrast with a ring around it; rim_fraction, the share of the core's
       boundary on the edge of the field (a view facing the wall darkens toward its rim);
       radius, the centre's distance from the field's centre over the field's radius; and
       area_fraction, the core's share of the field.

    Args: as `detect_lumen`.
    """
    params = params or LumenParams()
    H, W = rgb.shape[:2]
    if field_mask is None:
        field_mask = np.ones((H, W), dtype=bool)
    if not field_mask.any():
        return LumenDetection.nothing(rgb.shape)
    intensity = rgb[..., :3].astype(np.float32).sum(axis=2)
    scale = max(H, W) / params.core_work_size
    size = (max(1, round(W / scale)), max(1, round(H / scale)))
    weight = cv2.resize(field_mask.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    work = cv2.resize(intensity * field_mask, size, interpolation=cv2.INTER_AREA)
    inside = weight > 0.99
    work = np.where(inside, work / np.maximum(weight, 1e-6), 0.0).astype(np.float32)
    mask = inside.astype(np.float32)
    if mask.sum() < 16:
        return LumenDetection.nothing(rgb.shape)
    # +6: three channels' worth of the darkest levels' noise, so black does not reach -inf.
    log = masked_blur(np.log(work + 6.0), mask, params.core_sigma * max(size))
    kernel = np.ones((3, 3), np.uint8)
    inner = cv2.erode(inside.astype(np.uint8), kernel, borderValue=0).astype(bool)
    search = inner
    if params.core_rim_margin > 0.0:
        search = inner & (inside_distance(inside)
                          >= params.core_rim_margin * float(np.hypot(*size)))
    if params.core_basin > 0.0:
        reach = max(1, round(params.core_basin * max(size)))
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
        level = np.where(inside, log, 1e6).astype(np.float32)
        lowest = cv2.erode(level, disc, borderType=cv2.BORDER_CONSTANT, borderValue=1e6)
        search = search & (level <= lowest)
    if not search.any():
        return LumenDetection.nothing(rgb.shape)
    darkest = np.unravel_index(int(np.argmin(np.where(search, log, np.inf))), log.shape)
    low = float(log[darkest])
    median = float(np.median(log[inside]))
    depth = median - low
    cut = low + params.core_level * max(depth, 1e-6)
    if params.core_quantile > 0.0:
        cut = max(float(np.quantile(log[inside], params.core_quantile)), low + 1e-6)
    below = (log <= cut) & inside
    field_radius = np.sqrt(inside.sum() / np.pi)
    if params.core_radius < 1.0:
        yy, xx = np.ogrid[0:size[1], 0:size[0]]
        below &= ((yy - darkest[0]) ** 2 + (xx - darkest[1]) ** 2
                  <= (params.core_radius * field_radius) ** 2)
    below = below.astype(np.uint8)
    _, labels = cv2.connectedComponents(below, connectivity=8)
    core = labels == labels[darkest]
    v, u = np.nonzero(core)
    # Range-like weights for the quantile's core (light at the lens falls off as the
    # square of the range: range ~ intensity^-1/2), else depth below the cut.
    weights = (np.exp(-0.5 * (log[core] - low)) if params.core_quantile > 0.0
               else cut - log[core] + 1e-3)
    centre_work = np.array([np.sum(u * weights), np.sum(v * weights)]) / np.sum(weights)
    pixel = (centre_work + 0.5) * scale - 0.5

    core8 = core.astype(np.uint8)
    boundary = core & ~cv2.erode(core8, kernel, borderValue=0).astype(bool)
    rim_fraction = float((boundary & ~inner).sum() / max(boundary.sum(), 1))
    ring = (cv2.dilate(core8, kernel, iterations=max(2, round(0.06 * max(size)))).astype(bool)
            & ~core & inside)
    surround = float(np.median(log[ring]) - np.mean(log[core])) if ring.any() else 0.0
    fv, fu = np.nonzero(inside)
    radius = float(np.hypot(centre_work[0] - fu.mean(), centre_work[1] - fv.mean())
                   / field_radius)
    features = {"depth": depth, "surround": surround, "rim_fraction": rim_fraction,
                "radius": radius, "area_fraction": float(core.sum() / inside.sum())}
    weights_ = params.confidence_weights
    logit = weights_[0] + sum(w * features[name] for w, name in zip(weights_[1:],
                                                                     CORE_FEATURES))
    confidence = float(1.0 / (1.0 + np.exp(-np.clip(logit, -50.0, 50.0))))
    visible = confidence >= params.min_confidence
    region = cv2.resize(core8 * 255, (W, H), interpolation=cv2.INTER_NEAREST)
    features["centre"] = pixel
    return LumenDetection(bool(visible), pixel if visible else np.full(2, np.nan),
                          confidence, region, float(np.exp(cut) - 6.0), features)


def core_detector(params: LumenParams | None = None) -> Detector:
    """The core detector (detect_lumen_core) as a detector function."""
    params = params or LumenParams()
    return lambda rgb, field_mask=None: detect_lumen_core(rgb, field_mask, params)


def gaussian_detector(params: LumenParams | None = None) -> Detector:
    """The seed's detector (Gaussian pre-filter) as a detector function."""
    params = dataclasses.replace(params or LumenParams(), prefilter="gaussian")
    return lambda rgb, field_mask=None: detect_lumen(rgb, field_mask, params)


def median_detector(params: LumenParams | None = None) -> Detector:
    """The STORM variant (median pre-filter) as a detector function."""
    params = dataclasses.replace(params or LumenParams(), prefilter="median")
    return lambda rgb, field_mask=None: detect_lumen(rgb, field_mask, params)


_NETS: dict = {}


def net_detector(params: LumenParams | None = None, path=None) -> Detector:
    """The learned detector (perception/lumen_net.py) as a detector function: the network's
    answer, reported visible when its probability that a lumen is in view is at least
    `params.min_confidence`. Weights (default models/lumen_net.npz) load once per path."""
    params = params or LumenParams()
    min_confidence, symmetries = params.min_confidence, params.net_symmetries
    key = str(path or DEFAULT_WEIGHTS)
    if key not in _NETS:
        _NETS[key] = LumenNet.load(key)
    net = _NETS[key]

    def detect(rgb, field_mask=None):
        pixel, confidence = net.predict(rgb, field_mask, symmetries)
        if not np.all(np.isfinite(pixel)):
            return LumenDetection.nothing(rgb.shape)
        visible = confidence >= min_confidence
        return LumenDetection(bool(visible), pixel if visible else np.full(2, np.nan),
                              confidence, np.zeros(rgb.shape[:2], np.uint8),
                              features={"centre": pixel})

    return detect


# The built-in detectors' names (`load_detector`); any other name is a user's plug-in.
BUILT_IN_DETECTORS = ("core", "gaussian", "median", "net")


def load_detector(name: str, params: LumenParams | None = None) -> Detector:
    """A detector by name: "core" (detect_lumen_core), "gaussian", "median" (the
    dark-class detectors of the seed and of STORM), "net" (the learned detector,
    perception/lumen_net.py), or "package.module:function" naming a
    user's function with the signature (rgb (H, W, 3|4) uint8, field_mask (H, W) bool or
    None) -> LumenDetection (or an object with visible, pixel, confidence and, optionally,
    region). Raises ValueError with one line if it cannot be found.

    The contract of a detector's result (`detection_problem` checks it): `visible` a bool;
    `pixel` (u, v), finite when visible (NaN when not); `confidence` a number in [0, 1];
    `region`, if any, None or (H, W). "No lumen" is a result with visible False
    (`LumenDetection.nothing(rgb.shape)`); None, NaN or any other value is not a result.
    `capsule-sim eval-lumen` stops at a result that breaks the contract (one line naming
    the value and the frame, exit status 1), as at a detector that raises; the lumen
    tracker in a simulation counts a detector that raises as a failure and reports no lumen
    for that frame, and a user's result that breaks the contract ends the run (one line
    naming the detector and the value, exit status 1). A detector is given read-only views
    of the frame and the field mask: it may not write into them."""
    if name == "core":
        return core_detector(params)
    if name == "gaussian":
        return gaussian_detector(params)
    if name == "median":
        return median_detector(params)
    if name == "net":
        return net_detector(params)
    return load_function("lumen detector", name,
                         ", ".join(repr(built_in) for built_in in BUILT_IN_DETECTORS))
