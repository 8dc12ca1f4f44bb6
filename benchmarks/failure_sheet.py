"""Contact sheet of a benchmark run's camera frames around where it stopped advancing.

    .venv/bin/python benchmarks/failure_sheet.py --navigator autonomy-truth --seed 1014 \
        [--tier population] [--scenario-text YAML] [--out docs/failure_1014.png]

Reruns one task of `capsule-sim benchmark` exactly as the suite does (`benchmark.task_scenario`:
the navigator's scenario, the tier's YAML, the seed), keeping a camera frame every `--every`
simulated seconds. The run stops at the cecum, at `--duration`, or once the capsule has not
advanced `benchmark.STALL_ADVANCE` past its furthest point for `--stalled` seconds (the
suite's own test of a stall, with a shorter window so a stuck run ends sooner). The sheet
shows the frames from `--before` seconds before the furthest point was first reached to the
end, each labelled with its time, station and segment; markers: green cross, the centreline
point 5 cm ahead (the `autonomy-truth` follower's target); cyan circle, the image-side truth
(the far region, perception/lumen_truth.py); red cross, the lumen tracker's detection (when
the navigator runs one). A row of text under the sheet says where and how the run ended.
"""

import argparse
from pathlib import Path

import cv2
import numpy as np
from pydrake.systems.framework import EventStatus, LeafSystem, PortDataType

from capsule_drake.anatomy import load_colon
from capsule_drake.app import benchmark
from capsule_drake.app.run import simulate


class FrameKeeper(LeafSystem):
    """Keeps the camera frame and what is known about the lumen every `period` seconds."""

    def __init__(self, station, period: float):
        super().__init__()
        self.kept = []
        self._ports = {}
        for name in ("capsule.camera.rgb_image", "capsule.state", "capsule.lumen.lumen_pixel",
                     "capsule.lumen.lumen_visible", "capsule.lumen.far_pixel",
                     "capsule.lumen.far_visible", "capsule.lumen_tracker.lumen_pixel",
                     "capsule.lumen_tracker.lumen_visible"):
            if station.HasOutputPort(name):
                port = station.GetOutputPort(name)
                if port.get_data_type() == PortDataType.kAbstractValued:
                    self._ports[name] = self.DeclareAbstractInputPort(name, port.Allocate())
                else:
                    self._ports[name] = self.DeclareVectorInputPort(name, port.size())
        self.DeclarePeriodicPublishEvent(period, 0.0, self._keep)

    def connect(self, builder, station):
        for name, port in self._ports.items():
            builder.Connect(station.GetOutputPort(name), port)

    def _keep(self, context):
        got = {name: port.Eval(context) for name, port in self._ports.items()}
        frame = {"t": context.get_time(), "position": np.array(got["capsule.state"][4:7])}
        if "capsule.camera.rgb_image" in got:
            frame["rgb"] = np.array(got["capsule.camera.rgb_image"].data[..., :3])
        for key, pixel, visible in (
                ("truth", "capsule.lumen.lumen_pixel", "capsule.lumen.lumen_visible"),
                ("far", "capsule.lumen.far_pixel", "capsule.lumen.far_visible"),
                ("tracker", "capsule.lumen_tracker.lumen_pixel",
                 "capsule.lumen_tracker.lumen_visible")):
            if pixel in got and got[visible][0] > 0.5:
                frame[key] = np.array(got[pixel])
        self.kept.append(frame)
        return EventStatus.Succeeded()


def run(task: benchmark.Task, every: float, stalled: float):
    """(frames, colon, how the run ended)."""
    scenario = benchmark.task_scenario(task)
    colon, _ = load_colon(scenario.colon)
    length = colon.centerline.length
    keeper, best = [None], {"s": -np.inf, "t": 0.0}

    def extend(builder, station):
        keeper[0] = builder.AddNamedSystem("failure_sheet_frames", FrameKeeper(station, every))
        keeper[0].connect(builder, station)

    def stop_when(station, context):
        state = station.GetOutputPort("capsule.state").Eval(context)
        s, t = float(colon.centerline.closest(state[4:7])[0]), context.get_time()
        if s >= length - benchmark.CECUM_MARGIN:
            return "reached the cecum"
        if s > best["s"] + benchmark.STALL_ADVANCE:
            best.update(s=s, t=t)
        if t - best["t"] >= stalled:
            return (f"stalled: no advance past {100 * best['s']:.1f} cm "
                    f"({colon.centerline.segment_at(best['s'])}) for {stalled:.0f} s")
        return None

    result = simulate(scenario, progress=False, extend=extend, stop_when=stop_when)
    ended = result.metrics.get("stopped_early") or result.metrics.get("stopped_at") \
        or f"time limit ({task.duration:.0f} s)"
    return keeper[0].kept, colon, str(ended), best["t"]


def sheet(frames, colon, title: str, count: int, columns: int = 4) -> np.ndarray:
    tiles = []
    picks = np.unique(np.linspace(0, len(frames) - 1, min(count, len(frames))).round()
                      .astype(int))
    for frame in (frames[k] for k in picks):
        tile = np.ascontiguousarray(frame["rgb"]).copy()
        if "truth" in frame:
            cv2.drawMarker(tile, tuple(int(round(x)) for x in frame["truth"]), (0, 255, 0),
                           cv2.MARKER_CROSS, 18, 2)
        if "far" in frame:
            cv2.circle(tile, tuple(int(round(x)) for x in frame["far"]), 9, (0, 255, 255), 2)
        if "tracker" in frame:
            cv2.drawMarker(tile, tuple(int(round(x)) for x in frame["tracker"]), (255, 40, 40),
                           cv2.MARKER_TILTED_CROSS, 14, 2)
        s = float(colon.centerline.closest(frame["position"])[0])
        cv2.putText(tile, f"t {frame['t']:.0f} s  {100 * s:.1f} cm {colon.centerline.segment_at(s)}",
                    (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    grid = np.vstack([np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)])
    band = np.zeros((28, grid.shape[1], 3), np.uint8)
    cv2.putText(band, title, (6, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                cv2.LINE_AA)
    return np.vstack([grid, band])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--navigator", default="autonomy-truth",
                        help=f"one of {', '.join(benchmark.BUILT_IN)}")
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--tier", choices=sorted(benchmark.TIERS), default="population")
    parser.add_argument("--scenario-text", default="")
    parser.add_argument("--duration", type=float, default=600.0)
    parser.add_argument("--every", type=float, default=1.0, help="s between kept frames")
    parser.add_argument("--stalled", type=float, default=40.0,
                        help="s without advance after which the run stops")
    parser.add_argument("--before", type=float, default=12.0,
                        help="s before the furthest point that the sheet starts")
    parser.add_argument("--count", type=int, default=12, help="frames on the sheet")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.navigator not in benchmark.NAVIGATORS:
        parser.error(f"--navigator {args.navigator}: not one of {', '.join(benchmark.BUILT_IN)}")
    task = benchmark.Task(args.navigator, args.seed, duration=args.duration,
                          scenario_text=args.scenario_text,
                          tier_text=benchmark.TIERS[args.tier][1])
    frames, colon, ended, furthest_t = run(task, args.every, args.stalled)
    frames = [f for f in frames if "rgb" in f and f["t"] >= furthest_t - args.before]
    if not frames:
        print(f"{args.navigator} seed {args.seed}: no camera frames kept ({ended})")
        return 1
    title = f"{args.navigator}, seed {args.seed} ({args.tier}): {ended}"
    print(title)
    after = [f for f in frames if f["t"] >= furthest_t]
    if after:
        print(f"from the furthest point on ({len(after)} frames): the point 5 cm ahead in view "
              f"in {sum('truth' in f for f in after)}, the far region in "
              f"{sum('far' in f for f in after)}, a detection in "
              f"{sum('tracker' in f for f in after)}")
    out = args.out or Path(f"failure_{args.navigator}_{args.seed}.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), cv2.cvtColor(sheet(frames, colon, title, args.count), cv2.COLOR_RGB2BGR))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
