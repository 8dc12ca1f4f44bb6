"""The teleoperation console in a real browser: headless Chromium opens the live Meshcat page
of a station with the browser operator, and screenshots show the scene and the capsule's
camera view drawn on its panel.

Each check compares two screenshots of the same page, one with the thing checked hidden
(`visible: false` in Meshcat), so that it does not depend on where the default view puts
things nor on the background's colours.
"""

import base64
import fcntl
import json
import os
import select
import shutil
import signal
import time

import cv2
import numpy as np
import pytest
from pydrake.geometry import Meshcat, MeshcatParams
from pydrake.systems.analysis import Simulator

from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station

WIDTH, HEIGHT = 1200, 800
CAMERA_VIEW = "/teleop/camera_view"


def _chromium() -> str:
    """The Chromium executable; skips without one, except on CI, which must have it."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is not on PATH (the CI set-up must install it)")
        pytest.skip("chromium is not on PATH")
    return exe


class HeadlessPage:
    """One page in headless Chromium, driven over the DevTools protocol on a pipe
    (`--remote-debugging-pipe`: the browser reads commands from its fd 3 and writes replies
    to its fd 4, JSON messages each ended by a NUL byte).

    Chromium's own `--screenshot` is not used: a live Meshcat page never finishes loading
    (its websocket stays open, and the scene arrives over it), so there is no moment at
    which that screenshot is known to show the whole scene. Here screenshots are taken
    until the page stops changing.
    """

    def __init__(self, exe: str, url: str, profile, timeout: float = 30.0):
        self._timeout = timeout
        self._buffer = b""
        self._id = 0
        self._session = None
        to_browser, self._to_browser = self._pipe()
        self._from_browser, from_browser = self._pipe()
        args = [exe, "--headless=new", "--no-sandbox", "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader", f"--window-size={WIDTH},{HEIGHT}",
                f"--user-data-dir={profile}", "--remote-debugging-pipe", "about:blank"]
        # posix_spawn rather than subprocess: the fds must land on 3 and 4 in the child,
        # and a fork-time callback is unsafe here (Meshcat's server thread is running).
        self._pid = os.posix_spawnp(exe, args, os.environ, file_actions=[
            (os.POSIX_SPAWN_OPEN, 0, os.devnull, os.O_RDONLY, 0),
            (os.POSIX_SPAWN_OPEN, 1, os.devnull, os.O_WRONLY, 0),
            (os.POSIX_SPAWN_DUP2, 1, 2),
            (os.POSIX_SPAWN_DUP2, to_browser, 3),
            (os.POSIX_SPAWN_DUP2, from_browser, 4)])
        os.close(to_browser)
        os.close(from_browser)
        try:
            target = self._call("Target.createTarget", url=url)["targetId"]
            self._session = self._call("Target.attachToTarget", targetId=target,
                                       flatten=True)["sessionId"]
            self._call("Emulation.setDeviceMetricsOverride", width=WIDTH, height=HEIGHT,
                       deviceScaleFactor=1, mobile=False)
        except BaseException:
            self.close()
            raise

    @staticmethod
    def _pipe():
        """A pipe whose ends are numbered 10 or above, so moving them to 3 and 4 in the
        child cannot overwrite one with the other."""
        ends = []
        for fd in os.pipe():
            ends.append(fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10))
            os.close(fd)
        return ends

    def _call(self, method: str, **params) -> dict:
        self._id += 1
        message = {"id": self._id, "method": method, "params": params}
        if self._session is not None:
            message["sessionId"] = self._session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + self._timeout
        while True:  # skip events and replies to other calls
            while b"\0" not in self._buffer:
                if not select.select([self._from_browser], [], [],
                                     max(0.0, deadline - time.monotonic()))[0]:
                    raise TimeoutError(f"chromium did not answer {method}")
                chunk = os.read(self._from_browser, 1 << 20)
                if not chunk:
                    raise RuntimeError("chromium closed its DevTools pipe")
                self._buffer += chunk
            raw, self._buffer = self._buffer.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"chromium: {method}: {reply['error']}")
                return reply["result"]

    def screenshot(self) -> np.ndarray:
        png = base64.b64decode(self._call("Page.captureScreenshot", format="png")["data"])
        return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)

    def settled_screenshot(self, quiet: float = 2.0, interval: float = 0.5) -> np.ndarray:
        """A screenshot once the page has not changed for `quiet` seconds."""
        deadline = time.monotonic() + self._timeout
        last = self.screenshot()
        since = time.monotonic()
        while time.monotonic() - since < quiet:
            if time.monotonic() > deadline:
                raise TimeoutError(f"the page kept changing for {self._timeout} s")
            time.sleep(interval)
            image = self.screenshot()
            if not np.array_equal(image, last):
                last, since = image, time.monotonic()
        return last

    def close(self):
        try:
            self._session = None  # a browser-wide command
            self._call("Browser.close")
        except (OSError, RuntimeError, TimeoutError):
            pass
        for fd in (self._to_browser, self._from_browser):
            os.close(fd)
        for _ in range(100):
            if os.waitpid(self._pid, os.WNOHANG)[0]:
                return
            time.sleep(0.1)
        os.kill(self._pid, signal.SIGKILL)
        os.waitpid(self._pid, 0)


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
    exe = _chromium()
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
