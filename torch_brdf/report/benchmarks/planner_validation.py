"""The GI planner on scenes its tuning never used: predicted against achieved error.

Run through ``python benchmarks/planner.py --capabilities validation`` (``--quick``: two
scenes at 24², else the whole :data:`~torch_brdf.scene.generated.VALIDATION_SET` at 48²).

Per scene of :mod:`torch_brdf.scene.generated` (seeded; its kind and seed are its name) and
per error target (``--validation-errors``, default 0.05 and 0.03), the default planner
(:func:`~torch_brdf.planner.gi.plan_polynomial` with the default time budget, so the 0.03 plan
is exactly ``precompute_planned(scene)``'s default) is carried out with an independent seed,
and:

* ``achieved_error``: relative RMSE over the pixels that see no emitter against the
  *reference*: the same polynomial model converged, traced by the precompute's own path
  tracer at 6 bounces, twice the planned bands (at least 64) on glossy objects and twice the
  second-bounce bands, with the tightest plan's spp map x ``ref_factor`` in each of two
  independent halves (the adaptive map puts the reference's paths where the noise is; a
  uniform high-spp reference of the same cost was several times noisier on glossy floors
  under a sun). The reference's own noise (``reference_noise``, from its halves'
  difference) is taken out in quadrature. ``noise_error`` / ``achieved_noise``: the plan's
  predicted noise and the noise of the carried-out record measured from a second run of the
  same plan (another seed): ``relative_rmse(T1, T2) / sqrt 2``;
  Targets are keyed ``e`` + the error in thousandths (``e50`` = 0.05, ``e30`` = 0.03);
* ``ratio`` = achieved / predicted (acceptance: within [0.67, 1.5]);
* ``seconds`` / ``time_budget``: the planned run's measured seconds (``met``: at most the budget);
* ``bounces`` / ``needed_bounces`` / ``reference_needed_bounces``: the series' length, the
  bounces the planner says the light needs, and the same measured on the reference (the
  last bounce whose own light is above 10% of the error): ``series_within_light``;
* per scene ``object_means`` (the 0.03 = default plan): per object seen by at least 4 pixels,
  the record's mean over the object's pixels against the plain path tracer's
  (:func:`~torch_brdf.transport.pathtrace.path_trace`, full BRDFs, MIS, 6 bounces,
  ``pt_spp`` x 2 runs): ``rel_diff``, the path tracer's own standard error ``pt_se``
  (relative, from its two runs) and ``within_1pct``.

Textured scenes are rendered with their textures on both sides
(:func:`~torch_brdf.render.polynomial.apply_scene_textures`).
"""

from __future__ import annotations

import dataclasses
import math
import time

import torch

from torch_brdf.metrics import relative_rmse
from torch_brdf.planner.gi import DEFAULT_SECONDS, LAST_BOUNCE_SHARE, plan_polynomial, precompute_planned, with_fixed
from torch_brdf.records.polynomial import Series
from torch_brdf.render.polynomial import PolynomialRenderer, apply_scene_textures, emitter_mask
from torch_brdf.scene.generated import VALIDATION_SET, validation_scenes
from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial

#: the quick subset: a glossy floor reflecting a glossy ball, and the textured floor
QUICK_SET = (("glossy_floor_glossy", 102), ("textured_floor", 105))


def _renderer(T, sc, mats):
    r = PolynomialRenderer(T, mats, dtype=torch.float64)
    if any(o.textures for o in sc.objects):
        apply_scene_textures(r, sc)
    return r


def _image(T, sc, mats) -> torch.Tensor:
    return _renderer(T, sc, mats)().double()


def _reference(sc, plans, mats, ref_factor: int):
    """Two independent halves of the converged model (see the module) and their per-bounce light."""
    tight = min(plans, key=lambda p: p.error)
    second = max(p.series.second if p.series.two_level else 1 for p in plans)
    bases = []
    for m, b in enumerate(tight.bases):
        if b is None or b.J == 1:
            bases.append(b)
            continue
        J = max(64, 2 * max(p.bases[m].J for p in plans))
        bases.append(dataclasses.replace(b, J=J, second=min(J, 2 * second) if second > 1 else 1))
    J = max([1] + [b.J for b in bases if b is not None])
    series = Series((J, min(J, 2 * second)) + (1,) * 4) if second > 1 else Series((J,) + (1,) * 5)
    ref_sc = with_fixed(sc, tight.fixed)
    halves, per_bounce = [], None
    for k in range(2):
        R = precompute_polynomial(
            ref_sc, PolynomialSettings(series, spp=tight.spp_map * ref_factor, bases=bases), seed=99 + k, progress=False
        )
        r = _renderer(R, sc, mats)
        halves.append(r().double())
        if k == 0:
            per_bounce = [p.double() for p in r.evaluate(per_bounce=True)]
            mask = emitter_mask(R)
    return halves, per_bounce, mask, series.key


def run_validation(
    size: int, errors: tuple[float, ...], subset=None, ref_factor: int = 8, pt_spp: int = 256, seconds=DEFAULT_SECONDS
) -> dict:
    """Predicted against achieved error of the planner on the generated validation scenes."""
    out: dict = {
        "size": size,
        "errors": list(errors),
        "reference_factor": ref_factor,
        "pt_spp": pt_spp,
        "scenes_listed": [f"{k}-{s}" for k, s in (VALIDATION_SET if subset is None else subset)],
        "scenes": {},
    }
    worst, ok_ratio, ok_time, ok_series, ok_means = 1.0, True, True, True, True
    for sc in validation_scenes(size, subset):
        mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
        res: dict = {"targets": {}}
        plans, runs = {}, {}
        for e in errors:
            t0 = time.perf_counter()
            plan = plan_polynomial(sc, error=e, seconds=seconds, seed=0, progress=False)
            plan_s = time.perf_counter() - t0
            print(plan, flush=True)
            t0 = time.perf_counter()
            T = precompute_planned(sc, plan=plan, seed=1, progress=False)
            secs = time.perf_counter() - t0
            T2 = precompute_planned(sc, plan=plan, seed=2, progress=False)
            plans[e], runs[e] = plan, (T, T2, secs, plan_s)
        halves, per_bounce, mask, ref_key = _reference(sc, list(plans.values()), mats, ref_factor)
        ref = (halves[0] + halves[1]) / 2
        ref_noise = relative_rmse(halves[0], halves[1], mask) / 2
        res |= {"reference_series": ref_key, "reference_noise": ref_noise}
        norm = float((ref[mask] ** 2).sum()) ** 0.5
        light = [float((b[mask] ** 2).sum()) ** 0.5 / norm for b in per_bounce]
        for e, plan in plans.items():
            T, T2, secs, plan_s = runs[e]
            img, img2 = _image(T, sc, mats), _image(T2, sc, mats)
            m = mask & emitter_mask(T)
            raw = relative_rmse(img, ref, m)
            a = math.sqrt(max(0.0, raw * raw - ref_noise * ref_noise))
            noise = relative_rmse(img, img2, m) / math.sqrt(2)
            ref_needed = max([1] + [n for n in range(1, len(light)) if light[n] > LAST_BOUNCE_SHARE * e])
            r = {
                "series": plan.series.key,
                "spp": round(plan.spp, 1),
                "light_samples": plan.light_samples,
                "predicted_error": plan.predicted_error,
                "achieved_error": a,
                "achieved_raw": raw,
                "ratio": a / plan.predicted_error,
                "noise_error": plan.noise_error,
                "achieved_noise": noise,
                "noise_ratio": noise / plan.noise_error if plan.noise_error > 0 else None,
                "band_error": plan.band_error,
                "bounce_error": plan.bounce_error,
                "seconds": secs,
                "plan_seconds": plan_s,
                "predicted_seconds": plan.predicted_seconds,
                "time_budget": seconds,
                "met": secs <= seconds,
                "bounces": plan.series.bounces,
                "needed_bounces": plan.needed_bounces,
                "reference_needed_bounces": ref_needed,
                "series_within_light": plan.series.bounces <= min(plan.needed_bounces, max(ref_needed, 1)),
            }
            print(
                f"{sc.name} {e}: predicted {r['predicted_error']:.4f} achieved {a:.4f} ({r['ratio']:.2f})", flush=True
            )
            res["targets"][f"e{round(e * 1000)}"] = r  # e50 = 0.05 (no dot: docs quote dotted key paths)
            worst = max(worst, r["ratio"], 1 / max(r["ratio"], 1e-9))
            ok_ratio &= 0.67 <= r["ratio"] <= 1.5
            ok_time &= r["met"]
            ok_series &= r["series_within_light"]
        # object means of the tightest (default) plan against the plain path tracer
        T = runs[min(plans)][0]
        img = _image(T, sc, mats)
        pt = [path_trace(sc, PathTraceSettings(spp=pt_spp, max_bounces=6), seed=10 + s, progress=False) for s in (0, 1)]
        pt = torch.stack(pt).double()
        o, d = sc.camera.generate_rays(dtype=torch.float64)
        ids = sc.trace(o.float(), d.float()).object_id.reshape(sc.camera.height, sc.camera.width)
        means = {}
        for k, obj in enumerate(sc.objects):
            reg = (ids == k) & mask
            if int(reg.sum()) < 4:
                continue
            theirs = pt[:, reg].mean((1, 2))
            ref_m = float(theirs.mean())
            ours = float(img[reg].mean())
            rd = (ours - ref_m) / ref_m
            se = float((theirs[0] - theirs[1]).abs()) / 2 / ref_m
            means[obj.name] = {"pixels": int(reg.sum()), "rel_diff": rd, "pt_se": se, "within_1pct": abs(rd) <= 0.01}
            ok_means &= abs(rd) <= 0.01
        res["object_means"] = means
        out["scenes"][sc.name] = res
    out |= {
        "prediction_ratio": worst,
        "all_ratios_within": ok_ratio,
        "all_time_met": ok_time,
        "all_series_within_light": ok_series,
        "all_object_means_within_1pct": ok_means,
    }
    return out
