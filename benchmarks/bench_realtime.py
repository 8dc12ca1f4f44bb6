"""Real-time factor of a scenario and what its 1 ms step spends its time on.

    .venv/bin/python benchmarks/bench_realtime.py [--scenario NAME] [--scenario-text YAML]
        [--sim-seconds 10] [--repeats 3]

Physics and magnet only (no rendering, no Meshcat), the full-length colon, 1 ms step.
Prints the median real-time factor over repeats of the scenario from diagrams/default.yaml,
then what one step costs:
  - the magnet force (the MagneticForce system and its port traffic), as the difference
    between two variants that simulate the same motion: magnets of zero moment with the
    force applied, and the force not applied at all (the capsule rests on the wall in both);
  - the contact query alone (SceneGraph: hydroelastic surfaces or point pairs), timed
    directly on the final context;
  - the rest of the plant step (contact solver, dynamics, PD servos), by difference.
"""

import argparse
import copy
import platform
import statistics
import time

from pydrake.geometry import HydroelasticContactRepresentation
from pydrake.systems.analysis import Simulator

from capsule_drake.anatomy import load_colon
from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station


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


def magnet_share_ms(scenario, sim_seconds: float, chunk: float = 0.05) -> float:
    """Per-step cost of the magnet force system, from two stations that move identically:
    magnets of zero moment with the force applied, and the force not applied. They advance
    in interleaved chunks, timed in CPU time, so that other load on the machine affects both
    alike; the median of the per-chunk differences is the system's cost."""
    unmagnetised = copy.deepcopy(scenario)
    unmagnetised.capsule.ipm.remanence = 0.0
    unmagnetised.epm.magnet.remanence = 0.0
    not_applied = copy.deepcopy(unmagnetised)  # as `magnet_force: {apply: false}`
    not_applied.magnet_force.apply = False
    simulators = [Simulator(make_station(unmagnetised)),
                  Simulator(make_station(not_applied))]
    for simulator in simulators:
        simulator.Initialize()
        simulator.AdvanceTo(1.0)
    differences = []
    t = 1.0
    while t < 1.0 + sim_seconds:
        t += chunk
        spent = []
        for simulator in simulators:
            start = time.process_time()
            simulator.AdvanceTo(t)
            spent.append(time.process_time() - start)
        differences.append(spent[0] - spent[1])
    return 1000.0 * statistics.median(differences) * scenario.plant.time_step / chunk


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="Default")
    parser.add_argument("--scenario-text", default=None,
                        help="YAML layered on the scenario, e.g. "
                             "'{magnet_force: {field_model: finite}}'")
    parser.add_argument("--sim-seconds", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    scenario = load_scenario(name=args.scenario, override=args.scenario_text)
    start = time.perf_counter()
    load_colon(scenario.colon)
    colon_seconds = time.perf_counter() - start
    start = time.perf_counter()
    diagram = make_station(scenario)
    build_seconds = time.perf_counter() - start

    factors, simulator = real_time_factors(diagram, args.sim_seconds, args.repeats)
    step_ms = 1000.0 * scenario.plant.time_step / statistics.median(factors)
    magnet_ms = magnet_share_ms(scenario, args.sim_seconds)

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
    print(f"colon build (and its mesh files): {colon_seconds:.2f} s; "
          f"diagram build: {build_seconds:.2f} s")
    print(f"real-time factor over {args.sim_seconds:.0f} s: median "
          f"{statistics.median(factors):.2f} (runs: {', '.join(f'{f:.2f}' for f in factors)})")
    print(f"step: {step_ms:.3f} ms of simulated 1 ms")
    print(f"  magnet force (MagneticForce + port traffic) : {magnet_ms:.3f} ms")
    print(f"  contact query                              : {query_ms:.3f} ms")
    print(f"  solver, dynamics, servos, rest             : "
          f"{step_ms - magnet_ms - query_ms:.3f} ms (by difference)")


if __name__ == "__main__":
    main()
