"""Camera latency and the render worker: a frame exposed at t reaches the outputs at
t + latency, drawn meanwhile in another process; the images are those the camera draws
itself, and a worker that dies or never starts changes nothing but the speed."""

import logging
import os
import signal

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from capsule_drake.capsule.camera_config import CameraConfig, check_camera_config
from capsule_drake.scenario import ScenarioError, load_scenario
from capsule_drake.station import make_station

FPS, LATENCY = 10.0, 0.04


def _station(latency, render_process=True):
    scenario = load_scenario()
    scenario.capsule.camera = CameraConfig(fps=FPS, latency=latency,
                                           render_process=render_process)
    diagram = make_station(scenario)
    camera = diagram.GetSubsystemByName("capsule.camera")
    simulator = Simulator(diagram)
    simulator.Initialize()
    if camera.worker is not None:
        assert camera.worker.wait_until_ready(), camera.worker.state
    return simulator, camera


def _outputs(simulator, camera, t):
    simulator.AdvanceTo(t)
    context = camera.GetMyContextFromRoot(simulator.get_context())
    return (camera.get_rgb_image_output_port().Eval(context).data.copy(),
            camera.get_frame_info_output_port().Eval(context).copy())


@pytest.fixture(scope="module")
def runs():
    """Images and frame info at 0.13 s (exposure at 0.1, not yet delivered with latency) and
    0.145 s (delivered), for the synchronous camera, latency drawn by the worker, and
    latency drawn in-process."""
    out = {}
    for name, latency, process in (("sync", 0.0, False), ("worker", LATENCY, True),
                                   ("in_process", LATENCY, False)):
        simulator, camera = _station(latency, process)
        out[name] = [_outputs(simulator, camera, t) for t in (0.13, 0.145)]
        if camera.worker is not None:
            out["worker_state"] = camera.worker.state
            camera.worker.close()
    return out


@pytest.mark.slow
def test_a_frame_arrives_latency_after_its_exposure(runs):
    (_, info_before), (_, info_after) = runs["worker"]
    # [exposure time of the last frame delivered, frames delivered, delivered now, rate]
    np.testing.assert_allclose(info_before[:2], [0.0, 1.0])  # 0.1's frame still in flight
    np.testing.assert_allclose(info_after[:2], [0.1, 2.0])
    (_, sync_before), (_, sync_after) = runs["sync"]
    np.testing.assert_allclose(sync_before[:2], [0.1, 2.0])
    np.testing.assert_allclose(sync_after[:2], [0.1, 2.0])


def test_the_worker_draws_the_frame_the_camera_would(runs):
    assert runs["worker_state"] == "ready"
    worker = runs["worker"][1][0]
    np.testing.assert_array_equal(worker, runs["in_process"][1][0])
    # The synchronous camera drew the same exposure through the capsule's frame: the same
    # pose to round-off, so the same image up to a rare rounding of a pixel.
    sync = runs["sync"][1][0]
    differs = np.any(worker != sync, axis=-1)
    assert differs.mean() < 0.001
    assert np.abs(worker.astype(int) - sync).max() <= 2
    # And it is a new frame, not the one before.
    assert np.any(runs["worker"][0][0] != worker)


@pytest.mark.slow
def test_a_dead_worker_changes_nothing_but_the_speed(caplog):
    simulator, camera = _station(LATENCY)
    _outputs(simulator, camera, 0.05)
    os.kill(camera.worker._process.pid, signal.SIGKILL)
    with caplog.at_level(logging.WARNING):
        rgb, info = _outputs(simulator, camera, 0.145)
    assert camera.worker.state == "failed"
    assert "render worker failed" in caplog.text
    np.testing.assert_allclose(info[:2], [0.1, 2.0])
    reference, _ = _outputs(*_station(LATENCY, render_process=False), 0.145)
    np.testing.assert_array_equal(rgb, reference)


def test_latency_must_fit_in_a_tick_and_needs_a_still_scene():
    with pytest.raises(ValueError, match="latency 0.1 s must be below the camera's tick"):
        check_camera_config(CameraConfig(fps=10.0, latency=0.1))
    with pytest.raises(ValueError, match="latency must be finite and >= 0 s, got -0.01"):
        check_camera_config(CameraConfig(latency=-0.01))
    from test_camera import _moving_capsule_diagram
    with pytest.raises(ValueError, match="latency needs a scene the camera sees unmoving"):
        _moving_capsule_diagram(CameraConfig(fps=10.0, latency=0.05), 0.0)
    # The scenario's check names the key and the value, on one line.
    with pytest.raises(ScenarioError,
                       match="^scenario: capsule.camera: camera latency 0.5 s") as error:
        load_scenario(override="capsule: {camera: {fps: 10.0, latency: 0.5}}")
    assert "\n" not in str(error.value)
