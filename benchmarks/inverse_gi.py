"""Inverse material design with global illumination (issue #16): fits through the polynomial tensors.

    python benchmarks/inverse_gi.py [--quick] [--no-mitsuba]

Scene: the glossy Cornell box. Prints progress, then one JSON object as the last line:

* per resolution (``runs``; 128² and 256², ``--quick``: 32²): ``precompute_s`` (series
  ``64,1,1,1``, ``spp`` paths per pixel, 4 bounces), and for the back wall alone
  (``back``) and back wall + floor (``back_floor``): a target rendered from the tensors with
  known coefficients (back wall: Blinn-Phong kd 0.3, ks 0.5, n 100 projected on its bands;
  floor: Lambert (0.6, 0.3, 0.2)), fitted from Lambert 0.5 by :func:`torch_brdf.render.fit_image`
  (float64): ``fit_s``, ``iterations``, ``loss`` (½ Σ w (B - B*)², back-wall pixels),
  ``param_rel_err`` (max |c - c*| / max |c*|), ``kkt_residual``, ``violation``.
* ``gi_fit_err`` / ``direct_fit_err``: a target path-traced (``reference_path_trace``, 4
  bounces) with a GGX back wall (Cook-Torrance, roughness 0.2, f0 0.5, kd 0.25: outside the
  Blinn family) at ``gi_res``², fitted on the back-wall pixels with the GI tensors and with the
  same tensors truncated to 1 bounce; both fitted curves are rendered with all bounces and
  compared to the target (relative RMSE, emitter pixels excluded).
* top-level ``ours_fit_s``, ``ours_loss``, ``param_rel_err``, ``precompute_s``: 256², back wall
  (``--quick``: 32²). ``mitsuba_fit_s`` / ``mitsuba_loss``: see the README (null when the
  Mitsuba comparison did not run).
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from torch_brdf.metrics import relative_rmse
from torch_brdf.render import PolynomialRenderer, fit_image, object_mask
from torch_brdf.render.polynomial import emitter_mask
from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.transport.pathtrace import reference_path_trace
from torch_brdf.transport.polynomial import precompute_polynomial

TRUTH = {
    "back": {"type": "blinn_phong", "kd": 0.3, "ks": 0.5, "exponent": 100.0},
    "floor": {"type": "lambert", "albedo": (0.6, 0.3, 0.2)},
}
START = {"type": "lambert", "albedo": 0.5}


def _materials(scene):
    return {o.name: scene.materials[o.material] for o in scene.objects if o.editable}


def _recovery(T, mats, objects):
    R = PolynomialRenderer(T, mats, dtype=torch.float64)
    for o in objects:
        R.set_material(o, TRUTH[o])
    truth = {o: R.c[T.object_id(o)].clone() for o in objects}
    target = R().detach()
    for o in objects:
        R.set_material(o, START)
    w = sum(object_mask(T, o).double() for o in objects).clamp(max=1)
    t0 = time.perf_counter()
    res = fit_image(R, objects, target, weights=w)
    fit_s = time.perf_counter() - t0
    err = max(float((res.coefficients[o] - truth[o]).abs().max() / truth[o].abs().max()) for o in objects)
    return {
        "fit_s": round(fit_s, 3),
        "iterations": res.iterations,
        "loss": res.loss,
        "start_loss": res.loss_curve[0],
        "param_rel_err": err,
        "kkt_residual": res.kkt_residual,
        "violation": res.violation,
    }


def _gi_vs_direct(res: int, spp: int, ref_spp: int) -> dict:
    sc = cornell_box_glossy(res)
    T = precompute_polynomial(sc, "64,1,1,1", spp=spp, seed=0, progress=False)
    ggx = cornell_box_glossy(res)
    ggx.materials["glossy_back"] = {"type": "cook_torrance", "distribution": "ggx", "roughness": 0.2, "f0": 0.5}
    ggx.materials["glossy_back"]["kd"] = 0.25
    target = reference_path_trace(ggx, spp=ref_spp, max_bounces=4, seed=1, progress=False).double()
    mats = _materials(sc)
    mask = object_mask(T, "back")
    keep = emitter_mask(T)
    out = {}
    for key, bounces in (("gi", None), ("direct", 1)):
        R = PolynomialRenderer(T, mats, dtype=torch.float64, max_bounces=bounces)
        t0 = time.perf_counter()
        fit = fit_image(R, "back", target, weights=mask)
        out[f"{key}_fit_s"] = round(time.perf_counter() - t0, 3)
        full = PolynomialRenderer(T, mats, dtype=torch.float64)
        full.set_coefficients("back", fit.coefficients["back"])
        img = full().detach()
        out[f"{key}_fit_err"] = relative_rmse(img, target, keep)
        out[f"{key}_wall_err"] = relative_rmse(img, target, mask & keep)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-mitsuba", action="store_true")
    ap.add_argument("--sizes", default=None, help="comma-separated resolutions (default 128,256; --quick 32)")
    args = ap.parse_args()
    sizes = [32] if args.quick else [128, 256]
    if args.sizes:
        sizes = [int(v) for v in args.sizes.split(",")]
    spp = 4 if args.quick else 16
    out = {"series": "64,1,1,1", "spp": spp, "runs": {}}
    warm = cornell_box_glossy(16)  # one-off imports (forward-mode AD) and thread tuning, not timed
    _recovery(precompute_polynomial(warm, "8,1", spp=1, seed=0, progress=False), _materials(warm), ["back"])
    for res in sizes:
        sc = cornell_box_glossy(res)
        t0 = time.perf_counter()
        T = precompute_polynomial(sc, "64,1,1,1", spp=spp, seed=0, progress=False)
        run = {"precompute_s": round(time.perf_counter() - t0, 3)}
        mats = _materials(sc)
        run["back"] = _recovery(T, mats, ["back"])
        run["back_floor"] = _recovery(T, mats, ["back", "floor"])
        out["runs"][str(res)] = run
        print(f"{res}: {json.dumps(run)}", flush=True)
    top = out["runs"][str(sizes[-1])]
    out["precompute_s"] = top["precompute_s"]
    out["ours_fit_s"] = top["back"]["fit_s"]
    out["ours_loss"] = top["back"]["loss"]
    out["param_rel_err"] = top["back"]["param_rel_err"]
    gi_res = 32 if args.quick else 64
    gi = _gi_vs_direct(gi_res, spp, 16 if args.quick else 64)
    out |= {"gi_res": gi_res, **gi}
    out["mitsuba_fit_s"] = None
    out["mitsuba_loss"] = None
    if not args.no_mitsuba:
        try:
            from _mitsuba_fit import mitsuba_fit  # sibling module (benchmarks/)

            out |= mitsuba_fit(sizes[-1], quick=args.quick)
        except Exception as exc:  # the benchmark reports why the peer did not run
            out["mitsuba_error"] = f"{type(exc).__name__}: {exc}"
    print(json.dumps(out))


if __name__ == "__main__":
    main()
