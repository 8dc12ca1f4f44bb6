"""The run's replay page, recording.html: Meshcat's replay of the run (its static HTML,
which inlines its viewer and the whole scene) with a panel beside it showing the capsule
camera's frames and plots of the run, each following the replay's time.

- `CameraStream` keeps the capsule camera's frames for the page as it goes: at most
  STREAM_FPS a simulated second, shrunk to STREAM_SIDE px and JPEG-encoded; when they pass
  STREAM_BUDGET bytes, every other frame is dropped and the rate halved, as often as need
  be, so a long run keeps a stream over its whole length at a bounded size.
- `replay_page` puts Meshcat's page, the frames (as data URIs), the plots and the map of the
  wall's pressure (io/wall_map.py, the capsule's place on it following the replay) into one
  file.
  The page's script reads the time of Meshcat's animation (`viewer.animator.time`: set as
  it plays, and by its time slider) each display frame, shows the last camera frame exposed
  by then and draws a cursor on the plots. Nothing is fetched when the page is viewed.
"""

import base64
import json

import cv2
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import EventStatus, LeafSystem
from pydrake.systems.sensors import ImageRgba8U

STREAM_SYSTEM = "replay.camera_stream"
# The embedded stream: frames per simulated second at most, longest side (px), JPEG quality,
# and the bytes of JPEG at which it thins (base64 adds a third in the page). Measured on a
# 60 s WithSensors run: 3.8 kB a frame (5 kB in the page), 1.5 MB of page a simulated
# minute at 5 frames/s; the stream is at most 8 MB of page, at 5 frames/s for the first
# ~5 simulated minutes of a run, at 2.5 up to ~10, and so on.
STREAM_FPS = 5.0
STREAM_SIDE = 160
STREAM_QUALITY = 70
STREAM_BUDGET = 6e6
# Points kept of each plotted series.
PLOT_POINTS = 600
PANEL_WIDTH = 340


class CameraStream(LeafSystem):
    """Keeps the capsule camera's frames for the replay page (module docstring): polls
    every 1 / STREAM_FPS s and keeps a frame the camera delivered since, stamped with its
    exposure time, unless it comes sooner than the stream's interval after the last kept.

    .. pydrake_system::

        name: CameraStream
        input_ports:
        - rgb_image
        - frame_info

    rgb_image: ImageRgba8U, the camera's last frame; frame_info: the camera's [exposure
    time of that frame (s), frames delivered, ...] (capsule/camera.py).

    The frames are held here (a recorder's state, as a log spool's): one simulation at a
    time; they start again when a simulation initialises.
    """

    def __init__(self, fps: float = STREAM_FPS, side: int = STREAM_SIDE,
                 quality: int = STREAM_QUALITY, budget: float = STREAM_BUDGET):
        super().__init__()
        self._side, self._quality, self._budget = side, quality, budget
        self._base_interval = 1.0 / fps
        self._rgb = self.DeclareAbstractInputPort("rgb_image",
                                                  AbstractValue.Make(ImageRgba8U()))
        self._info = self.DeclareVectorInputPort("frame_info", 4)
        self._reset()
        self.DeclareInitializationPublishEvent(self._initialize)
        self.DeclarePeriodicPublishEvent(self._base_interval, 0.0, self._poll)

    def _reset(self):
        self._frames = []       # (exposure time, JPEG bytes)
        self._bytes = 0
        self._interval = self._base_interval
        self._delivered = 0.0   # the camera's frame count at the last poll

    def _initialize(self, context):
        self._reset()
        return self._poll(context)

    @property
    def interval(self) -> float:
        """Smallest time between kept frames (s): 1 / STREAM_FPS, doubled at each thinning."""
        return self._interval

    def frames(self) -> list:
        """The kept frames, [(exposure time (s), JPEG bytes)], in time order."""
        return list(self._frames)

    def _poll(self, context):
        info = self._info.Eval(context)
        if info[1] <= self._delivered or not np.isfinite(info[0]):
            return EventStatus.DidNothing()
        self._delivered = info[1]
        t = float(info[0])
        if self._frames and t < self._frames[-1][0] + self._interval - 1e-9:
            return EventStatus.DidNothing()
        jpeg = encode_frame(self._rgb.Eval(context).data, self._side, self._quality)
        self._frames.append((t, jpeg))
        self._bytes += len(jpeg)
        while self._bytes > self._budget and len(self._frames) > 1:
            self._frames = self._frames[::2]
            self._bytes = sum(len(j) for _, j in self._frames)
            self._interval *= 2.0
        return EventStatus.Succeeded()


def encode_frame(rgba: np.ndarray, side: int, quality: int) -> bytes:
    """An RGBA(8) image as JPEG bytes, shrunk (area-averaged) so its longest side is at
    most `side` px."""
    h, w = rgba.shape[:2]
    scale = min(1.0, side / max(h, w))
    bgr = cv2.cvtColor(np.ascontiguousarray(rgba[..., :3]), cv2.COLOR_RGB2BGR)
    if scale < 1.0:
        bgr = cv2.resize(bgr, (max(1, round(w * scale)), max(1, round(h * scale))),
                         interpolation=cv2.INTER_AREA)
    ok, data = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("could not encode a camera frame as JPEG")
    return data.tobytes()


def decimate(t, y, points: int = PLOT_POINTS, keep: str = "sample"):
    """At most `points` of a series for a plot: every k-th sample, or (keep "max") the
    largest of each run of k, so that peaks survive."""
    t, y = np.asarray(t, dtype=float), np.asarray(y, dtype=float)
    k = max(1, int(np.ceil(len(t) / points)))
    if k == 1:
        return t, y
    n = len(t) // k * k
    if keep == "max":
        block = y[:n].reshape(-1, k)
        rows = np.arange(len(block))
        pick = np.nanargmax(np.where(np.isfinite(block), block, -np.inf), axis=1)
        return t[:n].reshape(-1, k)[rows, pick], block[rows, pick]
    return t[:n:k], y[:n:k]


def run_plots(colon, times, capsule_state, contact_load) -> list:
    """The replay's plots of a run's logs: where the capsule is along the colon's
    centreline (cm from the anus) and the contact load (N, the largest of each thinned
    run of samples), over simulated time. None where the state is not finite."""
    times = np.asarray(times, dtype=float)
    if len(times) == 0:
        return []
    p = np.asarray(capsule_state, dtype=float)[4:7].T
    finite = np.all(np.isfinite(p), axis=1)
    s = np.full(len(times), np.nan)
    if finite.any():
        s[finite] = colon.centerline.closest(p[finite])[0]
    plots = []
    for label, unit, y, keep in (("along the colon", "cm", 100.0 * s, "sample"),
                                 ("contact load", "N", contact_load, "max")):
        t, y = decimate(times, y, keep=keep)
        plots.append({"label": label, "unit": unit, "t": t, "y": y})
    return plots


def wall_map_panel(png: bytes, boxes, s_range_cm, times, s_cm, title: str) -> dict:
    """The replay's section of the wall's pressure map: the picture (PNG bytes of
    io/wall_map.py `wall_map_png`), its maps' boxes in the image ([left, top, right, bottom]
    fractions from its top left), the arc length its maps span (cm), the capsule's track
    (times (s) and its centreline station (cm), thinned) for the cursor, and a title."""
    t, s = decimate(times, s_cm)
    return {"src": "data:image/png;base64," + base64.b64encode(png).decode(),
            "boxes": [[round(float(v), 5) for v in box] for box in boxes],
            "s_range": [float(s_range_cm[0]), float(s_range_cm[1])],
            "t": [round(float(v), 4) for v in t],
            "s": [round(float(v), 3) if np.isfinite(v) else None for v in s], "title": title}


def replay_page(meshcat_html: str, frames=(), plots=(), wall_map: dict | None = None) -> str:
    """Meshcat's static HTML with a panel on its left: the camera frames [(exposure time
    (s), JPEG bytes)] (no camera section when there are none), the plots [{"label",
    "unit", "t", "y"}] (series of the run, already thinned) and the map of the wall's
    pressure (`wall_map_panel`, or None), all following the replay's time. Nothing to show,
    or an HTML that is not Meshcat's (no viewer to follow): the page as given."""
    if not frames and not plots and not wall_map:
        return meshcat_html
    head, body = meshcat_html.rfind("</head>"), meshcat_html.rfind("</body>")
    if head < 0 or body < head or "var viewer = new MeshCat.Viewer" not in meshcat_html:
        return meshcat_html
    data = {
        "frames": {"t": [round(t, 4) for t, _ in frames],
                   "src": ["data:image/jpeg;base64," + base64.b64encode(j).decode()
                           for _, j in frames]},
        "plots": [{"label": p["label"], "unit": p["unit"],
                   "t": [round(float(v), 4) for v in p["t"]],
                   "y": [round(float(v), 5) if np.isfinite(v) else None for v in p["y"]]}
                  for p in plots],
        "wall": wall_map,
    }
    # Inside a <script> element only "</" can end it early.
    payload = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    # With camera frames, a panel beside the scene; without, the plots in a box over the
    # scene's top left corner (empty in Meshcat's default view), the scene full width.
    camera = ("""
  <div class="replay-title">capsule camera</div>
  <img id="replay-camera" alt="capsule camera frame">
  <div id="replay-camera-caption" class="replay-caption"></div>""" if frames else "")
    panel = f"""
<div id="replay-panel" class="{'replay-side' if frames else 'replay-box'}">{camera}
  <div id="replay-plots"></div>{_WALL_SECTION if wall_map else ""}
</div>
<script type="application/json" id="replay-data">{payload}</script>
<script>{_PANEL_SCRIPT}</script>
"""
    style = _PANEL_STYLE + (_SIDE_STYLE if frames else "")
    return (meshcat_html[:head] + style + meshcat_html[head:body] + panel
            + meshcat_html[body:])


_PANEL_STYLE = f"""<style>
  #replay-panel {{ position: fixed; left: 0; top: 0; width: {PANEL_WIDTH}px;
    box-sizing: border-box; padding: 10px; overflow-y: auto; color: #e8e8e8;
    font: 12px sans-serif; }}
  #replay-panel.replay-side {{ bottom: 0; background: #202329; }}
  #replay-panel.replay-box {{ max-height: 100vh; background: rgba(32, 35, 41, 0.85);
    border-bottom-right-radius: 6px; }}
  #replay-camera {{ display: block; width: 100%; image-rendering: auto; background: #000; }}
  .replay-title {{ font-weight: bold; margin: 6px 0 4px; }}
  .replay-caption {{ margin: 3px 0 8px; color: #b8b8b8; }}
  #replay-plots canvas {{ display: block; width: 100%; margin-bottom: 2px; }}
  #replay-wall {{ position: relative; background: #fff; }}
  #replay-wall img {{ display: block; width: 100%; }}
  #replay-wall canvas {{ position: absolute; left: 0; top: 0; width: 100%; height: 100%; }}
</style>
"""
# The scene beside the side panel (in <head>, so the viewer is sized to it when made).
_SIDE_STYLE = f"""<style>
  body #meshcat-pane {{ margin-left: {PANEL_WIDTH}px !important;
    width: calc(100vw - {PANEL_WIDTH}px) !important; }}
</style>
"""

# The wall's pressure map: its picture, and a canvas over it for the capsule's place.
_WALL_SECTION = """
  <div id="replay-wall-title" class="replay-title"></div>
  <div id="replay-wall"><img id="replay-wall-map" alt="wall pressure map">
    <canvas id="replay-wall-cursor"></canvas></div>
  <div class="replay-caption">the capsule's place along the colon now: green line</div>"""

# Follows Meshcat's animation (viewer.animator.time, in simulated seconds: the recording
# starts at 0) once per display frame; redraws only when that time changes.
_PANEL_SCRIPT = r"""
(function () {
  const data = JSON.parse(document.getElementById("replay-data").textContent);
  const img = document.getElementById("replay-camera");
  const caption = document.getElementById("replay-camera-caption");
  const plots = data.plots.map(function (p) {
    const title = document.createElement("div");
    title.className = "replay-title";
    const canvas = document.createElement("canvas");
    canvas.width = 320; canvas.height = 96;
    const box = document.getElementById("replay-plots");
    box.appendChild(title); box.appendChild(canvas);
    const ys = p.y.filter(function (v) { return v !== null; });
    let lo = Math.min.apply(null, ys.concat([0])), hi = Math.max.apply(null, ys.concat([0]));
    if (hi - lo < 1e-9) { hi = lo + 1; }
    const end = Math.max(p.t.length ? p.t[p.t.length - 1] : 1, 1e-9);
    return {p: p, title: title, canvas: canvas, lo: lo, hi: hi, end: end};
  });
  function lastAtOrBefore(times, t) {
    let a = 0, b = times.length - 1, found = -1;
    while (a <= b) {
      const m = (a + b) >> 1;
      if (times[m] <= t + 1e-6) { found = m; a = m + 1; } else { b = m - 1; }
    }
    return found;
  }
  // A plot: its range on the left (from 0, or below it), time along the bottom, the
  // series, and the replay's time as a cursor.
  function drawPlot(q, t) {
    const g = q.canvas.getContext("2d"), w = q.canvas.width, h = q.canvas.height;
    const left = 38, right = w - 6, top = 8, bottom = h - 16;
    const x = function (s) { return left + (right - left) * Math.min(s, q.end) / q.end; };
    const y = function (v) { return bottom - (bottom - top) * (v - q.lo) / (q.hi - q.lo); };
    g.fillStyle = "#15171b"; g.fillRect(0, 0, w, h);
    g.fillStyle = "#9a9a9a"; g.font = "10px sans-serif"; g.textAlign = "right";
    g.fillText(q.hi.toPrecision(3), left - 4, top + 6);
    g.fillText(q.lo.toPrecision(3), left - 4, bottom + 3);
    g.fillText(q.end.toFixed(1) + " s", right, h - 3);
    g.textAlign = "left"; g.fillText("0 s", left, h - 3);
    g.strokeStyle = "#3a3d44"; g.lineWidth = 1;
    g.strokeRect(left + 0.5, top + 0.5, right - left, bottom - top);
    g.strokeStyle = "#ffd21a"; g.lineWidth = 1.5; g.beginPath();
    let pen = false;
    for (let i = 0; i < q.p.t.length; i++) {
      const v = q.p.y[i];
      if (v === null) { pen = false; continue; }
      if (pen) { g.lineTo(x(q.p.t[i]), y(v)); } else { g.moveTo(x(q.p.t[i]), y(v)); pen = true; }
    }
    g.stroke();
    g.strokeStyle = "#3cff5a"; g.lineWidth = 1; g.beginPath();
    g.moveTo(x(t), top); g.lineTo(x(t), bottom); g.stroke();
    const i = lastAtOrBefore(q.p.t, t);
    const now = i >= 0 && q.p.y[i] !== null ? q.p.y[i].toPrecision(3) + " " + q.p.unit : "-";
    q.title.textContent = q.p.label + ": " + now;
  }
  const wall = data.wall;
  const wallImg = document.getElementById("replay-wall-map");
  const wallCanvas = document.getElementById("replay-wall-cursor");
  if (wall) {
    document.getElementById("replay-wall-title").textContent = wall.title;
    wallImg.onload = function () {
      wallCanvas.width = wallImg.naturalWidth; wallCanvas.height = wallImg.naturalHeight;
      last = null;
    };
    wallImg.src = wall.src;
  }
  // The capsule's station at time t as a line across each map.
  function drawWall(t) {
    if (!wall || !wallCanvas.width) { return; }
    const g = wallCanvas.getContext("2d"), w = wallCanvas.width, h = wallCanvas.height;
    g.clearRect(0, 0, w, h);
    const i = lastAtOrBefore(wall.t, t);
    if (i < 0 || wall.s[i] === null) { return; }
    const f = (wall.s[i] - wall.s_range[0]) / (wall.s_range[1] - wall.s_range[0]);
    g.strokeStyle = "#3cff5a"; g.lineWidth = 2;
    wall.boxes.forEach(function (b) {
      const x = w * (b[0] + (b[2] - b[0]) * Math.min(Math.max(f, 0), 1));
      g.beginPath(); g.moveTo(x, h * b[1]); g.lineTo(x, h * b[3]); g.stroke();
    });
  }
  function update(t) {
    drawWall(t);
    if (img) {
      const i = lastAtOrBefore(data.frames.t, t);
      if (img.dataset.frame !== String(i)) {
        img.dataset.frame = String(i);
        if (i >= 0) { img.src = data.frames.src[i]; } else { img.removeAttribute("src"); }
      }
      caption.textContent = i >= 0 ? "frame exposed at t = " + data.frames.t[i].toFixed(2) +
          " s (replay at " + t.toFixed(2) + " s)" : "no frame yet";
    }
    plots.forEach(function (q) { drawPlot(q, t); });
  }
  let last = null;
  function tick() {
    const animator = (typeof viewer !== "undefined") ? viewer.animator : null;
    const t = animator && isFinite(animator.time) ? animator.time : 0;
    if (t !== last) { last = t; update(t); }
    requestAnimationFrame(tick);
  }
  update(0);
  requestAnimationFrame(tick);
})();
"""
