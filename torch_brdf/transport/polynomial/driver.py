"""The driver of the multibounce precomputation: tiles, seeds, the tile cache, the record."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from ..._checks import MAX_BANDS, check_count, check_seed
from ...data import progress_default
from ...errors import ShapeError, ValueRangeError
from ...records.cache import TileCache, settings_key
from ...records.polynomial import ObjectBasis, PolynomialTensors, Series, TensorBlock
from ...scene.envmap import EnvironmentMap
from ...scene.lights import Light
from ...scene.scene import Scene
from ..pathtrace import seeded_generator
from .plan import plan_bases
from .reduce import _blocks_from_entries, _reduce, _term_tables
from .sampler import Mixture
from .tracer import _Tracer

__all__ = ["TILE_KIND", "precompute_polynomial"]

TILE_KIND = "multibounce-tile"


def _tile_entries(tracer, scene, pixels, tile, spp, group, seed, paths=None, tick=None):
    """Trace a tile and reduce its entries to (sum, sum of per-path squares) per key;
    ``tick()`` (if given) after each pass group."""
    cam = scene.camera
    p = pixels.numel()
    sizes = {
        "rec": p,
        "obj": tracer.num_objects,
        "bounce": tracer.series.bounces + 1,
        "j": max([1] + [b.size for b in tracer.bases if b is not None]),
        "w": max(1, sum(b.second_size for b in tracer.bases if b is not None) if tracer.series.two_level else 1),
    }
    emis = torch.zeros(p, 3, dtype=torch.float64)
    reduced = []
    for gi, g0 in enumerate(range(0, spp, group)):
        ng = min(group, spp - g0)
        gen = seeded_generator(seed, tile, gi)
        off = torch.rand(ng * p, 2, generator=gen, dtype=torch.float64)
        ray = torch.arange(ng * p)
        rec = ray % p
        pix = pixels[rec]
        o, d = cam.rays_through((pix % cam.width).double() + off[:, 1], (pix // cam.width).double() + off[:, 0])
        e, ent = tracer.run(o, d, ray, gen, paths)  # entries carry the ray index as "path"
        emis.index_add_(0, rec, e.double())
        if tick is not None:
            tick()
        dd = ent.cat()
        if not dd:
            continue
        ray_id = dd.pop("path")
        dd["rec"], dd["path"] = ray_id % p, ray_id // p
        reduced.append(_reduce(dd, {**sizes, "path": ng}, by_path=True))
    reduced = [r for r in reduced if r]
    if not reduced:
        return emis, {}
    cat = {k: torch.cat([r[k] for r in reduced]) for k in reduced[0]}
    cat["weight"] = cat.pop("sum")
    return emis, _reduce(cat, sizes, by_path=False)


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
    spp: int = 64,
    seed: int = 0,
    bases: list[ObjectBasis | None] | dict[str, dict[str, Any]] | None = None,
    mixture: Mixture | None = None,
    env_point_lights: int | None = None,
    tile_rows: int | None = None,
    group: int | None = None,
    checkpoint: str | Path | None = None,
    progress: bool | None = None,
    paths: dict | None = None,
    keep_checkpoint: bool = False,
) -> PolynomialTensors:
    """Precompute the multibounce tensors of ``scene``'s view (Sec. 5.1).

    Args:
        scene: the scene; objects with ``editable=False`` are fixed.
        series: the BRDF series, e.g. ``"64,1,1,1"``; its length is the number of bounces.
        spp: paths per pixel.
        seed: the result is a deterministic function of (scene, settings, seed).
        bases: per-object :class:`ObjectBasis` list, or overrides for :func:`plan_bases`.
        mixture: direction sampling (default 70% cosine, 30% Blinn 200).
        env_point_lights: replace the environment by its K median-cut point lights for NEE.
        tile_rows: image rows per tile (default: about 16k pixels per tile).
        group: passes traced together (default: enough for >= 64k rays per batch, which
            lets embree use both cores).
        checkpoint: folder for finished tiles (a :class:`~torch_brdf.records.cache.TileCache`);
            an interrupted run resumes from it; removed on success unless ``keep_checkpoint``.
        progress: tqdm bar over tiles and pass groups (None: on when attached to a terminal
            or notebook, see :func:`~torch_brdf.records.cache.progress_default`).
        paths: tests only: a dict that receives the raw path records (exactness oracle).
        keep_checkpoint: keep the finished tiles after success (e.g. to extend the run).
    Returns:
        :class:`PolynomialTensors`.
    """
    series = Series.parse(series)
    check_count(series.eye, "series bands per bounce", MAX_BANDS)
    spp, seed = check_count(spp, "spp"), check_seed(seed)
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
    lights = _lights(scene, env_point_lights)
    cam = scene.camera
    h, w = cam.height, cam.width
    tile_rows = tile_rows or max(1, min(h, 16384 // w))
    tiles = [torch.arange(r0 * w, min(h, r0 + tile_rows) * w) for r0 in range(0, h, tile_rows)]
    group = group or max(1, min(spp, math.ceil(65536 / max(1, tiles[0].numel()))))
    tracer = _Tracer(scene, plan, series, mixture, lights)
    settings = {
        "scene": scene.name,
        "width": w,
        "height": h,
        "series": list(series.bands),
        "spp": spp,
        "seed": seed,
        "bases": [None if b is None else b.spec() for b in plan],
        "mixture": [mixture.diffuse, mixture.exponent],
        "env_point_lights": env_point_lights,
        "tile_rows": tile_rows,
        "group": group,
    }
    cache = TileCache(checkpoint, TILE_KIND, settings_key(settings, scene))  # scene content in the key
    term_index: dict[int, dict] = {}
    blocks: list[TensorBlock] = []
    emission = torch.zeros(3, h * w)
    t0 = time.perf_counter()
    groups = math.ceil(spp / group)  # the bar ticks per pass group of every tile
    bar = tqdm(
        total=len(tiles) * groups,
        desc=f"precompute {scene.name} ({series.key})",
        unit="group",
        disable=not progress_default(progress),
    )
    for ti in range(len(tiles)):
        pix = tiles[ti]
        done = cache.load(ti)
        if done is not None:
            arrays, meta = done
            red = {k[2:]: torch.from_numpy(v) for k, v in arrays.items() if k.startswith("r_")}
            emis = torch.from_numpy(arrays["emission"])
            for k, v in meta.get("rays", {}).items():
                tracer.rays[k] += int(v)
            bar.update(groups)
        else:
            before = dict(tracer.rays)
            emis, red = _tile_entries(tracer, scene, pix, ti, spp, group, seed, paths, tick=lambda: bar.update(1))
            rays = {k: tracer.rays[k] - before[k] for k in before}
            arrays = {"emission": emis.numpy(), **{f"r_{k}": v.numpy() for k, v in red.items()}}
            cache.save(ti, arrays, meta={"settings": settings, "rays": rays})
        emission[:, pix] = (emis / spp).float().T
        blocks.extend(_blocks_from_entries(red, pix, plan, spp, term_index))
    bar.close()
    terms = _term_tables(term_index, len(scene.objects), series.bounces)
    meta = {**settings, "rays": dict(tracer.rays), "seconds": time.perf_counter() - t0}
    if not keep_checkpoint:
        cache.remove()
    return PolynomialTensors(h, w, series, [o.name for o in scene.objects], plan, emission, terms, blocks, meta)
