"""RenderWorker: a capsule camera's frames drawn in a process of its own, on another core.

Software rendering (Mesa llvmpipe) is the largest single cost of a simulated second with the
camera on, and a simulation runs on one core. A camera with a transmission latency
(`CameraConfig.latency` > 0) exposes a frame at t and delivers it at t + latency; in between,
the frame is drawn here while the physics goes on.

The worker builds its own copy of what the camera sees (the colon's camera walls: anchored,
so a frame is fully given by the camera's pose) with the same meshes, renderers and lens,
and draws exactly the image the camera would draw itself. So a simulation's outputs do not
depend on whether, or how fast, the worker runs: whenever it is still starting, has failed,
or was not given that frame, the camera draws the frame itself.

The worker is a fresh interpreter (`python -m capsule_drake.capsule.render_process`), so it
never re-runs the user's script. Protocol over its stdin and stdout, every message a 4-byte
little-endian length and that many bytes: first the camera's settings (a pickle of the
ColonParams and CameraConfig), then camera poses [R_WC row-major (9), p_WC (3)] as 12
float64; the worker answers each pose with the RGBA image's bytes (H x W x 4), and answers
the settings with b"ready" (or, at any point, with what failed, as text). Closing its stdin
stops it.
"""

from __future__ import annotations

import fcntl
import logging
import os
import pickle
import select
import struct
import subprocess
import sys
import weakref

import numpy as np

log = logging.getLogger(__name__)

# Longest wait for a frame already submitted (s): a worker this late is taken for dead.
FRAME_TIMEOUT = 30.0
POSE_BYTES = 12 * 8
_F_SETPIPE_SZ = getattr(fcntl, "F_SETPIPE_SZ", 1031)


def read_exactly(stream, n: int) -> bytes:
    data = bytearray()
    while len(data) < n:
        chunk = stream.read(n - len(data))
        if not chunk:
            raise EOFError("pipe closed")
        data += chunk
    return bytes(data)


def read_message(stream) -> bytes:
    (n,) = struct.unpack("<I", read_exactly(stream, 4))
    return read_exactly(stream, n)


def write_message(stream, payload) -> None:
    payload = memoryview(payload).cast("B")
    stream.write(struct.pack("<I", len(payload)))
    stream.write(payload)
    stream.flush()


def _stop(process):
    try:
        process.stdin.close()
    except OSError:
        pass
    try:
        process.wait(timeout=2.0)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
    process.stdout.close()


class RenderWorker:
    """Draws a camera's frames in another process (module docstring).

    Args:
        colon_params: the scenario's ColonParams (the worker builds the same walls).
        config: the camera's CameraConfig.
        stderr: where the worker's own messages go (default: discarded; VTK is chatty).
    """

    def __init__(self, colon_params, config, stderr=subprocess.DEVNULL):
        self._shape = (config.lens.height, config.lens.width, 4)
        self._size = int(np.prod(self._shape))
        self._process = subprocess.Popen(
            [sys.executable, "-m", "capsule_drake.capsule.render_process"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=stderr,
            # One rasteriser thread: the worker keeps to the core the simulation leaves.
            env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path), LP_NUM_THREADS="1"))
        # Room in the pipe for a whole frame, so the worker finishes writing it while the
        # simulation runs and collecting it is a copy (Linux; elsewhere the default pipe).
        try:
            fcntl.fcntl(self._process.stdout.fileno(), _F_SETPIPE_SZ, self._size + 4096)
        except (OSError, AttributeError):
            pass
        self._state = "starting"  # -> "ready" -> "failed" or "closed"
        self._pending: bytes | None = None  # the pose of the frame being drawn
        self._finalizer = weakref.finalize(self, _stop, self._process)
        try:
            write_message(self._process.stdin, pickle.dumps((colon_params, config)))
        except OSError as e:
            self._fail(f"cannot start ({e})")

    @property
    def state(self) -> str:
        """"starting", "ready", "failed" or "closed"."""
        return self._state

    def wait_until_ready(self, timeout: float = 120.0) -> bool:
        """Blocks until the worker can draw (True) or has failed or timed out (False)."""
        if self._state == "starting":
            self._receive_start(timeout)
        return self._state == "ready"

    def submit(self, pose) -> bool:
        """Starts drawing the frame at camera pose [R_WC (9), p_WC (3)]; False if the worker
        cannot take it now (the camera then draws it itself)."""
        if self._pending is not None:
            self._receive_frame()  # a frame nobody collected: keep the replies in step
        if self._state == "starting":
            self._receive_start(0.0)
        if self._state != "ready":
            return False
        pose = np.ascontiguousarray(pose, dtype="<f8")
        try:
            write_message(self._process.stdin, pose)
        except (OSError, ValueError) as e:
            return self._fail(f"cannot send it a frame ({e})")
        self._pending = pose.tobytes()
        return True

    def collect(self, pose, out: np.ndarray) -> bool:
        """Copies the frame drawn at `pose` into `out` (H x W x 4 uint8); False when the
        worker was not drawing that frame or failed (the camera then draws it itself)."""
        if self._pending is None \
                or self._pending != np.ascontiguousarray(pose, dtype="<f8").tobytes():
            return False
        image = self._receive_frame()
        if image is None:
            return False
        out[...] = np.frombuffer(image, dtype=np.uint8).reshape(self._shape)
        return True

    def close(self):
        self._state = "closed"
        self._finalizer()

    # ---- internals ------------------------------------------------------------------------
    def _next_reply(self, timeout: float):
        """The worker's next message, None if none came within `timeout` (s), or the
        exception that ended the pipe."""
        stdout = self._process.stdout
        if not select.select([stdout], [], [], timeout)[0]:
            return None
        try:
            return read_message(stdout)
        except (EOFError, OSError, ValueError, struct.error) as e:
            return e

    def _receive_start(self, timeout: float):
        reply = self._next_reply(timeout)
        if reply is None:
            return  # still starting
        if reply == b"ready":
            self._state = "ready"
        else:
            self._fail(self._describe(reply, "while starting"))

    def _receive_frame(self) -> bytes | None:
        self._pending = None
        reply = self._next_reply(FRAME_TIMEOUT)
        if reply is None:
            self._fail(f"no frame within {FRAME_TIMEOUT:.0f} s")
            return None
        if isinstance(reply, Exception) or len(reply) != self._size:
            self._fail(self._describe(reply, "instead of a frame"))
            return None
        return reply

    @staticmethod
    def _describe(reply, when: str) -> str:
        if isinstance(reply, Exception):
            return f"stopped {when} ({reply or type(reply).__name__})"
        return f"{reply.decode(errors='replace')} ({when})"

    def _fail(self, why: str) -> bool:
        if self._state not in ("failed", "closed"):
            log.warning("camera render worker failed: %s; the camera draws its frames itself",
                        why)
        self._state = "failed"
        self._pending = None
        self._finalizer()
        return False

