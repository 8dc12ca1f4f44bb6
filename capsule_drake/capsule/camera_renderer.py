"""LensRenderer: a lens's image drawn by VTK, offline or inside the camera system.

No pinhole renders 150-172 degrees, so a fisheye image is assembled from several pinhole
views from the camera's centre (the faces of a cube map, each cropped to the part the field
of view reaches) and resampled through the lens model with `cv2.remap`; the maps are
computed once, at construction, from `Lens.unproject`. A pinhole lens renders one view and
applies its radial-tangential distortion the same way.

Cost model (measured, Drake 1.58 RenderEngineVtk on Mesa llvmpipe, 2 cores): a render call
costs the vertex work of every triangle its renderer holds, in view or not (RenderEngineVtk
culls nothing: ~0.3 ms colour per 10k triangles), plus ~1 ms per 10k pixels. So in a colon
the camera draws with the renderer of the window it is in (`renderer_for`, see
anatomy/windows.py and capsule/camera_walls.py): ~15k triangles instead of the whole wall.
"""

import dataclasses
import math

import cv2
import numpy as np
from pydrake.geometry import (
    ClippingRange,
    ColorRenderCamera,
    DepthRange,
    DepthRenderCamera,
    FrameId,
    LightParameter,
    MakeRenderEngineVtk,
    QueryObject,
    RenderCameraCore,
    RenderEngineVtkParams,
    RenderLabel,
    Rgba,
)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.sensors import CameraInfo

from capsule_drake.capsule.camera_config import FACE_MARGIN_PX, FACES, CameraConfig
from capsule_drake.perception import Lens

LABEL_FACE_SCALE = 4.0
"""How much denser the faces of a fisheye's label images are than its colour's
(LensRenderer's label_scale)."""
# the nearest sample instead (no "flying" depths between foreground and background).
_DEPTH_EDGE_FRACTION = 0.05
# Added to the principal point handed to RenderEngineVtk (see LensRenderer._add_view).
_VTK_PIXEL_OFFSET = 0.5



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
        axes = np.array([axis for axis, _ in FACES.values()])
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
        for index, (name, (axis, down)) in enumerate(FACES.items()):
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
            margin = FACE_MARGIN_PX / density
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
