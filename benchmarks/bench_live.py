"""Cost of the channel outputs (app/channels.py, app/live/) in a WithSensors run (the Default
drag with its camera and sensors), and whether a paced run with the Foxglove output keeps
real time.

Prints:
  - per output (none, the MCAP file, the Foxglove server with a client subscribed to every
    channel, the ROS 2 topics with a DDS reader on the image, IMU and tf topics): the
    simulation process's CPU seconds per simulated second after the run's first second (the
    build, the scene's encoding and the servers' start are once a run: their cost is in the
    per-message table), waits for the pace not counted; median of interleaved runs; and,
    against the run without outputs, the extra CPU per plant step;
  - inside the runs with outputs: the messages' encoding (once per message, shared by every
    output) and each output's own time per message, by topic group (ms, median and mean);
  - a paced run (simulator.target_realtime_rate 1, as every live run is) with the Foxglove
    output and its client: its real-time factor, the slowest 5 s window's pace, and what it
    said on stderr about keeping up.

The clients run in their own processes (the Foxglove client of tests/foxglove_client under
node, installed with npm the first time; a Cyclone DDS reader in Python), on the same
cores, as a viewer on the same machine would.

Run: python benchmarks/bench_live.py [--seconds 5] [--repeats 3] [--paced-seconds 20]
         [--scenario WithSensors] [--scenario-text YAML]
"""

import argparse
import contextlib
import io
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from pydrake.systems.framework import LeafSystem

from capsule_drake.app import channels
from capsule_drake.app.live import outputs as live_outputs
from capsule_drake.app.run import simulate
from capsule_drake.scenario import load_scenario

ROOT = Path(__file__).resolve().parent.parent
CLIENT = ROOT / "tests" / "foxglove_client"

DDS_READER = """
import sys, time
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from capsule_drake.app.live.dds_types import dds_topic_name, idl_type
from capsule_drake.app.live.ros2_out import participant
dds, keep = participant(int(sys.argv[1]), loopback=True)
types = {"/tf": "tf2_msgs/msg/TFMessage", "/capsule/imu/data": "sensor_msgs/msg/Imu",
         "/capsule/camera/image_raw": "sensor_msgs/msg/Image"}
readers = [DataReader(dds, Topic(dds, dds_topic_name(t), idl_type(n))) for t, n in types.items()]
count, end = 0, time.monotonic() + float(sys.argv[2])
while time.monotonic() < end:
    count += sum(len(r.take(N=100)) for r in readers)
    time.sleep(0.01)
print(count)
"""


WARM = 1.0   # s of simulated time not counted: the build, the scene and the first messages


class _Mark(LeafSystem):
    """Notes the process's CPU time once, at simulated time `at`."""

    def __init__(self, cpu: dict, at: float):
        super().__init__()
        self._cpu = cpu
        self.DeclarePeriodicPublishEvent(1e9, at, self._mark)

    def _mark(self, context):
        self._cpu.setdefault("start", time.process_time())


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _group(topic: str) -> str:
    for prefix, name in (("/capsule/camera", "camera"), ("/capsule/lumen", "lumen"),
                         ("/capsule/imu", "imu"), ("/capsule/magnetometer", "magnetometer"),
                         ("/capsule/contact/wall_pressure", "wall map"), ("/tf", "tf"),
                         ("/capsule/contact", "contact"), ("/scene", "scene")):
        if topic.startswith(prefix):
            return name
    return "other"


@contextlib.contextmanager
def timed_outputs(timings: dict):
    """Times ChannelWriter's encoding and each output's publish, per topic group."""
    write, sinks_of = channels.ChannelWriter.write, live_outputs.channel_sinks

    def timed_write(self, topic, type_name, message, log_time_ns, latched=False):
        start = time.perf_counter()
        write(self, topic, type_name, message, log_time_ns, latched)
        timings.setdefault(("all outputs + encoding", _group(topic)), []).append(
            time.perf_counter() - start)

    def timed_sinks(outputs):
        made = sinks_of(outputs)
        for sink in made:
            publish, label = sink.publish, type(sink).__name__

            def timed(topic, spec, message, data, log_time_ns, publish=publish, label=label):
                start = time.perf_counter()
                publish(topic, spec, message, data, log_time_ns)
                timings.setdefault((label, _group(topic)), []).append(
                    time.perf_counter() - start)
            sink.publish = timed
        return made

    channels.ChannelWriter.write = timed_write
    live_outputs.channel_sinks = timed_sinks
    try:
        yield
    finally:
        channels.ChannelWriter.write, live_outputs.channel_sinks = write, sinks_of


def _foxglove_client(port: int, seconds: float):
    """The node client, started once the server listens; it subscribes to every channel
    and stays until the run ends (it waits for a topic that never comes)."""
    def start():
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.05)
        holder["process"] = subprocess.Popen(
            ["node", str(CLIENT / "client.mjs"), f"ws://127.0.0.1:{port}", str(seconds),
             "/never"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    holder = {}
    thread = threading.Thread(target=start, daemon=True)
    thread.start()
    return thread, holder


def run(name, output: str, seconds: float, timings=None, text: str | None = None):
    """One run with `output` ("none", "mcap", "foxglove", "ros2") on `text` (YAML on
    the named scenario, or None); returns (metrics, CPU s
    of the simulation process per simulated second after its first WARM, stderr text)."""
    cpu = {}
    folder = Path(tempfile.mkdtemp(prefix="bench_live_"))
    client = reader = None
    if output == "mcap":
        extra = f"{{outputs: {{mcap: {{path: {folder / 'run.mcap'}}}}}}}"
    elif output == "foxglove":
        port = _free_port()
        extra = f"{{outputs: {{foxglove: {{port: {port}, wait_for_client: 60}}}}}}"
        client = _foxglove_client(port, 4 * seconds + 120)
    elif output == "ros2":
        domain = 60 + os.getpid() % 100
        extra = f"{{outputs: {{ros2: {{domain_id: {domain}}}}}}}"
        reader = subprocess.Popen([sys.executable, "-c", DDS_READER, str(domain),
                                   str(4 * seconds + 60)], stdout=subprocess.PIPE, text=True,
                                  env=dict(os.environ, PYTHONPATH=str(ROOT)))
        time.sleep(2.0)   # the reader's participant up before the run's writers
    else:
        extra = None
    # A live output paces the run to real time (app/run.py `paced`): the CPU time a run
    # takes does not count the waits.
    scenario = load_scenario(name=name, override=[f"{{duration: {seconds}}}", text, extra])

    def extend(builder, station):
        builder.AddSystem(_Mark(cpu, WARM))
        return lambda: cpu.setdefault("end", time.process_time())

    err = io.StringIO()
    with contextlib.ExitStack() as stack:
        if timings is not None:
            stack.enter_context(timed_outputs(timings))
        stack.enter_context(contextlib.redirect_stderr(err))
        result = simulate(scenario, progress=False, extend=extend)
    if client is not None:
        client[0].join()
        process = client[1].get("process")
        if process is not None:
            process.kill()
            process.wait()
    if reader is not None:
        reader.kill()
        reader.wait()
    shutil.rmtree(folder, ignore_errors=True)
    return result.metrics, (cpu["end"] - cpu["start"]) / (seconds - WARM), err.getvalue()


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="simulated s a run")
    parser.add_argument("--scenario", default="WithSensors", help="named scenario")
    parser.add_argument("--scenario-text", default="", metavar="YAML",
                        help="YAML layered on it, e.g. '{capsule: {camera: {}}}'")
    parser.add_argument("--repeats", type=int, default=3, help="interleaved runs per output")
    parser.add_argument("--paced-seconds", type=float, default=20.0,
                        help="simulated s of the paced Foxglove run (0: none)")
    args = parser.parse_args()
    if shutil.which("node") is None or shutil.which("npm") is None:
        sys.exit("bench_live: node and npm are needed for the Foxglove client")
    if not (CLIENT / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        subprocess.run(["npm", "ci", "--no-audit", "--no-fund", "--silent"], cwd=CLIENT,
                       check=True, timeout=600)
    name = args.scenario
    text = args.scenario_text or None   # layered on every run
    steps_per_s = 1.0 / load_scenario(name=name).plant.time_step
    run(name, "none", WARM + 0.5, text=text)   # warm-up: colon, settling and renderers cached
    outputs = ("none", "mcap", "foxglove", "ros2")
    cpu = {o: [] for o in outputs}
    timings: dict = {}
    for k in range(args.repeats):
        for output in outputs:
            metrics, per_second, err = run(name, output, args.seconds,
                                           timings if k == 0 and output != "none" else None,
                                           text=text)
            cpu[output].append(per_second)
            if "warning" in err:
                print(f"  ({output}: {err.strip().splitlines()[-1]})")
    print(f"{name} {args.scenario_text}, {args.seconds:g} s simulated a run, CPU counted after its first "
          f"{WARM:g} s (the build and the scene are once a run); plant step "
          f"{1e3 / steps_per_s:g} ms; median of {args.repeats} interleaved runs:")
    none = statistics.median(cpu["none"])
    for output in outputs:
        median = statistics.median(cpu[output])
        extra = "" if output == "none" else (
            f"; +{1e6 * (median - none) / steps_per_s:.0f} us CPU per plant step "
            f"(+{100 * (median - none) / none:.0f} %)")
        print(f"  {output:9s} {median:6.3f} CPU s per simulated s "
              f"({', '.join(f'{v:.3f}' for v in cpu[output])}){extra}")
    print("time per message inside the runs (ms; encoding once for all outputs):")
    print(f"  {'':38s}{'n':>6s}{'median':>9s}{'mean':>9s}")
    for (label, group), samples in sorted(timings.items()):
        ms = [1e3 * s for s in samples]
        print(f"  {label + ', ' + group:38s}{len(ms):6d}{statistics.median(ms):9.3f}"
              f"{statistics.fmean(ms):9.3f}")
    if args.paced_seconds > 0:
        paced = "{simulator: {target_realtime_rate: 1.0}}"
        port = _free_port()
        scenario = load_scenario(name=name, override=[
            f"{{duration: {args.paced_seconds}}}", text, paced,
            f"{{outputs: {{foxglove: {{port: {port}, wait_for_client: 60}}}}}}"])
        client = _foxglove_client(port, args.paced_seconds + 180)
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            result = simulate(scenario, progress=False)
        client[0].join()
        if client[1].get("process") is not None:
            client[1]["process"].kill()
        m = result.metrics
        said = [line for line in err.getvalue().splitlines() if "pace" in line]
        print(f"paced run with Foxglove and its client, {args.paced_seconds:g} s: real-time "
              f"factor x{m['real_time_factor']:.3f}, target x{m.get('pace_target', 0):g}, "
              f"slowest 5 s window x{m.get('pace_slowest', float('nan')):.3f}; "
              + ("said: " + " | ".join(said) if said else "said nothing about its pace"))


if __name__ == "__main__":
    main()
