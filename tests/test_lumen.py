"""Lumen detection: synthetic dark blobs of known centre, the threshold against a brute-force
evaluation, the darker-scores-higher fix, the gates, the tracker system with built-in and
users' detectors, and the detector scored on rendered frames against the lumen truth."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.sensors import ImageRgba8U

from capsule_drake.perception.evaluation import evaluate, sample_frames
from capsule_drake.scenario import ScenarioError, load_scenario
from capsule_drake.perception.lumen_tracker import LumenTracker, LumenTrackerConfig
from capsule_drake.perception import Lens, LensConfig
from capsule_drake.perception.lumen import (LumenDetection, LumenParams, dark_biased_threshold,
                                        detect_lumen, load_detector)

SIZE = 256


def _field(shape=(SIZE, SIZE)):
    v, u = np.mgrid[0:shape[0], 0:shape[1]]
    return np.hypot(u - (shape[1] - 1) / 2, v - (shape[0] - 1) / 2) < shape[0] / 2 - 1


def _image(blobs, seed=0, background=200.0, noise=6.0, vessels=True):
    """RGB image as a camera with its own light forms it: red = light x albedo + noise.
    The albedo has thin dark vessels (x 0.7); the light has dark Gaussian blobs, given as
    (u, v, sigma, depth in red levels at their centre)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    albedo = np.ones((SIZE, SIZE))
    if vessels:
        for _ in range(6):
            a, b = rng.uniform(0, SIZE, 2)
            angle = rng.uniform(0, np.pi)
            distance = np.abs((u - a) * np.sin(angle) - (v - b) * np.cos(angle))
            albedo -= 0.3 * np.exp(-0.5 * (distance / 1.2) ** 2)
    light = np.ones((SIZE, SIZE))
    for bu, bv, sigma, depth in blobs:
        light -= depth / background * np.exp(-0.5 * ((u - bu) ** 2 + (v - bv) ** 2) / sigma ** 2)
    red = np.clip(background * light * albedo + rng.normal(0.0, noise, (SIZE, SIZE)), 0, 255)
    return np.stack([red, 0.55 * red, 0.5 * red], axis=-1).astype(np.uint8)


@pytest.mark.parametrize("detector", ["gaussian", "median"])
@pytest.mark.parametrize("seed", range(6))
def test_dark_blob_centre_within_two_pixels(detector, seed):
    rng = np.random.default_rng(100 + seed)
    centre = rng.uniform(70, 186, 2)
    sigma = rng.uniform(10, 25)
    rgb = _image([(centre[0], centre[1], sigma, 180.0)], seed=seed)
    result = load_detector(detector)(rgb, _field())
    assert result.visible
    assert np.linalg.norm(result.pixel - centre) < 2.0, (result.pixel, centre)
    assert result.region[int(centre[1]), int(centre[0])] == 255


def test_blob_in_an_image_without_a_field_mask():
    rgb = _image([(60.3, 170.8, 14.0, 170.0)], seed=3)
    result = detect_lumen(rgb)
    assert result.visible and np.linalg.norm(result.pixel - [60.3, 170.8]) < 2.0


def test_threshold_equals_brute_force_over_levels():
    rng = np.random.default_rng(1)
    values = np.concatenate([rng.normal(40, 10, 3000), rng.normal(170, 25, 9000)])
    values = np.clip(values, 0, 255).astype(np.uint8)
    gradients = rng.uniform(0.0, 10.0, values.shape) + (values < 90) * 5.0
    for bias in (0.0, 1.0, 2.0):
        for g in (None, gradients):
            fast = dark_biased_threshold(values, g, bias)
            # Brute force: class statistics from the pixels, level by level.
            best, best_t = -np.inf, 0
            _mean, variance = values.mean(), values.var()
            overall = None if g is None else g.mean()
            for t in range(256):
                dark = values <= t
                if dark.all() or not dark.any():
                    continue
                w0 = dark.mean()
                eta = w0 * (1 - w0) * (values[dark].mean() - values[~dark].mean()) ** 2 / variance
                criterion = eta * ((255.0 - t) / 255.0) ** bias
                if g is not None:
                    near = np.abs(values.astype(int) - t) <= 3
                    relative = g[near].mean() / overall if near.any() else 1.0
                    criterion /= max(relative, 0.05)
                if criterion > best + 1e-12:
                    best, best_t = criterion, t
            assert fast == best_t, (bias, g is None, fast, best_t)
    # Plain Otsu (no bias, no gradients) separates the two modes.
    assert 60 < dark_biased_threshold(values, None, 0.0) < 150


def test_the_darker_of_two_equal_blobs_wins():
    # Same size and shape; the right one darker. Unnormalised intensity would prefer the
    # brighter one (the public implementation's flaw).
    rgb = _image([(80.0, 128.0, 16.0, 120.0), (176.0, 128.0, 16.0, 175.0)], vessels=False)
    result = detect_lumen(rgb, _field(), LumenParams(max_radius=1.0))
    assert result.visible and abs(result.pixel[0] - 176.0) < 3.0


def test_no_lumen_in_a_uniform_view_or_a_dark_rim():
    uniform = _image([], seed=2, vessels=False)
    assert not detect_lumen(uniform, _field()).visible
    # A view facing the wall: bright centre, darkening toward the edge of the field.
    v, u = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    r = np.hypot(u - 127.5, v - 127.5) / 128.0
    red = np.clip(210.0 * (1.0 - 0.9 * r ** 4), 0, 255)
    rim = np.stack([red, 0.5 * red, 0.5 * red], -1).astype(np.uint8)
    result = detect_lumen(rim, _field())
    assert not result.visible and result.confidence < 0.5


def test_detector_cost_is_small_enough_to_run_every_frame():
    # A coarse guard only; benchmarks/bench_lumen.py measures it.
    import time
    rgb = _image([(120.0, 140.0, 18.0, 170.0)])
    field = _field()
    detect_lumen(rgb, field)
    start = time.perf_counter()
    for _ in range(20):
        detect_lumen(rgb, field)
    assert (time.perf_counter() - start) / 20 < 0.05


# ---- the tracker system --------------------------------------------------------------------

def offset_detector(rgb, field_mask):
    """A user's detector (plugged in by name in the tests): a fixed pixel."""
    return LumenDetection(True, np.array([100.0, 90.0]), 0.8,
                          np.zeros(rgb.shape[:2], dtype=np.uint8))


def blind_detector(rgb, field_mask):
    """A user's detector that never finds the lumen: its errors are undefined."""
    return LumenDetection.nothing(rgb.shape)


def broken_detector(rgb, field_mask):
    raise RuntimeError("user bug")


def _tracker_outputs(tracker, rgb, frame_count=1.0):
    context = tracker.CreateDefaultContext()
    image = ImageRgba8U(SIZE, SIZE)
    image.mutable_data[..., :3] = rgb
    image.mutable_data[..., 3] = 255
    tracker.GetInputPort("rgb_image").FixValue(context, image)
    tracker.GetInputPort("frame_info").FixValue(context, [0.0, frame_count, 1.0, 10.0])
    # The tracker checks 1 us after each camera tick: the first check processes the frame.
    Simulator(tracker, context).AdvanceTo(1e-4)
    return {name: tracker.GetOutputPort(name).Eval(context)
            for name in ("lumen_pixel", "lumen_ray", "lumen_confidence", "lumen_visible",
                         "stats")}, tracker.GetOutputPort("region").Eval(context)


def test_tracker_outputs_the_detection_and_its_ray_through_the_lens():
    lens = Lens(LensConfig())
    tracker = LumenTracker(lens, LumenTrackerConfig(detector="gaussian"), period=0.1)
    rgb = _image([(150.0, 110.0, 15.0, 180.0)])
    outputs, region = _tracker_outputs(tracker, rgb)
    expected = detect_lumen(rgb, lens.pixel_rays()[1])
    np.testing.assert_allclose(outputs["lumen_pixel"], expected.pixel)
    assert outputs["lumen_visible"][0] == 1.0
    ray = outputs["lumen_ray"]
    np.testing.assert_allclose(np.linalg.norm(ray), 1.0)
    # The ray projects back to the pixel (independent route: the lens's forward model).
    pixel, valid = lens.project(ray[None, :])
    assert valid[0] and np.linalg.norm(pixel[0] - expected.pixel) < 1e-6
    assert region.data[110, 150, 0] == 255
    np.testing.assert_array_equal(outputs["stats"], [1.0, 0.0])


def test_tracker_runs_a_users_detector_by_name_and_survives_a_broken_one():
    lens = Lens(LensConfig())
    rgb = _image([(150.0, 110.0, 15.0, 180.0)])
    user = LumenTracker(lens, LumenTrackerConfig(detector="test_lumen:offset_detector"))
    outputs, _ = _tracker_outputs(user, rgb)
    np.testing.assert_allclose(outputs["lumen_pixel"], [100.0, 90.0])
    broken = LumenTracker(lens, LumenTrackerConfig(detector="test_lumen:broken_detector"))
    outputs, _ = _tracker_outputs(broken, rgb)
    assert outputs["lumen_visible"][0] == 0.0
    np.testing.assert_array_equal(outputs["stats"], [1.0, 1.0])


def test_tracker_reports_a_detection_once_consecutive_frames_agree():
    """confirm_frames 3, agree_deg 10: a lumen held still is reported from the third frame;
    one that jumps across the view between frames (a dark patch on a wall coming and going)
    never is; a frame without a detection starts the count again."""
    lens = Lens(LensConfig())
    answers = []

    def scripted(rgb, field_mask):
        return answers.pop(0)

    def found(u, v):
        return LumenDetection(True, np.array([u, v]), 0.9, np.zeros((SIZE, SIZE), np.uint8))

    tracker = LumenTracker(lens, LumenTrackerConfig(confirm_frames=3, agree_deg=10.0),
                           period=0.1, detector=scripted)
    context = tracker.CreateDefaultContext()
    image = ImageRgba8U(SIZE, SIZE)
    tracker.GetInputPort("rgb_image").FixValue(context, image)
    simulator = Simulator(tracker, context)
    reported = []
    script = [found(128, 128), found(130, 127), found(131, 128), found(133, 129),  # held
              LumenDetection.nothing((SIZE, SIZE)), found(131, 128), found(132, 128),
              found(40, 200), found(210, 60), found(45, 190)]  # lost, then jumping
    for frame, answer in enumerate(script, start=1):
        answers.append(answer)
        tracker.GetInputPort("frame_info").FixValue(context, [0.0, frame, 1.0, 10.0])
        simulator.AdvanceTo(0.1 * frame - 0.05)
        reported.append(tracker.GetOutputPort("lumen_visible").Eval(context)[0])
    assert reported == [0, 0, 1, 1, 0, 0, 0, 0, 0, 0]
    with pytest.raises(ValueError, match="confirm_frames"):
        LumenTracker(lens, LumenTrackerConfig(confirm_frames=0))


def test_bad_detector_names_give_one_line_scenario_errors():
    for name, words in (("nonsense", "is not 'core', 'gaussian', 'median'"),
                        ("no_such_module_x:f", "no module .no_such_module_x. on the Python path"),
                        ("test_lumen:missing_function", "has no function")):
        with pytest.raises(ScenarioError, match=words) as info:
            load_scenario(name="WithSensors", override=(
                f"capsule: {{camera: {{}}, lumen_tracker: {{detector: '{name}'}}}}"))
        assert "\n" not in str(info.value)
    with pytest.raises(ScenarioError, match="needs capsule.camera"):
        load_scenario(override="capsule: {camera: null, lumen_tracker: {}}")


# ---- rendered frames -----------------------------------------------------------------------

@pytest.fixture(scope="module")
def rendered_frames():
    return sample_frames(36, colons=2, seed=20, wall_fraction=0.3)


@pytest.mark.slow
@pytest.mark.parametrize("detector", ["gaussian", "median"])
def test_detector_on_rendered_frames_against_the_lumen_truth(rendered_frames, detector):
    summary = evaluate(rendered_frames, load_detector(detector)).summary()
    assert summary["lumen_visible"] >= 20 and summary["lumen_hidden"] >= 5
    assert summary["median_error"] < 0.05
    assert summary["detection_rate"] >= 0.9
    assert summary["false_positive_rate"] < 0.2


@pytest.mark.slow
def test_eval_lumen_cli_scores_a_users_detector_and_saves_the_sheet(tmp_path, capsys):
    from capsule_drake.app.cli import main

    out = tmp_path / "eval"
    code = main(["eval-lumen", "--frames", "6", "--colons", "1", "--seed", "20", "--quiet",
                 "--renderer", "raycast", "--lens", "fisheye",
                 "--conditions", "nominal,noise,light_all",
                 "--detector", "core", "--detector", "test_lumen:offset_detector",
                 "--detector", "test_lumen:blind_detector", "--out", str(out)])
    assert code == 0
    printed = capsys.readouterr().out
    assert "core on raycast, fisheye" in printed and "test_lumen:offset_detector" in printed
    # A detector that never detects has no error to score: "n/a" and why, never "nan".
    assert "nan" not in printed.lower().replace("n/a", "")
    assert "n/a in nominal: errors: the lumen was in view in" in printed
    import json

    def refuse(constant):
        raise AssertionError(f"results.json holds {constant}, which strict JSON refuses")

    results = json.loads((out / "results.json").read_text(), parse_constant=refuse)
    assert results["test_lumen:blind_detector"]["raycast_fisheye"]["nominal"][
        "median_error"] is None
    assert set(results["core"]["raycast_fisheye"]) == {"nominal", "noise", "light_all"}
    assert results["core"]["raycast_fisheye"]["noise"]["frames"] == 6
    assert (out / "core_raycast_fisheye_sheet.png").stat().st_size > 10_000
    assert (out / "test_lumen_offset_detector_raycast_fisheye_sheet.png").exists()
    assert "| light_all |" in (out / "tables.md").read_text()
    assert main(["eval-lumen", "--detector", "nope:nothing", "--frames", "1"]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    assert main(["eval-lumen", "--conditions", "fog", "--frames", "1"]) == 2
    assert "--conditions" in capsys.readouterr().err


@pytest.mark.slow
def test_station_tracks_the_lumen_and_feeds_the_pseudo_force():
    """WithSensors: camera -> lumen tracker -> pseudo-force, in the running station."""
    from capsule_drake.station import make_station

    scenario = load_scenario(name="WithSensors", override="duration: 0.6")
    diagram = make_station(scenario)
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.6)
    context = simulator.get_context()
    port = lambda name: diagram.GetOutputPort(name).Eval(context)  # noqa: E731
    assert port("capsule.lumen_tracker.stats")[0] >= 6  # a frame every 0.1 s, from t = 0
    assert port("capsule.lumen_tracker.lumen_visible")[0] == 1.0
    assert port("capsule.lumen.lumen_visible")[0] == 1.0
    error = np.linalg.norm(port("capsule.lumen_tracker.lumen_pixel")
                           - port("capsule.lumen.lumen_pixel"))
    assert error < 0.05 * np.hypot(256, 256)
    force = port("pseudo_force.F_D")
    assert np.all(np.isfinite(force)) and np.linalg.norm(force) <= 3.3 + 1e-9
    # Looking down the lumen, the lumen term pulls the stylus away from the operator (-z_D).
    assert port("pseudo_force.terms_D")[2] < -0.3
