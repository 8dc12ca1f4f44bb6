"""Diverticula (anatomy/diverticula.py): pouches cut into every mesh of the wall, checked
against their analytic shape (rays down and across each sac), the wall away from them
unchanged, the meshes still closed, the texture unbroken across each neck, the cut robust on
drawn patients, and the camera's label image showing each sac exactly through its neck (the
neck's rim projected through the lens model, independently of the renderer)."""

import cv2
import numpy as np
import pytest
import trimesh
from pydrake.geometry import Role

from capsule_drake.anatomy import load_colon
from capsule_drake.anatomy.colon import build_colon
from capsule_drake.anatomy.lesions import drawn_lesions
from capsule_drake.anatomy.lumen_state import geometry_params
from capsule_drake.anatomy.params import ColonParams, Lesions, PlacedLesion
from capsule_drake.anatomy.source import lesion_scene
from capsule_drake.capsule.camera import capsule_camera_for_frame
from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.capsule.camera_walls import lesion_labels
from capsule_drake.capsule.model import CAPSULE_BODY, start_pose
from capsule_drake.perception.views import camera_scene

PLACED = [PlacedLesion(kind="diverticulum", size_mm=10.0, segment="sigmoid", along=0.5,
                       around_deg=90.0),
          PlacedLesion(kind="diverticulum", size_mm=6.0, segment="descending", along=0.3,
                       around_deg=10.0),
          PlacedLesion(kind="diverticulum", size_mm=8.0, segment="transverse", along=0.6,
                       around_deg=200.0)]
PARAMS = ColonParams(seed=3, lesions=Lesions(drawn=False, placed=PLACED))


@pytest.fixture(scope="module")
def colons():
    return build_colon(PARAMS), build_colon(ColonParams(seed=3))


def meshes_of(colon):
    """The wall's meshes as trimesh: visual, camera (with the sacs, geometry of their own
    for the camera), collision chunks together."""
    camera = colon.camera_mesh()
    return {"visual": colon.visual_mesh(),
            "camera": trimesh.util.concatenate(
                [trimesh.Trimesh(camera.vertices, camera.faces, process=False)]
                + [pouch.sac for pouch in colon.diverticula]),
            "collision": trimesh.util.concatenate(colon.collision_meshes())}


def first_hit(mesh, origins, directions):
    """Distance along each ray to its first hit on `mesh` (inf where none)."""
    locations, index_ray, _ = mesh.ray.intersects_location(origins, directions,
                                                          multiple_hits=True)
    out = np.full(len(origins), np.inf)
    for point, k in zip(locations, index_ray):
        out[k] = min(out[k], float(np.linalg.norm(point - origins[k])))
    return out


def test_each_sac_has_its_analytic_depth_and_width_in_every_mesh(colons):
    """A ray down each neck's axis reaches the sac's bottom (a cylinder of the neck's radius
    ending in a hemisphere, as deep as the neck is wide), and rays across the sac's
    cylinder meet it at the neck's radius (less the 24-gon's chord, 0.9 %)."""
    colon, _ = colons
    assert len(colon.diverticula) == 3
    for name, mesh in meshes_of(colon).items():
        for pouch in colon.diverticula:
            x, y, axis = pouch.frame_W.T
            lift = float(np.mean((pouch.rim_W - pouch.base_W) @ axis))
            rho = pouch.neck_radius
            assert pouch.depth == pytest.approx(2 * rho)
            origin = pouch.base_W + 0.005 * axis
            down = first_hit(mesh, origin[None], -axis[None])[0]
            assert down == pytest.approx(0.005 - lift + pouch.depth, abs=2e-4), name
            # Across the cylinder, 1 mm above where the hemisphere begins.
            centre = pouch.base_W + (lift - (pouch.depth - rho) + 0.001) * axis
            phi = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
            dirs = np.outer(np.cos(phi), x) + np.outer(np.sin(phi), y)
            across = first_hit(mesh, np.repeat(centre[None], 16, axis=0), dirs)
            assert np.all(across <= rho + 1e-6) and np.all(
                across >= rho * np.cos(np.pi / 24) - 1e-6), (name, across / rho)


def test_the_wall_away_from_the_necks_is_unchanged(colons):
    colon, plain = colons
    cl = colon.centerline
    s = np.linspace(0.05, cl.length - 0.05, 400)
    far = np.min(np.abs(s[:, None] - np.array([p.s for p in colon.diverticula])[None]),
                 axis=1) > 0.04
    s = s[far]
    theta = np.linspace(0.0, 2 * np.pi, len(s))
    _, n, b = cl.frame_at(s)
    dirs = np.cos(theta)[:, None] * n + np.sin(theta)[:, None] * b
    origins = cl.point_at(s)
    for name, mesh in meshes_of(colon).items():
        before = first_hit(meshes_of(plain)[name], origins, dirs)
        after = first_hit(mesh, origins, dirs)
        assert np.allclose(before, after, atol=1e-9), name


def test_the_meshes_stay_closed_and_the_lumen_gains_the_sacs(colons):
    """The visual mesh is closed before and after; the lumen's volume grows by the sacs
    (each closed by a fan at its neck) less what the collars' flat triangles take from the
    concave wall around each neck (at most a few tenths of a millimetre deep over the
    collar: bounded by the collar's area x 0.5 mm)."""
    colon, plain = colons
    before, after = plain.visual_mesh(), colon.visual_mesh()
    assert after.is_watertight and after.is_winding_consistent
    sacs = 0.0
    for pouch in colon.diverticula:
        sac = pouch.sac
        cap = np.stack([np.full(24, len(sac.vertices)), (np.arange(24) + 1) % 24,
                        np.arange(24)], axis=-1)
        closed = trimesh.Trimesh(np.vstack([sac.vertices, pouch.rim_W.mean(axis=0)]),
                                 np.vstack([sac.faces, cap]), process=False)
        assert closed.is_watertight and closed.is_winding_consistent
        sacs += abs(closed.volume)
        rho = pouch.neck_radius
        analytic = np.pi * rho**2 * (pouch.depth - rho) + 2 / 3 * np.pi * rho**3
        assert abs(closed.volume) == pytest.approx(analytic, rel=0.05)
    gained = abs(after.volume) - abs(before.volume)
    collar_area = sum(np.pi * ((p.neck_radius + 0.016) ** 2 - p.neck_radius ** 2)
                      for p in colon.diverticula)
    assert sacs - 0.5e-3 * collar_area <= gained <= sacs + 1e-9, (gained, sacs)


def test_the_texture_runs_on_across_each_neck(colons):
    """No triangle near a neck spans a texture seam: its texture coordinates differ by a
    few columns of the mesh at most (a seam would make them differ by ~1)."""
    colon, _ = colons
    mesh = colon.camera_mesh()
    for pouch in colon.diverticula:
        centroid = mesh.vertices[mesh.faces].mean(axis=1)
        near = np.linalg.norm(centroid - pouch.base_W, axis=1) < 0.03
        uv = mesh.uv[mesh.faces[near]]
        span = uv.max(axis=1) - uv.min(axis=1)
        assert near.sum() > 30 and span.max() < 0.2, span.max()


@pytest.mark.slow   # ~13 s: two patients' colons cut
def test_drawn_diverticula_cut_every_mesh():
    """The patients with the most drawn diverticula among seeds 0-39: every one is cut into
    the camera, visual and collision meshes (the cut's checks raise otherwise) and the
    visual mesh stays closed."""
    counts = {seed: sum(not x.polyp for x in drawn_lesions(
        ColonParams(seed=seed, lesions=Lesions()))) for seed in range(40)}
    seeds = sorted(counts, key=counts.get)[-2:]
    total = 0
    for seed in seeds:
        colon = build_colon(geometry_params(ColonParams(seed=seed, lesions=Lesions())))
        total += len(colon.diverticula)
        assert colon.visual_mesh().is_watertight
        colon.camera_mesh()
        colon.collision_meshes()
    assert total >= 30, counts


def test_only_diverticula_shape_the_colon():
    """Polyps are geometry of their own, so a patient's colon (its cached files) is the
    same with or without them; diverticula are resolved into placements."""
    assert geometry_params(ColonParams(seed=3, lesions=Lesions(diverticula=False))).lesions \
        is None
    both = geometry_params(PARAMS)
    placed = [PlacedLesion(kind="0-Is", size_mm=8.0, segment="sigmoid", along=0.2)]
    with_polyp = geometry_params(ColonParams(
        seed=3, lesions=Lesions(drawn=False, placed=PLACED + placed)))
    assert both == with_polyp
    drawn = geometry_params(ColonParams(seed=11, lesions=Lesions()))
    expected = [x for x in drawn_lesions(ColonParams(seed=11, lesions=Lesions()))
                if not x.polyp]
    assert len(drawn.lesions.placed) == len(expected)


@pytest.mark.slow
def test_the_label_image_shows_each_sac_through_its_neck():
    """The label image's pixels of a diverticulum are its neck's rim projected through the
    lens model and filled (everything seen through the opening is the sac, and the sac is
    seen nowhere else), IoU >= 0.9 where the neck is in view."""
    colon, _ = load_colon(PARAMS)
    pouches = lesion_scene(PARAMS).diverticula
    config = CameraConfig()
    _, context, plant, scene_graph, renderer_for = camera_scene(0.3, config, PARAMS)
    camera = capsule_camera_for_frame(plant, plant.GetFrameByName("camera"), config,
                                      renderer_for, static_scene=True)
    body = plant.GetBodyByName(CAPSULE_BODY)
    frame_id = plant.GetBodyFrameIdOrThrow(body.index())
    X_BC = plant.GetFrameByName("camera").GetFixedPoseInBodyFrame()
    labels = {k: label for label, k in lesion_labels(pouches).items()}
    # Each sac hangs on the world frame (anchored: no renderer re-poses it at a step).
    inspector = scene_graph.model_inspector()
    sacs = [g for g in inspector.GetAllGeometryIds(Role.kPerception)
            if inspector.GetName(g).startswith("diverticulum_label_")]
    assert len(sacs) == len(pouches) == 3
    assert all(inspector.GetFrameId(g) == inspector.world_frame_id() for g in sacs)
    lens = camera.lens
    _, field = lens.pixel_rays()
    checked = 0
    for pouch in pouches:
        for back in (0.02, 0.035):
            X_WB = start_pose(colon, pouch.s - back)
            plant.SetFreeBodyPose(plant.GetMyMutableContextFromRoot(context), body, X_WB)
            query = scene_graph.get_query_output_port().Eval(
                scene_graph.GetMyContextFromRoot(context))
            label = camera.renderer.render_label(query, frame_id, X_BC,
                                                 renderer=camera.renderer_name(query))
            got = label == labels[pouch.index]
            rim_C = X_WB.multiply(X_BC).inverse().multiply(pouch.rim_W.T).T
            pixels, _ = lens.project(rim_C)
            if not np.isfinite(pixels).all():
                continue
            k = 8
            fine = np.zeros((lens.height * k, lens.width * k), np.uint8)
            corners = (pixels + 0.5) * k - 0.5
            cv2.fillPoly(fine, [np.round(corners * 16).astype(np.int32)], 255,
                         lineType=cv2.LINE_8, shift=4)
            share = cv2.resize(fine, (lens.width, lens.height), interpolation=cv2.INTER_AREA)
            expected = (share >= 128) & field
            if expected.sum() < 40:
                continue
            iou = float((got & expected).sum()) / float((got | expected).sum())
            assert iou >= 0.9, (pouch.index, back, iou, int(got.sum()), int(expected.sum()))
            checked += 1
    assert checked >= 3


def test_a_capsule_nose_enters_a_wide_neck():
    """Felt by the capsule (the hydroelastic wall, the default): its nose pushed 3 mm past
    the wall's surface straight down the axis of a 16 mm neck touches nothing (its 5.8 mm
    radius clears the neck), and 20 mm down it meets the sac's bottom (16 mm deep); the
    3 mm pose where there is no pouch is in contact. (The convex pieces wrap the analytic
    wall and bridge every neck.)"""
    from pydrake.geometry import HydroelasticContactRepresentation
    from pydrake.math import RigidTransform, RotationMatrix

    from capsule_drake.capsule.model import capsule_model
    from capsule_drake.scenario import load_scenario
    from capsule_drake.station import make_station

    placed = ("{drawn: false, placed: [{kind: diverticulum, size_mm: 16, segment: rectum, "
              "along: 0.5, around_deg: 120}]}")
    pouch = lesion_scene(load_scenario(
        name="Default", override=f"{{colon: {{lesions: {placed}}}}}").colon).diverticula[0]
    shape = capsule_model()
    z = -pouch.axis_W
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = RotationMatrix(np.column_stack([x, np.cross(z, x), z]))
    nose = shape.half_length                 # the body's origin to its nose tip
    surfaces = {}
    for name, lesions in (("pouch", placed), ("plain", "null")):
        station = make_station(load_scenario(
            name="Default", override=f"{{colon: {{lesions: {lesions}}}}}"))
        context = station.CreateDefaultContext()
        plant = station.GetSubsystemByName("plant")
        scene_graph = station.GetSubsystemByName("scene_graph")
        for depth in (0.003, 0.020):
            tip = pouch.base_W - depth * pouch.axis_W
            plant.SetFreeBodyPose(plant.GetMyMutableContextFromRoot(context),
                                  plant.GetBodyByName(CAPSULE_BODY),
                                  RigidTransform(R, tip - nose * z))
            query = scene_graph.get_query_output_port().Eval(
                scene_graph.GetMyContextFromRoot(context))
            surfaces[name, depth] = len(query.ComputeContactSurfaces(
                HydroelasticContactRepresentation.kPolygon))
    assert surfaces["pouch", 0.003] == 0 and surfaces["plain", 0.003] >= 1, surfaces
    assert surfaces["pouch", 0.020] >= 1, surfaces
