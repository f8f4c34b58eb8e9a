"""Mitsuba 3's ``roughplastic``/``plastic`` as a library model: the shared contract at three
settings, Mitsuba's own ``eval`` as the oracle at seeded direction pairs (reference), the
textured diffuse, and the generic band projection."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.brdf.common import F64, BRDFContract, _EvalAndPdf, direction, half_vector_albedo, hemisphere
from torch_brdf.brdf import create
from torch_brdf.brdf.bands import BandBasis, Factored1D, SchlickFresnel, SmithQuotient, project, projection_error
from torch_brdf.brdf.plastic import RoughPlastic, coat_albedo, coat_transmittance, dielectric_fresnel
from torch_brdf.brdf.textured import textured_eval_local
from torch_brdf.errors import ValueRangeError

#: largest relative difference from Mitsuba's ``eval`` over the seeded pairs of
#: :func:`test_matches_mitsuba_eval`: the two quadratures of the coat tables (measured below
#: 1e-3 for GGX and Beckmann at alpha 0.05 to 1) plus Mitsuba's float32
ROUGH_RTOL = 2e-3
#: ``plastic``: Mitsuba's polynomial fit of the internal diffuse reflectance against our integral
SMOOTH_RTOL = 1e-2


class _Plastic(BRDFContract):
    """The documented bound: 1.02 (the coat tables' quadrature, see the module docstring).

    Gradients: exact (gradcheck) for the reflectances. The tables are quadratures whose
    internal reflectance has a kink wherever a node crosses the critical angle, so their
    derivative in roughness and IOR is piecewise: it is checked against wide central
    differences to 2%."""

    def albedo_bound(self, brdf, wo):
        return brdf.albedo_bound(wo)

    def test_gradcheck(self):
        brdf = self.make(F64)
        wi, wo = self.pairs(12, F64, 6)
        raws = {n: p.detach().clone() for n, p in brdf.named_parameters()}
        for n in ("raw_diffuse_reflectance", "raw_specular_reflectance"):
            raws[n] = raws[n].clamp(1e-3, 1 - 1e-3)

        def call(**over):
            state = {"brdf." + k: v for k, v in {**raws, **over}.items()}
            return torch.cat([t.reshape(-1) for t in torch.func.functional_call(_EvalAndPdf(brdf), state, (wi, wo))])

        def fn(d, s):
            return call(raw_diffuse_reflectance=d, raw_specular_reflectance=s)

        d, s = (raws[n].clone().requires_grad_(True) for n in ("raw_diffuse_reflectance", "raw_specular_reflectance"))
        assert torch.autograd.gradcheck(fn, (d, s), eps=1e-6, atol=1e-6, rtol=1e-4)
        for n in ("raw_roughness", "raw_eta"):
            x = raws[n].clone().requires_grad_(True)
            (g,) = torch.autograd.grad(call(**{n: x}).sum(), x)
            h = 1e-3
            fd = (call(**{n: raws[n] + h}).sum() - call(**{n: raws[n] - h}).sum()) / (2 * h)
            torch.testing.assert_close(g, fd, rtol=2e-2, atol=1e-6)


class TestRoughPlasticGGX(_Plastic):
    def make(self, dtype):
        return RoughPlastic("ggx", roughness=0.3, diffuse_reflectance=(0.2, 0.5, 0.8)).to(dtype)


class TestRoughPlasticBeckmannWhite(_Plastic):
    def make(self, dtype):
        return RoughPlastic("beckmann", roughness=0.1, diffuse_reflectance=1.0, eta=1.5).to(dtype)


class TestRoughPlasticNonlinear(_Plastic):
    def make(self, dtype):
        return RoughPlastic("ggx", roughness=0.6, diffuse_reflectance=0.7, nonlinear=True).to(dtype)


_CONTRACTS = [TestRoughPlasticGGX, TestRoughPlasticBeckmannWhite, TestRoughPlasticNonlinear]
_Plastic.chi2_family_size = len(_CONTRACTS) * len(BRDFContract.chi2_thetas)


def _mitsuba_eval(params: dict, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """Mitsuba's BSDF ``eval`` (f times cos(theta_o)) divided by the cosine: (n, 3) float64."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    bsdf = mi.load_dict(params)
    ctx, out = mi.BSDFContext(), []
    for a, b in zip(wi.tolist(), wo.tolist(), strict=True):
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*a)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
        v = bsdf.eval(ctx, si, mi.Vector3f(*b))
        out.append([v[0] / b[2], v[1] / b[2], v[2] / b[2]])
    return torch.tensor(out, dtype=F64)


def _pairs(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return hemisphere(n, g, min_cos=0.02), hemisphere(n, g, min_cos=0.02)


ROUGH_CASES = [
    ("ggx", 0.05, 1.49, (0.2, 0.5, 0.8), 1.0, False),
    ("ggx", 0.3, 1.5, (0.9, 0.1, 0.4), (0.5, 0.8, 1.0), False),
    ("ggx", 1.0, 1.33, 0.5, 1.0, True),
    ("beckmann", 0.1, 1.49, (0.2, 0.5, 0.8), 1.0, False),
    ("beckmann", 0.5, 1.7, 0.9, 1.0, True),
]


@pytest.mark.reference
@pytest.mark.parametrize("dist, alpha, eta, rho, spec, nonlinear", ROUGH_CASES)
def test_matches_mitsuba_eval(dist, alpha, eta, rho, spec, nonlinear):
    """Pointwise against Mitsuba's ``roughplastic`` at 200 seeded pairs: within ROUGH_RTOL."""
    rgb = lambda v: {"type": "rgb", "value": list(v) if isinstance(v, tuple) else [v] * 3}  # noqa: E731
    params = {
        "type": "roughplastic",
        "distribution": dist,
        "alpha": alpha,
        "int_ior": eta,
        "ext_ior": 1.0,
        "diffuse_reflectance": rgb(rho),
        "specular_reflectance": rgb(spec),
        "nonlinear": nonlinear,
    }
    wi, wo = _pairs(200, seed=7)
    theirs = _mitsuba_eval(params, wi, wo)
    model = create(
        {
            "type": "rough_plastic",
            "distribution": dist,
            "roughness": alpha,
            "eta": eta,
            "diffuse_reflectance": rho,
            "specular_reflectance": spec,
            "nonlinear": nonlinear,
        }
    ).double()
    with torch.no_grad():
        ours = model.eval(wi, wo)
    rel = float(((ours - theirs).abs() / theirs.abs().clamp_min(1e-6)).max())
    print(f"roughplastic {dist} alpha={alpha} eta={eta}: max relative difference {rel:.2e}")
    assert rel < ROUGH_RTOL, rel


@pytest.mark.reference
def test_smooth_limit_matches_mitsuba_plastic_diffuse():
    """``smooth=True`` against Mitsuba's ``plastic`` (its delta coat is not in ``eval``: the
    diffuse part, away from the mirror pairs where our sharp coat lobe lives)."""
    wi, wo = _pairs(200, seed=11)
    keep = (wi + wo * torch.tensor([1.0, 1.0, -1.0], dtype=F64)).norm(dim=-1) > 0.3
    wi, wo = wi[keep], wo[keep]
    params = {"type": "plastic", "int_ior": 1.5, "ext_ior": 1.0}
    params["diffuse_reflectance"] = {"type": "rgb", "value": [0.2, 0.5, 0.8]}
    theirs = _mitsuba_eval(params, wi, wo)
    model = RoughPlastic("ggx", roughness=1e-3, eta=1.5, diffuse_reflectance=(0.2, 0.5, 0.8), smooth=True).double()
    with torch.no_grad():
        ours = model.eval(wi, wo)
    rel = float(((ours - theirs).abs() / theirs).max())
    print(f"plastic (smooth limit): max relative difference {rel:.2e}")
    assert rel < SMOOTH_RTOL, rel


def test_coat_integrals_conserve_energy_and_reach_fresnel():
    # a near-smooth coat reflects F and transmits 1 - F; a rough one loses a little to the
    # single-scattering masking (up to 40% at grazing incidence), so R + T < 1
    mu = torch.tensor([0.2, 0.6, 1.0], dtype=F64)
    eta = torch.tensor(1.5, dtype=F64)
    for dist in ("ggx", "beckmann"):
        smooth = torch.tensor(1e-3, dtype=F64)
        r, t = coat_albedo(dist, smooth, eta, mu), coat_transmittance(dist, smooth, eta, mu)
        torch.testing.assert_close(r, dielectric_fresnel(mu, eta), rtol=1e-3, atol=1e-4)
        torch.testing.assert_close(t, 1.0 - dielectric_fresnel(mu, eta), rtol=1e-3, atol=1e-4)
        rough = torch.tensor(0.8, dtype=F64)
        total = coat_albedo(dist, rough, eta, mu) + coat_transmittance(dist, rough, eta, mu)
        assert bool((total < 1.0).all()) and bool((total > 0.5).all()), total


def test_white_plastic_loses_energy_as_mitsuba_does():
    # Mitsuba's linear diffuse weight with its coarse internal reflectance and the coat's
    # single-scattering loss: a white plastic reflects about 0.8 at normal incidence, never above 1
    brdf = RoughPlastic("ggx", roughness=0.2, diffuse_reflectance=1.0, eta=1.5).double()
    for th in (0.0, 45.0, 80.0):
        a = half_vector_albedo(brdf, direction(math.radians(th)))
        assert 0.5 < float(a.min()) and float(a.max()) < 1.0, (th, a)


def test_texture_scales_the_diffuse_reflectance():
    wi, wo = _pairs(50, seed=3)
    scale = torch.rand(50, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    for nonlinear in (False, True):
        brdf = RoughPlastic("ggx", roughness=0.3, diffuse_reflectance=(0.6, 0.4, 0.2), nonlinear=nonlinear).double()
        got = textured_eval_local(brdf, wi, wo, scale)
        for k in (0, 17, 49):
            one = RoughPlastic(
                "ggx",
                roughness=0.3,
                diffuse_reflectance=(brdf.diffuse_reflectance * scale[k]).tolist(),
                nonlinear=nonlinear,
            ).double()
            torch.testing.assert_close(got[k], one.eval_local(wi[k], wo[k]), rtol=1e-6, atol=0)


def test_parameters_are_checked_and_created_by_name():
    assert isinstance(create({"type": "rough_plastic", "roughness": 0.2}), RoughPlastic)
    with pytest.raises(ValueRangeError, match=r"RoughPlastic\.roughness"):
        RoughPlastic(roughness=0.0)
    with pytest.raises(ValueRangeError, match=r"RoughPlastic\.eta"):
        RoughPlastic(eta=0.9)
    with pytest.raises(ValueRangeError, match=r"RoughPlastic\.distribution"):
        RoughPlastic("phong")
    brdf = RoughPlastic()
    with pytest.raises(ValueRangeError, match=r"RoughPlastic\.diffuse_reflectance"):
        brdf.diffuse_reflectance = 1.5


def test_band_projection():
    # the generic theta_h projection: the coat alone with the Schlick x Smith quotient of its
    # F0 and alpha is nearly a function of theta_h (Schlick stands in for the dielectric
    # Fresnel), its error falls with J and is below 10% at J = 64; the diffuse base,
    # T(theta_i) T(theta_o), is not a function of theta_h, so with it the error stays near
    # 0.4 at any J (the coat of such a material is what theta_h bands edit)
    eta = 1.49 / 1.000277
    coat_q = SchlickFresnel(SmithQuotient("ggx", 0.3), f0=((eta - 1) / (eta + 1)) ** 2)
    errs = {}
    for rho, q in ((0.0, coat_q), (0.5, SmithQuotient("ggx", 0.3))):
        brdf = RoughPlastic("ggx", roughness=0.3, eta=eta, diffuse_reflectance=rho)
        for J in (8, 64):
            basis = BandBasis("theta_h", J)
            fac = Factored1D(basis, coefficients=project(brdf, basis, q), quotient=q)
            errs[rho, J] = projection_error(brdf, fac)
    print("rough_plastic band projection errors:", errs)
    assert all(np.isfinite(list(errs.values()))), errs
    assert errs[0.0, 8] > errs[0.0, 64] and errs[0.0, 64] < 0.1, errs
    assert errs[0.5, 8] > errs[0.5, 64] > 0.2, errs
