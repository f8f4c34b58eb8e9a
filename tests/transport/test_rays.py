"""The GI rays cast by the compiled kernel (transport/rays.py) against the tracer's embreex path."""

from __future__ import annotations

import pytest
import torch
import trimesh

from torch_brdf.errors import ShapeError, ValueRangeError
from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.scene.raytrace import RayTracer
from torch_brdf.transport import _native
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial
from torch_brdf.transport.rays import NativeRays

_FIELDS = ("t", "object_id", "prim_id", "barycentrics", "position", "geometric_normal", "normal")


def _tracer(workers: int = 1) -> RayTracer:
    """A smooth sphere, a flat box and a floor: both kinds of shading normals, three geometries."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.4)
    ball.apply_translation([-0.4, 0.5, 0.0])
    box = trimesh.creation.box(extents=(0.5, 0.7, 0.5))
    box.apply_translation([0.5, 0.35, 0.1])
    floor = trimesh.creation.box(extents=(3.0, 0.05, 3.0))
    return RayTracer([ball, box, floor], [True, False, False], workers=workers)


def _rays(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    o = torch.rand(n, 3, generator=g) * torch.tensor([3.0, 1.5, 3.0]) - torch.tensor([1.5, 0.0, 1.5])
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return o, d, g


@pytest.fixture(scope="module")
def native():
    if _native.library() is None:
        pytest.skip("no C compiler here (or TORCH_BRDF_NATIVE=0): the tracer's own path runs")
    rt = _tracer()
    rays = NativeRays.make(rt)
    assert rays is not None  # the embreex layout checks pass with the pinned embreex
    return rt, rays


def test_hits_equal_the_tracer(native):
    """Same query on the same scene: ids equal, positions, normals, t and barycentrics to float32
    rounding; misses and hits of all three objects occur."""
    rt, rays = native
    o, d, _ = _rays(20000, 0)
    want = rt.trace(o, d)
    got = rays.trace(o, d)
    assert torch.equal(got.object_id, want.object_id) and torch.equal(got.prim_id, want.prim_id)
    assert set(want.object_id.unique().tolist()) == {-1, 0, 1, 2}
    hit = want.hit
    assert torch.equal(torch.isinf(got.t), ~hit)
    for name in _FIELDS[3:]:
        a, b = getattr(got, name), getattr(want, name)
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5, msg=name)
    torch.testing.assert_close(got.t[hit], want.t[hit], rtol=1e-6, atol=1e-6)
    smooth = want.object_id == 0
    assert not torch.allclose(want.normal[smooth], want.geometric_normal[smooth])  # interpolated there
    flat = hit & ~smooth
    assert torch.equal(got.normal[flat], got.geometric_normal[flat])


def test_hits_are_reused_buffers_and_every_call_is_complete(native):
    """A smaller call after a larger one (the buffers are reused) gives its own rays' hits."""
    rt, rays = native
    o, d, _ = _rays(3000, 1)
    rays.trace(*_rays(5000, 2)[:2])
    got, want = rays.trace(o, d), rt.trace(o, d)
    assert len(got) == 3000 and torch.equal(got.object_id, want.object_id)


def test_shadow_rays_equal_the_tracer(native):
    """Occlusion within t_max (inf included), directions by rows, equals the tracer's."""
    rt, rays = native
    o, d, g = _rays(20000, 3)
    t_max = torch.rand(len(o), generator=g) * 2
    t_max[::5] = float("inf")
    rows = torch.randint(0, len(d), (len(o),), generator=g)
    want = rt.occluded(o, d[rows], t_max)
    assert torch.equal(rays.occluded(o, d, t_max, rows), want)
    assert torch.equal(rays.occluded(o, d[rows], t_max), want)
    assert 0.05 < want.float().mean() < 0.95


def test_bad_rays_are_refused(native):
    _, rays = native
    o, d, _ = _rays(10, 4)
    o[7, 1] = float("nan")
    with pytest.raises(ValueRangeError, match="ray 7"):
        rays.trace(o, d)
    with pytest.raises(ValueRangeError, match="NaN t_max"):
        rays.occluded(d, d, torch.full((10,), float("nan")))
    with pytest.raises(ShapeError):
        rays.occluded(d, d, torch.ones(9))
    with pytest.raises(ValueRangeError, match="outside"):
        rays.occluded(d, d, torch.ones(10), rows=torch.full((10,), 10))
    hits = rays.trace(d.double(), d.double())  # not float32: the tracer's own path
    assert hits.position.dtype == torch.float64


def test_fallbacks(native, monkeypatch):
    """No kernel or no checked embree handle: no NativeRays (a tracer with forked workers gets
    them: the compiled loop casts in the calling process)."""
    rt, _ = native
    assert NativeRays.make(_tracer(workers=2)) is not None
    other = _tracer()
    monkeypatch.setattr(other._kernel, "native", lambda: None)
    assert NativeRays.make(other) is None
    monkeypatch.setenv(_native.ENV_VAR, "0")
    assert NativeRays.make(rt) is None


def test_precompute_with_and_without_the_compiled_rays(monkeypatch):
    """The GI precompute through the compiled rays equals the one through the tracer's embreex
    path (the same hits, so the same tensors, to float32 rounding of the hit points)."""
    if _native.library() is None:
        pytest.skip("no C compiler here")
    sc = cornell_box_glossy(16)
    settings, kw = PolynomialSettings("8,1,1", spp=4), {"seed": 0, "progress": False, "processes": 1}
    calls, trace, occluded = [], NativeRays.trace, NativeRays.occluded
    monkeypatch.setattr(NativeRays, "trace", lambda self, *a: calls.append("t") or trace(self, *a))
    monkeypatch.setattr(NativeRays, "occluded", lambda self, *a: calls.append("o") or occluded(self, *a))
    fast = precompute_polynomial(sc, settings, **kw)
    assert {"t", "o"} <= set(calls)
    monkeypatch.setattr(NativeRays, "make", classmethod(lambda cls, rt: None))
    slow = precompute_polynomial(sc, settings, **kw)
    a, b = fast.to_arrays()[0], slow.to_arrays()[0]
    assert sorted(a) == sorted(b)
    for k in a:
        if a[k].dtype.kind == "f":
            torch.testing.assert_close(torch.from_numpy(a[k]), torch.from_numpy(b[k]), rtol=1e-4, atol=1e-6, msg=k)
        else:
            assert (a[k] == b[k]).all(), k
    assert fast.meta["rays"] == slow.meta["rays"]
