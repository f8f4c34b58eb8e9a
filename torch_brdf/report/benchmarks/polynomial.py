"""BRDF editing with global illumination: precomputation, freezing, frames, and accuracy.

    python benchmarks/polynomial.py [--quick] [--precompute-only] [--baseline] [--torch-path]
    python benchmarks/polynomial.py --memory-only [--quick]

Scene: the glossy Cornell box (Ben-Artzi et al. 2008, Fig. 6b: Blinn-Phong n = 100 back wall,
coloured blocks, 7 editable objects). Prints progress, then one JSON object as the last line:

* ``precompute_s``: tensors for 256x256, series (64,1,1,1), 64 spp, 4 bounces (``--quick``:
  64x64, 8 spp); ``precompute_paths_per_s``; ``rays`` cast (closest-hit, shadow).
* ``rays_s``: the time embree alone (one process) takes to trace those rays, measured on the
  first rays of a second, 8x fewer-spp run in this process (recorded after the timed run; the
  timed run's tiles may trace in forked processes) and scaled by the timed run's total counts,
  best of two rounds, the faster per kind of ray of ``rays_embreex_s`` (one ``EmbreeScene.run``
  per batch) and ``rays_c_s`` (with the kernel: a C loop calling embree's ``rtcIntersect1`` /
  ``rtcOccluded1`` per ray, as the precompute's kernel casts them, null without it);
  ``precompute_over_rays``: the ratio (the goal is <= 1.5). ``precompute_processes``:
  processes that computed tiles at once (by default one per core unless the machine is busy;
  with ``--baseline`` one per core whatever the load), and with ``--baseline`` also
  ``one_process_s`` (tiles one after another in this process, without parallel tiles),
  ``speedup_over_one_process`` and ``equals_one_process`` (bit for bit).
* ``tile_timeline``: per tile of that precompute [tile, process id, start, end (wall seconds
  after the call began), CPU seconds]; ``serial_before_tiles_s`` / ``serial_after_tiles_s``
  the wall time before the first tile started and after the last ended (process start,
  assembly of the last tile, the record), ``tiles_cpu_s`` the tiles' CPU seconds and
  ``tiles_parallelism`` those over ``precompute_s`` (2 on two cores at perfect efficiency).
* ``native``: whether the compiled entry kernel (``transport/csrc``) ran;
  ``native_build_s``: seconds this process spent compiling it on first use (0 when the cached
  build was loaded), ``native_load_s`` building or loading it, both before and outside
  ``precompute_s``. With ``--torch-path`` also ``torch_path_s`` (the same precompute with the
  kernel off, ``TORCH_BRDF_NATIVE=0``), ``native_again_s`` (the kernel once more, after it),
  ``kernel_speedup`` (``torch_path_s / native_again_s``: both warm), ``kernel_cpu_speedup``
  (the same in CPU seconds of this process and its finished tile processes, ``*_cpu_s``: less
  sensitive to the load than wall time) and ``equals_torch_path`` (bit for bit: false since the
  per-vertex steps moved into the kernel, whose libm rounds differently in the last ulp; the
  tests compare the two paths with tolerances).
* ``split_s``: the profile split of that precompute (exclusive seconds): ``rays`` (embree
  calls with the hit interpolation, ``transport/rays.py``'s compiled loop or the tracer's
  embreex path with its array conversions), ``sampling`` (camera rays, light samples, frames, the
  direction mixture), ``brdf`` (band indices, quotients, fixed BRDFs), ``bookkeeping``
  (entries, per-path and per-tile reduction), ``assemble`` (sparse blocks, term tables),
  ``write`` (tile files; none without a checkpoint); ``split_other_s`` the rest.
* ``mitsuba_s`` (when mitsuba is installed): Mitsuba 3's path tracer on the same scene,
  resolution, spp and depth (max_depth 5 = 4 surface vertices), llvm variant when it works
  here (else scalar_rgb, reported in ``mitsuba_variant``); ``precompute_over_mitsuba``.
* ``mb_per_bounce`` (float32 values; ``mb_variance_per_bounce`` the variances kept beside).
* ``freeze_s``, ``frame_s``, ``stream_s`` at 512x512, (64,1,1,1), 4 bounces, M = 7 editable
  objects, freezing the glossy back wall (``--quick``: 128x128); the tensors for this part use
  ``freeze_spp`` paths per pixel, and ``freeze_entries`` says how many entries freezing read
  (``freeze_dense_entries``: what dense per-tile blocks would hold); ``freeze_load_avg`` (and
  ``..._after``) the load average around this part. ``frame_s`` (an edit of the wall and its
  frame) and ``stream_s`` (one pass summing every array the frame reads,
  ``PolynomialRenderer.frame_arrays``: ``stream_bytes``, ``stream_gb_per_s``) are each the
  fastest of 7 calls, each right after touching a buffer of twice the last-level cache
  (``cache_flush_mb``), so both read from memory; ``frame_warm_s`` without the flush.
  ``frame_over_stream``: the goal is <= 2 (memory bandwidth). ``frame_1thread_s``,
  ``stream_1thread_s`` and ``frame_over_stream_1thread``: the same pair on one thread each
  (the frame's thread count is otherwise tuned per call, the stream's torch's default; on a
  busy machine the one-thread pair is the steadier comparison).
* Several objects frozen: ``freeze_left_s`` (first visit of the left wall), ``switch_s`` (the
  median of four switches between the wall and the left wall, each after an edit of the other:
  the kept state is updated, not rebuilt), ``switch_over_freeze``, ``switch_unchanged_s`` (a
  switch back when nothing the state depends on changed: reused as is), ``frame_2_frozen_s`` /
  ``frame_3_frozen_s`` (cold frames with 2 and 3 states kept), ``frozen_objects``,
  ``frozen_cache_mb`` and its bound ``max_frozen_mb``; ``full_evaluation_s`` (no state).
* ``rel_rmse``: relative RMSE against a full-BRDF reference at ``reference_spp`` on 128x128
  (``--quick``: 32x32), pixels seeing the light excluded: Mitsuba 3's llvm variant at 4096
  spp when it runs here (``reference``), else ``reference_path_trace`` at 256 spp; keys
  the seed's teatray series ("128,1,1,1", "16,8,1,1", "128,8,1", "64,16") at 64 spp and the
  (64,1,1,1) series at "spp16", "spp64", "spp256", each with ``seconds`` and ``mb`` beside.
* ``approximation_rel_rmse``: (64,1,1,1) vs full-BRDF direct + diffuse indirect (1,1,1,1)
  (Fig. 7a) vs direct only (Fig. 7b), same reference.
* ``mitsuba_point``: Mitsuba 3 at the accuracy resolution and 256 spp (``--quick``: 64):
  ``seconds`` and ``rel_rmse`` against the same reference (the peer on the report's curve).
* ``mitsuba_vs_reference_rel_rmse`` and ``reference_seed_rel_rmse`` (two seeds of our
  reference at the Mitsuba spp): agreement within noise means the first is about the second.
* ``memory`` (with ``--memory`` or ``--memory-only``): peak RSS of precompute (with its save),
  freeze and the denoised freeze (``freeze(obj, "linear")``), each in a fresh subprocess, at two
  sizes (128² and 256², 8 spp; ``--quick``: 64² and 128²) of the glossy Cornell box
  (:mod:`torch_brdf.report.benchmarks._memory`): per stage ``peak_mb``, ``above_start_mb``,
  ``bytes_per_pixel``, ``bytes_per_pixel_sample`` and ``over_file`` at each size; per stage
  ``growth_over_file`` (the growth of the peak between the two sizes over the growth of the saved
  record: the multiple of the record a stage holds on large scenes) and
  ``growth_bytes_per_pixel`` (the same growth per pixel), and ``predicted_gb`` for a 512², 64-spp
  (0.26 GB record), a 1024², 64-spp (1.05 GB) and a 1024², 1024-spp (4.2 GB) scene: the
  precompute scales with its record (entries grow with spp), freezing and denoising with the
  pixels (the frozen object's dense basis images), each as the peak at the larger size plus the
  growth.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from torch_brdf.metrics import relative_rmse
from torch_brdf.parallel import threads as _threads
from torch_brdf.parallel.threads import usable_cores
from torch_brdf.parallel.tiles import wait_tile_processes
from torch_brdf.render.polynomial import PolynomialRenderer, emitter_mask, series_approximations
from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.transport import _native
from torch_brdf.transport.pathtrace import reference_path_trace
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial
from torch_brdf.transport.rays import NativeRays


def _materials(scene):
    return {o.name: scene.materials[o.material] for o in scene.objects if o.editable}


@contextmanager
def _recording_rays(scene, limit: int):
    """Keep the first ``limit`` closest-hit and shadow rays the scene's rays take, whether they go
    through its tracer (embreex) or the compiled kernel (:class:`NativeRays`), in the yielded log."""
    tracer = scene.tracer
    log = {"closest": [], "shadow": [], "n": {"closest": 0, "shadow": 0}}
    real_trace, real_occ = tracer.trace, tracer.occluded
    native_trace, native_occ = NativeRays.trace, NativeRays.occluded

    def keep(kind, o, d, t_max=None):
        if log["n"][kind] < limit:
            rays = [o.numpy().astype(np.float32), d.numpy().astype(np.float32)]
            if t_max is not None:
                tm = t_max.numpy() if isinstance(t_max, torch.Tensor) else np.full(o.shape[0], t_max)
                rays.append(tm.astype(np.float32))
            log[kind].append(tuple(rays))
            log["n"][kind] += o.shape[0]

    def trace(o, d):
        keep("closest", o, d)
        return real_trace(o, d)

    def occluded(o, d, t_max):
        keep("shadow", o, d, t_max)
        return real_occ(o, d, t_max)

    def n_trace(self, o, d):
        if self.rt is tracer:
            keep("closest", o, d)
        return native_trace(self, o, d)

    def n_occluded(self, o, d, t_max, rows=None):
        if self.rt is tracer:
            keep("shadow", o, d if rows is None else d[rows], t_max)
        return native_occ(self, o, d, t_max, rows)

    tracer.trace, tracer.occluded = trace, occluded
    NativeRays.trace, NativeRays.occluded = n_trace, n_occluded
    try:
        yield log
    finally:
        del tracer.trace, tracer.occluded
        NativeRays.trace, NativeRays.occluded = native_trace, native_occ


def _embree_seconds(scene, log, totals) -> dict[str, float]:
    """Embree alone on the recorded rays, scaled to the run's total ray counts, best of two rounds:
    ``embreex`` (``EmbreeScene.run`` per batch) and, with the compiled kernel, ``c`` (a C loop
    calling ``rtcIntersect1`` / ``rtcOccluded1`` per ray on the same scene, as the precompute's
    kernel does, keeping only the geometry id / the occlusion). ``fastest``: per kind of ray the
    faster of the two, summed (the strictest baseline)."""
    from embreex import mesh_construction, rtcore_scene

    from torch_brdf.scene.embree import embree_entry, embree_function

    es = rtcore_scene.EmbreeScene()
    for obj in scene.objects:
        v = np.ascontiguousarray(obj.mesh.vertices, dtype=np.float32)
        f = np.ascontiguousarray(obj.mesh.faces, dtype=np.int32)
        mesh_construction.TriangleMesh(es, v, f)
    es.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))  # the BVH, outside the timing
    lib, entry, intersect = _native.library(), embree_entry(es), embree_function("rtcIntersect1")
    c_loop = lib is not None and entry is not None and intersect is not None

    def embreex(kind, b):
        if kind == "closest":
            es.run(b[0], b[1], output=1)
        else:
            es.run(b[0], b[1], query="OCCLUDED", dists=np.minimum(b[2], 1e37))

    def c(kind, b):
        out = np.empty(len(b[0]), np.int32 if kind == "closest" else np.uint8)
        if kind == "closest":
            lib.tb_intersect_only(entry[0], intersect, len(b[0]), b[0].ctypes.data, b[1].ctypes.data, None,
                                  out.ctypes.data)  # fmt: skip
        else:
            lib.tb_occluded_rays(entry[0], entry[1], len(b[0]), b[0].ctypes.data, b[1].ctypes.data, len(b[1]),
                                 None, b[2].ctypes.data, out.ctypes.data)  # fmt: skip

    secs = {"embreex": 0.0, "c": 0.0, "fastest": 0.0}
    for kind in ("closest", "shadow"):
        n = sum(b[0].shape[0] for b in log[kind])
        if n == 0:
            continue
        best = {}
        for name, fn in [("embreex", embreex)] + ([("c", c)] if c_loop else []):
            rounds = []
            for _ in range(2):
                t0 = time.perf_counter()
                for b in log[kind]:
                    fn(kind, b)
                rounds.append((time.perf_counter() - t0) * totals[kind] / n)
            best[name] = min(rounds)
            secs[name] += best[name]
        secs["fastest"] += min(best.values())
    if not c_loop:
        del secs["c"]
    return secs


def _cpu_seconds() -> float:
    """User + system CPU seconds of this process and its finished children (forked tiles, once
    they have exited; the scene's trace process, which lives on, is not counted: ray casting is
    outside)."""
    wait_tile_processes()
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def _mitsuba(scene, spp, max_bounces, quiet=False):
    try:
        from torch_brdf.transport import mitsuba as tm
    except ImportError:
        return None
    if not tm.mitsuba_available():
        return None
    variant = tm.default_variant()
    img, secs = tm.render_mitsuba(scene, spp=spp, max_bounces=max_bounces, seed=0, variant=variant, return_seconds=True)
    return {"image": img, "seconds": secs, "variant": variant}


def _llc_bytes() -> int:
    """The largest CPU cache (bytes) sysfs reports for CPU 0; 32 MiB when it reports none."""
    best = 0
    for d in Path("/sys/devices/system/cpu/cpu0/cache").glob("index*"):
        try:
            size = (d / "size").read_text().strip()
        except OSError:
            continue
        units = {"K": 2**10, "M": 2**20, "G": 2**30}
        best = max(best, int(size[:-1]) * units[size[-1]] if size[-1] in units else int(size))
    return best or 32 * 2**20


class _CacheFlush:
    """Touching (read and write) a buffer of twice the last-level cache pushes earlier data out
    of every cache: a timing right after starts from memory."""

    def __init__(self):
        self.buffer = torch.zeros(2 * max(_llc_bytes(), 32 * 2**20) // 4)

    def __call__(self):
        self.buffer.add_(1.0)


def _cold(fn, flush, repeats: int) -> float:
    """Fastest of ``repeats`` calls of ``fn``, each right after a cache flush (seconds)."""
    best = math.inf
    for _ in range(repeats):
        flush()
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _freeze_and_frames(q: bool, out: dict) -> None:
    """Freezing the back wall and its frames at 512² (128² quick) into ``out``; then several
    objects kept frozen: the switches between them and frames with 2 and 3 states kept."""
    fres, fspp = (128, 2) if q else (512, 4)
    sc5 = cornell_box_glossy(fres)
    T5 = precompute_polynomial(sc5, PolynomialSettings("64,1,1,1", spp=fspp), seed=1, progress=True)
    R = PolynomialRenderer(T5, _materials(sc5))
    out["freeze_resolution"], out["freeze_spp"] = fres, fspp
    out["freeze_entries"] = T5.num_entries
    out["freeze_dense_entries"] = T5.num_dense_entries  # what dense per-tile blocks would hold
    out["freeze_load_avg"] = list(os.getloadavg())
    t0 = time.perf_counter()
    R.freeze("back")
    out["freeze_s"] = time.perf_counter() - t0
    flush = _CacheFlush()
    out["cache_flush_mb"] = flush.buffer.numel() * 4 / 2**20
    base = {o: R.c[T5.object_id(o)].clone() for o in ("back", "left", "floor")}
    k = [0]

    def edit(obj):
        def run():
            k[0] += 1
            R.set_coefficients(obj, base[obj] * (1 + 0.01 * (k[0] % 7)))
            return R()

        return run

    for _ in range(4 * _threads.TRIALS):  # the CSR arrays are made on first use; the tuner measures thread counts
        edit("back")()
    out["frame_s"] = _cold(edit("back"), flush, 7)  # (the edit's own cost, Eq. 37, is inside)
    out["frame_warm_s"] = min(_cold(edit("back"), lambda: None, 1) for _ in range(7))
    out["stream_s"] = _cold(R.stream, flush, 7)
    out["stream_bytes"] = sum(a.numel() * a.element_size() for a in R.frame_arrays())
    out["stream_gb_per_s"] = out["stream_bytes"] / out["stream_s"] / 1e9
    out["frame_over_stream"] = out["frame_s"] / out["stream_s"]
    # the same pair on one thread each: on a shared machine the least disturbed comparison
    R.threads = 1
    with _threads.single_thread():
        edit("back")()
        out["frame_1thread_s"] = _cold(edit("back"), flush, 7)
        out["stream_1thread_s"] = _cold(R.stream, flush, 7)
    R.threads = None
    out["frame_over_stream_1thread"] = out["frame_1thread_s"] / out["stream_1thread_s"]
    out["frozen_mb"] = R.frozen_nbytes / 2**20
    # several objects: first visits contract, later visits reuse or update the kept state
    t0 = time.perf_counter()
    R.freeze("left")
    out["freeze_left_s"] = time.perf_counter() - t0
    for _ in range(4 * _threads.TRIALS):
        edit("left")()
    out["frame_2_frozen_s"] = _cold(edit("left"), flush, 7)
    switches = []
    for obj in ("back", "left", "back", "left"):  # each switch follows an edit of the other object
        t0 = time.perf_counter()
        R.freeze(obj)
        switches.append(time.perf_counter() - t0)
        edit(obj)()
    out["switch_s"] = sorted(switches)[len(switches) // 2]
    out["switch_over_freeze"] = out["switch_s"] / out["freeze_s"]
    R.freeze("back")  # (left was just edited: back's state is updated)
    t0 = time.perf_counter()
    R.freeze("left")  # back has not changed since left's last visit: its state is reused as is
    out["switch_unchanged_s"] = time.perf_counter() - t0
    R.freeze("floor")
    R.freeze("back")
    out["frame_3_frozen_s"] = _cold(edit("back"), flush, 7)
    out["frozen_objects"] = R.frozen_objects
    out["frozen_cache_mb"] = R.frozen_cache_nbytes / 2**20
    out["max_frozen_mb"] = R.max_frozen_bytes / 2**20
    t0 = time.perf_counter()
    R.evaluate()
    out["full_evaluation_s"] = time.perf_counter() - t0
    out["freeze_load_avg_after"] = list(os.getloadavg())
    print(
        f"freeze {out['freeze_s']:.2f} s, frame {out['frame_s'] * 1e3:.2f} ms, stream {out['stream_s'] * 1e3:.2f} ms "
        f"({out['stream_gb_per_s']:.1f} GB/s), switch {out['switch_s'] * 1e3:.1f} ms",
        flush=True,
    )


def _series_errors(q: bool, sca, ref, mask, rspp: int, out: dict) -> None:
    """``out["rel_rmse"]``: each series' relative RMSE against the reference (a reference of the
    same depth for series of other bounces), seconds and MB."""
    rel, refs = {}, {}
    runs = [(s, 64, s) for s in ("128,1,1,1", "16,8,1,1", "128,8,1", "64,16")]
    runs += [("64,1,1,1", n, f"spp{n}") for n in ((16, 64) if q else (16, 64, 256))]
    for series, n, key in runs:
        t0 = time.perf_counter()
        Tk = precompute_polynomial(sca, PolynomialSettings(series, spp=n), seed=2, progress=False)
        secs = time.perf_counter() - t0
        img = PolynomialRenderer(Tk, _materials(sca)).evaluate()
        bounces = Tk.series.bounces
        r = ref
        if bounces != 4:  # the teatray series with fewer bounces: a reference of that depth
            r = refs.get(bounces)
            if r is None:
                hi = _mitsuba(sca, rspp, bounces, quiet=True) if out["reference"].startswith("mitsuba") else None
                r = (
                    hi["image"]
                    if hi is not None
                    else reference_path_trace(sca, spp=rspp, max_bounces=bounces, seed=124, progress=False)
                )
                refs[bounces] = r
        rel[key] = {
            "rel_rmse": relative_rmse(img, r, mask),
            "seconds": secs,
            "mb": sum(Tk.memory_per_bounce().values()) / 2**20,
            "bounces": bounces,
        }
        print(key, rel[key], flush=True)
    out["rel_rmse"] = rel


def _args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    ap.add_argument("--precompute-only", action="store_true", help="stop after the precompute, rays and Mitsuba")
    ap.add_argument(
        "--baseline", action="store_true", help="also time the precompute with tiles in one process (processes=1)"
    )
    ap.add_argument(
        "--torch-path", action="store_true", help="also time the precompute with the compiled kernel off (torch path)"
    )
    ap.add_argument("--memory", action="store_true", help="also measure peak RSS per stage (subprocesses)")
    ap.add_argument("--memory-only", action="store_true", help="only the peak RSS per stage")
    return ap.parse_args()


#: record sizes (GB) of the scenes the memory keys predict for (series 64,1,1,1; the 1024-spp
#: size from the entries' growth with spp measured on the glossy Cornell box)
RECORD_GB = {"512_spp64": 0.26, "1024_spp64": 1.05, "1024_spp1024": 4.2}


def _memory_keys(quick: bool) -> dict:
    from torch_brdf.report.benchmarks._memory import stage_peaks

    small, large = (64, 128) if quick else (128, 256)
    return memory_model(stage_peaks(small, 8), stage_peaks(large, 8), os.getloadavg()[0])


def memory_model(a: dict, b: dict, load: float) -> dict:
    """The memory keys from two :func:`_memory.stage_peaks` results (see the module docstring)."""
    out: dict = {"small": a, "large": b, "load": load}
    grow_file = b["file_mb"] - a["file_mb"]
    grow_pixels = b["resolution"] ** 2 - a["resolution"] ** 2
    for stage in ("precompute", "freeze", "denoise"):
        grow = max(0.0, b[stage]["peak_mb"] - a[stage]["peak_mb"])
        k, per_pixel = grow / grow_file, grow * 2**20 / grow_pixels
        pred = {}
        for name, gb in RECORD_GB.items():
            pixels = int(name.split("_")[0]) ** 2
            if stage == "precompute":
                more = k * (gb * 1024 - b["file_mb"])
            else:
                more = per_pixel * (pixels - b["resolution"] ** 2) / 2**20
            pred[name] = round((b[stage]["peak_mb"] + more) / 1024, 2)
        out[stage] = {"growth_over_file": round(k, 2), "growth_bytes_per_pixel": round(per_pixel), "predicted_gb": pred}
    return out


def _same(one, other) -> bool:
    """The two records' arrays are equal."""
    a, b = one.to_arrays()[0], other.to_arrays()[0]
    return sorted(a) == sorted(b) and all(np.array_equal(a[k], b[k]) for k in a)


def _timeline(out: dict, tl: list) -> None:
    """The tiles' timeline ([tile, process, start, end, CPU s], s after the call began) into ``out``."""
    out["tile_timeline"] = tl
    out["serial_before_tiles_s"] = min(r[2] for r in tl)
    out["serial_after_tiles_s"] = out["precompute_s"] - max(r[3] for r in tl)
    out["tiles_cpu_s"] = sum(r[4] for r in tl)
    out["tiles_parallelism"] = out["tiles_cpu_s"] / out["precompute_s"]


def _native_load(out: dict) -> None:
    t0 = time.perf_counter()  # the kernel's first-use build (or load), outside precompute_s
    out["native"] = _native.library() is not None
    out["native_load_s"], out["native_build_s"] = time.perf_counter() - t0, _native.build_seconds()


def _prologue(args, out: dict) -> bool:
    """The memory keys (``--memory``, ``--memory-only``: then printed, True), else the kernel's load."""
    if args.memory or args.memory_only:
        out["memory"] = _memory_keys(args.quick)
        if args.memory_only:
            print(json.dumps(out))
            return True
    _native_load(out)
    return False


def main() -> None:
    args = _args()
    q = args.quick
    out: dict = {"quick": q}
    if _prologue(args, out):  # --memory-only: printed, nothing else to run
        return

    # -- precomputation at 256^2, 64 spp (and rays, Mitsuba) -----------------------------------
    res, spp = (64, 8) if q else (256, 64)
    sc = cornell_box_glossy(res)
    t0 = time.perf_counter()
    forked = {"processes": usable_cores()} if args.baseline else {}  # else the default (load-aware)
    T = precompute_polynomial(sc, PolynomialSettings("64,1,1,1", spp=spp), seed=0, progress=True, **forked)
    out["precompute_s"] = time.perf_counter() - t0
    out["precompute_processes"] = T.meta["processes"]
    if T.meta["timeline"]:
        _timeline(out, T.meta["timeline"])

    def again(**kw):
        """The same precompute once more -> (tensors, seconds); CPU seconds in ``cpu[0]``."""
        t0, c0 = time.perf_counter(), _cpu_seconds()
        T_ = precompute_polynomial(sc, PolynomialSettings("64,1,1,1", spp=spp), seed=0, progress=True, **kw)
        cpu[0] = _cpu_seconds() - c0
        return T_, time.perf_counter() - t0

    cpu = [0.0]
    if args.baseline:  # the same precompute with its tiles in this process, one after another
        T1, out["one_process_s"] = again(processes=1)
        out["speedup_over_one_process"] = out["one_process_s"] / out["precompute_s"]
        out["equals_one_process"] = _same(T, T1)
        out["one_process_split_s"] = {k: round(v, 4) for k, v in T1.meta["split"].items()}
        del T1
    if args.torch_path:  # the same precompute with the kernel off, same processes
        os.environ[_native.ENV_VAR] = "0"
        T2, out["torch_path_s"] = again(**forked)
        out["torch_path_cpu_s"] = cpu[0]
        del os.environ[_native.ENV_VAR]
        _, out["native_again_s"] = again(**forked)  # the kernel once more: both warm
        out["native_again_cpu_s"] = cpu[0]
        out["kernel_speedup"] = out["torch_path_s"] / out["native_again_s"]
        out["kernel_cpu_speedup"] = out["torch_path_cpu_s"] / out["native_again_cpu_s"]
        out["equals_torch_path"] = _same(T, T2)
        out["torch_path_split_s"] = {k: round(v, 4) for k, v in T2.meta["split"].items()}
        del T2
    # embree alone: the rays of a run in this process (tiles may run in forked processes),
    # recorded after the timed run (which stays the first call in the process)
    rec_spp = max(1, spp // 8)
    rsc = cornell_box_glossy(res)
    with _recording_rays(rsc, limit=1 << 20 if q else 1 << 22) as log:
        precompute_polynomial(
            rsc, PolynomialSettings("64,1,1,1", spp=rec_spp, guides=False), seed=1, progress=False, processes=1
        )
    out["precompute_resolution"], out["precompute_spp"] = res, spp
    out["precompute_paths_per_s"] = res * res * spp / out["precompute_s"]
    out["rays"] = T.meta["rays"]
    alone = _embree_seconds(sc, log, T.meta["rays"])
    out["rays_s"], out["rays_embreex_s"], out["rays_c_s"] = alone["fastest"], alone["embreex"], alone.get("c")
    out["precompute_over_rays"] = out["precompute_s"] / out["rays_s"]
    # where the time went (exclusive seconds per stage, summed over tiles; meta["split"])
    out["split_s"] = {k: round(v, 4) for k, v in T.meta["split"].items()}
    out["split_other_s"] = out["precompute_s"] - sum(T.meta["split"].values())
    out["mb_per_bounce"] = {str(k): v / 2**20 for k, v in T.memory_per_bounce().items()}
    out["mb_variance_per_bounce"] = {
        str(k): (v - T.memory_per_bounce()[k]) / 2**20 for k, v in T.memory_per_bounce(variance=True).items()
    }
    print(f"precompute {out['precompute_s']:.1f} s, rays alone {out['rays_s']:.1f} s", flush=True)
    mi = _mitsuba(sc, spp, 4)
    if mi is not None:
        out["mitsuba_s"], out["mitsuba_variant"] = mi["seconds"], mi["variant"]
        out["precompute_over_mitsuba"] = out["precompute_s"] / mi["seconds"]
        print(f"mitsuba {mi['seconds']:.2f} s ({mi['variant']})", flush=True)
    del T
    if args.precompute_only:
        out["load_avg"] = list(os.getloadavg())
        print(json.dumps({k: (round(v, 6) if isinstance(v, float) else v) for k, v in out.items()}))
        return

    # -- freezing and frames at 512^2 ------------------------------------------------------------
    _freeze_and_frames(q, out)

    # -- accuracy against the full-BRDF reference --------------------------------------------
    # The high-spp reference is Mitsuba 3 (llvm) when it runs here -- our reference_path_trace
    # agrees with it within noise (tests/transport/test_mitsuba.py and the figures at the end)
    # and is ~50x faster at this -- else our reference_path_trace at fewer spp.
    ares = 32 if q else 128
    sca = cornell_box_glossy(ares)
    t0 = time.perf_counter()
    rspp = 256 if q else 4096
    hi = _mitsuba(sca, rspp, 4, quiet=True)
    if hi is not None and hi["variant"].startswith("llvm"):
        ref, out["reference"] = hi["image"], f"mitsuba {hi['variant']}"
    else:
        rspp = 64 if q else 256
        ref = reference_path_trace(sca, spp=rspp, max_bounces=4, seed=123, progress=True)
        out["reference"] = "reference_path_trace"
    out["reference_s"], out["reference_spp"], out["accuracy_resolution"] = time.perf_counter() - t0, rspp, ares
    apx = series_approximations(sca, "64,1,1,1", spp=64, seed=0)
    mask = emitter_mask(apx["tensors"])
    out["approximation_rel_rmse"] = {
        "64,1,1,1": relative_rmse(apx["series"], ref, mask),
        "diffuse_indirect_1,1,1,1": relative_rmse(apx["diffuse_indirect"], ref, mask),
        "direct_only": relative_rmse(apx["direct"], ref, mask),
    }
    print("ordering", out["approximation_rel_rmse"], flush=True)
    _series_errors(q, sca, ref, mask, rspp, out)

    # -- our reference against Mitsuba (equal spp) ----------------------------------------------
    n = 64 if q else 256
    mi = _mitsuba(sca, n, 4)
    if mi is not None:
        ours_a = reference_path_trace(sca, spp=n, max_bounces=4, seed=5, progress=False)
        ours_b = reference_path_trace(sca, spp=n, max_bounces=4, seed=6, progress=False)
        # both at n spp: Mitsuba vs ours should differ about as much as two seeds of ours
        out["mitsuba_vs_reference_rel_rmse"] = relative_rmse(mi["image"], ours_a, mask)
        out["reference_seed_rel_rmse"] = relative_rmse(ours_b, ours_a, mask)
        out["mitsuba_mean_ratio"] = float(mi["image"][mask].mean() / ours_a[mask].mean())
        # the peer's point on the error-vs-time curve of ``rel_rmse`` (same reference)
        out["mitsuba_point"] = {"spp": n, "seconds": mi["seconds"], "rel_rmse": relative_rmse(mi["image"], ref, mask)}
    out = {k: (round(v, 6) if isinstance(v, float) and math.isfinite(v) else v) for k, v in out.items()}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
