"""The navigation tables of the results pages, from benchmark runs, finished or still going.

    .venv/bin/python benchmarks/population_tables.py RUNS.csv [RUNS.csv ...]

Reads each `runs.csv` or `runs-as-finished.csv` that `capsule-sim benchmark` wrote (the
latter is appended run by run, so a suite still going can be tabled) and prints, as
Markdown, per navigator: the cecal intubation rate with its 95 % Wilson interval, the mean
time to the cecum, the mean speed to it, wall contact, peak contact force and pressure, the
wall's per-site figures, and coverage; then the breakdown by sigmoid variant, sex and
tercile of the colon's length, and the runs that did not reach the cecum with where they
stopped. The documentation site makes the same tables from the same files where a results
page names them (capsule_drake/app/benchmark/result_tables.py).
"""

import argparse
from pathlib import Path

from capsule_drake.app.benchmark.result_tables import block


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    runs = " ".join(str(path) for path in parser.parse_args().runs)
    for kind in ("table", "breakdown", "stops"):
        print(block(kind, runs))
        print()


if __name__ == "__main__":
    main()
