"""The run's replay page (recording.html): the capsule visible in it, the camera stream beside
it following the replay's time, at a bounded size.

The browser test renders a real run's recording.html in headless Chromium and compares
screenshots of the same instant with one thing hidden at a time (the marker and trail, the
capsule, and, to show what the translucency buys, the capsule behind an opaque colon),
around where the run's logged capsule position projects with the page's own camera.
"""

import base64
import json
import re

import cv2
import numpy as np
import pytest
import trimesh
from pydrake.common.value import AbstractValue
from pydrake.geometry import Meshcat, MeshcatParams
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantValueSource
from pydrake.systems.sensors import ImageRgba8U

from browser import chromium
from capsule_drake.io.headless import HeadlessPage
from capsule_drake.io.replay import (PANEL_WIDTH, CameraStream, decimate, encode_frame,
                                     replay_page)
from capsule_drake.app.run import simulate
from capsule_drake.io.visualization import tube_mesh
from capsule_drake.scenario import load_scenario
from capsule_drake.station import station_value


def _replay_data(page: str) -> dict:
    found = re.search(r'<script type="application/json" id="replay-data">(.*?)</script>',
                      page, re.S)
    return json.loads(found.group(1))


def _jpeg(seed: int, size: int = 48) -> bytes:
    rgba = np.random.default_rng(seed).integers(0, 256, (size, size, 4), dtype=np.uint8)
    return encode_frame(rgba, 160, 70)


def test_the_page_carries_the_frames_and_plots_and_keeps_meshcat_whole():
    meshcat_html = Meshcat(MeshcatParams(port=0)).StaticHtml()
    frames = [(0.0, _jpeg(0)), (0.2, _jpeg(1)), (0.4, _jpeg(2))]
    plots = [{"label": "contact load", "unit": "N", "t": [0.0, 0.5], "y": [0.1, np.nan]}]
    page = replay_page(meshcat_html, frames, plots)

    data = _replay_data(page)
    # The frames come back byte for byte from their data URIs, with their times.
    assert data["frames"]["t"] == [0.0, 0.2, 0.4]
    assert [base64.b64decode(src.split(",", 1)[1]) for src in data["frames"]["src"]] == \
        [jpeg for _, jpeg in frames]
    assert data["plots"][0]["y"] == [0.1, None]  # no NaN in JSON
    assert page.count('id="replay-camera"') == 1
    # Meshcat's page is all there, in order: removing what was added gives it back.
    added = re.compile(r"<style>\n  (#replay-panel|body #meshcat-pane).*?</style>\n|"
                       r"\n<div id=\"replay-panel\".*?</script>\n(?=</body>)", re.S)
    assert added.sub("", page) == meshcat_html
    assert f"margin-left: {PANEL_WIDTH}px" in page   # the scene beside the panel
    # What was added names nothing to fetch: its images are data URIs.
    extra = "".join(m.group(0) for m in added.finditer(page))
    assert not re.search(r"https?:|url\(|src=\"(?!data:)|import ", extra)
    # No camera: no camera section and the scene full width, the plots still over it;
    # nothing to add, or a page that is not Meshcat's: the page as it was.
    plots_only = replay_page(meshcat_html, [], plots)
    assert 'id="replay-camera"' not in plots_only
    assert f"margin-left: {PANEL_WIDTH}px" not in plots_only
    assert added.sub("", plots_only) == meshcat_html
    assert _replay_data(plots_only)["plots"] == data["plots"]
    assert replay_page(meshcat_html, [], []) == meshcat_html
    assert replay_page("<html><body></body></html>", frames, plots) == \
        "<html><body></body></html>"


class _FakeCamera(LeafSystem):
    """frame_info of a camera taking a frame every 0.1 s: [exposure time, frames, 0, 10]."""

    def __init__(self):
        super().__init__()
        self.DeclareVectorOutputPort("frame_info", 4, self._calc)

    def _calc(self, context, output):
        k = np.floor(context.get_time() * 10.0 + 1e-6)
        output.SetFromVector([k / 10.0, k + 1.0, 0.0, 10.0])


def test_the_stream_keeps_at_most_its_rate_and_thins_to_its_budget():
    image = ImageRgba8U(64, 64)
    image.mutable_data[...] = np.random.default_rng(3).integers(0, 256, (64, 64, 4))
    size = len(encode_frame(image.data, 160, 70))   # every frame is this image
    duration, budget = 20.0, 30.5 * size
    builder = DiagramBuilder()
    stream = builder.AddSystem(CameraStream(fps=5.0, budget=budget))
    source = builder.AddSystem(ConstantValueSource(AbstractValue.Make(image)))
    camera = builder.AddSystem(_FakeCamera())
    builder.Connect(source.get_output_port(), stream.GetInputPort("rgb_image"))
    builder.Connect(camera.get_output_port(), stream.GetInputPort("frame_info"))
    simulator = Simulator(builder.Build())
    simulator.AdvanceTo(duration)

    frames = stream.frames()
    times = np.array([t for t, _ in frames])
    # Closed form: at interval 0.2 * 2^k a run of 20 s keeps floor(20 / interval) + 1
    # frames; the stream settles on the smallest k whose frames fit the budget.
    k = next(k for k in range(10) if (np.floor(duration / (0.2 * 2**k)) + 1) * size <= budget)
    assert stream.interval == pytest.approx(0.2 * 2**k)
    assert k >= 1   # the budget was reached: the test exercises the thinning
    np.testing.assert_allclose(times, np.arange(len(times)) * 0.2 * 2**k, atol=1e-9)
    assert len(times) == np.floor(duration / (0.2 * 2**k)) + 1  # the whole run is covered
    assert sum(len(j) for _, j in frames) <= budget


def test_a_tube_along_a_path_has_its_radius_and_area():
    radius, sides = 0.002, 6
    # A straight tube: its area is the hexagon's perimeter (6 r) times its length.
    straight = np.array([[0.0, 0, 0], [0.05, 0, 0], [0.1, 0, 0], [0.3, 0, 0]])
    vertices, faces = tube_mesh(straight, radius, sides)
    mesh = trimesh.Trimesh(vertices.T, faces.T, process=False)
    assert mesh.area == pytest.approx(6 * radius * 0.3, rel=1e-9)
    # A bent path, and one that turns back on itself: every ring lies at the radius from
    # its point, normal to the path there, without degenerate triangles.
    angle = np.linspace(0.0, np.pi, 12)
    for path in (np.c_[np.cos(angle), np.sin(angle), 0.1 * angle] * 0.05,
                 np.array([[0.0, 0, 0], [0.01, 0, 0], [0.0, 0.0, 0.0001], [-0.01, 0, 0]])):
        vertices, faces = tube_mesh(path, radius, sides)
        rings = vertices.T.reshape(len(path), sides, 3) - path[:, None, :]
        np.testing.assert_allclose(np.linalg.norm(rings, axis=2), radius, rtol=1e-9)
        tangent = np.gradient(path, axis=0)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        np.testing.assert_allclose(np.einsum("rsk,rk->rs", rings, tangent), 0.0, atol=1e-12)
        assert faces.shape == (3, 2 * (len(path) - 1) * sides)
        assert trimesh.Trimesh(vertices.T, faces.T, process=False).area_faces.min() > 0


def test_thinned_series_keep_their_peaks():
    t = np.linspace(0.0, 10.0, 10001)
    y = np.zeros_like(t)
    y[4567] = 3.0   # a contact spike one sample long
    kept_t, kept_y = decimate(t, y, points=600, keep="max")
    assert len(kept_t) <= 600 and kept_y.max() == 3.0 and t[4567] in kept_t
    assert len(decimate(t, y, points=600)[0]) <= 600



def _changed(a: np.ndarray, b: np.ndarray, threshold: int = 25) -> np.ndarray:
    return np.abs(a.astype(int) - b.astype(int)).max(axis=2) > threshold


# Shows the replay at one instant: paused, seeked, the panel's time set (as the replay's
# time slider does); then, as after a property is set, drawn: the promise resolves after two
# display frames.
DRAWN = ("viewer.set_dirty(); new Promise(function (done) { requestAnimationFrame("
         "function () { requestAnimationFrame(function () { done(true); }); }); })")
SEEK = ("(function (t) { const a = viewer.animator; a.pause(); a.seek(t); "
        "a.display_progress(t); })(%f); " + DRAWN)
SET = "viewer.set_property(%s, %s, %s); " + DRAWN
# Where a world point (Drake's frame) is drawn on the page: Meshcat's scene turns z up.
PROJECT = """(function (p) {
  const v = new MeshCat.THREE.Vector3(p[0], p[1], p[2]);
  viewer.scene.updateMatrixWorld(); viewer.scene.localToWorld(v); v.project(viewer.camera);
  const r = viewer.renderer.domElement.getBoundingClientRect();
  return [r.left + (v.x + 1) / 2 * r.width, r.top + (1 - v.y) / 2 * r.height];
})(%s)"""


@pytest.mark.slow
def test_the_replay_shows_the_capsule_and_the_camera_stream_at_the_replays_time(tmp_path):
    exe = chromium()
    # The capsule starts in the sigmoid, inside the colon (not at its open end).
    scenario = load_scenario(name="WithSensors", override=(
        "{duration: 1.0, capsule: {start_s: 0.30, lumen_tracker: null}, pseudo_force: null}"))
    result = simulate(scenario, meshcat=Meshcat(MeshcatParams(port=0)),
                      out_dir=tmp_path / "run", progress=False)
    html = tmp_path / "run" / "recording.html"
    frames = station_value(result.station, "meshcat.replay_frames")()
    instant = 0.9
    i = int(np.argmin(np.abs(result.times - instant)))
    p_WB = result.capsule_state[4:7, i]
    expected_frame = max(k for k, (t, _) in enumerate(frames) if t <= instant + 1e-6)

    page = HeadlessPage(exe, html.as_uri(), profile=tmp_path / "chromium", timeout=60.0)
    try:
        page.wait_for("typeof viewer !== 'undefined' && viewer.animator.duration > 0")
        # Meshcat's floor grid and axes are off.
        assert page.evaluate('[viewer.scene_tree.find(["Grid"]).object.visible, '
                             'viewer.scene_tree.find(["Axes"]).object.visible]') == [False,
                                                                                    False]
        trail = 'Object.values(viewer.scene_tree.find(["capsule_trail"]).children)'
        page.evaluate(SEEK % 0.0)
        trail_at_start = page.evaluate(f"{trail}.map(function (n) {{ return n.object.visible; }})")
        end = page.evaluate("viewer.animator.duration")
        page.evaluate(SEEK % end)
        trail_at_end = page.evaluate(f"{trail}.map(function (n) {{ return n.object.visible; }})")
        page.evaluate(SEEK % instant)
        x, y = page.evaluate(PROJECT % json.dumps(list(map(float, p_WB))))
        shown_frame = page.evaluate('Number(document.getElementById("replay-camera")'
                                    '.dataset.frame)')
        box = page.evaluate('(function () { const r = document.getElementById('
                            '"replay-camera").getBoundingClientRect(); '
                            'return [r.left, r.top, r.width, r.height]; })()')
        # The first once the page is still (textures decode after the scene is built).
        shots = {"as written": page.settled_screenshot(quiet=0.6, interval=0.2)}
        page.evaluate(SEEK % 0.35)
        earlier_frame = page.evaluate('Number(document.getElementById("replay-camera")'
                                      '.dataset.frame)')
        page.evaluate(SEEK % instant)
        page.evaluate(SET % ('["capsule_marker"]', '"visible"', "false"))
        page.evaluate(SET % ('["capsule_trail"]', '"visible"', "false"))
        shots["no marker"] = page.screenshot()
        page.evaluate(SET % ('["drake", "visualizer", "capsule"]', '"visible"', "false"))
        shots["no capsule"] = page.screenshot()
        page.evaluate(SET % ('["drake", "visualizer", "capsule"]', '"visible"', "true"))
        page.evaluate(SET % ('["drake", "visualizer", "colon_mucosa"]',
                             '"modulated_opacity"', "1.0"))
        shots["opaque colon"] = page.screenshot()
        page.evaluate(SET % ('["drake", "visualizer", "capsule"]', '"visible"', "false"))
        shots["opaque colon, no capsule"] = page.screenshot()
    finally:
        page.close()
    for name, image in shots.items():
        cv2.imwrite(str(tmp_path / f"{name.replace(' ', '_').replace(',', '')}.png"), image)

    # Around where the logged capsule position is drawn (the marker's radius on screen is
    # ~10 px in this view; 30 px leaves room for the replay's interpolation).
    h, w = shots["as written"].shape[:2]
    yy, xx = np.mgrid[:h, :w]
    near = (xx - x) ** 2 + (yy - y) ** 2 < 30 ** 2
    marker = _changed(shots["as written"], shots["no marker"]) & near
    capsule = _changed(shots["no marker"], shots["no capsule"])
    behind_opaque = _changed(shots["opaque colon"], shots["opaque colon, no capsule"]) & near
    cy, cx = (np.mean(np.nonzero(capsule)[k]) if capsule.any() else np.inf for k in (0, 1))
    figures = (f"marker {marker.sum()} px, capsule {capsule.sum()} px (centre "
               f"{np.hypot(cx - x, cy - y):.1f} px from its logged position), behind an "
               f"opaque colon {behind_opaque.sum()} px; trail pieces {len(trail_at_end)}; "
               f"camera frame {shown_frame} (expected {expected_frame})")
    print(figures)
    assert marker.sum() > 100, figures
    # The capsule itself shows through the translucent colon, where it is, and nowhere
    # else; an opaque colon would hide it.
    assert capsule.sum() > 15 and np.hypot(cx - x, cy - y) < 10, figures
    assert behind_opaque.sum() < 0.2 * capsule.sum(), figures
    # The trail is drawn piece by piece as the replay goes: none at its start, all at its
    # end.
    assert trail_at_end and not any(trail_at_start) and all(trail_at_end), figures

    # The panel shows the frame exposed last before the replay's time, as it was kept.
    assert shown_frame == expected_frame, figures
    left, top, width, height = (int(round(v)) for v in box)
    on_page = cv2.cvtColor(shots["as written"][top:top + height, left:left + width],
                           cv2.COLOR_BGR2GRAY)
    kept = cv2.imdecode(np.frombuffer(frames[expected_frame][1], np.uint8),
                        cv2.IMREAD_GRAYSCALE)
    on_page = cv2.resize(on_page, kept.shape[::-1], interpolation=cv2.INTER_AREA)
    assert np.corrcoef(on_page.ravel(), kept.ravel())[0, 1] > 0.95
    # Earlier in the replay, an earlier frame.
    assert earlier_frame == max(k for k, (t, _) in enumerate(frames) if t <= 0.35 + 1e-6)
    assert earlier_frame < expected_frame
