"""Steps per second of the Gymnasium environment capsule_drake/ColonNavigation-v0.

    .venv/bin/python benchmarks/bench_gym.py [--steps 100] [--repeats 5] [--image-size 64]

For the default observations (imu, magnetometer, epm: nothing rendered) and with the
camera added, in one environment and in a vector of two (gymnasium.vector.AsyncVectorEnv,
spawned worker processes), random actions from reset seed 0 (colon 0, the rectum): the
median over `repeats` batches of `steps` steps of the environment steps per second (a vector
step counts as two), and the real-time factor that gives (simulated seconds per wall second,
each step being `control_period`, 0.1 s). For one environment, also the steps per second of
the stepping process's CPU time (what a core of its own would give, whatever else the
machine runs; the camera's render worker, a process of its own, is not counted in it). A
batch starts with a reset (not timed); an
episode that ends within a batch is reset and goes on (timed: it is part of training). Also
the time to build a colon's diagram (the first reset) and of a reset that reuses it.

The process runs with the allocator setting the launchers give every run
(scripts/bootstrap.sh), set here when GLIBC_TUNABLES is not.
"""

import argparse
import os
import platform
import statistics
import sys
import time

ALLOCATOR = "glibc.malloc.tcache_count=65000:glibc.malloc.tcache_max=262144"

if "GLIBC_TUNABLES" not in os.environ:   # before anything allocates: start again with it
    os.execve(sys.executable, [sys.executable] + sys.argv,
              dict(os.environ, GLIBC_TUNABLES=ALLOCATOR))

import gymnasium  # noqa: E402
import numpy as np  # noqa: E402

import capsule_drake  # noqa: E402,F401  (registers the environment)
from capsule_drake.app.gym_env import DEFAULT_OBSERVATIONS, ENV_ID  # noqa: E402

SEED = 0


def make(observations, image_size):
    return gymnasium.make(f"capsule_drake:{ENV_ID}", observations=observations,
                          colons=(SEED,), image_size=image_size)


def single(observations, image_size, steps, repeats):
    env = make(observations, image_size)
    start = time.perf_counter()
    env.reset(seed=SEED)
    build = time.perf_counter() - start
    env.action_space.seed(SEED)
    resets, rates, cpu_rates = [], [], []
    for _ in range(repeats):
        start = time.perf_counter()
        env.reset(seed=SEED)
        resets.append(time.perf_counter() - start)
        start, cpu_start = time.perf_counter(), time.process_time()
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()
        rates.append(steps / (time.perf_counter() - start))
        cpu_rates.append(steps / (time.process_time() - cpu_start))
    env.close()
    return {"build_s": build, "reset_s": statistics.median(resets), "rates": rates,
            "cpu_rate": statistics.median(cpu_rates)}


def vector(observations, image_size, steps, repeats, count=2):
    envs = gymnasium.vector.AsyncVectorEnv(
        [lambda: make(observations, image_size)] * count, context="spawn")
    envs.reset(seed=[SEED + k for k in range(count)])   # builds (not timed)
    envs.action_space.seed(SEED)
    rates = []
    for _ in range(repeats):
        envs.reset(seed=[SEED + k for k in range(count)])
        start = time.perf_counter()
        for _ in range(steps):
            envs.step(envs.action_space.sample())   # ended episodes reset themselves
        rates.append(count * steps / (time.perf_counter() - start))
    envs.close()
    return {"rates": rates}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100, help="steps per batch")
    parser.add_argument("--repeats", type=int, default=5, help="batches (the median is shown)")
    parser.add_argument("--image-size", type=int, default=64, help="camera image side (px)")
    args = parser.parse_args()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"{args.repeats} x {args.steps} steps, camera {args.image_size} px, load average "
          f"{os.getloadavg()[0]:.1f} at the start")
    period = gymnasium.make(f"capsule_drake:{ENV_ID}").unwrapped.control_period
    rows = []
    for label, observations in (("default", DEFAULT_OBSERVATIONS),
                                ("with camera", ("camera",) + DEFAULT_OBSERVATIONS)):
        one = single(observations, args.image_size, args.steps, args.repeats)
        rows.append((label, 1, one["rates"], one))
        two = vector(observations, args.image_size, args.steps, args.repeats)
        rows.append((label, 2, two["rates"], None))
    print(f"{'observations':<14}{'envs':>5}{'steps/s (median)':>18}{'min-max':>14}"
          f"{'real-time factor':>18}{'per CPU s':>11}{'build (s)':>11}{'reset (s)':>11}")
    for label, count, rates, extra in rows:
        rate = statistics.median(rates)
        cpu = f"{extra['cpu_rate']:.1f}" if extra else "-"
        build = f"{extra['build_s']:.1f}" if extra else "-"
        reset = f"{extra['reset_s']:.3f}" if extra else "-"
        print(f"{label:<14}{count:>5}{rate:>18.1f}{f'{min(rates):.1f}-{max(rates):.1f}':>14}"
              f"{rate * period:>18.2f}{cpu:>11}{build:>11}{reset:>11}")
    print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
