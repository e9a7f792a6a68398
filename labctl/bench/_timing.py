"""Shared timing helper for the benchmarks: medians of repeated calls."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable


def median_time(fn: Callable[[], object], repeat: int = 50, warmup: int = 3) -> float:
    """Median wall time (s) of ``fn()`` over ``repeat`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    return statistics.median(samples)


def row(case: str, median_s: float, baseline: str | None = None, baseline_s: float | None = None, **extra):
    """A bench row; ``ratio`` is baseline time / this time (>1 means faster than the baseline)."""
    r = {"case": case, "median_s": median_s, "baseline": baseline, **extra}
    if baseline_s is not None and median_s > 0:
        r["ratio"] = baseline_s / median_s
    return r
