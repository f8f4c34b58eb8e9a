"""The GI precompute through the local executor and through Ray with 1 and 2 workers, and a scale-out model.

    python benchmarks/scaleout.py [--quick]

Scene: the glossy Cornell box, series (64,1,1,1), 4 bounces; 128x128 at 16 spp in 16 tiles
(``--quick``: 64x64 at 8 spp in 8 tiles). Each Ray figure is the best of two runs after a
warm-up run (workers started and the scene loaded; ``ray1_cold_s``, ``ray2_cold_s`` are the
first runs). Prints progress, then one JSON object as the last line:

* ``local_s``, ``ray1_s``, ``ray2_s`` and ``*_tiles_per_s``; ``ray_equals_local`` (both Ray
  results equal the local one bit for bit); ``ray2_over_local`` (goal <= 1.1).
* ``task_overhead_s``: round trip of an empty task through the same path (submit, schedule,
  return), measured over 50 tasks; ``result_mb_per_tile``: what a tile sends back through the
  object store; ``context_mb``: the pickled scene and settings, put once;
  ``transfer_s_per_tile``: ``ray.get`` of an object of ``result_mb_per_tile`` from the store.
* ``tile_s``: worker seconds per tile (``ray1_s / tiles``), ``driver_s_per_tile``: the
  driver's serial work per tile (assembling the record, from ``meta["split"]``, plus
  ``write_s_per_tile``, writing the tile into a checkpoint folder as the CLI does).
* the model (stated in the README): a 1024x1024, 1024 spp precompute as ``n`` tiles on ``N``
  nodes of 2 workers. Tile sizing for that scene: 16 rows (16k pixels, 16.8M paths, a few
  minutes of work) while there are at most 64 tiles per 2N workers, otherwise ``n = 4 * 2N``
  tiles (at N = 64: 512 tiles of 2 rows, 2M paths each), so that each task runs for seconds
  to minutes and its scheduling round trip and result transfer are a small fraction:
  ``T(N) = max(R * c, c + n * t_driver) + t_driver`` with ``R = ceil(n / 2N)`` rounds and
  ``c = t_tile + task_overhead + transfer`` one task (the driver numbers the terms of tile k,
  in tile order, while later tiles compute; it starts when the first tile arrives), with
  ``t_tile`` the measured worker seconds per path times the paths of a tile and ``t_driver``
  the measured driver seconds per tile (numbering the tile's terms, re-sorting its blocks when
  needed, writing it) scaled by the entries of a tile (entries per pixel grow as spp^0.54:
  11 MB at 64 spp, ~50 MB at 1024 spp on the 128² box, ../shared/FACTS.md) and ``transfer``
  the measured ``ray.get`` of a tile's result scaled the same way;
  ``predicted_speedup_N = T(1) / T(N)`` for N = 8 and 64, and ``predicted_s_*``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pickle
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.transport.polynomial import precompute_polynomial

sys.path.insert(0, os.path.dirname(__file__))
from _timing import best_of


def _same(a, b) -> bool:
    xa, xb = a.to_arrays()[0], b.to_arrays()[0]
    return sorted(xa) == sorted(xb) and all(np.array_equal(xa[k], xb[k]) for k in xa)


def _noop(i: int) -> int:
    return i


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    args = ap.parse_args()
    import ray

    res, spp, rows = (64, 8, 8) if args.quick else (128, 16, 8)
    sc = cornell_box_glossy(res)
    kw = {"series": "64,1,1,1", "spp": spp, "seed": 0, "tile_rows": rows, "progress": False}
    tiles = -(-res // rows)
    out: dict = {"quick": args.quick, "resolution": res, "spp": spp, "tiles": tiles, "cpus": os.cpu_count()}
    out["load_avg_start"] = os.getloadavg()[0]
    out["local_s"], local = best_of(lambda: precompute_polynomial(sc, **kw), 2)
    ck = tempfile.mkdtemp(prefix="tbck")  # what a tile sends back: the size of its cached arrays
    written = precompute_polynomial(sc, **kw, checkpoint=ck, keep_checkpoint=True)
    out["write_s_per_tile"] = written.meta["split"]["write"] / tiles  # the CLI keeps tiles (--resume)
    tile_bytes = sum(f.stat().st_size for f in Path(ck).glob("*.npz")) / tiles
    shutil.rmtree(ck, ignore_errors=True)
    print(f"local {out['local_s']:.2f} s", flush=True)
    tmp = tempfile.mkdtemp(prefix="tbso")
    os.environ.setdefault("RAY_TMPDIR", tmp)
    # agents and workers that start slowly on a loaded machine are waited for (defaults 15 s / 60 s)
    os.environ.setdefault("RAY_agent_register_timeout_ms", "180000")
    os.environ.setdefault("RAY_worker_register_timeout_seconds", "300")
    equal = True
    try:
        for n in (1, 2):
            t0 = time.perf_counter()
            ray.init(num_cpus=n, include_dashboard=False, log_to_driver=False, _temp_dir=tmp)
            out[f"ray{n}_init_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            T = precompute_polynomial(sc, **kw, executor="ray")
            out[f"ray{n}_cold_s"] = time.perf_counter() - t0
            out[f"ray{n}_s"], T = best_of(lambda: precompute_polynomial(sc, **kw, executor="ray"), 2)
            equal &= _same(T, local)
            print(f"ray {n} worker(s): {out[f'ray{n}_s']:.2f} s (cold {out[f'ray{n}_cold_s']:.2f} s)", flush=True)
            if n == 1:
                task = ray.remote(num_cpus=1)(_noop)
                ray.get(task.remote(0))
                t0 = time.perf_counter()
                for i in range(50):
                    ray.get(task.remote(i))
                out["task_overhead_s"] = (time.perf_counter() - t0) / 50
                blob = np.zeros(int(tile_bytes) // 8 + 1)
                ref = ray.put(blob)
                out["transfer_s_per_tile"], _ = best_of(lambda ref=ref: ray.get(ref), 5)
                out["result_mb_per_tile"] = blob.nbytes / 2**20
                out["context_mb"] = len(pickle.dumps(sc)) / 2**20
                split = T.meta["split"]
            ray.shutdown()
    finally:
        ray.shutdown()
        shutil.rmtree(tmp, ignore_errors=True)
    out["ray_equals_local"] = bool(equal)
    for k in ("local", "ray1", "ray2"):
        out[f"{k}_tiles_per_s"] = tiles / out[f"{k}_s"]
    out["ray2_over_local"] = out["ray2_s"] / out["local_s"]
    # -- the model ---------------------------------------------------------------------------
    paths = res * res * spp
    out["tile_s"] = out["ray1_s"] / tiles
    out["driver_s_per_tile"] = split["assemble"] / tiles + out["write_s_per_tile"]
    worker_s_per_path = (out["ray1_s"] - out["driver_s_per_tile"] * tiles - out["task_overhead_s"] * tiles) / paths
    big_res, big_spp, tile_px = 1024, 1024, 16 * 1024
    entries_scale = (tile_px / (res * res / tiles)) * (big_spp / spp) ** 0.54
    t_driver = out["driver_s_per_tile"] * entries_scale
    transfer = out["transfer_s_per_tile"] * entries_scale

    def model(nodes: int) -> float:
        n_tiles = max(big_res * big_res // tile_px, 4 * 2 * nodes)
        t_tile = worker_s_per_path * big_res * big_res * big_spp / n_tiles
        scale = (big_res * big_res // tile_px) / n_tiles  # the same entries over more tiles
        per_tile_driver, per_task = t_driver * scale, t_tile + out["task_overhead_s"] + transfer * scale
        rounds = math.ceil(n_tiles / (2 * nodes))
        return max(rounds * per_task, per_task + n_tiles * per_tile_driver) + per_tile_driver

    base = model(1)
    for n in (8, 64):
        out[f"predicted_s_{n}"] = model(n)
        out[f"predicted_speedup_{n}"] = base / model(n)
    out["predicted_s_1"] = base
    out["load_avg_end"] = os.getloadavg()[0]
    out = {k: (round(v, 6) if isinstance(v, float) and math.isfinite(v) else v) for k, v in out.items()}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
