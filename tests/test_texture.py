"""Procedural mucosa texture, the visual wall's texture coordinates and the textured assets."""

import dataclasses

import cv2
import numpy as np
import pytest
import trimesh

from capsule_drake.anatomy import ColonParams, build_colon, colon_assets
from capsule_drake.anatomy.params import MucosaParams, check_colon_params
from capsule_drake.anatomy.texture import mucosa_texture


@pytest.fixture(scope="module")
def texture():
    return mucosa_texture(MucosaParams(), [0, 2])


@pytest.fixture(scope="module")
def colon():
    return build_colon(ColonParams(seed=0))


@pytest.fixture(scope="module")
def textured(colon):
    return colon.textured_visual_mesh()


def _dark_lines(rgb: np.ndarray, margin: float = 10.0) -> np.ndarray:
    """Texels clearly darker in green than their neighbourhood's median: vessels absorb green
    (haemoglobin) while the patches and grain vary slowly or weakly."""
    green = rgb[..., 1]
    background = cv2.medianBlur(green, 15).astype(float)
    return green.astype(float) < background - margin


@pytest.mark.slow
def test_same_seed_same_texture_other_seed_other_texture(texture):
    again = mucosa_texture(MucosaParams(), [0, 2])
    np.testing.assert_array_equal(again.rgb, texture.rgb)
    other = mucosa_texture(MucosaParams(), [1, 2])
    assert np.mean(np.any(other.rgb != texture.rgb, axis=-1)) > 0.5


def test_size_and_mean_colour(texture):
    p = MucosaParams()
    assert texture.rgb.shape == (p.texels_along, p.texels_around, 3)
    assert texture.rgb.dtype == np.uint8
    r, g, b = texture.rgb.reshape(-1, 3).mean(axis=0)
    # Pink-red: red dominant, green and blue well below it and close to each other.
    assert 180 < r < 240 and 80 < g < 150 and 70 < b < 140
    assert r > g + 60 and abs(g - b) < 30
    # Near the configured base colour (the variation is zero-mean, vessels are a few %).
    np.testing.assert_allclose([r, g, b], 255 * np.array(p.base_color), atol=15)


def test_colour_varies_in_patches(texture):
    # Low-frequency variation: block means of ~20 texels (the patch size) still differ.
    red = texture.rgb[..., 0].astype(float)
    h, w = red.shape
    blocks = red[:h // 32 * 32, :w // 32 * 32].reshape(h // 32, 32, w // 32, 32).mean(axis=(1, 3))
    assert blocks.std() > 4.0


@pytest.mark.parametrize("density", [0.03, 0.07])
def test_vessel_density(density):
    tex = mucosa_texture(MucosaParams(vessel_density=density), [3, 2])
    # The generator's own coverage meets the target closely (it tops up or prunes trees).
    assert tex.vessel_fraction() == pytest.approx(density, rel=0.1)
    # Independent route: thin dark lines found in the image itself.
    found = _dark_lines(tex.rgb)
    assert np.mean(found) == pytest.approx(density, rel=0.3)
    # ... and they are where the vessels were drawn.
    assert np.mean(tex.vessel_alpha[found] > 0.05) > 0.8


def test_no_vessels_when_density_zero():
    tex = mucosa_texture(MucosaParams(vessel_density=0.0), [0, 2])
    assert tex.vessel_fraction() == 0.0
    assert np.mean(_dark_lines(tex.rgb)) < 0.01


def test_texture_tiles_without_seam(texture):
    # Wrapping around (u) and along (v), the edge rows and columns continue each other as
    # smoothly as any two neighbouring rows and columns inside.
    rgb = texture.rgb.astype(float)
    for axis in (0, 1):
        inside = np.mean(np.abs(np.diff(rgb, axis=axis)))
        first, last = np.take(rgb, 0, axis=axis), np.take(rgb, -1, axis=axis)
        assert np.mean(np.abs(first - last)) < 1.2 * inside


def test_uvs_in_range_and_no_face_across_the_seam(colon, textured):
    uv = textured.uv
    assert np.all(uv >= 0.0) and np.all(uv <= 1.0)
    face_uv = uv[textured.faces]
    u_span = np.ptp(face_uv[..., 0], axis=1)
    v_span = np.ptp(face_uv[..., 1], axis=1)
    # Neither around the lumen (u = 0 | 1) nor at a repeat of v does a triangle interpolate
    # across the texture.
    assert np.max(u_span) < 0.5 and np.max(v_span) < 0.5
    p = colon.params
    # Wall triangles span one step of u and at most one ring step of v.
    wall = np.all(textured.faces < len(uv) - 2 * (p.visual_points_around + 1), axis=1)
    assert np.max(u_span[wall]) == pytest.approx(1.0 / p.visual_points_around)
    v_step = p.visual_axial_step * p.mucosa.texels_per_metre / p.mucosa.texels_along
    assert np.max(v_span[wall]) <= v_step * 1.1  # a ring dropped next to a v repeat


def test_textured_mesh_is_the_visual_wall(colon, textured):
    cl = colon.centerline
    # Every vertex lies on the wall (the seam and wrap duplicates too).
    ring_vertices = textured.vertices[:-2 * (colon.params.visual_points_around + 1)]
    assert np.max(np.abs(colon.excursion(ring_vertices))) < 2e-4
    # Normals are unit length and face the lumen; the triangles are wound the same way.
    np.testing.assert_allclose(np.linalg.norm(textured.normals, axis=1), 1.0, atol=1e-6)
    tri = textured.vertices[textured.faces]
    face_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(np.sum(face_normal * textured.normals[textured.faces].sum(axis=1), axis=1)
                  > 0)
    centres = tri.mean(axis=1)
    s, _, _ = cl.closest(centres)
    inward = np.sum(face_normal * (cl.point_at(s) - centres), axis=1)
    assert np.mean(inward > 0) > 0.999
    # Same surface as the watertight visual mesh: equal area.
    area = 0.5 * np.linalg.norm(face_normal, axis=1).sum()
    assert area == pytest.approx(colon.visual_mesh().area, rel=2e-3)


@pytest.mark.slow
def test_assets_textured_and_collision_unchanged(tmp_path):
    params = ColonParams(seed=4)
    assets = colon_assets(params, cache_dir=tmp_path / "a")
    folder = assets.visual_obj.parent
    mtl = (folder / "colon_visual.mtl").read_text()
    assert "map_Kd colon_mucosa.png" in mtl and "Ks " in mtl and "Ns " in mtl
    obj = assets.visual_obj.read_text()
    assert "\nvt " in obj and "\nvn " in obj
    assert obj[obj.index("\nf ") + 1:].split("\n", 1)[0].count("/") == 6

    mesh = trimesh.load(assets.visual_obj, process=False)
    assert isinstance(mesh.visual, trimesh.visual.TextureVisuals)
    assert mesh.visual.uv is not None and len(mesh.visual.uv) == len(mesh.vertices)
    m = params.mucosa
    assert mesh.visual.material.image.size == (m.texels_around, m.texels_along)
    # The texture decides the look only: another mucosa leaves the collision files as
    # they were, byte for byte.
    other = dataclasses.replace(params, mucosa=MucosaParams(vessel_density=0.02))
    other_assets = colon_assets(other, cache_dir=tmp_path / "b")
    for a, b in zip(assets.collision_objs, other_assets.collision_objs, strict=True):
        assert a.read_bytes() == b.read_bytes()
    assert (folder / "colon_mucosa.png").read_bytes() != \
        (other_assets.visual_obj.parent / "colon_mucosa.png").read_bytes()


@pytest.mark.slow
def test_vtk_renders_the_texture(tmp_path):
    """Drake's VTK engine applies the MTL's texture: the wall looks pink-red, not Kd white."""
    from pydrake.geometry import (ClippingRange, ColorRenderCamera, GeometryInstance,
                                  IllustrationProperties, LightParameter,
                                  MakeRenderEngineVtk, Mesh, PerceptionProperties,
                                  RenderCameraCore, RenderEngineVtkParams)
    from pydrake.math import RigidTransform, RotationMatrix
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.sensors import CameraInfo

    params = ColonParams(seed=0)
    assets = colon_assets(params, cache_dir=tmp_path)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, 0.0)
    mucosa = GeometryInstance(RigidTransform(), Mesh(str(assets.visual_obj)), "mucosa")
    mucosa.set_illustration_properties(IllustrationProperties())
    mucosa.set_perception_properties(PerceptionProperties())
    plant.RegisterVisualGeometry(plant.world_body(), mucosa)
    plant.Finalize()
    light = LightParameter(type="point", frame="camera", attenuation_values=[1.0, 0.0, 100.0])
    scene_graph.AddRenderer("vtk", MakeRenderEngineVtk(RenderEngineVtkParams(lights=[light])))
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    query = scene_graph.get_query_output_port().Eval(scene_graph.GetMyContextFromRoot(context))
    cl = build_colon(params).centerline
    s = 0.5 * sum(cl.segment_ranges()["sigmoid"])
    t, n, b = (v[0] for v in cl.frame_at(np.array([s])))
    X_WC = RigidTransform(RotationMatrix(np.column_stack([n, np.cross(t, n), t])),
                          cl.point_at(s))
    camera = ColorRenderCamera(RenderCameraCore(
        "vtk", CameraInfo(128, 128, np.radians(100)), ClippingRange(0.0005, 1.0),
        RigidTransform()), False)
    rgb = np.array(query.RenderColorImage(camera, scene_graph.world_frame_id(), X_WC).data,
                   dtype=float)[..., :3]
    r, g, b = rgb.reshape(-1, 3).mean(axis=0)
    assert r > 1.5 * g and r > 1.5 * b
    # The lit wall near the image border is brighter than the lumen in the middle.
    assert rgb[:16].mean() > 1.5 * rgb[56:72, 56:72].mean()


def test_mucosa_params_checked():
    params = ColonParams()
    params.mucosa.vessel_color = [1.2, 0.0, 0.0]
    with pytest.raises(ValueError, match="colon.mucosa.vessel_color"):
        check_colon_params(params)
    params = ColonParams()
    params.mucosa.texels_around = 4
    with pytest.raises(ValueError, match="colon.mucosa.texels_around"):
        check_colon_params(params)
