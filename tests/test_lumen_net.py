"""The learned lumen detector (perception/lumen_net.py): its layers against an independent
convolution, its gradients against finite differences of its loss, its symmetries, its
weights file's errors, and the shipped weights on views whose truth has a closed form."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix
from scipy import ndimage

from capsule_drake.app.commands.benchmark import parse_seeds
from capsule_drake.perception import lumen_net
from capsule_drake.perception.lens import LensConfig
from capsule_drake.perception.lumen import load_detector
from capsule_drake.perception.lumen_truth import far_region
from capsule_drake.perception.raycast import RayCaster, Shading

from tube_set import straight_tube


@pytest.mark.parametrize("stride, dilation", [(1, 1), (2, 1), (1, 2), (1, 4)])
def test_convolution_matches_scipy_correlation(stride, dilation):
    rng = np.random.default_rng(stride * 10 + dilation)
    x = rng.standard_normal((2, 12, 12, 3))
    w = rng.standard_normal((4, 3, 3, 3))
    b = rng.standard_normal(4)
    out = lumen_net.conv_forward(x, w, b, stride, dilation)
    for n in range(2):
        for k in range(4):
            total = np.zeros((12, 12))
            for c in range(3):
                kernel = np.zeros((2 * dilation + 1,) * 2)
                kernel[::dilation, ::dilation] = w[k, c]
                total += ndimage.correlate(x[n, :, :, c], kernel, mode="constant")
            np.testing.assert_allclose(out[n, :, :, k], total[::stride, ::stride] + b[k],
                                       atol=1e-10)


def test_gradients_match_finite_differences_of_the_loss():
    """Along a random direction in each weight tensor, the analytic gradient's projection
    equals the central difference of the loss (float64; ReLU kinks are measure zero)."""
    rng = np.random.default_rng(3)
    weights = {k: v.astype(np.float64) for k, v in lumen_net.init_weights(rng).items()}
    for key in weights:
        if key.endswith("_b"):
            weights[key] = 0.1 * rng.standard_normal(weights[key].shape)
    x = rng.standard_normal((3, 64, 64, 4))
    cells = np.ones((3, 16, 16), bool)
    cells[0, :3] = False
    cells[2, :, 12:] = False
    target = rng.uniform(-0.5, 0.5, (3, 2))
    visible = np.array([True, False, True])
    _, grads, parts = lumen_net.loss_and_gradients(weights, x, cells, target, visible)
    assert parts["position"] > 0 and parts["visible"] > 0
    for key in weights:
        direction = rng.standard_normal(weights[key].shape)
        step = 1e-6
        shifted = dict(weights)
        shifted[key] = weights[key] + step * direction
        up, _, _ = lumen_net.loss_and_gradients(shifted, x, cells, target, visible)
        shifted[key] = weights[key] - step * direction
        down, _, _ = lumen_net.loss_and_gradients(shifted, x, cells, target, visible)
        numeric = (up - down) / (2 * step)
        analytic = float(np.sum(grads[key] * direction))
        assert analytic == pytest.approx(numeric, rel=1e-4, abs=1e-8), key


def test_the_soft_argmax_lands_on_the_cell_its_logits_pick():
    weights = {k: np.zeros_like(v) for k, v in lumen_net.init_weights(
        np.random.default_rng(0)).items()}
    weights["heat_b"][:] = 0.0
    x = np.zeros((1, 64, 64, 4), np.float32)
    cells = np.ones((1, 16, 16), bool)
    position, vis, _ = lumen_net.forward(weights, x, cells)
    np.testing.assert_allclose(position[0], [0.0, 0.0], atol=1e-6)  # uniform: the centre
    only = np.zeros((1, 16, 16), bool)
    only[0, 3, 11] = True
    position, _, _ = lumen_net.forward(weights, x, only)
    np.testing.assert_allclose(position[0], lumen_net.cell_centres()[:, 3, 11], atol=1e-6)


@pytest.mark.parametrize("code", range(8))
def test_each_symmetry_moves_the_target_with_the_image(code):
    image = np.zeros((64, 64), np.float32)
    u, v = 41, 13  # a marked pixel
    image[v, u] = 1.0
    unit = np.array([(u + 0.5) / 64 * 2 - 1, (v + 0.5) / 64 * 2 - 1])
    moved, point = lumen_net.symmetry([image], unit, code)
    vv, uu = np.unravel_index(np.argmax(moved), moved.shape)
    np.testing.assert_allclose(point, [(uu + 0.5) / 64 * 2 - 1, (vv + 0.5) / 64 * 2 - 1],
                               atol=1e-6)


@pytest.mark.parametrize("code", range(8))
def test_unsymmetry_moves_a_point_back(code):
    unit = np.array([0.3, -0.7])
    _, moved = lumen_net.symmetry([np.zeros((4, 4))], unit, code)
    np.testing.assert_allclose(lumen_net.unsymmetry(moved, code), unit, atol=1e-7)


def test_reading_a_frame_under_its_symmetries_averages_the_moved_frames_answers():
    """predict(..., symmetries=k) against a second route: the network run on each of the k
    flipped or turned frames (full size, before preprocessing), each answer moved back by
    hand, the positions and the visible logits averaged."""
    net = lumen_net.LumenNet.load()
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[:256, :256]
    grey = 60 + 120 * np.exp(-((xx - 90) ** 2 + (yy - 170) ** 2) / 4000.0)
    rgb = np.repeat(np.clip(grey + rng.normal(0, 5, grey.shape), 0, 255)[..., None], 3,
                    axis=2).astype(np.uint8)
    field = (yy - 127.5) ** 2 + (xx - 127.5) ** 2 < 128 ** 2
    for k in (1, 3, 8):
        pixel, probability = net.predict(rgb, field, symmetries=k)
        points, logits = [], []
        for code in range(k):
            moved, moved_field, _ = lumen_net.symmetry([rgb, field], np.zeros(2), code)
            moved, moved_field = np.ascontiguousarray(moved), np.ascontiguousarray(moved_field)
            p, q = net.predict(moved, moved_field)
            unit = lumen_net.to_unit(p, rgb.shape)
            points.append(lumen_net.unsymmetry(unit, code))
            logits.append(np.log(q / (1 - q)))
        np.testing.assert_allclose(pixel, lumen_net.to_pixel(np.mean(points, axis=0),
                                                             rgb.shape), atol=1e-3)
        assert probability == pytest.approx(1 / (1 + np.exp(-np.mean(logits))), abs=1e-5)


def test_preprocess_removes_exposure_and_keeps_the_field():
    rng = np.random.default_rng(0)
    rgb = rng.integers(20, 120, (256, 256, 3)).astype(np.uint8)
    field = np.zeros((256, 256), bool)
    yy, xx = np.mgrid[:256, :256]
    field[(yy - 127.5) ** 2 + (xx - 127.5) ** 2 < 120 ** 2] = True
    x, inside, cells = lumen_net.preprocess(rgb, field)
    assert x.shape == (64, 64, 4) and cells.shape == (16, 16)
    assert not inside[0, 0] and inside[32, 32] and not cells[0, 0] and cells[8, 8]
    assert np.median(x[..., 0][inside]) == pytest.approx(0.0, abs=1e-6)
    assert np.all(x[..., 0][~inside] == 0.0)
    brighter = np.clip(rgb.astype(np.float64) * 2.0, 0, 255).astype(np.uint8)
    x2, _, _ = lumen_net.preprocess(brighter, field)
    # log(2 I + 6) - median vs log(I + 6) - median: nearly the same where I >> 6.
    assert np.median(np.abs(x2[..., 0] - x[..., 0])[inside]) < 0.05


def test_missing_or_foreign_weights_are_one_line_errors(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        lumen_net.LumenNet.load(tmp_path / "none.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="not the layers"):
        lumen_net.LumenNet.load(tmp_path / "other.npz")
    net = lumen_net.LumenNet(lumen_net.init_weights(np.random.default_rng(1)), {"epochs": 3})
    net.save(tmp_path / "net.npz")
    again = lumen_net.LumenNet.load(tmp_path / "net.npz")
    assert again.info["epochs"] == 3
    for key, value in net.weights.items():
        np.testing.assert_array_equal(again.weights[key], value)
    wider = dict(net.weights, c5_b=np.zeros(32, np.float32))  # another network's layer
    lumen_net.LumenNet(wider, {}).save(tmp_path / "wider.npz")
    with pytest.raises(ValueError, match=r"wider.npz: c5_b is \(32,\), not \(24,\)"):
        lumen_net.LumenNet.load(tmp_path / "wider.npz")


def test_widening_keeps_the_function_and_then_learns_on_the_new_channels():
    """`widen` embeds trained weights in wider layers: the same outputs to rounding, and the
    new channels' weights get gradients (so training can use them)."""
    rng = np.random.default_rng(5)
    narrow = lumen_net.init_weights(rng)
    for key in narrow:
        if key.endswith("_b"):
            narrow[key] = 0.1 * rng.standard_normal(narrow[key].shape).astype(np.float32)
    wide = lumen_net.widen(narrow, (16, 24, 32, 32, 32), rng)
    assert lumen_net.widths_of(wide) == (16, 24, 32, 32, 32)
    x = rng.standard_normal((2, 64, 64, 4)).astype(np.float32)
    cells = np.ones((2, 16, 16), bool)
    cells[1, :, :4] = False
    position, vis, _ = lumen_net.forward(narrow, x, cells)
    position_w, vis_w, _ = lumen_net.forward(wide, x, cells)
    np.testing.assert_allclose(position_w, position, atol=1e-6)
    np.testing.assert_allclose(vis_w, vis, rtol=1e-5, atol=1e-5)
    _, grads, _ = lumen_net.loss_and_gradients(wide, x, cells, np.zeros((2, 2)),
                                               np.array([True, True]))
    assert np.abs(grads["c3_w"][:, 16:]).max() > 0     # the next layer's weights on new ones
    assert np.abs(grads["heat_w"][24:]).max() > 0
    with pytest.raises(ValueError, match="narrower"):
        lumen_net.widen(wide, (12, 16, 24, 24, 24), rng)
# --- the shipped weights ------------------------------------------------------------------

RADIUS = 0.025


@pytest.fixture(scope="module")
def fisheye_tube():
    tube = straight_tube(0.6, RADIUS, rings=121, around=256, start=-0.3)
    return RayCaster(tube, LensConfig(), far=0.2)


@pytest.mark.parametrize("angle", [0.0, 20.0, 35.0])
def test_shipped_network_finds_the_far_region_of_a_straight_tube(fisheye_tube, angle):
    """Down a straight tube (a shape it was not trained on: its colons bend and fold), lit
    as the ray caster's default, the network's answer lies within 4 % of the diagonal of
    the truth's far region, which has a closed form here
    (test_lumen_robust.test_far_region_of_a_straight_tube_is_the_cone_around_its_axis)."""
    caster = fisheye_tube
    X_WC = RigidTransform(RotationMatrix.MakeYRotation(np.radians(angle)), [0.0, 0.0, 0.0])
    hits = caster.cast(X_WC)
    truth = far_region(caster.range_image(hits), caster.field, caster.far,
                       lens=caster.lens)
    assert truth.visible
    rgb = caster.shade(hits, Shading())
    detection = load_detector("net")(rgb, caster.field)
    assert detection.visible
    diagonal = np.hypot(*rgb.shape[:2])
    assert np.linalg.norm(detection.pixel - truth.pixel) / diagonal < 0.04


def test_shipped_network_sees_no_lumen_facing_the_wall(fisheye_tube):
    caster = fisheye_tube
    X_WC = RigidTransform(RotationMatrix.MakeYRotation(np.radians(90.0)), [0.0, 0.0, 0.0])
    hits = caster.cast(X_WC)
    assert not far_region(caster.range_image(hits), caster.field, caster.far,
                          lens=caster.lens).visible
    detection = load_detector("net")(caster.shade(hits, Shading()), caster.field)
    assert not detection.visible and np.all(np.isnan(detection.pixel))


def test_shipped_network_was_trained_away_from_every_reported_seed():
    """The weights record the colon seeds they were trained and validated on: none of the
    seeds eval-lumen reports (100-104) or the in-loop acceptance drives (0-19)."""
    info = lumen_net.LumenNet.load().info
    used = set(parse_seeds(info["train_seeds"])) | set(parse_seeds(info["valid_seeds"]))
    assert used and not used & (set(range(100, 105)) | set(range(0, 20)))


def test_operating_point_is_the_lowest_threshold_within_every_sources_budget():
    """Against a scan of every candidate threshold (each logit, and just above it)."""
    rng = np.random.default_rng(3)
    for trial in range(20):
        n = int(rng.integers(20, 200))
        sources = rng.choice(["a", "b", "c"], n)
        visible = rng.random(n) < 0.6
        logits = np.round(rng.normal(size=n) + 2.0 * visible, 1)  # ties on purpose
        budget = float(rng.choice([0.0, 0.05, 0.1, 0.3]))
        threshold, rates = lumen_net.operating_point(logits, visible, sources, budget)

        def within(t):
            return all(np.mean(logits[(sources == s) & ~visible] >= t) <= budget
                       for s in np.unique(sources) if ((sources == s) & ~visible).any())
        candidates = np.sort(np.concatenate([logits, np.nextafter(logits, np.inf)]))
        lowest = next(t for t in candidates if within(t))
        assert within(threshold)
        assert threshold <= lowest
        # nothing lies between the scan's answer and ours
        assert not ((logits >= threshold) & (logits < lowest)).any()
        for s, (detection, false_pos) in rates.items():
            assert detection == pytest.approx(np.mean(logits[(sources == s) & visible]
                                                      >= threshold))
            assert not false_pos > budget  # NaN: no frame without a lumen
