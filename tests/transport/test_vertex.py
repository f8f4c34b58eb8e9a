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
from torch_brdf.transport.polynomial import Mixture, ObjectBasis, Series, precompute_polynomial
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


@needs_cc
@pytest.mark.parametrize("series", ["64,1,1,1", "16,8,1,1"])
def test_precompute_close_to_torch_path(series, monkeypatch):
    """The whole precomputation with the compiled steps against the torch steps: the same random
    numbers make the same paths, so renders at random coefficients agree to float32 rounding on
    (almost) every pixel; a path whose last-ulp difference lands it on the other side of a band
    or geometry edge may change a few pixels, and the oracles check those paths exactly."""
    sc = cornell_box_glossy(16)
    kw = {"spp": 6, "seed": 5, "progress": False, "processes": 1, "guides": False, "tile_rows": 8}
    fused = precompute_polynomial(sc, series, **kw)
    monkeypatch.setenv(_native.ENV_VAR, "0")
    plain = precompute_polynomial(sc, series, **kw)
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
