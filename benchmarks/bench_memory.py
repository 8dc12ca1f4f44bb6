"""Resident memory of the Gymnasium environment over many colons, and the time of a build.

    .venv/bin/python benchmarks/bench_memory.py [--resets 50] [--colons 10] [--steps 1]
        [--configs default,camera] [--every 10] [--no-collect] [--system-allocator]

For each configuration, in a process of its own: a ColonNavigationEnv (capsule_drake/
ColonNavigation-v0, its default max_cached_colons) is reset `--resets` times with seeds 0,
1, 2, ..., which cycle over `--colons` colons (seed k runs colon k mod colons), each reset
followed by `--steps` zero-action steps. With more colons than the environment keeps built,
every reset builds its colon's diagram and drops the oldest one. Configurations: "default"
(the default observations: imu, magnetometer, epm; nothing renders) and "camera"
(observations camera and imu: the capsule camera, its walls and renderers, and its render
worker process).

Printed for each: the process's resident memory (RSS, MB) after the first reset and every
`--every`-th, with the diagrams still alive (weak references to every diagram the
environment built), a garbage collection run after every reset (--no-collect: only
Python's own, automatic ones, as in a training loop); after close() and a collection; and
after glibc's malloc_trim (what of the freed memory the allocator held goes back to the
system). Then the growth from the 10th reset to the last (acceptance: 50 resets over 10
colons stay within 300 MB of the 10th) and the median wall and CPU time of a reset that
builds (the CPU time is this process's alone: a camera's render worker starts in a process
of its own).

The processes run with the allocator setting the launchers give every run
(scripts/bootstrap.sh), set here when GLIBC_TUNABLES is not (--system-allocator: glibc's
defaults).
"""

import argparse
import os
import subprocess
import sys

ALLOCATOR = "glibc.malloc.tcache_count=65000:glibc.malloc.tcache_max=262144"
CONFIGS = {"default": None, "camera": ("camera", "imu")}
ACCEPTED_GROWTH_MB = 300.0


def rss_mb() -> float:
    """The process's resident set size (MB)."""
    try:
        import psutil
        return psutil.Process().memory_info().rss / 2**20
    except ImportError:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    return float("nan")


def malloc_trim() -> bool:
    """Asks glibc to give its free memory back to the system; False where there is none."""
    import ctypes
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        return False
    return True


def measure(config: str, resets: int, colons: int, steps: int, every: int,
            collect: bool = True) -> None:
    """One configuration, in this process: prints its lines."""
    import gc
    import statistics
    import time
    import weakref

    import numpy as np

    from capsule_drake.app.gym_env import DEFAULT_OBSERVATIONS, ColonNavigationEnv

    observations = CONFIGS[config] or DEFAULT_OBSERVATIONS
    start = rss_mb()
    env = ColonNavigationEnv(observations=observations, colons=tuple(range(colons)))
    print(f"{config}: observations {', '.join(observations)}; {colons} colons, "
          f"{resets} resets, {steps} step(s) each{'' if collect else ', no collections'}; "
          f"RSS {start:.0f} MB at start", flush=True)
    diagrams, run = [], None
    builds = []          # (wall s, CPU s) of the resets that built a diagram
    rss = {}
    for k in range(resets):
        built = env.build_count
        wall, cpu = time.perf_counter(), time.process_time()
        env.reset(seed=k)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        if env.build_count > built:
            builds.append((wall, cpu))
            run = getattr(env, "_run", None)   # the environment's own: for the count only
            if run is not None:
                diagrams.append(weakref.ref(run.diagram))
        for _ in range(steps):
            env.step(np.zeros(6))
        if collect:
            gc.collect()
        rss[k + 1] = rss_mb()
        if k == 0 or (k + 1) % every == 0 or k + 1 == resets:
            alive = sum(ref() is not None for ref in diagrams)
            print(f"  after reset {k + 1:3d}: RSS {rss[k + 1]:6.0f} MB, diagrams built "
                  f"{env.build_count}, alive {alive}", flush=True)
    env.close()
    del env, run
    gc.collect()
    alive = sum(ref() is not None for ref in diagrams)
    print(f"  after close():   RSS {rss_mb():6.0f} MB, diagrams alive {alive}")
    if malloc_trim():
        print(f"  and malloc_trim: RSS {rss_mb():6.0f} MB")
    if resets >= 10:
        growth = rss[resets] - rss[10]
        verdict = "within" if growth <= ACCEPTED_GROWTH_MB else "OVER"
        print(f"  growth from reset 10 to {resets}: {growth:+.0f} MB ({verdict} "
              f"{ACCEPTED_GROWTH_MB:.0f} MB)")
    if builds:
        walls, cpus = zip(*builds)
        print(f"  a reset that builds: median {statistics.median(walls):.1f} s wall "
              f"(min {min(walls):.1f}, max {max(walls):.1f}), {statistics.median(cpus):.1f} s "
              f"CPU, over {len(builds)} builds", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resets", type=int, default=50)
    parser.add_argument("--colons", type=int, default=10)
    parser.add_argument("--steps", type=int, default=1, help="zero-action steps per reset")
    parser.add_argument("--configs", default="default,camera",
                        help=f"comma-separated, of {', '.join(CONFIGS)}")
    parser.add_argument("--every", type=int, default=10, help="print the RSS every so many")
    parser.add_argument("--no-collect", action="store_true",
                        help="no garbage collection after each reset (Python's own only)")
    parser.add_argument("--system-allocator", action="store_true",
                        help="glibc's default allocator settings, not the launchers'")
    parser.add_argument("--one", help=argparse.SUPPRESS)   # a configuration, in this process
    args = parser.parse_args()
    if args.one:
        measure(args.one, args.resets, args.colons, args.steps, args.every,
                collect=not args.no_collect)
        return
    configs = [c for c in args.configs.split(",") if c]
    unknown = [c for c in configs if c not in CONFIGS]
    if unknown:
        parser.error(f"unknown configuration(s) {', '.join(unknown)}: choose from "
                     f"{', '.join(CONFIGS)}")
    env = dict(os.environ)
    if not args.system_allocator:
        env.setdefault("GLIBC_TUNABLES", ALLOCATOR)
    print(f"GLIBC_TUNABLES={env.get('GLIBC_TUNABLES', '(unset)')}", flush=True)
    for config in configs:   # a fresh process each: one's memory does not count in another's
        subprocess.run([sys.executable, os.path.abspath(__file__), "--one", config,
                        "--resets", str(args.resets), "--colons", str(args.colons),
                        "--steps", str(args.steps), "--every", str(args.every)]
                       + (["--no-collect"] if args.no_collect else []),
                       env=env, check=True)


if __name__ == "__main__":
    main()
