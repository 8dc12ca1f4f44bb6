"""Real-time factors of the scenarios, their build times and memory, and what a step costs.

    .venv/bin/python benchmarks/bench_realtime.py [--scenarios Default,FastContact,WithArm,Navigation]
        [--scenario-text YAML] [--sim-seconds 10] [--repeats 3] [--versus YAML]

Each scenario (diagrams/default.yaml, at its own plant step) runs in a process of its own, so
that its build time and peak memory (resident set, build and simulation) are its own, with
the allocator setting the launchers use (ALLOCATOR, unless GLIBC_TUNABLES is set). No
Meshcat; the Navigation scenario renders its camera and runs its tracker and follower as a
run would. Prints, per scenario, the build time (colon and diagram), the peak memory, the
median real-time factor over `repeats` simulations of `sim-seconds` after one second of
settling, the wall time of one step, and, for the scenarios without a camera, what one step
costs:
  - the magnet force (the MagneticForce system and its port traffic), as the difference
    between two variants that simulate the same motion: magnets of zero moment with the
    force applied, and the force not applied at all (the capsule rests on the wall in both);
  - the contact query alone (SceneGraph: hydroelastic surfaces or point pairs), timed
    directly on the final context;
  - the rest of the plant step (contact solver, dynamics, PD servos), by difference.

With --versus YAML, each scenario is measured against itself with that YAML layered on
(e.g. the rigid wall against the compliant one): both stations are built in one process and
advanced in alternate chunks of 0.5 simulated seconds, each chunk timed, so that a change in
the machine's speed during the measurement (a shared VM's neighbours) falls on both alike.
Prints each one's real-time factor per repeat (its chunks' total) and the ratio, median of
the repeats.
"""

import argparse
import copy
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time

from pydrake.geometry import HydroelasticContactRepresentation
from pydrake.systems.analysis import Simulator

from capsule_drake.anatomy import load_colon
from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station


ALLOCATOR = "glibc.malloc.tcache_count=65000:glibc.malloc.tcache_max=262144"
"""The allocator setting ./capsule-sim and ./run-tests give every run (scripts/bootstrap.sh):
the scenarios are measured with it unless GLIBC_TUNABLES is set already."""


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


def measure(name, override, sim_seconds, repeats, breakdown):
    """The figures of one scenario, in this process (a dict)."""
    scenario = load_scenario(name=name, override=override)
    start = time.perf_counter()
    load_colon(scenario.colon)
    colon_seconds = time.perf_counter() - start
    start = time.perf_counter()
    diagram = make_station(scenario)
    build_seconds = time.perf_counter() - start

    factors, simulator = real_time_factors(diagram, sim_seconds, repeats)
    step = scenario.plant.time_step
    figures = {"scenario": name, "contact": scenario.contact.label(), "time_step_ms": 1e3 * step,
               "colon_s": colon_seconds, "build_s": build_seconds, "factors": factors,
               "step_ms": 1000.0 * step / statistics.median(factors),
               # Before the breakdown's extra stations: the build and the simulations.
               "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0**2}
    if breakdown:
        figures["magnet_ms"] = magnet_share_ms(scenario, sim_seconds)
        context = simulator.get_context()
        scene_graph = diagram.GetSubsystemByName("scene_graph")
        query = scene_graph.get_query_output_port().Eval(
            scene_graph.GetMyContextFromRoot(context))
        n = 300
        if scenario.contact.pressure_field:
            def contact_query():
                for _ in range(n):
                    query.ComputeContactSurfaces(HydroelasticContactRepresentation.kPolygon)
        else:
            def contact_query():
                for _ in range(n):
                    query.ComputePointPairPenetration()
        figures["query_ms"] = 1000.0 * median_seconds(contact_query, 3) / n
    return figures


def paired_factors(name, override, versus, sim_seconds, repeats, chunk=0.5, warm_up=1.0):
    """(the scenario's real-time factors, with `versus` layered on, their ratios), one of
    each per repeat: the two advanced in alternate chunks (module docstring)."""
    texts = [override, [override, versus] if override else versus]
    diagrams = [make_station(load_scenario(name=name, override=text)) for text in texts]
    rows = []
    for _ in range(repeats):
        simulators = [Simulator(diagram) for diagram in diagrams]
        for simulator in simulators:
            simulator.Initialize()
            simulator.AdvanceTo(warm_up)
        spent = [0.0, 0.0]
        t = warm_up
        while t < warm_up + sim_seconds - 1e-9:
            t = min(t + chunk, warm_up + sim_seconds)
            for k, simulator in enumerate(simulators):
                start = time.perf_counter()
                simulator.AdvanceTo(t)
                spent[k] += time.perf_counter() - start
        rows.append((sim_seconds / spent[0], sim_seconds / spent[1], spent[0] / spent[1]))
    return rows


def run_child(name, args, env):
    """One scenario measured in a process of its own (this script with --one): its JSON
    line, or None after printing the row that says why it failed."""
    command = [sys.executable, __file__, "--one", name, "--sim-seconds",
               str(args.sim_seconds), "--repeats", str(args.repeats)]
    if args.versus is not None:
        command += ["--versus", args.versus]
    if args.scenario_text:
        command += ["--scenario-text", args.scenario_text]
    done = subprocess.run(command, capture_output=True, text=True, env=env)
    if done.returncode != 0:
        print(f"| {name} | failed: {done.stderr.strip().splitlines()[-1:]} |")
        return None
    return json.loads(done.stdout.strip().splitlines()[-1])


def cpu_name():
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown cpu"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", default="Default,FastContact,WithArm,Navigation")
    parser.add_argument("--scenario-text", default=None,
                        help="YAML layered on every scenario, e.g. "
                             "'{magnet_force: {field_model: finite}}'")
    parser.add_argument("--sim-seconds", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--versus", default=None,
                        help="YAML layered on a second copy of each scenario, measured in "
                             "alternate chunks against the first, e.g. "
                             "'{contact: !CompliantWall {}}'")
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.versus is not None and args.one is not None:
        print(json.dumps(paired_factors(args.one, args.scenario_text, args.versus,
                                        args.sim_seconds, args.repeats)))
        return

    if args.one is not None:   # the child: one scenario, one JSON line
        breakdown = load_scenario(name=args.one).capsule.camera is None
        print(json.dumps(measure(args.one, args.scenario_text, args.sim_seconds,
                                 args.repeats, breakdown)))
        return

    env = dict(os.environ)
    env.setdefault("GLIBC_TUNABLES", ALLOCATOR)
    print(f"machine: {platform.machine()}, {cpu_name()}, Python "
          f"{platform.python_version()}; {args.repeats} x {args.sim_seconds:g} s after 1 s; "
          f"GLIBC_TUNABLES={env['GLIBC_TUNABLES']}")
    if args.versus is not None:
        print(f"| scenario | as given{' (' + args.scenario_text + ')' if args.scenario_text else ''} "
              f"| with {args.versus} | ratio (median; repeats) |")
        print("|---|---|---|---|")
        for name in args.scenarios.split(","):
            rows = run_child(name, args, env)
            if rows is None:
                continue
            a, b, r = zip(*rows)
            print(f"| `{name}` | {statistics.median(a):.2f} ({', '.join(f'{x:.2f}' for x in a)}) "
                  f"| {statistics.median(b):.2f} ({', '.join(f'{x:.2f}' for x in b)}) "
                  f"| **{statistics.median(r):.2f}** ({', '.join(f'{x:.2f}' for x in r)}) |",
                  flush=True)
        return
    print("| scenario | contact | step | build (colon + diagram) | peak memory "
          "| real-time factor (median; runs) | wall per step | magnet force | contact query "
          "| solver, dynamics, rest |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in args.scenarios.split(","):
        f = run_child(name, args, env)
        if f is None:
            continue
        factors = f["factors"]
        row = (f"| `{name}` | {f['contact']} | {f['time_step_ms']:g} ms | "
               f"{f['colon_s']:.1f} + {f['build_s']:.1f} s | {f['peak_rss_gb']:.2f} GB | "
               f"**{statistics.median(factors):.2f}** "
               f"({', '.join(f'{x:.2f}' for x in factors)}) | {f['step_ms']:.3f} ms | ")
        if "magnet_ms" in f:
            rest = f["step_ms"] - f["magnet_ms"] - f["query_ms"]
            row += f"{f['magnet_ms']:.3f} ms | {f['query_ms']:.3f} ms | {rest:.3f} ms |"
        else:
            row += "(camera, tracker) | | |"
        print(row, flush=True)


if __name__ == "__main__":
    main()
