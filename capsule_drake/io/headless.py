"""Screenshots of a page in headless Chromium, for the tests that check what a browser shows
(the Meshcat console, the replay page) and the documentation's figures
(benchmarks/meshcat_figures.py).

Needs a Chromium executable (`chromium`, as Debian packages it, or `chromium-browser`); it
is driven over the DevTools protocol on a pipe, so nothing listens on a port.
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

WIDTH, HEIGHT = 1200, 800


def chromium_executable() -> str | None:
    """The Chromium executable on PATH, or None."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


class HeadlessPage:
    """One page in headless Chromium, driven over the DevTools protocol on a pipe
    (`--remote-debugging-pipe`: the browser reads commands from its fd 3 and writes replies
    to its fd 4, JSON messages each ended by a NUL byte).

    Chromium's own `--screenshot` is not used: a live Meshcat page never finishes loading
    (its websocket stays open, and the scene arrives over it), so there is no moment at
    which that screenshot is known to show the whole scene. Here screenshots are taken
    until the page stops changing, or after the page's script says it is ready
    (`wait_for`).
    """

    def __init__(self, exe: str, url: str, profile, timeout: float = 30.0,
                 width: int = WIDTH, height: int = HEIGHT):
        self._timeout = timeout
        self._buffer = b""
        self._id = 0
        self._session = None
        to_browser, self._to_browser = self._pipe()
        self._from_browser, from_browser = self._pipe()
        args = [exe, "--headless=new", "--no-sandbox", "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader", "--disable-background-networking",
                f"--window-size={width},{height}", f"--user-data-dir={profile}",
                "--remote-debugging-pipe", "about:blank"]
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
            self._call("Emulation.setDeviceMetricsOverride", width=width, height=height,
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

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page (a promise is awaited); raises
        RuntimeError if it throws."""
        reply = self._call("Runtime.evaluate", expression=expression, returnByValue=True,
                           awaitPromise=True)
        if "exceptionDetails" in reply:
            details = reply["exceptionDetails"]
            text = details.get("exception", {}).get("description") or details.get("text")
            raise RuntimeError(f"in the page: {text}")
        return reply["result"].get("value")

    def wait_for(self, expression: str, interval: float = 0.2):
        """Waits until a JavaScript expression is true in the page (TimeoutError after the
        page's timeout)."""
        deadline = time.monotonic() + self._timeout
        while not self.evaluate(expression):
            if time.monotonic() > deadline:
                raise TimeoutError(f"the page never had {expression}")
            time.sleep(interval)

    def screenshot(self) -> np.ndarray:
        """The page as a BGR image."""
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

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
