"""Polyps in the camera's label image (anatomy/lesion_geometry.py, LensRenderer.render_label)
against an independent projection of their geometry through the lens model: each polyp's
mask is where the renderer's labels say it is, and a polyp hidden behind a fold (by a ray
march through the analytic wall, not by the renderer) has no pixels."""

import cv2
import numpy as np
import pytest
from pydrake.geometry import Role

from capsule_drake.anatomy import load_colon
from capsule_drake.anatomy.params import ColonParams, Lesions, PlacedLesion
from capsule_drake.anatomy.source import lesion_scene
from capsule_drake.capsule.camera import capsule_camera_for_frame
from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.capsule.camera_walls import lesion_labels
from capsule_drake.capsule.model import CAPSULE_BODY, start_pose
from capsule_drake.perception.lens import LensConfig
from capsule_drake.perception.views import camera_scene

PLACED = [PlacedLesion(kind="0-Is", size_mm=8.0, segment="descending", along=0.45,
                       around_deg=200.0),
          PlacedLesion(kind="0-IIa", size_mm=12.0, segment="descending", along=0.55,
                       around_deg=100.0),
          PlacedLesion(kind="0-Ip", size_mm=12.0, segment="descending", along=0.65,
                       around_deg=250.0)]
LENSES = {"fisheye": LensConfig(),
          "pinhole": LensConfig(model="pinhole_radtan", fov_deg=120.0)}


def above_wall(polyp, colon):
    """(vertices, faces) of the polyp's surface inside the lumen: the faces whose corners
    all lie on or above the analytic wall (TubeColon.excursion <= 0.05 mm); the part sunk
    into the wall drops out."""
    inside = colon.excursion(polyp.mesh.vertices) <= 5e-5
    faces = polyp.mesh.faces[inside[polyp.mesh.faces].all(axis=1)]
    return polyp.mesh.vertices, faces


class Scene:
    def __init__(self, params, lens: LensConfig):
        self.colon, _ = load_colon(params)
        self.polyps = lesion_scene(params).polyps
        config = CameraConfig(lens=lens)
        diagram, self.context, self.plant, self.scene_graph, renderer_for = camera_scene(
            0.3, config, params)
        self.diagram = diagram
        self.camera = capsule_camera_for_frame(self.plant, self.plant.GetFrameByName("camera"),
                                               config, renderer_for, static_scene=True)
        self.body = self.plant.GetBodyByName(CAPSULE_BODY)
        self.frame_id = self.plant.GetBodyFrameIdOrThrow(self.body.index())
        self.X_BC = self.plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()
        self.labels = {k: label for label, k in lesion_labels(self.polyps).items()}

    def look(self, s: float):
        """(label image, X_WC) from the centreline at arc length s, looking down the lumen."""
        X_WB = start_pose(self.colon, s)
        self.plant.SetFreeBodyPose(self.plant.GetMyMutableContextFromRoot(self.context),
                                   self.body, X_WB)
        query = self.scene_graph.get_query_output_port().Eval(
            self.scene_graph.GetMyContextFromRoot(self.context))
        renderer = self.camera.renderer_name(query)
        label = self.camera.renderer.render_label(query, self.frame_id, self.X_BC,
                                                  renderer=renderer)
        return label, X_WB.multiply(self.X_BC)

    def projected_mask(self, polyp, X_WC) -> np.ndarray:
        """The polyp's part above the wall (cut at its base plane) projected triangle by
        triangle through the lens model: its silhouette, ignoring what may hide it."""
        vertices, faces = above_wall(polyp, self.colon)
        points_C = X_WC.inverse().multiply(vertices.T).T
        pixels, _ = self.camera.lens.project(points_C)
        lens = self.camera.lens
        # Filled at 8 x 8 samples per pixel, then a pixel is the polyp's when most of it is:
        # the pixel-centre rule a renderer follows, without the fill's boundary rounding.
        k = 8
        fine = np.zeros((lens.height * k, lens.width * k), np.uint8)
        ahead = points_C[:, 2] > 0.0 if not lens.is_fisheye else np.ones(len(points_C), bool)
        for face in faces:
            if not ahead[face].all() or not np.isfinite(pixels[face]).all():
                continue
            # Pixel (u, v) spans [u - 0.5, u + 0.5]: fine pixel j covers u = (j + 0.5) / k - 0.5.
            corners = (pixels[face] + 0.5) * k - 0.5
            cv2.fillConvexPoly(fine, np.round(corners * 16).astype(np.int32), 255,
                               lineType=cv2.LINE_8, shift=4)
        share = cv2.resize(fine, (lens.width, lens.height), interpolation=cv2.INTER_AREA)
        _, field = lens.pixel_rays()
        return (share >= 128) & field

    def hidden_by_wall(self, polyp, X_WC, samples: int = 200) -> bool:
        """Every vertex of the polyp's part above the wall lies behind tissue as seen from
        the camera: the segment to it passes through the wall (TubeColon.excursion > 0)
        before reaching it (the last millimetre, where the polyp meets the wall, aside)."""
        vertices, faces = above_wall(polyp, self.colon)
        eye = X_WC.translation()
        for vertex in vertices[np.unique(faces)]:
            gap = np.linalg.norm(vertex - eye)
            t = np.linspace(0.0, 1.0 - 0.001 / gap, samples)
            path = eye + t[:, None] * (vertex - eye)
            if not (self.colon.excursion(path) > 0.0).any():
                return False
        return True


@pytest.fixture(scope="module", params=sorted(LENSES))
def scene(request):
    params = ColonParams(seed=0, lesions=Lesions(drawn=False, placed=PLACED))
    return Scene(params, LENSES[request.param])


def iou(a, b) -> float:
    return float((a & b).sum()) / max(float((a | b).sum()), 1.0)


def within_a_pixel(got, expected) -> bool:
    """Whether `got` differs from `expected` only on its boundary: inside it grown by one
    pixel and covering it shrunk by one (a small polyp's mask, ~100 px, loses a tenth of
    its IoU to one pixel's rounding on its rim; a polyp two pixels astray fails)."""
    kernel = np.ones((3, 3), np.uint8)
    grown = cv2.dilate(expected.astype(np.uint8), kernel).astype(bool)
    shrunk = cv2.erode(expected.astype(np.uint8), kernel).astype(bool)
    return not (got & ~grown).any() and not (shrunk & ~got).any()


@pytest.mark.parametrize("back", [0.04, 0.06])
def test_each_polyp_in_view_is_where_its_geometry_projects(scene, back):
    for polyp in scene.polyps:
        label, X_WC = scene.look(polyp.s - back)
        expected = scene.projected_mask(polyp, X_WC)
        if expected.sum() < 30 or scene.hidden_by_wall(polyp, X_WC):
            continue
        got = label == scene.labels[polyp.index]
        assert iou(got, expected) >= 0.9 or within_a_pixel(got, expected), (
            polyp.lesion.kind, back, iou(got, expected), int(got.sum()), int(expected.sum()))
    # The three shapes were each in view from one of the two distances.


def test_the_views_see_each_shape(scene):
    seen = set()
    for polyp in scene.polyps:
        for back in (0.04, 0.06):
            label, _ = scene.look(polyp.s - back)
            if (label == scene.labels[polyp.index]).sum() >= 30:
                seen.add(polyp.lesion.kind)
    assert seen == {"0-Is", "0-IIa", "0-Ip"}


@pytest.mark.slow   # ~13 s: a colon with its polyp built and rendered
def test_a_polyp_behind_a_fold_has_no_pixels():
    """A flat polyp just beyond a haustral fold, looked at along the lumen from further
    back: where the analytic wall hides all of it from the camera, the label image has none
    of it; nearer, where it is not hidden, it has."""
    colon, _ = load_colon(ColonParams(seed=0))
    start, end = colon.centerline.segment_ranges()["transverse"]
    hidden_seen = visible_seen = 0
    for along in np.linspace(0.2, 0.8, 7):
        placed = PlacedLesion(kind="0-IIa", size_mm=5.0, segment="transverse", along=along,
                              around_deg=0.0)
        scene = Scene(ColonParams(seed=0, lesions=Lesions(drawn=False, placed=[placed])),
                      LensConfig())
        polyp = scene.polyps[0]
        for back in (0.03, 0.05, 0.07, 0.09):
            label, X_WC = scene.look(polyp.s - back)
            expected = scene.projected_mask(polyp, X_WC)
            if expected.sum() < 10:
                continue
            pixels = int((label == scene.labels[polyp.index]).sum())
            if scene.hidden_by_wall(polyp, X_WC):
                assert pixels == 0, (along, back, pixels)
                hidden_seen += 1
            elif pixels > 0:
                visible_seen += 1
        if hidden_seen >= 2 and visible_seen >= 2:
            break
    assert hidden_seen >= 2 and visible_seen >= 2, (hidden_seen, visible_seen)


def test_polyps_are_anchored_so_no_renderer_reposes_them(scene):
    """The polyps' perception geometry hangs on the world frame (a body's would be re-posed
    in every camera window's renderer at every step: 37 % of Navigation's real-time factor
    with three polyps)."""
    inspector = scene.scene_graph.model_inspector()
    polyps = [g for g in inspector.GetAllGeometryIds(Role.kPerception)
              if inspector.GetName(g).startswith("polyp_label_")]
    assert len(polyps) == len(scene.polyps) == 3
    assert all(inspector.GetFrameId(g) == inspector.world_frame_id() for g in polyps)
