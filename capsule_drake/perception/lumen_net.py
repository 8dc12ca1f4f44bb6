"""A learned lumen detector: a small convolutional network, in numpy, that reads a capsule
frame and answers where the image-side truth's far region is (perception/lumen_truth.py,
`far_region`) and whether a lumen is in view by that truth's definition.

Why a learned one beside the hand-made detectors (perception/lumen.py): the principle that
the darkest region is the farthest holds only while the light sits at the lens and falls off
as the inverse square. Under an LED ring with a narrow emission profile the periphery of
every view is darker than the lumen, and an intensity rule cannot tell the two apart; the
shape of the hole (folds converging on it, the wall brighter all round it) can. The network
is trained only on generated frames (both image paths, both lenses, random light and image
conditions) of colon seeds that no reported figure uses, by
`benchmarks/train_lumen_net.py`, which writes `models/lumen_net.npz`. Nothing downloads.

Architecture (every layer a 3x3 convolution with ReLU unless said otherwise):
input 64 x 64 x 4 (log intensity less the field's median, the field mask, x and y in
[-1, 1]) -> stride 2 -> plain -> stride 2 -> dilation 2 -> dilation 4 (LAYERS; each
layer's width is its weights', WIDTHS for new ones) on a 16 x 16 grid (each output cell sees about the whole frame), then two heads: a
1x1 convolution to one logit per cell, whose softmax over the field's cells weights the
cells' centres into the answer's position (a soft-argmax: sub-cell precision, trained on the
distance itself); and the mean and maximum of the last features over the field, through a
dense layer, to the logit that a lumen is in view.

Its operating point: `benchmarks/train_lumen_net.py calibrate` moves the visible logit's
bias so that the detector's default threshold (probability 0.5) sits where, on the
validation seeds' frames read as the detector reads them, no image path, lens or light
calls more than a set share of the views without a lumen visible (`operating_point`); the
weights' info records the shift and the rule.

Inference is numpy only (one frame: about a millisecond); the backward pass is here too, so
that the training script and the gradient test share one implementation.
"""

import dataclasses
from pathlib import Path

import cv2
import numpy as np

INPUT_SIZE = 64
GRID = 16
INPUT_CHANNELS = 4
LAYERS = (  # (name, stride, dilation); each layer's width is its weights' (WIDTHS: new ones)
    ("c1", 2, 1),
    ("c2", 1, 1),
    ("c3", 2, 1),
    ("c4", 1, 2),
    ("c5", 1, 4),
)
WIDTHS = (12, 16, 24, 24, 24)
DEFAULT_WEIGHTS = Path(__file__).resolve().parents[2] / "models" / "lumen_net.npz"


def preprocess(rgb: np.ndarray, field: np.ndarray | None = None):
    """(x (64, 64, 4) float32, inside (64, 64) bool, cells (16, 16) bool): the network's
    input from a frame (H, W, 3|4) uint8 and the lens's field. Intensity is R + G + B,
    averaged by area over the field's pixels only; its logarithm less the field's median
    (an exposure becomes an offset that this removes)."""
    H, W = rgb.shape[:2]
    if field is None:
        field = np.ones((H, W), dtype=bool)
    n = INPUT_SIZE
    intensity = rgb[..., 0].astype(np.float32)
    intensity += rgb[..., 1]
    intensity += rgb[..., 2]
    intensity *= field
    weight, cells = _field_maps(field)
    work = cv2.resize(intensity, (n, n), interpolation=cv2.INTER_AREA)
    inside = weight > 0.5
    x = np.zeros((n, n, 4), dtype=np.float32)
    if inside.any():
        log = np.log(work / np.maximum(weight, 1e-6) + 6.0)
        x[..., 0] = np.where(inside, log - np.median(log[inside]), 0.0)
    x[..., 1] = inside
    coords = (np.arange(n, dtype=np.float32) + 0.5) / n * 2.0 - 1.0
    x[..., 2] = coords[None, :]
    x[..., 3] = coords[:, None]
    return x, inside, cells


_FIELDS: dict = {}


def _field_maps(field):
    """(share of each input pixel inside the field (64, 64), cells (16, 16) bool), cached per
    field (a lens's field does not change from frame to frame)."""
    key = (field.shape, hash(np.packbits(field).tobytes()))
    if key not in _FIELDS:
        weight = cv2.resize(field.astype(np.float32), (INPUT_SIZE, INPUT_SIZE),
                            interpolation=cv2.INTER_AREA)
        cells = cv2.resize(weight, (GRID, GRID), interpolation=cv2.INTER_AREA) > 0.5
        if len(_FIELDS) > 16:
            _FIELDS.clear()
        _FIELDS[key] = (weight, cells)
    return _FIELDS[key]


def cell_centres() -> np.ndarray:
    """(2, 16, 16): each grid cell's centre (x, y) in [-1, 1] image coordinates."""
    c = (np.arange(GRID, dtype=np.float32) + 0.5) / GRID * 2.0 - 1.0
    return np.stack([np.broadcast_to(c[None, :], (GRID, GRID)),
                     np.broadcast_to(c[:, None], (GRID, GRID))])


CENTRES = cell_centres()


def to_unit(pixel, shape) -> np.ndarray:
    """Pixel (u, v) of an (H, W) image -> [-1, 1] coordinates (pixel centres)."""
    H, W = shape[:2]
    return np.array([(pixel[0] + 0.5) / W * 2.0 - 1.0, (pixel[1] + 0.5) / H * 2.0 - 1.0])


def to_pixel(unit, shape) -> np.ndarray:
    H, W = shape[:2]
    return np.array([(unit[0] + 1.0) / 2.0 * W - 0.5, (unit[1] + 1.0) / 2.0 * H - 0.5])


def symmetry(images, unit, code: int):
    """One of the eight symmetries of the square frame, for training: code bit 0 transposes,
    bit 1 flips x, bit 2 flips y. `images`: square arrays (H, W, ...) moved alike; `unit`:
    a point (x, y) in [-1, 1] coordinates, moved with them. Returns (*images, point)."""
    u, v = float(unit[0]), float(unit[1])
    images = list(images)
    if code & 1:
        images = [np.swapaxes(a, 0, 1) for a in images]
        u, v = v, u
    if code & 2:
        images = [a[:, ::-1] for a in images]
        u = -u
    if code & 4:
        images = [a[::-1] for a in images]
        v = -v
    return (*images, np.array([u, v], np.float32))


def unsymmetry(unit, code: int) -> np.ndarray:
    """A point moved by `symmetry` with `code`, moved back."""
    u, v = float(unit[0]), float(unit[1])
    if code & 4:
        v = -v
    if code & 2:
        u = -u
    if code & 1:
        u, v = v, u
    return np.array([u, v])


# --- layers (channels last: N, H, W, C) ---------------------------------------------------

def _columns(x, stride, dilation):
    """(N, H, W, C) -> (N, Ho, Wo, 9 C): each output pixel's 3x3 neighbourhood of the
    zero-padded input ('same' for stride 1; half the size for stride 2), rows (k, l, c)."""
    pad = dilation
    xp = np.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
    N, _, _, C = xp.shape
    Ho = (x.shape[1] - 1) // stride + 1
    Wo = (x.shape[2] - 1) // stride + 1
    s = xp.strides
    view = np.lib.stride_tricks.as_strided(
        xp, (N, Ho, Wo, 3, 3, C),
        (s[0], s[1] * stride, s[2] * stride, s[1] * dilation, s[2] * dilation, s[3]),
        writeable=False)
    return view.reshape(N, Ho, Wo, 9 * C)


def _matrix(w):
    """Weights (K, C, 3, 3) -> (9 C, K) in the row order of _columns."""
    return w.transpose(2, 3, 1, 0).reshape(-1, w.shape[0])


def conv_forward(x, w, b, stride, dilation):
    """3x3 convolution: x (N, H, W, C), w (K, C, 3, 3), b (K,) -> (N, Ho, Wo, K)."""
    return _columns(x, stride, dilation) @ _matrix(w) + b


def conv_backward(x, w, stride, dilation, grad, need_dx=True):
    """Gradients (dx, dw, db) of conv_forward's output against `grad` (N, Ho, Wo, K); dx
    None unless `need_dx`."""
    N, H, W, C = x.shape
    K = w.shape[0]
    cols = _columns(x, stride, dilation).reshape(-1, 9 * C)
    flat = grad.reshape(-1, K)
    dw = (cols.T @ flat).reshape(3, 3, C, K).transpose(3, 2, 0, 1)
    db = flat.sum(axis=0)
    if not need_dx:
        return None, dw, db
    dcols = (flat @ _matrix(w).T).reshape(N, grad.shape[1], grad.shape[2], 3, 3, C)
    pad = dilation
    dxp = np.zeros((N, H + 2 * pad, W + 2 * pad, C), dtype=grad.dtype)
    Ho, Wo = grad.shape[1:3]
    for k in range(3):
        for l in range(3):
            r0, c0 = k * dilation, l * dilation
            dxp[:, r0:r0 + stride * (Ho - 1) + 1:stride,
                c0:c0 + stride * (Wo - 1) + 1:stride] += dcols[:, :, :, k, l]
    return dxp[:, pad:pad + H, pad:pad + W], dw, db


def init_weights(rng, widths=WIDTHS) -> dict:
    """He-initialised weights for LAYERS, `widths` output channels each, and both heads."""
    weights, cin = {}, INPUT_CHANNELS
    for (name, _, _), cout in zip(LAYERS, widths, strict=True):
        weights[name + "_w"] = (rng.standard_normal((cout, cin, 3, 3))
                                * np.sqrt(2.0 / (9 * cin))).astype(np.float32)
        weights[name + "_b"] = np.zeros(cout, np.float32)
        cin = cout
    weights["heat_w"] = (rng.standard_normal(cin) * np.sqrt(1.0 / cin)).astype(np.float32)
    weights["heat_b"] = np.zeros(1, np.float32)
    weights["vis_w"] = (rng.standard_normal(2 * cin) * np.sqrt(1.0 / cin)).astype(np.float32)
    weights["vis_b"] = np.zeros(1, np.float32)
    return weights


def widths_of(weights) -> tuple:
    """The layers' widths read from `weights`; ValueError naming the first tensor that does
    not fit the one before it."""
    expected = {name + suffix for name, _, _ in LAYERS for suffix in ("_w", "_b")} | {
        "heat_w", "heat_b", "vis_w", "vis_b"}
    if set(weights) != expected:
        raise ValueError(f"hold {sorted(weights)}, not the layers {sorted(expected)}")
    widths, cin = [], INPUT_CHANNELS
    for name, _, _ in LAYERS:
        w = weights[name + "_w"]
        if w.ndim != 4 or w.shape[1:] != (cin, 3, 3):
            raise ValueError(f"{name}_w is {w.shape}, not (width, {cin}, 3, 3)")
        if weights[name + "_b"].shape != (w.shape[0],):
            raise ValueError(f"{name}_b is {weights[name + '_b'].shape}, not ({w.shape[0]},)")
        cin = w.shape[0]
        widths.append(cin)
    for key, shape in (("heat_w", (cin,)), ("heat_b", (1,)), ("vis_w", (2 * cin,)),
                       ("vis_b", (1,))):
        if weights[key].shape != shape:
            raise ValueError(f"{key} is {weights[key].shape}, not {shape}")
    return tuple(widths)


def widen(weights, widths, rng, scale: float = 0.1) -> dict:
    """The same function on wider layers: each layer's old channels keep their weights, its
    new channels get small random ones (`scale` times He's) and nothing reads them yet (the
    next layer's and the heads' weights on them are zero), so the output is unchanged and
    training can put the new channels to use."""
    old = widths_of(weights)
    if any(n < o for n, o in zip(widths, old, strict=True)):
        raise ValueError(f"widths {tuple(widths)} narrower than the weights' {old}")
    wide = init_weights(rng, widths)
    cin_old = INPUT_CHANNELS
    for (name, _, _), cout_old in zip(LAYERS, old):
        w = wide[name + "_w"]
        w *= scale
        w[:, cin_old:] = 0.0                      # inputs nothing produced before
        w[:cout_old, :cin_old] = weights[name + "_w"]
        wide[name + "_b"][:cout_old] = weights[name + "_b"]
        cin_old = cout_old
    c_old, c_new = old[-1], widths[-1]
    wide["heat_w"][:] = 0.0
    wide["heat_w"][:c_old] = weights["heat_w"]
    wide["heat_b"][:] = weights["heat_b"]
    wide["vis_w"][:] = 0.0
    wide["vis_w"][:c_old] = weights["vis_w"][:c_old]                  # means
    wide["vis_w"][c_new:c_new + c_old] = weights["vis_w"][c_old:]    # maxima
    wide["vis_b"][:] = weights["vis_b"]
    return wide


def forward(weights, x, cells):
    """x (N, 64, 64, 4), cells (N, 16, 16) bool -> (position (N, 2) in [-1, 1], visible
    logit (N,), cache for `backward`)."""
    cache = {"acts": []}
    h = x
    for name, stride, dilation in LAYERS:
        z = conv_forward(h, weights[name + "_w"], weights[name + "_b"], stride, dilation)
        cache["acts"].append((h, z))
        h = np.maximum(z, 0.0)
    cache["h"] = h
    logits = h @ weights["heat_w"] + weights["heat_b"][0]
    logits = np.where(cells, logits, -np.inf)
    top = logits.max(axis=(1, 2), keepdims=True)
    e = np.where(cells, np.exp(logits - top), 0.0)
    prob = e / np.maximum(e.sum(axis=(1, 2), keepdims=True), 1e-30)
    position = np.einsum("nhw,chw->nc", prob, CENTRES)
    area = np.maximum(cells.sum(axis=(1, 2)), 1)[:, None]
    mean = np.einsum("nhwc,nhw->nc", h, cells) / area
    N, C = h.shape[0], h.shape[3]
    peak = np.where(cells.reshape(N, -1, 1), h.reshape(N, -1, C), -np.inf).max(axis=1)
    peak = np.where(np.isfinite(peak), peak, 0.0)
    pooled = np.concatenate([mean, peak], axis=1)
    vis = pooled @ weights["vis_w"] + weights["vis_b"][0]
    cache.update(prob=prob, pooled=pooled, mean_area=area)
    return position, vis, cache


def loss_and_gradients(weights, x, cells, target, visible, position_scale=1.0,
                       huber=0.05):
    """The training loss and its gradients: a Huber loss (`huber` in [-1, 1] units) on the
    distance between the soft-argmax and the truth's far region, over frames with a lumen in
    view, plus the binary cross-entropy of the visible logit, both means over the batch.
    target (N, 2) in [-1, 1]; visible (N,) bool. Returns (loss, grads, parts)."""
    position, vis, cache = forward(weights, x, cells)
    N = len(x)
    grads = {}
    # position loss
    d = np.where(visible[:, None], position - target, 0.0)
    dist = np.sqrt((d ** 2).sum(axis=1) + 1e-12)
    quad = dist <= huber
    per = np.where(quad, 0.5 * dist ** 2 / huber, dist - 0.5 * huber)
    n_vis = max(int(visible.sum()), 1)
    loss_pos = position_scale * per[visible].sum() / n_vis
    dper = np.where(quad, dist / huber, 1.0) * position_scale / n_vis
    dpos = np.where(visible[:, None], dper[:, None] * d / dist[:, None], 0.0).astype(
        weights["heat_w"].dtype)
    # visible loss
    y = visible.astype(np.float64)
    p = 1.0 / (1.0 + np.exp(-np.clip(vis, -50, 50)))
    loss_vis = float(np.mean(np.logaddexp(0.0, vis) - y * vis))
    dvis = ((p - y) / N).astype(weights["vis_w"].dtype)
    # heads
    grads["vis_w"] = cache["pooled"].T @ dvis
    grads["vis_b"] = np.array([dvis.sum()], dvis.dtype)
    dpooled = dvis[:, None] * weights["vis_w"][None, :]
    h = cache["h"]
    C = h.shape[3]
    cells_f = cells.astype(h.dtype)
    dh = (dpooled[:, None, None, :C] * cells_f[..., None]
          / cache["mean_area"][:, None, None, :])
    masked = np.where(cells[..., None], h, -np.inf)
    flat = masked.reshape(N, -1, C)
    arg = flat.argmax(axis=1)
    dpeak = np.zeros_like(flat)
    np.put_along_axis(dpeak, arg[:, None, :], dpooled[:, None, C:], axis=1)
    dh = dh + dpeak.reshape(h.shape)
    prob = cache["prob"]
    dprob = np.einsum("nc,chw->nhw", dpos, CENTRES)
    dlogits = prob * (dprob - (dprob * prob).sum(axis=(1, 2), keepdims=True))
    grads["heat_w"] = np.einsum("nhwc,nhw->c", h, dlogits)
    grads["heat_b"] = np.array([dlogits.sum()], dlogits.dtype)
    dh = dh + dlogits[..., None] * weights["heat_w"]
    # trunk
    for depth, ((name, stride, dilation), (h_in, z)) in enumerate(
            zip(LAYERS[::-1], cache["acts"][::-1])):
        dz = dh * (z > 0)
        dx, dw, db = conv_backward(h_in, weights[name + "_w"], stride, dilation, dz,
                                   need_dx=depth < len(LAYERS) - 1)
        grads[name + "_w"] = dw
        grads[name + "_b"] = db
        dh = dx
    return loss_pos + loss_vis, grads, {"position": loss_pos, "visible": loss_vis}


def operating_point(logits, visible, sources, budget):
    """The lowest threshold on the visible logit at which no source calls more than `budget`
    of its frames without a lumen in view visible (a Neyman-Pearson operating point: the
    false positives fixed, the detection then as high as they allow). Returns (threshold,
    {source: (detection rate, false-positive rate)})."""
    logits, visible, sources = (np.asarray(v) for v in (logits, visible, sources))
    lowest = -np.inf
    for source in np.unique(sources):
        negatives = np.sort(logits[(sources == source) & ~visible])
        if len(negatives) == 0:
            continue
        # at most floor(budget * n) negatives may lie at or above the threshold
        allowed = int(np.floor(budget * len(negatives)))
        bound = negatives[len(negatives) - allowed - 1] if allowed < len(negatives) else -np.inf
        lowest = max(lowest, np.nextafter(bound, np.inf))
    threshold = float(lowest if np.isfinite(lowest) else logits.min())

    def rate(values):
        return float(np.mean(values >= threshold)) if len(values) else float("nan")
    rates = {source: (rate(logits[(sources == source) & visible]),
                      rate(logits[(sources == source) & ~visible]))
             for source in np.unique(sources)}
    return threshold, rates


# --- the detector -------------------------------------------------------------------------

@dataclasses.dataclass
class LumenNet:
    """Loaded weights and the settings they were trained with."""

    weights: dict
    info: dict

    @classmethod
    def load(cls, path: str | Path = DEFAULT_WEIGHTS) -> "LumenNet":
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"lumen network weights {path} not found; "
                             "benchmarks/train_lumen_net.py writes them")
        with np.load(path, allow_pickle=False) as data:
            weights = {key: data[key].astype(np.float32) for key in data.files
                       if not key.startswith("info_")}
            info = {key[len("info_"):]: data[key].tolist() for key in data.files
                    if key.startswith("info_")}
        try:
            widths_of(weights)
        except ValueError as e:
            raise ValueError(f"lumen network weights {path}: {e}") from None
        return cls(weights, info)

    def save(self, path: str | Path) -> None:
        extra = {"info_" + key: np.asarray(value) for key, value in self.info.items()}
        np.savez_compressed(path, **self.weights, **extra)

    def predict(self, rgb: np.ndarray, field: np.ndarray | None = None,
                symmetries: int = 1):
        """(pixel (u, v) in the frame, probability that a lumen is in view). With
        `symmetries` > 1 the network reads the frame under that many of the square's eight
        symmetries (codes 0, 1, ... of `symmetry`) at once and the answers, each moved back,
        are averaged (positions, and visible logits)."""
        x, inside, cells = preprocess(rgb, field)
        if not cells.any():
            return np.full(2, np.nan), 0.0
        codes = range(symmetries)
        xs = np.empty((symmetries,) + x.shape, np.float32)
        cs = np.empty((symmetries,) + cells.shape, bool)
        for i, code in enumerate(codes):
            log, ins, cs[i], _ = symmetry((x[..., 0], inside, cells), np.zeros(2), code)
            xs[i, ..., 0] = log
            xs[i, ..., 1] = ins
            xs[i, ..., 2:] = x[..., 2:]
        position, vis, _ = forward(self.weights, xs, cs)
        back = np.array([unsymmetry(p, code) for p, code in zip(position, codes)])
        logit = float(np.mean(vis))
        return (to_pixel(back.mean(axis=0), rgb.shape),
                float(1.0 / (1.0 + np.exp(-np.clip(logit, -50.0, 50.0)))))

