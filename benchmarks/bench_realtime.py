"""Real-time factor of the default scenario and what the 1 ms step spends its time on.

    .venv/bin/python benchmarks/bench_realtime.py [--sim-seconds 10] [--repeats 3]

Physics and magnet only (no rendering, no Meshcat), full-length colon, 1 ms step.
Prints the median real-time factor over repeats, then a breakdown of one step measured
component by component on a context where the capsule touches the wall:
  - the hydroelastic contact query (SceneGraph ComputeContactSurfaces),
  - the MagneticForce system (Python), evaluated with its cache invalidated,
  - the rest of the plant's discrete update (contact solver, dynamics), by difference.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import numpy as np
from pydrake.geometry import HydroelasticContactRepresentation
from pydrake.systems.analysis import Simulator

from capsule_drake.scenario import load_scenario
from capsule_drake.station import colon_for, make_station


def median_seconds(fn, repeats: int) -> float:
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    return statistics.median(samples)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sim-seconds", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    scenario = load_scenario()
    start = time.perf_counter()
    colon_for(scenario)
    colon_seconds = time.perf_counter() - start
    start = time.perf_counter()
    diagram = make_station(scenario)
    build_seconds = time.perf_counter() - start

    factors = []
    for _ in range(args.repeats):
        simulator = Simulator(diagram)
        simulator.Initialize()
        start = time.perf_counter()
        simulator.AdvanceTo(args.sim_seconds)
        factors.append(args.sim_seconds / (time.perf_counter() - start))
    step_ms = 1000.0 * scenario.time_step / statistics.median(factors)

    # Component costs on the final context (the capsule lies against the wall by now).
    context = simulator.get_context()
    plant = diagram.GetSubsystemByName("plant")
    scene_graph = diagram.GetSubsystemByName("scene_graph")
    magnet_force = diagram.GetSubsystemByName("magnet_force")
    sg_context = scene_graph.GetMyContextFromRoot(context)
    query = scene_graph.get_query_output_port().Eval(sg_context)
    n = 500
    query_ms = 1000.0 * median_seconds(
        lambda: [query.ComputeContactSurfaces(HydroelasticContactRepresentation.kPolygon)
                 for _ in range(n)], 3) / n
    surfaces = query.ComputeContactSurfaces(HydroelasticContactRepresentation.kPolygon)

    mf_context = magnet_force.GetMyContextFromRoot(context)
    port = magnet_force.get_applied_spatial_force_output_port()
    poses = magnet_force.get_body_poses_input_port().Eval(mf_context)
    fixed = magnet_force.CreateDefaultContext()
    fixed_input = magnet_force.get_body_poses_input_port().FixValue(fixed, poses)

    def eval_magnet():
        for _ in range(n):
            fixed_input.GetMutableData()  # marks the input changed: the cache recomputes
            port.Eval(fixed)
    magnet_ms = 1000.0 * median_seconds(eval_magnet, 3) / n

    print(f"machine: {platform.machine()}, {platform.processor() or 'cpu'}, "
          f"python {platform.python_version()}")
    print(f"colon build (cached after the first run): {colon_seconds:.2f} s; "
          f"diagram build: {build_seconds:.2f} s")
    print(f"real-time factor over {args.sim_seconds:.0f} s of the default scenario: "
          f"median {statistics.median(factors):.2f} "
          f"(runs: {', '.join(f'{f:.2f}' for f in factors)})")
    print(f"step: {step_ms:.3f} ms per 1 ms step ({len(surfaces)} contact surfaces at the end)")
    print(f"  hydroelastic contact query : {query_ms:.3f} ms")
    print(f"  MagneticForce (Python)     : {magnet_ms:.3f} ms")
    rest = step_ms - query_ms - magnet_ms
    print(f"  solver, dynamics, rest     : {rest:.3f} ms (by difference)")
    state = plant.GetPositions(plant.GetMyContextFromRoot(context))
    assert np.all(np.isfinite(state))


if __name__ == "__main__":
    main()
