"""Where the lumen really is in the capsule camera's image: LumenTruth, the centreline point
a fixed distance ahead through the lens; and `far_region`, the image-side truth read from the
view's range image (the seed's principle, "the darkest region is the lumen when the light is at
the camera", at its ideal: the farthest part of the view)."""

import dataclasses

import cv2
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, LeafSystem, ValueProducer
from pydrake.systems.sensors import ImageDepth32F

from capsule_drake.capsule.model import rotation_from_quaternion
from capsule_drake.lifetime import CacheRef, weak_method
from capsule_drake.perception.lumen import inside_distance


def lumen_target(colon, p_WC, z_WC, lookahead: float):
    """The centerline point `lookahead` metres ahead of the camera along the colon.

    "Ahead" follows the way the camera looks: toward the cecum when its optical axis z_WC
    points down the colon (positive s), toward the anus otherwise. Returns (point_W, s).
    """
    s, _, _ = colon.centerline.closest(np.asarray(p_WC, dtype=float))
    direction = 1.0 if float(np.dot(z_WC, colon.centerline.tangent_at(s))) >= 0.0 else -1.0
    s_target = float(np.clip(s + direction * lookahead, 0.0, colon.centerline.length))
    return colon.centerline.point_at(s_target), s_target


def project_lumen(lens, X_WC: RigidTransform, point_W, depth=None, depth_is_range=True,
                  tolerance: float = 0.003):
    """Pixel of a world point through the lens, and whether the camera sees it.

    Visible means: inside the lens's field of view and image, and, when a depth image is
    given, not hidden behind nearer tissue (the depth at that pixel reaches within
    `tolerance` of the point's own distance).
    Returns (pixel (2,), visible bool).
    """
    p_C = X_WC.inverse().multiply(np.asarray(point_W, dtype=float))
    distance = float(np.linalg.norm(p_C))
    if distance < 1e-9:
        return np.array([np.nan, np.nan]), False
    pixels, valid = lens.project((p_C / distance)[None, :])
    pixel = pixels[0]
    if not bool(valid[0]):
        return pixel, False
    u, v = int(round(pixel[0])), int(round(pixel[1]))
    if depth is not None:
        height, width = depth.shape[:2]
        if not (0 <= u < width and 0 <= v < height):
            return pixel, False
        seen = float(depth[v, u])
        expected = distance if depth_is_range else float(p_C[2])
        if np.isfinite(seen) and seen < expected - tolerance:
            return pixel, False
    return pixel, True


FAR_FRACTION = 0.10
"""The far region is the farthest tenth of the lens's field (`far_region`): the share that
lands nearest the centreline point 5 cm ahead on the default fisheye. Seen first in
benchmarks/lumen_truth_ceiling.py's sweep of 2-20 % on colon seeds 100-104, the seeds
eval-lumen reports (median 1.2 %, p90 4.2 % of the diagonal; 5 %: 1.7 / 4.6 %, 20 %:
2.6 / 6.6 %), and so checked on the tuning seeds 0-4 too: 1.2 / 3.9 % against 1.3 / 4.9 %
for the farthest 5 %. Measured again when the pixels came to count by their solid angle
(chosen on colon seeds 65-69): the tenth still has the lowest median, 1.3 / 5.0 % on the fisheye
and 1.7 / 5.0 % on the pinhole (5 %: 2.0 / 4.9 and 3.1 / 7.7 %; 7 %: 1.6 / 4.0 and
2.4 / 6.2 %)."""
RIM_MARGIN = 0.08
"""The lumen is in view when the far region's centre lies at least this share of the image
diagonal inside the lens's field. Facing the wall, the farthest tenth is the lumen's two
ends grazing the rim of a wide lens, thin crescents whose centres lie 2-7 % of the
diagonal inside it (ray-cast range images of the evaluation's wall-facing poses, colon seeds
0-4: 90th percentile 6.6 % on the fisheye, 9.2 % on the pinhole); looking along the lumen,
its centre lies 15-31 % inside (5th-95th percentile, fisheye; 10-31 % pinhole)."""


RIM_ANGLE_DEG = 19.5
"""Through a lens (`far_region`'s `lens`), the lumen is in view when the far region's
centre lies at least this angle inside the field's edge (`Lens.inside_angles`): RIM_MARGIN
on the default 172-degree fisheye, whose 8 % of the 362 px diagonal is 29 px of 0.67 degree
each, turned into an angle so that it means the same through any lens. Counted in pixels,
the 120-degree pinhole's 8 % was 7 degrees where its pixels are densest, and 65 % of the
wall-facing views of colon seeds 65-69 kept a far region inside it once the pixels counted
by their solid angle (none do inside 19.5 degrees; the fisheye's 1 of 61)."""


@dataclasses.dataclass(frozen=True)
class FarRegion:
    """The image-side lumen truth of one view (`far_region`)."""

    pixel: np.ndarray     # (u, v): the range-weighted centroid of the far region
    visible: bool         # whether that is a lumen in view (RIM_MARGIN)
    mask: np.ndarray      # (H, W) bool: the far region
    rim_distance: float   # its centre's distance inside the field's edge, share of the diagonal
    range: float          # its mean range (m, at most `far`)

    @classmethod
    def none(cls, shape) -> "FarRegion":
        """No far region in an (H, W) view: NaN pixel, not in view, an empty mask."""
        return cls(np.array([np.nan, np.nan]), False, np.zeros(shape, dtype=bool), 0.0, 0.0)


def far_region(range_image, field, far: float, fraction: float = FAR_FRACTION,
               rim: float = RIM_MARGIN, lens=None) -> FarRegion:
    """The farthest part of the view, from its range image: the definition every lumen score
    against the image (`eval-lumen`, `tune_lumen.py`, datasets' `far_u_px`, `far_v_px`,
    `far_visible`) uses.

    - Ranges: a pixel that sees nothing within `far` (+inf) counts as `far`: the open lumen
      beyond the camera's clip; a surface nearer than the near plane (0) as 0; a NaN, like a
      pixel outside the lens's `field`, does not count. Ranges are capped at `far`.
    - Each pixel counts by the solid angle it sees (`lens.solid_angles()`; without a
      `lens`, every pixel alike). The part of the view is then a part of the field of
      view, not of the image: the same scene gives the same region through any lens, where
      a count of pixels would favour a pinhole's stretched edges.
    - The far set: the field's pixels at or beyond the range beyond which `fraction` of the
      field's solid angle lies (every pixel at `far` when more than `fraction` of it sees
      beyond the clip; when that range is the nearest, as where a small window sees past a
      flat wall, the pixels farther than the nearest).
    - The far region: the set's 8-connected component with the largest sum of range times
      solid angle; its pixel is the centroid of that component weighted by range times
      solid angle.
    - In view: the pixel's ray lies at least RIM_ANGLE_DEG inside the field's edge
      (`lens.inside_angles()`; without a `lens`, the pixel lies at least `rim` of the image
      diagonal inside it): a region hugging the rim is the lumen's ends seen sideways past
      the wall, not a lumen ahead. A view whose ranges are all equal (nothing farther) has
      none.

    `lens`: the `Lens` the range image was taken through (its size the image's), or None
    for a bare image whose pixels all see alike.
    """
    r = np.asarray(range_image, dtype=float)
    field = np.asarray(field, dtype=bool)
    if r.shape != field.shape:
        raise ValueError(f"far_region: range image {r.shape} and field {field.shape} differ")
    if lens is None:
        omega = np.ones(r.shape)
    else:
        omega = lens.solid_angles()
        if omega.shape != r.shape:
            raise ValueError(f"far_region: the lens's image {omega.shape} and the range "
                             f"image {r.shape} differ")
    counted = field & ~np.isnan(r) & (omega > 0.0)
    r = np.clip(np.nan_to_num(r, nan=0.0, posinf=far), 0.0, far)
    empty = FarRegion.none(field.shape)
    if not counted.any():
        return empty
    values, weights = r[counted], omega[counted]
    order = np.argsort(values, kind="stable")
    below = np.cumsum(weights[order])
    k = min(int(np.searchsorted(below, (1.0 - fraction) * below[-1], side="left")),
            len(values) - 1)
    cut, nearest = values[order][k], values[order][0]
    far_set = counted & ((r >= cut) if cut > nearest else (r > nearest))
    if not far_set.any():
        return empty
    count, labels = cv2.connectedComponents(far_set.astype(np.uint8), connectivity=8)
    mass = np.bincount(labels.ravel(), weights=(r * omega).ravel(), minlength=count)
    mask = labels == 1 + int(np.argmax(mass[1:]))
    v, u = np.nonzero(mask)
    w = r[v, u] * omega[v, u]
    pixel = np.array([np.sum(u * w), np.sum(v * w)]) / np.sum(w)
    diagonal = float(np.hypot(*field.shape))
    row, column = int(round(pixel[1])), int(round(pixel[0]))
    depth_in = float(inside_distance(field)[row, column]) / diagonal
    visible = (depth_in >= rim if lens is None
               else float(lens.inside_angles()[row, column]) >= RIM_ANGLE_DEG)
    return FarRegion(pixel, visible, mask, depth_in, float(np.mean(r[v, u])))


class LumenTruth(LeafSystem):
    """The lumen centre in the image: the centerline point a fixed distance ahead of the
    camera, projected through the camera's lens model, with a visibility flag.

    .. pydrake_system::

        name: LumenTruth
        input_ports:
        - capsule_state
        - depth (optional)
        output_ports:
        - lumen_pixel
        - lumen_visible
        - lumen_point_W
        - far_pixel
        - far_visible

    capsule_state: [quaternion wxyz, p_WC, w, v] of the capsule body (the station's
    `capsule.state`). depth: the camera's depth image (m), for the occlusion test; when it is
    not connected, visibility is the field of view alone. lumen_pixel: (u, v) in pixels
    (NaN when behind the lens). lumen_visible: 1.0 or 0.0. lumen_point_W: the target (m)
    and its arc length, [x, y, z, s]. far_pixel, far_visible: the image-side truth
    (`far_region`) of the depth image's frame: where the farthest part of the view is and
    whether that is a lumen in view (NaN and 0 without a depth image). Computed once per
    frame (a frame's depth is kept until the next), about 7 ms at 256 px.

    Args:
        colon: the scenario's Colon (centerline ground truth).
        lens: the camera's lens model (`project(rays (N,3)) -> (pixels (N,2), valid (N,))`).
        X_BC: camera pose in the capsule body frame.
        lookahead: distance ahead along the centerline (m).
        depth_is_range: whether the depth image holds range along the ray (else z-depth).
        far: the camera's far clip (m), which the image-side truth counts a pixel that sees
            nothing as.
    """

    def __init__(self, colon, lens, X_BC: RigidTransform, lookahead: float = 0.05,
                 depth_is_range: bool = True, far: float = 0.2):
        super().__init__()
        self._far = float(far)
        # The lens's field (an ideal pinhole without one sees the whole image).
        self._field = lens.pixel_rays()[1] if hasattr(lens, "pixel_rays") else None
        self._far_lens = lens if hasattr(lens, "solid_angles") else None
        self._far_memo = None  # (depth image's hash, (pixel, visible)) of the last frame
        self._colon = colon
        self._lens = lens
        self._X_BC = X_BC
        self._lookahead = float(lookahead)
        self._depth_is_range = depth_is_range
        self._state_port = self.DeclareVectorInputPort("capsule_state", 13)
        self._depth_port = self.DeclareAbstractInputPort(
            "depth", AbstractValue.Make(ImageDepth32F()))
        self._cache = CacheRef(self, self.DeclareCacheEntry(
            description="lumen truth",
            value_producer=ValueProducer(
                allocate=AbstractValue.Make((np.zeros(2), 0.0, np.zeros(4))).Clone,
                calc=weak_method(self._calc_truth)),
            prerequisites_of_calc={self._state_port.ticket(), self._depth_port.ticket()}))
        self.DeclareVectorOutputPort("lumen_pixel", 2, self._calc_pixel,
                                     {self._cache.ticket()})
        self.DeclareVectorOutputPort("lumen_visible", 1, self._calc_visible,
                                     {self._cache.ticket()})
        self.DeclareVectorOutputPort("lumen_point_W", 4, self._calc_point,
                                     {self._cache.ticket()})
        self._far_cache = CacheRef(self, self.DeclareCacheEntry(
            description="image-side lumen truth",
            value_producer=ValueProducer(
                allocate=AbstractValue.Make((np.zeros(2), False)).Clone,
                calc=weak_method(self._calc_far_truth)),
            prerequisites_of_calc={self._depth_port.ticket()}))
        self.DeclareVectorOutputPort("far_pixel", 2, self._calc_far_pixel,
                                     {self._far_cache.ticket()})
        self.DeclareVectorOutputPort("far_visible", 1, self._calc_far_visible,
                                     {self._far_cache.ticket()})

    def camera_pose(self, state) -> RigidTransform:
        """X_WC from the capsule state vector."""
        X_WB = RigidTransform(RotationMatrix(rotation_from_quaternion(state[:4])),
                              np.asarray(state[4:7]))
        return X_WB.multiply(self._X_BC)

    def truth_at(self, X_WC: RigidTransform, depth=None):
        """The lumen truth of a camera at X_WC whose depth image (H x W, m) is `depth` (or
        None: the field of view alone): (pixel (2,), visible bool, point_W (3,), s)."""
        z_WC = X_WC.rotation().col(2)
        point_W, s = lumen_target(self._colon, X_WC.translation(), z_WC, self._lookahead)
        pixel, visible = project_lumen(self._lens, X_WC, point_W, depth,
                                       self._depth_is_range)
        return pixel, visible, np.asarray(point_W, dtype=float), float(s)

    def far_at(self, depth) -> FarRegion:
        """The image-side truth (`far_region`, through this camera's lens: its field, its
        pixels' solid angles and its edge) of a range image (H x W, m); `FarRegion.none`
        when the image is not the lens's size or holds no finite range."""
        field = self._field if self._field is not None else np.ones(depth.shape, bool)
        if depth.shape != field.shape or not np.isfinite(depth).any():
            return FarRegion.none(depth.shape)
        return far_region(depth, field, self._far, lens=self._far_lens)

    def _calc_truth(self, context, abstract_value):
        X_WC = self.camera_pose(self._state_port.Eval(context))
        depth = None
        if self._depth_port.HasValue(context):
            image = self._depth_port.Eval(context)
            if image.width() > 0:
                depth = image.data[:, :, 0]
        pixel, visible, point_W, s = self.truth_at(X_WC, depth)
        abstract_value.set_value((pixel, 1.0 if visible else 0.0, np.append(point_W, s)))

    def _calc_far_truth(self, context, abstract_value):
        """(pixel, visible) of the image-side truth for the depth input's frame."""
        answer = (np.full(2, np.nan), False)
        image = self._depth_port.Eval(context) if self._depth_port.HasValue(context) else None
        if image is not None and image.width() > 0:
            depth = image.data[:, :, 0]
            # Drake invalidates the input at every step; the frame's depth changes only with
            # a new frame, so its truth is kept by the image's content.
            key = hash(depth.tobytes())
            if self._far_memo is None or self._far_memo[0] != key:
                region = self.far_at(depth)
                self._far_memo = (key, (region.pixel, bool(region.visible)))
            answer = self._far_memo[1]
        abstract_value.set_value(answer)

    def _calc_far_pixel(self, context, output: BasicVector):
        output.SetFromVector(self._far_cache.Eval(context)[0])

    def _calc_far_visible(self, context, output: BasicVector):
        output.SetAtIndex(0, 1.0 if self._far_cache.Eval(context)[1] else 0.0)

    def _calc_pixel(self, context, output: BasicVector):
        output.SetFromVector(self._cache.Eval(context)[0])

    def _calc_visible(self, context, output: BasicVector):
        output.SetAtIndex(0, self._cache.Eval(context)[1])

    def _calc_point(self, context, output: BasicVector):
        output.SetFromVector(self._cache.Eval(context)[2])


def add_lumen_truth(builder, parts, camera):
    """`capsule.lumen` on a capsule camera (with its depth, for what tissue hides) and the
    capsule's state; exports capsule.lumen.{lumen_pixel, lumen_visible, lumen_point_W,
    far_pixel, far_visible}."""
    lumen = builder.AddNamedSystem("capsule.lumen", LumenTruth(
        parts.colon, camera.lens, parts.capsule.X_BC, lookahead=parts.lumen_lookahead,
        depth_is_range=True, far=camera.config.far))
    builder.Connect(parts.capsule_state, lumen.GetInputPort("capsule_state"))
    builder.Connect(camera.get_depth_image_output_port(), lumen.GetInputPort("depth"))
    parts.export_outputs(lumen, "capsule.lumen",
                         ("lumen_pixel", "lumen_visible", "lumen_point_W", "far_pixel",
                          "far_visible"))
    parts.share("capsule.lumen.truth_at", lumen.truth_at)
    parts.share("capsule.lumen.far_at", lumen.far_at)
    return lumen


class LumenRayFromTruth(LeafSystem):
    """The lumen truth's pixel as a ray through the lens, for an operator who sees the truth.

    .. pydrake_system::

        name: LumenRayFromTruth
        input_ports:
        - pixel
        - visible
        output_ports:
        - ray
        - visible
    """

    def __init__(self, lens):
        super().__init__()
        self._lens = lens
        self._pixel = self.DeclareVectorInputPort("pixel", 2)
        self._visible = self.DeclareVectorInputPort("visible", 1)
        self.DeclareVectorOutputPort("ray", 3, self._calc_ray)
        self.DeclareVectorOutputPort("visible", 1, self._calc_visible)

    def _ok(self, context):
        pixel = np.asarray(self._pixel.Eval(context), dtype=float)
        return float(self._visible.Eval(context)[0]) > 0.5 and np.all(np.isfinite(pixel)), pixel

    def _calc_ray(self, context, output):
        ok, pixel = self._ok(context)
        output.SetFromVector(self._lens.unproject(pixel[None, :])[0] if ok else np.zeros(3))

    def _calc_visible(self, context, output):
        output.SetAtIndex(0, 1.0 if self._ok(context)[0] else 0.0)


def add_lumen_ray_from_truth(builder, parts, name: str):
    """`name`, a LumenRayFromTruth on the lumen truth (capsule.lumen) through the capsule
    camera's lens: what an operator or navigator who sees the true lumen is given."""
    seen = builder.AddNamedSystem(name, LumenRayFromTruth(parts.shared("capsule.camera.lens")))
    builder.Connect(parts.output("capsule.lumen.lumen_pixel"), seen.GetInputPort("pixel"))
    builder.Connect(parts.output("capsule.lumen.lumen_visible"), seen.GetInputPort("visible"))
    return seen
