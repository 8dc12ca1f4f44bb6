"""`capsule-sim record`: a dataset of one run, or of one run per seed."""

from __future__ import annotations

import numpy as np

from capsule_drake.app.mcap_log import expected_mcap_bytes
from capsule_drake.app.record import record, record_seeds, with_all_sensors
from capsule_drake.app.outputs import DATASET_OUTPUTS, SEED_PREFIX, SEEDS_OUTPUTS
from capsule_drake.scenario import ScenarioError, load_scenario
from capsule_drake.app.commands.benchmark import parse_seeds
from capsule_drake.app.commands.common import (_claim, _exit_code, _finish, _flags, _load,
                                               _plan, _report_mcap, _report_stop,
                                               planned_mcap)


def _record(args) -> int:
    if args.seeds is not None:
        return _record_seeds(args)
    if args.split is not None:
        raise ScenarioError("--split: only with --seeds (it splits the seeds recorded)")
    scenario = _load(args)
    plan = _plan(args, "datasets", args.scenario or "Default", DATASET_OUTPUTS,
                 mcap_bytes=expected_mcap_bytes(with_all_sensors(scenario)),
                 inputs=[args.scenario_file], scenario=scenario)
    out_dir = _claim(plan)
    result = record(planned_mcap(scenario, plan), out_dir, progress=not args.quiet,
                    scenario_name=args.scenario or "Default")
    frames = len(list((out_dir / "Frames").glob("FrameBuffer_*.png")))
    m = result.metrics
    print(f"recorded {frames} frames over {m.get('sim_time_s', 0.0):.2f} s into {out_dir}/ "
          f"(README.md there describes every file)")
    return _finish(result, _report_mcap(result))


def _split_fractions(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if (len(values) != 3 or not all(np.isfinite(v) and 0.0 <= v <= 1.0 for v in values)
            or abs(sum(values) - 1.0) > 1e-6):
        raise ScenarioError(f"--split {text!r}: expected three shares TRAIN,VAL,TEST in "
                            "[0, 1] that add up to 1, e.g. 0.7,0.15,0.15")
    return values


def _record_seeds(args) -> int:
    """One dataset per colon seed into --out/seed_XXXX/, with splits.csv and README.md."""
    if args.mcap is not None:
        raise ScenarioError("--mcap: not with --seeds (an MCAP log holds one recording; "
                            "record a seed on its own to log it)")
    seeds = parse_seeds(args.seeds, "--seeds")
    fractions = _split_fractions(args.split or "0.7,0.15,0.15")
    name = args.scenario or "Default"
    # Each seed is its own patient and its own noise; the user's --scenario-text comes after,
    # so it may fix random_seed (or anything else), but not the colon seed.
    def scenario_of(seed):
        scenario = load_scenario(args.scenario_file, args.scenario, [
            _flags(colon={"seed": seed}, random_seed=seed), args.scenario_text,
            *([_flags(duration=args.duration)] if args.duration is not None else [])])
        if getattr(scenario.colon, "seed", seed) != seed:
            raise ScenarioError("--seeds: --scenario-text sets colon.seed, which --seeds sets "
                                "for each recording")
        return scenario

    # A bad scenario: one line before anything is written.
    if scenario_of(seeds[0]).outputs.mcap is not None:
        raise ScenarioError("outputs.mcap: not with --seeds (an MCAP log holds one recording; "
                            "record a seed on its own to log it)")
    out_dir = _claim(_plan(args, "datasets", f"{name}-seeds", SEEDS_OUTPUTS,
                           prefixes=(SEED_PREFIX,), inputs=[args.scenario_file]))
    batch = record_seeds(scenario_of, seeds, fractions, out_dir, name, quiet=args.quiet,
                         on_stop=_report_stop)
    if batch.interrupted is not None:
        return _exit_code(batch.interrupted)
    print(f"recorded {len(batch.recorded)} of {len(seeds)} seeds into {out_dir}/ ("
          + ", ".join(f"{split} {n}" for split, n in batch.counts.items())
          + "; splits.csv and README.md there)"
          + (f"; failed: {', '.join(map(str, batch.failed))}" if batch.failed else ""))
    return 1 if batch.failed else 0
