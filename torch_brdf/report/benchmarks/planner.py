"""The error-budget planners against fixed defaults: GI editing, inverse design, relighting,
the BRDF manifold.

    python benchmarks/planner.py [--quick] [--error 0.1] [--resolution 32] [--capabilities gi,inverse,relight,manifold]
        [--psnr 50] [--families 7,11,13] [--orders 8] [--pool 80] [--heldout 240] [--statistic trimmed]
        [--scores FILE]

GI editing, on two scenes: the glossy Cornell box (Blinn-Phong n = 100 back wall, area light)
and ``teatray`` (Blinn-Phong n = 200 tray, Lambertian teapot, procedural sky with a sun). The
reference is the converged polynomial model of the same scene: 6 bounces, twice the planned
bands (at least 64) on glossy objects, 1 on Lambertian ones, ``reference_spp`` paths per pixel
in two independent halves; the reference's own noise (``reference_noise``, from the halves'
difference) is taken out of every achieved error in quadrature. Errors are relative RMSE over
the pixels that do not see an emitter (``emitter_mask``). Per scene (``scenes``):

* ``plan``: the planner's printed plan; ``planned``: its series, spp, predicted error,
  achieved error, ``reached`` (achieved <= requested), precompute seconds and rays;
  ``plan_seconds``: what planning cost (band projections and the two pilots).
  An adaptive plan (the default) adds ``spp_min``, ``spp_max`` and ``spp_levels`` of its map;
  ``planned_uniform``: the same planner with ``adaptive=False`` (one spp), carried out alike.
* ``prediction_ratio``: max(achieved / predicted, predicted / achieved) (goal <= 1.5).
* ``defaults``: every fixed default series -- the CLI's "64,1,1,1" and the seed's teatray
  series "128,1,1,1", "16,8,1,1", "128,8,1", "64,16" -- at spp 8, 11, 16, 23, 32, ... (steps of
  sqrt 2) until a power of two reaches the error: achieved error, seconds, rays.
* ``planner_cost_ratio``: precompute seconds of the planned settings over those of the default
  (series, spp a power of two from 8) of fewest rays that reaches the error (goal <= 0.7);
  ``planner_cost_ratio_rays``: the same in rays cast (load-independent);
  ``planner_cost_ratio_fine_spp`` / ``_rays_fine_spp``: against the defaults on the sqrt-2 spp
  grid (a stronger baseline than a user's powers of two); ``planner_cost_ratio_with_planning``;
  ``retimed``, ``planner_cost_ratio_retimed`` / ``_retimed_fine_spp``: the planned run and the
  best defaults timed again, interleaved, the least of ``--repeats`` (3) each.

Inverse design (``inverse``): the teapot of ``teatray`` (64x48 solving frame; ``--quick``
40x30), one brightening stroke, error 0.05 (quick 0.06) on the design image; achieved = RMS
over three light-sample seeds against a dense 4096-sample (quick 2048), 147-lobe design;
``default`` = the design defaults (1024 samples, 147 lobes, dense) measured the same way.

Relighting (``relight``): ``bunny_relight`` with the procedural bunny (160x120, plane 16 quads
a side; ``--quick`` 32x24, 4), PSNR 50 dB (quick 45) of the seen vertices' radiance (peak = the
reference's maximum) against the converged reference (dense product at the largest candidate
cubemap, 64 (quick 32), 4x4 rays per texel, 8 bits); ``planned`` and every fixed default
(``RELIGHT_DEFAULTS``: 64x64x6 binary with the Appendix A rule -- the CLI's -- or the generic
rule, and both at 32x32x6) carried out on the whole scene: achieved error and PSNR, precompute
and frame seconds, ``cost_s`` = precompute + 100 frames; ``planner_cost_ratio`` over the
cheapest default that reaches the PSNR, ``planner_cost_ratio_vs_cli_default``.

Manifold (``manifold``): q and the training materials for a held-out log-RMSE of 0.01 -- its
``--statistic`` over the materials, by default the interquartile mean of the log errors (see
``torch_brdf/planner/manifold.py``) -- on the analytic family (9 x 9 x 18 grid: materials 80 to
80 + ``--pool`` - 1 the pool (default 80: 80-159), the rest ``--heldout`` (240) held out: the first 80 and
160 more of the same draw, never in the pool; family seeds 7, 11 and 13, ``--quick`` 7 only,
or ``--families``), for pool orders 0-7 (quick 0-1, or ``--orders N``): per plan (``orders``)
its q, n, predicted error with its 90% interval and achieved error (the statistic over the
held-out materials of the plan carried out; ``achieved_first_80``: over the first 80, the former
set; ``achieved_mean``: the mean over the held-out materials, the manifold benchmark's
statistic) and their ratio, CPU seconds of the fit + placements and of the planning
(``plan_cpu_s``), ``achieved_interval`` (the achieved statistic's own 90% bootstrap interval:
how far another set of materials would move it); ``planned`` is the first; ``defaults``: the
seed's q = 2 and 5 trained on the whole pool, measured alike; ``prediction_ratio`` (worst over
the plans), ``achieved_over_predicted`` (range), ``within_1_5`` (share of plans within 1.5x both
ways), ``planner_cost_ratio`` (worst over the plans, against the cheapest default that reaches
the error); ``statistics``: every candidate statistic on the plans' own per-material scores
(bootstrap spread and the ratio each plan's model would have had; no fits). ``--scores FILE``
saves the per-material scores.

Top level (one JSON object, the last line): ``prediction_ratio`` (worst over scenes and
capabilities), ``planner_cost_ratio`` / ``planner_cost_ratio_rays`` and the same against the
sqrt-2 grid, ``planner_cost_ratio_fine_spp`` / ``planner_cost_ratio_rays_fine_spp`` (worst over the GI scenes),
``load`` / ``load_end`` (1-min load average at start and end).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import time

import torch

from torch_brdf.inverse import (
    Brush,
    CutOptions,
    LightSamples,
    Stroke,
    cosine_visibility,
    object_pixels,
    paint,
    transfer_functions,
)
from torch_brdf.io import save_arrays
from torch_brdf.manifold import analytic_observations, heldout_reconstruction
from torch_brdf.manifold.data import MERLGrid
from torch_brdf.metrics import relative_rmse
from torch_brdf.planner.gi import plan_polynomial, precompute_planned, with_fixed
from torch_brdf.planner.inverse import _basis, design_image, plan_inverse
from torch_brdf.planner.manifold import STATISTICS, bootstrap_interval, plan_manifold
from torch_brdf.planner.relight_pilots import DEFAULT_RULE, make_rule, plan_relighting, shade_vertices
from torch_brdf.records.polynomial import Series
from torch_brdf.render.polynomial import PolynomialRenderer, emitter_mask
from torch_brdf.render.triple import TripleProductRenderer
from torch_brdf.scene.builtin import bunny_relight, cornell_box_glossy, teatray
from torch_brdf.scene.gbuffer import trace_gbuffer
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial
from torch_brdf.transport.visibility import VisibilitySettings, precompute_visibility


def _rays(T) -> int:
    return int(sum(T.meta["rays"].values()))


#: the fixed default series: the CLI's and the seed's teatray series (Ben-Artzi et al. 2008)
DEFAULT_SERIES = ("64,1,1,1", "128,1,1,1", "16,8,1,1", "128,8,1", "64,16")


def _spp_grid(max_spp: int, fine: bool) -> list[int]:
    """8, 16, 32, ... (``fine``: 8, 11, 16, 23, 32, 45, ..., steps of sqrt 2) up to ``max_spp``."""
    out, k = [], 0
    while round(8 * 2 ** (k / (2 if fine else 1))) <= max_spp:
        out.append(round(8 * 2 ** (k / (2 if fine else 1))))
        k += 1
    return out


def run_scene(
    sc, error: float, ref_spp: int, max_spp: int, defaults: tuple[str, ...] = DEFAULT_SERIES, repeats: int = 3
) -> dict:
    """Plan ``sc`` for ``error``, carry the plan out, and find the cheapest default reaching it."""
    mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
    out: dict = {"scene": sc.name, "resolution": sc.camera.width, "error": error, "reference_spp": ref_spp}
    t0 = time.perf_counter()
    plan = plan_polynomial(sc, error=error, seed=0)
    out["plan_seconds"] = time.perf_counter() - t0
    print(plan, flush=True)
    # the reference: the converged polynomial model, 6 bounces, twice the planned bands (at
    # least 64) on every glossy object, 1 on Lambertian ones
    ref_bases = [
        None if b is None else dataclasses.replace(b, J=max(64, 2 * b.J), second=1) if b.J > 1 else b
        for b in plan.bases
    ]
    ref_series = Series((max([1] + [b.J for b in ref_bases if b is not None]),) + (1,) * 5)
    print(f"reference: {ref_series.key} at 2 x {ref_spp // 2} spp", flush=True)
    refs = [
        precompute_polynomial(
            with_fixed(sc, plan.fixed),
            PolynomialSettings(ref_series, spp=ref_spp // 2, bases=ref_bases),
            seed=99 + k,
            progress=False,
        )
        for k in range(2)
    ]
    halves = [PolynomialRenderer(R, mats, dtype=torch.float64)() for R in refs]
    ref = (halves[0] + halves[1]) / 2
    mask = emitter_mask(refs[0]) & emitter_mask(refs[1])
    # the reference's own noise (relative), from its two independent halves: Var(R1 - R2) =
    # 4 Var(mean); it is taken out of every achieved error in quadrature (planned and defaults)
    ref_noise = relative_rmse(halves[0], halves[1], mask) / 2
    out["reference_noise"] = ref_noise

    def achieved(T) -> float:
        e = relative_rmse(PolynomialRenderer(T, mats, dtype=torch.float64)(), ref, mask)
        return math.sqrt(max(0.0, e * e - ref_noise * ref_noise))

    t0 = time.perf_counter()
    T = precompute_planned(sc, plan=plan, seed=1, progress=False)
    secs = time.perf_counter() - t0
    a = achieved(T)
    out["plan"] = str(plan)
    out["planned"] = {
        "series": plan.series.key,
        "spp": round(plan.spp, 1),
        "predicted_error": plan.predicted_error,
        "achieved_error": a,
        "reached": a <= error,
        "seconds": secs,
        "predicted_seconds": plan.predicted_seconds,
        "rays": _rays(T),
    }
    if plan.spp_map is not None:
        out["planned"] |= {"spp_min": int(plan.spp_map.min()), "spp_max": int(plan.spp_map.max())}
        out["planned"]["spp_levels"] = int(torch.unique(plan.spp_map).numel())
    out["prediction_ratio"] = max(a / plan.predicted_error, plan.predicted_error / a)
    print(f"planned: achieved {a:.4f}, predicted {plan.predicted_error:.4f}, {secs:.2f} s, {_rays(T)} rays", flush=True)
    # the same planner with one spp for every pixel (what adaptive sampling buys)
    flat = plan_polynomial(sc, error=error, seed=0, adaptive=False)
    t0 = time.perf_counter()
    U = precompute_planned(sc, plan=flat, seed=1, progress=False)
    u_secs, u = time.perf_counter() - t0, achieved(U)
    out["planned_uniform"] = {
        "series": flat.series.key,
        "spp": flat.spp,
        "predicted_error": flat.predicted_error,
        "achieved_error": u,
        "reached": u <= error,
        "seconds": u_secs,
        "rays": _rays(U),
    }
    print(f"planned, one spp: {flat.spp} spp, achieved {u:.4f}, {u_secs:.2f} s, {_rays(U)} rays", flush=True)
    # every default series on the fine spp grid (steps of sqrt 2 from 8) until it reaches the
    # error; the doubling grid (8, 16, 32, ...) is its every other point
    rows_by_key = {}
    for key in defaults:
        rows = []
        for spp in _spp_grid(max_spp, fine=True):
            t0 = time.perf_counter()
            D = precompute_polynomial(sc, PolynomialSettings(key, spp=spp), seed=1, progress=False)
            s = time.perf_counter() - t0
            e = achieved(D)
            rows.append({"spp": spp, "achieved_error": e, "seconds": s, "rays": _rays(D)})
            print(f"default {key} spp {spp}: error {e:.4f}, {s:.2f} s", flush=True)
            if e <= error and spp in _spp_grid(max_spp, fine=False):
                break
        rows_by_key[key] = rows
    out["defaults"] = rows_by_key
    for name, fine in (("", False), ("_fine_spp", True)):
        grid = set(_spp_grid(max_spp, fine))
        hits = [
            {"series": k, **next(r for r in rows if r["spp"] in grid and r["achieved_error"] <= error)}
            for k, rows in rows_by_key.items()
            if any(r["spp"] in grid and r["achieved_error"] <= error for r in rows)
        ]
        if not hits:
            continue
        best = min(hits, key=lambda r: r["rays"])  # rays: the load-independent cost
        out[f"best_default{name}"] = best
        out[f"planner_cost_ratio{name}"] = secs / best["seconds"]
        out[f"planner_cost_ratio_rays{name}"] = _rays(T) / best["rays"]
    if "best_default" in out:
        out["planner_cost_ratio_with_planning"] = (secs + out["plan_seconds"]) / out["best_default"]["seconds"]
    if repeats > 1:
        out |= retime(sc, plan, out, repeats)
    return out


def retime(sc, plan, out: dict, repeats: int) -> dict:
    """Seconds of the planned run and of the best defaults (both spp grids) again, interleaved,
    ``repeats`` times each, the least of each: one timing per setting on a shared machine
    scatters by 2x and more. Returns ``retimed`` (seconds per setting) and
    ``planner_cost_ratio_retimed`` / ``planner_cost_ratio_retimed_fine_spp``."""
    runs = {"planned": lambda: precompute_planned(sc, plan=plan, seed=1, progress=False)}
    for name in ("", "_fine_spp"):
        b = out.get(f"best_default{name}")
        if b is not None:
            runs[f"best_default{name}"] = lambda b=b: precompute_polynomial(
                sc, PolynomialSettings(b["series"], spp=b["spp"]), seed=1, progress=False
            )
    best: dict[str, float] = {}
    for _ in range(repeats):
        for key, run in runs.items():
            t0 = time.perf_counter()
            run()
            best[key] = min(best.get(key, math.inf), time.perf_counter() - t0)
    res: dict = {"retimed": best}
    for name in ("", "_fine_spp"):
        if f"best_default{name}" in best:
            res[f"planner_cost_ratio_retimed{name}"] = best["planned"] / best[f"best_default{name}"]
    print(f"retimed (least of {repeats}): {best}", flush=True)
    return res


def _stroke_target(scene, px):
    """One brightening stroke across the teapot, painted on its diffuse-only image."""
    ls = LightSamples.from_environment(scene.environment, 64, torch.Generator().manual_seed(1))
    rec = transfer_functions(px, ls, cosine_visibility(scene, px, ls), f0=0.9)
    before = rec.pixel_values(torch.cat((torch.zeros(rec.values.shape[1] - 1, 3), torch.full((1, 3), 0.3))))
    w, h = px.width, px.height
    stroke = Stroke(
        torch.tensor([[0.3 * w, 0.55 * h], [0.7 * w, 0.55 * h]]), Brush(scale=1.8, diameter=h / 3, kappa=0.1)
    )
    return paint(rec, before, [stroke])


def run_inverse(error: float, size: tuple[int, int], ref_samples: int, seeds: int = 3) -> dict:
    """Plan the teapot design of ``teatray`` for ``error``; its achieved error (RMS over
    ``seeds`` light-sample seeds) and cost against the default settings (1024 samples, 147
    lobes, dense), both measured here (visibility + transfer + fit)."""
    scene = teatray(size)
    px = object_pixels(scene, "teapot")
    target = _stroke_target(scene, px)
    t0 = time.perf_counter()
    plan = plan_inverse(scene, px, scene.environment, target, error=error, generator=torch.Generator().manual_seed(0))
    plan_s = time.perf_counter() - t0
    print(plan, flush=True)

    def run(S: int, n: int, tol: float, seed: int) -> tuple[torch.Tensor, float]:
        t0 = time.perf_counter()
        ls = LightSamples.from_environment(scene.environment, S, torch.Generator().manual_seed(seed))
        vis = cosine_visibility(scene, px, ls)
        rec = transfer_functions(px, ls, vis, basis=_basis(n), f0=0.9, cuts=CutOptions(tol) if tol else None)
        return design_image(rec, target, n, 0.3), time.perf_counter() - t0

    ref, _ = run(ref_samples, 7, 0.0, 99)

    def measured(S: int, n: int, tol: float) -> tuple[float, float]:
        runs = [run(S, n, tol, 11 + k) for k in range(seeds)]
        errs = [float((d - ref).norm() / ref.norm()) for d, _ in runs]
        return math.sqrt(sum(e * e for e in errs) / seeds), min(t for _, t in runs)

    s = plan.settings
    a, secs = measured(s["light_samples"], s["hemicube"], s["cut_tolerance"])
    da, dsecs = measured(1024, 7, 0.0)
    out = {
        "scene": "teatray teapot",
        "pixels": px.count,
        "error": error,
        "reference_samples": ref_samples,
        "plan": str(plan),
        "plan_seconds": plan_s,
        "planned": {**s, "predicted_error": plan.predicted_error, "achieved_error": a, "seconds": secs},
        "prediction_ratio": max(a / plan.predicted_error, plan.predicted_error / a),
        "default": {"light_samples": 1024, "J": 147, "cut_tolerance": 0.0, "achieved_error": da, "seconds": dsecs},
    }
    if da <= error:
        out["planner_cost_ratio"] = secs / dsecs
    print(f"inverse: planned {a:.4f} ({secs:.2f} s), default {da:.4f} ({dsecs:.2f} s)", flush=True)
    return out


RELIGHT_DEFAULTS = (
    (64, 1, 0, DEFAULT_RULE),
    (64, 1, 0, "generic:1"),
    (32, 1, 0, DEFAULT_RULE),
    (32, 1, 0, "generic:1"),
)


def run_relight(psnr: float, quick: bool, frames: int = 100) -> dict:
    """Plan the relighting of ``bunny_relight`` (procedural bunny) for ``psnr``; carry out the
    plan and the fixed defaults (the CLI's 64x64x6 binary maps with the Appendix A rule, the
    generic rule, and both at 32x32x6) on the whole scene and score every seen vertex against
    the converged reference (dense product, largest cubemap, 4x4 rays, 8 bits). Cost =
    precompute + ``frames`` frames, measured (a frame: the fastest of three, after one)."""
    scene = (
        bunny_relight((32, 24), plane_quads=4, use_data=False)
        if quick
        else bunny_relight((160, 120), 16, use_data=False)
    )
    resolutions = (16, 32) if quick else (16, 32, 64)
    defaults = [d for d in RELIGHT_DEFAULTS if d[0] <= max(resolutions)]
    t0 = time.perf_counter()
    plan = plan_relighting(
        scene, psnr=psnr, resolutions=resolutions, frames=frames, generator=torch.Generator().manual_seed(0)
    )
    plan_s = time.perf_counter() - t0
    print(plan, flush=True)
    gb = trace_gbuffer(scene)
    t0 = time.perf_counter()
    ref = shade_vertices(scene, gb.vertex_ids, gb.eye, max(resolutions), 4, 8, [None])[0][None].double()
    ref_s = time.perf_counter() - t0
    peak = float(ref.max())

    def carry_out(R: int, k: int, b: int, rule: str) -> dict:
        t0 = time.perf_counter()
        vis = precompute_visibility(
            scene, VisibilitySettings(resolution=R, block=16, supersample=k, bits=b), progress=False
        )
        pre = time.perf_counter() - t0
        r = TripleProductRenderer(scene, vis, rule=make_rule(rule))
        view = r.view()
        rad, _ = r.shade(view, progress=False)
        frame = math.inf  # the fastest of three frames: the machine is shared
        for _ in range(3):
            t0 = time.perf_counter()
            r.shade(view, progress=False)
            frame = min(frame, time.perf_counter() - t0)
        e = float(((rad.double() - ref) ** 2).mean().sqrt()) / peak
        out = {"cubemap": R, "supersample": k, "bits": b, "rule": rule, "achieved_error": e}
        out.update(psnr=-20 * math.log10(e), precompute_s=pre, frame_s=frame, cost_s=pre + frames * frame)
        out["bytes_per_vertex"] = vis.bytes_per_vertex
        print(f"relight {R},{k},{b},{rule}: {out['psnr']:.2f} dB, {pre:.2f} s + {frame:.3f} s/frame", flush=True)
        return out

    s = plan.settings
    planned = carry_out(s["cubemap"], s["supersample"], s["bits"], s["rule"])
    planned["predicted_error"] = plan.predicted_error
    planned["predicted_psnr"] = -20 * math.log10(plan.predicted_error)
    planned["predicted_cost_s"] = plan.predicted_seconds
    out = {
        "scene": "bunny_relight (procedural bunny)",
        "vertices_seen": len(gb.vertex_ids),
        "psnr": psnr,
        "frames": frames,
        "plan": str(plan),
        "plan_seconds": plan_s,
        "reference_seconds": ref_s,
        "planned": planned,
        "prediction_ratio": max(
            planned["achieved_error"] / plan.predicted_error, plan.predicted_error / planned["achieved_error"]
        ),
        "defaults": [carry_out(*d) for d in defaults],
    }
    cli = out["defaults"][0]
    out["planner_cost_ratio_vs_cli_default"] = planned["cost_s"] / cli["cost_s"]
    reach = [d for d in out["defaults"] if d["psnr"] >= psnr]
    if reach:
        best = min(reach, key=lambda d: d["cost_s"])
        out["best_default"] = {k: best[k] for k in ("cubemap", "supersample", "bits", "rule")}
        out["planner_cost_ratio"] = planned["cost_s"] / best["cost_s"]
    return out


#: the manifold's fixed defaults: the seed's q (2 for "smaller and more consistent sets", 5 for the
#: whole MERL set; Soler et al. 2017, Sec. 3.1), trained on the whole pool
MANIFOLD_DEFAULTS = (2, 5)
#: the manifold plans' fit settings (those of tests/planner/test_manifold.py)
MANIFOLD_FIT = {"metric": "weighted", "max_iter": 100}
#: pool materials per family draw (materials 80 to 80 + pool - 1 of the draw; the planner's
#: prediction scatters with the pool's size, see ``torch_brdf/planner/manifold.py``)
MANIFOLD_POOL = 80
#: held-out materials per family draw (the analytic family makes as many as asked): the achieved
#: statistic's own scatter between sets of materials must stay well inside 1.5x
MANIFOLD_HELDOUT = 240


def statistic_table(pairs: list[tuple[torch.Tensor, torch.Tensor]], resamples: int = 4000) -> dict:
    """Every statistic of ``STATISTICS`` on the plans' own per-material scores (no fits): per plan,
    its chosen option's pool scores (the prediction's) and its model's held-out scores (the
    achieved). Per statistic: the median over the plans of the bootstrap standard deviation of
    the statistic's log on the pool, on the first 80 and on all held-out scores; the RMS and mean
    of log(held-out / pool) -- the prediction ratio each plan's model would have had under that
    statistic (the choice itself may differ by statistic); the worst ratio either way and how
    many are within 1.5x both ways."""

    def sd(x: torch.Tensor, f) -> float:
        idx = torch.randint(x.numel(), (resamples, x.numel()), generator=torch.Generator().manual_seed(0))
        return float(f(x[idx].double()).log().std())

    def median(v: list[float]) -> float:
        return sorted(v)[len(v) // 2]

    table = {}
    for name, f in STATISTICS.items():
        r = [float(f(h.double())) / float(f(p.double())) for p, h in pairs]
        logs = [math.log(x) for x in r]
        table[name] = {
            "sd_log_pool": median([sd(p, f) for p, _ in pairs]),
            "sd_log_heldout_80": median([sd(h[:80], f) for _, h in pairs]),
            "sd_log_heldout": median([sd(h, f) for _, h in pairs]),
            "rms_log_ratio": math.sqrt(sum(v * v for v in logs) / len(logs)),
            "mean_log_ratio": sum(logs) / len(logs),
            "worst_ratio": max(max(x, 1 / x) for x in r),
            "within_1_5": sum(1 / 1.5 <= x <= 1.5 for x in r),
            "ratios": [round(x, 3) for x in r],
        }
    return table


def _manifold_carry_out(obs, train, test, q):
    """Fit on ``train`` with ``q`` latent dimensions, place ``test``: (log-RMSE per held-out material, CPU s)."""
    t0 = time.process_time()
    h = heldout_reconstruction(obs, list(train), test, q, generator=torch.Generator().manual_seed(q), **MANIFOLD_FIT)
    return h.gplvm_logrmse, time.process_time() - t0


def _manifold_defaults(obs, pool, test, fam: int, stat, saved: dict) -> list[dict]:
    """The fixed defaults (``MANIFOLD_DEFAULTS``, trained on the whole pool) carried out and scored."""
    out = []
    for q in MANIFOLD_DEFAULTS:
        scores, secs = _manifold_carry_out(obs, pool, test, q)
        saved[f"f{fam}_default_q{q}_heldout"] = scores.numpy()
        out.append(
            {
                "family": fam,
                "q": q,
                "n": len(pool),
                "achieved_error": float(stat(scores)),
                "achieved_mean": float(scores.mean()),
                "cpu_s": secs,
            }
        )
    return out


def run_manifold(
    error: float,
    families: tuple[int, ...],
    orders: tuple[int, ...],
    heldout: int = MANIFOLD_HELDOUT,
    statistic: str = "trimmed",
    scores_path: str | None = None,
    pool_size: int = MANIFOLD_POOL,
) -> dict:
    """Plan q and the training materials of the GPLVM for a held-out log-RMSE ``error`` (its
    ``statistic`` over the materials) on the analytic family (per ``families`` seed, 120 +
    ``heldout`` - 80 materials on the 9 x 9 x 18 strided grid: materials 80-119 are the pool, the
    rest the held-out set; the first 120 are the same whatever ``heldout``), once per pool order
    (``orders``); each plan is carried out (fit on its training names, the held-out materials
    placed) and scored by the same statistic of their log-RMSE; so are the fixed defaults
    (``MANIFOLD_DEFAULTS``, trained on the whole pool). Cost = CPU seconds of the fit + the
    placements. ``scores_path``: the per-material scores (every measured option's pool scores,
    every plan's and default's held-out scores, each plan's (q, n)) saved there (``torch_brdf.io``,
    kind ``manifold-planner-scores``), so another statistic can be studied without new fits;
    ``statistics`` in the output: :func:`statistic_table` of the plans' own scores."""
    stat = STATISTICS[statistic]
    carry_out = _manifold_carry_out

    runs, defaults, saved, pairs = [], [], {}, []
    for fam in families:
        obs, _ = analytic_observations(
            pool_size + max(heldout, 80), MERLGrid.strided(9, 9, 18), generator=torch.Generator().manual_seed(fam)
        )
        names = list(obs.names)
        test, pool = names[:80] + names[80 + pool_size :], names[80 : 80 + pool_size]
        assert not set(test) & set(pool)
        defaults += _manifold_defaults(obs, pool, test, fam, stat, saved)
        for order in orders:
            t0 = time.process_time()
            pilots: dict = {}
            plan = plan_manifold(
                obs,
                pool,
                error=error,
                generator=torch.Generator().manual_seed(order),
                statistic=statistic,
                scores=pilots,
                **MANIFOLD_FIT,
            )
            plan_s = time.process_time() - t0
            s = plan.settings
            scores, secs = carry_out(obs, s["train"], test, s["q"])
            for (q, n), (held, sc) in pilots.items():
                saved[f"f{fam}_o{order}_q{q}_n{n}_pool"] = sc.numpy()
                saved[f"f{fam}_o{order}_q{q}_n{n}_pool_index"] = torch.tensor([pool.index(m) for m in held]).numpy()
            saved[f"f{fam}_o{order}_heldout"] = scores.numpy()
            saved[f"f{fam}_o{order}_chosen"] = torch.tensor([s["q"], s["n"]]).numpy()
            pairs.append((pilots[s["q"], s["n"]][1], scores))
            a = float(stat(scores))
            r = a / plan.predicted_error
            runs.append(
                {
                    "family": fam,
                    "order": order,
                    "q": s["q"],
                    "n": s["n"],
                    "predicted_error": plan.predicted_error,
                    "predicted_interval": plan.chosen.interval,
                    "achieved_error": a,
                    "achieved_interval": bootstrap_interval(scores, stat),
                    "achieved_first_80": float(stat(scores[:80])),
                    "achieved_mean": float(scores.mean()),
                    "ratio": r,
                    "cpu_s": secs,
                    "plan_cpu_s": plan_s,
                    "metric": plan.metric,
                }
            )
            print(
                f"manifold family {fam} order {order}: q {s['q']}, n {s['n']}, predicted {plan.predicted_error:.5f}, "
                f"achieved {a:.5f} ({statistic} of {len(test)}), achieved / predicted {r:.3f}; "
                f"intervals {runs[-1]['predicted_interval']}, {runs[-1]['achieved_interval']}",
                flush=True,
            )
    if scores_path:
        save_arrays(
            scores_path,
            saved,
            "manifold-planner-scores",
            meta={
                "families": list(families),
                "orders": list(orders),
                "pool": len(pool),
                "heldout": len(test),
                "statistic": statistic,
            },
        )
    first = runs[0]
    out = {
        "data": f"analytic family ({len(families)} draws): {len(pool)} pool, {len(test)} held-out materials; "
        "9 x 9 x 18 grid",
        "pool": len(pool),
        "error": error,
        "statistic": statistic,
        "heldout": len(test),
        "families": list(families),
        "orders": runs,
        "planned": {k: first[k] for k in ("q", "n", "predicted_error", "achieved_error", "achieved_mean")}
        | {"seconds": first["cpu_s"], "statistic": statistic, "heldout": len(test)},
        "defaults": defaults,
        "prediction_ratio": max(max(o["ratio"], 1 / o["ratio"]) for o in runs),
        "achieved_over_predicted": [min(o["ratio"] for o in runs), max(o["ratio"] for o in runs)],
        "within_1_5": sum(1 / 1.5 <= o["ratio"] <= 1.5 for o in runs) / len(runs),
        "reached": sum(o["achieved_error"] <= error for o in runs) / len(runs),
        "statistics": statistic_table(pairs),
    }
    ratios = []
    for o in runs:
        ok = [d for d in defaults if d["family"] == o["family"] and d["achieved_error"] <= error]
        if ok:
            ratios.append(o["cpu_s"] / min(d["cpu_s"] for d in ok))
    if ratios:
        out["planner_cost_ratio"] = max(ratios)  # worst over the plans, against the cheapest default that reaches
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="24 px, error 0.2, reference 256 spp")
    ap.add_argument("--error", type=float, default=None, help="requested relative RMSE (default 0.1; quick 0.2)")
    ap.add_argument("--resolution", type=int, default=None, help="image size (default 32; quick 24)")
    ap.add_argument(
        "--capabilities",
        default="gi,inverse,relight,manifold",
        help="comma-separated: gi, inverse, relight, manifold, validation (the generated scenes)",
    )
    ap.add_argument("--psnr", type=float, default=None, help="relighting target in dB (default 50; quick 45)")
    ap.add_argument("--families", default=None, help="manifold: analytic family seeds (default 7,11,13; quick 7)")
    ap.add_argument("--orders", type=int, default=None, help="manifold: pool orders 0..N-1 (default 8; quick 2)")
    ap.add_argument(
        "--heldout",
        type=int,
        default=MANIFOLD_HELDOUT,
        help=f"manifold: held-out materials (>= 80; default {MANIFOLD_HELDOUT})",
    )
    ap.add_argument(
        "--statistic", default="trimmed", choices=sorted(STATISTICS), help="manifold: the planned statistic (trimmed)"
    )
    ap.add_argument(
        "--pool", type=int, default=MANIFOLD_POOL, help=f"manifold: pool materials (default {MANIFOLD_POOL})"
    )
    ap.add_argument("--scores", default=None, help="manifold: save the per-material scores to this .npz")
    ap.add_argument("--max-spp", type=int, default=512, help="largest spp tried for a default series")
    ap.add_argument("--repeats", type=int, default=3, help="timings of the planned run and best defaults (least)")
    ap.add_argument(
        "--validation-errors",
        default="0.05,0.03",
        help="validation: error targets (comma-separated; 0.03 = the default)",
    )
    ap.add_argument("--validation-size", type=int, default=None, help="validation: image size (default 48; quick 24)")
    args = ap.parse_args()
    q = args.quick
    error = args.error or (0.2 if q else 0.1)
    res = args.resolution or (24 if q else 32)
    ref_spp = 256 if q else 2048
    out: dict = {"quick": q, "error": error, "resolution": res, "load": os.getloadavg()[0], "scenes": {}}
    caps = args.capabilities.split(",")
    if "gi" in caps:
        for sc in (cornell_box_glossy(res), teatray(res)):
            out["scenes"][sc.name] = run_scene(sc, error, ref_spp, args.max_spp, repeats=args.repeats)
    if "inverse" in caps:
        out["inverse"] = run_inverse(0.06 if q else 0.05, (40, 30) if q else (64, 48), 2048 if q else 4096)
    if "relight" in caps:
        out["relight"] = run_relight(args.psnr or (45.0 if q else 50.0), q)
    if "validation" in caps:
        from .planner_validation import QUICK_SET, run_validation

        out["validation"] = run_validation(
            args.validation_size or (24 if q else 48),
            tuple(float(e) for e in args.validation_errors.split(",")),
            subset=QUICK_SET if q else None,
            pt_spp=64 if q else 256,
        )
    if "manifold" in caps:
        families = tuple(int(f) for f in args.families.split(",")) if args.families else (7,) if q else (7, 11, 13)
        orders = tuple(range(args.orders or (2 if q else 8)))
        out["manifold"] = run_manifold(0.01, families, orders, args.heldout, args.statistic, args.scores, args.pool)
    out["load_end"] = os.getloadavg()[0]
    others = [out[k]["prediction_ratio"] for k in ("inverse", "relight", "manifold", "validation") if k in out]
    if not out["scenes"]:
        if others:
            out["prediction_ratio"] = max(others)
        print(json.dumps(out))
        return
    gi = out["scenes"].values()
    out["gi"] = {
        k: max(s[k] for s in gi)
        for k in (
            "prediction_ratio",
            "planner_cost_ratio",
            "planner_cost_ratio_rays",
            "planner_cost_ratio_fine_spp",
            "planner_cost_ratio_rays_fine_spp",
            "planner_cost_ratio_retimed",
            "planner_cost_ratio_retimed_fine_spp",
        )
        if all(k in s for s in gi)
    }
    out["planner_cost_ratio"] = out["gi"].get("planner_cost_ratio")
    out["planner_cost_ratio_rays"] = out["gi"].get("planner_cost_ratio_rays")
    out["planner_cost_ratio_fine_spp"] = out["gi"].get("planner_cost_ratio_fine_spp")
    out["planner_cost_ratio_rays_fine_spp"] = out["gi"].get("planner_cost_ratio_rays_fine_spp")
    out["prediction_ratio"] = max([out["gi"]["prediction_ratio"]] + others)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
