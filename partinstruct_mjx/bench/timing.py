"""Timing of jitted JAX calls: compile time kept apart, medians of repeats, device work awaited."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import jax
import numpy as np


@dataclass(frozen=True)
class Throughput:
    compile_s: float
    """First call (trace, compile, one run) minus one median call; a cache load where JAX's persistent cache is on."""
    per_s: float
    """Items per second, median over repeats."""
    spread: tuple[float, float]
    """Slowest and fastest repeat, items per second."""

    def cells(self) -> str:
        """Markdown cells: median, range over repeats, compile seconds."""
        return f"{self.per_s:,.0f} | {self.spread[0]:,.0f} - {self.spread[1]:,.0f} | {self.compile_s:.2f}"


def measure_throughput(call: Callable[[], jax.Array], batch_size: int, repeats: int, min_items: int) -> Throughput:
    """Time `call` (one batch of `batch_size` items) with JAX's caches cleared first; each repeat runs enough calls
    for `min_items` items and waits for the device."""
    jax.clear_caches()
    start = time.perf_counter()
    call().block_until_ready()
    first = time.perf_counter() - start
    calls = math.ceil(min_items / batch_size)
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            result = call()
        result.block_until_ready()
        rates.append(calls * batch_size / (time.perf_counter() - start))
    median = float(np.median(rates))
    return Throughput(max(first - batch_size / median, 0.0), median, (min(rates), max(rates)))
