"""Forked trace workers run with one torch thread and one BLAS thread (asked of the workers
themselves), whatever the parent uses."""

from __future__ import annotations

import os
import time

import numpy as np
import torch
from threadpoolctl import threadpool_info

from torch_brdf.parallel.tracepool import TracePool
from torch_brdf.scene.embree import CHUNK, HitArrays, TraceKernel


class _AskingKernel(TraceKernel):
    """Writes, per ray, the tracing process's pid (object_id), torch threads (prim_id) and
    BLAS threads (t) instead of tracing."""

    def __init__(self):
        super().__init__(None, np.zeros((1, 21), np.float32), np.zeros(1, np.int64), np.ones(1, bool))

    def commit(self) -> None:
        pass

    def trace(self, o, d, out: HitArrays) -> None:
        time.sleep(0.02)  # let every process take chunks
        blas = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
        out.object_id[:] = os.getpid()
        out.prim_id[:] = torch.get_num_threads()
        out.t[:] = max(blas, default=1)


def test_workers_run_one_torch_and_one_blas_thread():
    n = 24 * CHUNK
    o = np.zeros((n, 3), np.float32)
    out = HitArrays.empty(n)
    before = torch.get_num_threads()
    torch.set_num_threads(2)  # the parent's own setting must not leak into the workers
    pool = TracePool(_AskingKernel(), 3)
    try:
        pool.trace(o, o, out)
        pool.trace(o, o, out)  # a reused pool keeps the setting
    finally:
        pool.close()
        torch.set_num_threads(before)
    pids = out.object_id.astype(np.int64)
    workers = pids != os.getpid()
    assert workers.any(), "no chunk was traced by a worker"
    assert set(out.prim_id[workers].tolist()) == {1}
    assert set(out.t[workers].tolist()) == {1.0}
    assert set(out.prim_id[~workers].tolist()) <= {2}  # the parent's chunks: its own setting
