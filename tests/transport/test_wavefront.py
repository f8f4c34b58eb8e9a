"""The GI tracer's wavefront in reused buffers (transport/polynomial/vertex.py Wavefront): its
random numbers are torch.rand's bit for bit, and whole precomputations through it equal the
per-step kernel calls it replaces bit for bit (same arithmetic, same stream, same order)."""

from __future__ import annotations

import ctypes
import ctypes.util

import numpy as np
import pytest
import torch

from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.scene.lights import DirectionalLight
from torch_brdf.transport import _native
from torch_brdf.transport.polynomial import Mixture, ObjectBasis, PolynomialSettings, Series, precompute_polynomial
from torch_brdf.transport.polynomial import vertex as vx
from torch_brdf.transport.polynomial.tracer import _Tracer

LIB = _native.library()
needs_cc = pytest.mark.skipif(
    LIB is None, reason="no compiled kernel (no C compiler, or TORCH_BRDF_NATIVE=0): only the torch path runs"
)


def _words(state: torch.Tensor) -> torch.Tensor:
    """The bytes of a generator state that tb_rand reads and writes (left, next, the 624 words)."""
    return torch.cat([state[8:12], state[16 : 24 + 8 * 624]])


@needs_cc
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("skip", [0, 1, 623, 700])
def test_rand_equals_torch(dtype, skip):
    """tb_rand draws torch.rand's numbers from a generator's state bytes and leaves the state
    torch would, across the engine's 624-word refills, after any number of earlier draws."""
    assert vx.c_rand_matches(LIB)
    g = torch.Generator().manual_seed(7 + skip)
    torch.rand(skip, generator=g)
    state = g.get_state()
    for n in (0, 1, 311, 624, 625, 2000):
        want = torch.rand(n, generator=g, dtype=dtype)
        got = torch.empty(n, dtype=dtype)
        LIB.tb_rand(_native.ptr(state), n, int(dtype == torch.float64), _native.ptr(got))
        assert torch.equal(got, want)
        assert torch.equal(_words(state), _words(g.get_state()))
    h = torch.Generator()
    h.set_state(state)  # the bytes written back are a state torch takes and goes on from
    assert torch.equal(torch.rand(100, generator=h), torch.rand(100, generator=g))


def _arrays(sc, series, **kw):
    t = precompute_polynomial(
        sc, PolynomialSettings(series, spp=5, guides=False, **kw), seed=3, progress=False, processes=1
    )
    return t.to_arrays()[0], t.meta["rays"]


@needs_cc
@pytest.mark.parametrize(
    ("series", "fixed", "light_samples"), [("64,1,1,1", False, 1), ("16,8,1,1", True, 2), ("16,4,1", False, 1)]
)
def test_precompute_equals_per_step_kernel(series, fixed, light_samples, monkeypatch):
    """Whole precomputations (one and two band levels, a fixed Lambertian object, two eye light
    samples) through the wavefront equal those of the per-step calls bit for bit."""
    sc = cornell_box_glossy(12)
    if fixed:
        sc.objects[sc.object_id("short_box")].editable = False  # a fixed Lambertian: fixed_f in the kernel
    runs = {"wavefront": 0}
    make = vx.Wavefront.make

    def counted(vk):
        wf = make(vk)
        runs["wavefront"] += wf is not None
        return wf

    monkeypatch.setattr(vx.Wavefront, "make", staticmethod(counted))
    a, ra = _arrays(sc, series, light_samples=light_samples)
    assert runs["wavefront"] > 0
    monkeypatch.setattr(vx.Wavefront, "make", staticmethod(lambda vk: None))
    b, rb = _arrays(sc, series, light_samples=light_samples)
    assert ra == rb and sorted(a) == sorted(b)
    for k in a:
        assert np.array_equal(a[k], b[k]), k


@needs_cc
def test_wavefront_only_where_the_kernel_knows_every_step():
    """Lights other than area lights and fixed BRDFs the kernel does not know keep the per-step
    path (torch fills those rows there)."""
    sc = cornell_box_glossy(8)
    s = Series.parse("16,1,1,1")

    def tracer(scene, lights):
        bases = [ObjectBasis(1, "theta_h", "uniform", "one", False, 1) if o.editable else None for o in scene.objects]
        return _Tracer(scene, bases, s, Mixture(), lights)

    assert vx.Wavefront.make(vx.VertexKernel.make(tracer(sc, list(sc.lights)))) is not None
    sun = DirectionalLight(torch.tensor([0.2, 1.0, 0.3]), 2.0)
    assert vx.Wavefront.make(vx.VertexKernel.make(tracer(sc, [*sc.lights, sun]))) is None
    sc.materials["fixed_gloss"] = {"type": "blinn_phong", "kd": 0.3, "ks": 0.4, "exponent": 20.0}
    sc.objects[sc.object_id("tall_box")].editable = False
    sc.objects[sc.object_id("tall_box")].material = "fixed_gloss"
    assert vx.Wavefront.make(vx.VertexKernel.make(tracer(sc, list(sc.lights)))) is None


def _powf():
    libm = ctypes.CDLL(ctypes.util.find_library("m"))
    libm.powf.restype, libm.powf.argtypes = ctypes.c_float, [ctypes.c_float, ctypes.c_float]
    return libm.powf


@needs_cc
@pytest.mark.parametrize("exponent", [200.0, 12.0, 3000.0])
def test_mixture_pdf_without_negligible_lobe_terms_is_exact(exponent):
    """tb_mixture leaves the Blinn lobe's pdf term out where it is below a quarter ulp of the
    cosine term; its pdf and cos / pdf still equal, bit for bit, the full float32 formula with
    libm's powf (sampler.py Mixture.pdf in the kernel's operation order), recomputed here in
    numpy float32 from the directions the kernel drew."""
    g = torch.Generator().manual_seed(int(exponent))
    n = 40000
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    wo[:, 2] = wo[:, 2].abs()
    wo[: n // 8, 2] *= 1e-3  # grazing: small cosine terms
    wo = torch.nn.functional.normalize(wo, dim=-1).contiguous()
    u = torch.rand(n, 3, generator=g)
    # directions near the horizon (the disk's rim): tiny cosine terms, where the lobe's term counts
    u[n // 2 :, 1] = 1 - torch.rand(n - n // 2, generator=g) * torch.logspace(-8, -2, n - n // 2)
    m = Mixture(exponent=exponent)
    nn = float(m.exponent)
    mix = [m.diffuse, 1 - m.diffuse, nn, (nn + 1.0) / (2 * np.pi)]
    wi, pdf, cosw = torch.empty(n, 3), torch.empty(n), torch.empty(n)
    ok = torch.empty(n, dtype=torch.uint8)
    LIB.tb_mixture(
        n, _native.ptr(u), _native.ptr(wo), *map(ctypes.c_float, mix), *map(_native.ptr, (wi, pdf, cosw, ok))
    )
    f = np.float32
    d, gl, ex, nm = (f(x) for x in mix)
    w, o = wi.numpy(), wo.numpy()
    s = w + o
    ln = np.sqrt(np.maximum((s[:, 0] * s[:, 0] + s[:, 1] * s[:, 1]) + s[:, 2] * s[:, 2], f(0)))
    big = ln > f(1.1920929e-07)
    h = np.where(big[:, None], s / np.where(big, ln, f(1))[:, None], np.array([0, 0, 1], np.float32))
    coh = np.abs((o[:, 0] * h[:, 0] + o[:, 1] * h[:, 1]) + o[:, 2] * h[:, 2])
    coh = np.where(coh < f(1e-12), f(1e-12), coh)
    ch = np.maximum(h[:, 2], f(0))
    powf = _powf()
    pw = np.array([powf(float(max(c, f(1.17549435e-38))), float(ex)) for c in ch], np.float32)
    ph = np.where(ch > 0, nm * pw, f(0))
    cz = np.maximum(w[:, 2], f(0))
    p = d * (cz * f(1 / np.pi)) + (gl * ph) / (f(4) * coh)
    p = np.where(w[:, 2] > 0, p, f(0))
    good = (p > 0) & (w[:, 2] > 0) & (o[:, 2] > 0)
    want_cosw = np.where(good, w[:, 2] / np.maximum(p, f(1e-30)), f(0))
    assert np.array_equal(pdf.numpy(), p.astype(np.float32))
    assert np.array_equal(cosw.numpy(), want_cosw.astype(np.float32))
    assert np.array_equal(ok.numpy().astype(bool), good)
