r"""A plain wavefront path tracer with the full BRDFs and next-event estimation.

The renderer of ``torch-brdf render`` / ``demo``; direct lighting when
``max_bounces == 1``. Each object's material dict becomes a BRDF module of
:mod:`torch_brdf.brdf` (:func:`~torch_brdf.brdf.create`).

Estimator. A path is traced from the eye; at every surface vertex each light is sampled
once (next-event estimation, with a shadow ray), then the path continues in a direction
drawn by the BRDF's own importance sampling with throughput ``*= f cos / pdf``. Emission
is counted only where NEE cannot see it: the environment and emitters seen directly
from the eye. So the estimator is unbiased for every BRDF, but noisy where a sharp lobe
reflects a bright, large light (no MIS yet). Surfaces are two-sided: normals are flipped
to face the arriving ray; shading frames come from the shading normal.

Reproducibility: every sample pass ``s`` uses its own generator seeded from
``(seed, s)``, so a render interrupted after ``k`` passes and resumed from its
checkpoint equals the uninterrupted render bit for bit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from .._checks import check_count, check_seed
from ..brdf import BRDF, create
from ..errors import SceneError, TorchBRDFError
from ..frame import Frame
from ..records.cache import Checkpoint
from ..scene.scene import Scene

CHECKPOINT_KIND = "pathtrace-checkpoint"


def material_brdfs(scene: Scene) -> list[BRDF]:
    """One BRDF module per object (index = object id), from the scene's material dicts."""
    cache: dict[str, BRDF] = {}
    for obj in scene.objects:
        if obj.material not in cache:
            try:
                cache[obj.material] = create(scene.materials[obj.material])
            except TorchBRDFError as exc:
                raise SceneError(f"material {obj.material!r}: {exc}") from exc
    return [cache[o.material] for o in scene.objects]


def rows_by_object(oid: torch.Tensor) -> list[tuple[int, torch.Tensor]]:
    """Rows of each object id: [(object, row indices)], by one stable sort (not a mask per object)."""
    if oid.numel() == 0:
        return []
    order = torch.argsort(oid, stable=True)
    ids, counts = torch.unique_consecutive(oid[order], return_counts=True)
    return list(zip(ids.tolist(), torch.split(order, counts.tolist()), strict=True))


def _grouped(oid: torch.Tensor, fn, width: int) -> torch.Tensor:
    """Apply ``fn(object_id, rows) -> (m, width)`` to each object's rows of a batch."""
    out = torch.zeros(oid.numel(), width)
    for o, rows in rows_by_object(oid):
        out[rows] = fn(o, rows)
    return out


def seeded_generator(*keys: int) -> torch.Generator:
    """A torch generator whose stream is a function of ``keys`` (e.g. (seed, pass) or
    (seed, tile, group)), through numpy's SeedSequence, so streams of different keys are
    independent and any one can be regenerated on resume."""
    g = torch.Generator()
    g.manual_seed(int(np.random.SeedSequence(list(keys)).generate_state(1, np.uint64)[0] >> 1))
    return g


def emission_seen(scene: Scene, directions: torch.Tensor, hits) -> torch.Tensor:
    """(P, 3) radiance of what the rays see directly: the environment where they miss, area
    lights where they hit an emitter."""
    out = torch.zeros(directions.shape[0], 3)
    env = scene.environment
    miss = ~hits.hit
    if env is not None and bool(miss.any()):
        out[miss] += env.eval_miss(directions[miss])
    for oid, light in scene.area_lights.items():
        on = hits.object_id == oid
        if bool(on.any()):
            out[on] += light.emitted(directions[on], hits.geometric_normal[on])
    return out


def shading_frame(d_in: torch.Tensor, ng: torch.Tensor, ns: torch.Tensor):
    """Two-sided shading at path vertices: normals flipped to face the arriving ray, the shading
    normal replaced by the geometric one where they disagree.

    Returns:
        (ng, ns, frame, wo): the flipped normals (n, 3), the local :class:`Frame` and the
        local outgoing direction (n, 3).
    """
    flip = torch.where((d_in * ng).sum(-1, keepdim=True) > 0, -1.0, 1.0)
    ng, ns = ng * flip, ns * flip
    ns = torch.where((ns * ng).sum(-1, keepdim=True) > 0, ns, ng)
    frame = Frame.from_normal(ns)
    return ng, ns, frame, frame.to_local(-d_in)


def sample_light(scene: Scene, light, pos, ng, ns, gen):
    """Next-event estimation towards ``light`` from every vertex.

    Returns:
        (ls, cos, candidates, visible): the :class:`~torch_brdf.scene.lights.LightSample`, the
        cosine at the shading normal (n,), how many shadow rays were cast, and the rows (long)
        that see the light.
    """
    ls = light.sample(pos, gen)
    cos = (ls.direction * ns).sum(-1)
    k = torch.nonzero((cos > 0) & ((ls.direction * ng).sum(-1) > 0) & (ls.pdf > 0)).squeeze(1)
    if k.numel() == 0:
        return ls, cos, 0, k
    return ls, cos, k.numel(), k[scene.visible(pos[k], ng[k], ls.direction[k], ls.distance[k])]


@torch.no_grad()
def _radiance(scene: Scene, origins, directions, brdfs: list[BRDF], max_bounces: int, gen) -> torch.Tensor:
    """One path per ray: (P, 3) radiance estimates (float32)."""
    hits = scene.trace(origins, directions)
    out = emission_seen(scene, directions, hits)
    # the active paths, compacted: pixel index, arriving direction, surface, throughput
    idx = torch.nonzero(hits.hit).squeeze(1)
    d_in, pos = directions[idx], hits.position[idx]
    ng, ns, oid = hits.geometric_normal[idx], hits.normal[idx], hits.object_id[idx]
    beta = torch.ones(idx.numel(), 3)
    for bounce in range(max_bounces):
        if idx.numel() == 0:
            break
        ng, ns, frame, wo = shading_frame(d_in, ng, ns)
        for light in scene.lights:
            ls, cos, _, k = sample_light(scene, light, pos, ng, ns, gen)
            if k.numel() == 0:
                continue
            wi_k, wo_k = frame.to_local(ls.direction)[k], wo[k]
            f = _grouped(oid[k], lambda o, m, wi_k=wi_k, wo_k=wo_k: brdfs[o].eval_local(wi_k[m], wo_k[m]), 3)
            out.index_add_(0, idx[k], beta[k] * f * ls.weight[k] * cos[k, None])
        if bounce == max_bounces - 1:
            break
        # continue the path by the BRDF's own importance sampling: beta *= f cos / pdf
        u = torch.rand(idx.numel(), 2, generator=gen)

        def step(o, m, u=u, wo=wo):
            wi_l, pdf = brdfs[o].sample_local(wo[m], u[m])
            f = brdfs[o].eval_local(wi_l, wo[m])
            w = torch.where(pdf > 0, wi_l[:, 2].clamp_min(0) / pdf.clamp_min(1e-30), 0.0)
            return torch.cat((wi_l, f * w[:, None]), -1)

        res = _grouped(oid, step, 6)
        wi, beta = frame.to_world(res[:, :3]), beta * res[:, 3:]
        ok = torch.nonzero(((wi * ng).sum(-1) > 0) & (beta.amax(-1) > 0)).squeeze(1)
        sub = scene.trace(scene.spawn(pos[ok], ng[ok], wi[ok]), wi[ok])
        keep = ok[sub.hit]
        idx, beta, d_in = idx[keep], beta[keep], wi[keep]
        pos, ng, ns, oid = (x[sub.hit] for x in (sub.position, sub.geometric_normal, sub.normal, sub.object_id))
    return out


def path_trace(
    scene: Scene,
    spp: int = 16,
    max_bounces: int = 4,
    seed: int = 0,
    chunk: int = 1 << 16,
    checkpoint: str | Path | None = None,
    checkpoint_every: int = 4,
    progress: bool = True,
) -> torch.Tensor:
    """Render ``scene`` from its camera: (H, W, 3) float32 linear radiance.

    Args:
        scene: the scene (any BRDFs of the library; see the module docstring).
        spp: samples (paths) per pixel, each through a jittered point of the pixel.
        max_bounces: surface vertices per path; 1 is direct lighting only.
        seed: the render is a deterministic function of (scene, spp, max_bounces, seed).
        chunk: rays traced together (memory vs. overhead).
        checkpoint: file to save progress to every ``checkpoint_every`` passes and to
            resume from when it exists with matching settings (a
            :class:`~torch_brdf.records.cache.Checkpoint`: versioned, checksummed, atomic).
        checkpoint_every: passes between checkpoint saves.
        progress: show a tqdm bar over sample passes.
    Raises:
        ValueRangeError: a count (``spp``, ``max_bounces``, ``chunk``, ``checkpoint_every``)
            that is not a positive integer, or a seed outside ``[0, 2**63)``.
    """
    spp, max_bounces, seed = check_count(spp, "spp"), check_count(max_bounces, "max_bounces"), check_seed(seed)
    chunk, checkpoint_every = check_count(chunk, "chunk"), check_count(checkpoint_every, "checkpoint_every")
    cam = scene.camera
    h, w = cam.height, cam.width
    brdfs = material_brdfs(scene)
    settings = {"scene": scene.name, "width": w, "height": h, "spp": spp, "max_bounces": max_bounces, "seed": seed}
    total = torch.zeros(h * w, 3, dtype=torch.float64)
    start = 0
    ckpt = None if checkpoint is None else Checkpoint(checkpoint, CHECKPOINT_KIND, settings)
    saved = None if ckpt is None else ckpt.load()
    if saved is not None:
        total = torch.from_numpy(saved[0]["sum"])
        start = int(saved[1]["passes_done"])
    bar = tqdm(range(start, spp), total=spp, initial=start, desc=f"path trace {scene.name}", disable=not progress)
    for s in bar:
        gen = seeded_generator(seed, s)
        o, d = cam.generate_rays(jitter=True, generator=gen)
        for a in range(0, h * w, chunk):
            sl = slice(a, min(a + chunk, h * w))
            total[sl] += _radiance(scene, o[sl], d[sl], brdfs, max_bounces, gen).double()
        done = s + 1
        if ckpt is not None and (done % checkpoint_every == 0 or done == spp):
            ckpt.save({"sum": total.numpy()}, meta={"settings": settings, "passes_done": done})
    return (total / spp).to(torch.float32).reshape(h, w, 3)


def reference_path_trace(scene: Scene, spp: int = 256, max_bounces: int = 4, seed: int = 0, **kwargs) -> torch.Tensor:
    """The unbiased reference of the multibounce editor: :func:`path_trace` with every
    object's full BRDF, BRDF importance sampling and next-event estimation (see the module
    docstring), to measure what a BRDF series, diffuse equivalents and band projections cost.

    Args:
        scene, spp, max_bounces, seed: as :func:`path_trace`; ``max_bounces`` counts surface
            vertices, so it matches a series of that length (Mitsuba's ``max_depth`` is
            ``max_bounces + 1``).
        kwargs: ``chunk``, ``checkpoint``, ``checkpoint_every``, ``progress``.
    Returns:
        (H, W, 3) float32 linear radiance.
    """
    return path_trace(scene, spp=spp, max_bounces=max_bounces, seed=seed, **kwargs)
