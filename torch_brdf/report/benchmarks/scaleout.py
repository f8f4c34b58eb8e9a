"""The GI precompute through the local executor and through Ray with 1 and 2 workers, and a scale-out model.

    python benchmarks/scaleout.py [--quick] [--ray-start-s S]

Scene: the glossy Cornell box, series (64,1,1,1), 4 bounces; 128x128 at 16 spp in 16 tiles
(``--quick``: 64x64 at 8 spp in 8 tiles). Each Ray figure is the best of two runs after a
warm-up run (workers started and the scene loaded; ``ray1_cold_s``, ``ray2_cold_s`` are the
first runs). Prints progress, then one JSON object as the last line:

* ``local_s``, ``ray1_s``, ``ray2_s`` and ``*_tiles_per_s``; ``ray_equals_local`` (both Ray
  results equal the local one bit for bit); ``ray2_over_local`` (goal <= 1.1).
* ``ray_skipped``: present only when Ray could not start within ``--ray-start-s`` seconds (600; quick 300)
  (its starts are retried until then; on a loaded machine a node can miss Ray's startup
  timeouts): "skipped: <reason>"; the local figures are still measured and the Ray ones and
  the model (which needs Ray's worker seconds) are left out.
* ``task_overhead_s``: round trip of an empty task through the same path (submit, schedule,
  return), measured over 50 tasks; ``result_mb_per_tile``: what a tile sends back through the
  object store; ``context_mb``: the pickled scene and settings, put once;
  ``transfer_s_per_tile``: ``ray.get`` of an object of ``result_mb_per_tile`` from the store.
* ``tile_s``: worker seconds per tile (``ray1_s / tiles``), ``assemble_s_per_tile``: the
  driver's assembly of the record per tile (``meta["split"]``: taking each tile's blocks, then
  numbering every term once all are in, spread over the tiles), ``write_s_per_tile``: writing
  the tile file a Ray worker encoded into the checkpoint folder as the CLI does, in the driver's
  writer thread (``local_write_s_per_tile``: encoding and writing it there), and
  ``driver_s_per_tile`` the larger of the two (the writes run beside the assembly, so not
  their sum).
* the model (stated in the cluster guide): a 1024x1024, 1024 spp precompute as ``n`` tiles on ``N``
  nodes of 2 workers. Tile sizing for that scene: 16 rows (16k pixels, 16.8M paths, a few
  minutes of work) while there are at most 64 tiles per 2N workers, otherwise ``n = 4 * 2N``
  tiles (at N = 64: 512 tiles of 2 rows, 2M paths each), so that each task runs for seconds
  to minutes and its scheduling round trip and result transfer are a small fraction:
  ``T(N) = max(R * c, c + n * t_driver) + t_driver`` with ``R = ceil(n / 2N)`` rounds and
  ``c = t_tile + task_overhead + transfer`` one task (the driver numbers the terms of tile k,
  in tile order, while later tiles compute; it starts when the first tile arrives), with
  ``t_tile`` the measured worker seconds per path times the paths of a tile and ``t_driver``
  the measured driver seconds per tile (``driver_s_per_tile``: assembly or writing, whichever
  is longer) scaled by the entries of a tile (entries per pixel grow as spp^0.54:
  11 MB at 64 spp, ~50 MB at 1024 spp on the 128² box, measured) and ``transfer``
  the measured ``ray.get`` of a tile's result scaled the same way;
  ``predicted_speedup_N = T(1) / T(N)`` for N = 8 and 64, and ``predicted_s_*``; the
  ``*_no_checkpoint`` keys: the same without tile files (``t_driver`` = assembly only).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import pickle
import shutil
import signal
import tempfile
import time
from pathlib import Path

import numpy as np

from torch_brdf.errors import TorchBRDFError
from torch_brdf.parallel.tiles import connect_ray
from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial

from ._timing import best_of


def _same(a, b) -> bool:
    xa, xb = a.to_arrays()[0], b.to_arrays()[0]
    return sorted(xa) == sorted(xb) and all(np.array_equal(xa[k], xb[k]) for k in xa)


def _stop_processes_under(folder: str) -> None:
    """SIGKILL what a failed Ray start left (the processes whose command line names ``folder``)."""
    for p in Path("/proc").iterdir():
        if p.name.isdigit() and int(p.name) != os.getpid():
            with contextlib.suppress(OSError):
                if folder.encode() in (p / "cmdline").read_bytes():
                    os.kill(int(p.name), signal.SIGKILL)


def _noop(i: int) -> int:
    return i


def _start_ray(budget_s: float, num_cpus: int, temp_dir: str) -> str | None:
    """Start a local Ray (``num_cpus`` workers), trying again while ``budget_s`` seconds have
    not passed since the first try. Returns None once started, else why it did not start."""
    t0, tries = time.perf_counter(), 0
    while True:
        tries += 1
        try:
            connect_ray(None, attempts=1, num_cpus=num_cpus, _temp_dir=temp_dir)
            return None
        except TorchBRDFError as exc:
            _stop_processes_under(temp_dir)  # what the failed start left
            spent = time.perf_counter() - t0
            print(f"Ray start {tries} failed after {spent:.0f} s: {exc}", flush=True)
            if spent >= budget_s:
                load, reason = os.getloadavg()[0], str(exc).splitlines()[0]
                what = f"Ray ({num_cpus} worker(s)) did not start in {tries} tries, {spent:.0f} s, load {load:.1f}"
                return f"skipped: {what}: {reason}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    ap.add_argument(
        "--ray-start-s",
        type=float,
        default=None,
        help="seconds to keep retrying Ray's start, then skip Ray "
        "(default 600; quick 300: Ray gives its node a hard-coded 30 s per try)",
    )
    args = ap.parse_args()
    import ray

    res, spp, rows = (64, 8, 8) if args.quick else (128, 16, 8)
    sc = cornell_box_glossy(res)
    kw = {"settings": PolynomialSettings("64,1,1,1", spp=spp, tile_rows=rows), "seed": 0, "progress": False}
    tiles = -(-res // rows)
    out: dict = {"quick": args.quick, "resolution": res, "spp": spp, "tiles": tiles, "cpus": os.cpu_count()}
    out["load_avg_start"] = os.getloadavg()[0]
    tmp = tempfile.mkdtemp(prefix="tbso")
    os.environ.setdefault("RAY_TMPDIR", tmp)
    os.environ["HOME"] = tmp  # Ray's auth token goes to ~/.ray: keep it in the run's folder
    # agents and workers that start slowly on a loaded machine are waited for (defaults 15 s / 60 s)
    os.environ.setdefault("RAY_agent_register_timeout_ms", "180000")
    os.environ.setdefault("RAY_worker_register_timeout_seconds", "300")
    results = []
    try:
        for n in (1, 2):
            t0 = time.perf_counter()
            skipped = _start_ray(args.ray_start_s or (300.0 if args.quick else 600.0), n, tmp)
            if skipped:
                out["ray_skipped"] = skipped
                break
            out[f"ray{n}_init_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            T = precompute_polynomial(sc, **kw, executor="ray")
            out[f"ray{n}_cold_s"] = time.perf_counter() - t0
            out[f"ray{n}_s"], T = best_of(lambda: precompute_polynomial(sc, **kw, executor="ray"), 2)
            results.append(T)
            print(f"ray {n} worker(s): {out[f'ray{n}_s']:.2f} s (cold {out[f'ray{n}_cold_s']:.2f} s)", flush=True)
            if n == 1:
                task = ray.remote(num_cpus=1)(_noop)
                ray.get(task.remote(0))
                t0 = time.perf_counter()
                for i in range(50):
                    ray.get(task.remote(i))
                out["task_overhead_s"] = (time.perf_counter() - t0) / 50
                # what a tile sends back: about the size of its arrays
                blob = np.zeros(int(sum(v.nbytes for v in T.to_arrays()[0].values()) / tiles) // 8 + 1)
                ref = ray.put(blob)
                out["transfer_s_per_tile"], _ = best_of(lambda ref=ref: ray.get(ref), 5)
                out["result_mb_per_tile"] = blob.nbytes / 2**20
                out["context_mb"] = len(pickle.dumps(sc)) / 2**20
                split = T.meta["split"]
                ck = tempfile.mkdtemp(prefix="tbck")  # the CLI keeps tiles (--resume): Ray workers encode them
                written = precompute_polynomial(sc, **kw, executor="ray", checkpoint=ck)
                out["write_s_per_tile"] = written.meta["split"]["write"] / tiles  # the driver writes bytes
                shutil.rmtree(ck, ignore_errors=True)
            ray.shutdown()
    finally:
        ray.shutdown()
        _stop_processes_under(tmp)
        shutil.rmtree(tmp, ignore_errors=True)
    # local last: Ray starts (its raylet has 30 s) before this process forks its trace workers
    out["local_s"], local = best_of(lambda: precompute_polynomial(sc, **kw), 2)
    print(f"local {out['local_s']:.2f} s", flush=True)
    ck = tempfile.mkdtemp(prefix="tbck")
    written = precompute_polynomial(sc, **kw, checkpoint=ck)  # local: the driver encodes and writes
    out["local_write_s_per_tile"] = written.meta["split"]["write"] / tiles
    shutil.rmtree(ck, ignore_errors=True)
    out["local_tiles_per_s"] = tiles / out["local_s"]
    if "ray_skipped" in out:
        print(out["ray_skipped"], flush=True)
        out["load_avg_end"] = os.getloadavg()[0]
        print(json.dumps({k: (round(v, 6) if isinstance(v, float) else v) for k, v in out.items()}))
        return
    out["ray_equals_local"] = all(_same(T, local) for T in results)
    for k in ("ray1", "ray2"):
        out[f"{k}_tiles_per_s"] = tiles / out[f"{k}_s"]
    out["ray2_over_local"] = out["ray2_s"] / out["local_s"]
    # -- the model ---------------------------------------------------------------------------
    paths = res * res * spp
    out["tile_s"] = out["ray1_s"] / tiles
    out["assemble_s_per_tile"] = split["assemble"] / tiles
    # the writer thread writes tile k - 1 while the driver assembles tile k
    out["driver_s_per_tile"] = max(out["assemble_s_per_tile"], out["write_s_per_tile"])
    worker_s_per_path = (out["ray1_s"] - split["assemble"] - out["task_overhead_s"] * tiles) / paths
    big_res, big_spp, tile_px = 1024, 1024, 16 * 1024
    entries_scale = (tile_px / (res * res / tiles)) * (big_spp / spp) ** 0.54
    transfer = out["transfer_s_per_tile"] * entries_scale
    t_driver = 0.0

    def model(nodes: int) -> float:
        n_tiles = max(big_res * big_res // tile_px, 4 * 2 * nodes)
        t_tile = worker_s_per_path * big_res * big_res * big_spp / n_tiles
        scale = (big_res * big_res // tile_px) / n_tiles  # the same entries over more tiles
        per_tile_driver, per_task = t_driver * scale, t_tile + out["task_overhead_s"] + transfer * scale
        rounds = math.ceil(n_tiles / (2 * nodes))
        return max(rounds * per_task, per_task + n_tiles * per_tile_driver) + per_tile_driver

    # with tile files (the CLI's default --resume), and without (the API's default checkpoint=None)
    for suffix, per_tile in (("", out["driver_s_per_tile"]), ("_no_checkpoint", split["assemble"] / tiles)):
        t_driver = per_tile * entries_scale
        base = model(1)
        for n in (8, 64):
            out[f"predicted_s_{n}{suffix}"] = model(n)
            out[f"predicted_speedup_{n}{suffix}"] = base / model(n)
        out[f"predicted_s_1{suffix}"] = base
    out["load_avg_end"] = os.getloadavg()[0]
    out = {k: (round(v, 6) if isinstance(v, float) and math.isfinite(v) else v) for k, v in out.items()}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
