"""Mucosa coverage: the wall patches a frame shows, checked against ray casting through the
wall mesh (a second route to occlusion), and the coverage a camera accumulates."""

import numpy as np
import pytest
import trimesh
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.navigation.coverage import WallPatches, seen_in_frame
from capsule_drake.scenario import Scenario
from capsule_drake.anatomy import load_colon
from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.capsule.camera_renderer import LensRenderer
from capsule_drake.capsule.camera_walls import add_camera_walls


@pytest.fixture(scope="module")
def scene():
    scenario = Scenario()
    colon, _ = load_colon(scenario.colon)
    config = CameraConfig()
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(MultibodyPlantConfig(time_step=0.0), builder)
    walls = add_camera_walls(plant, scene_graph, scenario.colon, colon, config)
    plant.Finalize()
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    query = scene_graph.get_query_output_port().Eval(scene_graph.GetMyContextFromRoot(context))
    renderer = LensRenderer(config)

    def depth_at(X_WC, keep_alive=(diagram, context)):  # the query object refers to them
        return renderer.render_range(query, query.inspector().world_frame_id(), X_WC,
                                     renderer=walls(X_WC.translation()))

    mesh = colon.camera_mesh()
    return colon, config, renderer, depth_at, WallPatches(colon), trimesh.Trimesh(
        mesh.vertices, mesh.faces, process=False)


def _looking_along(colon, s, off_axis=(0.0, 0.0)):
    p = colon.centerline.point_at(s)
    z = colon.centerline.tangent_at(s)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = RotationMatrix(np.column_stack([x, y, z]))
    return RigidTransform(R, p + off_axis[0] * x + off_axis[1] * y)


@pytest.mark.parametrize("s", [0.25, 0.6, 1.1])
def test_shown_patches_are_the_first_surface_along_their_rays(scene, s):
    colon, config, renderer, depth_at, patches, wall = scene
    X_WC = _looking_along(colon, s, off_axis=(0.004, -0.003))
    R, p = X_WC.rotation().matrix(), X_WC.translation()
    shown = seen_in_frame(patches, renderer.lens, R, p, depth_at(X_WC), config.far)
    assert len(shown) > 500
    # Candidates: in range, in the field, facing the camera; shown or hidden.
    offset = patches.centres - p
    distance = np.linalg.norm(offset, axis=1)
    _, in_field = renderer.lens.project(offset @ R)
    facing = np.einsum("ij,ij->i", offset, patches.normals) < 0.0
    candidates = np.flatnonzero((distance < config.far) & in_field & facing)
    hidden = np.setdiff1d(candidates, shown)
    assert set(shown) <= set(candidates)
    rng = np.random.default_rng(0)

    def first_hit(indices):
        directions = offset[indices] / distance[indices, None]
        locations, rays, _ = wall.ray.intersects_location(
            np.repeat(p[None], len(indices), axis=0), directions, multiple_hits=True)
        nearest = np.full(len(indices), np.inf)
        hit = np.linalg.norm(locations - p, axis=1)
        np.minimum.at(nearest, rays, hit)
        return nearest

    sample = rng.choice(shown, size=min(150, len(shown)), replace=False)
    nearest = first_hit(sample)
    # The first surface along the ray is (about) the patch itself: nothing nearer.
    assert np.mean(nearest >= distance[sample] - 0.003 - 0.03 * distance[sample]) > 0.97
    assert len(hidden) > 150  # folds hide part of the wall at every place tested
    sample = rng.choice(hidden, size=150, replace=False)
    nearest = first_hit(sample)
    # Hidden patches have tissue in front of them.
    assert np.mean(nearest < distance[sample] - 0.002) > 0.9


def test_coverage_grows_as_the_camera_moves_along_and_counts_area_once(scene):
    colon, config, renderer, depth_at, patches, _ = scene
    seen = np.zeros(len(patches), dtype=bool)
    total = patches.areas.sum()
    fractions = []
    for s in np.arange(0.2, 0.5, 0.02):
        X_WC = _looking_along(colon, s)
        shown = seen_in_frame(patches, renderer.lens, X_WC.rotation().matrix(),
                              X_WC.translation(), depth_at(X_WC), config.far)
        seen[shown] = True
        fractions.append(patches.areas[seen].sum() / total)
    assert np.all(np.diff(fractions) >= 0.0) and fractions[-1] > fractions[0]
    # A stretch of ~0.5 m seen from its axis is well under the colon's 1.47 m, so the
    # coverage stays below the share of wall within that reach.
    covered_s = colon.centerline.closest(patches.centres[seen])[0]
    assert covered_s.min() > 0.2 - config.far and covered_s.max() < 0.48 + config.far
