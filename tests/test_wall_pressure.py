"""Pressure on the wall where it acts (physics/wall_pressure.py; io/metrics.py
site_pressure_metrics; io/wall_map.py; the run's outputs, summary line, replay and MCAP
topic): the mapping against patches computed by hand, the spells above a threshold against
a plain loop over the samples, the locator against the centreline's own `closest`, the
contact's faces against the hydroelastic closed form E depth / R, and a run's map against
the faces it sampled."""

import gc
import json
import weakref

import cv2
import numpy as np
import pytest
from pydrake.geometry import Meshcat, MeshcatParams
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator

from capsule_drake.anatomy import load_colon
from capsule_drake.anatomy.centerline import Centerline, rotation_minimising_frame
from capsule_drake.app.commands.common import pressure_summary
from capsule_drake.app.run import simulate
from capsule_drake.io.metrics import SITE_OUTCOMES, site_pressure_metrics
from capsule_drake.io.replay import replay_page, wall_map_panel
from capsule_drake.io.wall_map import wall_map_png
from capsule_drake.physics import wall_pressure
from capsule_drake.physics.tissue import INJURY_PRESSURE, ISCHAEMIA_PRESSURE, time_above
from capsule_drake.physics.wall_pressure import (MapLayout, PatchGrid, WallLocator,
                                                 WallPressure, WallPressureMap, accumulate,
                                                 capsule_has_pressure_field, contact_faces,
                                                 face_peaks, patch_index, patch_peaks)
from capsule_drake.scenario import load_scenario
from test_tissue import capsule_and_plate as tissue_capsule_and_plate

RADIUS, LENGTH = 0.0058, 0.020   # the capsule's collision shape (m)
THRESHOLDS = np.array([INJURY_PRESSURE, ISCHAEMIA_PRESSURE])


def straight_centerline(length=0.2, y=0.0, z=0.02) -> Centerline:
    """A straight colon along world x through (0, y, z), its frame's normal +z (so theta 0
    is up and theta 90 degrees is the binormal, x cross z = -y); two segments of 10 cm."""
    s = np.arange(0.0, length + 1e-9, 0.001)
    points = np.column_stack([s, np.full_like(s, y), np.full_like(s, z)])
    normals = np.tile([0.0, 0.0, 1.0], (len(s), 1))
    return Centerline(s, points, normals, np.full_like(s, 0.025),
                      (s >= 0.1).astype(int), ["rectum", "sigmoid"])


def helix_centerline() -> Centerline:
    """A helix of radius 4 cm and pitch 6 cm (curvature 1 / 4.2 cm, torsion), with its
    rotation-minimising frame: a centreline bending and twisting as a colon's does."""
    u = np.linspace(0.0, 3.0 * np.pi, 4001)
    points = np.column_stack([0.04 * np.cos(u), 0.04 * np.sin(u), 0.06 * u / (2 * np.pi)])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    keep = np.searchsorted(s, np.arange(0.0, s[-1], 0.001))
    s, points = s[keep], points[keep]
    tangents = np.gradient(points, s, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    normals = rotation_minimising_frame(points, tangents, np.array([0.0, 0.0, 1.0]))
    return Centerline(s, points, normals, np.full_like(s, 0.025), np.zeros(len(s), int),
                      ["sigmoid"])


def wall_point(centerline, s, theta_deg, radius):
    t, n, b = centerline.frame_at(np.asarray(s, dtype=float))
    theta = np.radians(np.asarray(theta_deg, dtype=float))[..., None]
    return centerline.point_at(s) + radius * (np.cos(theta) * n + np.sin(theta) * b)


# --- the mapping, by hand ---------------------------------------------------------------

def test_each_face_carries_its_largest_vertex_pressure():
    # Drake's flat face_data: a triangle (0, 1, 2), a quadrilateral (2, 3, 4, 5), a
    # triangle (5, 6, 0).
    face_data = [3, 0, 1, 2, 4, 2, 3, 4, 5, 3, 5, 6, 0]
    values = [1.0, 7.0, 2.0, 0.0, 9.0, 3.0, 4.0]
    assert face_peaks(face_data, values).tolist() == [7.0, 9.0, 4.0]
    assert face_peaks([], []).size == 0


def test_points_fall_in_the_patches_counted_by_hand():
    grid = PatchGrid(colon_length=0.035, length=0.01, n_around=12)
    assert grid.n_along == 4 and grid.s_edges.tolist() == [0.0, 0.01, 0.02, 0.03, 0.035]
    s = [0.004, 0.015, 0.034, 0.2, -0.1, 0.0299]
    theta = np.radians([5.0, -5.0, 180.0, 31.0, 360.0 + 12.0, 359.9])
    # (along, around): 0.4 cm -> 0, 5 deg -> 0; -5 deg is 355 -> 11; 180 -> 6; beyond the
    # end -> the last patch along, 31 -> 1; before the anus -> the first; 359.9 -> 11.
    expected = [(0, 0), (1, 11), (3, 6), (3, 1), (0, 0), (2, 11)]
    assert patch_index(s, theta, grid).tolist() == [i * 12 + j for i, j in expected]


def test_each_patch_keeps_its_largest_pressure():
    peaks = patch_peaks([3, 5, 3, 0], [10.0, 2.0, 30.0, 4.0], 6)
    assert peaks.tolist() == [4.0, 0.0, 0.0, 30.0, 0.0, 2.0]
    assert patch_peaks([], [], 3).tolist() == [0.0, 0.0, 0.0]


def test_wall_points_of_a_straight_colon_map_to_the_patches_worked_out_by_hand():
    centerline = straight_centerline()
    grid = PatchGrid(centerline.length)          # 1 cm x 30 degrees
    # Points about 2 cm from the axis (y = 0, z = 2 cm); with d their offset from it,
    # theta = atan2(d . b, d . n) = atan2(-d_y, d_z):
    points = np.array([[0.015, -0.005, 0.04],    # atan2(0.005, 0.02) = 14 deg: patch (1, 0)
                       [0.025, -0.02, 0.015],    # atan2(0.02, -0.005) = 104 deg: (2, 3)
                       [0.027, -0.02, 0.017],    # 98.5 deg: the same patch, a higher pressure
                       [0.1234, 0.005, 0.0],     # atan2(-0.005, -0.02) = 194 deg: (12, 6)
                       [0.0999, 0.02, 0.025]])   # atan2(-0.02, 0.005) = 284 deg: (9, 9)
    pressure = [5e3, 1e3, 2e3, 400e3, 3e3]
    s, theta = WallLocator(centerline).locate(points)
    found = patch_peaks(patch_index(s, theta, grid), pressure, grid.size).reshape(grid.shape)
    expected = np.zeros(grid.shape)
    expected[1, 0], expected[2, 3], expected[12, 6], expected[9, 9] = 5e3, 2e3, 400e3, 3e3
    np.testing.assert_array_equal(found, expected)


def test_the_locator_agrees_with_the_centrelines_own_closest_on_a_bending_colon():
    # The locator (nearest sample, one Newton step) against Centerline.closest (Newton on
    # the spline): wall points 1-2.8 cm from the axis of a helix whose bends have a radius
    # of 4.23 cm, inside and outside them (a colon's bends are at least 1.5 lumen radii:
    # docs/models/colon.md, "Acute-angle flexures"; here 1.5 radii of 2.8 cm).
    centerline = helix_centerline()
    rng = np.random.default_rng(3)
    s = rng.uniform(0.01, centerline.length - 0.01, 3000)
    theta = rng.uniform(0.0, 360.0, 3000)
    points = wall_point(centerline, s, theta, rng.uniform(0.01, 0.028, 3000)[:, None])
    s_fast, theta_fast = WallLocator(centerline).locate(points)
    s_ref, _, theta_ref = centerline.closest(points)
    assert np.max(np.abs(s_fast - s_ref)) < 1e-5
    assert np.degrees(np.max(np.abs(np.angle(np.exp(1j * (theta_fast - theta_ref)))))) < 0.05
    # And both give the station and angle the points were made at.
    np.testing.assert_allclose(s_ref, s, atol=1e-6)


# --- spells above a threshold ---------------------------------------------------------------

def run_history(history, times, thresholds=THRESHOLDS):
    """`accumulate` over a (K, P) history of patch pressures."""
    P, T = history.shape[1], len(thresholds)
    peak, start, longest = np.zeros(P), np.full((T, P), np.nan), np.zeros((T, P))
    for t, sample in zip(times, history):
        peak, start, longest = accumulate(peak, start, longest, sample, t, thresholds)
    return peak, start, longest


def test_a_spell_restarts_when_the_pressure_drops_below_the_threshold():
    # Samples every 0.5 s. Patch 0 rises above 4 kPa at 0.5 s, drops at 2.0 (a spell of
    # 1.5 s), rises again at 2.5 and drops at 3.5 (1.0 s): its longest is 1.5 s, not the
    # 2.5 s it spent above in all. Patch 1 goes above at 1.0 s and stays to the last
    # sample (3.5 s): 2.5 s; above 330 kPa from 1.5 to 2.5 s: 1.0 s. Patch 2 is touched
    # below both thresholds. Patch 3 is never touched.
    times = np.arange(8) * 0.5
    kPa = 1000.0
    history = np.array([
        [0, 0, 1, 0], [5, 0, 1, 0], [5, 6, 1, 0], [5, 400, 1, 0],
        [0, 400, 1, 0], [9, 5, 1, 0], [9, 5, 2, 0], [0, 5, 1, 0]], dtype=float) * kPa
    peak, start, longest = run_history(history, times)
    assert peak.tolist() == [9 * kPa, 400 * kPa, 2 * kPa, 0.0]
    injury, ischaemia = longest
    assert ischaemia.tolist() == pytest.approx([1.5, 2.5, 0.0, 0.0])
    assert injury.tolist() == pytest.approx([0.0, 1.0, 0.0, 0.0])
    # Going at the end: patch 1's spell above 4 kPa began at 1.0 s; the others are below.
    assert start[1, 1] == 1.0 and np.isnan(start[1, [0, 2, 3]]).all()
    # One unbroken spell is what tissue.time_above counts (each sample held to the next).
    assert ischaemia[1] == pytest.approx(time_above(times[2:], history[2:, 1],
                                                    ISCHAEMIA_PRESSURE))


def longest_spells_by_loop(history, times, threshold):
    """The longest unbroken time above `threshold` of each patch, sample by sample: a spell
    runs from its first sample above to the first sample below (or the last sample)."""
    out = []
    for column in history.T:
        best, began = 0.0, None
        for t, value in zip(times, column):
            if value > threshold and began is None:
                began = t
            elif value <= threshold and began is not None:
                best, began = max(best, t - began), None
            if began is not None:
                best = max(best, t - began)
        out.append(best)
    return np.array(out)


def test_spells_agree_with_a_plain_loop_over_random_histories():
    rng = np.random.default_rng(7)
    times = np.cumsum(rng.uniform(0.005, 0.02, 400))
    # Patches that switch between untouched, gentle and hard presses, in runs.
    levels = np.array([0.0, 2e3, 50e3, 500e3])
    history = levels[np.repeat(rng.integers(0, 4, (40, 25)), 10, axis=0)]
    history *= rng.uniform(0.8, 1.2, history.shape)
    peak, _, longest = run_history(history, times)
    np.testing.assert_array_equal(peak, history.max(axis=0))
    for k, threshold in enumerate(THRESHOLDS):
        np.testing.assert_allclose(longest[k], longest_spells_by_loop(history, times,
                                                                      threshold))
    # Above 330 kPa is above 4 kPa: a patch's spells above the first lie within the second's.
    assert np.all(longest[0] <= longest[1] + 1e-12)


# --- Drake's contact, as faces; the system ---------------------------------------------------

def capsule_and_plate(point_contact: bool = False):
    """test_tissue's capsule free above a rigid plate (z <= 0), the plate under x = 0.1 m:
    (builder, plant, scene graph, body)."""
    return tissue_capsule_and_plate(point_contact=point_contact, plate_x=0.1)


def test_the_faces_of_a_pressed_capsule_carry_the_closed_form_peak():
    # Pressed a depth delta into the plate, the capsule's field peaks at E delta / R (its
    # pressure field: tests/test_tissue.py), on the plate's surface (z = 0), under the
    # capsule's cylinder (x within its length).
    builder, plant, scene_graph, body = capsule_and_plate()
    assert capsule_has_pressure_field(plant, scene_graph, "capsule")
    diagram = builder.Build()
    context = plant.GetMyMutableContextFromRoot(diagram.CreateDefaultContext())
    for delta in (0.0003, 0.001):
        plant.SetFreeBodyPose(context, body, RigidTransform([0.05, 0.0, RADIUS - delta]))
        centroids, pressures, points = contact_faces(
            plant.get_contact_results_output_port().Eval(context))
        assert points == 0 and len(centroids) == len(pressures) > 4
        assert pressures.max() == pytest.approx(5.0e6 * delta / RADIUS, rel=1e-9)
        assert np.all(pressures > 0.0)
        np.testing.assert_allclose(centroids[:, 2], 0.0, atol=1e-12)
        assert np.all(np.abs(centroids[:, 0] - 0.05) < 0.5 * LENGTH + RADIUS)


def test_point_contact_has_no_pressure_field_and_is_counted():
    builder, plant, scene_graph, body = capsule_and_plate(point_contact=True)
    assert not capsule_has_pressure_field(plant, scene_graph, "capsule")
    diagram = builder.Build()
    context = plant.GetMyMutableContextFromRoot(diagram.CreateDefaultContext())
    plant.SetFreeBodyPose(context, body, RigidTransform([0.05, 0.0, RADIUS - 0.0005]))
    centroids, pressures, points = contact_faces(
        plant.get_contact_results_output_port().Eval(context))
    assert points > 0 and len(centroids) == len(pressures) == 0


def test_the_system_maps_a_capsule_pressed_lifted_and_pressed_again():
    # The capsule lies on a straight colon's floor: pressed 0.5 mm for the samples at
    # 0-0.3 s, lifted at 0.4-0.5 s, pressed 1 mm at 0.6-0.7 s. The centreline runs 2 cm
    # from where the capsule touches, at theta 195 degrees (y = -r sin 15, z = r cos 15), so
    # the contact, +-3.4 mm wide at 1 mm (sqrt(2 R delta)), stays within 180-210 degrees:
    # patch 6 around. Its 20 mm cylinder (centred at x = 5 cm) covers patches 4 and 5
    # along, which feel its full depth: E delta / R, 431 kPa at 0.5 mm and 862 kPa at 1 mm,
    # both above 330 kPa.
    builder, plant, scene_graph, body = capsule_and_plate()
    r, tilt = 0.02, np.radians(15.0)
    centerline = straight_centerline(y=-r * np.sin(tilt), z=r * np.cos(tilt))
    system = builder.AddSystem(WallPressureMap(centerline, period=0.1))
    builder.Connect(plant.get_contact_results_output_port(), system.get_input_port())
    diagram = builder.Build()
    root = diagram.CreateDefaultContext()
    context = plant.GetMyMutableContextFromRoot(root)
    mine = system.GetMyMutableContextFromRoot(root)
    for k, delta in enumerate([0.0005] * 4 + [-0.001] * 2 + [0.001] * 2):
        plant.SetFreeBodyPose(context, body, RigidTransform([0.05, 0.0, RADIUS - delta]))
        root.SetTime(0.1 * k)
        mine.SetDiscreteState(0, system.sampled(mine))
    wall = system.wall_pressure(root)
    assert wall.has_pressure and wall.samples == 8
    assert (wall.first_time, wall.last_time) == (0.0, pytest.approx(0.7))
    for i in (4, 5):
        assert wall.peak[i, 6] == pytest.approx(5.0e6 * 0.001 / RADIUS, rel=1e-9)
    touched = np.argwhere(wall.peak > 0.0)
    assert set(touched[:, 1]) == {6} and set(touched[:, 0]) == {3, 4, 5, 6}
    # Above both thresholds at 0-0.3 s and lifted at 0.4 s (a spell of 0.4 s), again from
    # 0.6 s to the last sample, 0.7 s (0.1 s): the longest is 0.4 s, not their 0.5 s sum.
    for name in ("injury", "ischaemia"):
        assert wall.longest_above[name][4, 6] == pytest.approx(0.4)
        assert wall.longest_above[name][5, 6] == pytest.approx(0.4)


def test_without_a_pressure_field_the_map_samples_nothing_and_says_so():
    centerline = straight_centerline()
    system = WallPressureMap(centerline, pressure_field=False)
    simulator = Simulator(system)
    system.get_input_port().FixValue(simulator.get_mutable_context(),
                                     system.get_input_port().Allocate().get_value())
    simulator.AdvanceTo(0.1)
    wall = system.wall_pressure(simulator.get_context())
    assert wall.samples == 0 and not wall.has_pressure
    metrics = site_pressure_metrics(wall, centerline)
    assert all(metrics[key] is None for key in SITE_OUTCOMES)
    assert metrics["wall_pressure_field"] is False
    assert pressure_summary(metrics) == ("wall pressure per 1 cm x 30 deg patch: none (the "
                                         "contact has no pressure field)")
    assert np.isnan(wall.arrays()["peak_pressure_kPa"]).all()


def test_without_contact_the_map_samples_zeros():
    centerline = straight_centerline()
    system = WallPressureMap(centerline)
    simulator = Simulator(system)
    system.get_input_port().FixValue(simulator.get_mutable_context(),
                                     system.get_input_port().Allocate().get_value())
    simulator.AdvanceTo(0.055)
    wall = system.wall_pressure(simulator.get_context())
    # Samples at 0, 0.01, ..., 0.05; nothing pressed: zeros, not nulls.
    assert wall.samples == 6 and wall.has_pressure and wall.peak.max() == 0.0
    metrics = site_pressure_metrics(wall, centerline)
    assert metrics["site_peak_pressure_kPa"] == 0.0 and metrics["sites_above_ischaemia"] == 0
    assert metrics["site_longest_above_ischaemia_at_s_m"] is None


# --- what a map says ---------------------------------------------------------------------------

def hand_map() -> tuple[WallPressure, Centerline]:
    centerline = straight_centerline()
    grid = PatchGrid(centerline.length)
    peak = np.zeros(grid.shape)
    longest = {"injury": np.zeros(grid.shape), "ischaemia": np.zeros(grid.shape)}
    peak[3, 2], longest["ischaemia"][3, 2] = 20e3, 1.5         # s 3.5 cm, 75 degrees
    peak[14, 7], longest["ischaemia"][14, 7] = 500e3, 4.25     # s 14.5 cm, 225 degrees
    longest["injury"][14, 7] = 0.5
    peak[15, 7] = 3e3                                          # touched, never above
    return WallPressure(grid, peak, longest, {"injury": INJURY_PRESSURE,
                                              "ischaemia": ISCHAEMIA_PRESSURE},
                        samples=900, first_time=0.0, last_time=8.99), centerline


def test_site_metrics_name_the_worst_patches():
    wall, centerline = hand_map()
    m = site_pressure_metrics(wall, centerline)
    assert m["site_peak_pressure_kPa"] == 500.0
    assert m["site_peak_at_s_m"] == pytest.approx(0.145)
    assert m["site_peak_at_theta_deg"] == 225.0 and m["site_peak_segment"] == "sigmoid"
    assert m["site_longest_above_ischaemia_s"] == 4.25
    assert m["site_longest_above_ischaemia_at_s_m"] == pytest.approx(0.145)
    assert m["site_longest_above_ischaemia_segment"] == "sigmoid"
    assert m["site_longest_above_injury_s"] == 0.5
    assert (m["sites_above_injury"], m["sites_above_ischaemia"]) == (1, 2)
    assert (m["wall_patch_length_m"], m["wall_patch_angle_deg"]) == (0.01, 30.0)
    assert site_pressure_metrics(None, centerline) == {key: None for key in SITE_OUTCOMES}
    line = pressure_summary({**m, "peak_contact_pressure_kPa": 612.0})
    assert line == ("wall pressure per 1 cm x 30 deg patch: peak 500 kPa (sigmoid, 14.5 cm); "
                    "longest on one patch above 330 kPa (mucosal injury) 0.50 s, above 4.0 "
                    "kPa (blood flow falls) 4.25 s (sigmoid, 14.5 cm)")
    assert pressure_summary({"advance_m": 0.1}) is None


def test_the_map_comes_back_from_its_arrays():
    wall, _ = hand_map()
    again = WallPressure.from_arrays(wall.arrays())
    assert again.grid == wall.grid and again.thresholds == pytest.approx(wall.thresholds)
    np.testing.assert_array_equal(again.peak, wall.peak)
    for name in wall.longest_above:
        np.testing.assert_array_equal(again.longest_above[name], wall.longest_above[name])
    assert (again.samples, again.last_time, again.has_pressure) == (900, 8.99, True)


def test_the_layout_reads_the_systems_state_vector():
    layout = MapLayout(PatchGrid(0.05), (("injury", INJURY_PRESSURE),), period=0.02)
    x = layout.initial()
    peak, start, longest, counts = layout.split(x)
    assert x.size == layout.size == 5 * 12 * 3 + 4
    assert np.isnan(start).all() and not longest.any() and counts[0] == 0
    peak[7], longest[0, 7], counts[:] = 1e5, 0.3, [4, 0, 0.0, 0.06]
    wall = layout.map_of(x)
    assert wall.peak[0, 7] == 1e5 and wall.longest_above["injury"][0, 7] == 0.3
    assert (wall.samples, wall.period, wall.last_time) == (4, 0.02, 0.06)


def test_the_pictures_boxes_frame_its_maps():
    # One hot patch half way along: its colour shows inside each map's box at the column
    # its arc length gives (the replay draws the capsule's place with those boxes).
    wall, centerline = hand_map()
    wall.peak[:] = 0.0
    for longest in wall.longest_above.values():
        longest[:] = 0.0
    wall.peak[10, 6], wall.longest_above["ischaemia"][10, 6] = 200e3, 3.0   # s 10-11 cm
    png, boxes = wall_map_png(wall, centerline, width=6.0, height=4.0, dpi=100)
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(int)
    h, w = image.shape[:2]
    grey = np.abs(image - 0xd9).max(axis=2) < 4
    for left, top, right, bottom in boxes:
        x0, x1 = int(w * left) + 2, int(w * right) - 2
        y0, y1 = int(h * top) + 2, int(h * bottom) - 2
        inside = image[y0:y1, x0:x1]
        coloured = (~grey[y0:y1, x0:x1]) & (inside.max(axis=2) - inside.min(axis=2) > 40)
        columns = np.flatnonzero(coloured.any(axis=0)) + x0
        assert len(columns)
        s_cm = (columns.mean() / w - left) / (right - left) * centerline.length * 100.0
        assert s_cm == pytest.approx(10.5, abs=0.6)


def test_the_replay_page_carries_the_map_and_the_track():
    wall, centerline = hand_map()
    png, boxes = wall_map_png(wall, centerline, width=3.2, height=2.7, compact=True)
    panel = wall_map_panel(png, boxes, (0.0, 20.0), [0.0, 1.0, 2.0], [3.0, 3.5, np.nan],
                           "wall pressure per patch")
    page = replay_page(Meshcat(MeshcatParams(port=0)).StaticHtml(), [], [], panel)
    assert page.count('id="replay-wall-map"') == 1 and 'id="replay-wall-cursor"' in page
    data = json.loads(page.split('id="replay-data">', 1)[1].split("</script>", 1)[0])
    assert data["wall"]["s"] == [3.0, 3.5, None] and data["wall"]["boxes"] == [
        [round(v, 5) for v in box] for box in boxes]
    assert data["wall"]["src"].startswith("data:image/png;base64,")


# --- a run ---------------------------------------------------------------------------------------

@pytest.mark.slow
def test_a_default_run_puts_the_faces_it_sampled_on_the_wall(tmp_path, monkeypatch):
    # Every face the map sampled, kept as it went: the run's figures are theirs.
    sampled = []
    faces = wall_pressure.contact_faces

    def spy(results):
        found = faces(results)
        sampled.append(found)
        return found

    monkeypatch.setattr(wall_pressure, "contact_faces", spy)
    result = simulate(load_scenario(name="Default", override="duration: 3.0"),
                      out_dir=tmp_path, progress=False)
    m = json.loads((tmp_path / "metrics.json").read_text())
    wall = result.wall_pressure
    assert wall.has_pressure and wall.samples == len(sampled) == 300
    pressures = np.concatenate([p for _, p, _ in sampled])
    assert m["site_peak_pressure_kPa"] == pytest.approx(pressures.max() / 1000.0, rel=1e-12)
    # They are the samples logs.npz has of the contact's peak pressure (ContactMonitor, at
    # every vertex): the same states at the same times, all but the last (at the run's end).
    np.testing.assert_array_equal(
        [p.max() if len(p) else 0.0 for _, p, _ in sampled], result.contact_pressure[:-1])
    assert result.times[-2] == pytest.approx(wall.last_time)
    # The peak's patch is where Centerline.closest (not the map's locator) puts that face.
    centroids = np.concatenate([c for c, _, _ in sampled])
    colon, _ = load_colon(load_scenario(name="Default").colon)
    s, _, theta = colon.centerline.closest(centroids[np.argmax(pressures)])
    assert m["site_peak_at_s_m"] == pytest.approx((np.floor(s / 0.01) + 0.5) * 0.01)
    assert m["site_peak_at_theta_deg"] == pytest.approx(
        (np.floor(np.degrees(theta) % 360.0 / 30.0) + 0.5) * 30.0)
    assert 0.0 <= m["site_longest_above_injury_s"] <= m["site_longest_above_ischaemia_s"] \
        <= m["sim_time_s"]
    assert m["site_longest_above_ischaemia_s"] > 0.5 and m["sites_above_ischaemia"] >= 1
    assert m["wall_pressure_field"] is True and m["wall_pressure_period_s"] == 0.01
    # The map beside the logs, and its picture.
    with np.load(tmp_path / "wall_pressure.npz") as data:
        again = WallPressure.from_arrays({key: data[key] for key in data.files})
    np.testing.assert_array_equal(again.peak, wall.peak)
    assert (tmp_path / "wall_pressure.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_a_runs_diagram_with_its_map_is_freed_when_dropped():
    # The map holds numbers and the centreline's arrays, nothing of another system
    # (capsule_drake/lifetime.py): a run's diagram goes with its result.
    result = simulate(load_scenario(name="Default", override="duration: 0.05"),
                      progress=False)
    assert result.wall_pressure.samples == 5   # at 0, 0.01, ..., 0.04
    refs = [weakref.ref(result.diagram),
            weakref.ref(result.diagram.GetSubsystemByName("wall_pressure"))]
    del result
    gc.collect()
    assert all(ref() is None for ref in refs)
