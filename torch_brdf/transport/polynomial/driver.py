"""The driver of the multibounce precomputation: tiles, seeds, the tile cache, the record."""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..._checks import check_seed
from ...data import progress_default
from ...errors import FileFormatError, ShapeError, ValueRangeError
from ...parallel.threads import available_memory, tile_processes
from ...parallel.tiles import run_tiles, single_process, tile_tick
from ...records.cache import ArraySpec, CacheSchema, MetaSpec, TileCache, settings_key
from ...records.guides import GUIDE_VERSION
from ...records.polynomial import ObjectBasis, PolynomialTensors
from ...scene.camera import Camera
from ...scene.envmap import EnvironmentMap
from ...scene.lights import Light
from ...scene.scene import Scene
from .._native import Accumulator, TileSums, library
from .._native import ptr as _p
from ..guides import guide_buffers
from ..pathtrace import seeded_generator
from .bases import plan_bases, with_fixed
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
from .settings import PolynomialSettings, _run_lengths
from .tracer import _Tracer
from .vertex import c_rand_matches

__all__ = ["TILE_KIND", "TILE_PIXELS", "precompute_polynomial", "spp_map_of"]

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


#: the keywords ``precompute_polynomial`` took before its settings were one object
_SETTING_KEYWORDS = {f.name for f in dataclasses.fields(PolynomialSettings)}
_PLAN_KEYWORDS = {"plan", "error", "time_budget"}


def _old_call(settings: Any, old: dict[str, Any]) -> TypeError:
    """The error for a call that passes settings one by one (or a plan) instead of an object."""
    given = sorted(old) + ([] if isinstance(settings, (PolynomialSettings, type(None))) else [repr(settings)])
    planned = _PLAN_KEYWORDS & set(old)
    where = "the planner (torch_brdf.planner.precompute_planned)" if planned else "a PolynomialSettings"
    return TypeError(
        f"precompute_polynomial(scene, settings, *, seed, progress, checkpoint, ...) takes its settings from {where}, "
        f"e.g. precompute_polynomial(scene, PolynomialSettings(series='64,1,1,1', spp=64), seed=0); "
        f"got {', '.join(given)} (settings fields: {', '.join(sorted(_SETTING_KEYWORDS))})"
    )


@dataclasses.dataclass
class _Prepared:
    """What a run derives from (scene, settings, seed) before any tracing: bases, sampler,
    lights, tiles, the record's settings (its ``meta``) and the resume key."""

    bases: list[ObjectBasis | None]
    mixture: Mixture | LobeMixture
    lights: list[Light]
    tiles: list[torch.Tensor]
    tile_spp: list[torch.Tensor | int]
    group_of: list[int | None]
    record: dict[str, Any]
    key: str


def _prepare(scene: Scene, s: PolynomialSettings, seed: int) -> _Prepared:
    """Resolve ``s`` on ``scene`` (bases, sampler ids, lights, tiles, pass groups)."""
    cam = scene.camera
    h, w = cam.height, cam.width
    spp_map = s.spp_map(h, w)
    if isinstance(s.bases, tuple):
        if len(s.bases) != len(scene.objects):
            raise ShapeError(f"expected {len(scene.objects)} bases (one per object); got {len(s.bases)}")
        bases = list(s.bases)
    else:
        bases = plan_bases(scene, s.series, s.bases)
    mixture = s.mixture.resolve(scene, bases) if isinstance(s.mixture, LobeMixture) else s.mixture  # names -> ids
    lights = _lights(scene, s.env_point_lights)
    tile_rows = s.tile_rows or max(1, min(h, TILE_PIXELS // w))
    tiles, tile_spp = _tiles(spp_map.reshape(-1), tile_rows * w)
    uniform = bool((spp_map == spp_map.flatten()[0]).all())
    # passes traced together: >= 64k rays per batch; a tile of equal spp counts tile_rows x
    # width pixels per pass (as a uniform run always did), a tile of several spp its passes'
    # own rays (None, see _pass_groups)
    group_of = [
        s.group or (max(1, min(n, math.ceil(65536 / (tile_rows * w)))) if isinstance(n, int) else None)
        for n in tile_spp
    ]
    record = {
        "scene": scene.name,
        "width": w,
        "height": h,
        "series": list(s.series.bands),
        "spp": int(spp_map.flatten()[0]) if uniform else float(spp_map.double().mean()),
        "seed": seed,
        "bases": [None if b is None else b.spec() for b in bases],
        "mixture": mixture.spec(),
        "env_point_lights": s.env_point_lights,
        "tile_rows": tile_rows,
        "group": group_of[0] if uniform else s.group,
    }
    if not uniform:  # a uniform run's meta has no map; a map enters it as run lengths
        record["spp_map"] = _run_lengths(spp_map.reshape(-1))
        record["adaptive_tiles"] = "rows"  # row bands of mixed spp
    if s.light_samples != 1:  # likewise
        record["light_samples"] = s.light_samples
    # tile format 2: tiles hold their blocks (tile-local numbers), not the reduced entries; the
    # scene's content (meshes, materials, lights, camera) is in the key too
    key = settings_key({"settings": s.key(), "scene": scene.name, "seed": seed, "tile_format": 2}, scene)
    return _Prepared(bases, mixture, lights, tiles, tile_spp, group_of, record, key)


class _Assembly:
    """The record's driver side: tiles in (tile order), their terms numbered once every tile is in."""

    def __init__(self, work: _TileWork, height: int, width: int, num_objects: int, bounces: int):
        self.work = work
        self.numbering = TermNumbering(num_objects, bounces)
        self.emission = torch.zeros(3, height * width)
        self.rays = {"closest": 0, "shadow": 0}
        self.split: dict[str, float] = {"rays": 0.0, "sampling": 0.0, "brdf": 0.0, "bookkeeping": 0.0, "blocks": 0.0}
        self.split["assemble"] = 0.0
        self.cached = 0
        self.timeline: list[list] = []
        self.epoch0 = time.time()

    def consume(self, ti: int, arrays: dict, meta: dict) -> None:
        """Tile ``ti`` into the record (in tile order; its terms are numbered once every tile is in)."""
        t = time.perf_counter()
        pix = self.work.pixels(ti)
        nblocks = sum(k.endswith("_head") for k in arrays)
        local = [{n: torch.from_numpy(arrays[f"b{g}_{n}"]) for n in _BLOCK_ARRAYS} for g in range(nblocks)]
        emis = torch.from_numpy(arrays["emission"])
        for k, v in meta.get("rays", {}).items():
            self.rays[k] += int(v)
        if meta.get("cached"):
            self.cached += 1
        else:
            for k, v in meta.get("split", {}).items():
                self.split[k] = self.split.get(k, 0.0) + float(v)
            if "clock" in meta:  # [tile, process, start, end (s after the call's start), CPU s]
                pid, start, end, cpu = meta["clock"]
                e0 = self.epoch0
                self.timeline.append([ti, int(pid), round(start - e0, 4), round(end - e0, 4), round(cpu, 4)])
        n = self.work.counts[ti]
        self.emission[:, pix] = (emis / (n if isinstance(n, int) else n[:, None])).float().T
        self.numbering.add(local, pix)
        self.split["assemble"] += time.perf_counter() - t

    def finish(self) -> tuple[list, list]:
        """The global term ids and blocks, once every tile is in."""
        t = time.perf_counter()
        terms, blocks = self.numbering.finish()
        self.split["assemble"] += time.perf_counter() - t
        return terms, blocks


def precompute_polynomial(
    scene: Scene,
    settings: PolynomialSettings | None = None,
    *,
    seed: int = 0,
    progress: bool | None = None,
    checkpoint: str | Path | None = None,
    keep_checkpoint: bool = False,
    executor: str = "local",
    address: str | None = None,
    max_retries: int = 3,
    processes: int | None = None,
    paths: dict | None = None,
    **old: Any,
) -> PolynomialTensors:
    """Precompute the multibounce tensors of ``scene``'s view (Sec. 5.1).

    Args:
        scene: the scene; objects with ``editable=False`` (or named in ``settings.fixed``) are fixed.
        settings: :class:`~.settings.PolynomialSettings` (series, spp or spp map, bases,
            sampler, light samples, tiles, guides; None: its defaults); the planner
            (:func:`torch_brdf.planner.plan_polynomial`) returns one for an error or time budget.
        seed: the result is a deterministic function of (scene, settings, seed).
        progress: tqdm bar over finished tiles (None: on when attached to a terminal or
            notebook, see :func:`~torch_brdf.records.cache.progress_default`).
        checkpoint: folder for finished tiles (a :class:`~torch_brdf.records.cache.TileCache`
            keyed by ``settings.key()``, the seed and the scene's content); an interrupted run
            resumes from it; removed on success unless ``keep_checkpoint``.
        keep_checkpoint: keep the finished tiles after success (e.g. to extend the run).
        executor: ``"local"`` (this process) or ``"ray"`` (one Ray task per tile, see
            :mod:`torch_brdf.parallel.tiles`); the tensors are the same bit for bit.
        address: Ray only: None / ``"auto"`` (the running or a new local instance) or a
            cluster address.
        max_retries: Ray only: reruns of a tile whose worker died before :class:`TileError`.
        processes: ``local`` only: tiles computed at once in forked processes (None: one per
            usable core, 1 on a busy machine, while that many tiles fit in the available memory at
            :data:`TILE_BYTES_PER_PATH`; 1: in this process, as ``paths`` needs); the tensors
            are the same.
        paths: tests only: a dict that receives the raw path records (exactness oracle;
            local executor only).
    Returns:
        :class:`PolynomialTensors`; ``meta`` holds the resolved settings (series, spp, bases,
        sampler, tiles...), ``meta["split"]`` the profile split in seconds (``rays``,
        ``sampling``, ``brdf``, ``bookkeeping``, ``blocks`` summed over the tiles computed in
        this call; ``assemble`` and ``write`` on the driver), ``meta["timeline"]`` those tiles
        as [tile, process id, start, end (wall seconds after the call began), CPU seconds],
        ``meta["tiles_cached"]``, ``meta["ray_nodes"]``, ``meta["processes"]`` and
        ``meta["guides"]`` the version of the view's denoiser guides
        (:func:`~torch_brdf.transport.guides.guide_buffers`; None without guides).
    Raises:
        TypeError: settings given one by one (``spp=``, ``series=``...) or a plan (``plan=``).
    """
    if old or not isinstance(settings, (PolynomialSettings, type(None))):
        raise _old_call(settings, old)
    s = PolynomialSettings() if settings is None else settings
    seed = check_seed(seed)
    if paths is not None and executor != "local":
        raise ValueRangeError("paths (the exactness oracle) needs executor='local'")
    scene = with_fixed(scene, s.fixed)
    run = _prepare(scene, s, seed)
    schema = _tile_schema(run.bases, s.series.bounces)
    cache = TileCache(checkpoint, TILE_KIND, run.key, schema=schema, sizes=lambda k: {"P": int(run.tiles[k].numel())})
    h, w = scene.camera.height, scene.camera.width
    # paths per tile: its expected cost (the executor starts the longest first) and memory
    tile_paths = [
        t.numel() * n if isinstance(n, int) else int(n.sum()) for t, n in zip(run.tiles, run.tile_spp, strict=True)
    ]
    if processes is None:  # the largest tile's paths (k light samples: k x the eye entries)
        processes = _default_processes(max(tile_paths) * s.light_samples)
    common = (run.bases, s.series, run.mixture, run.lights, run.tiles, run.tile_spp, run.group_of, seed)
    work = _TileWork(scene, *common, paths, s.light_samples)
    # Ray tasks and forked tile processes trace in their own process (one per CPU)
    ray_work = _TileWork(single_process(scene), *common, None, s.light_samples)
    asm = _Assembly(work, h, w, len(scene.objects), s.series.bounces)
    view_guides = None

    def make_guides() -> None:  # independent of the tiles: computed while they run
        nonlocal view_guides
        # traced in this process (the tiles have the cores): no trace worker to start
        view_guides = guide_buffers(ray_work.scene) if s.guides else None

    if executor == "local":
        library()  # build (or load) the compiled kernel once, before tiles fork
    t0, asm.epoch0 = time.perf_counter(), time.time()
    results = run_tiles(
        _polynomial_tile,
        work,
        len(run.tiles),
        cache,
        executor=executor,
        address=address,
        max_retries=max_retries,
        desc=f"precompute {scene.name} ({s.series.key})",
        progress=progress_default(progress),
        ray_context=ray_work,
        meta={"settings": run.record},
        consume=asm.consume,
        processes=1 if paths is not None else processes,
        steps_per_tile=[work.steps(k) for k in range(len(run.tiles))],
        idle=make_guides,
        cost=tile_paths,
    )
    terms, blocks = asm.finish()
    asm.split["write"] = results.write_seconds
    meta = {
        **run.record,
        "rays": asm.rays,
        "seconds": time.perf_counter() - t0,
        "split": asm.split,
        "timeline": asm.timeline,
        "tiles_cached": asm.cached,
        "executor": executor,
        "ray_nodes": len(results.nodes),
        "processes": results.processes,
    }
    meta["guides"] = GUIDE_VERSION if s.guides else None
    if not keep_checkpoint:
        cache.remove()
    names = [o.name for o in scene.objects]
    return PolynomialTensors(h, w, s.series, names, run.bases, asm.emission, terms, blocks, meta, guides=view_guides)
