"""The kernel's embree-only entry that no precomputation calls (``tb_intersect_only``, the
benchmarks' baseline of embree alone) against the tracer: the same geometry ids, and ``tfar``
honoured."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.transport.test_rays import _rays, _tracer
from torch_brdf.transport import _native

LIB = _native.library()
needs_cc = pytest.mark.skipif(LIB is None, reason="no C compiler here: only the torch path runs")


@needs_cc
def test_intersect_only_gives_the_tracer_object_ids():
    rt = _tracer()
    entry = rt.embree_hits()
    assert entry is not None  # the embreex layout checks pass with the pinned embreex
    o, d, _ = _rays(5000, 3)
    want = rt.trace(o, d)
    o32, d32 = np.ascontiguousarray(o.numpy(), np.float32), np.ascontiguousarray(d.numpy(), np.float32)
    geom = np.full(len(o32), 99, np.int32)
    n = LIB.tb_intersect_only(entry.scene, entry.intersect, len(o32), o32.ctypes.data, d32.ctypes.data, None,
                              geom.ctypes.data)  # fmt: skip
    assert n == int(want.hit.sum()) and 0 < n < len(o32)
    assert torch.equal(torch.from_numpy(geom).long(), want.object_id)
    # tfar half way to the first hit: nothing is hit (misses keep a far bound)
    tfar = np.where(want.hit.numpy(), want.t.numpy() / 2, 1e30).astype(np.float32)
    assert LIB.tb_intersect_only(entry.scene, entry.intersect, len(o32), o32.ctypes.data, d32.ctypes.data,
                                 tfar.ctypes.data, geom.ctypes.data) == 0  # fmt: skip
    assert (geom == -1).all()
    assert LIB.tb_intersect_only(entry.scene, entry.intersect, len(o32), o32.ctypes.data, d32.ctypes.data, None,
                                 None) == n  # fmt: skip
