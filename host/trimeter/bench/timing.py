"""How the benches time and weigh a call: best-of milliseconds, a cold start (the caches evicted), and the
Python heap's peak during it."""

from __future__ import annotations

import time
import tracemalloc
from collections.abc import Callable

import numpy as np


def timed_ms(fn: Callable[[], object]) -> float:
    t = time.perf_counter()
    fn()
    return (time.perf_counter() - t) * 1e3



_EVICT: list[np.ndarray] = []


def evict_caches() -> None:
    """Write 64 MB (twice this machine's last-level cache): whatever a fit had cached is gone."""
    if not _EVICT:
        _EVICT.append(np.zeros(8 << 20))
    _EVICT[0] += 1.0



def peak_bytes(fn: Callable[[], object]) -> int:
    """Peak of the Python heap (numpy arrays included) during fn(), above what was allocated before."""
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
