"""Timing helper shared by the benchmark scripts (run them from the repository root)."""

import statistics
import time


def median_us(fn, repeats: int = 7, number: int = 2000) -> float:
    """Median over `repeats` batches of `number` calls of the time per call (microseconds),
    after one warm-up call."""
    fn()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(number):
            fn()
        samples.append((time.perf_counter() - start) / number * 1e6)
    return statistics.median(samples)
