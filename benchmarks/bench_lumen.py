"""Milliseconds per 256 px frame of the lumen detectors, on rendered colon frames.

    python benchmarks/bench_lumen.py [--frames 30] [--repeats 20]

Renders `--frames` frames (seeded, two random colons, a quarter facing the wall), then times
each detector on each frame `--repeats` times; prints the median and 90th percentile over
frames of the per-frame medians.
"""

import argparse
import os
import time

import numpy as np

from capsule_drake.perception.evaluation import sample_frames
from capsule_drake.perception.lumen import load_detector


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    frames = sample_frames(args.frames, colons=2, seed=7)
    print(f"load average before: {os.getloadavg()[0]:.2f} (2 cores)")
    print(f"{'detector':10s} {'median ms':>9s} {'p90 ms':>7s}  ({len(frames)} frames of "
          f"{frames[0].rgb.shape[1]} x {frames[0].rgb.shape[0]} px)")
    for name in ("gaussian", "median"):
        detector = load_detector(name)
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
