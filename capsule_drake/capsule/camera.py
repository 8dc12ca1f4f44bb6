"""CapsuleCamera: the capsule's wide-angle camera with its on-board light, rendered by VTK.

No pinhole renders 150-172 degrees, so a fisheye image is assembled from several pinhole
views from the camera's centre (the faces of a cube map, each cropped to the part the field
of view reaches) and resampled through the lens model with `cv2.remap`; the maps are
computed once, at construction, from `Lens.unproject`. A pinhole lens renders one view and
applies its radial-tangential distortion the same way.

Cost model (measured, Drake 1.58 RenderEngineVtk on Mesa llvmpipe, 2 cores): a render call
costs the vertex work of every triangle its renderer holds, in view or not (RenderEngineVtk
culls nothing: ~0.3 ms colour per 10k triangles), plus ~1 ms per 10k pixels. So in a colon
the camera draws with the renderer of the window it is in (`renderer_for`, see
anatomy/windows.py and station.add_camera_walls): ~15k triangles instead of the whole wall.
"""

import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import (
    ClippingRange,
    ColorRenderCamera,
    DepthRange,
    DepthRenderCamera,
    FrameId,
    GeometryInstance,
    LightParameter,
    MakeRenderEngineVtk,
    Mesh,
    PerceptionProperties,
    QueryObject,
    RenderCameraCore,
    RenderEngineVtkParams,
    RenderLabel,
    Rgba,
    Role,
)
from pydrake.multibody.parsing import Parser
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem
from pydrake.systems.primitives import RandomSource
from pydrake.systems.sensors import CameraInfo, ImageDepth32F, ImageLabel16I, ImageRgba8U
from pydrake.common import RandomDistribution

from capsule_drake.anatomy import colon_assets
from capsule_drake.anatomy.lumen_state import BUBBLE_RGBA, FLUID_RGBA
from capsule_drake.anatomy.source import fluid_scene, lesion_scene
from capsule_drake.anatomy.windows import CameraWindows, camera_windows
from capsule_drake.capsule.render_worker import RenderWorker
from capsule_drake.lifetime import weak_method
from capsule_drake.perception import Lens, LensConfig, photometry
from capsule_drake.perception.lumen_truth import add_lumen_truth
from capsule_drake.blocks import block
from capsule_drake.schema import need_range

FPS_MODES = ("fixed", "adaptive")
LABEL_FACE_SCALE = 4.0
"""How much denser the faces of a fisheye's label images are than its colour's
(LensRenderer's label_scale)."""
LESION_LABEL_BASE = 1000
"""The render label of polyp k is LESION_LABEL_BASE + k (the plant's own labels are body
indices, far below)."""
DEFAULT_RENDERER = "capsule_camera"

# Faces of the cube map: optical axis and image "down" of each, in the camera frame C.
_FACES = {
    "front": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    "right": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    "left": ((-1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    "down": ((0.0, 1.0, 0.0), (0.0, 0.0, -1.0)),
    "up": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "back": ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
}
# Face pixels kept beyond the region a face serves, so bilinear samples stay inside it.
_FACE_MARGIN_PX = 2
# Depth: a face pixel whose inverse depth departs from the affine trend of its neighbours by
# more than this fraction lies on an occluding edge; output pixels that would blend it take
# the nearest sample instead (no "flying" depths between foreground and background).
_DEPTH_EDGE_FRACTION = 0.05
# Added to the principal point handed to RenderEngineVtk (see LensRenderer._add_view).
_VTK_PIXEL_OFFSET = 0.5


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
    if not 0.0 < config.fps_min <= config.fps_max:
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
    if not (math.isfinite(config.latency) and config.latency >= 0.0):
        raise ValueError(f"camera latency {config.latency} must be >= 0 and finite")
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
    faces = _face_pixels(lens, config)
    if faces > MAX_FACE_PIXELS:
        raise ValueError(f"lens (width, height, fov_deg, fx, fy, distortion) and "
                         f"face_resolution_scale need render faces of ~{faces:,.0f} px, more "
                         f"than {MAX_FACE_PIXELS:,} (a smaller image, a shorter focal length "
                         "or a lower face_resolution_scale needs fewer)")


def _face_pixels(lens: Lens, config: CameraConfig, samples: int = 65) -> float:
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
    axes = np.array([axis for axis, _ in _FACES.values()])
    face_of = (np.argmax(rays.reshape(-1, 3) @ axes.T, axis=1).reshape(samples, samples)
               if lens.is_fisheye else np.zeros((samples, samples), dtype=int))
    face_of[~in_field] = -1
    total = 0.0
    for index, (axis, down) in enumerate(_FACES.values()):
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
        margin = _FACE_MARGIN_PX / density
        width = (max(a[mine].max() + margin, margin) - min(a[mine].min() - margin, -margin))
        height = (max(b[mine].max() + margin, margin) - min(b[mine].min() - margin, -margin))
        total += (width * density + 1.0) * (height * density + 1.0)
    return total


def make_render_engine_params(light_intensity: float = 1.6,
                              light_attenuation: float = 1000.0) -> RenderEngineVtkParams:
    """RenderEngineVtk parameters for capsule cameras: one white point light at the camera
    (frame='camera'), falling off as 1 / (1 + k d^2) with k = `light_attenuation` (1/m^2),
    no default lights and a black background, so the unlit lumen is dark.

    The light follows whichever camera renders, so every view of a cube map is lit from the
    same point (the camera's centre) and the faces join without seams.
    """
    light = LightParameter(type="point", frame="camera", color=Rgba(1.0, 1.0, 1.0, 1.0),
                           intensity=light_intensity,
                           attenuation_values=[1.0, 0.0, light_attenuation])
    return RenderEngineVtkParams(default_clear_color=[0.0, 0.0, 0.0], lights=[light])


def add_camera_renderer(scene_graph, config: CameraConfig | None = None,
                        name: str | None = None) -> str:
    """Adds a VTK renderer for the camera to `scene_graph` (once), named `name` (default
    `config.renderer_name`); returns its name."""
    config = config or CameraConfig()
    name = name or config.renderer_name
    if not scene_graph.HasRenderer(name):
        scene_graph.AddRenderer(name, MakeRenderEngineVtk(
            make_render_engine_params(config.light_intensity, config.light_attenuation)))
    return name


@dataclasses.dataclass
class _View:
    """One pinhole render: its cameras, pose in the lens frame and place in the atlas."""

    name: str
    info: CameraInfo
    X_CF: RigidTransform
    width: int
    height: int
    row: int  # first atlas row
    range_scale: np.ndarray  # (h, w) float32: range along the ray / z-depth of the face


class LensRenderer:
    """Renders a lens's image from a QueryObject: pinhole views resampled through the lens.

    Plain Python (no Drake system): `CapsuleCamera` wraps it; benchmarks and tests call it.

    Args:
        config: the camera configuration (lens, clipping, renderer name).
        label_scale: the label images' faces are this much denser than the colour's: a
            label is sampled from the nearest face pixel, not blended. Against the
            projection of the polyps' geometry (tests/test_lesion_render.py, fisheye, masks
            of 100-2,200 px) the IoU was 0.74-0.94 at the colour's density, 0.83-0.97 at
            twice it and 0.91-0.99 at four times (measured; a label image then costs ~1.5
            colour images).
    """

    def __init__(self, config: CameraConfig, label_scale: float = LABEL_FACE_SCALE):
        self.config = config
        self._label_scale = float(label_scale)
        self._labels = None   # the renderer of the label images (denser faces), made once
        self.lens = Lens(config.lens)
        self.width, self.height = self.lens.width, self.lens.height
        rays, in_field = self.lens.pixel_rays()
        self.in_field = in_field
        self.views: list[_View] = []
        self._cameras: dict[str, list] = {}
        self._identity = (not self.lens.is_fisheye
                          and not np.any(config.lens.radtan_coefficients))
        if self._identity:
            # A distortion-free pinhole: one view with the lens's own intrinsics, no remap.
            self._add_view("front", RotationMatrix(), self.lens.fx, self.lens.fy,
                           self.lens.cx, self.lens.cy, self.width, self.height, row=0)
            self.atlas_shape = (self.height, self.width)
            return
        self._build_views_and_maps(rays, in_field)

    # ---- construction ---------------------------------------------------------------------
    def _add_view(self, name, R_CF: RotationMatrix, fx, fy, cx, cy, width, height, row):
        # RenderEngineVtk puts the ray through (cx, cy) half a pixel up and left of where
        # CameraInfo's documentation says (measured: a plane's depth fits u = fx a + cx - 0.5
        # for every cx), so it gets the principal point of pixel centres at i + 0.5.
        info = CameraInfo(width, height, fx, fy, cx + _VTK_PIXEL_OFFSET, cy + _VTK_PIXEL_OFFSET)
        u, v = np.meshgrid(np.arange(width), np.arange(height))
        a, b = (u - cx) / fx, (v - cy) / fy
        self.views.append(_View(
            name=name, info=info,
            X_CF=RigidTransform(R_CF, np.zeros(3)), width=width, height=height, row=row,
            range_scale=np.sqrt(1.0 + a * a + b * b).astype(np.float32)))

    def _build_views_and_maps(self, rays, in_field):
        H, W = self.height, self.width
        flat = rays.reshape(-1, 3)
        axes = np.array([axis for axis, _ in _FACES.values()])
        if self.lens.is_fisheye:
            face_of = np.argmax(flat @ axes.T, axis=1).reshape(H, W)
        else:
            face_of = np.zeros((H, W), dtype=int)  # one view for a pinhole: the front face
        face_of[~in_field] = -1
        map_u = np.full((H, W), -10.0, dtype=np.float32)  # outside the field: black border
        map_v = np.full((H, W), -10.0, dtype=np.float32)
        # Range along an output pixel's ray per unit z-depth of the face it samples.
        range_per_z = np.full((H, W), np.inf, dtype=np.float32)
        row = 0
        for index, (name, (axis, down)) in enumerate(_FACES.items()):
            mine = face_of == index
            if not mine.any():
                continue
            z_F = np.array(axis)
            y_F = np.array(down)
            R_CF = RotationMatrix(np.column_stack([np.cross(y_F, z_F), y_F, z_F]))
            r_F = rays @ R_CF.matrix()  # (H, W, 3): every pixel's ray in the face frame
            # Face pixel density: match the lens's sharpest sampling over this face, from the
            # Jacobian of face coordinates with respect to output pixels (infinite behind
            # the face, and not used there).
            with np.errstate(divide="ignore", invalid="ignore"):
                a = r_F[..., 0] / r_F[..., 2]
                b = r_F[..., 1] / r_F[..., 2]
                da_du, da_dv = np.gradient(a, axis=1), np.gradient(a, axis=0)
                db_du, db_dv = np.gradient(b, axis=1), np.gradient(b, axis=0)
                det = np.abs(da_du * db_dv - da_dv * db_du)
            inner = mine & np.isfinite(det) & (det > 0.0)
            density = np.percentile(1.0 / np.sqrt(det[inner]), 95.0)
            density *= self.config.face_resolution_scale
            lo_a, hi_a = a[mine].min(), a[mine].max()
            lo_b, hi_b = b[mine].min(), b[mine].max()
            margin = _FACE_MARGIN_PX / density
            # Drake needs the principal point inside the image: extend the crop to the axis.
            lo_a, lo_b = min(lo_a - margin, -margin), min(lo_b - margin, -margin)
            hi_a, hi_b = max(hi_a + margin, margin), max(hi_b + margin, margin)
            width = int(math.ceil((hi_a - lo_a) * density)) + 1
            height = int(math.ceil((hi_b - lo_b) * density)) + 1
            # Pixel centres at lo + k / density: the principal point is where a = 0.
            cx, cy = -lo_a * density, -lo_b * density
            self._add_view(name, R_CF, density, density, cx, cy, width, height, row)
            map_u[mine] = a[mine] * density + cx
            range_per_z[mine] = np.sqrt(1.0 + a[mine] ** 2 + b[mine] ** 2)
            map_v[mine] = b[mine] * density + cy + row
            row += height
        self.atlas_shape = (row, max(view.width for view in self.views))
        self._map_u, self._map_v = map_u, map_v
        self._range_per_z = range_per_z
        self._fixed_maps = cv2.convertMaps(map_u, map_v, cv2.CV_16SC2)
        self._range_scale = np.zeros(self.atlas_shape, dtype=np.float32)
        for view in self.views:
            self._range_scale[view.row:view.row + view.height, :view.width] = view.range_scale

    # ---- rendering ------------------------------------------------------------------------
    def cameras(self, renderer: str | None = None):
        """[(ColorRenderCamera, DepthRenderCamera)] of the views, for a renderer (default:
        the configured one); made once per renderer."""
        c = self.config
        name = renderer or c.renderer_name
        if name not in self._cameras:
            pairs = []
            for view in self.views:
                core = RenderCameraCore(name, view.info, ClippingRange(c.near, c.far),
                                        RigidTransform())
                pairs.append((ColorRenderCamera(core, False),
                              DepthRenderCamera(core, DepthRange(c.near, c.far))))
            self._cameras[name] = pairs
        return self._cameras[name]

    def render_rgba(self, query_object: QueryObject, parent_frame: FrameId,
                    X_PC: RigidTransform, out: np.ndarray | None = None,
                    renderer: str | None = None) -> np.ndarray:
        """(H, W, 4) uint8 RGBA image through the lens; black outside its field.
        `renderer`: the SceneGraph renderer to use (default: the configured one)."""
        cameras = self.cameras(renderer)
        if self._identity:
            image = query_object.RenderColorImage(cameras[0][0], parent_frame, X_PC)
            if out is None:
                return image.data.copy()
            out[...] = image.data
            return out
        atlas = np.zeros(self.atlas_shape + (4,), dtype=np.uint8)
        for view, (color_camera, _) in zip(self.views, cameras):
            image = query_object.RenderColorImage(color_camera, parent_frame,
                                                  X_PC.multiply(view.X_CF))
            atlas[view.row:view.row + view.height, :view.width] = image.data
        if out is None:
            out = np.empty((self.height, self.width, 4), dtype=np.uint8)
        cv2.remap(atlas, self._fixed_maps[0], self._fixed_maps[1], cv2.INTER_LINEAR,
                  dst=out, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        out[..., 3] = 255
        return out

    def render_label(self, query_object: QueryObject, parent_frame: FrameId,
                     X_PC: RigidTransform, renderer: str | None = None) -> np.ndarray:
        """(H, W) int16 render labels through the lens (each pixel the label of the geometry
        it sees, taken from the nearest pixel of the views: labels do not blend);
        RenderLabel.kDontCare outside the lens's field, RenderLabel.kEmpty where nothing is
        within range. `renderer` as for `render_rgba`."""
        if not self._identity and self._label_scale != 1.0:
            if self._labels is None:
                self._labels = LensRenderer(dataclasses.replace(
                    self.config, face_resolution_scale=self._label_scale
                    * self.config.face_resolution_scale), label_scale=1.0)
            return self._labels.render_label(query_object, parent_frame, X_PC, renderer)
        cameras = self.cameras(renderer)
        outside = int(RenderLabel.kDontCare)
        if self._identity:
            return np.array(query_object.RenderLabelImage(
                cameras[0][0], parent_frame, X_PC).data[..., 0], dtype=np.int16)
        atlas = np.full(self.atlas_shape, outside, dtype=np.int16)
        for view, (color_camera, _) in zip(self.views, cameras):
            image = query_object.RenderLabelImage(color_camera, parent_frame,
                                                  X_PC.multiply(view.X_CF))
            atlas[view.row:view.row + view.height, :view.width] = image.data[..., 0]
        return cv2.remap(atlas, self._fixed_maps[0], self._fixed_maps[1], cv2.INTER_NEAREST,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=outside)

    def render_range(self, query_object: QueryObject, parent_frame: FrameId,
                     X_PC: RigidTransform, out: np.ndarray | None = None,
                     renderer: str | None = None) -> np.ndarray:
        """(H, W) float32 range (m) along each pixel's ray from the camera centre.

        +inf where nothing is within range `far` (and outside the lens's field), 0 where the
        first surface is nearer than `near`. `renderer` as for `render_rgba`.
        """
        cameras = self.cameras(renderer)
        if self._identity:
            view = self.views[0]
            image = query_object.RenderDepthImage(cameras[0][1], parent_frame, X_PC)
            result = image.data[..., 0] * view.range_scale
        else:
            atlas = np.full(self.atlas_shape, np.inf, dtype=np.float32)
            for view, (_, depth_camera) in zip(self.views, cameras):
                image = query_object.RenderDepthImage(depth_camera, parent_frame,
                                                      X_PC.multiply(view.X_CF))
                atlas[view.row:view.row + view.height, :view.width] = image.data[..., 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                # Inverse z-depth is affine in a pinhole image over any plane, so bilinear
                # interpolation of it is exact on planes at any incidence.
                inverse = 1.0 / atlas
                # Occluding edges: where inverse depth is not locally affine (second
                # differences), or not finite (too near), samples take the nearest pixel
                # instead of blending foreground and background.
                edge = np.zeros(self.atlas_shape, dtype=np.float32)
                d2 = np.abs(inverse[:, :-2] - 2.0 * inverse[:, 1:-1] + inverse[:, 2:])
                edge[:, 1:-1] += ~(d2 <= _DEPTH_EDGE_FRACTION * inverse[:, 1:-1])
                d2 = np.abs(inverse[:-2] - 2.0 * inverse[1:-1] + inverse[2:])
                edge[1:-1] += ~(d2 <= _DEPTH_EDGE_FRACTION * inverse[1:-1])
                edge += ~np.isfinite(inverse)
                inverse[~np.isfinite(inverse)] = 0.0
                linear = self._range_per_z / cv2.remap(
                    inverse, self._map_u, self._map_v, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
                atlas *= self._range_scale
            near_edge = cv2.remap(edge, self._map_u, self._map_v, cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=1.0) > 0.0
            nearest = cv2.remap(atlas, self._map_u, self._map_v, cv2.INTER_NEAREST,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=np.inf)
            result = np.where(near_edge, nearest, linear)
            result[~self.in_field] = np.inf
        # Views clip at z-depth `far`, which reaches farther along oblique rays.
        result[result > self.config.far] = np.inf
        if out is None:
            return result.astype(np.float32, copy=False)
        out[...] = result
        return out


class CapsuleCamera(LeafSystem):
    """The capsule's camera: colour and depth through its lens, sampled and held.

    A periodic unrestricted update renders from the SceneGraph's query object and stores the
    images in abstract state; the outputs are that state (sample-and-hold, no algebraic
    loop). With `latency` > 0 a frame exposed at t is delivered at t + latency by a second
    periodic event (drawn meanwhile by `worker`, when given and able, else at delivery from
    the exposure's pose: the same image). Fixed mode captures every 1 / fps. Adaptive mode ticks at fps_max and captures
    when the time since the last frame reaches 1 / rate, where the rate rises linearly from
    fps_min (camera at rest) to fps_max (image motion >= motion_for_fps_max); image motion
    is estimated from the camera's pose change over the last tick, read from the query
    object. A frame is also captured when the simulation initialises.

    .. pydrake_system::

        name: CapsuleCamera
        input_ports:
        - query_object
        - condition_draw (with config.conditions other than nominal)
        output_ports:
        - rgb_image
        - depth_image
        - frame_info
        - frame_pose
        - label_image (with static_scene)

    condition_draw: two uniform numbers in [0, 1) read at each frame (a RandomSource at
    the camera's tick): which image condition of `config.conditions` the frame meets, and
    the seed of its strengths (`condition_of`).
    rgb_image: ImageRgba8U (H x W); black outside the lens's image circle; with its image
    condition applied.
    depth_image: ImageDepth32F (H x W), metres of RANGE along each pixel's ray from the
    camera centre (not z-depth: beyond 90 degrees z-depth is meaningless); +inf beyond `far`
    and outside the image circle, 0 nearer than `near`. Stays +inf if render_depth is off.
    frame_info: [exposure time of the last frame delivered (s), frames delivered, 1 if the
    camera's last event delivered a frame else 0, current frame rate (1/s)].
    frame_pose: the camera's pose at that frame's exposure, [R_WC row-major (9), p_WC (3)]
    (NaN before the first frame).
    label_image: ImageLabel16I (H x W), the RenderLabel each pixel of that frame sees
    (`LensRenderer.render_label`), drawn when first read: a lesion's label is its own.

    Args:
        config: CameraConfig (lens, frame rate, clipping, light, renderer name). The
            renderer must exist in the SceneGraph (see `add_camera_renderer`).
        parent_frame: SceneGraph frame the camera is fixed to (e.g. the capsule body's,
            `plant.GetBodyFrameIdOrThrow(body.index())`).
        X_PC: camera pose in that frame (e.g. the capsule's `camera` frame in its body).
        renderer_for: optional function of the camera's world position (3,) returning the
            name of the renderer to draw with (the colon window it is in; see
            `add_camera_walls`). None: always `config.renderer_name`.
        static_scene: True when everything the camera can see is anchored (in a colon with
            camera walls, the station strips the perception role from all else). Then the
            depth image of a frame is drawn when something first reads it, from the pose
            the frame was taken at, and never when nothing does: the same image, at no
            cost to a diagram that does not use depth. False: drawn with every frame.
        worker: optional RenderWorker drawing the frames of a camera with latency.
    """

    def __init__(self, config: CameraConfig, parent_frame: FrameId, X_PC: RigidTransform,
                 renderer_for=None, static_scene: bool = False, worker=None):
        super().__init__()
        self._config = dataclasses.replace(config)
        self._renderer = LensRenderer(self._config)
        self._parent_frame = parent_frame
        self._X_PC = RigidTransform(X_PC)
        self._renderer_for = renderer_for
        W, H = self._renderer.width, self._renderer.height
        c = self._config
        self._adaptive = c.fps_mode == "adaptive"
        self._tick = camera_tick(c)
        self._latency = c.latency
        if self._latency > 0.0 and not static_scene:
            raise ValueError("camera latency needs a scene the camera sees unmoving (a "
                             "colon's camera walls): a frame is drawn after its exposure")
        self._worker = worker if self._latency > 0.0 else None

        self._query_object_port = self.DeclareAbstractInputPort(
            "query_object", AbstractValue.Make(QueryObject()))
        # Image conditions: two uniform draws per frame (which condition, its strengths).
        self._conditions = c.conditions
        self._draw_port = None
        if self._conditions != "nominal":
            self._draw_port = self.DeclareVectorInputPort("condition_draw", 2)
            self._field = self._renderer.lens.pixel_rays()[1]
        rgb = ImageRgba8U(W, H)
        depth = ImageDepth32F(W, H)
        depth.mutable_data[...] = np.inf
        self._rgb_index = self.DeclareAbstractState(AbstractValue.Make(rgb))
        self._depth_index = self.DeclareAbstractState(AbstractValue.Make(depth))
        first_rate = c.fps_min if self._adaptive else c.fps
        self._info_index = self.DeclareDiscreteState(
            BasicVector([-np.inf, 0.0, 0.0, first_rate]))
        # Camera pose at the previous tick, [R_WC row-major (9), p_WC (3)], for the motion.
        self._pose_index = self.DeclareDiscreteState(np.full(12, np.nan))
        self._rgb_port = self.DeclareStateOutputPort("rgb_image", self._rgb_index)
        # Depth drawn on demand (static scene): the pose of the last frame, in the same
        # layout, and an output port cached until the next frame. Its calculation reads the
        # query object but depends only on that pose: the scene it sees does not move.
        self._lazy_depth = bool(static_scene and c.render_depth)
        self._depth_memo = None   # (frame pose bytes, range image) of the last lazy depth
        self._frame_pose_index = self.DeclareDiscreteState(np.full(12, np.nan))
        self._frame_pose_port = self.DeclareStateOutputPort("frame_pose",
                                                            self._frame_pose_index)
        if self._lazy_depth:
            self._depth_port = self.DeclareAbstractOutputPort(
                "depth_image", lambda: AbstractValue.Make(ImageDepth32F(W, H)),
                weak_method(self._calc_lazy_depth),
                {self.discrete_state_ticket(self._frame_pose_index)})
        else:
            self._depth_port = self.DeclareStateOutputPort("depth_image", self._depth_index)
        # Render labels of the last frame (static scene), drawn when read, like the lazy
        # depth: each pixel the RenderLabel of what it sees (a lesion's is its own: an
        # instance mask for free; `lesion_labels` names them).
        self._label_memo = None   # (frame pose bytes, label image) of the last one drawn
        self._label_port = None
        if static_scene:
            self._label_port = self.DeclareAbstractOutputPort(
                "label_image", lambda: AbstractValue.Make(ImageLabel16I(W, H)),
                weak_method(self._calc_label),
                {self.discrete_state_ticket(self._frame_pose_index)})
        self._frame_info_port = self.DeclareStateOutputPort("frame_info", self._info_index)
        # A frame in flight (latency > 0): [exposed (0/1), exposure time, pose (12)].
        self._exposure_index = self.DeclareDiscreteState(np.full(14, np.nan))
        self.DeclareInitializationUnrestrictedUpdateEvent(self._initialize)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self._tick, 0.0, self._on_tick)
        if self._latency > 0.0:
            self.DeclarePeriodicUnrestrictedUpdateEvent(self._tick, self._latency,
                                                        self._on_delivery)

    @property
    def lens(self) -> Lens:
        return self._renderer.lens

    @property
    def config(self) -> CameraConfig:
        """The camera's settings (a copy)."""
        return dataclasses.replace(self._config)

    def tick(self) -> float:
        """Period (s) at which the camera checks whether to take a frame."""
        return self._tick

    @property
    def worker(self):
        """The RenderWorker drawing this camera's frames, or None."""
        return self._worker

    def latency(self) -> float:
        """Time (s) from a frame's exposure (at a tick) to its delivery at the outputs."""
        return self._latency

    @property
    def renderer(self) -> LensRenderer:
        return self._renderer

    def get_query_object_input_port(self):
        return self._query_object_port

    def get_rgb_image_output_port(self):
        return self._rgb_port

    def get_depth_image_output_port(self):
        return self._depth_port

    def get_frame_info_output_port(self):
        return self._frame_info_port

    def get_frame_pose_output_port(self):
        return self._frame_pose_port

    # ---- events ---------------------------------------------------------------------------
    def renderer_name(self, query_object) -> str:
        """The renderer this frame draws with (the window the camera is in)."""
        if self._renderer_for is None:
            return self._config.renderer_name
        X_WP = query_object.GetPoseInWorld(self._parent_frame)
        return self._renderer_for(X_WP.multiply(self._X_PC.translation()))

    def _capture(self, context, query_object, state, pose_now=None):
        renderer = self.renderer_name(query_object)
        rgb = state.get_mutable_abstract_state(self._rgb_index).get_mutable_value()
        self._renderer.render_rgba(query_object, self._parent_frame, self._X_PC,
                                   out=rgb.mutable_data, renderer=renderer)
        self._degrade(context, rgb.mutable_data)
        if pose_now is None:
            pose_now = self._camera_pose_vector(query_object)
        state.get_mutable_discrete_state(self._frame_pose_index).set_value(pose_now)
        if not self._lazy_depth and self._config.render_depth:
            depth = state.get_mutable_abstract_state(self._depth_index).get_mutable_value()
            self._renderer.render_range(query_object, self._parent_frame, self._X_PC,
                                        out=depth.mutable_data[..., 0], renderer=renderer)

    def condition_of(self, draw) -> tuple[str, np.random.Generator]:
        """The condition a frame meets and the generator of its strengths, from the two
        uniform numbers `draw` of its condition_draw input."""
        name = self._conditions
        if name == "all":
            name = CAMERA_CONDITIONS[min(int(draw[0] * len(CAMERA_CONDITIONS)),
                                         len(CAMERA_CONDITIONS) - 1)]
        return name, np.random.default_rng(int(draw[1] * 2**32) % 2**32)

    def _degrade(self, context, rgb: np.ndarray) -> None:
        """Applies the frame's image condition to the RGBA buffer `rgb` in place."""
        if self._draw_port is None:
            return
        name, rng = self.condition_of(self._draw_port.Eval(context))
        rgb[..., :3] = photometry.apply(name, rgb[..., :3].copy(), self._field, rng)

    def _view_at(self, pose):
        """(X_WC, renderer name) of a camera pose [R_WC (9), p_WC (3)]."""
        X_WC = RigidTransform(RotationMatrix(pose[:9].reshape(3, 3)), pose[9:])
        renderer = (self._config.renderer_name if self._renderer_for is None
                    else self._renderer_for(pose[9:]))
        return X_WC, renderer

    def _draw_at(self, query_object, pose, rgb: np.ndarray):
        """Draws the colour frame at camera pose [R_WC (9), p_WC (3)] (static scene)."""
        X_WC, renderer = self._view_at(pose)
        self._renderer.render_rgba(query_object, query_object.inspector().world_frame_id(),
                                   X_WC, out=rgb, renderer=renderer)

    def _calc_lazy_depth(self, context, value):
        pose = context.get_discrete_state(self._frame_pose_index).value()
        depth = value.get_mutable_value()
        if not np.all(np.isfinite(pose)):  # no frame yet
            depth.mutable_data[...] = np.inf
            return
        # The depth is a function of the frame's pose alone (static scene), but Drake
        # invalidates this cache at every unrestricted update (the plant's step), so a
        # reader between two frames would render it again (~9 ms): the last frame's range
        # is kept, keyed by its pose.
        key = pose.tobytes()
        if self._depth_memo is not None and self._depth_memo[0] == key:
            depth.mutable_data[..., 0] = self._depth_memo[1]
            return
        query_object = self._query_object_port.Eval(context)
        X_WC, renderer = self._view_at(pose)
        self._renderer.render_range(query_object, query_object.inspector().world_frame_id(),
                                    X_WC, out=depth.mutable_data[..., 0], renderer=renderer)
        self._depth_memo = (key, depth.data[..., 0].copy())

    def _calc_label(self, context, value):
        pose = context.get_discrete_state(self._frame_pose_index).value()
        labels = value.get_mutable_value().mutable_data[..., 0]
        if not np.all(np.isfinite(pose)):  # no frame yet
            labels[...] = int(RenderLabel.kEmpty)
            return
        key = pose.tobytes()
        if self._label_memo is None or self._label_memo[0] != key:
            query_object = self._query_object_port.Eval(context)
            X_WC, renderer = self._view_at(pose)
            self._label_memo = (key, self._renderer.render_label(
                query_object, query_object.inspector().world_frame_id(), X_WC,
                renderer=renderer))
        labels[...] = self._label_memo[1]

    def _camera_pose_vector(self, query_object) -> np.ndarray:
        X_WC = query_object.GetPoseInWorld(self._parent_frame).multiply(self._X_PC)
        return np.concatenate([X_WC.rotation().matrix().ravel(), X_WC.translation()])

    def frame_rate(self, pose_before: np.ndarray, pose_now: np.ndarray, dt: float) -> float:
        """Frame rate (1/s) the camera picks for a pose change over dt (fixed: fps)."""
        c = self._config
        if not self._adaptive:
            return c.fps
        if not np.all(np.isfinite(pose_before)) or dt <= 0.0:
            return c.fps_min
        R_before = pose_before[:9].reshape(3, 3)
        R_now = pose_now[:9].reshape(3, 3)
        cos_angle = np.clip((np.trace(R_before.T @ R_now) - 1.0) / 2.0, -1.0, 1.0)
        angular_speed = math.acos(cos_angle) / dt
        speed = np.linalg.norm(pose_now[9:] - pose_before[9:]) / dt
        motion = speed / c.viewing_distance + angular_speed
        fraction = min(1.0, motion / c.motion_for_fps_max)
        return c.fps_min + fraction * (c.fps_max - c.fps_min)

    def _initialize(self, context, state):
        query_object = self._query_object_port.Eval(context)
        self._capture(context, query_object, state)
        t = context.get_time()
        rate = self._config.fps_min if self._adaptive else self._config.fps
        state.get_mutable_discrete_state(self._info_index).set_value([t, 1.0, 1.0, rate])
        state.get_mutable_discrete_state(self._pose_index).set_value(
            self._camera_pose_vector(query_object))
        return EventStatus.Succeeded()

    def _on_tick(self, context, state):
        query_object = self._query_object_port.Eval(context)
        t = context.get_time()
        t_last, count, _, _ = context.get_discrete_state(self._info_index).value()
        pose_before = context.get_discrete_state(self._pose_index).value()
        pose_now = self._camera_pose_vector(query_object)
        rate = self.frame_rate(pose_before, pose_now, self._tick)
        # Half a tick of slack: ticks land on multiples of the tick period up to rounding.
        take = t - t_last >= 1.0 / rate - 0.5 * self._tick
        delivered = take
        if take and self._latency > 0.0:
            # Exposed now, delivered `latency` later (_on_delivery); meanwhile drawn by the
            # worker, if it can take it.
            state.get_mutable_discrete_state(self._exposure_index).set_value(
                np.concatenate([[1.0, t], pose_now]))
            if self._worker is not None:
                self._worker.submit(pose_now)
            delivered = False
        elif take:
            self._capture(context, query_object, state, pose_now)
            t_last, count = t, count + 1.0
        state.get_mutable_discrete_state(self._info_index).set_value(
            [t_last, count, 1.0 if delivered else 0.0, rate])
        state.get_mutable_discrete_state(self._pose_index).set_value(pose_now)
        return EventStatus.Succeeded()

    def _on_delivery(self, context, state):
        exposure = context.get_discrete_state(self._exposure_index).value()
        if not exposure[0] == 1.0:
            return EventStatus.DidNothing()
        pose = exposure[2:]
        rgb = state.get_mutable_abstract_state(self._rgb_index).get_mutable_value()
        if self._worker is None or not self._worker.collect(pose, rgb.mutable_data):
            self._draw_at(self._query_object_port.Eval(context), pose, rgb.mutable_data)
        self._degrade(context, rgb.mutable_data)
        state.get_mutable_discrete_state(self._frame_pose_index).set_value(pose)
        _, count, _, rate = context.get_discrete_state(self._info_index).value()
        state.get_mutable_discrete_state(self._info_index).set_value(
            [exposure[1], count + 1.0, 1.0, rate])
        state.get_mutable_discrete_state(self._exposure_index).set_value(np.full(14, np.nan))
        return EventStatus.Succeeded()


def capsule_camera_for_frame(plant, frame, config: CameraConfig, renderer_for=None,
                             static_scene: bool = False, worker=None) -> CapsuleCamera:
    """A CapsuleCamera fixed to a plant frame (e.g. the capsule model's `camera` frame):
    resolves the frame's body to its SceneGraph frame and the frame's pose in that body."""
    body = frame.body()
    return CapsuleCamera(config, plant.GetBodyFrameIdOrThrow(body.index()),
                         frame.GetFixedPoseInBodyFrame(), renderer_for, static_scene, worker)

# --- The camera in a colon: its walls, and the camera block --------------------------------

@dataclasses.dataclass
class CameraWalls:
    """The camera windows and their renderers; called with a camera's world position, it
    names the renderer to draw with (the window of the centreline foot's arc length)."""

    windows: CameraWindows
    renderer_names: list[str]
    centerline: object

    def __call__(self, p_WC) -> str:
        s = self.centerline.closest(np.asarray(p_WC, dtype=float))[0]
        return self.renderer_names[self.windows.index_at(s)]


def add_camera_walls(plant, scene_graph, colon_params, colon,
                     config: CameraConfig) -> CameraWalls:
    """The colon wall as capsule cameras see it, and their renderers. Call before Finalize,
    after every other model: the cameras see nothing else (the geometry registered so far
    loses its perception role).

    Each window is accepted by a renderer of its own (`<config.renderer_name>.<k>`, added
    here), so a frame draws only the stretch the camera is in. Returns the `CameraWalls`
    that names the renderer for a camera at p_WC; another camera in the colon sees the wall
    through it.
    """
    assets = colon_assets(colon_params)
    windows = camera_windows(colon, assets.visual_obj.parent, config.far,
                             config.window_spacing)
    if len(windows.objs) == 1:
        names = [config.renderer_name]
    else:
        names = [f"{config.renderer_name}.{k:02d}" for k in range(len(windows.objs))]
    for name in names:
        add_camera_renderer(scene_graph, config, name)
    visuals = [(f"window_{k:02d}", obj, name)
               for k, (obj, name) in enumerate(zip(windows.objs, names))]
    # pydrake cannot set the ("renderer", "accepting") property (a set of names), so the
    # walls come as an SDF model with <drake:accepting_renderer> tags.
    body = "".join(
        f"<visual name='{name}'><geometry><mesh><uri>{Path(obj).resolve().as_uri()}</uri>"
        f"</mesh></geometry><drake:accepting_renderer>{renderer}</drake:accepting_renderer>"
        "</visual>" for name, obj, renderer in visuals)
    fluid = fluid_scene(colon_params)
    accepting = "".join(f"<drake:accepting_renderer>{name}</drake:accepting_renderer>"
                        for name in names)
    for name, path, colour in (("fluid_surface", fluid.surface_obj, FLUID_RGBA),
                               ("fluid_bubbles", fluid.bubbles_obj, BUBBLE_RGBA)):
        if path is None:   # the liquid's surface and bubbles (colon.lumen), in every window
            continue
        rgba = " ".join(f"{c:g}" for c in colour)
        body += (f"<visual name='{name}'><geometry><mesh><uri>{path.resolve().as_uri()}"
                 f"</uri></mesh></geometry><material><diffuse>{rgba}</diffuse></material>"
                 f"{accepting}</visual>")
    sdf = ("<?xml version='1.0'?><sdf version='1.9' xmlns:drake='http://drake.mit.edu'>"
           f"<model name='camera_walls_{config.renderer_name}'><static>true</static>"
           f"<link name='walls'>{body}"
           "</link></model></sdf>")
    instance, = Parser(plant).AddModelsFromString(sdf, "sdf")
    for index in plant.GetBodyIndices(instance):
        for geometry_id in plant.GetVisualGeometriesForBody(plant.get_body(index)):
            scene_graph.RemoveRole(plant.get_source_id(), geometry_id, Role.kIllustration)
    # A capsule camera sees only the inside of the colon. Everything else (the capsule's own
    # shell, the EPM, the arm, the table) would sit in every window's renderer, unseen, and
    # each renderer re-poses its moving geometry at every physics step: with the arm's links
    # in 16 renderers that cost ~1.5 s per simulated second (measured), more than drawing.
    inspector = scene_graph.model_inspector()
    source = plant.get_source_id()
    for geometry_id in inspector.GetAllGeometryIds(Role.kPerception):
        if not inspector.BelongsToSource(geometry_id, source):
            continue
        body = plant.GetBodyFromFrameId(inspector.GetFrameId(geometry_id))
        if not plant.GetModelInstanceName(body.model_instance()).startswith("camera_walls_"):
            scene_graph.RemoveRole(source, geometry_id, Role.kPerception)
    # Then each polyp on the world body (anchored: a renderer never re-poses it) with a
    # render label of its own, so that the label image is each lesion's instance mask.
    # Every renderer draws them (pydrake cannot name accepting renderers); a later camera's
    # walls strip them above and register them again, so there is one set whatever the
    # number of cameras. (Links of their own would give them their bodies' labels, but a
    # body's geometry is re-posed in every renderer at every step: Navigation's real-time
    # factor fell 37 %.)
    # A diverticulum's sac likewise (its neck's collar is part of the wall), in the mucosa's
    # own colour.
    lesions = lesion_scene(colon_params)
    sac_colour = Rgba(*colon_params.mucosa.base_color, 1.0)
    # A polyp's look is its surface's own material and texture (anatomy/lesion_texture.py).
    for lesion, path, colour, kind in (
            [(p, o, None, "polyp") for p, o in zip(lesions.polyps, lesions.surface_objs)]
            + [(d, o, sac_colour, "diverticulum")
               for d, o in zip(lesions.diverticula, lesions.sac_objs)]):
        name = f"{kind}_label_{lesion.index:03d}"
        properties = PerceptionProperties()
        if colour is not None:
            properties.AddProperty("phong", "diffuse", colour)
        properties.AddProperty("label", "id", RenderLabel(LESION_LABEL_BASE + lesion.index))
        geometry = GeometryInstance(RigidTransform(), Mesh(str(path)), name)
        geometry.set_perception_properties(properties)
        plant.RegisterVisualGeometry(plant.world_body(), geometry)
    return CameraWalls(windows, names, colon.centerline)


def lesion_labels(lesions) -> dict[int, int]:
    """{render label: lesion index} of placed polyps (anatomy/lesion_geometry.py) or
    diverticula (anatomy/diverticula.py) in a camera's label image (`add_camera_walls`
    labels them)."""
    return {LESION_LABEL_BASE + p.index: p.index for p in lesions}


def add_camera_wall_models(parts, config: CameraConfig):
    """Before Finalize, after every other model (the camera sees only these walls): the
    capsule camera's walls and renderers (`add_camera_walls`); sets parts.renderer_for."""
    parts.renderer_for = add_camera_walls(parts.plant, parts.scene_graph, parts.colon_params,
                                          parts.colon, config)


block("capsule.camera_walls", CameraConfig, key="capsule.camera",
      models=add_camera_wall_models)(None)


@block("capsule.camera", CameraConfig, check=lambda config, _: check_camera_config(config),
       where="capsule.camera: ")
def add_camera(builder, parts, config: CameraConfig):
    """`capsule.camera` at the capsule's `camera` frame (its own renderers, light at the
    lens) and `capsule.lumen`, the lumen ground truth; exports capsule.camera.<signal> and
    capsule.lumen.<signal>, and shares the camera's lens, config, tick (the period of its
    frames) and latency (`capsule.camera.<that>`). The camera's walls are in the scene
    before (`capsule.camera_walls`, parts.renderer_for), so the camera sees only the
    anchored wall: its depth image is drawn on demand, and frames with latency in a render
    worker on another core."""
    plant = parts.plant
    camera_frame = plant.GetFrameByName("camera", parts.capsule_instance)
    static = parts.renderer_for is not None
    worker = (RenderWorker(parts.colon_params, config)
              if static and config.latency > 0.0 and config.render_process else None)
    camera = builder.AddNamedSystem("capsule.camera", capsule_camera_for_frame(
        plant, camera_frame, config, parts.renderer_for, static_scene=static, worker=worker))
    builder.Connect(parts.scene_graph.get_query_output_port(),
                    camera.get_query_object_input_port())
    if config.conditions != "nominal":   # the draws of the frames' image conditions
        draws = builder.AddNamedSystem("capsule.camera.condition_draws", RandomSource(
            RandomDistribution.kUniform, 2, camera.tick()))
        builder.Connect(draws.get_output_port(), camera.GetInputPort("condition_draw"))
    for name in ("rgb_image", "depth_image", "frame_info", "frame_pose", "label_image"):
        if camera.HasOutputPort(name):
            parts.export(camera.GetOutputPort(name), f"capsule.camera.{name}")
    for name, value in (("lens", camera.lens), ("config", camera.config),
                        ("tick", camera.tick()), ("latency", camera.latency())):
        parts.share(f"capsule.camera.{name}", value)
    add_lumen_truth(builder, parts, camera)
    return camera

