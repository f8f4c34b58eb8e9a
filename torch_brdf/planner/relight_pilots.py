r"""The relighting planner's pilots: cubemap resolution, graded-visibility bits and
the BRDF-sampling rule for a PSNR target, measured on a sample of the seen vertices.

The decision (the error metric, the cost model, the choice) is
:mod:`torch_brdf.planner.relight`'s; the pilots shade with
:class:`~torch_brdf.render.triple.TripleProductRenderer` (the render layer sits below the
planner). ``plan_relighting(scene, psnr=40)`` returns a printed
:class:`~torch_brdf.planner.table.Plan`; :func:`planned_renderer` carries it out.

Pilots, all on the vertices the camera sees:

1. a cheap full-view pass (the smallest candidate resolution, binary maps, the default rule
   and one sample per block) finds the ``brightest`` error-prone vertices (see below);
2. those plus ``pilot_vertices`` of the other seen vertices drawn at random (seeded): for each candidate
   resolution and supersampling, the visibility of those vertices is cast
   (:func:`~torch_brdf.transport.visibility.visibility_fraction`) and encoded at each
   candidate bit depth; each (resolution, visibility) is shaded with every candidate rule;
3. the reference: the dense standard-basis product at ``reference`` (resolution, supersample,
   bits), by default the largest candidate resolution with 4 x 4 rays per texel and 8 bits.

The errors are heavy-tailed: a rule that misses a highlight errs on the few vertices under
it, binary maps on the few under a sun's shadow edge. So the sample is stratified: the
``brightest`` error-prone vertices of the cheap pass (a third the brightest, which also give
the peak; a third those where one sample per block changes the cheap pass most; a third those
with most lighting in partially visible blocks) are shaded all, the rest by ``pilot_vertices``
drawn at random, and the mean squared error is the strata's weighted sum (each sampled vertex
standing for (seen - brightest) / pilot_vertices of the rest).

Costs are work counts times one rate each: precompute seconds are the rays per vertex (half the
cubemap's texels times k^2, plus one per texel for the horizon test and encoding) times the
scene's vertices times the median seconds per ray of the pilots' casts; frame seconds are
:func:`frame_units` of the rule's pilot frame (per vertex) times the seen vertices times the
median seconds per unit of all pilot frames. So one slow call cannot reorder the candidates;
the two rates (and so the trade between precompute and frames) still follow the machine and
its load.
"""

from __future__ import annotations

import functools
import math
import statistics
import time
from collections.abc import Sequence

import torch

from ..errors import ValueRangeError
from ..records.visibility import VertexVisibility, scene_vertices
from ..records.visibility_codec import BlockVisibility
from ..render.triple import FixedRule, GenericRule, PhongRule, SamplingRule, TripleProductRenderer, View
from ..scene.camera import Camera
from ..scene.envmap import EnvironmentMap
from ..scene.gbuffer import GBuffer, trace_gbuffer
from ..scene.scene import Scene
from ..sphere.cubemap import CubemapBlocks
from ..transport.visibility import BITS, VisibilitySettings, precompute_visibility, visibility_fraction
from .relight import RelightPilot, error_from_psnr, plan_from_relight_pilots
from .table import Plan

__all__ = [
    "DEFAULT_RULE",
    "RULES",
    "frame_units",
    "make_rule",
    "plan_relighting",
    "planned_renderer",
    "shade_vertices",
    "visibility_settings",
]

#: the candidate BRDF-sampling rules: ``kind:factor``; fixed:l = l x l samples everywhere,
#: appendix-a:f = :class:`PhongRule` with its angles x f (other models: :class:`GenericRule`),
#: generic:f = :class:`GenericRule` with its thresholds x f (larger: cheaper, less exact)
RULES = (
    "fixed:1",
    "fixed:2",
    "fixed:4",
    "appendix-a:0.5",
    "appendix-a:1",
    "appendix-a:2",
    "generic:10",
    "generic:1",
    "generic:0.1",
)
#: the renderer's default rule (what ``TripleProductRenderer(rule=None)`` uses)
DEFAULT_RULE = "appendix-a:1"
#: candidate (supersample, bits): binary maps, then graded ones
VISIBILITY = ((1, 0), (2, 2), (2, 6), (4, 6), (4, 8))


def make_rule(name: str) -> SamplingRule:
    """The sampling rule named ``kind:factor`` (see :data:`RULES`)."""
    kind, _, f = name.partition(":")
    try:
        x = float(f) if f else 1.0
    except ValueError:
        x = math.nan
    if not (math.isfinite(x) and x > 0):
        raise ValueRangeError(f"rule {name!r}: the factor after ':' must be a positive number")
    if kind == "fixed":
        return FixedRule(int(x))
    if kind == "appendix-a":
        return PhongRule(angles=(math.pi / 8 * x, math.pi / 4 * x), fallback=GenericRule())
    if kind == "generic":
        return GenericRule(1e-3 * x, 1e-2 * x, 1e-3 * x)
    raise ValueRangeError(f"rule kind must be fixed, appendix-a or generic; got {name!r}")


def shade_vertices(
    scene: Scene,
    ids: torch.Tensor,
    eye: torch.Tensor,
    resolution: int,
    supersample: int,
    bits: int,
    rules: Sequence[str | None],
    lighting_samples: int = 4,
    fraction: torch.Tensor | None = None,
    renderers: dict | None = None,
    envmap: EnvironmentMap | None = None,
) -> tuple[dict[str | None, torch.Tensor], dict]:
    """Shade some vertices with visibility cast for them alone (no record of the whole scene).

    Args:
        scene: the scene; ids: (m,) its vertex ids; eye: (3,) the viewpoint.
        resolution: the visibility's cubemap resolution.
        supersample: the visibility's supersampling.
        bits: the visibility's bits.
        rules: rule names (:func:`make_rule`); None for the dense standard-basis product.
        lighting_samples: as :class:`~torch_brdf.render.triple.TripleProductRenderer`.
        fraction: (m, NB, S^2) the undecoded visibility if already cast at (resolution, supersample).
        renderers: a cache of renderers per resolution (their lighting projection), filled here.
        envmap: the lighting (default the scene's).
    Returns:
        ({rule: (m, C) radiance}, {"vis_s": seconds to cast + encode, "shade_s": {rule: seconds},
        "bytes_per_vertex": float, "fraction": the undecoded visibility}).
    """
    verts = scene_vertices(scene)
    geom = CubemapBlocks(resolution, 16)
    t0 = time.perf_counter()
    if fraction is None:
        fraction = visibility_fraction(scene, geom, verts.positions[ids], verts.normals[ids], supersample)
    blocks = BlockVisibility.encode(fraction > 0.5 if supersample == 1 else fraction, bits=bits)
    vis_s = time.perf_counter() - t0
    renderers = {} if renderers is None else renderers
    if resolution not in renderers:
        # a record of the scene's vertices whose maps cover only ``ids``: the renderer reads the
        # vertices and layout from it; the maps are given through the view below
        record = VertexVisibility(geom, verts, blocks, supersample, bits)
        renderers[resolution] = TripleProductRenderer(scene, record, envmap, lighting_samples=lighting_samples)
    r = renderers[resolution]
    cam = scene.camera
    view = View(GBuffer.of_vertices(ids, eye, cam.height, cam.width), torch.zeros(0, 3), blocks)
    out, secs, work = {}, {}, {}
    for name in rules:
        t0 = time.perf_counter()
        if name is None:
            out[name] = r.shade_standard(view, progress=False)
        else:
            out[name], stats = r.shade(view, rule=make_rule(name), progress=False)
            work[name] = frame_units(stats)
        secs[name] = time.perf_counter() - t0
    info = {"vis_s": vis_s, "shade_s": secs, "units": work, "bytes_per_vertex": float(blocks.nbytes_per_vertex)}
    info["fraction"], info["blocks"] = fraction, blocks
    return out, info


def _error_prone(cheap: dict, blocks: BlockVisibility, r: TripleProductRenderer, count: int) -> torch.Tensor:
    """Rows of the cheap pass's vertices where candidates' errors concentrate: a third each (then
    the brightest to fill ``count``) of the brightest (highlights set the peak), those the one-
    sample rule changes most (the rule's error) and those with most lighting in partially
    visible blocks (shadow edges: the visibility's error)."""
    bright = cheap[DEFAULT_RULE].amax(-1)
    rule = (cheap[DEFAULT_RULE] - cheap["fixed:1"]).abs().amax(-1)
    energy = r.lighting.texels.sum(1).amax(-1).to(torch.float64)  # (NB,) lighting per block
    edge = (blocks.states == 2).to(torch.float64) @ energy
    chosen: dict[int, None] = {}  # ordered, no repeats
    third = -(-count // 3)
    for score, upto in ((bright, third), (rule, 2 * third), (edge, count), (bright, count)):
        for i in score.argsort(descending=True).tolist():
            if len(chosen) >= min(upto, count):
                break
            chosen.setdefault(i)
    return torch.tensor(list(chosen), dtype=torch.long)


def frame_units(stats) -> float:
    """A frame's work from its :class:`~torch_brdf.render.triple.FrameStats`, in BRDF-evaluation
    equivalents: evaluations + visibility entries read + 50 per pixel product (line 11: a
    256-texel expansion and contraction) + 4 per DCT dot product (lines 6 and 9)."""
    c = stats.cases
    return float(stats.brdf_evals + stats.visibility_entries + 50 * c["line11"] + 4 * (c["line6"] + c["line9"]))


def plan_relighting(
    scene: Scene,
    error: float | None = None,
    psnr: float | None = None,
    seconds: float | None = None,
    camera: Camera | None = None,
    envmap: EnvironmentMap | None = None,
    resolutions: Sequence[int] = (16, 32, 64),
    visibility: Sequence[tuple[int, int]] = VISIBILITY,
    rules: Sequence[str] = RULES,
    reference: tuple[int, int, int] | None = None,
    frames: int = 100,
    pilot_vertices: int = 256,
    brightest: int = 64,
    lighting_samples: int = 4,
    generator: torch.Generator | None = None,
) -> Plan:
    """Plan cubemap resolution, visibility (supersample, bits) and sampling rule for a PSNR or
    RMSE / peak target (see the module and :mod:`torch_brdf.planner.relight`).

    Args:
        scene: a scene with an environment map (its materials and camera as rendered).
        error: budget on RMSE / peak; psnr: the same budget in dB (give one, or ``seconds``).
        seconds: budget on precompute + ``frames`` frames.
        camera: the view (default the scene's); envmap: the lighting (default the scene's).
        resolutions: candidate cubemap resolutions (multiples of 16).
        visibility: candidate (supersample, bits): (1, 0) binary; k > 1 with bits in (2, 6, 8).
        rules: candidate rule names (:data:`RULES`).
        reference: (resolution, supersample, bits) of the converged reference (default
            (max(resolutions), 4, 8)).
        frames: frames a session is priced for.
        pilot_vertices: seen vertices the pilots shade at random, besides the brightest.
        brightest: error-prone vertices of the cheap pass, all shaded (a stratum of their own).
        lighting_samples: as the renderer's.
        generator: seeds the vertex sample.
    Returns:
        :class:`~torch_brdf.planner.table.Plan`; ``settings``: ``cubemap``, ``supersample``,
        ``bits``, ``rule``.
    """
    if psnr is not None:
        if error is not None:
            raise ValueRangeError("give error or psnr, not both")
        if not math.isfinite(float(psnr)):
            raise ValueRangeError(f"psnr must be finite; got {psnr}")
        error = error_from_psnr(psnr)
    for k, b in visibility:
        if b not in BITS or (k > 1) != (b > 0) or k < 1:
            raise ValueRangeError(f"visibility (supersample, bits) must be (1, 0) or (k > 1, 2|6|8); got {(k, b)}")
    if not rules or not resolutions:
        raise ValueRangeError("need at least one candidate rule and resolution")
    for name in rules:
        make_rule(name)
    res_ref, k_ref, b_ref = reference if reference is not None else (max(resolutions), 4, 8)
    g = generator if generator is not None else torch.Generator().manual_seed(0)
    t_start = time.perf_counter()
    gb = trace_gbuffer(scene, camera)
    seen, eye = gb.vertex_ids, gb.eye
    total = len(scene_vertices(scene))
    # 1. the cheap full-view pass: the vertices where the error can concentrate
    renderers: dict = {}
    shade = functools.partial(
        shade_vertices, scene, lighting_samples=lighting_samples, renderers=renderers, envmap=envmap
    )
    cheap, info = shade(seen, eye, min(resolutions), 1, 0, [DEFAULT_RULE, "fixed:1"])
    top = _error_prone(cheap, info["blocks"], renderers[min(resolutions)], min(brightest, len(seen)))
    rest = torch.ones(len(seen), dtype=torch.bool)
    rest[top] = False
    rest = rest.nonzero().squeeze(-1)
    rest = rest[torch.randperm(len(rest), generator=g)[:pilot_vertices]]
    ids = torch.cat((seen[top], seen[rest]))
    # stratified mean of the squared error: the error-prone stratum whole, the rest by its sample
    scale = (len(seen) - len(top)) / max(len(rest), 1)
    weight = torch.cat((torch.ones(len(top)), torch.full((len(rest),), scale)))
    weight = (weight / len(seen)).to(torch.float64)[:, None]
    # 3. the reference
    ref, _ = shade(ids, eye, res_ref, k_ref, b_ref, [None])
    ref = ref[None].to(torch.float64)
    peak = float(ref.max())
    # 2. every candidate; the costs are work counts (rays, frame units) times one rate each, the
    # median of the pilots' seconds per unit, so that timer noise scales the printed seconds
    # but never reorders the candidates
    measured, casts, shades = [], [], []
    for R in resolutions:
        T = CubemapBlocks(R, 16).texel_count
        for k in sorted({k for k, _ in visibility}):
            fraction = None
            for kk, b in visibility:
                if kk != k:
                    continue
                rad, info = shade(ids, eye, R, k, b, rules, fraction=fraction)
                rays = T * (k * k / 2 + 1)  # per vertex: half the sphere is above the horizon, + encoding
                if fraction is None:  # the rays are cast once per (R, k)
                    casts.append(info["vis_s"] / len(ids) / rays)
                fraction = info["fraction"]
                for name in rules:
                    sq = float((weight * (rad[name].to(torch.float64) - ref) ** 2).sum()) / ref.shape[1]
                    units = info["units"][name] / len(ids)
                    shades.append(info["shade_s"][name] / len(ids) / units)
                    measured.append((R, k, b, name, sq, rays, units, info["bytes_per_vertex"]))
    ray_rate, unit_rate = statistics.median(casts), statistics.median(shades)
    pilots = [
        RelightPilot(R, k, b, name, sq, ray_rate * rays * total, unit_rate * units * len(seen), nbytes)
        for R, k, b, name, sq, rays, units, nbytes in measured
    ]
    return plan_from_relight_pilots(pilots, peak, error, seconds, frames, time.perf_counter() - t_start)


def planned_renderer(
    scene: Scene, plan: Plan, envmap: EnvironmentMap | None = None, **visibility_kwargs
) -> TripleProductRenderer:
    """Carry out a relighting plan: the visibility at its settings
    (:func:`~torch_brdf.transport.visibility.precompute_visibility`, ``visibility_kwargs`` passed
    on, e.g. ``checkpoint=``) and a renderer with its rule (lit by ``envmap``, default the scene's)."""
    vis = precompute_visibility(scene, visibility_settings(plan), **visibility_kwargs)
    return TripleProductRenderer(scene, vis, envmap, rule=make_rule(plan.settings["rule"]))


def visibility_settings(plan: Plan) -> VisibilitySettings:
    """The :class:`~torch_brdf.transport.visibility.VisibilitySettings` of a relighting plan
    (its cubemap, supersampling and bits)."""
    s = plan.settings
    return VisibilitySettings(resolution=s["cubemap"], block=16, supersample=s["supersample"], bits=s["bits"])
