"""`capsule-sim benchmark`: the seeds, the navigators and the suite's outputs."""

from __future__ import annotations

import sys

import numpy as np

from capsule_drake.app.benchmark import (FAILED, NAVIGATORS, TIERS, EngineError, NotedSignals,
                                         RowWriter, Task, default_run_timeout, report,
                                         run_suite, task_scenario)
from capsule_drake.plugins import load_function
from capsule_drake.scenario import DEFAULT_SCENARIO_FILE, ScenarioError, scenario_names
from capsule_drake.app.commands.common import BENCHMARK_OUTPUTS, _output_folder


MAX_SEEDS = 10_000  # a benchmark of more runs than this is a typing mistake


def parse_seeds(text: str, flag: str = "--seeds") -> list[int]:
    """Seeds from '0-9', '0,3,7' or '5'; ScenarioError (one line) on anything else."""
    ranges = []
    try:
        for part in text.split(","):
            first, _, last = part.strip().partition("-")
            ranges.append((int(first), int(last) if last else int(first)))
    except ValueError:
        raise ScenarioError(f"{flag} {text!r}: expected e.g. '0-9', '0,3,7' or '5'") from None
    if not all(0 <= first <= last < 2**32 for first, last in ranges):
        raise ScenarioError(f"{flag} {text!r}: expected seeds in [0, 2^32), each range from "
                            "low to high")
    if sum(last - first + 1 for first, last in ranges) > MAX_SEEDS:
        raise ScenarioError(f"{flag} {text!r}: at most {MAX_SEEDS:,} seeds")
    seeds = [seed for first, last in ranges for seed in range(first, last + 1)]
    if len(set(seeds)) != len(seeds):
        raise ScenarioError(f"{flag} {text!r}: a seed is given twice")
    return seeds


def _benchmark(args) -> int:
    tier_seeds, tier_text = TIERS[args.tier]
    seeds = parse_seeds(args.seeds if args.seeds is not None else tier_seeds)
    navigators = [n.strip() for n in args.navigators.split(",") if n.strip()]
    if not navigators:
        raise ScenarioError("--navigators: none given")
    if not (np.isfinite(args.duration) and 0 < args.duration <= 1e5):
        raise ScenarioError(f"--duration must be > 0 and <= 1e5 s, got {args.duration}")
    workers = 2 if args.workers is None else args.workers
    if not 1 <= workers <= 64:
        raise ScenarioError(f"--workers must be 1-64, got {workers}")
    scenario = "Navigation" if args.scenario is None else args.scenario
    run_timeout = (default_run_timeout(args.duration) if args.run_timeout is None
                   else args.run_timeout)
    if not (np.isfinite(run_timeout) and 0 < run_timeout <= 1e7):
        raise ScenarioError(f"--run-timeout must be > 0 and <= 1e7 s, got {run_timeout}")
    if args.polyp_detector:
        try:
            load_function("polyp detector", args.polyp_detector, "a function")
        except ValueError as e:
            raise ScenarioError(f"--polyp-detector: {e}") from None
    tasks = [Task(n, seed, args.duration, scenario, args.scenario_text,
                  tier_text=tier_text, polyp_detector=args.polyp_detector)
             for n in navigators for seed in seeds]
    # Fail on a bad navigator or scenario here, with one line, not in a worker.
    names = scenario_names(DEFAULT_SCENARIO_FILE)
    if scenario not in names:
        raise ScenarioError(f"--scenario {scenario!r}: no scenario of that name in "
                            f"{DEFAULT_SCENARIO_FILE.name} (it has: {', '.join(names)})")
    for navigator in navigators:
        try:
            first = task_scenario(Task(navigator, seeds[0], args.duration, scenario,
                                       args.scenario_text, tier_text=tier_text))
        except ValueError as e:
            raise ScenarioError(str(e)) from None
        outputs = first.outputs
        taken = [name for name in ("mcap", "meshcat", "foxglove", "ros2")
                 if getattr(outputs, name) is not None]
        if taken:   # every run would write one file, or open one port
            raise ScenarioError(f"--scenario-text: outputs.{taken[0]} is for one run, not a "
                                "benchmark's many (run one seed with `capsule-sim run`)")
    if args.scenario is not None and all(n in NAVIGATORS for n in navigators):
        raise ScenarioError("--scenario: only with a user's navigator (package.module:function); "
                            f"the built-in ones ({', '.join(navigators)}) are named scenarios "
                            "of their own")
    out_dir = _output_folder(args, "runs", "benchmark", outputs=BENCHMARK_OUTPUTS)
    # Rows as the runs finish, in the order they finish; runs.csv is written at the end.
    partial = RowWriter(out_dir / "runs-as-finished.csv")
    finished = []

    def keep(result):
        partial(result)
        finished.append(result)

    try:
        results = run_suite(tasks, workers=workers, engine=args.engine,
                            address=args.address, progress=not args.quiet, on_result=keep,
                            run_timeout=run_timeout)
    except EngineError as e:
        partial.path.unlink(missing_ok=True)
        raise ScenarioError(f"--address: {e}") from None
    except KeyboardInterrupt:
        # The runs have been stopped: the table and outputs of those that finished.
        order = {(task.navigator, task.seed): k for k, task in enumerate(tasks)}
        finished.sort(key=lambda r: order.get((r["row"]["navigator"], r["row"]["seed"]), 0))
        with NotedSignals():  # a second signal waits until the files are whole
            report(finished, out_dir)
        raise
    with NotedSignals() as signals:
        report(results, out_dir)
    signals.raise_noted()
    failed = [r["row"] for r in results if r["row"].get("status") == FAILED]
    if failed:
        print(f"capsule-sim: {len(failed)} of {len(results)} runs failed (the error column "
              f"says why): {', '.join(f'{r['navigator']} seed {r['seed']}' for r in failed)}",
              file=sys.stderr)
    return 1 if failed else 0
