"""One plug-in cannot change what another sees: a lumen detector is given read-only views of
the frame and the field mask (in eval-lumen and in the lumen tracker), and a navigator's
camera image is a copy of its own. Before, a detector that wrote into its frame changed the
scores of the detectors after it (one went from 1.0 % to 22.8 % median error), and a
navigator that painted its image black blacked out the camera's frame for everyone."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.sensors import ImageRgba8U

from capsule_drake.app.run import Run
from capsule_drake.perception import Lens, LensConfig
from capsule_drake.perception.evaluation import DetectorError, Frame, evaluate
from capsule_drake.perception.lumen import load_detector
from capsule_drake.perception.lumen_tracker import LumenTracker, LumenTrackerConfig
from capsule_drake.scenario import load_scenario

SIZE = 64


def _frame(seed: int) -> Frame:
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8)
    field = np.ones((SIZE, SIZE), dtype=bool)
    field[:4] = False
    return Frame(0, 0.1, "lumen", rgb, field, np.array([30.0, 30.0]), True,
                 np.array([32.0, 32.0]), True)


@pytest.mark.parametrize("detector", ["scribbles", "clears_the_mask"])
def test_a_detector_cannot_change_the_frames_another_scores(detector):
    frames = [_frame(seed) for seed in range(3)]
    before = [(frame.rgb.copy(), frame.field.copy()) for frame in frames]
    with pytest.raises(DetectorError, match=rf"lumen detector {detector} raised ValueError: "
                                            r".*read-only.* on frame 0 of 3"):
        evaluate(frames, load_detector(f"plugins.detectors:{detector}"), detector)
    for frame, (rgb, field) in zip(frames, before):
        assert np.array_equal(frame.rgb, rgb) and np.array_equal(frame.field, field)
    # The built-in detectors do not write into what they are given.
    for name in ("core", "gaussian", "median", "net"):
        evaluate(frames, load_detector(name), name)


def test_the_trackers_detector_is_given_a_read_only_field_mask():
    # The camera's frame reaches the detector read-only already (the image's `data`); the
    # field mask is the tracker's, kept for every frame: a detector that clears it would
    # have cleared it for its later frames. Now its write fails, counted as a failure.
    lens = Lens(LensConfig(width=SIZE, height=SIZE))
    tracker = LumenTracker(lens, LumenTrackerConfig(
        detector="plugins.detectors:clears_the_mask"), period=0.1)
    context = tracker.CreateDefaultContext()
    image = ImageRgba8U(SIZE, SIZE)
    image.mutable_data[...] = 90
    tracker.GetInputPort("rgb_image").FixValue(context, image)
    tracker.GetInputPort("frame_info").FixValue(context, [0.0, 1.0, 1.0, 10.0])
    Simulator(tracker, context).AdvanceTo(1e-4)
    assert tracker.GetOutputPort("stats").Eval(context)[1] == 1.0


@pytest.mark.slow
def test_a_navigator_that_paints_its_image_leaves_the_cameras_frame_alone():
    scenario = load_scenario(None, "Navigation", [
        "{duration: 0.3, capsule: {camera: {fps: 10.0, latency: 0.0}, lumen_tracker: {}}, "
        "epm: {driver: !Plugin {factory: 'plugins.misbehaving:paints_its_image'}}}"])
    with Run(scenario, log=False) as run:
        run.initialize()
        assert run.advance_to(0.3) is None
        station_context = run.station.GetMyContextFromRoot(run.context)
        navigator = run.station.GetSubsystemByName("navigator")
        # The navigator's own copy is black (it painted it) ...
        own = navigator.GetInputPort("rgb_image").Eval(
            navigator.GetMyContextFromRoot(run.context)).data
        assert not own[..., :3].any()
        # ... the camera's frame, which the tracker and the recording see, is not.
        frame = run.station.GetOutputPort("capsule.camera.rgb_image").Eval(station_context)
        assert frame.data[..., :3].any()
