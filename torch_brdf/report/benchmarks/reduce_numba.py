"""Is a numba kernel faster than torch for the GI precompute's per-tile reduction?

    python benchmarks/reduce_numba.py [--quick] [--n 2000000]

The reduction of :func:`torch_brdf.transport.polynomial.reduce._reduce`: int64 keys (n,) and
float64 weights (n, 3) -> sorted unique keys, each row's group, each group's first row and
the per-group sums in row order. torch (``unique`` + ``scatter_reduce`` + ``index_add_``, one
thread) against two fused numba kernels: a stable merge sort and an LSD radix sort (16-bit
digits), each followed by one pass. numba is not a dependency of torch_brdf (this script
prints ``"numba": null`` without it). Prints one JSON object: ``first_call_s`` (JIT compile,
or loading the on-disk cache on later runs), best-of-3 seconds per method, whether each
kernel equals torch bit for bit, and the load average. ``--quick``: 200,000 entries (what the
report runs).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import numpy as np
import torch


def _kernels():
    from numba import njit

    @njit(cache=True)
    def groups(key, order, w):
        n, c = key.shape[0], w.shape[1]
        u = 0
        for i in range(n):
            if i == 0 or key[order[i]] != key[order[i - 1]]:
                u += 1
        uniq, first = np.empty(u, np.int64), np.empty(u, np.int64)
        s, inv = np.zeros((u, c), np.float64), np.empty(n, np.int64)
        g = -1
        for i in range(n):
            r = order[i]
            if i == 0 or key[r] != key[order[i - 1]]:
                g += 1
                uniq[g], first[g] = key[r], r
            inv[r] = g
            for k in range(c):
                s[g, k] += w[r, k]
        return uniq, inv, first, s

    @njit(cache=True)
    def merge(key, w):
        return groups(key, np.argsort(key, kind="mergesort"), w)

    @njit(cache=True)
    def radix(key, w):
        n = key.shape[0]
        order, tmp = np.arange(n), np.empty(n, np.int64)
        top = 0
        for i in range(n):
            top = max(top, key[i])
        shift = 0
        while (top >> shift) > 0:
            cnt = np.zeros(65537, np.int64)
            for i in range(n):
                cnt[((key[order[i]] >> shift) & 65535) + 1] += 1
            for d in range(65536):
                cnt[d + 1] += cnt[d]
            for i in range(n):
                r = order[i]
                d = (key[r] >> shift) & 65535
                tmp[cnt[d]] = r
                cnt[d] += 1
            order, tmp = tmp, order
            shift += 16
        return groups(key, order, w)

    return merge, radix


def _torch(key, w):
    n = key.numel()
    uq, inv = torch.unique(key, return_inverse=True)
    first = torch.full((uq.numel(),), n, dtype=torch.long).scatter_reduce(0, inv, torch.arange(n), reduce="amin")
    return uq, inv, first, torch.zeros(uq.numel(), 3, dtype=torch.float64).index_add_(0, inv, w)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2_000_000, help="entries (a 16k-pixel tile at 64 spp has ~4 M)")
    ap.add_argument("--quick", action="store_true", help="200,000 entries")
    args = ap.parse_args()
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    n = 200_000 if args.quick else args.n
    key = torch.randint(0, 1 << 40, (n // 4,), generator=g)[torch.randint(0, n // 4, (n,), generator=g)]
    w = torch.rand(n, 3, generator=g, dtype=torch.float64)
    out: dict = {"n": n, "quick": args.quick, "unique": None}
    try:
        import numba
    except ImportError:
        out["numba"] = None
        print(json.dumps(out))
        return
    out["numba"] = numba.__version__
    os.environ.setdefault("NUMBA_CACHE_DIR", tempfile.mkdtemp(prefix="numba_cache_"))
    t0 = time.perf_counter()
    merge, radix = _kernels()
    merge(key[:8].numpy(), w[:8].numpy())
    radix(key[:8].numpy(), w[:8].numpy())
    out["first_call_s"] = time.perf_counter() - t0
    ref = _torch(key, w)
    out["unique"] = int(ref[0].numel())
    for name, fn in (("torch", _torch), ("numba_merge", merge), ("numba_radix", radix)):
        best = float("inf")
        for _ in range(3):
            t0 = time.perf_counter()
            got = fn(key, w) if name == "torch" else fn(key.numpy(), w.numpy())
            best = min(best, time.perf_counter() - t0)
        out[f"{name}_s"] = best
        if name != "torch":
            same = [np.array_equal(np.asarray(a), b.numpy()) for a, b in zip(got, ref, strict=True)]
            out[f"{name}_equals_torch"] = all(same)
    out["load_avg"] = list(os.getloadavg())
    print(json.dumps(out))


if __name__ == "__main__":
    main()
