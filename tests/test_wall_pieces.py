"""The colon wall as convex pieces: convex, covering, not in the way, and usable by Drake."""

import dataclasses

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.geometry import AddContactMaterial, Convex, ProximityProperties, RoleAssign
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import (
    AddMultibodyPlant,
    CoulombFriction,
    ExternallyAppliedSpatialForce,
    MultibodyPlantConfig,
)
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource, VectorLogSink
from scipy.spatial import ConvexHull, cKDTree

from capsule_drake.anatomy import ColonParams, build_colon
from capsule_drake.anatomy.pieces import wall_pieces
from capsule_drake.capsule.model import start_pose
from capsule_drake.io.metrics import capsule_poses, capsule_surface_points_C, wall_excursion
from capsule_drake.models import configure_parser

CHORD = 0.0005       # the default max_chord_depth [m]
THICKNESS = 0.003    # the default thickness [m]


class Hulls:
    """Facet planes of every piece, found by their centroids: point-in-union queries."""

    def __init__(self, pieces):
        self.equations = [ConvexHull(p.T).equations for p in pieces]
        self.centroids = np.array([p.mean(axis=1) for p in pieces])
        self.reach = max(float(np.max(np.linalg.norm(p.T - c, axis=1)))
                         for p, c in zip(pieces, self.centroids))
        self.tree = cKDTree(self.centroids)

    def contains(self, points, tolerance=1e-9) -> np.ndarray:
        """True for each point inside (or on) at least one piece."""
        inside = np.zeros(len(points), dtype=bool)
        for i, candidates in enumerate(self.tree.query_ball_point(points, self.reach)):
            for j in candidates:
                eq = self.equations[j]
                if np.all(eq[:, :3] @ points[i] + eq[:, 3] <= tolerance):
                    inside[i] = True
                    break
        return inside


def wall_samples(colon, n, rng):
    """Random points on the analytic wall and the outward radial direction there."""
    cl = colon.centerline
    s = rng.uniform(0.0, cl.length, n)
    theta = rng.uniform(0.0, 2.0 * np.pi, n)
    _, normal, binormal = cl.frame_at(s)
    u = np.cos(theta)[:, None] * normal + np.sin(theta)[:, None] * binormal
    return cl.point_at(s) + colon.wall_radius(s, theta)[:, None] * u, u


def lumen_side_samples(colon, pieces, rng, per_facet=2):
    """Points on the lumen-facing facets of the wall pieces (not the two end caps)."""
    corners, normals = [], []
    for vertices in pieces[1:-1]:
        hull = ConvexHull(vertices.T)
        corners.append(hull.points[hull.simplices])  # (F, 3, 3)
        normals.append(hull.equations[:, :3])
    corners, normals = np.concatenate(corners), np.concatenate(normals)
    s, _, theta = colon.centerline.closest(corners.mean(axis=1))
    _, n, b = colon.centerline.frame_at(s)
    outward = np.cos(theta)[:, None] * n + np.sin(theta)[:, None] * b
    facing = np.einsum("fk,fk->f", normals, outward) < -0.5
    weights = rng.dirichlet(np.ones(3), size=(int(facing.sum()), per_facet))
    return np.einsum("fpk,fkd->fpd", weights, corners[facing]).reshape(-1, 3)


@pytest.fixture(scope="module")
def colon():
    return build_colon(ColonParams())


@pytest.fixture(scope="module")
def pieces(colon):
    return wall_pieces(colon)


@pytest.fixture(scope="module")
def hulls(pieces):
    return Hulls(pieces)


def test_count_for_the_default_colon(pieces):
    # Drake's build time and memory grow with the square of the geometry count (~5 s and
    # 1.1 GB at 2,000 pieces, 33 s and 3.9 GB at 4,000): the default must stay near 2,700.
    assert 2300 <= len(pieces) <= 3000


def test_pieces_are_convex_and_not_degenerate(pieces):
    for vertices in pieces:
        assert vertices.shape[0] == 3 and vertices.shape[1] >= 8
        assert np.all(np.isfinite(vertices))
        hull = ConvexHull(vertices.T)
        # Every vertex is a hull vertex: the array is already its own convex hull.
        assert len(hull.vertices) == vertices.shape[1]
        # At least the thickness times a few mm squared: no sliver Drake would choke on.
        assert hull.volume > THICKNESS * 0.003**2


def test_every_wall_point_is_covered(colon, hulls):
    rng = np.random.default_rng(1)
    points, u = wall_samples(colon, 3000, rng)
    # Fold crests bulge into the lumen between the 1 mm samples by ~0.15 mm at most: a point
    # 0.25 mm behind the wall must be inside a piece, or the capsule could pass it.
    assert np.all(hulls.contains(points + 2.5e-4 * u))
    # ... and every crest: the wall at the centre of each fold, all the way around.
    crest_s = np.concatenate([f.s for f in colon.wall.haustra])
    theta = rng.uniform(0.0, 2.0 * np.pi, len(crest_s))
    _, n, b = colon.centerline.frame_at(crest_s)
    u = np.cos(theta)[:, None] * n + np.sin(theta)[:, None] * b
    crest = colon.centerline.point_at(crest_s) + colon.wall_radius(crest_s, theta)[:, None] * u
    assert np.all(hulls.contains(crest + 2.5e-4 * u))


def test_end_caps_close_the_tube(colon, hulls):
    cl = colon.centerline
    rng = np.random.default_rng(2)
    for s_end, outward_sign in ((0.0, -1.0), (cl.length, 1.0)):
        t, n, b = (v[0] for v in cl.frame_at(np.array([s_end])))
        theta = rng.uniform(0.0, 2.0 * np.pi, 200)
        fraction = np.sqrt(rng.uniform(0.0, 1.0, 200))
        radius = fraction * colon.wall_radius(np.full(200, s_end), theta)
        disc = cl.point_at(s_end) + radius[:, None] * (np.cos(theta)[:, None] * n
                                                       + np.sin(theta)[:, None] * b)
        assert np.all(hulls.contains(disc + outward_sign * 2.5e-4 * t))
        # The cap stays behind the end plane: it takes nothing from the lumen (1 mm clear of
        # the wall, whose pieces bridge the round lumen by up to max_chord_depth).
        inner = cl.point_at(s_end) + (1.0 - 1e-3 / radius.max()) * (disc - cl.point_at(s_end))
        assert not np.any(hulls.contains(inner - outward_sign * 2.5e-4 * t))


@pytest.mark.slow
def test_pieces_stay_out_of_a_fold_free_lumen():
    # Without folds the only bridged concavities are the round lumen (chords at most
    # max_chord_depth deep around), the lumen's curvature along its length (flexures, radius
    # flaring between segments: at most max_chord_depth more) and the feet of the 1 mm taenia
    # ridges (~0.25 mm). The worst spots add the first two; typical ones do not.
    params = dataclasses.replace(ColonParams(), fold_height_scale=0.0)
    colon = build_colon(params)
    points = lumen_side_samples(colon, wall_pieces(colon), np.random.default_rng(3))
    excursion = colon.excursion(points)
    assert np.min(excursion) >= -(2.0 * CHORD + 2.5e-4)
    assert np.percentile(excursion, 1) >= -(CHORD + 2.5e-4)
    # The lumen side is made of wall samples: it is at the wall, not millimetres behind it
    # (facets at a piece's ends lean a few tenths of a millimetre into the tissue).
    assert np.median(np.abs(excursion)) <= CHORD
    assert np.max(excursion) <= 5e-4


def test_pieces_bridge_fold_feet_only_a_little(colon, pieces):
    # The concave feet of folds (and the flanks where a crescent fold rises from a taenia)
    # are bridged by the hulls; most of the wall is within a millimetre, none beyond 6 mm.
    points = lumen_side_samples(colon, pieces, np.random.default_rng(4), per_facet=1)
    intrusion = -colon.excursion(points)
    assert np.percentile(intrusion, 90) <= 1.0e-3
    assert np.max(intrusion) <= 6.0e-3


@pytest.mark.slow
def test_deterministic(colon, pieces):
    again = wall_pieces(colon)
    assert len(again) == len(pieces)
    assert all(np.array_equal(a, b) for a, b in zip(again, pieces))


def test_capsule_pressed_on_pieces_stays_at_the_wall(colon, pieces):
    # Only the pieces near the start are registered: 0.5 s cannot take the capsule further,
    # and the plant builds in well under a second.
    start_s = 0.75
    centre = colon.centerline.point_at(start_s)
    near = [p for p in pieces if np.linalg.norm(p.mean(axis=1) - centre) < 0.12]
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(
        MultibodyPlantConfig(time_step=1e-3, discrete_contact_approximation="lagged",
                             use_sampled_output_ports=False), builder)
    capsule_instance, = configure_parser(Parser(plant)).AddModels(
        url="package://capsule_drake/capsule.sdf")

    def props():
        p = ProximityProperties()
        AddContactMaterial(dissipation=5.0, point_stiffness=2.0e4,
                           friction=CoulombFriction(0.2, 0.2), properties=p)
        return p

    for i, vertices in enumerate(near):
        plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform(),
                                        Convex(vertices, f"piece_{i}"), f"piece_{i}", props())
    body = plant.GetBodyByName("capsule")
    for geometry_id in plant.GetCollisionGeometriesForBody(body):
        scene_graph.AssignRole(plant.get_source_id(), geometry_id, props(),
                               RoleAssign.kReplace)
    plant.Finalize()
    plant.SetDefaultFloatingBaseBodyPose(body, start_pose(colon, start_s))
    force = ExternallyAppliedSpatialForce()
    force.body_index = body.index()
    force.p_BoBq_B = np.zeros(3)
    force.F_Bq_W = SpatialForce(np.zeros(3), [0.0, 0.0, -1.0])
    source = builder.AddSystem(ConstantValueSource(AbstractValue.Make([force])))
    builder.Connect(source.get_output_port(), plant.get_applied_spatial_force_input_port())
    logger = builder.AddSystem(VectorLogSink(13, publish_period=0.005))
    builder.Connect(plant.get_state_output_port(capsule_instance), logger.get_input_port())
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.5)
    log = logger.FindLog(simulator.get_context())
    R_WC, p_WC = capsule_poses(log.data())
    excursion = wall_excursion(colon, R_WC, p_WC, capsule_surface_points_C(0.0058, 0.0199, 24))
    # 1 N on 1e4 N/m (the two 2e4 N/m geometries in series) presses 0.1 mm into the pieces;
    # the drop from the centreline onto the wall overshoots a little more.
    assert np.max(excursion) < 1.0e-3
    # And it did reach the wall (the pieces are not holding it millimetres off).
    assert excursion[-1] > -1.0e-3
