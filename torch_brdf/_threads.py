"""Thread settings for small dense kernels."""

from __future__ import annotations

from contextlib import contextmanager

import torch


@contextmanager
def single_thread(enabled: bool = True):
    """Use one torch intra-op thread inside the block (restored on exit).

    Small kernels (a 147 x 192 product, a 100 x 100 Cholesky) are up to ~10-40x slower with two
    threads on a shared 2-core machine (thread hand-off under load; cf. OPENBLAS_NUM_THREADS=1
    in ../shared/FACTS.md). ``enabled=False`` leaves the setting alone.
    """
    n = torch.get_num_threads()
    if enabled:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)
