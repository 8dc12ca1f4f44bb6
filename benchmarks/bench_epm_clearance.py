"""The EPM's smallest gap to the skin, where the magnet is, for each mount under each kind of
driver: the figures behind the table of docs/results/epm.md.

    python benchmarks/bench_epm_clearance.py [--mounts a,b] [--drivers a,b]

For each pair it simulates the default scenario with that mount and driver (the drivers as
tests/test_epm_clearance.py has them: a plug-in and a script on the !External input that
command the floor over one flank, then the other, every 2.5 s; the built-in path, follower
and teleoperation drivers), logs the EPM's pose every 5 ms, and prints the smallest gap
between the magnet's surface (sampled: its side and caps) and the skin under each sample,
the smallest gap as the guard measures it (the magnet's lowest point over the highest skin
under its footprint), the clearance, how the run ended, and how far across the belly the
magnet went.
"""

import argparse
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from test_epm_clearance import DRIVERS, MOUNTS, run_and_measure  # noqa: E402

from capsule_drake.epm.clearance import CLEARANCE_TOLERANCE  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mounts", default=",".join(MOUNTS))
    parser.add_argument("--drivers", default=",".join(DRIVERS))
    args = parser.parse_args()
    print(f"tolerance {CLEARANCE_TOLERANCE * 1000:g} mm")
    print("| mount | driver | duration (s) | status | smallest gap (mm) | as the guard "
          "measures it (mm) | clearance (mm) | x range (m) | wall (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for mount in args.mounts.split(","):
        for driver in args.drivers.split(","):
            start = time.perf_counter()
            scenario, result, gap, guards_gap = run_and_measure(mount, driver)
            x = result.epm_pose[0]
            print(f"| {mount} | {driver} | {DRIVERS[driver][2]:g} | {result.status} | "
                  f"{gap * 1000:.2f} | {guards_gap * 1000:.2f} | "
                  f"{scenario.epm.clearance * 1000:g} | "
                  f"{x.min():+.3f} .. {x.max():+.3f} | {time.perf_counter() - start:.0f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
