"""The compiled per-vertex steps of the GI tracer (transport/polynomial/vertex.py) against the
torch steps they replace. C's scalar libm and torch's vectorised math may round differently in
the last ulp, so values are compared with the float32 tolerance and discrete outcomes (band
slots, which side of a horizon) only away from their edges."""

from __future__ import annotations

import math

import pytest
import torch

from tests.conftest import RTOL
from torch_brdf.brdf.bands._geometry import half_and_diff
from torch_brdf.frame import polar_angle
from torch_brdf.render.polynomial import PolynomialRenderer
from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.transport import _native
from torch_brdf.transport.pathtrace import shading_frame
from torch_brdf.transport.polynomial import Mixture, ObjectBasis, PolynomialSettings, Series, precompute_polynomial
from torch_brdf.transport.polynomial.tracer import _Tracer
from torch_brdf.transport.polynomial.vertex import VertexKernel, quotient_code

LIB = _native.library()
needs_cc = pytest.mark.skipif(
    LIB is None, reason="no compiled kernel (no C compiler, or TORCH_BRDF_NATIVE=0): only the torch path runs"
)
TOL = {"rtol": RTOL[torch.float32], "atol": 1e-6}


def _unit(g, n):
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)


def _tracer(series="16,4,1,1", fresnel_back=True, quotient="cook_torrance"):
    """A glossy box with a fixed Lambertian object (in the kernel) and a fixed Blinn-Phong one
    (its BRDF from torch), theta_h and theta_d bands, a Fresnel layer."""
    sc = cornell_box_glossy(8)
    sc.materials["fixed_gloss"] = {"type": "blinn_phong", "kd": 0.3, "ks": 0.4, "exponent": 20.0}
    for name in ("short_box", "tall_box"):
        sc.objects[sc.object_id(name)].editable = False
    sc.objects[sc.object_id("tall_box")].material = "fixed_gloss"
    s = Series.parse(series)
    bases = []
    for o in sc.objects:
        if not o.editable:
            bases.append(None)
        elif o.name == "back":
            bases.append(ObjectBasis(16, "theta_h", "lobe:100", "one", fresnel_back, s.second))
        elif o.name == "floor":
            bases.append(ObjectBasis(8, "theta_d", "uniform", quotient, False, min(s.second, 8)))
        else:
            bases.append(ObjectBasis(1, "theta_h", "uniform", "one", False, 1))
    tr = _Tracer(sc, bases, s, Mixture(), list(sc.lights))
    vk = VertexKernel.make(tr)
    assert vk is not None
    return sc, tr, vk


@needs_cc
def test_frame_equals_torch():
    g = torch.Generator().manual_seed(1)
    n = 4000
    d, ng = _unit(g, n), _unit(g, n)
    ns = torch.where(torch.rand(n, 1, generator=g) < 0.3, -ng, torch.nn.functional.normalize(ng + 0.4 * _unit(g, n)))
    _, _, vk = _tracer()
    g2, s2, fr, wo = vk.frame(d, ng, ns)
    want_g, want_s, frame, want_wo = shading_frame(d, ng, ns)
    torch.testing.assert_close(g2, want_g, **TOL)
    torch.testing.assert_close(s2, want_s, **TOL)
    torch.testing.assert_close(fr, torch.cat((frame.s, frame.t, frame.n), -1), **TOL)
    torch.testing.assert_close(wo, want_wo, **TOL)


@needs_cc
def test_area_light_samples_and_shadow_rays_equal_torch():
    """The same uniforms as AreaLight.sample; shadow rays as Scene.visible casts them."""
    sc, _, vk = _tracer()
    light = sc.lights[0]
    g = torch.Generator().manual_seed(3)
    n = 5000
    lo, hi = light.triangles.reshape(-1, 3).amin(0), light.triangles.reshape(-1, 3).amax(0)
    pos = (lo + hi) / 2 + (hi - lo).amax() * torch.randn(n, 3, generator=g)
    ng = _unit(g, n)
    ns = torch.where(torch.rand(n, 1, generator=g) < 0.5, ng, torch.nn.functional.normalize(ng + 0.3))
    d, w, cos, cast, kk = vk.light(light, pos, ng, ns, torch.Generator().manual_seed(9))
    ls = light.sample(pos, torch.Generator().manual_seed(9))
    torch.testing.assert_close(d, ls.direction, **TOL)
    torch.testing.assert_close(w, ls.weight, rtol=1e-4, atol=1e-4 * float(ls.weight.abs().max()))
    want_cos = (ls.direction * ns).sum(-1)
    torch.testing.assert_close(cos, want_cos, **TOL)
    ok = (want_cos > 0) & ((ls.direction * ng).sum(-1) > 0) & (ls.pdf > 0)
    vis = torch.zeros(n, dtype=torch.bool)
    vis[ok] = sc.visible(pos[ok], ng[ok], ls.direction[ok], ls.distance[ok])
    got = torch.zeros(n, dtype=torch.bool)
    got[kk] = True
    clear = (want_cos.abs() > 1e-4) & ((ls.direction * ng).sum(-1).abs() > 1e-4)  # away from either horizon
    assert 0 < int(vis.sum()) < n and abs(cast - int(ok.sum())) <= int((~clear).sum())
    assert torch.equal(got[clear], vis[clear])


@needs_cc
@pytest.mark.parametrize("quotient", ["one", "distribution", "microfacet", "cook_torrance", "ashikhmin_shirley"])
def test_band_slots_and_quotients_equal_torch(quotient):
    """Both levels, theta_h and theta_d bands, a Fresnel layer, and a fixed object (filled in by
    torch with its BRDF); slots compared away from band edges."""
    sc, tr, vk = _tracer(quotient=quotient)
    assert quotient_code(tr.level1.per_object[sc.object_id("floor")][1][0]) is not None
    g = torch.Generator().manual_seed(5)
    n = 6000
    wi, wo = _unit(g, n), _unit(g, n)
    wi[: n // 2, 2], wo[: n // 3, 2] = wi[: n // 2, 2].abs(), wo[: n // 3, 2].abs()
    oid = torch.randint(0, len(sc.objects), (n,), generator=g)
    for level, layers in ((1, tr.level1), (2, tr.level2)):
        with torch.no_grad():
            idx, w = vk.layers(level, oid, wi, wo)
            want_idx, want_w = layers(oid, wi, wo)
        h, _, theta_d = half_and_diff(wi, wo)
        gamma = torch.zeros(n)
        near = torch.zeros(n, dtype=torch.bool)
        for o, spec in enumerate(layers.per_object):
            if spec is None:
                continue
            m = oid == o
            gamma = polar_angle(h) if spec[0].variable == "theta_h" else theta_d
            edges = spec[0].edges.float()
            near |= m & ((gamma[:, None] - edges).abs() < 1e-5).any(-1)
        assert int(near.sum()) < n // 100
        assert torch.equal(idx[~near], want_idx[~near])
        torch.testing.assert_close(w, want_w, rtol=RTOL[torch.float32], atol=1e-6 * float(want_w.abs().max()))
        for name in ("short_box", "tall_box"):  # fixed objects' BRDFs: Lambert in the kernel, Blinn-Phong by torch
            assert bool((w[oid == sc.object_id(name), 0] != 0).any())
    with torch.no_grad():
        torch.testing.assert_close(vk.fixed_f(oid, wi, wo), tr._fixed_f(oid, wi, wo), **TOL)


@needs_cc
def test_mixture_equals_torch():
    g = torch.Generator().manual_seed(2)
    n = 20000
    wo = _unit(g, n)
    wo[: n - 100, 2] = wo[: n - 100, 2].abs()
    u = torch.rand(n, 3, generator=g)
    _, _, vk = _tracer()
    wi, pdf, cosw, ok = vk.mixture(u, wo)
    want_wi, want_pdf = Mixture().sample(wo, u)
    torch.testing.assert_close(wi, want_wi, rtol=1e-4, atol=2e-5)
    clear = want_wi[:, 2].abs() > 1e-4
    torch.testing.assert_close(pdf[clear], want_pdf[clear], rtol=1e-3, atol=1e-6)  # cos^200: 200 x the ulps
    want_ok = (want_pdf > 0) & (want_wi[:, 2] > 0) & (wo[:, 2] > 0)
    assert torch.equal(ok[clear], want_ok[clear]) and 0 < int(ok.sum()) < n
    want_cosw = torch.where(want_ok, want_wi[:, 2] / want_pdf.clamp_min(1e-30), 0.0)
    torch.testing.assert_close(cosw[clear], want_cosw[clear], rtol=1e-3, atol=1e-6)


def _ulps(got: torch.Tensor, want: torch.Tensor) -> torch.Tensor:
    """|got - want| in units of the float32 spacing at want (float64 want; 2^-149 at least)."""
    a = want.abs().to(torch.float32).to(torch.float64)
    e = torch.frexp(a.clamp_min(2.0**-126)).exponent.to(torch.float64)
    return (got.to(torch.float64) - want).abs() / torch.pow(2.0, e - 24).clamp_min(2.0**-149)


@needs_cc
def test_sincos_against_float64_over_its_range():
    """The kernel's own cos / sin (sincos_fd in _native.c: the mixture's angles, no
    libm call) against float64 over the mixture's angles [-pi/4, 2 pi]: random angles, every
    float within 4096 ulps of each multiple of pi/4 (the quadrant edges and the zeros) and tiny
    angles. Stated bound 0.5 ulp (float64 arithmetic rounded once, without FMA, so the AVX2 and
    the baseline copies give the same bits); measured here with a margin for ties."""
    g = torch.Generator().manual_seed(9)
    parts = [torch.rand(1 << 21, generator=g, dtype=torch.float64) * (2.25 * math.pi) - math.pi / 4]
    step = torch.arange(-4096, 4097, dtype=torch.int32)
    for k in range(-1, 9):
        c = torch.tensor([k * math.pi / 4], dtype=torch.float32)
        if k == 0:
            continue
        parts.append((c.view(torch.int32) + step).view(torch.float32).double())
    tiny = torch.tensor([0.0, 2.0**-149, 1e-30, 1e-8, 3e-4, -1e-8], dtype=torch.float64)
    x = torch.cat([*parts, tiny, -tiny]).to(torch.float32)
    x = x[(x >= -math.pi / 4 - 1e-3) & (x <= 2 * math.pi + 1e-3)].contiguous()
    c, s = torch.empty_like(x), torch.empty_like(x)
    LIB.tb_sincos(x.numel(), _native.ptr(x), _native.ptr(c), _native.ptr(s))
    xd = x.double()
    err = torch.maximum(_ulps(c, torch.cos(xd)), _ulps(s, torch.sin(xd)))
    assert float(err.max()) <= 0.5 + 2.0**-10, f"max error {float(err.max())} ulp at x = {float(x[err.argmax()])}"


@needs_cc
@pytest.mark.parametrize("exponent", [1.0, 200.0, 1e4])
def test_mixture_against_float64_at_the_extremes(exponent):
    """tb_mixture (its own sin/cos, libm's logf/expm1f/powf) against the float64 torch mixture:
    uniforms at 0, 2^-24 and 1 - 2^-24 in every coordinate, grazing and upright wo, exponents
    up to 1e4. Directions within a few float32 eps; the pdf at the kernel's direction within
    the float32 rounding of its terms (the half vector: ~100 ulps near wi = -wo; cos^n: 2n)."""
    g = torch.Generator().manual_seed(3)
    ends = torch.tensor([0.0, 2.0**-24, 0.25, 0.5, 0.75, 1 - 2.0**-24])
    grid = torch.cartesian_prod(ends, ends, ends)
    u = torch.cat([grid, torch.rand(20000, 3, generator=g)]).to(torch.float32)
    wo = _unit(g, u.shape[0])
    wo[:, 2] = wo[:, 2].abs()
    z = torch.tensor([1e-4, 1e-3, 0.05, 1.0])[torch.arange(u.shape[0]) % 4]  # grazing to upright
    wo[: u.shape[0] // 2] = torch.cat([(1 - z * z).sqrt()[:, None] * torch.tensor([[0.6, 0.8]]), z[:, None]], 1)[
        : u.shape[0] // 2
    ]
    wo = wo.contiguous()
    _, _, vk = _tracer()
    mix = Mixture(diffuse=0.7, exponent=exponent)
    vk.mix = [mix.diffuse, 1 - mix.diffuse, exponent, (exponent + 1.0) / (2 * math.pi)]
    wi, pdf, cosw, ok = vk.mixture(u, wo)
    want_wi, _ = mix.sample(wo.double(), u.double())
    torch.testing.assert_close(wi.double()[:, :2], want_wi[:, :2], rtol=0, atol=16 * 2.0**-23)
    # z = sqrt(1 - x^2 - y^2) at the disk's rim (u = 0 or 1): a few eps under the root, sqrt(eps) out
    torch.testing.assert_close(wi.double()[:, 2], want_wi[:, 2], rtol=0, atol=16 * 2.0**-23 + (8 * 2.0**-23) ** 0.5)
    want_pdf = mix.pdf(wi.double(), wo.double())
    up = wi[:, 2] > 1e-3
    torch.testing.assert_close(pdf.double()[up], want_pdf[up], rtol=(2 * exponent + 128) * 2.0**-23, atol=1e-30)
    assert bool(torch.isfinite(pdf).all() and torch.isfinite(cosw).all()) and 0 < int(ok.sum()) < u.shape[0]


@needs_cc
@pytest.mark.parametrize("series", ["64,1,1,1", "16,8,1,1"])
def test_precompute_close_to_torch_path(series, monkeypatch):
    """The whole precomputation with the compiled steps against the torch steps: the same random
    numbers make the same paths, so renders at random coefficients agree to float32 rounding on
    (almost) every pixel; a path whose last-ulp difference lands it on the other side of a band
    or geometry edge may change a few pixels, and the oracles check those paths exactly."""
    sc = cornell_box_glossy(16)
    settings = PolynomialSettings(series, spp=6, guides=False, tile_rows=8)
    kw = {"seed": 5, "progress": False, "processes": 1}
    fused = precompute_polynomial(sc, settings, **kw)
    monkeypatch.setenv(_native.ENV_VAR, "0")
    plain = precompute_polynomial(sc, settings, **kw)
    for k in ("closest", "shadow"):
        assert abs(fused.meta["rays"][k] - plain.meta["rays"][k]) <= 0.01 * plain.meta["rays"][k]
    g = torch.Generator().manual_seed(0)
    ra, rb = PolynomialRenderer(fused, dtype=torch.float64), PolynomialRenderer(plain, dtype=torch.float64)
    for m, b in enumerate(fused.bases):
        if b is not None:
            c, d = (
                torch.rand(b.size, 3, generator=g, dtype=torch.float64),
                torch.rand(3, generator=g, dtype=torch.float64),
            )
            ch = torch.rand(b.second_size, 3, generator=g, dtype=torch.float64) if fused.series.two_level else None
            for r in (ra, rb):
                r.set_coefficients(m, c, d=d, c_hat=ch)
    a, b = ra.evaluate(), rb.evaluate()
    close = ((a - b).abs() <= 1e-4 * b.abs() + 1e-6).all(-1)
    assert float(close.double().mean()) >= 0.97
    assert math.isclose(float(a.sum()), float(b.sum()), rel_tol=1e-2)
