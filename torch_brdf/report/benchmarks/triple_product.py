"""All-frequency relighting with locally adaptive triple products: speed, accuracy, storage.

    python benchmarks/triple_product.py [--quick] [--checkpoint DIR] [--precompute-only] [--baseline] [--rounds N]
        [--split] [--compare-numpy] [--embree-chunks N] [--processes N] [--frames N] [--plane-quads N]

Scene: ``bunny_relight`` (Inger et al.'s test: the Stanford bunny, Phong exponent 200, on a
96x96-quad plane with Phong exponent 20) under a sun-like map (the shared HDR
``quarry_01_sun``, a sunny quarry with a very small, very bright sun; the procedural sun and
sky when the data is absent), 64x64x6
binary visibility (``--quick``: the procedural stand-in bunny, a 32x32-quad plane, a
smaller image; ``--plane-quads`` sets the plane's quads a side). Three frames (``--frames N``:
the first N): the scene camera; the map turned by 2 rad about +y; the camera moved around the
bunny. Every figure compares methods run in this process on the same culled vertices. Prints
progress, then one JSON object as the last line:

* ``vertices`` (all), ``shaded_vertices`` (per frame, after culling), ``precompute_s`` (the
  visibility cubemaps; a ``--checkpoint`` folder resumes) beside ``rays_s``, embree alone on
  the very rays it casts (one per texel centre above each vertex's horizon, built beforehand,
  untimed), with as many forked processes (``--processes``, default the usable cores) over
  the same chunks of 512 vertices, pool start included as in the precompute: the fastest of
  ``(n, 3)`` arrays through embreex in calls of 16384 rays (``embree``), one embreex call per
  vertex with a zero-stride origin (``embree_fans``) and, with the compiled kernel, a C loop
  calling embree's ``rtcOccluded1`` per ray on the same scene, each ray's origin per vertex and
  its direction by texel index (``embree_c``: the same query the precompute's kernel makes,
  without embreex's per-call arrays; the fastest, so the strictest baseline). ``--rounds``
  interleaved rounds (each variant goes first in turn; ``rounds`` lists every time and the
  load); the figures are medians (``embree_alone`` per variant), ``precompute_over_rays`` the
  median of the per-round ratios to the fastest, ``precompute_over_rays_cpu`` the same of CPU
  seconds (all processes; less load-dependent); ``same_rays``: the record's visible texels
  equal embree's escaping rays (``embree_c`` casts every ray). The embreex variants cast every
  ray with ``--quick``, else the first ``--embree-chunks`` chunks (16; 0: none), scaled by the
  rays. ``--compare-numpy``: also the precompute without the compiled loop
  (``TORCH_BRDF_NATIVE=0``) in every round: ``numpy_path_s``, ``numpy_path_over_rays(_cpu)``.
  ``--split``: ``split_cpu_s``, CPU seconds over all chunks in one process (``kernel`` for the
  compiled loop; else horizon test, gather of the directions, embree, scatter into maps, flips
  from packed bits), ``split_embree_alone_cpu_s`` (``embree_c`` on the same rays in this
  process) and ``split_overhead_over_embree`` (the chunks' CPU time over embree alone's, less 1).
  With ``--baseline`` also ``one_process_s`` (chunks one after another in this process, rays
  on the scene's trace pool), ``speedup_over_one_process``, ``equals_one_process`` (bit for
  bit); ``visibility_bytes_per_vertex`` (varint stream) beside ``dense_bytes_per_vertex``
  (one bit per texel) and the seed's ~1 KB goal; ``lighting_s`` (a lighting update);
  ``cull_s`` (primary rays + culling).
* ``visibility_load_s`` and ``visibility_load_peak_over_file``: ``VertexVisibility.load`` of
  the precomputed record's file (``visibility_file_bytes``) in a fresh process (after a load
  of a tiny record, so that code paths are paged in), its seconds and its peak resident memory
  above the start over the file's size; ``visibility_load_kept_over_file`` is what stays
  resident (the record: the file's varint stream and vertices),
  ``visibility_load_transient_over_file`` the peak above that (the parse's temporaries),
  ``visibility_load_mb_per_s`` the file's MB per second. Linux only (the peak is reset
  through ``/proc/self/clear_refs``).
* ``--large`` runs only the scene of the paper's size (the bunny on a plane of
  ``--plane-quads``, default 720, quads a side: 555,788 vertices with the shared bunny;
  ``--large-resolution`` cubemap side, default 32) and prints ``{"large": {...}}``:
  ``precompute_s``, ``precompute_peak_over_record`` (this process's peak resident memory
  above its start, over the record's file), ``record_bytes``, ``load_s``,
  ``load_peak_over_file`` / ``load_kept_over_file`` (a fresh process, as above),
  ``shaded_vertices``, ``view_s`` (culling and unpacking the visible vertices), ``frame_s``
  (ours), ``frame_peak_bytes`` (load, view and frame in this process).
* ``frame_s`` (ours, default rule: Appendix A for Phong), ``standard_frame_s`` (dense
  texel sum; visibility expanded beforehand, as a standard-basis system stores it),
  ``haar_frame_s`` (Ng et al.'s product on 1% of the lighting and BRDF wavelet coefficients;
  the BRDF wavelets, which they tabulate, are computed outside that figure:
  ``haar_brdf_s``), ``speedup_vs_standard`` = standard / ours, ``haar_speedup_vs_standard``.
  Times are the mean over the frames (best of ``--repeat`` runs each).
* ``psnr`` / ``haar_psnr``: dB against the standard-basis image over the pixels that see the
  scene, peak = the reference's maximum (mean over frames; ``psnr_frames``); ``psnr_display``
  the same on sRGB-encoded images with the reference's 99th-percentile luminance mapped to 1.
* ``cases`` / ``sampling``: the seed's Tables 1 and 2 (percent, frame 1), ``brdf_evals``.
* ``curve``: frame time and PSNR as the BRDF-sampling thresholds vary (the generic rule's
  thresholds times 0.1..10, the Appendix A angles times 0.5..2, and fixed 1/4/16/256 samples).
  ``frame_s``, ``psnr`` and ``curve`` time the frame users get (``shade``: the compiled frame
  where it supports the rule, else the torch path).
* ``vertex_rates`` (frame 1, the default rule): the compiled frame and the torch path in CPU
  seconds per frame on one thread (best of ``--repeat``; CPU time is less load-dependent than
  wall time), as scene vertices per second per core (all vertices, as the paper counts;
  ``*_per_core``) and microseconds per shaded vertex; the paper's rates from its Table 3
  (``paper``: fps x vertices / 4 cores of its i7-2600K, each scene, its median, Sappho and Round
  Table) and ours over them (``over_paper_*``); ``max_rel_diff`` of the two paths (of each vertex's
  largest channel) and ``same_stats`` (levels, cases, samples, entries); ``psnr_compiled`` /
  ``psnr_torch`` against the standard basis; ``fps_2_threads`` (wall: the compiled frame on two
  threads plus the image) and ``fps_150k_2_cores`` (projected: 2 cores x the per-core rate /
  150k scene vertices); ``kernel_lighting_s``, the kernel's lighting tables (built on the first
  frame after ``set_lighting``, beside ``lighting_s``); ``load_avg``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import multiprocessing
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import torch

from torch_brdf.data import data_path
from torch_brdf.metrics import psnr
from torch_brdf.parallel.threads import single_thread, usable_cores
from torch_brdf.parallel.tiles import single_process
from torch_brdf.render import _relight
from torch_brdf.render.triple import FixedRule, GenericRule, PhongRule, TripleProductRenderer
from torch_brdf.scene.builtin import bunny_relight
from torch_brdf.scene.camera import Camera
from torch_brdf.scene.embree import CHUNK
from torch_brdf.scene.envmap import EnvironmentMap
from torch_brdf.sphere.cubemap import CubemapBlocks
from torch_brdf.transport import _native
from torch_brdf.transport.visibility import (
    HORIZON_EPS,
    VertexVisibility,
    VisibilitySettings,
    _chunk_entries,
    precompute_visibility,
    scene_vertices,
)

from ._timing import best_of


def _display(img: torch.Tensor, exposure: float) -> torch.Tensor:
    x = (img.double() / exposure).clamp(0, 1)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.pow(1 / 2.4) - 0.055)


def _psnrs(img, ref, mask) -> tuple[float, float]:
    lum = (ref[mask] * torch.tensor([0.2126, 0.7152, 0.0722])).sum(-1)
    exposure = float(torch.quantile(lum.double(), 0.99)) or 1.0
    return psnr(img, ref, mask), psnr(_display(img, exposure), _display(ref, exposure), mask, peak=1.0)


def _orbit(cam: Camera, angle: float) -> Camera:
    ox, oy, oz = cam.origin
    tx, _, tz = cam.target
    c, s = math.cos(angle), math.sin(angle)
    dx, dz = ox - tx, oz - tz
    return Camera(
        (tx + c * dx + s * dz, oy, tz - s * dx + c * dz), cam.target, cam.up, cam.fov_deg, cam.width, cam.height
    )


def _chunk_rays(scene, geom, verts, chunk: int, limit: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The rays the precompute casts, per chunk of ``chunk`` vertices (the first ``limit``
    chunks): (n, 3) float32 origins and directions, one per texel centre above each vertex's
    horizon, built the plain way (torch, one (n, 3) array each), and (m,) rays per vertex."""
    dirs = geom.supersampled_directions(1).reshape(-1, 3)
    out = []
    for s in range(0, min(len(verts), limit * chunk), chunk):
        pos, nrm = verts.positions[s : s + chunk], verts.normals[s : s + chunk]
        up = (nrm @ dirs.T) > HORIZON_EPS
        vi, ti = up.nonzero(as_tuple=True)
        o = (pos + scene.ray_epsilon * nrm).float()[vi]
        o, d = (np.ascontiguousarray(x.numpy()) for x in (o, dirs[ti].float()))
        out.append((o, d, up.sum(1).numpy()))
    return out


def _chunk_fans(scene, geom, verts, chunk: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The same rays for every chunk, compactly, for embree alone in the compiled loop: per
    vertex the (m, 3) float32 origin and (m,) ray count, per ray the (n,) uint16 texel whose
    direction (:func:`_texel_directions`) it takes, in the order of :func:`_chunk_rays`."""
    dirs = geom.supersampled_directions(1).reshape(-1, 3)
    out = []
    for s in range(0, len(verts), chunk):
        pos, nrm = verts.positions[s : s + chunk], verts.normals[s : s + chunk]
        up = (nrm @ dirs.T) > HORIZON_EPS
        ti = up.nonzero(as_tuple=True)[1].numpy().astype(np.uint16)
        out.append(((pos + scene.ray_epsilon * nrm).float().numpy(), up.sum(1).numpy(), ti))
    return out


def _texel_directions(geom) -> np.ndarray:
    """(T, 3) float32 ray directions per texel: the precompute's and :func:`_chunk_rays`'s."""
    return np.ascontiguousarray(geom.supersampled_directions(1).reshape(-1, 3).float().numpy())


def _ray_count(geom, verts) -> int:
    """Texels above the horizon summed over all vertices."""
    dirs = geom.directions.reshape(-1, 3)
    return sum(int(((n @ dirs.T) > HORIZON_EPS).sum()) for n in verts.normals.split(4096))


def _cpu_seconds() -> float:
    """CPU seconds (user + system) of this process and of its finished children."""
    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


_RAYS: tuple | None = None  # (embree scene, rays): set before forking, inherited


def _embree_chunk(i: int) -> int:
    """Occluded rays of chunk ``i``: embreex's ``run`` on the prepared arrays, CHUNK rays a
    call; or (fans) one call per vertex with its origin as a zero-stride view, as the precompute
    calls it."""
    embree, rays, fans = _RAYS
    if fans == "c":  # the compiled loop, rtcOccluded1 per ray (embree, lib, entry, dirs)
        _, lib, entry, dirs = embree
        o, counts, texels = rays[i]
        return _native.occluded_fans(lib, entry, o, counts, texels, dirs)
    o, d, counts = rays[i]
    if not fans:
        return sum(int((embree.run(o[a : a + CHUNK], d[a : a + CHUNK], query="OCCLUDED") != -1).sum())
                   for a in range(0, len(o), CHUNK))  # fmt: skip
    hits, a = 0, 0
    for n in counts.tolist():
        origin = np.lib.stride_tricks.as_strided(o[a], (n, 3), (0, 4), writeable=False)
        hits += int((embree.run(origin, d[a : a + n], query="OCCLUDED") != -1).sum())
        a += n
    return hits


def _embree_alone(scene, rays, processes: int, fans: bool | str = False, dirs=None) -> int:
    """Embree alone on ``rays`` (per chunk), chunks in ``processes`` forked processes as the
    precompute's tiles (pool start included, as there); returns the occluded count. ``fans``:
    False, (n, 3) arrays through embreex; True, one embreex call per vertex; ``"c"``, the
    compiled loop on :func:`_chunk_fans` rays (``dirs``: :func:`_texel_directions`)."""
    global _RAYS
    embree = scene.tracer._kernel.scene  # the committed embreex scene the precompute traces
    embree.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))  # BVH built before forking
    if fans == "c":
        embree = (embree, _native.library(), scene.tracer._kernel.native(), dirs)
    _RAYS = (embree, rays, fans)
    try:
        if processes == 1:
            return sum(_embree_chunk(i) for i in range(len(rays)))
        with ProcessPoolExecutor(processes, multiprocessing.get_context("fork")) as pool:
            return sum(pool.map(_embree_chunk, range(len(rays))))
    finally:
        _RAYS = None


def _visible_texels(vis) -> int:
    """Visible texels of a binary record, from its flips: +1 at texel i adds 256 - i, -1 subtracts."""
    b = vis.blocks
    return int((b.values(torch.float64) * (256 - b.index.double())).sum())


# a fresh process: warm the load path on a tiny record, reset the peak resident memory (VmHWM),
# load the record, then report the peak and what stays resident above the start, and the seconds
_LOAD_CHILD = """
import json, sys, tempfile, time
import torch
from torch_brdf.records import BlockVisibility
from torch_brdf.records.visibility import SceneVertices, VertexVisibility
from torch_brdf.sphere.cubemap import CubemapBlocks

def status():
    with open("/proc/self/status") as f:
        return {k: int(v.split()[0]) * 1024 for k, v in (line.split(":", 1) for line in f) if k in ("VmHWM", "VmRSS")}

with tempfile.TemporaryDirectory() as tmp:  # the code of a vertex record's load paged in
    normals = torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=torch.float64)
    verts = SceneVertices(normals * 2, normals, torch.zeros(2, dtype=torch.int64), torch.tensor([0, 2]))
    blocks = BlockVisibility.encode(torch.ones(2, 6, 256, dtype=torch.bool))
    VertexVisibility.load(VertexVisibility(CubemapBlocks(16, 16), verts, blocks).save(tmp + "/warm.npz"))
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")
before = status()["VmRSS"]
t = time.perf_counter()
rec = VertexVisibility.load(sys.argv[1])
seconds = time.perf_counter() - t
after = status()
print(json.dumps({"peak": after["VmHWM"] - before, "kept": after["VmRSS"] - before, "seconds": seconds}))
"""


def _load_memory(vis) -> dict:
    """Peak memory and seconds of ``VertexVisibility.load`` of ``vis``'s file, in a fresh process
    (Linux: needs ``/proc/self/clear_refs``; else empty)."""
    if not os.path.exists("/proc/self/clear_refs"):
        return {}
    with tempfile.TemporaryDirectory() as tmp:
        path = vis.save(os.path.join(tmp, "visibility.npz"))
        size = os.path.getsize(path)
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        run = subprocess.run([sys.executable, "-c", _LOAD_CHILD, str(path)], capture_output=True, text=True, env=env)
    if run.returncode:
        raise RuntimeError(f"visibility load measurement failed: {run.stderr.strip().splitlines()[-1:]}")
    got = json.loads(run.stdout.strip().splitlines()[-1])
    return {
        "visibility_file_bytes": size,
        "visibility_load_s": got["seconds"],
        "visibility_load_mb_per_s": size / 1e6 / got["seconds"],
        "visibility_load_peak_over_file": got["peak"] / size,
        "visibility_load_kept_over_file": got["kept"] / size,
        "visibility_load_transient_over_file": (got["peak"] - got["kept"]) / size,
    }


def _parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small scene and image")
    ap.add_argument("--checkpoint", default=None, help="folder for resumable visibility chunks")
    ap.add_argument("--precompute-only", action="store_true", help="stop after the visibility precompute vs embree")
    ap.add_argument(
        "--baseline", action="store_true", help="also time the visibility with its chunks in one process (processes=1)"
    )
    ap.add_argument("--repeat", type=int, default=2, help="timed runs per frame (best is kept)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved precompute / embree-alone pairs (median)")
    ap.add_argument(
        "--embree-chunks", type=int, default=None, help="chunks embree alone casts (default: all with --quick, else 16)"
    )
    ap.add_argument("--split", action="store_true", help="also the CPU seconds per stage of the chunks")
    ap.add_argument(
        "--compare-numpy", action="store_true", help="also time the numpy path (no compiled loop) in the rounds"
    )
    ap.add_argument("--processes", type=int, default=None, help="processes for both (default: usable cores)")
    ap.add_argument("--haar-fraction", type=float, default=0.01)
    ap.add_argument("--frames", type=int, default=3, choices=(1, 2, 3), help="frames shaded (the first N of three)")
    ap.add_argument("--plane-quads", type=int, default=None, help="plane quads a side (default 96; quick 32)")
    ap.add_argument(
        "--large",
        action="store_true",
        help="only the scene of the paper's size (plane of --plane-quads, default 720: 500k+ vertices): "
        "precompute, load and one frame, with their peak memory",
    )
    ap.add_argument("--large-resolution", type=int, default=32, help="cubemap side of --large (default 32)")
    return ap.parse_args()


@dataclasses.dataclass
class _Rounds:
    """What the visibility precompute and embree alone share across the interleaved rounds."""

    scene: object
    res: int
    chunk: int
    procs: int
    verts: object
    geom: CubemapBlocks
    rays: list | None  # the embreex variants' (n, 3) arrays, dropped after the rounds
    n_rays: int  # the rays those arrays hold
    all_rays: int  # every ray the precompute casts
    native: bool
    fans: list | None  # the compiled loop's compact rays, dropped after the split
    texel_dirs: np.ndarray
    order: list[str]  # the variants timed in each round
    alone: list[str]  # the embree-alone variants among them
    vis: object = None
    runs: list = dataclasses.field(default_factory=list)
    occluded: int | None = None  # the last embreex variant's occluded rays
    occluded_c: int | None = None  # the compiled loop's occluded rays


def _prepare_rounds(scene, args) -> _Rounds:
    """The rays the embree-alone variants cast (built once, untimed) and the variants to time."""
    procs = args.processes or usable_cores()
    chunk, res = 512, 64
    verts, geom = scene_vertices(scene), CubemapBlocks(res)
    # the rays as (n, 3) arrays, built once (24 B a ray: the full scene's 544 M would not fit, the
    # embreex runs time the first --embree-chunks chunks and scale by the ray count); compactly
    # (2 B a ray) for the compiled loop, every ray
    n_chunks = -(-len(verts) // chunk)
    limit = n_chunks if args.quick and args.embree_chunks is None else min(n_chunks, args.embree_chunks or 16)
    if args.embree_chunks == 0:
        limit = 0
    rays = _chunk_rays(scene, geom, verts, chunk, limit)
    n_rays = sum(len(o) for o, _, _ in rays)
    all_rays = n_rays if limit == n_chunks else _ray_count(geom, verts)
    native = _native.library() is not None and scene.tracer._kernel.native() is not None
    fans = _chunk_fans(scene, geom, verts, chunk) if native else None
    order = ("precompute", "embree", "embree_fans", "embree_c", "precompute_numpy")
    order = [w for w in order if (w != "embree_c" or native) and (w != "precompute_numpy" or args.compare_numpy)]
    order = [w for w in order if limit or w not in ("embree", "embree_fans")]
    alone = [w for w in order if w.startswith("embree")]
    return _Rounds(
        scene,
        res,
        chunk,
        procs,
        verts,
        geom,
        rays,
        n_rays,
        all_rays,
        native,
        fans,
        _texel_directions(geom),
        order,
        alone,
    )


def _run_variant(st: _Rounds, what: str, checkpoint: str | None) -> None:
    """One timed variant of a round: a precompute (kept in ``st.vis``) or embree alone."""
    settings = VisibilitySettings(resolution=st.res, chunk=st.chunk)
    if what == "precompute":
        st.vis = precompute_visibility(st.scene, settings, checkpoint=checkpoint, processes=st.procs)
    elif what == "precompute_numpy":  # the numpy path (before the compiled loop), same run
        os.environ[_native.ENV_VAR] = "0"
        try:
            precompute_visibility(st.scene, settings, processes=st.procs)
        finally:
            del os.environ[_native.ENV_VAR]
    elif what == "embree_c":
        st.occluded_c = _embree_alone(st.scene, st.fans, st.procs, fans="c", dirs=st.texel_dirs)
    else:
        st.occluded = _embree_alone(st.scene, st.rays, st.procs, fans=what == "embree_fans")


def _run_rounds(st: _Rounds, rounds: int, checkpoint: str | None) -> None:
    """``rounds`` interleaved rounds of every variant (each goes first in turn), into ``st.runs``."""
    order, alone = st.order, st.alone
    for r in range(rounds):
        pair = {}
        for what in order[r % len(order) :] + order[: r % len(order)]:  # each goes first in turn
            t, c = time.perf_counter(), _cpu_seconds()
            _run_variant(st, what, checkpoint)
            pair[what] = time.perf_counter() - t
            pair[f"{what}_cpu"] = _cpu_seconds() - c
        for k in ("embree", "embree_fans"):
            if k in pair:
                pair[k] *= st.all_rays / st.n_rays
                pair[f"{k}_cpu"] *= st.all_rays / st.n_rays
        pair["ratio"] = pair["precompute"] / min(pair[k] for k in alone)
        pair["cpu_ratio"] = pair["precompute_cpu"] / min(pair[f"{k}_cpu"] for k in alone)
        if "precompute_numpy" in pair:
            pair["numpy_ratio"] = pair["precompute_numpy"] / min(pair[k] for k in alone)
            pair["numpy_cpu_ratio"] = pair["precompute_numpy_cpu"] / min(pair[f"{k}_cpu"] for k in alone)
        pair["load_avg"] = list(os.getloadavg())
        st.runs.append(pair)
        times = ", ".join(f"{k} {pair[k]:.2f} s ({pair[k + '_cpu']:.2f} CPU-s)" for k in order)
        print(f"round {r}: {times}; ratio {pair['ratio']:.3f} (CPU time {pair['cpu_ratio']:.3f}), "
              f"load {pair['load_avg'][0]:.1f}", flush=True)  # fmt: skip
    st.rays = None


def _rounds_figures(st: _Rounds, compare_numpy: bool) -> dict:
    """The medians of the rounds and whether the record's visible texels are embree's escaping rays."""
    runs, alone = st.runs, st.alone
    visible = _visible_texels(st.vis)
    if st.native:
        same_rays = visible == st.all_rays - st.occluded_c
    else:
        same_rays = visible == st.n_rays - st.occluded if st.n_rays == st.all_rays else None
    figures = {
        "processes": st.procs,
        "rounds": runs,
        "precompute_s": statistics.median(p["precompute"] for p in runs),
        "precompute_cpu_s": statistics.median(p["precompute_cpu"] for p in runs),
        "rays": st.all_rays,
        "rays_s": statistics.median(min(p[k] for k in alone) for p in runs),
        "rays_cpu_s": statistics.median(min(p[f"{k}_cpu"] for k in alone) for p in runs),
        "embree_alone": {k: statistics.median(p[k] for p in runs) for k in alone},
        "embree_timed_rays": st.n_rays,
        "native": st.native,
        "precompute_over_rays": statistics.median(p["ratio"] for p in runs),
        "precompute_over_rays_cpu": statistics.median(p["cpu_ratio"] for p in runs),
        # the record's visible texels = embree's escaping rays (when embree cast them all)
        "same_rays": same_rays,
    }
    if compare_numpy:
        figures["numpy_path_s"] = statistics.median(p["precompute_numpy"] for p in runs)
        figures["numpy_path_over_rays"] = statistics.median(p["numpy_ratio"] for p in runs)
        figures["numpy_path_over_rays_cpu"] = statistics.median(p["numpy_cpu_ratio"] for p in runs)
    return figures


def _split_figures(st: _Rounds) -> dict:
    """CPU seconds per stage, every chunk in this process (load barely changes CPU time)."""
    one, split, figures = single_process(st.scene), {}, {}
    dirs = st.geom.supersampled_directions(1).reshape(-1, 1, 3).float()
    with single_thread():
        for s in range(0, len(st.verts), st.chunk):
            pos, nrm = st.verts.positions[s : s + st.chunk], st.verts.normals[s : s + st.chunk]
            _chunk_entries(one, st.geom, pos, nrm, dirs, 0, split=split)
        figures["split_cpu_s"] = split
        if st.native:  # embree alone in the compiled loop, this process, the same rays
            c = time.process_time()
            _embree_alone(st.scene, st.fans, 1, fans="c", dirs=st.texel_dirs)
            split_alone = figures["split_embree_alone_cpu_s"] = time.process_time() - c
        else:
            split_alone = split["embree"]
    figures["split_overhead_over_embree"] = (sum(split.values()) - split_alone) / split_alone
    return figures


def _one_process_baseline(st: _Rounds, precompute_s: float) -> dict:
    """The chunks one after another in this process (rays on the scene's trace pool)."""
    baseline = {}
    t = time.perf_counter()
    vis1 = precompute_visibility(st.scene, VisibilitySettings(resolution=st.res, chunk=st.chunk), processes=1)
    baseline["one_process_s"] = time.perf_counter() - t
    baseline["speedup_over_one_process"] = baseline["one_process_s"] / precompute_s
    a, b = vis1.blocks, st.vis.blocks
    names = ("counts", "offsets", "index", "states")
    baseline["equals_one_process"] = all(torch.equal(getattr(a, n), getattr(b, n)) for n in names) and (
        (a.delta is None and b.delta is None) or torch.equal(a.delta, b.delta)
    )
    return baseline


def _shade_frames(r, env, frames, args, out: dict):
    """Every frame by ours, the standard basis and Haar: the means into ``out``; returns the
    first frame's (view, reference, mask, stats)."""
    per = {k: [] for k in ("frame_s", "standard_frame_s", "haar_frame_s", "haar_brdf_s", "cull_s", "shaded_vertices")}
    per.update({k: [] for k in ("psnr", "psnr_display", "haar_psnr", "haar_psnr_display")})
    first = None
    for name, cam, angle in frames:
        r.set_lighting(env.rotated(angle) if angle else env)
        cull_s, view = best_of(lambda cam=cam: r.view(cam), 1)
        mask = view.mask
        frame_s, (rad, stats) = best_of(lambda view=view: r.shade(view), args.repeat)
        dense = view.blocks.decode()  # the standard basis stores visibility expanded
        std_s, ref_rad = best_of(lambda view=view, dense=dense: r.shade_standard(view, dense_visibility=dense), 1)
        del dense
        tim: dict = {}
        haar_rad = r.shade_haar(view, fraction=args.haar_fraction, timings=tim)
        img, ref, himg = r.image(view, rad), r.image(view, ref_rad), r.image(view, haar_rad)
        p, pd = _psnrs(img, ref, mask)
        hp, hpd = _psnrs(himg, ref, mask)
        for k, v in (
            ("frame_s", frame_s),
            ("standard_frame_s", std_s),
            ("haar_frame_s", tim["product_s"]),
            ("haar_brdf_s", tim["brdf_s"]),
            ("cull_s", cull_s),
            ("shaded_vertices", len(view.vertex_ids)),
            ("psnr", p),
            ("psnr_display", pd),
            ("haar_psnr", hp),
            ("haar_psnr_display", hpd),
        ):
            per[k].append(v)
        print(
            f"frame {name}: {len(view.vertex_ids)} vertices, ours {frame_s:.3f} s, standard {std_s:.2f} s, "
            f"haar product {tim['product_s']:.2f} s (+{tim['brdf_s']:.2f} s BRDF wavelets); "
            f"PSNR ours {p:.2f} dB, haar {hp:.2f} dB",
            flush=True,
        )
        if first is None:
            first = (view, ref, mask, stats)
    for k, v in per.items():
        out[k] = sum(v) / len(v)
    out["psnr_frames"] = per["psnr"]
    out["haar_psnr_frames"] = per["haar_psnr"]
    return first


def _threshold_curve(r, env, vis, view, ref, mask, repeat: int) -> dict:
    """The speed/accuracy curve of the BRDF-sampling thresholds (frame 1)."""
    r.set_lighting(env)
    base = GenericRule()
    auto = vis.geometry.angular_radius / CubemapBlocks(64).angular_radius  # PhongRule's default scale
    rules = {
        f"generic_x{m:g}": GenericRule(base.constant * m, base.linear * m, base.smooth * m)
        for m in (0.1, 0.3, 1, 3, 10)
    }
    rules.update({f"appendix_a_angles_x{m:g}": PhongRule(scale=auto * m) for m in (0.5, 1, 2)})
    rules.update({f"fixed_{l * l}": FixedRule(l) for l in (1, 2, 4, 16)})
    curve = {}
    for key, rule in rules.items():
        s, (rad, st) = best_of(lambda rule=rule: r.shade(view, rule=rule), repeat)
        curve[key] = {
            "frame_s": s,
            "psnr": psnr(r.image(view, rad), ref, mask),
            "sampling": st.percentages()["sampling"],
            "brdf_evals_per_vertex": st.brdf_evals / max(1, st.vertices),
        }
        print(f"curve {key}: {s:.3f} s, {curve[key]['psnr']:.2f} dB", flush=True)
    return curve


#: Inger et al., Table 3 (Intel Core i7-2600K, four cores, vertices culled on the GPU): fps, vertices
_PAPER_TABLE_3 = {
    "bas_relief": (5, 506e3),
    "round_table": (14, 280e3),
    "sappho": (17, 113e3),
    "david": (11, 293e3),
    "piano": (14, 195e3),
    "skeleton": (9, 635e3),
    "dining_table": (17, 381e3),
    "bicycle": (24, 206e3),
    "museum": (22, 231e3),
    "lucy": (9, 367e3),
}
_PAPER_CORES = 4


def _cpu_best(fn, repeat: int) -> float:
    """The least CPU seconds (this process) of ``repeat`` calls of ``fn`` (after one warm-up)."""
    fn()
    best = math.inf
    for _ in range(max(1, repeat)):
        c = time.process_time()
        fn()
        best = min(best, time.process_time() - c)
    return best


def _vertex_rates(r, view, ref, mask, scene_vertices: int, repeat: int) -> dict:
    """Scene vertices per second per core of the compiled frame, the torch path and the paper."""
    rule = r.rule
    shaded = len(view.vertex_ids)
    out: dict = {"scene_vertices": scene_vertices, "shaded_vertices": shaded, "path": r.frame_path(rule)}
    if out["path"] != "compiled":
        return out
    threads = r.threads
    try:
        r.threads = 1
        with single_thread():
            out["compiled_cpu_s"] = _cpu_best(lambda: r.shade_compiled(view, rule), repeat * 3)
            out["torch_cpu_s"] = _cpu_best(lambda: r.shade_torch(view, rule, progress=False), repeat)
        r.threads = 2
        wall, _ = best_of(lambda: r.image(view, r.shade_compiled(view, rule)[0]), repeat * 3)
    finally:
        r.threads = threads
    a, sa = r.shade_compiled(view, rule)
    b, sb = r.shade_torch(view, rule, progress=False)
    for k in ("compiled", "torch"):
        out[f"{k}_per_core"] = scene_vertices / out[f"{k}_cpu_s"]
        out[f"{k}_us_per_shaded_vertex"] = out[f"{k}_cpu_s"] / max(1, shaded) * 1e6
    rates = {k: fps * v / _PAPER_CORES for k, (fps, v) in _PAPER_TABLE_3.items()}
    out["paper"] = {
        "derivation": "Table 3: fps x scene vertices / 4 cores (i7-2600K); all vertices counted, culling included",
        "per_core": rates,
        "median": statistics.median(rates.values()),
    }
    for k in ("sappho", "round_table", "median"):
        out[f"over_paper_{k}"] = out["compiled_per_core"] / (out["paper"]["median"] if k == "median" else rates[k])
    out["speedup_over_torch"] = out["torch_cpu_s"] / out["compiled_cpu_s"]
    scale = b.abs().amax(-1).clamp_min(1e-30)
    out["max_rel_diff"] = float(((a - b).abs().amax(-1) / scale).max())
    out["same_stats"] = sa.as_dict() == sb.as_dict()
    out["psnr_compiled"] = psnr(r.image(view, a), ref, mask)
    out["psnr_torch"] = psnr(r.image(view, b), ref, mask)
    out["frame_2_threads_s"] = wall
    out["fps_2_threads"] = 1.0 / wall
    out["fps_150k_2_cores"] = 2 * out["compiled_per_core"] / 150e3
    out["fps_150k_derivation"] = "2 cores x compiled_per_core / 150k scene vertices (this scene's culled share)"
    out["kernel_lighting_s"], _ = best_of(lambda: _relight.NativeLighting.of(r.lighting, r.geometry.block), repeat)
    out["load_avg"] = list(os.getloadavg())
    print(
        f"vertex rates: compiled {out['compiled_per_core'] / 1e3:.0f}k, torch {out['torch_per_core'] / 1e3:.0f}k, "
        f"paper (median) {out['paper']['median'] / 1e3:.0f}k scene vertices/s/core; "
        f"{out['fps_2_threads']:.1f} fps on 2 threads, load {out['load_avg'][0]:.1f}",
        flush=True,
    )
    return out


def _precompute_figures(scene, args) -> tuple[_Rounds, dict, dict]:
    """The visibility precompute against embree alone on the very rays it casts, with as many
    processes over the same chunks of vertices, interleaved (embree's own time varies most),
    then the optional split and one-process baseline and the record's load: (state, figures,
    baseline)."""
    st = _prepare_rounds(scene, args)
    _run_rounds(st, args.rounds, args.checkpoint)
    figures = _rounds_figures(st, args.compare_numpy)
    if args.split:
        figures.update(_split_figures(st))
    st.fans = None
    figures.update(_load_memory(st.vis))
    print(
        f"load: {figures.get('visibility_load_s', float('nan')):.3f} s, peak "
        f"{figures.get('visibility_load_peak_over_file', float('nan')):.2f}x the file",
        flush=True,
    )
    baseline = _one_process_baseline(st, figures["precompute_s"]) if args.baseline else {}
    return st, figures, baseline


def _status() -> dict[str, int]:
    """This process's peak (``VmHWM``) and current (``VmRSS``) resident bytes (Linux)."""
    with open("/proc/self/status") as f:
        return {k: int(v.split()[0]) * 1024 for k, v in (line.split(":", 1) for line in f) if k in ("VmHWM", "VmRSS")}


def _reset_peak() -> int:
    """Reset this process's peak resident memory (VmHWM, Linux); its resident bytes now."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    return _status()["VmRSS"]


def _load_file(path) -> dict:
    """``VertexVisibility.load`` of ``path`` in a fresh process: its peak and kept bytes above
    the start and its seconds (as :func:`_load_memory`)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = subprocess.run([sys.executable, "-c", _LOAD_CHILD, str(path)], capture_output=True, text=True, env=env)
    if run.returncode:
        raise RuntimeError(f"visibility load measurement failed: {run.stderr.strip().splitlines()[-1:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


def _large_case(args, env) -> dict:
    """The scene of the paper's size (``--large``): the bunny on a plane of ``--plane-quads``
    (default 720) quads a side, 500k+ vertices. Its visibility precompute (peak resident
    memory of this process above its start, over the record's file: the chunks' streams and
    their assembly; the forked ray casters are separate processes), the record's load in a
    fresh process (peak and kept memory over the file, seconds), and one frame of ours (the
    view: culling and unpacking the visible vertices; the shading; the peak of the load, view
    and shading in this process above their start)."""
    scene = bunny_relight((320, 240), plane_quads=args.plane_quads or 720, envmap=env)
    n = sum(len(o.mesh.vertices) for o in scene.objects)
    print(f"large scene: {n} vertices, cubemap {args.large_resolution}^2x6", flush=True)
    settings = VisibilitySettings(resolution=args.large_resolution, chunk=512)
    before = _reset_peak()
    t = time.perf_counter()
    vis = precompute_visibility(scene, settings, checkpoint=args.checkpoint, processes=args.processes)
    precompute_s = time.perf_counter() - t
    precompute_peak = _status()["VmHWM"] - before
    with tempfile.TemporaryDirectory() as tmp:
        path = vis.save(os.path.join(tmp, "visibility.npz"))
        size = os.path.getsize(path)
        del vis
        got = _load_file(path)
        print(f"large: record {size / 2**20:.1f} MB, load {got['seconds']:.2f} s", flush=True)
        before = _reset_peak()
        vis = VertexVisibility.load(path)
    r = TripleProductRenderer(scene, vis)
    view_s, view = best_of(lambda: r.view(), 1)
    frame_s, _ = best_of(lambda: r.shade(view, progress=False), 1)
    frame_peak = _status()["VmHWM"] - before
    return {
        "vertices": n,
        "cubemap": f"{args.large_resolution}x{args.large_resolution}x6",
        "blocks_per_vertex": vis.geometry.block_count,
        "record_bytes": size,
        "bytes_per_vertex": size / n,
        "precompute_s": precompute_s,
        "precompute_peak_bytes": precompute_peak,
        "precompute_peak_over_record": precompute_peak / size,
        "load_s": got["seconds"],
        "load_peak_over_file": got["peak"] / size,
        "load_kept_over_file": got["kept"] / size,
        "shaded_vertices": len(view.vertex_ids),
        "view_s": view_s,
        "frame_s": frame_s,
        "frame_peak_bytes": frame_peak,
        "frame_peak_over_file": frame_peak / size,
        "load_avg": list(os.getloadavg()),
    }


def main() -> None:
    args = _parse_args()
    torch.manual_seed(0)
    sun = None if args.quick else data_path("envmaps", "quarry_01_sun_512x256.exr", required=False)
    env = EnvironmentMap.from_exr(sun) if sun is not None else None  # else the procedural sun and sky
    if args.large:
        print(json.dumps({"large": _large_case(args, env)}))
        return
    if args.quick:
        scene = bunny_relight((160, 120), plane_quads=args.plane_quads or 32, use_data=False)
    else:
        scene = bunny_relight((320, 240), plane_quads=args.plane_quads or 96, envmap=env)
    print(f"scene {scene.name}: {[len(o.mesh.vertices) for o in scene.objects]} vertices", flush=True)
    st, figures, baseline = _precompute_figures(scene, args)
    vis, res = st.vis, st.res
    if args.precompute_only:
        print(json.dumps({"vertices": len(vis.vertices), **figures, **baseline, "load_avg": list(os.getloadavg())}))
        return
    r = TripleProductRenderer(scene, vis)
    env = r.envmap
    lighting_s, _ = best_of(lambda: r.set_lighting(env), 3)

    frames = [
        ("camera", scene.camera, 0.0),
        ("rotated_map", scene.camera, 2.0),
        ("orbit", _orbit(scene.camera, 0.7), 0.0),
    ][: args.frames]
    out: dict = {
        "scene": scene.name,
        "quick": args.quick,
        "vertices": len(vis.vertices),
        "cubemap": f"{res}x{res}x6",
        "blocks_per_vertex": vis.geometry.block_count,
        "envmap": str(sun.name) if sun is not None else "procedural sky",
        **figures,
        **baseline,
        "visibility_bytes_per_vertex": vis.bytes_per_vertex,
        "dense_bytes_per_vertex": CubemapBlocks(res).texel_count / 8,
        "seed_bytes_per_vertex": 1024,
        "lighting_s": lighting_s,
        "haar_fraction": args.haar_fraction,
    }
    view, ref, mask, stats = _shade_frames(r, env, frames, args, out)
    out["speedup_vs_standard"] = out["standard_frame_s"] / out["frame_s"]
    out["haar_speedup_vs_standard"] = out["standard_frame_s"] / out["haar_frame_s"]
    pct = stats.percentages()
    out["cases"] = {**pct["cases"], "occluded_of_all": pct["occluded"]}
    out["sampling"] = pct["sampling"]
    out["brdf_evals"] = stats.brdf_evals
    out["brdf_evals_per_vertex"] = stats.brdf_evals / max(1, stats.vertices)
    r.set_lighting(env)
    out["vertex_rates"] = _vertex_rates(r, view, ref, mask, len(vis.vertices), args.repeat)
    out["curve"] = _threshold_curve(r, env, vis, view, ref, mask, args.repeat)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
