"""Interleaved timing for the benchmarks that compare solvers (a helper module, not a benchmark)."""

from __future__ import annotations

import statistics
import time
from typing import Callable


def interleaved(runs: dict[str, Callable[[], object]], repeats: int, warm_up: bool = False) -> dict:
    """``{name: (median seconds, last output)}`` of the callables in ``runs``, run in turn ``repeats``
    times so that load on the machine hits them alike; with ``warm_up`` each runs once untimed first."""
    outputs = {name: fn() for name, fn in runs.items()} if warm_up else {}
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, fn in runs.items():
            start = time.perf_counter()
            outputs[name] = fn()
            times[name].append(time.perf_counter() - start)
    return {name: (statistics.median(times[name]), outputs[name]) for name in runs}
