"""What the run loop adds to the diagram's own stepping: `capsule-sim run --no-recording`
against `bench_realtime.py`'s real-time factor of the same scenario, back to back.

    .venv/bin/python benchmarks/bench_run_loop.py [--scenario Default] [--sim-seconds 20]
        [--pairs 3]

Each pair runs, one after the other, in processes of their own and with the allocator
setting the launchers use (bench_realtime.ALLOCATOR unless GLIBC_TUNABLES is set):
  - bench_realtime.py's measurement: the station alone (make_station), a bare Simulator,
    `sim-seconds` after one second of settling;
  - the command `capsule-sim run --scenario S --duration 1+sim-seconds --no-recording
    --quiet`: the whole run loop (the settled start if any, the contact monitor and the run
    guard, the loggers and their spool, the signal watch, progress, metrics), its
    real-time factor from the run's own metrics.json (`sim_time_s / wall_time_s`, from the
    first step to the last, the first second included).
Prints both per pair, their medians and the run's share of the bench's factor.
"""

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))
from bench_realtime import ALLOCATOR, cpu_name  # noqa: E402


def bench_factor(scenario: str, sim_seconds: float, env) -> float:
    done = subprocess.run([sys.executable, str(HERE / "bench_realtime.py"), "--one", scenario,
                           "--sim-seconds", str(sim_seconds), "--repeats", "1"],
                          capture_output=True, text=True, env=env, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])["factors"][0]


def run_factor(scenario: str, sim_seconds: float, env) -> float:
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "run"
        subprocess.run([sys.executable, "-m", "capsule_drake.app", "run", "--scenario",
                        scenario, "--duration", str(1.0 + sim_seconds), "--no-recording",
                        "--quiet", "--out", str(out)],
                       capture_output=True, text=True, env=env, check=True, cwd=REPO)
        metrics = json.loads((out / "metrics.json").read_text())
    return metrics["sim_time_s"] / metrics["wall_time_s"]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="Default")
    parser.add_argument("--sim-seconds", type=float, default=20.0)
    parser.add_argument("--pairs", type=int, default=3)
    args = parser.parse_args()
    env = dict(os.environ)
    env.setdefault("GLIBC_TUNABLES", ALLOCATOR)
    print(f"machine: {platform.machine()}, {cpu_name()}, Python {platform.python_version()}, "
          f"{os.cpu_count()} cores; {args.scenario}, {args.sim_seconds:g} s; "
          f"GLIBC_TUNABLES={env['GLIBC_TUNABLES']}")
    bench, run = [], []
    for k in range(args.pairs):
        bench.append(bench_factor(args.scenario, args.sim_seconds, env))
        run.append(run_factor(args.scenario, args.sim_seconds, env))
        print(f"pair {k + 1}: bench_realtime x{bench[-1]:.2f}, capsule-sim run x{run[-1]:.2f}",
              flush=True)
    b, r = statistics.median(bench), statistics.median(run)
    print(f"median: bench_realtime x{b:.2f}, capsule-sim run x{r:.2f}: the run at "
          f"{100.0 * r / b:.1f} % of the bench's real-time factor")


if __name__ == "__main__":
    main()
