"""Milliseconds per 256 px frame of the lumen detectors, on rendered colon frames.

    python benchmarks/bench_lumen.py [--frames 30] [--repeats 20] [--detector NAME ...]

Renders `--frames` frames (seeded, two random colons, a quarter facing the wall), then times
each detector on each frame `--repeats` times; prints the median and 90th percentile over
frames of the per-frame medians. `net` is timed as the tracker runs it (four symmetries)
and on the frame alone (`net x1`); `net xK` reads K symmetries.
"""

import argparse
import dataclasses
import os
import time

import numpy as np

from capsule_drake.perception.evaluation import sample_frames
from capsule_drake.perception.lumen import LumenParams, load_detector


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--detector", action="append",
                        help="net, 'net xK' (K of the eight symmetries), core, gaussian, median "
                             "(default: all)")
    args = parser.parse_args()
    frames = sample_frames(args.frames, colons=2, seed=7)
    print(f"load average before: {os.getloadavg()[0]:.2f} (2 cores)")
    print(f"{'detector':10s} {'median ms':>9s} {'p90 ms':>7s}  ({len(frames)} frames of "
          f"{frames[0].rgb.shape[1]} x {frames[0].rgb.shape[0]} px)")
    for name in args.detector or ("net", "net x1", "core", "gaussian", "median"):
        params = (dataclasses.replace(LumenParams(), net_symmetries=int(name.split("x")[1]))
                  if name.startswith("net x") else None)
        detector = load_detector(name.split()[0], params)
        per_frame = []
        for frame in frames:
            detector(frame.rgb, frame.field)
            times = []
            for _ in range(args.repeats):
                start = time.perf_counter()
                detector(frame.rgb, frame.field)
                times.append(time.perf_counter() - start)
            per_frame.append(1e3 * np.median(times))
        print(f"{name:10s} {np.median(per_frame):9.2f} {np.percentile(per_frame, 90):7.2f}")


if __name__ == "__main__":
    main()
