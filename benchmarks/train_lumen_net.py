"""Trains the learned lumen detector (perception/lumen_net.py) on generated frames only, and
writes its weights to models/lumen_net.npz.

    python benchmarks/train_lumen_net.py data     # colon seeds 20-64, 60 poses each
    python benchmarks/train_lumen_net.py train    # 24 epochs; writes models/lumen_net.npz
    python benchmarks/train_lumen_net.py calibrate  # its operating point (0.5) on seeds 60-64

The shipped weights' `cycles` (in their info) say which runs made them: `train`; then, after
`data --seeds 20-64 --light-group spot --raycast-variants 2`, `train --init W --epochs 12
--rate 1e-3 --light-groups spot` and again with `--light-groups spot,spot`; `calibrate` last
(a run goes on from weights before their calibration: `train` does not carry the shift).

Frames: the evaluation's seeded poses (perception/evaluation.py, `seeded_poses`: a quarter
facing the wall) in colon seeds that no reported figure uses (the default 20-59: eval-lumen
reports seeds 100-104, the in-loop acceptance uses 0-19, the hand-made detectors were tuned
on 0-4), each pose through both lenses and both image paths: the ray caster under random
light (`Shading.sample`, every group at once) and the simulator's own renderer, each then
under a random image condition (perception/photometry.py). Labels: the image-side truth
(`far_region` of the frame's own range image): where the far region is and whether a lumen
is in view. The training loss, the optimiser (Adam) and the augmentation (the eight flips
and quarter turns of the square frame, which move the truth with the image) are below;
the validation seeds (default 60-64) choose the epoch kept.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from capsule_drake.app.commands.benchmark import parse_seeds
from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.perception import lumen_net, photometry
from capsule_drake.perception.evaluation import IMAGE_CONDITIONS, _vtk_renderer, seeded_poses
from capsule_drake.perception.lens import LensConfig
from capsule_drake.perception.lumen_truth import far_region
from capsule_drake.perception.raycast import SHADING_GROUPS, RayCaster, Shading

LENSES = {"fisheye": "equidistant", "pinhole": "pinhole_radtan"}
SOURCE_NAMES = ("raycast fisheye", "raycast pinhole", "vtk fisheye", "vtk pinhole")
"""The frames' `source` codes: 2 x (simulator's renderer) + (pinhole)."""


def generate(seeds, poses_per_colon, raycast_variants, vtk_variants, out: Path, log=print,
             light_group=None):
    """Writes one .npz of frames per group of five colon seeds. `light_group` (a key of
    raycast.SHADING_GROUPS): the ray caster's light varies in that group alone (the rest
    at its defaults) rather than in all of them at once, and no frame of the simulator's
    renderer is made (vtk_variants is then ignored); the files are named after it."""
    out.mkdir(parents=True, exist_ok=True)
    groups = [seeds[i:i + 5] for i in range(0, len(seeds), 5)]
    for group in groups:
        suffix = f"_{light_group}" if light_group else ""
        path = out / f"frames_{group[0]}-{group[-1]}{suffix}.npz"
        if path.exists():
            continue
        started = time.time()
        rows = {key: [] for key in ("log", "inside", "cells", "target", "visible", "source")}
        configs = {lens: CameraConfig(lens=LensConfig(model=model))
                   for lens, model in LENSES.items()}
        rng = np.random.default_rng([group[0], 7] + ([sorted(SHADING_GROUPS).index(
            light_group) + 1] if light_group else []))
        for colon_params, colon, poses in seeded_poses(poses_per_colon * len(group),
                                                       len(group), group[0]):
            for lens, config in configs.items():
                caster = RayCaster(colon.visual_mesh(), config.lens, far=config.far)
                render = None if light_group else _vtk_renderer(colon_params, config)
                for kind, X_WC, _ in poses:
                    hits = caster.cast(X_WC)
                    depth = caster.range_image(hits)
                    images = []
                    far = far_region(depth, caster.field, config.far,
                                     lens=caster.lens)
                    for _ in range(raycast_variants):
                        rgb = caster.shade(hits, Shading.sample(rng, light_group))
                        images.append((0, rgb, caster.field, far))
                    if not light_group:
                        rgb, depth_vtk, lens_vtk, field = render(X_WC)
                        far_vtk = far_region(depth_vtk, field, config.far, lens=lens_vtk)
                        for _ in range(vtk_variants):
                            images.append((1, rgb, field, far_vtk))
                    for source, rgb, field, truth in images:
                        condition = IMAGE_CONDITIONS[rng.integers(len(IMAGE_CONDITIONS))]
                        image = photometry.apply(condition, rgb, field, rng)
                        x, inside, cells = lumen_net.preprocess(image, field)
                        rows["log"].append(x[..., 0].astype(np.float16))
                        rows["inside"].append(inside)
                        rows["cells"].append(cells)
                        rows["target"].append(lumen_net.to_unit(truth.pixel, image.shape)
                                              if truth.visible else np.zeros(2))
                        rows["visible"].append(bool(truth.visible))
                        rows["source"].append(source * 2 + (lens == "pinhole"))
        np.savez_compressed(path, **{key: np.asarray(value) for key, value in rows.items()})
        log(f"{path.name}: {len(rows['log'])} frames, {np.mean(rows['visible']):.0%} with a "
            f"lumen in view, {time.time() - started:.0f} s")


def load(paths):
    parts = [np.load(path) for path in paths]
    data = {key: np.concatenate([part[key] for part in parts]) for key in parts[0].files}
    return data


def batch_input(data, index, turn=None):
    """Network input for frames `index`, with flip/turn code 0-7 per frame (None: none)."""
    n = lumen_net.INPUT_SIZE
    log = data["log"][index].astype(np.float32)
    inside = data["inside"][index]
    cells = data["cells"][index]
    target = data["target"][index].astype(np.float32).copy()
    if turn is not None:
        for i, code in enumerate(turn):
            log[i], inside[i], cells[i], target[i] = lumen_net.symmetry(
                (log[i], inside[i], cells[i]), target[i], code)
    x = np.zeros((len(index), n, n, 4), np.float32)
    x[..., 0] = log
    x[..., 1] = inside
    coords = (np.arange(n, dtype=np.float32) + 0.5) / n * 2.0 - 1.0
    x[..., 2] = coords[None, :]
    x[..., 3] = coords[:, None]
    return x, cells, target, data["visible"][index]


def evaluate(weights, data, batch=256):
    """Median and 90th-percentile error (% of the diagonal, in view and detected at 0.5),
    detection rate and false-positive rate, per source."""
    out = {}
    errors, probs = [], []
    for start in range(0, len(data["log"]), batch):
        index = np.arange(start, min(start + batch, len(data["log"])))
        x, cells, target, visible = batch_input(data, index)
        position, vis, _ = lumen_net.forward(weights, x, cells)
        errors.append(np.linalg.norm(position - target, axis=1) / (2 * np.sqrt(2)))
        probs.append(1 / (1 + np.exp(-vis)))
    errors, probs = np.concatenate(errors), np.concatenate(probs)
    visible = data["visible"]
    for code, name in enumerate(SOURCE_NAMES):
        sel = data["source"] == code
        hit = sel & visible & (probs >= 0.5)
        out[name] = (100 * np.median(errors[hit]), 100 * np.percentile(errors[hit], 90),
                     100 * np.mean(probs[sel & visible] >= 0.5),
                     100 * np.mean(probs[sel & ~visible] >= 0.5))
    return out


def visible_logits(weights, data, symmetries=1, batch=256):
    """The visible logit of every frame, averaged over the first `symmetries` of the
    square's eight as the detector reads a frame (LumenNet.predict)."""
    out = []
    for start in range(0, len(data["log"]), batch):
        index = np.arange(start, min(start + batch, len(data["log"])))
        total = 0.0
        for code in range(symmetries):
            x, cells, _, _ = batch_input(data, index, np.full(len(index), code))
            total = total + lumen_net.forward(weights, x, cells)[1]
        out.append(total / symmetries)
    return np.concatenate(out)


def train(data, valid, epochs, batch, rate, seed, log=print, start=None,
          widths=lumen_net.WIDTHS):
    """Adam on a cosine schedule from `rate`, from He-initialised weights of `widths` or
    from `start` (weights to go on from, widened to `widths` if narrower); returns the
    weights of the epoch whose worst validation p90 was lowest."""
    rng = np.random.default_rng(seed)
    weights = lumen_net.init_weights(rng, widths)
    if start is not None:
        weights = lumen_net.widen(start, widths, rng)
    moments = {key: (np.zeros_like(w), np.zeros_like(w)) for key, w in weights.items()}
    beta1, beta2, step = 0.9, 0.999, 0
    best, best_score = None, np.inf
    count = len(data["log"])
    for epoch in range(epochs):
        started = time.time()
        order = rng.permutation(count)
        lr = rate * 0.5 * (1 + np.cos(np.pi * epoch / epochs))
        total = []
        for start in range(0, count - batch + 1, batch):
            index = order[start:start + batch]
            x, cells, target, visible = batch_input(data, index, rng.integers(0, 8, batch))
            loss, grads, _ = lumen_net.loss_and_gradients(weights, x, cells, target, visible)
            total.append(loss)
            step += 1
            for key, g in grads.items():
                m, v = moments[key]
                m *= beta1
                m += (1 - beta1) * g
                v *= beta2
                v += (1 - beta2) * g * g
                weights[key] -= (lr * (m / (1 - beta1 ** step))
                                 / (np.sqrt(v / (1 - beta2 ** step)) + 1e-8)).astype(np.float32)
        scores = evaluate(weights, valid)
        worst = max(s[1] for s in scores.values())
        log(f"epoch {epoch + 1}/{epochs}: loss {np.mean(total):.4f}, {time.time() - started:.0f} s; "
            + "; ".join(f"{name} {s[0]:.1f}/{s[1]:.1f}/{s[2]:.0f}/{s[3]:.0f}"
                        for name, s in scores.items()))
        if worst < best_score:
            best_score, best = worst, {key: w.copy() for key, w in weights.items()}
    return best


def calibrate(args, files) -> int:
    """Moves the network's visible bias so that its probability 0.5 (the detector's default
    min_confidence) sits at `lumen_net.operating_point` on the validation frames, read as the
    detector reads them; the shift and the rates it gives are kept in the weights' info."""
    if not 0.0 <= args.false_positives < 1.0:
        raise SystemExit("train_lumen_net: --false-positives must be in [0, 1)")
    try:
        net = lumen_net.LumenNet.load(args.weights)
    except ValueError as e:
        raise SystemExit(f"train_lumen_net: --weights: {e}")
    if str(net.info.get("valid_seeds")) != args.valid_seeds:
        print(f"train_lumen_net: note: {args.weights} chose its epoch on seeds "
              f"{net.info.get('valid_seeds')}, calibrating on {args.valid_seeds}")
    groups = [g for g in args.light_groups.split(",") if g]
    data = load(files(args.valid_seeds))
    logits = [visible_logits(net.weights, data, args.symmetries)]
    visible, sources = [data["visible"]], [np.array(SOURCE_NAMES)[data["source"]]]
    for group in groups:
        part = load(files(args.valid_seeds, (group,)))
        logits.append(visible_logits(net.weights, part, args.symmetries))
        visible.append(part["visible"])
        sources.append(np.array([f"{SOURCE_NAMES[c]} ({group} light)" for c in part["source"]]))
    logits, visible, sources = (np.concatenate(v) for v in (logits, visible, sources))
    earlier = float(net.info.get("visible_shift", 0.0))
    threshold, rates = lumen_net.operating_point(logits, visible, sources, args.false_positives)
    for source, (detection, false_pos) in rates.items():
        print(f"{source:34s} detected {100 * detection:5.1f} %  false positives "
              f"{100 * false_pos:4.1f} %")
    net.weights["vis_b"] = (net.weights["vis_b"] - np.float32(threshold)).astype(np.float32)
    net.info.update({
        "visible_shift": earlier - threshold,
        "operating_point": f"at most {100 * args.false_positives:g} % false positives per "
                           f"source on seeds {args.valid_seeds} ({', '.join(['all'] + groups)} "
                           f"light), {args.symmetries} symmetries",
    })
    out = args.out or args.weights
    net.save(out)
    print(f"logit threshold {threshold:+.3f} (probability {1 / (1 + np.exp(-threshold)):.3f}) "
          f"moved to 0.5; wrote {out}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    data = sub.add_parser("data", help="generate training frames")
    data.add_argument("--seeds", default="20-64")
    data.add_argument("--poses", type=int, default=60, help="poses per colon")
    data.add_argument("--raycast-variants", type=int, default=3)
    data.add_argument("--vtk-variants", type=int, default=2)
    data.add_argument("--out", type=Path, default=Path("runs/lumen_net_data"))
    data.add_argument("--light-group", choices=sorted(SHADING_GROUPS), default=None,
                      help="ray-caster frames with this group of its light alone varied "
                           "(files frames_A-B_<group>.npz)")
    fit = sub.add_parser("train", help="train on generated frames")
    fit.add_argument("--data", type=Path, default=Path("runs/lumen_net_data"))
    fit.add_argument("--train-seeds", default="20-59")
    fit.add_argument("--valid-seeds", default="60-64")
    fit.add_argument("--epochs", type=int, default=24)
    fit.add_argument("--batch", type=int, default=32)
    fit.add_argument("--rate", type=float, default=2e-3)
    fit.add_argument("--seed", type=int, default=0)
    fit.add_argument("--out", type=Path, default=lumen_net.DEFAULT_WEIGHTS)
    fit.add_argument("--widths", default=",".join(map(str, lumen_net.WIDTHS)),
                     help="the layers' widths (comma-separated, one per layer)")
    fit.add_argument("--light-groups", default="",
                     help="comma-separated light groups whose frames (made by 'data "
                          "--light-group') join the training seeds' frames")
    fit.add_argument("--init", type=Path, default=None,
                     help="go on training these weights (a second cosine cycle)")
    cal = sub.add_parser("calibrate", help="set the detector's operating point on the "
                         "validation seeds' frames")
    cal.add_argument("--weights", type=Path, default=lumen_net.DEFAULT_WEIGHTS)
    cal.add_argument("--data", type=Path, default=Path("runs/lumen_net_data"))
    cal.add_argument("--valid-seeds", default="60-64")
    cal.add_argument("--light-groups", default="spot",
                     help="comma-separated light groups whose validation frames (made by "
                          "'data --light-group') count as sources of their own")
    cal.add_argument("--false-positives", type=float, default=0.05,
                     help="the most of any source's frames without a lumen in view that may "
                          "be called visible (default 0.05)")
    cal.add_argument("--symmetries", type=int, default=4,
                     help="symmetries averaged, as the detector reads a frame (default 4)")
    cal.add_argument("--out", type=Path, default=None, help="default: --weights, rewritten")
    args = parser.parse_args(argv)
    if args.command == "data":
        generate(parse_seeds(args.seeds), args.poses, args.raycast_variants, args.vtk_variants,
                 args.out, light_group=args.light_group)
        return 0

    def files(text, groups=("",)):
        seeds = parse_seeds(text)
        paths = [args.data / f"frames_{s}-{s + 4}{'_' + g if g else ''}.npz"
                 for g in groups for s in seeds[::5]]
        missing = [str(p) for p in paths if not p.exists()]
        if missing:
            raise SystemExit(f"train_lumen_net: no frames at {', '.join(missing)}; run 'data' first")
        return paths

    if args.command == "calibrate":
        return calibrate(args, files)
    try:
        widths = tuple(int(w) for w in args.widths.split(","))
        if len(widths) != len(lumen_net.LAYERS) or min(widths) < 1:
            raise ValueError
    except ValueError:
        raise SystemExit(f"train_lumen_net: --widths {args.widths}: give "
                         f"{len(lumen_net.LAYERS)} positive integers")
    start, before = None, []
    if args.init is not None:
        try:
            first = lumen_net.LumenNet.load(args.init)
        except ValueError as e:
            raise SystemExit(f"train_lumen_net: --init: {e}")
        start = first.weights
        before = [str(x) for x in np.atleast_1d(first.info.get("cycles", first.info.get(
            "epochs", "?")))]
        for key in ("train_seeds", "valid_seeds"):
            if str(first.info.get(key)) != getattr(args, key):
                raise SystemExit(f"train_lumen_net: --init {args.init} was trained with "
                                 f"{key} {first.info.get(key)}, not {getattr(args, key)}")
    groups = ("",) + tuple(g for g in args.light_groups.split(",") if g)
    weights = train(load(files(args.train_seeds, groups)), load(files(args.valid_seeds)),
                    args.epochs,
                    args.batch, args.rate, args.seed, start=start, widths=widths)
    info = {"train_seeds": args.train_seeds, "valid_seeds": args.valid_seeds,
            "epochs": args.epochs, "widths": ",".join(map(str, widths)),
            "cycles": " ".join(before + [f"{args.epochs}@{args.rate:g}"
                                         + (f"+{args.light_groups}" if args.light_groups
                                            else "")])}
    lumen_net.LumenNet(weights, info).save(args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
