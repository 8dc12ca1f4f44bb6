"""Real-time factor of a scenario and what its 1 ms step spends its time on.

    .venv/bin/python benchmarks/bench_realtime.py [--scenario NAME] [--sim-seconds 10] [--repeats 3]

Physics and magnet only (no rendering, no Meshcat), the full-length colon, 1 ms step.
Prints the median real-time factor over repeats of the scenario from diagrams/default.yaml,
then what one step costs, by ablation and by direct timing on the final context:
  - the same station with the magnet's force not applied (the MagneticForce system and its
    port traffic drop out of the step): the difference is the magnet's share;
  - the contact query alone (SceneGraph, hydroelastic surfaces or point pairs);
  - the remainder of the plant step (contact solver, dynamics, PD servos), by difference.
"""

import argparse
import platform
import statistics
import time

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


def real_time_factors(diagram, sim_seconds, repeats, warm_up=1.0):
    factors = []
    for _ in range(repeats):
        simulator = Simulator(diagram)
        simulator.Initialize()
        simulator.AdvanceTo(warm_up)  # the capsule settles onto the wall
        start = time.perf_counter()
        simulator.AdvanceTo(warm_up + sim_seconds)
        factors.append(sim_seconds / (time.perf_counter() - start))
    return factors, simulator


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="Default")
    parser.add_argument("--sim-seconds", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    scenario = load_scenario(name=args.scenario)
    start = time.perf_counter()
    colon_for(scenario)
    colon_seconds = time.perf_counter() - start
    start = time.perf_counter()
    diagram = make_station(scenario)
    build_seconds = time.perf_counter() - start

    factors, simulator = real_time_factors(diagram, args.sim_seconds, args.repeats)
    no_magnet, _ = real_time_factors(make_station(scenario, apply_magnet_force=False),
                                     args.sim_seconds, args.repeats)
    step_ms = 1000.0 * scenario.time_step / statistics.median(factors)
    plant_ms = 1000.0 * scenario.time_step / statistics.median(no_magnet)

    context = simulator.get_context()
    scene_graph = diagram.GetSubsystemByName("scene_graph")
    query = scene_graph.get_query_output_port().Eval(scene_graph.GetMyContextFromRoot(context))
    n = 300
    if scenario.contact.model == "hydroelastic":
        def contact_query():
            for _ in range(n):
                query.ComputeContactSurfaces(HydroelasticContactRepresentation.kPolygon)
    else:
        def contact_query():
            for _ in range(n):
                query.ComputePointPairPenetration()
    query_ms = 1000.0 * median_seconds(contact_query, 3) / n

    print(f"machine: {platform.machine()}, {platform.python_version()}, "
          f"scenario {args.scenario} (contact: {scenario.contact.model})")
    print(f"colon build: {colon_seconds:.2f} s; diagram build: {build_seconds:.2f} s")
    print(f"real-time factor over {args.sim_seconds:.0f} s: median "
          f"{statistics.median(factors):.2f} (runs: {', '.join(f'{f:.2f}' for f in factors)})")
    print(f"step: {step_ms:.3f} ms of simulated 1 ms")
    print(f"  magnet force (MagneticForce + port traffic) : {step_ms - plant_ms:.3f} ms "
          f"(by ablation; without it x{statistics.median(no_magnet):.2f})")
    print(f"  contact query                              : {query_ms:.3f} ms")
    print(f"  solver, dynamics, servos, rest             : {plant_ms - query_ms:.3f} ms "
          "(by difference)")


if __name__ == "__main__":
    main()
