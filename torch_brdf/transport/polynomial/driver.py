"""The driver of the multibounce precomputation: tiles, seeds, the tile cache, the record."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..._checks import MAX_BANDS, check_count, check_seed
from ...data import progress_default
from ...errors import FileFormatError, ShapeError, ValueRangeError
from ...parallel.threads import available_memory, tile_processes
from ...parallel.tiles import run_tiles, single_process, tile_tick
from ...planner.gi import GIPlan, plan_from_pilots, planned_bases, with_fixed
from ...records.cache import ArraySpec, CacheSchema, MetaSpec, TileCache, settings_key
from ...records.guides import GUIDE_VERSION
from ...records.polynomial import ObjectBasis, PolynomialTensors, Series
from ...scene.camera import Camera
from ...scene.envmap import EnvironmentMap
from ...scene.lights import Light
from ...scene.scene import Scene
from .._native import Accumulator, TileSums, library
from .._native import ptr as _p
from ..guides import guide_buffers
from ..pathtrace import seeded_generator
from .plan import plan_bases
from .reduce import (
    NativeEntries,
    TermNumbering,
    _local_blocks,
    _reduce,
    native_bits,
    native_local_blocks,
    tile_accumulator,
)
from .sampler import EyeStrata, LobeMixture, Mixture
from .tracer import _Tracer
from .vertex import c_rand_matches

__all__ = ["TILE_KIND", "TILE_PIXELS", "plan_polynomial", "precompute_polynomial", "spp_map_of"]

TILE_KIND = "multibounce-tile"

#: peak memory of a tile per path (bytes): its transient entries set it (measured 0.6-0.9 kB
#: on the 128² box at 64-1024 spp); bounds the tiles run at once.
TILE_BYTES_PER_PATH = 1024

#: pixels of a default tile (whole rows: ``TILE_PIXELS // width`` of them, at least one). Small
#: enough that the processes pulling tiles run out of work nearly together and the last tile's
#: hand-back and assembly (serial after the tiles) are short: 16 tiles of 16 rows at 256²
#: (16384 pixels, 4 tiles of 64 rows, left one of two processes waiting for the last tile).
#: Part of the random stream (each tile is seeded by its index).
TILE_PIXELS = 4096


def _default_processes(tile_paths: int) -> int:
    """Tiles at once by default: :func:`~torch_brdf.parallel.threads.tile_processes` (one per usable
    core, 1 on a busy machine), fewer when that many tiles would not fit in the available
    memory (at least one)."""
    n = tile_processes()
    free = available_memory()
    if free is not None:
        n = min(n, max(1, free // max(1, tile_paths * TILE_BYTES_PER_PATH)))
    return n


def _pass_groups(counts: torch.Tensor, group: int | None) -> list[tuple[int, int]]:
    """Pass ranges [s0, s1) traced together in a tile whose pixels take ``counts`` paths each:
    ``group`` passes at a time, or (None) as many passes as make >= 64k rays (at least one)."""
    passes = int(counts.max())
    if group is not None:
        return [(s0, min(passes, s0 + group)) for s0 in range(0, passes, group)]
    # pixels in pass s: those with counts > s
    live = counts.numel() - torch.searchsorted(torch.sort(counts).values, torch.arange(passes), right=True)
    out, s0, rays = [], 0, 0
    for s, n in enumerate(live.tolist()):
        rays += n
        if rays >= 65536 or s == passes - 1:
            out.append((s0, s + 1))
            s0, rays = s + 1, 0
    return out


def _offsets(n: int, gen: torch.Generator) -> torch.Tensor:
    """``torch.rand(n, 2, generator=gen, dtype=torch.float64)``: the same numbers, drawn by the
    kernel's ``tb_rand`` from ``gen``'s state where it matches torch's (a few times faster than
    torch's serial float64 draws; ``gen`` advances as torch's would)."""
    lib = library()
    if lib is None or gen.device.type != "cpu" or not c_rand_matches(lib):
        return torch.rand(n, 2, generator=gen, dtype=torch.float64)
    gs, out = gen.get_state(), torch.empty(n, 2, dtype=torch.float64)
    lib.tb_rand(_p(gs), 2 * n, 1, _p(out))
    gen.set_state(gs)
    return out


def eye_rays(cam, pixels: torch.Tensor, rec: torch.Tensor, off: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A pass group's eye rays: ``cam.rays_through`` at the raster positions of ``pixels[rec]``
    (flat indices) plus ``off`` (row, column) offsets. For a plain
    :class:`~torch_brdf.scene.camera.Camera` with the compiled kernel: its
    ``tb_camera_local`` and ``tb_camera_finish`` around the product with the camera frame and the
    row norms, which stay torch's (their rounding is BLAS's and torch's own), so the same rays bit
    for bit with a fraction of the passes over memory.

    Args:
        cam: the scene's camera.
        pixels: (P,) int64 flat pixel indices of the tile.
        rec: (n,) int64 indices into ``pixels``, one per ray.
        off: (n, 2) float64 offsets in [0, 1): row, column.
    Returns:
        origins (n, 3), unit directions (n, 3), float32.
    Raises:
        ValueRangeError: NaN or Inf raster positions.
    """
    lib = library()
    if lib is None or type(cam) is not Camera:
        pix = pixels[rec]
        return cam.rays_through((pix % cam.width).double() + off[:, 1], (pix // cam.width).double() + off[:, 0])
    n = rec.numel()
    rec, pixels, off = rec.to(torch.int64).contiguous(), pixels.to(torch.int64).contiguous(), off.double().contiguous()
    local = torch.empty(n, 3, dtype=torch.float64)
    bad = lib.tb_camera_local(
        n, _p(rec), _p(pixels), cam.width, cam.height, _p(off), cam.tan_half, cam.width / cam.height, _p(local)
    )
    if bad < 0:
        raise ValueRangeError(f"raster position {-1 - bad} of {n} is NaN or Inf")
    d = local @ cam.frame
    norm = d.norm(dim=-1)
    o, out = torch.empty(n, 3, dtype=torch.float32), torch.empty(n, 3, dtype=torch.float32)
    origin = torch.tensor(cam.origin, dtype=torch.float64)
    lib.tb_camera_finish(n, _p(d), _p(norm), _p(origin), _p(o), _p(out))
    return o, out


def eye_strata(mixture, sample: torch.Tensor, count: torch.Tensor, key: torch.Tensor) -> EyeStrata:
    """The strata of paths ``sample`` of ``count`` at pixels ``key`` under a stratified mixture
    that is share ``(k, of)`` of one stratification: paths ``k * count + sample`` of ``of * count``."""
    k, of = getattr(mixture, "share", (0, 1))
    return EyeStrata(sample + k * count, count * of, key)


def _tile_entries(tracer, scene, pixels, counts, tile, group, seed, paths=None, tick=None, native=None):
    """Trace a tile whose pixel ``i`` takes ``counts[i]`` paths and reduce its entries to (sum,
    sum of per-path squares) per key; ``tick()`` (if given) after each pass group.

    Pass ``s`` traces one path from every pixel with ``counts > s`` (in raster order), and the
    passes of a group are one batch: with equal counts this is the uniform run's batch, ray
    for ray and random number for random number (so an adaptive tile whose pixels all take
    ``s`` paths equals the uniform run's tile at ``s`` entry for entry). ``native``: the compiled
    entry kernel (None: :func:`~torch_brdf.transport._native.library`, None without a compiler;
    False: the torch entries); the sums are the same bit for bit on the same paths (the paths
    themselves come from the tracer's compiled per-vertex steps whenever the kernel exists).

    Returns:
        (emission (P, 3) float64, the sums): with the kernel its tile
        :class:`~torch_brdf.transport._native.Accumulator` (read by
        :func:`~.reduce.native_local_blocks`), else ``_reduce``'s dict."""
    cam, clock = scene.camera, tracer.clock
    p = pixels.numel()
    sizes = {
        "rec": p,
        "obj": tracer.num_objects,
        "bounce": tracer.series.bounces + 1,
        "j": max([1] + [b.size for b in tracer.bases if b is not None]),
        "w": max(1, sum(b.second_size for b in tracer.bases if b is not None) if tracer.series.two_level else 1),
    }
    groups = _pass_groups(counts, group)
    lib = (library() if native is None else native) or None
    most = max(s1 - s0 for s0, s1 in groups)
    bits = native_bits({**sizes, "path": most}, tracer.num_objects, tracer.series.bounces) if lib else None
    lib = lib if bits else None  # keys too wide for the kernel: the torch path
    emis = torch.zeros(p, 3, dtype=torch.float64)
    reduced = []
    tile_acc = tile_accumulator(lib, tracer.num_objects, bits) if lib else None  # the pass groups' sums
    group_ent = NativeEntries(lib, tracer.num_objects, p, bits) if lib else None
    for gi, (s0, s1) in enumerate(groups):
        with clock("sampling"):
            # the (pass, pixel record) of each ray, pass-major: pass s0 + a, then its records
            pas, rec = torch.nonzero(counts[None, :] > torch.arange(s0, s1)[:, None], as_tuple=True)
            gen = seeded_generator(seed, tile, gi)
            off = _offsets(rec.numel(), gen)
            ray = pas * p + rec  # a ray's id: record id % p, path id // p (a uniform run's arange)
            o, d = eye_rays(cam, pixels, rec, off)
        if group_ent is not None:  # one group's entries at a time: the accumulator (and its memory) reused
            group_ent.acc.clear()
        ent = group_ent
        n_rows = len(paths.get("rows", ())) if paths is not None else 0
        strata = None
        if getattr(tracer.mixture, "stratified", False):
            strata = eye_strata(tracer.mixture, s0 + pas, counts[rec], pixels[rec])
        e, ent = tracer.run(o, d, ray, gen, paths, ent, strata)  # entries carry the ray id as "path"
        if paths is not None:  # the oracle's rows: ray id -> flat pixel index
            for r in paths.get("rows", [])[n_rows:]:
                r["rec"] = pixels[r["rec"] % p]
        with clock("bookkeeping"):
            emis.index_add_(0, rec, e.double())
            if tick is not None:
                tick()
            if lib:
                ent.reduce_into(tile_acc)
                continue
            dd = ent.cat()
            if not dd:
                continue
            ray_id = dd.pop("path")
            dd["rec"], dd["path"] = ray_id % p, ray_id // p
            reduced.append(_reduce(dd, {**sizes, "path": s1 - s0}, by_path=True))
    if lib:  # the tile's sums stay in the kernel (native_local_blocks reads them)
        return emis, tile_acc
    reduced = [r for r in reduced if r]
    if not reduced:
        return emis, {}
    with clock("bookkeeping"):
        cat = {k: torch.cat([r[k] for r in reduced]) for k in reduced[0]}
        cat["weight"] = cat.pop("sum")
        return emis, _reduce(cat, sizes, by_path=False)


class _TileWork:
    """Everything a tile needs besides its index (a pure function of this and the index).

    Pickles without its tracer (rebuilt lazily where it runs) and without ``paths``.
    """

    def __init__(self, scene, plan, series, mixture, lights, tiles, counts, group, seed, paths=None, light_samples=1):
        self.scene, self.plan, self.series, self.mixture, self.lights = scene, plan, series, mixture, lights
        self.tiles, self.counts, self.group, self.seed, self.paths = tiles, counts, group, seed, paths
        self.light_samples = light_samples
        self._tracer = None

    def __getstate__(self):
        return {**self.__dict__, "_tracer": None, "paths": None}

    @property
    def tracer(self) -> _Tracer:
        if self._tracer is None:
            self._tracer = _Tracer(self.scene, self.plan, self.series, self.mixture, self.lights, self.light_samples)
        return self._tracer

    def pixels(self, k: int) -> torch.Tensor:
        """(P,) flat pixel indices of tile ``k`` (ascending)."""
        return self.tiles[k]

    def path_counts(self, k: int) -> torch.Tensor:
        """(P,) int64 paths per pixel of tile ``k``."""
        spp = self.counts[k]
        return torch.full((self.tiles[k].numel(),), spp) if isinstance(spp, int) else spp

    def steps(self, k: int) -> int:
        """Pass groups of tile ``k`` (what its progress bar counts)."""
        return len(_pass_groups(self.path_counts(k), self.group[k]))


def _tiles(spp_map: torch.Tensor, tile_pixels: int) -> tuple[list[torch.Tensor], list[torch.Tensor | int]]:
    """The work units of a per-pixel spp map: bands of ``tile_pixels`` pixels in raster order
    (``tile_pixels / width`` rows), each with its pixels' spp (an int where they are equal).

    Every tile holds whole rows whatever the map, so an adaptive run does the same work per
    tile and per batch as a uniform run (:func:`_tile_entries` traces a tile's spp levels in
    one pass sequence), and its tile ``k`` equals a uniform run's tile ``k`` wherever that
    tile's pixels all take the uniform run's spp.

    Args:
        spp_map: (H*W,) int64, >= 1.
    Returns:
        (pixels per tile, paths per pixel per tile: (P,) int64, or an int when uniform).
    """
    tiles = list(torch.split(torch.arange(spp_map.numel()), tile_pixels))
    counts: list[torch.Tensor | int] = []
    for t in tiles:
        c = spp_map[t]
        counts.append(int(c[0]) if bool((c == c[0]).all()) else c)
    return tiles, counts


def _run_lengths(x: torch.Tensor) -> list[list[int]]:
    """[[value, run length], ...] of ``x`` (1-D int) in order: a compact, exact copy of an spp map."""
    vals, counts = torch.unique_consecutive(x, return_counts=True)
    return [[int(v), int(c)] for v, c in zip(vals.tolist(), counts.tolist(), strict=True)]


def spp_map_of(tensors: PolynomialTensors) -> torch.Tensor:
    """(H, W) int64: the paths per pixel of a record (adaptive or uniform)."""
    runs = tensors.meta.get("spp_map")
    if runs is None:
        return torch.full((tensors.height, tensors.width), int(tensors.meta["spp"]), dtype=torch.long)
    vals = torch.tensor([r[0] for r in runs], dtype=torch.long)
    return vals.repeat_interleave(torch.tensor([r[1] for r in runs])).reshape(tensors.height, tensors.width)


#: names of a tile's block arrays: ``b{g}_{name}`` for the g-th block of :func:`_local_blocks`
_BLOCK_ARRAYS = ("head", "upix", "tw", "tc", "key", "vals", "var")


def _tile_schema(plan: Sequence, bounces: int) -> CacheSchema:
    """What a finished tile file must hold: the ``emission`` of its ``P`` pixels and blocks
    ``b0..b{n-1}`` whose heads name an object, a bounce and that object's basis size, whose
    pixels lie in the tile and whose entry keys lie in their (term, basis, pixel) table."""
    m = len(plan)
    arrays = {"emission": ArraySpec("float64", ("P", 3), low=0.0)}
    patterns = {
        r"b\d+_head": ArraySpec("int64", (3,)),
        r"b\d+_upix": ArraySpec("int64", (None,), low=0),
        r"b\d+_tw": ArraySpec("int64", (None,), low=-1),
        r"b\d+_tc": ArraySpec("int8", (None, m), low=0),
        r"b\d+_key": ArraySpec("int64", (None,), low=0),
        r"b\d+_vals": ArraySpec("float32", (3, None)),
        r"b\d+_var": ArraySpec("float32", (3, None), low=0.0),
    }
    meta = {"rays": MetaSpec(dict, items=int), "split": MetaSpec(dict, required=False, items=(int, float))}

    def check(arrays: dict, meta: dict, sizes: dict) -> None:
        nblocks = sum(k.endswith("_head") for k in arrays)
        if len(arrays) != 1 + nblocks * len(_BLOCK_ARRAYS) or any(
            f"b{g}_{n}" not in arrays for g in range(nblocks) for n in _BLOCK_ARRAYS
        ):
            raise FileFormatError("tile blocks are incomplete (every block holds " + ", ".join(_BLOCK_ARRAYS) + ")")
        for g in range(nblocks):
            b = {n: arrays[f"b{g}_{n}"] for n in _BLOCK_ARRAYS}
            obj, bounce, size = (int(v) for v in b["head"])
            if not (0 <= obj < m and 1 <= bounce <= bounces) or size != (1 if plan[obj] is None else plan[obj].size):
                raise FileFormatError(f"tile block {g} has head {b['head'].tolist()}; not of this run's objects")
            p, z, e = b["upix"].size, b["tw"].size, b["key"].size
            if b["tc"].shape[0] != z or b["vals"].shape[1] != e or b["var"].shape[1] != e:
                raise FileFormatError(f"tile block {g}: term or entry tables of different lengths")
            key, upix = b["key"], b["upix"]
            if (p and int(upix.max()) >= sizes["P"]) or (e and int(key.max()) >= size * z * p):
                raise FileFormatError(f"tile block {g}: a pixel or entry outside its tables")
            # as written: pixels and entry keys ascending, every pixel and term used by an entry
            if (np.diff(upix) <= 0).any() or (np.diff(key) <= 0).any():
                raise FileFormatError(f"tile block {g}: pixels or entries not in ascending order")
            if p and (np.unique(key % p).size != p or np.unique((key // p) % z).size != z):
                raise FileFormatError(f"tile block {g}: a pixel or term that no entry uses")

    return CacheSchema(arrays=arrays, patterns=patterns, meta=meta, check=check)


def _polynomial_tile(work: _TileWork, k: int):
    """Tile ``k``: arrays (emission, its blocks with tile-local term and pixel numbers) and
    meta (rays cast, profile split, ``clock``: the process, wall-clock start and end (epoch
    seconds) and CPU seconds of the tile)."""
    start, cpu0 = time.time(), time.process_time()
    tracer = work.tracer
    rays0, split0 = dict(tracer.rays), dict(tracer.clock.seconds)
    pix = work.pixels(k)
    spp, group = work.counts[k], work.group[k]
    counts = work.path_counts(k)
    emis, red = _tile_entries(tracer, work.scene, pix, counts, k, group, work.seed, work.paths, tick=tile_tick)
    with tracer.clock("blocks"):  # an adaptive tile: each entry is the mean over its pixel's paths
        if isinstance(red, (TileSums, Accumulator)):  # the compiled entries: the blocks in the kernel too
            local = native_local_blocks(red, work.plan, spp)
        else:
            local = _local_blocks(
                red, work.plan, spp if isinstance(spp, int) else spp[red["rec"]][:, None] if red else 1
            )
    arrays = {"emission": emis.numpy()}
    arrays |= {f"b{g}_{n}": b[n].numpy() for g, b in enumerate(local) for n in _BLOCK_ARRAYS}
    rays = {n: tracer.rays[n] - rays0[n] for n in rays0}
    split = {n: v - split0.get(n, 0.0) for n, v in tracer.clock.seconds.items()}
    clock = [os.getpid(), start, time.time(), time.process_time() - cpu0]
    return arrays, {"rays": rays, "split": split, "clock": clock}


def _check_spp(spp, height: int, width: int) -> torch.Tensor:
    """(H, W) int64 paths per pixel from an int or an (H, W) integer map (every value >= 1)."""
    if not isinstance(spp, torch.Tensor) or spp.ndim == 0:
        return torch.full((height, width), check_count(spp, "spp"), dtype=torch.long)
    if spp.shape != (height, width) or spp.dtype.is_floating_point or spp.dtype.is_complex or spp.dtype == torch.bool:
        raise ShapeError(
            f"Expected an spp map of integers with shape ({height}, {width}); got {spp.dtype} {tuple(spp.shape)}"
        )
    if int(spp.min()) < 1:
        raise ValueRangeError(f"every pixel needs spp >= 1; the map's least is {int(spp.min())}")
    return spp.long()


def _lights(scene: Scene, env_point_lights: int | None) -> list[Light]:
    if env_point_lights is None:
        return list(scene.lights)
    if env_point_lights < 1:
        raise ValueRangeError(f"env_point_lights must be >= 1; got {env_point_lights}")
    out: list[Light] = []
    for li in scene.lights:
        if isinstance(li, EnvironmentMap):
            out.append(li.point_lights(env_point_lights).as_light())
        else:
            out.append(li)
    return out


def precompute_polynomial(
    scene: Scene,
    series: str | Sequence[int] | Series = "64,1,1,1",
    spp: int | torch.Tensor = 64,
    seed: int = 0,
    bases: list[ObjectBasis | None] | dict[str, dict[str, Any]] | None = None,
    mixture: Mixture | LobeMixture | None = None,
    env_point_lights: int | None = None,
    light_samples: int = 1,
    tile_rows: int | None = None,
    group: int | None = None,
    checkpoint: str | Path | None = None,
    progress: bool | None = None,
    paths: dict | None = None,
    keep_checkpoint: bool = False,
    plan: str | GIPlan | None = None,
    error: float | None = None,
    time_budget: float | None = None,
    executor: str = "local",
    address: str | None = None,
    max_retries: int = 3,
    guides: bool = True,
    processes: int | None = None,
) -> PolynomialTensors:
    """Precompute the multibounce tensors of ``scene``'s view (Sec. 5.1).

    Args:
        scene: the scene; objects with ``editable=False`` are fixed.
        series: the BRDF series, e.g. ``"64,1,1,1"``; its length is the number of bounces.
        spp: paths per pixel, or an (H, W) integer map of them (adaptive sampling: each pixel
            is the average over its own paths, so every pixel stays unbiased; tiles are row
            bands whatever the map, pass ``s`` tracing the pixels with more than ``s`` paths,
            see :func:`_tiles`).
        seed: the result is a deterministic function of (scene, settings, seed).
        bases: per-object :class:`ObjectBasis` list, or overrides for :func:`plan_bases`.
        mixture: direction sampling (default 70% cosine, 30% Blinn 200); a
            :class:`LobeMixture` samples its objects (the glossy ones by default) from a
            defensive mixture of lobe widths, for edits sharper than the material (the torch
            steps run then, not the compiled vertex kernel); ``LobeMixture(stratified=True)``
            also stratifies the eye vertex's light and direction samples over each pixel's
            paths (:class:`~.sampler.EyeStrata`).
        env_point_lights: replace the environment by its K median-cut point lights for NEE.
        light_samples: next-event samples per light at the eye vertex, each weighted 1/k
            (the same polynomial with less direct-light noise for k - 1 more shadow rays per
            path; later vertices take one).
        tile_rows: image rows per tile (default: about :data:`TILE_PIXELS` pixels per tile).
        group: passes traced together (default: enough for >= 64k rays per batch, which
            lets embree use both cores).
        checkpoint: folder for finished tiles (a :class:`~torch_brdf.records.cache.TileCache`);
            an interrupted run resumes from it; removed on success unless ``keep_checkpoint``.
        progress: tqdm bar over finished tiles (None: on when attached to a terminal or
            notebook, see :func:`~torch_brdf.records.cache.progress_default`).
        paths: tests only: a dict that receives the raw path records (exactness oracle;
            local executor only).
        keep_checkpoint: keep the finished tiles after success (e.g. to extend the run).
        plan: ``"auto"``: :func:`plan_polynomial` chooses series, bases, spp and fixed objects
            for ``error`` / ``time_budget`` (then ``series``, ``spp`` and ``bases`` are
            ignored); or a :class:`~torch_brdf.planner.GIPlan` to carry out.
        error: relative RMSE budget of ``plan="auto"``.
        time_budget: seconds budget of ``plan="auto"``.
        executor: ``"local"`` (this process) or ``"ray"`` (one Ray task per tile, see
            :mod:`torch_brdf.parallel.tiles`); the tensors are the same bit for bit.
        address: Ray only: None / ``"auto"`` (the running or a new local instance) or a
            cluster address.
        max_retries: Ray only: reruns of a tile whose worker died before :class:`TileError`.
        guides: attach the view's denoiser guides (:func:`torch_brdf.transport.guides.guide_buffers`:
            one pixel-centre ray and its mirror ray per pixel, saved with the record and
            versioned by :data:`~torch_brdf.records.guides.GUIDE_VERSION`, also in
            ``meta["guides"]``), so that :func:`torch_brdf.denoise.denoise` needs nothing else;
            False: no guides (``meta["guides"]`` None).
        processes: ``local`` only: tiles computed at once in forked processes (None: one per
            usable core, 1 on a busy machine, while that many tiles fit in the available memory at
            :data:`TILE_BYTES_PER_PATH`; 1: in this process, as ``paths`` needs); the tensors
            are the same.
    Returns:
        :class:`PolynomialTensors` (with ``plan="auto"`` its ``meta["plan"]`` prints the plan);
        ``meta["split"]`` holds the profile split in seconds
        (``rays``, ``sampling``, ``brdf``, ``bookkeeping``, ``blocks`` summed over the tiles
        computed in this call, wherever they ran; ``assemble`` and ``write`` on the driver) and
        ``meta["timeline"]`` the tiles computed in this call as [tile, process id, start, end
        (wall seconds after the call began), CPU seconds], ``meta["tiles_cached"]`` the tiles
        loaded from ``checkpoint``, ``meta["ray_nodes"]`` the
        Ray nodes that computed tiles (0 for ``local``), ``meta["processes"]`` the local
        processes that computed tiles at once (0 for Ray).
    """
    if plan is not None:
        if isinstance(plan, str):
            if plan != "auto":
                raise ValueRangeError(f"plan must be 'auto' or a GIPlan; got {plan!r}")
            plan = plan_polynomial(
                scene, error=error, seconds=time_budget, seed=seed, env_point_lights=env_point_lights, progress=progress
            )
        scene = with_fixed(scene, plan.fixed)
        out = precompute_polynomial(
            scene,
            **plan.kwargs(),
            seed=seed,
            mixture=mixture,
            env_point_lights=env_point_lights,
            tile_rows=tile_rows,
            group=group,
            checkpoint=checkpoint,
            progress=progress,
            paths=paths,
            keep_checkpoint=keep_checkpoint,
            executor=executor,
            address=address,
            max_retries=max_retries,
            guides=guides,
            processes=processes,
        )
        out.meta["plan"] = str(plan)
        return out
    series = Series.parse(series)
    check_count(series.eye, "series bands per bounce", MAX_BANDS)
    seed = check_seed(seed)
    spp_map = _check_spp(spp, scene.camera.height, scene.camera.width)
    tile_rows, group, env_point_lights = (
        None if v is None else check_count(v, k)
        for v, k in ((tile_rows, "tile_rows"), (group, "group"), (env_point_lights, "env_point_lights"))
    )
    if isinstance(bases, list):
        if len(bases) != len(scene.objects):
            raise ShapeError(f"expected {len(scene.objects)} bases (one per object); got {len(bases)}")
        plan = bases
    else:
        plan = plan_bases(scene, series, bases)
    mixture = mixture or Mixture()
    if isinstance(mixture, LobeMixture):  # its object names -> ids
        mixture = mixture.resolve(scene, plan)
    lights = _lights(scene, env_point_lights)
    if paths is not None and executor != "local":
        raise ValueRangeError("paths (the exactness oracle) needs executor='local'")
    cam = scene.camera
    h, w = cam.height, cam.width
    tile_rows = tile_rows or max(1, min(h, TILE_PIXELS // w))
    tiles, tile_spp = _tiles(spp_map.reshape(-1), tile_rows * w)
    uniform = bool((spp_map == spp_map.flatten()[0]).all())
    # passes traced together: >= 64k rays per batch; a tile of equal spp counts tile_rows x
    # width pixels per pass (as a uniform run always did), a tile of several spp its passes'
    # own rays (None, see _pass_groups)
    group_of = [
        group or (max(1, min(s, math.ceil(65536 / (tile_rows * w)))) if isinstance(s, int) else None) for s in tile_spp
    ]
    num_tiles = len(tiles)
    light_samples = check_count(light_samples, "light_samples", 1024)
    work = _TileWork(scene, plan, series, mixture, lights, tiles, tile_spp, group_of, seed, paths, light_samples)
    settings = {
        "scene": scene.name,
        "width": w,
        "height": h,
        "series": list(series.bands),
        "spp": int(spp_map.flatten()[0]) if uniform else float(spp_map.double().mean()),
        "seed": seed,
        "bases": [None if b is None else b.spec() for b in plan],
        "mixture": mixture.spec(),
        "env_point_lights": env_point_lights,
        "tile_rows": tile_rows,
        "group": group_of[0] if uniform else group,
    }
    if not uniform:  # a uniform run keeps the key it always had; a map enters it as run lengths
        settings["spp_map"] = _run_lengths(spp_map.reshape(-1))
        settings["adaptive_tiles"] = "rows"  # row bands of mixed spp (before: a tile per spp level)
    if light_samples != 1:  # likewise
        settings["light_samples"] = light_samples
    # tile format 2: tiles hold their blocks (tile-local numbers), not the reduced entries
    key = settings_key({**settings, "tile_format": 2}, scene)  # scene content in the key
    schema = _tile_schema(plan, series.bounces)
    cache = TileCache(checkpoint, TILE_KIND, key, schema=schema, sizes=lambda k: {"P": int(tiles[k].numel())})
    # paths per tile: its expected cost (the executor starts the longest first) and memory
    tile_paths = [t.numel() * n if isinstance(n, int) else int(n.sum()) for t, n in zip(tiles, tile_spp, strict=True)]
    if processes is None:  # the largest tile's paths (k light samples: k x the eye entries)
        processes = _default_processes(max(tile_paths) * light_samples)
    # Ray tasks and forked tile processes trace in their own process (one per CPU)
    ray_work = _TileWork(
        single_process(scene), plan, series, mixture, lights, tiles, tile_spp, group_of, seed, None, light_samples
    )
    numbering = TermNumbering(len(scene.objects), series.bounces)
    emission = torch.zeros(3, h * w)
    rays = {"closest": 0, "shadow": 0}
    split: dict[str, float] = {"rays": 0.0, "sampling": 0.0, "brdf": 0.0, "bookkeeping": 0.0, "blocks": 0.0}
    split["assemble"] = 0.0
    cached = [0]
    timeline: list[list] = []

    def consume(ti: int, arrays: dict, meta: dict) -> None:
        """Tile ``ti`` into the record (in tile order; its terms are numbered once every tile is in)."""
        t = time.perf_counter()
        pix = work.pixels(ti)
        nblocks = sum(k.endswith("_head") for k in arrays)
        local = [{n: torch.from_numpy(arrays[f"b{g}_{n}"]) for n in _BLOCK_ARRAYS} for g in range(nblocks)]
        emis = torch.from_numpy(arrays["emission"])
        for k, v in meta.get("rays", {}).items():
            rays[k] += int(v)
        if meta.get("cached"):
            cached[0] += 1
        else:
            for k, v in meta.get("split", {}).items():
                split[k] = split.get(k, 0.0) + float(v)
            if "clock" in meta:  # [tile, process, start, end (s after the call's start), CPU s]
                pid, start, end, cpu = meta["clock"]
                timeline.append([ti, int(pid), round(start - epoch0, 4), round(end - epoch0, 4), round(cpu, 4)])
        n = tile_spp[ti]
        emission[:, pix] = (emis / (n if isinstance(n, int) else n[:, None])).float().T
        numbering.add(local, pix)
        split["assemble"] += time.perf_counter() - t

    view_guides = None

    def make_guides() -> None:  # independent of the tiles: computed while they run
        nonlocal view_guides
        # traced in this process (the tiles have the cores): no trace worker to start
        view_guides = guide_buffers(ray_work.scene) if guides else None

    if executor == "local":
        library()  # build (or load) the compiled kernel once, before tiles fork
    t0, epoch0 = time.perf_counter(), time.time()
    results = run_tiles(
        _polynomial_tile,
        work,
        num_tiles,
        cache,
        executor=executor,
        address=address,
        max_retries=max_retries,
        desc=f"precompute {scene.name} ({series.key})",
        progress=progress_default(progress),
        ray_context=ray_work,
        meta={"settings": settings},
        consume=consume,
        processes=1 if paths is not None else processes,
        steps_per_tile=[work.steps(k) for k in range(num_tiles)],
        idle=make_guides,
        cost=tile_paths,
    )
    t = time.perf_counter()
    terms, blocks = numbering.finish()  # the global term ids, once every tile is in
    split["assemble"] += time.perf_counter() - t
    split["write"] = results.write_seconds
    meta = {
        **settings,
        "rays": rays,
        "seconds": time.perf_counter() - t0,
        "split": split,
        "timeline": timeline,
        "tiles_cached": cached[0],
        "executor": executor,
        "ray_nodes": len(results.nodes),
        "processes": results.processes,
    }
    meta["guides"] = GUIDE_VERSION if guides else None
    if not keep_checkpoint:
        cache.remove()
    names = [o.name for o in scene.objects]
    return PolynomialTensors(h, w, series, names, plan, emission, terms, blocks, meta, guides=view_guides)


def plan_polynomial(
    scene: Scene,
    error: float | None = 0.03,
    seconds: float | None = None,
    edit: list[str] | None = None,
    pilot_spp: int = 4,
    pilot_bounces: int = 8,
    seed: int = 0,
    env_point_lights: int | None = None,
    progress: bool | None = None,
    pilot_runs: int = 4,
    adaptive: bool = True,
    max_light_samples: int = 16,
) -> GIPlan:
    """Plan the precomputation for a relative-RMSE ``error`` and/or ``seconds``.

    Bands per object come from projection errors (no tracing); ``pilot_runs`` independent pilot
    runs of ``pilot_spp`` x 1, 2, 2, 4, 1, 2, 2, 4, ... spp and ``pilot_bounces`` bounces (seeds
    independent of ``seed``'s final run) measure the bounce tail, glossy-to-glossy transport,
    the per-pixel Monte Carlo noise and the cost; the decisions are
    :func:`torch_brdf.planner.plan_from_pilots`'s.

    Args:
        scene: the scene.
        error: relative RMSE budget (against the converged polynomial model).
        seconds: precompute time budget.
        edit: the objects to keep editable (default every editable object); the others are fixed.
        pilot_spp: the pilots' samples per pixel.
        pilot_bounces: the pilots' bounces (all 1-band after the eye).
        seed: the pilots use seeds derived from it, independent of the final run's ``seed``.
        env_point_lights: as :func:`precompute_polynomial` (the pilots light the scene the same way).
        progress: a tqdm bar per pilot run (None: on when attached to a terminal or notebook).
        pilot_runs: independent pilot runs (>= 2; more give a steadier per-pixel noise estimate).
        adaptive: plan a per-pixel spp map (adaptive sampling); False: one spp for all pixels.
        max_light_samples: the most light samples per eye vertex the plan may choose; above 1,
            two more pilots (``pilot_spp`` x 1 and 2 spp) with 4 samples measure what they buy.
    Returns:
        :class:`~torch_brdf.planner.GIPlan` (``print(plan)`` shows choices, cost and error).
    """
    if check_count(pilot_runs, "pilot_runs") < 2:
        raise ValueRangeError(f"the planner needs at least two pilot runs; got {pilot_runs}")
    bases, errors, fixed = planned_bases(scene, error if error is not None else 0.03, edit)
    scene = with_fixed(scene, fixed)
    eye = max([1] + [b.J for b in bases if b is not None])
    series = Series((eye,) + (1,) * (pilot_bounces - 1))
    pilots = [
        precompute_polynomial(
            scene,
            series,
            spp=pilot_spp * (1, 2, 2, 4)[k % 4],
            seed=seed + 7919 * (k + 1),
            bases=bases,
            env_point_lights=env_point_lights,
            progress=progress,
        )
        for k in range(pilot_runs)
    ]
    split = []
    if check_count(max_light_samples, "max_light_samples") > 1:
        split = [
            precompute_polynomial(
                scene,
                series,
                spp=pilot_spp * (k + 1),
                seed=seed + 7919 * (pilot_runs + k + 1),
                bases=bases,
                env_point_lights=env_point_lights,
                light_samples=4,
                progress=progress,
            )
            for k in range(2)
        ]
    return plan_from_pilots(
        scene,
        bases,
        errors,
        fixed,
        pilots,
        error=error,
        seconds=seconds,
        adaptive=adaptive,
        split_pilots=split,
        max_light_samples=max_light_samples,
    )
