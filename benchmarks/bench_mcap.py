"""Cost of the MCAP logger (app/mcap_log.py) in a WithSensors run.

Prints:
  - the logger's time per event inside a simulation, by stream: per camera frame (colour,
    depth, two CameraInfo, lumen truth and tracker), per IMU sample, per magnetometer sample,
    per pose sample (/tf and the contact wrench); "write" is the messages' encoding and
    writing (compression included when a chunk fills), "event" adds reading the input ports
    (the depth image is drawn on demand: a frame's depth render counts here when nothing
    else asked for it); medians and means in milliseconds; and the time to finish the file;
  - the real-time factor of the run with and without --mcap (median of interleaved runs),
    and the process's CPU seconds per simulated second (from the diagram's build to the end
    of the run; steadier than the wall clock on a shared machine);
  - the file's size per simulated second.

Run: python benchmarks/bench_mcap.py [--seconds 3] [--repeats 5] [--compression zstd]
         [--scenario-text YAML]   (e.g. '{capsule: {camera: {render_depth: false}}}')
"""

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from capsule_drake.app.mcap_log import add_mcap_logger
from capsule_drake.app.run import simulate
from capsule_drake.scenario import load_scenario


def run(scenario, path=None, compression="zstd", timings=None):
    """simulate() with (path given) or without the logger; with `timings`, each stream's
    write and each event is timed into it. Returns (result, CPU seconds from the build of
    the diagram to the end of the run)."""
    cpu = {}

    def extend(builder, station):
        cpu["start"] = time.process_time()
        if path is None:
            return lambda: cpu.setdefault("end", time.process_time())
        logger = add_mcap_logger(builder, station, scenario, path, compression)
        if timings is None:
            def close():
                logger.close()
                cpu["end"] = time.process_time()
            return close
        for stream in logger._streams:
            write = stream.write

            def timed_write(log, t, values, write=write, stream=stream):
                start = time.perf_counter()
                write(log, t, values)
                timings.setdefault((type(stream).__name__, "write"), []).append(
                    time.perf_counter() - start)
            stream.write = timed_write
        on_event = logger._on_event

        def timed_event(context, stream):
            frames = getattr(stream, "frames", None)
            start = time.perf_counter()
            status = on_event(context, stream)
            if frames is None or stream.frames > frames:  # camera: only events with a frame
                timings.setdefault((type(stream).__name__, "event"), []).append(
                    time.perf_counter() - start)
            return status
        logger._on_event = timed_event

        def close():
            start = time.perf_counter()
            logger.close()
            timings[("file", "close")] = [time.perf_counter() - start]
            cpu["end"] = time.process_time()
        return close

    result = simulate(scenario, progress=False, extend=extend)
    return result, cpu["end"] - cpu["start"]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="simulated seconds a run")
    parser.add_argument("--repeats", type=int, default=5, help="runs with and without")
    parser.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd")
    parser.add_argument("--scenario-text", default="", metavar="YAML",
                        help="YAML layered on WithSensors")
    args = parser.parse_args()
    scenario = load_scenario(name="WithSensors", override=[f"{{duration: {args.seconds}}}",
                                                           args.scenario_text or None])
    folder = Path(tempfile.mkdtemp(prefix="bench_mcap_"))
    path = folder / "run.mcap"

    run(scenario)  # warm-up: colon, settling and renderers cached
    timings = {}
    run(scenario, path, args.compression, timings)
    size = os.path.getsize(path)
    labels = {"_CameraStream": "camera frame", "_ImuStream": "IMU sample",
              "_FieldStream": "magnetometer sample", "_PosesStream": "pose sample (tf, wrench)",
              "file": "finishing the file"}
    print(f"MCAP logger in WithSensors, {args.seconds:g} s simulated, compression "
          f"{args.compression} (ms):")
    print(f"  {'':28s}{'n':>6s}{'median':>9s}{'mean':>9s}")
    for (name, kind), samples in sorted(timings.items()):
        ms = [1e3 * s for s in samples]
        print(f"  {labels.get(name, name) + ', ' + kind:28s}{len(ms):6d}"
              f"{statistics.median(ms):9.3f}{statistics.fmean(ms):9.3f}")
    print(f"  file: {size / 1e6:.2f} MB, {size / 1e6 / args.seconds:.2f} MB per simulated s")

    factors = {"without": [], "with --mcap": []}
    cpu = {"without": [], "with --mcap": []}
    for _ in range(args.repeats):
        for label, target in (("without", None), ("with --mcap", path)):
            if target is not None:
                target.unlink(missing_ok=True)
            result, seconds = run(scenario, target, args.compression)
            factors[label].append(result.metrics["real_time_factor"])
            cpu[label].append(seconds / result.metrics["sim_time_s"])
    print(f"median of {args.repeats} interleaved runs:")
    for label, values in factors.items():
        print(f"  {label:12s} real-time factor x{statistics.median(values):.3f} "
              f"({', '.join(f'{v:.3f}' for v in values)}); "
              f"CPU {statistics.median(cpu[label]):.3f} s per simulated s")
    path.unlink(missing_ok=True)
    folder.rmdir()


if __name__ == "__main__":
    main()
