"""Latency of a JAX call as a user waits for it: one warm-up call (compilation), then the
median wall time of ``repeats`` calls, each waiting for its result (JAX dispatches
asynchronously)."""

import statistics
import time
from collections.abc import Callable
from typing import Any

import jax


def call_times_ms(fn: Callable[[], Any], repeats: int = 10) -> list[float]:
    """Milliseconds of each of ``repeats`` calls of ``fn()`` after one warm-up call."""
    if repeats < 1:
        raise ValueError(f"repeats: expected >= 1, got {repeats}")
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append((time.perf_counter() - start) * 1e3)
    return times


def median_ms(fn: Callable[[], Any], repeats: int = 10) -> float:
    """Median milliseconds of ``fn()`` over ``repeats`` calls after one warm-up call."""
    return statistics.median(call_times_ms(fn, repeats))
