"""Image-space conditions a capsule camera meets: exposure, gamma, sensor noise, motion blur,
vignetting, colour cast, compression, bubbles. Each is a function (rgb, field, rng) -> rgb
that draws its own strength at random, so an evaluation scores a detector over a range of
each, not at one setting. Pure numpy / OpenCV.

Light (fall-off, spot profile, ambient, specular) and texture cannot be changed on a
finished frame; the ray caster (`perception/raycast.py`) renders them.
"""

import cv2
import numpy as np


def _linear(rgb):
    return (rgb.astype(np.float32) / 255.0) ** 2.2


def _encode(linear):
    return np.round(255.0 * np.clip(linear, 0.0, 1.0) ** (1.0 / 2.2)).astype(np.uint8)


def exposure(rgb, field, rng):
    """Under- to over-exposure: the linear signal times 0.35-2.5 (clipped at full scale)."""
    return _encode(_linear(rgb) * rng.uniform(0.35, 2.5))


def gamma(rgb, field, rng):
    """Another tone curve: the encoded values raised to 0.6-1.6."""
    return np.round(255.0 * (rgb / 255.0) ** rng.uniform(0.6, 1.6)).astype(np.uint8)


def noise(rgb, field, rng):
    """Sensor noise: shot noise (variance proportional to the signal, 0.3-3 levels per
    level) and read noise (2-10 levels), per channel."""
    signal = rgb.astype(np.float32)
    sigma = np.sqrt(rng.uniform(0.3, 3.0) * signal + rng.uniform(2.0, 10.0) ** 2)
    return np.clip(np.round(signal + sigma * rng.standard_normal(rgb.shape)), 0,
                   255).astype(np.uint8)


def motion_blur(rgb, field, rng):
    """Linear motion blur over 3-15 px at a random angle."""
    length = int(rng.integers(3, 16))
    kernel = np.zeros((length, length), np.float32)
    kernel[length // 2, :] = 1.0
    turn = cv2.getRotationMatrix2D(((length - 1) / 2, (length - 1) / 2),
                                   rng.uniform(0.0, 180.0), 1.0)
    kernel = cv2.warpAffine(kernel, turn, (length, length))
    kernel /= max(kernel.sum(), 1e-6)
    return cv2.filter2D(rgb, -1, kernel, borderType=cv2.BORDER_REFLECT)


def vignetting(rgb, field, rng):
    """Vignetting: the linear signal falls by 20-70 % from the field's centre to its edge
    (a smooth power of the radius)."""
    H, W = rgb.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    cu, cv = (W - 1) / 2.0, (H - 1) / 2.0
    radius = np.hypot(u - cu, v - cv) / (0.5 * min(H, W))
    falloff = 1.0 - rng.uniform(0.2, 0.7) * np.clip(radius, 0.0, 1.2) ** rng.uniform(2.0, 4.0)
    return _encode(_linear(rgb) * np.clip(falloff, 0.0, 1.0)[..., None])


def colour_cast(rgb, field, rng):
    """A white balance off by up to +-35 % per channel (linear)."""
    return _encode(_linear(rgb) * rng.uniform(0.65, 1.35, 3)[None, None, :])


def compression(rgb, field, rng):
    """JPEG compression at quality 10-60 (a capsule's radio link compresses hard)."""
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                            [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(10, 61))])
    return cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def bubbles(rgb, field, rng):
    """3-25 bubbles in the fluid film (radius 2-14 px): a faint bright disc with a bright
    rim and a specular spot where the light at the lens reflects, anywhere in the field."""
    out = rgb.astype(np.float32)
    H, W = rgb.shape[:2]
    inside = np.argwhere(field) if field is not None else np.argwhere(np.ones((H, W), bool))
    for _ in range(int(rng.integers(3, 26))):
        y, x = inside[rng.integers(len(inside))]
        r = float(rng.uniform(2.0, 14.0))
        layer = np.zeros((H, W), np.float32)
        cv2.circle(layer, (int(x), int(y)), int(round(r)), 0.15, -1, cv2.LINE_AA)
        cv2.circle(layer, (int(x), int(y)), int(round(r)), 0.6, max(1, int(r / 5)),
                   cv2.LINE_AA)
        cv2.circle(layer, (int(x - r / 3), int(y - r / 3)), max(1, int(r / 4)), 1.0, -1,
                   cv2.LINE_AA)
        out = out + layer[..., None] * (255.0 - out)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def everything(rgb, field, rng):
    """Every condition above at once, in the order a camera applies them."""
    for condition in (vignetting, colour_cast, exposure, gamma, bubbles, motion_blur, noise,
                      compression):
        rgb = condition(rgb, field, rng)
    return rgb


CONDITIONS = {
    "exposure": exposure, "gamma": gamma, "noise": noise, "motion_blur": motion_blur,
    "vignetting": vignetting, "colour_cast": colour_cast, "compression": compression,
    "bubbles": bubbles, "everything": everything,
}
"""The image-space conditions by name (each applied alone; `everything` applies them all)."""


def apply(name: str, rgb, field, rng):
    """Condition `name` applied to `rgb` ("nominal": unchanged); the surround outside the
    lens's field stays black."""
    if name == "nominal":
        return rgb
    out = CONDITIONS[name](rgb, field, rng)
    if field is not None:
        out = out.copy()
        out[~field] = 0
    return out
