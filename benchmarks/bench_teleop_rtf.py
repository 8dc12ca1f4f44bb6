"""Real-time factor of the full teleoperation diagram.

    .venv/bin/python benchmarks/bench_teleop_rtf.py [--fps 15 5] [--sim-seconds 5] [--repeats 3]

The `Teleop` scenario as a person would drive it: physics, the EPM on the arm, the 256 px
fisheye camera at the given frame rates (its frames 50 ms late, drawn on the second core by
the render worker; depth drawn only when read, and nothing reads it here), the lumen
tracker, the pseudo-force, and the haptic loop at 1 kHz (device, force feedback, mapping),
with the simulated operator standing in for the person's hand (it costs what a browser or
UDP device would). No Meshcat. `--latency 0` times the camera drawing in step instead. Prints, per frame rate, the median real-time factor over
repeats (each a fresh simulation warmed up for 1 s), and the wall time per simulated second.
Target: at least 1x with the camera at 15 frames/s.
"""

import argparse
import platform
import statistics
import time

from pydrake.systems.analysis import Simulator

from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station


def machine_reference_ms(calls: int = 20000) -> float:
    """Wall time (ms) of a fixed piece of the 1 kHz loop's kind of Python (dipole pair
    forces): this VM's speed drifts by tens of percent over minutes, so each real-time
    factor is printed beside it (26-50 ms when the figures of docs/results/performance.md,
    "Teleoperation", were taken)."""
    from capsule_drake.physics.magnetics import dipole_pair_interaction_float
    start = time.perf_counter()
    for k in range(calls):
        dipole_pair_interaction_float((0.0, 0.0, 1.0), (0.1, 0.0, 0.0), (0.0, 0.01 * k, 0.1))
    return 1000.0 * (time.perf_counter() - start)


def real_time_factor(fps: float, sim_seconds: float, latency: float | None = None,
                     warm_up: float = 1.0) -> float:
    scenario = load_scenario(name="Teleop", override=f"{{capsule: {{camera: {{fps: {fps}}}}}}}")
    if latency is not None:
        scenario.capsule.camera.latency = latency
    diagram = make_station(scenario)
    camera = diagram.GetSubsystemByName("capsule.camera")
    if camera.worker is not None:  # started with the build; steady state is what we time
        camera.worker.wait_until_ready()
    simulator = Simulator(diagram)
    simulator.Initialize()
    simulator.AdvanceTo(warm_up)
    start = time.perf_counter()
    simulator.AdvanceTo(warm_up + sim_seconds)
    return sim_seconds / (time.perf_counter() - start)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fps", type=float, nargs="+", default=[15.0, 5.0])
    parser.add_argument("--sim-seconds", type=float, default=5.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--latency", type=float, default=None,
                        help="camera latency (s); default: the scenario's")
    args = parser.parse_args()
    print(f"Teleop diagram, {platform.processor() or platform.machine()}, "
          f"{args.repeats} x {args.sim_seconds:.0f} s simulated per frame rate")
    for fps in args.fps:
        factors, references = [], []
        for _ in range(args.repeats):
            references.append(machine_reference_ms())
            factors.append(real_time_factor(fps, args.sim_seconds, args.latency))
        median = statistics.median(factors)
        print(f"camera {fps:4.0f} fps: real-time factor {median:.2f} "
              f"(runs {min(factors):.2f}-{max(factors):.2f}), "
              f"{1.0 / median:.2f} s per simulated second; machine reference "
              f"{statistics.median(references):.0f} ms "
              f"({min(references):.0f}-{max(references):.0f})")


if __name__ == "__main__":
    main()
