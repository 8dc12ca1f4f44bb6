"""The capsule camera's configuration and its checks: lens, frame rate, light, image
conditions, latency (CameraConfig), and the size of the render faces a lens needs
(`face_pixels`, bounded before anything is allocated)."""

import dataclasses

import numpy as np

from capsule_drake.perception import Lens, LensConfig, photometry
from capsule_drake.schema import need_range

FPS_MODES = ("fixed", "adaptive")
DEFAULT_RENDERER = "capsule_camera"

# Faces of the cube map: optical axis and image "down" of each, in the camera frame C.
FACES = {
    "front": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    "right": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    "left": ((-1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    "down": ((0.0, 1.0, 0.0), (0.0, 0.0, -1.0)),
    "up": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "back": ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
}
# Face pixels kept beyond the region a face serves, so bilinear samples stay inside it.
FACE_MARGIN_PX = 2
# Depth: a face pixel whose inverse depth departs from the affine trend of its neighbours by
# more than this fraction lies on an occluding edge; output pixels that would blend it take


@dataclasses.dataclass
class CameraConfig:
    """The capsule camera, its frame rate and its light. YAML-loadable; all fields default."""

    # Lens and sensor (model, image size, field of view, distortion); see vision/lens.py.
    # Default: 172-degree equidistant fisheye at 256 x 256 px (PillCam COLON 2's field).
    lens: LensConfig = dataclasses.field(default_factory=LensConfig)
    # "fixed": a frame every 1 / fps. "adaptive": between fps_min and fps_max, faster while
    # the view moves, as PillCam COLON 2 does (4-35 fps; docs/sources.md section 2).
    fps_mode: str = "fixed"
    # Frame rate of the fixed mode (1/s).
    fps: float = 10.0
    # Adaptive mode: slowest and fastest frame rates (1/s); the camera ticks at fps_max.
    fps_min: float = 4.0
    fps_max: float = 35.0
    # Adaptive mode: image motion (rad/s) at which the rate reaches fps_max; it rises
    # linearly from fps_min at rest. Image motion = |v_WC| / viewing_distance + |w_WC|,
    # the angular speed of tissue `viewing_distance` ahead (m) as the camera moves.
    motion_for_fps_max: float = 0.5
    viewing_distance: float = 0.02
    # Clipping (m): nothing nearer than `near` is drawn, and tissue farther than `far`
    # (range along the ray) may not be: depth reads 0 (too near) or +inf (too far) there.
    # The light leaves under 4 % of its intensity at 0.2 m, so the colour barely changes.
    near: float = 0.001
    far: float = 0.2
    # Whether the depth image is rendered (it costs about as much again as colour).
    render_depth: bool = True
    # The LED ring, modelled as a white point light at the camera: intensity (relative,
    # 1 = full white on a perpendicular white surface at zero distance) and its quadratic
    # distance attenuation k in intensity / (1 + k d^2) (1/m^2). k = 1000 halves the light
    # at 3.2 cm and leaves 9 % at 10 cm, so the lumen is the dark region (sources.md s. 5).
    light_intensity: float = 1.6
    light_attenuation: float = 1000.0
    # Name of the SceneGraph renderer the camera uses (added by `add_camera_renderer`);
    # with windows, the prefix of its renderers' names.
    renderer_name: str = DEFAULT_RENDERER
    # In a colon, the wall is cut into windows this far apart along the centreline (m),
    # each in a renderer of its own, and a frame renders only the window the camera is in:
    # a software render costs in proportion to the triangles its renderer holds (see
    # anatomy/windows.py). 0: the whole wall in one renderer.
    window_spacing: float = 0.1
    # Face resolution relative to what the lens needs where it is sharpest (1 = no finer
    # than one output pixel; lower is faster and blurrier).
    face_resolution_scale: float = 1.0
    # Time from a frame's exposure to its delivery at the outputs (s): a capsule sends its
    # frames over a radio link to the workstation. 0: delivered at the exposure. Must be
    # below the camera's tick (1 / fps, or 1 / fps_max in adaptive mode) and needs a scene
    # the camera sees unmoving (a colon's camera walls).
    latency: float = 0.0
    # With latency > 0: draw frames in a process of their own (capsule/render_worker.py),
    # on another core while the simulation runs on; the images are the same either way.
    render_process: bool = True
    # Image conditions a frame meets before it leaves the camera (perception/photometry.py):
    # "nominal" (none), one of exposure, gamma, noise, motion_blur, vignetting, colour_cast,
    # compression, bubbles, everything (each with its strength drawn per frame), or "all": a
    # condition drawn per frame from all of these and nominal. The draws come from the
    # scenario's random_seed (a RandomSource sampled at the camera's tick), so a run can be
    # repeated; the depth image is never degraded.
    conditions: str = "nominal"


CAMERA_CONDITIONS = ("nominal",) + tuple(photometry.CONDITIONS)
"""What `CameraConfig.conditions` may name, besides "all"."""


def camera_tick(config: CameraConfig) -> float:
    """Period (s) at which the camera checks whether to take a frame: 1 / fps, or 1 / fps_max
    in adaptive mode."""
    return 1.0 / (config.fps_max if config.fps_mode == "adaptive" else config.fps)


# Bounds of the camera (check_camera_config).
MAX_IMAGE_SIDE = 4096
"""Largest image side (px): capsule cameras have 256-512 px (PillCam COLON 2: 256 x 256)."""
MAX_IMAGE_PIXELS = 2048 * 2048
"""Most image pixels: each frame is resampled from the render faces pixel by pixel."""
MAX_FACE_PIXELS = 5 * 2048 * 2048
"""Most pixels of the render faces a frame is drawn from (their atlas): each holds colour,
depth and ray scales (~30 bytes), so 20 M pixels are ~600 MB; the default lens needs 0.16 M."""
MAX_FPS = 120.0
"""Fastest frame rate (1/s): capsule cameras take 2-35 frames/s (PillCam COLON 2 4-35);
every frame is a software render of several views."""


def check_camera_config(config: CameraConfig) -> None:
    """Raises ValueError naming the first impossible field, or a lens whose render faces
    would exceed MAX_FACE_PIXELS (estimated on a coarse grid of the image, as LensRenderer
    sizes them, before anything is allocated)."""
    if config.fps_mode not in FPS_MODES:
        raise ValueError(f"camera fps_mode {config.fps_mode!r} is not one of {FPS_MODES}")
    why = "capsule cameras take 2-35 frames/s"
    need_range(config.fps, "fps", f"(0, {MAX_FPS:g}]", "1/s", why)
    need_range(config.fps_max, "fps_max", f"(0, {MAX_FPS:g}]", "1/s", why)
    need_range(config.fps_min, "fps_min", "> 0", "1/s")
    if not config.fps_min <= config.fps_max:
        raise ValueError(f"camera fps_min {config.fps_min} and fps_max {config.fps_max} "
                         "must satisfy 0 < fps_min <= fps_max")
    need_range(config.near, "near", "[1e-4, 1]", "m")
    need_range(config.far, "far", "(0, 10]", "m")
    if not config.near < config.far:
        raise ValueError(f"camera near {config.near} and far {config.far} must satisfy "
                         "0 < near < far")
    need_range(config.motion_for_fps_max, "motion_for_fps_max", "> 0", "rad/s")
    need_range(config.viewing_distance, "viewing_distance", "(0, 1]", "m")
    need_range(config.light_intensity, "light_intensity", "[0, 100]", "",
               "1 = full white on a white surface at the lens")
    need_range(config.light_attenuation, "light_attenuation", ">= 0", "1/m^2")
    if config.window_spacing != 0:
        need_range(config.window_spacing, "window_spacing", ">= 0.02", "m",
                   "or 0: no windows; each window is a renderer of its own, ~75 of them "
                   "at 2 cm along a 1.5 m colon")
    need_range(config.face_resolution_scale, "face_resolution_scale", "[0.05, 4]", "",
               "1 = the lens's sharpest sampling")
    if config.conditions not in CAMERA_CONDITIONS + ("all",):
        raise ValueError(f"camera conditions {config.conditions!r} is not one of "
                         f"{', '.join(CAMERA_CONDITIONS)} or all")
    need_range(config.latency, "latency", ">= 0", "s")
    lens_config = config.lens
    for name in ("width", "height"):
        need_range(getattr(lens_config, name), f"lens.{name}", f"[16, {MAX_IMAGE_SIDE}]", "px",
                   "capsule cameras have 256-512 px")
    pixels = lens_config.width * lens_config.height
    if pixels > MAX_IMAGE_PIXELS:
        raise ValueError(f"lens.width x lens.height must be at most {MAX_IMAGE_PIXELS:,} px "
                         f"(2048 x 2048), got {lens_config.width} x {lens_config.height}")
    if lens_config.fov_deg is not None:
        need_range(lens_config.fov_deg, "lens.fov_deg", ">= 10", "deg",
                   "capsule cameras see 140-172 deg")
    for name in ("fx", "fy"):
        value = getattr(lens_config, name)
        if value is not None:
            need_range(value, f"lens.{name}", f"[1, {10 * MAX_IMAGE_SIDE}]", "px")
    for name, size in (("cx", lens_config.width), ("cy", lens_config.height)):
        value = getattr(lens_config, name)
        if value is not None:
            need_range(value, f"lens.{name}", f"[0, {size}]", "px", "inside the image")
    for name in ("kb_coefficients", "radtan_coefficients"):
        need_range(getattr(lens_config, name), f"lens.{name}", "[-10, 10]", "",
                   "calibrated lenses have |k| < 1")
    lens = Lens(lens_config)  # raises ValueError naming a bad lens field
    tick = camera_tick(config)
    if config.latency >= tick:
        raise ValueError(f"camera latency {config.latency} s must be below the camera's "
                         f"tick ({tick:.4g} s: one frame in flight at a time)")
    faces = face_pixels(lens, config)
    if faces > MAX_FACE_PIXELS:
        raise ValueError(f"lens (width, height, fov_deg, fx, fy, distortion) and "
                         f"face_resolution_scale need render faces of ~{faces:,.0f} px, more "
                         f"than {MAX_FACE_PIXELS:,} (a smaller image, a shorter focal length "
                         "or a lower face_resolution_scale needs fewer)")


def face_pixels(lens: Lens, config: CameraConfig, samples: int = 65) -> float:
    """About how many pixels LensRenderer's faces will have for `lens` (its
    _build_views_and_maps on a `samples` x `samples` grid of the image: each face's pixel
    density from the Jacobian of its coordinates, times the extent it covers)."""
    if not lens.is_fisheye and not np.any(config.lens.radtan_coefficients):
        return float(lens.width * lens.height)  # one view, the image itself
    u = np.linspace(0.0, lens.width - 1.0, samples)
    v = np.linspace(0.0, lens.height - 1.0, samples)
    du, dv = u[1] - u[0], v[1] - v[0]
    uu, vv = np.meshgrid(u, v)
    rays = lens.unproject(np.column_stack([uu.ravel(), vv.ravel()]))
    in_field = lens.in_field(rays).reshape(samples, samples)
    rays = rays.reshape(samples, samples, 3)
    axes = np.array([axis for axis, _ in FACES.values()])
    face_of = (np.argmax(rays.reshape(-1, 3) @ axes.T, axis=1).reshape(samples, samples)
               if lens.is_fisheye else np.zeros((samples, samples), dtype=int))
    face_of[~in_field] = -1
    total = 0.0
    for index, (axis, down) in enumerate(FACES.values()):
        mine = face_of == index
        if not mine.any():
            continue
        z_F, y_F = np.array(axis), np.array(down)
        r_F = rays @ np.column_stack([np.cross(y_F, z_F), y_F, z_F])
        with np.errstate(divide="ignore", invalid="ignore"):
            a, b = r_F[..., 0] / r_F[..., 2], r_F[..., 1] / r_F[..., 2]
            det = np.abs(np.gradient(a, axis=1) * np.gradient(b, axis=0)
                         - np.gradient(a, axis=0) * np.gradient(b, axis=1)) / (du * dv)
        inner = mine & np.isfinite(det) & (det > 0.0)
        if not inner.any():
            continue
        density = np.percentile(1.0 / np.sqrt(det[inner]), 95.0)
        density *= config.face_resolution_scale
        margin = FACE_MARGIN_PX / density
        width = (max(a[mine].max() + margin, margin) - min(a[mine].min() - margin, -margin))
        height = (max(b[mine].max() + margin, margin) - min(b[mine].min() - margin, -margin))
        total += (width * density + 1.0) * (height * density + 1.0)
    return total
