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
Prints both per pair, their medians and the run's share of the bench's factor. Then, in this
process and in CPU time (so that other load on the machine weighs on every variant alike),
what each part of the loop costs, variant by variant, interleaved `--pairs` times over the
same `sim-seconds` after one second of settling:
  - station: the station alone on a bare Simulator (bench_realtime's measurement);
  - + guard, monitor: `Run` without loggers or signal watch (the contact monitor and the run
    guard beside the station, scenario.simulator applied);
  - + loggers: the three loggers every run has (capsule state, contact load, EPM pose);
  - + signal watch: the simulator's per-step monitor that notices a Ctrl-C;
  - + chunks: `simulate`'s stepping, 200 chunks a run, each drained into the spool.
"""

import argparse
import json
import time
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

from capsule_drake.app.log_spool import LogSpool
from capsule_drake.app.run import Run, simulator_for
from capsule_drake.app.signals import DeferredSignals
from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station


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


def loop_breakdown(scenario_name: str, sim_seconds: float, pairs: int) -> dict:
    """CPU-time real-time factors of the loop's variants (module docstring)."""
    scenario = load_scenario(name=scenario_name,
                             override=f"{{duration: {1.0 + sim_seconds!r}}}")
    end = 1.0 + sim_seconds

    def station_alone():
        simulator = simulator_for(make_station(scenario))
        simulator.Initialize()
        simulator.AdvanceTo(1.0)
        start = time.process_time()
        simulator.AdvanceTo(end)
        return sim_seconds / (time.process_time() - start)

    def run(log: bool, signals: bool, chunks: bool):
        with Run(scenario, log=log, signals=DeferredSignals() if signals else None) as loop:
            spool = LogSpool(None)

            def drain():
                if log:
                    spool.add(loop.drain(), loop.time)
            loop.initialize()
            loop.advance_to(1.0)
            drain()
            chunk = max(scenario.duration / 200.0, 0.05)
            start = time.process_time()
            if chunks:
                t = 1.0
                while t < end - 1e-9:
                    t = min(t + chunk, end)
                    loop.advance_to(t)
                    drain()
            else:
                loop.advance_to(end)
            return sim_seconds / (time.process_time() - start)

    variants = {"station": station_alone,
                "+ guard, monitor": lambda: run(False, False, False),
                "+ loggers": lambda: run(True, False, False),
                "+ signal watch": lambda: run(True, True, False),
                "+ chunks": lambda: run(True, True, True)}
    factors = {name: [] for name in variants}
    for _ in range(pairs):
        for name, variant in variants.items():
            factors[name].append(variant())
    return factors


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
    print("the loop's parts, CPU-time real-time factors (median; runs):")
    factors = loop_breakdown(args.scenario, args.sim_seconds, args.pairs)
    base = statistics.median(factors["station"])
    for name, values in factors.items():
        median = statistics.median(values)
        print(f"  {name:<18} x{median:.2f} ({100.0 * median / base:5.1f} %; "
              f"{', '.join(f'{x:.2f}' for x in values)})")


if __name__ == "__main__":
    main()
