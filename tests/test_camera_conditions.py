"""Image conditions in the loop (capsule.camera.conditions): the station's frames meet the
conditions of perception/photometry.py, drawn per frame from the scenario's random_seed."""

import numpy as np
import pytest

from capsule_drake.app.run import simulator_for
from capsule_drake.capsule.camera_config import CAMERA_CONDITIONS, CameraConfig
from capsule_drake.perception import photometry
from capsule_drake.scenario import ScenarioError, load_scenario
from capsule_drake.station import make_station

TIMES = (0.05, 0.15, 0.25)
"""Between frames at 10 fps: the frames of 0.0, 0.1 and 0.2 s, and the draws that the frames
of 0.1, 0.2 and 0.3 s meet (a frame reads the RandomSource's sample of the tick before: at a
tick Drake runs the camera's unrestricted update before the source's discrete one)."""


def _frames(conditions: str, seed: int):
    scenario = load_scenario()
    scenario.capsule.camera = CameraConfig(fps=10.0, conditions=conditions)
    diagram = make_station(scenario)
    camera = diagram.GetSubsystemByName("capsule.camera")
    simulator = simulator_for(diagram, random_seed=seed)
    simulator.Initialize()
    frames, draws = [], []
    for t in TIMES:
        simulator.AdvanceTo(t)
        context = camera.GetMyContextFromRoot(simulator.get_context())
        frames.append(camera.get_rgb_image_output_port().Eval(context).data[..., :3].copy())
        if conditions != "nominal":
            draws.append(camera.GetInputPort("condition_draw").Eval(context).copy())
    return frames, draws, camera


@pytest.fixture(scope="module")
def runs():
    out = {key: _frames(*key) for key in (("nominal", 1), ("noise", 1), ("noise", 2),
                                          ("all", 1))}
    out["all", "again"] = _frames("all", 1)
    return out


@pytest.mark.slow
def test_frames_meet_the_condition_drawn_from_the_scenarios_seed(runs):
    nominal = runs["nominal", 1][0]
    noisy, draws, camera = runs["noise", 1]
    field = camera.lens.pixel_rays()[1]
    for clean, frame, draw in zip(nominal[1:], noisy[1:], draws[:-1]):
        # The camera's frame is the nominal one through the condition it drew...
        name, rng = camera.condition_of(draw)
        assert name == "noise"
        np.testing.assert_array_equal(frame, photometry.apply(name, clean, field, rng))
        assert np.any(frame != clean)
        assert not frame[~field].any()
    # ... another seed draws other strengths; the same seed the same frames.
    assert any(np.any(a != b) for a, b in zip(noisy, runs["noise", 2][0]))
    for a, b in zip(runs["all", 1][0], runs["all", "again"][0]):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow
def test_all_draws_a_condition_per_frame(runs):
    _, draws, camera = runs["all", 1]
    names = [camera.condition_of(d)[0] for d in draws]
    assert all(n in CAMERA_CONDITIONS for n in names)
    assert len({tuple(d) for d in draws}) == len(draws)   # a new draw every frame


def test_an_unknown_condition_is_one_line_at_load():
    with pytest.raises(ScenarioError) as error:
        load_scenario(override="capsule: {camera: {conditions: fog}}")
    message = str(error.value)
    assert "conditions" in message and "fog" in message and "\n" not in message
