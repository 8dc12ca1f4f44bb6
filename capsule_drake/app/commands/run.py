"""`capsule-sim run`: one scenario, its outputs and its report."""

from __future__ import annotations

import sys
import time

from capsule_drake.app.mcap_log import expected_mcap_bytes
from capsule_drake.app.cli_parser import LOOPBACK
from capsule_drake.app.run import simulate
from capsule_drake.app.commands.common import (_claim, _finish, _load, _meshcat, _plan,
                                               _report_epm_guard, _report_mcap,
                                               _report_pressure, contact_words,
                                               planned_mcap)


def _run(args) -> int:
    # The flags are spellings of the scenario's outputs (common.output_flags); from here on
    # only the scenario says what the run writes and shows.
    scenario = _load(args)
    outputs = scenario.outputs
    plan = _plan(args, "runs", args.scenario or "Default",
                 mcap_bytes=expected_mcap_bytes(scenario), inputs=[args.scenario_file],
                 scenario=scenario)
    out_dir = _claim(plan)
    scenario = planned_mcap(scenario, plan)
    meshcat = None
    if outputs.meshcat is not None:
        meshcat = _meshcat(outputs.meshcat.host, outputs.meshcat.port, announce=True)
    elif outputs.recording:  # only for the recording
        meshcat = _meshcat(args.host or LOOPBACK, 0, announce=False)
    result = simulate(scenario, meshcat=meshcat, out_dir=out_dir,
                      progress=not args.quiet, live_meshcat=outputs.meshcat is not None,
                      recording=outputs.recording)
    m = result.metrics
    if m.get("advance_m") is not None:
        print(f"advanced {m['advance_m'] * 100:.1f} cm along the centerline, from s = "
              f"{m['start_s_m'] * 100:.1f} cm to s = {m['final_s_m'] * 100:.1f} cm of "
              f"{m['colon_length_m'] * 100:.1f} cm; stopped in the {m['stop_segment']}")
        print(f"simulated {m['sim_time_s']:.2f} s in {m['wall_time_s']:.2f} s "
              f"(x{m['real_time_factor']:.2f} real time); {contact_words(m)}: peak contact "
              f"force {m['peak_contact_force_N']:.2f} N, largest excursion beyond the wall "
              f"{m['max_wall_excursion_m'] * 1000:.2f} mm; closest EPM to skin "
              f"{m['min_epm_skin_gap_m'] * 1000:.0f} mm")
    _report_pressure(m)
    _report_epm_guard(m)
    mcap_failure = _report_mcap(result)
    print(f"outputs in {out_dir}/ (metrics.json"
          f"{', wall_pressure.png' if (out_dir / 'wall_pressure.png').is_file() else ''}"
          f"{', recording.html' if outputs.recording else ''})")
    code = _finish(result, mcap_failure)
    if outputs.meshcat is not None:
        print("serving Meshcat; Ctrl-C to quit", file=sys.stderr)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
    return code
