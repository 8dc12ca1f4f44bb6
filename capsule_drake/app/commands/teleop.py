"""`capsule-sim teleop`: teleoperation with a person (in the browser or on a UDP device) or
the simulated operator."""

from __future__ import annotations

import sys

from capsule_drake.app.mcap_log import expected_mcap_bytes
from capsule_drake.app.run import simulate
from capsule_drake.scenario import DEFAULT_SCENARIO_FILE, ScenarioError
from capsule_drake.station import station_value
from capsule_drake.app.cli_parser import DEFAULT_PORT, LOOPBACK
from capsule_drake.app.commands.common import (_claim, _finish, _flags, _load, _meshcat,
                                               _plan, _report_mcap, planned_mcap)


def _teleop(args) -> int:
    if args.scenario is None and args.scenario_file == DEFAULT_SCENARIO_FILE:
        args.scenario = "Teleop"
    # The verb makes the operator drive the EPM: `!Teleop` merges into the scenario's own
    # Teleop driver (or replaces another driver with the default one).
    # The UDP bridge's host: --host, else the scenario's (127.0.0.1 by default).
    port = DEFAULT_PORT if args.port is None else args.port
    teleop = {"udp": {"port": port, **({"host": args.host} if args.host else {})}}
    if args.operator is not None:
        teleop["operator"] = args.operator
    if args.delay is not None:
        teleop["channel"] = {"forward": {"delay": args.delay},
                             "backward": {"delay": args.delay}}
    flags = ["{epm: {driver: !Teleop " + _flags(**teleop) + "}}"]
    if args.guidance == "off":
        flags.append("{pseudo_force: null}")
    scenario = _load(args, *flags)
    teleop = scenario.epm.driver
    if args.port is not None and teleop.operator == "simulated":
        raise ScenarioError("--port: the simulated operator listens on no port (--port is the "
                            "page's with --operator browser, the device's with udp)")
    live = teleop.operator in ("browser", "udp")
    if live and scenario.simulator.target_realtime_rate == 0.0:
        # A person at the device: paced to the wall clock.
        scenario = _load(args, *flags, "{simulator: {target_realtime_rate: 1.0}}")
    plan = _plan(args, "runs", f"teleop-{teleop.operator}",
                 mcap_bytes=expected_mcap_bytes(scenario), inputs=[args.scenario_file],
                 scenario=scenario)
    out_dir = _claim(plan)
    scenario = planned_mcap(scenario, plan)
    meshcat = _meshcat(args.host or LOOPBACK, port if teleop.operator == "browser" else 0,
                       announce=live)

    def announce(builder, station):
        if teleop.operator == "udp":
            host, port = station_value(station, "teleop.device.address")()
            print(f"listening for the haptic device on udp://{host}:{port} "
                  "(docs/udp_protocol.md)", file=sys.stderr)
        return None

    result = simulate(scenario, meshcat=meshcat, out_dir=out_dir, progress=not args.quiet,
                      live_meshcat=live,
                      extend=announce)
    m = result.metrics
    if m.get("advance_m") is not None:
        print(f"advanced {m['advance_m'] * 100:.1f} cm along the centerline in "
              f"{m['sim_time_s']:.1f} s (x{m['real_time_factor']:.2f} real time); peak "
              f"contact force {m['peak_contact_force_N']:.2f} N; closest EPM to skin "
              f"{m['min_epm_skin_gap_m'] * 1000:.0f} mm")
    mcap_failure = _report_mcap(result)
    print(f"outputs in {out_dir}/ (metrics.json, recording.html)")
    return _finish(result, mcap_failure)
