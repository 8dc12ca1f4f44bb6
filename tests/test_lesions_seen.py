"""Which polyps a run showed (navigation/lesions_seen.py): the per-polyp time in view on
hand-made frames, worked out by hand, and a benchmark run that passes one polyp and never
reaches another."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I, ImageRgba8U

from capsule_drake.app import benchmark
from capsule_drake.navigation.lesions_seen import SEEN_SECONDS, LesionViews, detection_points


def _run(views, frames, simulator=None):
    """Feeds `views` the frames [(exposure t, frame count, {label: (pixels, range m)})],
    each from its tick to the next, and returns its context."""
    simulator = simulator or Simulator(views)
    context = simulator.get_mutable_context()
    for t, count, polyps in frames:
        labels, depth = ImageLabel16I(10, 10), ImageDepth32F(10, 10)
        depth.mutable_data[...] = 0.1
        flat_labels, flat_depth = labels.mutable_data.reshape(-1), depth.mutable_data.reshape(-1)
        start = 0
        for label, (pixels, distance) in polyps.items():
            flat_labels[start:start + pixels] = label
            flat_depth[start:start + pixels] = distance
            start += pixels
        views.GetInputPort("label_image").FixValue(context, labels)
        views.GetInputPort("depth_image").FixValue(context, depth)
        views.GetInputPort("frame_info").FixValue(context, [t, count, 1.0, 10.0])
        simulator.AdvanceTo(t + 2e-6)    # the check just after the frame's tick
    return context


FRAMES = [(0.0, 1, {7: (4, 0.02), 9: (25, 0.05)}),   # polyp 0 near; polyp 1 beyond 30 mm
          (0.1, 2, {7: (4, 0.02), 9: (25, 0.02)}),   # both near
          (0.2, 3, {})]                              # neither in view


def test_time_in_view_counts_frames_near_and_large_enough():
    # A 100-pixel field: 0.5 % of it is half a pixel, so any polyp in view is large enough.
    views = LesionViews({7: 0, 9: 1}, 2, field_pixels=100, period=0.1)
    context = _run(views, FRAMES)
    # Each frame counts until the next: polyp 0 qualified in frames 1 and 2 (0.2 s), polyp
    # 1 in frame 2 only (0.1 s); frame 3 shows neither.
    np.testing.assert_allclose(views.final_shown(context), [0.2, 0.1], atol=1e-9)
    got = views.views(context)
    np.testing.assert_array_equal(got["frames"], [2, 2])
    np.testing.assert_array_equal(got["largest_px"], [4, 25])
    np.testing.assert_allclose(got["nearest_m"], [0.02, 0.02], rtol=1e-6)
    # With the area gate at 10 % of the field (10 px), the 4-pixel polyp never counts.
    strict = LesionViews({7: 0, 9: 1}, 2, field_pixels=100, period=0.1, area=0.1)
    np.testing.assert_allclose(strict.final_shown(_run(strict, FRAMES)), [0.0, 0.1],
                               atol=1e-9)
    assert SEEN_SECONDS == pytest.approx(0.2)


def test_a_detector_is_scored_per_polyp_and_per_minute():
    # Frame 1: a point on polyp 0 (label 7, the first 4 pixels of row 0) and one on the wall;
    # frame 2: a box whose centre is on polyp 1 (label 9, pixels 4-28 of the rows); frame 3:
    # the detector fails.
    answers = iter([[(1.0, 0.0), (9.0, 9.0)], [(4.0, 1.0, 4.0, 2.0)], RuntimeError("no")])

    def detector(rgb):
        answer = next(answers)
        if isinstance(answer, Exception):
            raise answer
        return answer

    views = LesionViews({7: 0, 9: 1}, 2, field_pixels=100, period=0.1, detector=detector)
    simulator = Simulator(views)
    views.GetInputPort("rgb_image").FixValue(simulator.get_mutable_context(),
                                             ImageRgba8U(10, 10))
    views_context = _run(views, FRAMES, simulator)
    score = views.detector_score(seen=views.final_shown(views_context) >= 0.1)
    np.testing.assert_array_equal(score["detected_frames"], [1, 1])
    assert (score["frames"], score["failures"], score["false_positives"]) == (3, 1, 1)
    # One false positive over 0.3 s of frames (0 to 0.2 s, and the last frame's period).
    assert score["fp_per_min"] == pytest.approx(1 / (0.3 / 60))
    assert (score["seen"], score["seen_detected"]) == (2, 2)
    assert detection_points([(1, 2), (0, 0, 4, 6)]) == [(1.0, 2.0), (2.0, 3.0)]
    with pytest.raises(ValueError):
        detection_points([(1, 2, 3)])


@pytest.mark.slow
def test_a_run_sees_the_polyp_it_passes_and_not_the_one_it_never_reaches():
    # A large sessile polyp on the rectum's wall 5 cm ahead of the capsule's start, which
    # it passes, and a small one in the cecum, which 4 s of following never reaches; a
    # diverticulum in the rectum before the polyp, and one in the ascending colon.
    # On the rigid stand-in with its drag, whose capsule passes the polyp within the 4 s
    # (on the compliant wall it starts slower: what is scored is the point, not how fast).
    text = ("{contact: !RigidWall {drag_translational: 2.0, drag_rotational: 6.0e-5}, "
            "epm: {driver: !LumenFollower {control: {lift: 1.0}}}, "
            "colon: {lesions: {drawn: false, placed: [{kind: 0-Is, size_mm: 12, segment: "
            "rectum, along: 0.7, around_deg: 200}, {kind: 0-Is, size_mm: 7, segment: cecum, "
            "along: 0.5, around_deg: 0}, {kind: diverticulum, size_mm: 9, segment: rectum, "
            "along: 0.45, around_deg: 160}, {kind: diverticulum, size_mm: 9, segment: "
            "ascending, along: 0.5, around_deg: 160}]}}}")
    row = benchmark.run_task(benchmark.Task(
        "autonomy-truth", 4, duration=4.0, scenario_text=text,
        polyp_detector="tests.plugins.polyp_detectors:brightest_spot"))["row"]
    assert (row["polyps_large"], row["seen_large"]) == (1, 1)
    assert (row["polyps_small"], row["seen_small"]) == (1, 0)
    assert (row["polyps_diminutive"], row["seen_diminutive"]) == (0, 0)
    assert benchmark.summary([{"row": row}])[0]["seen_large"] == "1/1"
    assert (row["diverticula"], row["seen_diverticula"]) == (2, 1)
    assert benchmark.summary([{"row": row}])[0]["seen_diverticula"] == "1/2"
    # The trivial detector is scored (what it scores is not the point): over the one seen.
    assert row["polyps_detected"] in (0, 1) and row["polyp_fp_per_min"] >= 0.0
    assert benchmark.summary([{"row": row}])[0]["polyp_sensitivity"] in ("0/1", "1/1")
