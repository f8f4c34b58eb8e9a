"""The GI tracer's wavefront in reused buffers (transport/polynomial/vertex.py Wavefront): its
random numbers are torch.rand's bit for bit, and whole precomputations through it equal the
per-step kernel calls it replaces bit for bit (same arithmetic, same stream, same order)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.scene.lights import DirectionalLight
from torch_brdf.transport import _native
from torch_brdf.transport.polynomial import Mixture, ObjectBasis, Series, precompute_polynomial
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
    t = precompute_polynomial(sc, series, spp=5, seed=3, progress=False, processes=1, guides=False, **kw)
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
