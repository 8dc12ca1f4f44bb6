"""Teleoperation with the simulated operator, haptic guidance on and off.

    python benchmarks/bench_teleop.py [--duration 120] [--scenario Teleop] [--seeds 0 1 2]
        [--scenario-text YAML]

Runs the scenario on each colon seed twice, in parallel processes: with the pseudo-force (guidance on) and
without it (the operator feels only the capsule's contact with the wall). Prints, for each:
how far the capsule advanced along the colon and the time it took to advance 50 cm, the time
the capsule spent touching the wall (contact load > 0.05 N) and the peak contact force, the
lumen-centring error (median angle between the optical axis and the lumen truth while it is
in view), the EPM's path length, the capsule's speed (median and 99th percentile of the
samples), and the real-time factor.
"""

import argparse
import multiprocessing
import time

import numpy as np


def run(args):
    scenario_name, duration, guidance, seed, text = args
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import LogVectorOutput

    from capsule_drake.anatomy import load_colon
    from capsule_drake.physics.contact_monitor import ContactMonitor
    from capsule_drake.scenario import layered, load_scenario
    from capsule_drake.station import make_station

    import yaml

    override = layered(yaml.safe_load(text) or {}, {"duration": duration, "colon": {"seed": seed}})
    if not guidance:
        override["pseudo_force"] = None
    override = yaml.safe_dump(override, default_flow_style=True)
    scenario = load_scenario(name=scenario_name, override=override)
    colon, _ = load_colon(scenario.colon)
    builder = DiagramBuilder()
    station = builder.AddSystem(make_station(scenario))
    monitor = builder.AddSystem(ContactMonitor())
    builder.Connect(station.GetOutputPort("contact_results"), monitor.get_input_port())
    period = 0.05
    logs = {name: LogVectorOutput(station.GetOutputPort(name), builder, period)
            for name in ("capsule.state", "epm.pose", "capsule.lumen.lumen_pixel",
                         "capsule.lumen.lumen_visible")}
    logs["load"] = LogVectorOutput(monitor.GetOutputPort("contact_load"), builder, period)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.Initialize()
    start = time.perf_counter()
    simulator.AdvanceTo(scenario.duration)
    wall = time.perf_counter() - start
    context = simulator.get_context()
    data = {name: log.FindLog(context).data() for name, log in logs.items()}
    times = logs["load"].FindLog(context).sample_times()
    s = colon.centerline.closest(data["capsule.state"][4:7].T)[0]
    advance = s - s[0]
    reached = np.nonzero(advance >= 0.5)[0]
    camera = station.GetSubsystemByName("capsule.camera")
    lens = camera.lens
    visible = data["capsule.lumen.lumen_visible"][0] > 0.5
    pixels = data["capsule.lumen.lumen_pixel"][:, visible].T
    angles = (np.degrees(np.arccos(np.clip(lens.unproject(pixels)[:, 2], -1, 1)))
              if len(pixels) else np.array([np.nan]))
    epm = data["epm.pose"][:3]
    return {
        "guidance": "on" if guidance else "off",
        "advance_cm": 100 * float(advance[-1]),
        "max_advance_cm": 100 * float(advance.max()),
        "time_to_50cm_s": float(times[reached[0]]) if len(reached) else float("nan"),
        "wall_contact_s": float(np.sum(data["load"][0] > 0.05) * period),
        "peak_contact_N": float(data["load"][0].max()),
        "centring_deg": float(np.median(angles)),
        "lumen_in_view": float(np.mean(visible)),
        "epm_path_m": float(np.sum(np.linalg.norm(np.diff(epm, axis=1), axis=0))),
        "speed_p50_p99": np.percentile(np.linalg.norm(data["capsule.state"][10:13], axis=0),
                                       [50, 99]),
        "rtf": scenario.duration / wall,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=120.0)
    parser.add_argument("--scenario", default="Teleop")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0],
                        help="colon seeds (default: 0, the default colon)")
    parser.add_argument("--scenario-text", default="",
                        help="YAML layered on the scenario, e.g. '{contact: {friction: 0.1}}'")
    args = parser.parse_args()
    jobs = [(args.scenario, args.duration, guidance, seed, args.scenario_text)
            for seed in args.seeds for guidance in (True, False)]
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        results = pool.map(run, jobs)
    print(f"{args.scenario} {args.scenario_text}, {args.duration:.0f} s simulated, "
          "simulated operator")
    print(f"{'seed':>4s} {'guidance':8s} {'advance':>8s} {'to 50 cm':>8s} {'wall contact':>12s} "
          f"{'peak force':>10s} {'centring':>8s} {'in view':>7s} {'EPM path':>8s} "
          f"{'speed p50/p99':>13s} {'RTF':>5s}")
    for (_, _, _, seed, _), r in zip(jobs, results):
        print(f"{seed:4d} {r['guidance']:8s} {r['advance_cm']:6.1f}cm {r['time_to_50cm_s']:7.1f}s "
              f"{r['wall_contact_s']:11.1f}s {r['peak_contact_N']:9.2f}N "
              f"{r['centring_deg']:7.1f}d {100 * r['lumen_in_view']:6.0f}% "
              f"{r['epm_path_m']:7.2f}m {100 * r['speed_p50_p99'][0]:5.1f}/"
              f"{100 * r['speed_p50_p99'][1]:5.1f}cm/s {r['rtf']:5.2f}")


if __name__ == "__main__":
    main()
