"""Which polyps a run showed (navigation/lesions_seen.py): the per-polyp time in view on
hand-made frames, worked out by hand, and a benchmark run that passes one polyp and never
reaches another."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

from capsule_drake.app import benchmark
from capsule_drake.navigation.lesions_seen import SEEN_SECONDS, LesionViews


def _run(views, frames):
    """Feeds `views` the frames [(exposure t, frame count, {label: (pixels, range m)})],
    each from its tick to the next, and returns its context."""
    simulator = Simulator(views)
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


@pytest.mark.slow
def test_a_run_sees_the_polyp_it_passes_and_not_the_one_it_never_reaches():
    # A large sessile polyp on the rectum's wall 5 cm ahead of the capsule's start, which
    # it passes, and a small one in the cecum, which 4 s of following never reaches.
    text = ("{colon: {lesions: {drawn: false, placed: [{kind: 0-Is, size_mm: 12, segment: "
            "rectum, along: 0.7, around_deg: 200}, {kind: 0-Is, size_mm: 7, segment: cecum, "
            "along: 0.5, around_deg: 0}]}}}")
    row = benchmark.run_task(benchmark.Task("autonomy-truth", 4, duration=4.0,
                                            scenario_text=text))["row"]
    assert (row["polyps_large"], row["seen_large"]) == (1, 1)
    assert (row["polyps_small"], row["seen_small"]) == (1, 0)
    assert (row["polyps_diminutive"], row["seen_diminutive"]) == (0, 0)
    assert benchmark.summary([{"row": row}])[0]["seen_large"] == "1/1"
