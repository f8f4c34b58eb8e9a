"""BRDF layer benchmark: evaluation throughput, 1-D projection error, band-albedo cost.

    python benchmarks/brdf.py [--quick]

Prints progress lines, then one JSON object as the last line:

* ``evals_per_s``: per model, ``eval_local`` on N random direction pairs (float32, best of
  3); ``evals_rel_lambert``: the same relative to Lambert in this run (the memory-bound
  floor of a BRDF evaluation).
* ``projection_rel_err``: cosine-weighted relative L2 error of the 1-D theta_h projection
  (Ben-Artzi et al. 2008, App. A), keys ``blinn_n{n}_J{J}`` (bands spaced for the lobe,
  ``spacing="lobe:n"``), ``blinn_n{n}_J{J}_sqrt`` (the generic sqrt spacing) and
  ``merl_{material}_J{J}`` (sqrt spacing; the MERL materials are NBRDF fits, an
  APPROXIMATION of MERL; shared data needed), ``mr_metal_r{r}_J{J}`` and
  ``mr_dielectric_r{r}_J{J}`` (the glTF metallic-roughness model, sqrt spacing; the metal
  with the Schlick x Smith quotient of its f0 and alpha, the dielectric with the microfacet
  quotient: its Lambert term is not a function of theta_h under any one quotient).
  ``projection_s`` beside each family: seconds per projection.
* ``albedo_table_s``: seconds to compute the band albedos e_j (App. B) for J = 64, uncached.
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from torch_brdf.brdf import create
from torch_brdf.brdf.bands import (
    BandBasis,
    Factored1D,
    SchlickFresnel,
    SmithQuotient,
    band_albedos,
    project,
    projection_error,
)
from torch_brdf.data import data_path

from ._timing import best_of

MERL_MATERIALS = ("gold-metallic-paint", "blue-acrylic")


def _pairs(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    w = torch.nn.functional.normalize(torch.randn(2, n, 3, generator=g), dim=-1)
    w[..., 2] = w[..., 2].abs()
    return w[0].contiguous(), w[1].contiguous()


def _models(have_nbrdf: bool) -> dict[str, torch.nn.Module]:
    m = {
        "lambert": create("lambert", albedo=0.5),
        "blinn_phong": create("blinn_phong", exponent=100.0),
        "phong": create("phong", exponent=100.0),
        "ward": create("ward", alpha=0.2),
        "ward_aniso": create("ward_aniso", alpha_x=0.1, alpha_y=0.3),
        "cook_torrance_beckmann": create("cook_torrance", distribution="beckmann"),
        "cook_torrance_ggx": create("cook_torrance", distribution="ggx"),
        "ashikhmin_shirley": create("ashikhmin_shirley", nu=100.0, nv=1000.0),
        "distribution_based": create("distribution_based"),
        "metallic_roughness": create("metallic_roughness", metallic=0.5, roughness=0.5),
        "factored_1d_J64": Factored1D(J=64),
    }
    if have_nbrdf:
        m["nbrdf"] = create("nbrdf", material="gold-metallic-paint")
        table = data_path("merl", "merl_nbrdf_sample_f16.npz", required=False)
        if table is not None:
            m["merl_nearest"] = create("merl", table=table, material="gold-metallic-paint")
    return m


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small run (100k pairs, fewer bands)")
    args = ap.parse_args()
    n = 100_000 if args.quick else 1_000_000
    js = (8, 64) if args.quick else (8, 16, 32, 64, 128, 256)
    have_nbrdf = data_path("merl", "nbrdf_merl100_weights.npz", required=False) is not None

    wi, wo = _pairs(n)
    evals = {}
    with torch.no_grad():
        for name, model in _models(have_nbrdf).items():
            s = best_of(lambda model=model: model.eval_local(wi, wo))[0]
            evals[name] = round(n / s)
            print(f"eval {name}: {evals[name]:,} pairs/s", flush=True)
    rel = {k: round(v / evals["lambert"], 4) for k, v in evals.items()}

    errors, times = {}, {}
    # (key, brdf, spacing, key suffix[, quotient]): Blinn-Phong with bands adapted to its lobe (the
    # recommended choice for a known exponent) and with the generic sqrt spacing
    families = []
    for e in (10, 100, 1000):
        blinn = create("blinn_phong", kd=0.0, ks=1.0, exponent=float(e))
        families += [(f"blinn_n{e}", blinn, f"lobe:{e}", ""), (f"blinn_n{e}", blinn, "sqrt", "_sqrt")]
    for r in (0.2, 0.5):
        gold = (1.0, 0.78, 0.34)
        metal = create("metallic_roughness", base_color=gold, metallic=1.0, roughness=r)
        plastic = create("metallic_roughness", base_color=(0.8, 0.4, 0.1), metallic=0.0, roughness=r)
        q_metal = SchlickFresnel(SmithQuotient("ggx", r * r), f0=list(gold))
        families += [
            (f"mr_metal_r{r}", metal, "sqrt", "", q_metal),
            (f"mr_dielectric_r{r}", plastic, "sqrt", "", "microfacet"),
        ]
    if have_nbrdf:
        families += [(f"merl_{m}", create("nbrdf", material=m), "sqrt", "") for m in MERL_MATERIALS]
    for key, brdf, spacing, suffix, *quotient in families:
        q = quotient[0] if quotient else "one"
        t0 = time.perf_counter()
        for J in js:
            basis = BandBasis("theta_h", J, spacing=spacing)
            fac = Factored1D(basis, coefficients=project(brdf, basis, q), quotient=q)
            k = f"{key}_J{J}{suffix}"
            errors[k] = round(projection_error(brdf, fac), 5)
            print(f"projection {k} ({spacing} spacing): rel err {errors[k]:.4%}", flush=True)
        times[key + suffix] = round((time.perf_counter() - t0) / len(js), 3)

    t0 = time.perf_counter()
    band_albedos(BandBasis("theta_h", 64), cache=False, progress=False)
    albedo_s = time.perf_counter() - t0

    print(
        json.dumps(
            {
                "pairs": n,
                "evals_per_s": evals,
                "evals_rel_lambert": rel,
                "projection_rel_err": errors,
                "projection_s": times,
                "albedo_table_s": round(albedo_s, 3),
                "merl_note": "MERL keys use NBRDF fits, an approximation of the measured MERL data"
                if have_nbrdf
                else "shared data absent: MERL keys skipped",
            }
        )
    )


if __name__ == "__main__":
    main()
