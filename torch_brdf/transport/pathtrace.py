r"""A plain wavefront path tracer with the full BRDFs and next-event estimation.

The renderer of ``torch-brdf render`` / ``demo``; direct lighting when
``max_bounces == 1``. Each object's material dict becomes a BRDF module of
:mod:`torch_brdf.brdf` (:func:`~torch_brdf.brdf.create`).

Estimator. A path is traced from the eye; at every surface vertex each light is sampled
once (next-event estimation, with a shadow ray), then the path continues in a direction
drawn by the BRDF's own importance sampling with throughput ``*= f cos / pdf``. With
``mis=True`` (the default) the light the BRDF-sampled ray finds (the environment where it
escapes, an emitter's front where it hits one) is counted too, and both samples of such a
light are weighted by Veach's power heuristic :math:`w_a = p_a^2/(p_a^2+p_b^2)` of their
solid-angle pdfs (Veach 1997, ch. 9), so sharp lobes reflecting large bright lights (a
glossy wall under an area light, a glossy object under sun and sky) converge without
fireflies; at the last vertex the BRDF ray is traced only for that emission. Delta lights
and area lights not bound to an object are found by NEE alone (weight 1). With
``mis=False`` emission is counted only where NEE cannot see it: the environment and
emitters seen directly from the eye. Either way the estimator is unbiased for every BRDF.
Surfaces are two-sided: normals are flipped to face the arriving ray; shading frames come
from the shading normal.

Reproducibility: every sample pass ``s`` uses its own generator seeded from
``(seed, s)``, so a render interrupted after ``k`` passes and resumed from its
checkpoint equals the uninterrupted render bit for bit.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from .._checks import check_bool, check_count, check_fields, check_seed
from ..brdf import BRDF, create
from ..brdf.textured import texturable, textured_eval_local
from ..data import progress_default
from ..errors import SceneError, TorchBRDFError
from ..frame import Frame
from ..records.cache import ArraySpec, CacheSchema, Checkpoint, MetaSpec, settings_key
from ..scene.scene import Scene
from ..scene.textures import texture_at_hits
from ._native import area_light_sample

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
    out = _BRDFList(cache[o.material] for o in scene.objects)
    out.textured = {i for i, o in enumerate(scene.objects) if o.textures}
    for i in out.textured:
        model = scene.materials[scene.objects[i].material]["type"]
        if not texturable(model):
            raise SceneError(
                f"object {scene.objects[i].name!r} has a base-colour texture but its material model {model!r} "
                "has no base colour to scale"
            )
    return out


class _BRDFList(list):
    """The per-object BRDFs, and ``textured``: the ids of objects with a base-colour texture."""

    textured: set[int]


def rows_by_object(oid: torch.Tensor) -> list[tuple[int, torch.Tensor]]:
    """Rows of each object id: [(object, row indices)], by one stable sort (not a mask per object)."""
    if oid.numel() == 0:
        return []
    order = torch.argsort(oid, stable=True)
    ids, counts = torch.unique_consecutive(oid[order], return_counts=True)
    return list(zip(ids.tolist(), torch.split(order, counts.tolist()), strict=True))


def _eval(brdfs: list[BRDF], o: int, wi, wo, tex: torch.Tensor | None, rows) -> torch.Tensor:
    """f of object ``o``'s BRDF at its rows ``rows`` of a batch, scaled by the base-colour texels
    ``tex`` (rows of the whole batch) where object ``o`` is textured (``brdfs.textured``)."""
    if tex is None or o not in getattr(brdfs, "textured", ()):
        return brdfs[o].eval_local(wi, wo)
    return textured_eval_local(brdfs[o], wi, wo, tex[rows])


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


def sample_light(scene: Scene, light, pos, ng, ns, gen, u: torch.Tensor | None = None):
    """Next-event estimation towards ``light`` from every vertex; ``u`` (n, 3) float64: the
    uniforms of an :class:`~torch_brdf.scene.lights.AreaLight` (e.g. stratified), instead of
    drawing them from ``gen``.

    Returns:
        (ls, cos, candidates, visible): the :class:`~torch_brdf.scene.lights.LightSample`, the
        cosine at the shading normal (n,), how many shadow rays were cast, and the rows (long)
        that see the light.
    """
    fast = area_light_sample(light, pos, ng, ns, gen, u)  # the same bits in the compiled kernel
    if fast is not None:
        ls, cos, ok = fast
    else:
        ls = light.sample(pos, gen) if u is None else light.sample(pos, gen, u=u)
        cos = (ls.direction * ns).sum(-1)
        ok = (cos > 0) & ((ls.direction * ng).sum(-1) > 0) & (ls.pdf > 0)
    k = torch.nonzero(ok).squeeze(1)
    if k.numel() == 0:
        return ls, cos, 0, k
    return ls, cos, k.numel(), k[scene.visible(pos[k], ng[k], ls.direction[k], ls.distance[k])]


def power_heuristic(p_a: torch.Tensor, p_b: torch.Tensor) -> torch.Tensor:
    r"""Veach's power heuristic (beta = 2) for one sample of each of two strategies:
    :math:`w_a = p_a^2 / (p_a^2 + p_b^2)` (Veach 1997, eq. 9.13), computed in float64.

    Args:
        p_a: (n,) solid-angle pdf of the strategy that drew the sample.
        p_b: (n,) pdf of the other strategy for the same direction.
    Returns:
        (n,) float32 weights in [0, 1]; 1 where ``p_b == 0`` or ``p_a`` is infinite (a delta
        strategy), 0 where ``p_a == 0``.
    """
    a, b = p_a.double() ** 2, p_b.double() ** 2
    w = torch.where(a > 0, a / (a + b).clamp_min(1e-300), 0.0)
    return torch.where(torch.isinf(a), 1.0, w).to(torch.float32)


def _mis_lights(scene: Scene) -> set[int]:
    """``id()`` of the lights a BRDF-sampled ray can also find: the environment map (rays that
    miss) and area lights bound to an object (rays that hit it). Delta lights and unbound area
    lights are reached by next-event estimation alone, so their samples keep weight 1."""
    found = list(scene.area_lights.values())
    if scene.environment is not None:
        found.append(scene.environment)
    return {id(li) for li in found}


def emission_and_light_pdf(scene: Scene, origins, directions, hits) -> tuple[torch.Tensor, torch.Tensor]:
    r"""What BRDF-sampled rays find on the lights, and how likely next-event estimation was to
    pick the same direction (the other strategy of MIS).

    Args:
        origins: (n, 3) path vertices the rays leave from.
        directions: (n, 3) unit ray directions.
        hits: the rays' :class:`~torch_brdf.scene.raytrace.Hits`.
    Returns:
        (radiance (n, 3), light pdf (n,)): the environment where a ray escapes, an area light's
        front-side emission where it hits that light's object (solid-angle pdf
        :math:`r^2 / (|\cos\theta_l| A)` of :meth:`AreaLight.sample`); zeros elsewhere.
    """
    le = emission_seen(scene, directions, hits)
    pdf = torch.zeros(directions.shape[0])
    env = scene.environment
    miss = ~hits.hit
    if env is not None and bool(miss.any()):
        pdf[miss] = env.pdf(directions[miss]).float()
    for oid, light in scene.area_lights.items():
        on = torch.nonzero(hits.object_id == oid).squeeze(1)
        if on.numel():
            r2 = ((hits.position[on] - origins[on]) ** 2).sum(-1)
            cos_l = (directions[on] * hits.geometric_normal[on]).sum(-1).abs().clamp_min(1e-12)
            pdf[on] = r2 / (cos_l * light.total_area)
    return le, pdf


@torch.no_grad()
def _radiance(
    scene: Scene, origins, directions, brdfs: list[BRDF], max_bounces: int, gen, mis: bool = False
) -> torch.Tensor:
    """One path per ray: (P, 3) radiance estimates (float32); ``mis`` as :func:`path_trace`."""
    hits = scene.trace(origins, directions)
    out = emission_seen(scene, directions, hits)
    mis_lights = _mis_lights(scene) if mis else set()
    # the active paths, compacted: pixel index, arriving direction, surface, throughput
    idx = torch.nonzero(hits.hit).squeeze(1)
    d_in, pos = directions[idx], hits.position[idx]
    ng, ns, oid = hits.geometric_normal[idx], hits.normal[idx], hits.object_id[idx]
    tex = texture_at_hits(scene, "base_color", oid, hits.prim_id[idx], hits.barycentrics[idx])
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
            tex_k = None if tex is None else tex[k]
            f = _grouped(oid[k], lambda o, m, wi_k=wi_k, wo_k=wo_k, t=tex_k: _eval(brdfs, o, wi_k[m], wo_k[m], t, m), 3)
            contrib = beta[k] * f * ls.weight[k] * cos[k, None]
            if id(light) in mis_lights:  # the BRDF sample below may find this light too
                pdf_f = _grouped(
                    oid[k], lambda o, m, wi_k=wi_k, wo_k=wo_k: brdfs[o].pdf_local(wi_k[m], wo_k[m])[:, None], 1
                )
                contrib = contrib * power_heuristic(ls.pdf[k], pdf_f[:, 0])[:, None]
            out.index_add_(0, idx[k], contrib)
        last = bounce == max_bounces - 1
        if last and not mis_lights:
            break
        # continue the path by the BRDF's own importance sampling: beta *= f cos / pdf
        u = torch.rand(idx.numel(), 2, generator=gen)

        def step(o, m, u=u, wo=wo, tex=tex):
            wi_l, pdf = brdfs[o].sample_local(wo[m], u[m])
            f = _eval(brdfs, o, wi_l, wo[m], tex, m)
            w = torch.where(pdf > 0, wi_l[:, 2].clamp_min(0) / pdf.clamp_min(1e-30), 0.0)
            return torch.cat((wi_l, f * w[:, None], pdf[:, None]), -1)

        res = _grouped(oid, step, 7)
        wi, beta = frame.to_world(res[:, :3]), beta * res[:, 3:6]
        ok = torch.nonzero(((wi * ng).sum(-1) > 0) & (beta.amax(-1) > 0)).squeeze(1)
        sub = scene.trace(scene.spawn(pos[ok], ng[ok], wi[ok]), wi[ok])
        if mis_lights:  # emission the BRDF sample finds, weighted against next-event estimation
            le, pdf_l = emission_and_light_pdf(scene, pos[ok], wi[ok], sub)
            w = power_heuristic(res[ok, 6], pdf_l)
            out.index_add_(0, idx[ok], beta[ok] * le * w[:, None])
        if last:
            break
        keep = ok[sub.hit]
        idx, beta, d_in = idx[keep], beta[keep], wi[keep]
        pos, ng, ns, oid = (x[sub.hit] for x in (sub.position, sub.geometric_normal, sub.normal, sub.object_id))
        if tex is not None:
            tex = texture_at_hits(scene, "base_color", oid, sub.prim_id[sub.hit], sub.barycentrics[sub.hit])
    return out


@dataclass(frozen=True)
class PathTraceSettings:
    """The settings of :func:`path_trace` (frozen; :meth:`key` feeds the checkpoint's key).

    Args:
        spp: samples (paths) per pixel, each through a jittered point of the pixel.
        max_bounces: surface vertices per path; 1 is direct lighting only.
        chunk: rays traced together (memory vs. overhead; part of the random stream: the rays
            of a chunk draw their numbers together).
        mis: combine next-event estimation with BRDF sampling by multiple importance
            sampling (power heuristic; default on): every vertex also counts the light its
            BRDF-sampled ray finds (environment, emitter), both weighted, so sharp lobes
            reflecting large bright lights converge without fireflies. ``False`` is plain
            next-event estimation. Both are unbiased; only the noise differs.
    Raises:
        ValueRangeError: a count that is not a positive integer (the exception's ``setting``
            names the field).
    """

    spp: int = 16
    max_bounces: int = 4
    chunk: int = 1 << 16
    mis: bool = True

    def __post_init__(self):
        check_fields(
            self,
            {
                "spp": lambda v: check_count(v, "spp"),
                "max_bounces": lambda v: check_count(v, "max_bounces"),
                "chunk": lambda v: check_count(v, "chunk"),
                "mis": lambda v: check_bool(v, "mis"),
            },
        )

    def key(self) -> dict:
        """Every field (what the checkpoint's key covers besides the scene and the seed)."""
        return asdict(self)


def path_trace(
    scene: Scene,
    settings: PathTraceSettings | None = None,
    *,
    seed: int = 0,
    checkpoint: str | Path | None = None,
    checkpoint_every: int = 4,
    progress: bool | None = None,
    **old,
) -> torch.Tensor:
    """Render ``scene`` from its camera: (H, W, 3) float32 linear radiance.

    Args:
        scene: the scene (any BRDFs of the library; see the module docstring).
        settings: :class:`PathTraceSettings` (spp, bounces, chunk, MIS; None: its defaults).
        seed: the render is a deterministic function of (scene, settings, seed).
        checkpoint: file to save progress to every ``checkpoint_every`` passes and to
            resume from when it exists with matching settings and scene content (a
            :class:`~torch_brdf.records.cache.Checkpoint`: versioned, checksummed, atomic); a
            checkpoint of other settings or an edited scene is ignored and overwritten, a
            corrupt one is moved aside to ``<name>.corrupt`` with a warning and the render
            starts afresh.
        checkpoint_every: passes between checkpoint saves.
        progress: show a tqdm bar over sample passes.
    Raises:
        ValueRangeError: a ``checkpoint_every`` that is not a positive integer, or a seed
            outside ``[0, 2**63)``.
        TypeError: settings given one by one (``spp=``, ``max_bounces=``...).
    """
    if old or not isinstance(settings, (PathTraceSettings, type(None))):
        given = sorted(old) + ([] if isinstance(settings, (PathTraceSettings, type(None))) else [repr(settings)])
        raise TypeError(
            "path_trace(scene, settings, *, seed, checkpoint, progress, ...) takes its settings from a "
            f"PathTraceSettings, e.g. path_trace(scene, PathTraceSettings(spp=16, max_bounces=4), seed=0); "
            f"got {', '.join(given)}"
        )
    s = PathTraceSettings() if settings is None else settings
    seed, checkpoint_every = check_seed(seed), check_count(checkpoint_every, "checkpoint_every")
    spp, max_bounces, chunk, mis = s.spp, s.max_bounces, s.chunk, s.mis
    cam = scene.camera
    h, w = cam.height, cam.width
    brdfs = material_brdfs(scene)
    settings = {**s.key(), "scene": scene.name, "width": w, "height": h, "seed": seed}
    total = torch.zeros(h * w, 3, dtype=torch.float64)
    start = 0
    key = settings_key(settings, scene)  # the scene's content too: an edited scene starts fresh
    schema = CacheSchema(
        arrays={"sum": ArraySpec("float64", ("P", 3), low=0.0)},  # radiance sums are >= 0
        meta={"passes_done": MetaSpec(int, 1, spp), "settings": MetaSpec(dict, required=False)},
    )
    ckpt = None
    if checkpoint is not None:
        ckpt = Checkpoint(checkpoint, CHECKPOINT_KIND, key, "recompute", schema, {"P": h * w})
    saved = None if ckpt is None else ckpt.load()
    if saved is not None:
        total = torch.from_numpy(saved[0]["sum"])
        start = int(saved[1]["passes_done"])
    bar = tqdm(
        range(start, spp),
        total=spp,
        initial=start,
        desc=f"path trace {scene.name}",
        disable=not progress_default(progress),
    )
    for s in bar:
        gen = seeded_generator(seed, s)
        o, d = cam.generate_rays(jitter=True, generator=gen)
        for a in range(0, h * w, chunk):
            sl = slice(a, min(a + chunk, h * w))
            total[sl] += _radiance(scene, o[sl], d[sl], brdfs, max_bounces, gen, mis).double()
        done = s + 1
        if ckpt is not None and (done % checkpoint_every == 0 or done == spp):
            ckpt.save({"sum": total.numpy()}, meta={"settings": settings, "passes_done": done})
    return (total / spp).to(torch.float32).reshape(h, w, 3)


def reference_path_trace(
    scene: Scene, spp: int = 256, max_bounces: int = 4, seed: int = 0, mis: bool = True, **kwargs
) -> torch.Tensor:
    """The unbiased reference of the multibounce editor: :func:`path_trace` with every
    object's full BRDF, BRDF importance sampling and next-event estimation combined by
    multiple importance sampling (``mis``, default on; see the module docstring), to
    measure what a BRDF series, diffuse equivalents and band projections cost.

    Args:
        scene: as :func:`path_trace`; ``max_bounces`` counts surface
            vertices, so it matches a series of that length (Mitsuba's ``max_depth`` is
            ``max_bounces + 1``).
        spp: as ``scene``.
        max_bounces: as ``scene``.
        seed: as ``scene``.
        mis: power-heuristic MIS of light and BRDF sampling (default ``True``); ``False``
            is next-event estimation alone (same expectation, more fireflies on glossy
            surfaces under large bright lights).
        kwargs: ``chunk`` (see :class:`PathTraceSettings`), ``checkpoint``,
            ``checkpoint_every``, ``progress``.
    Returns:
        (H, W, 3) float32 linear radiance.
    """
    chunk = {"chunk": kwargs.pop("chunk")} if "chunk" in kwargs else {}
    settings = PathTraceSettings(spp=spp, max_bounces=max_bounces, mis=mis, **chunk)
    return path_trace(scene, settings, seed=seed, **kwargs)
