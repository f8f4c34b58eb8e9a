"""Timing helper shared by the benchmark scripts (imported as a sibling module)."""

from __future__ import annotations

import math
import time


def best_of(fn, repeats: int = 3):
    """Run ``fn`` ``repeats`` times: (the fastest wall-clock seconds, the last result)."""
    best, out = math.inf, None
    for _ in range(max(1, int(repeats))):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out
