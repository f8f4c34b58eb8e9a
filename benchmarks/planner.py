"""The GI-editing planner against fixed default series (issue #17).

    python benchmarks/planner.py [--quick] [--error 0.1] [--resolution 32]

Scene: the glossy Cornell box (Blinn-Phong n = 100 back wall). The reference is the converged
polynomial model of the same scene: 6 bounces, 64 bands on glossy objects (1 on Lambertian
ones), ``reference_spp`` paths per pixel; errors are relative RMSE over the pixels that do not
see the light (``emitter_mask``). Prints progress, then one JSON object as the last line:

* ``plan``: the planner's printed plan; ``planned``: its series, spp, predicted error,
  achieved error, precompute seconds and rays; ``plan_seconds``: what planning cost (band
  projections and the two pilots).
* ``prediction_ratio``: max(achieved / predicted, predicted / achieved) (goal <= 1.5).
* ``defaults``: per fixed default series ("64,1,1,1" the CLI's, "64,16"), spp doubled from 8
  until the achieved error is <= the requested one: achieved error, seconds, rays per spp.
* ``planner_cost_ratio``: precompute seconds of the planned settings over those of the
  cheapest default that reaches the error (goal <= 0.7); ``planner_cost_ratio_rays``: the
  same in rays cast (load-independent); ``planner_cost_ratio_with_planning``: planning included.
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from torch_brdf.metrics import relative_rmse
from torch_brdf.records.polynomial import Series
from torch_brdf.render.polynomial import PolynomialRenderer, emitter_mask
from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.transport.polynomial import plan_bases, plan_polynomial, precompute_polynomial


def _rays(T) -> int:
    return int(sum(T.meta["rays"].values()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="24 px, error 0.2, reference 128 spp")
    ap.add_argument("--error", type=float, default=None, help="requested relative RMSE (default 0.1; quick 0.2)")
    ap.add_argument("--resolution", type=int, default=None, help="image size (default 32; quick 24)")
    ap.add_argument("--max-spp", type=int, default=1024, help="largest spp tried for a default series")
    args = ap.parse_args()
    q = args.quick
    error = args.error or (0.2 if q else 0.1)
    res = args.resolution or (24 if q else 32)
    ref_spp = 128 if q else 512
    sc = cornell_box_glossy(res)
    mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
    out: dict = {"quick": q, "scene": "cornell_box_glossy", "resolution": res, "error": error, "reference_spp": ref_spp}

    ref_series = Series((64,) + (1,) * 5)
    ref_bases = plan_bases(sc, ref_series)
    print(f"reference: {ref_series.key} at {ref_spp} spp", flush=True)
    R = precompute_polynomial(sc, ref_series, spp=ref_spp, seed=99, bases=ref_bases, progress=False)
    ref = PolynomialRenderer(R, mats, dtype=torch.float64)()
    mask = emitter_mask(R)

    def achieved(T) -> float:
        return relative_rmse(PolynomialRenderer(T, mats, dtype=torch.float64)(), ref, mask)

    t0 = time.perf_counter()
    plan = plan_polynomial(sc, error=error, seed=0)
    out["plan_seconds"] = time.perf_counter() - t0
    print(plan, flush=True)
    t0 = time.perf_counter()
    T = precompute_polynomial(sc, plan=plan, seed=1, progress=False)
    secs = time.perf_counter() - t0
    a = achieved(T)
    out["plan"] = str(plan)
    out["planned"] = {
        "series": plan.series.key,
        "spp": plan.spp,
        "predicted_error": plan.predicted_error,
        "achieved_error": a,
        "seconds": secs,
        "predicted_seconds": plan.predicted_seconds,
        "rays": _rays(T),
    }
    out["prediction_ratio"] = max(a / plan.predicted_error, plan.predicted_error / a)

    defaults = {}
    best = None
    for key in ("64,1,1,1", "64,16"):
        spp, rows = 8, []
        while spp <= args.max_spp:
            t0 = time.perf_counter()
            D = precompute_polynomial(sc, key, spp=spp, seed=1, progress=False)
            s = time.perf_counter() - t0
            e = achieved(D)
            rows.append({"spp": spp, "achieved_error": e, "seconds": s, "rays": _rays(D)})
            print(f"default {key} spp {spp}: error {e:.4f}, {s:.2f} s", flush=True)
            if e <= error:
                if best is None or s < best["seconds"]:
                    best = {"series": key, **rows[-1]}
                break
            spp *= 2
        defaults[key] = rows
    out["defaults"] = defaults
    out["best_default"] = best
    if best is not None:
        out["planner_cost_ratio"] = secs / best["seconds"]
        out["planner_cost_ratio_rays"] = _rays(T) / best["rays"]
        out["planner_cost_ratio_with_planning"] = (secs + out["plan_seconds"]) / best["seconds"]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
