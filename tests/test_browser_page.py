"""The teleoperation console in a real browser: headless Chromium opens the live Meshcat page
of a station with the browser operator, and screenshots show the scene and the capsule's
camera view drawn on its panel.

Each check compares two screenshots of the same page, one with the thing checked hidden
(`visible: false` in Meshcat), so that it does not depend on where the default view puts
things nor on the background's colours.
"""


import cv2
import numpy as np
import pytest
from pydrake.geometry import Meshcat, MeshcatParams
from pydrake.systems.analysis import Simulator

from browser import chromium
from capsule_drake.io.headless import HeadlessPage
from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station

CAMERA_VIEW = "/teleop/camera_view"



def _changed(a: np.ndarray, b: np.ndarray, threshold: int = 30) -> np.ndarray:
    """Pixels whose colour differs by more than `threshold` in some channel."""
    return np.abs(a.astype(int) - b.astype(int)).max(axis=2) > threshold


def _tissue(image: np.ndarray) -> np.ndarray:
    """Pixels of the colon's pink-red (BGR): red well above green and blue."""
    b, g, r = (image[..., i].astype(int) for i in range(3))
    return (r > 120) & (r - g > 35) & (r - b > 45)


def _unwarp(image: np.ndarray, region: np.ndarray, size: int) -> np.ndarray:
    """The quadrilateral `region` of `image` (a panel seen in perspective, tilted by less
    than 45 degrees) mapped back to a `size` x `size` square, grey."""
    ys, xs = np.nonzero(region)
    corners = np.float32([(xs[i], ys[i]) for i in (
        np.argmin(xs + ys), np.argmax(xs - ys), np.argmax(xs + ys), np.argmin(xs - ys))])
    square = np.float32([[0, 0], [size, 0], [size, size], [0, size]])
    warp = cv2.getPerspectiveTransform(corners, square)
    return cv2.cvtColor(cv2.warpPerspective(image, warp, (size, size)), cv2.COLOR_BGR2GRAY)


@pytest.mark.slow
def test_the_meshcat_page_draws_the_scene_and_the_camera_view(tmp_path):
    exe = chromium()
    meshcat = Meshcat(MeshcatParams(port=0))
    scenario = load_scenario(name="Teleop", override=(
        "{epm: {mount: !Stage {}, driver: !Teleop {operator: browser}}}"))
    diagram = make_station(scenario, meshcat)
    simulator = Simulator(diagram)
    simulator.set_target_realtime_rate(0.0)
    simulator.AdvanceTo(1.0)  # camera frames at 5 fps, each drawn on the panel
    assert meshcat.HasPath(CAMERA_VIEW), "the browser operator drew no camera view"
    camera = diagram.GetOutputPort("capsule.camera.rgb_image").Eval(
        simulator.get_context()).data[..., 2::-1]  # RGBA to BGR

    page = HeadlessPage(exe, meshcat.web_url(), profile=tmp_path / "chromium")
    try:
        shown = page.settled_screenshot()
        meshcat.SetProperty(CAMERA_VIEW, "visible", False)
        without_panel = page.settled_screenshot()
        meshcat.SetProperty("/drake", "visible", False)  # the table, patient, colon, capsule
        empty = page.settled_screenshot()
    finally:
        page.close()

    # The scene covers much of the page, and the colon's tissue colour is in it.
    scene = _changed(without_panel, empty)
    tissue = scene & _tissue(without_panel)
    # The camera view: hiding the panel changes a patch of the page which, seen face on,
    # looks like the capsule camera's latest image (the panel may show the frame before).
    panel = _changed(shown, without_panel)
    n = 64
    expected = cv2.cvtColor(cv2.resize(np.ascontiguousarray(camera), (n, n),
                                       interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2GRAY)
    similarity = (np.corrcoef(_unwarp(shown, panel, n).ravel(), expected.ravel())[0, 1]
                  if panel.sum() > 100 else float("nan"))
    figures = (f"scene {scene.mean():.1%} of the page, colon tissue {tissue.mean():.1%}; "
               f"camera panel {panel.mean():.1%}, correlation with the camera image "
               f"{similarity:.2f}")
    print(figures)
    assert scene.mean() > 0.08, figures
    assert tissue.mean() > 0.005, figures
    assert panel.mean() > 0.02, figures
    assert similarity > 0.6, figures
