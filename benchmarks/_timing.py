"""The timing loop every benchmark uses: best and median wall time over repeats, and the last result."""
from __future__ import annotations

import statistics
import time
from typing import Callable


def timeit(func: Callable[[], object], repeat: int) -> tuple[float, float, object]:
    """Run ``func`` ``repeat`` times; return (best seconds, median seconds, the last result)."""
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = func()
        times.append(time.perf_counter() - t0)
    return min(times), statistics.median(times), out
