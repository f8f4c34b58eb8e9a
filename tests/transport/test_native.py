"""The compiled entry kernel (transport/_native.c) against the torch path: exact equality
(the compiled per-vertex steps, which may round differently, are tests/transport/test_vertex.py's)."""

from __future__ import annotations

import math
import warnings
from types import SimpleNamespace

import pytest
import torch

from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.transport import _native
from torch_brdf.transport.polynomial import Mixture, PolynomialSettings, driver, precompute_polynomial
from torch_brdf.transport.polynomial.reduce import (
    NativeEntries,
    _code_fits,
    _exported,
    _local_blocks,
    _reduce,
    _reduce_groups,
    native_bits,
    native_local_blocks,
    tile_accumulator,
)
from torch_brdf.transport.polynomial.tracer import LightHit, PathState, _Entries, _Tracer

LIB = _native.library()
needs_cc = pytest.mark.skipif(LIB is None, reason="no C compiler here: only the torch path runs")


def _equal(a: dict, b: dict) -> None:
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k].dtype == b[k].dtype, k
        assert torch.equal(a[k], b[k]), k


def _sums(g: torch.Generator, n: int, m: int, count_max: int, sizes: dict) -> dict[str, torch.Tensor]:
    """Random per-path sums of one pass group, as ``_reduce(by_path=True)`` returns them, with
    repeated keys (few records) and float64 values of mixed magnitude."""
    d = {k: torch.randint(0, sizes[k], (n,), generator=g) for k in ("rec", "obj", "bounce", "j")}
    d["w"] = torch.randint(-1, sizes["w"], (n,), generator=g)
    pool = torch.randint(0, count_max + 1, (6, m), generator=g).to(torch.int8)  # a few multisets
    pool[0, -1] = count_max
    d["counts"] = pool[torch.randint(0, 6, (n,), generator=g)]
    s = torch.randn(n, 3, generator=g, dtype=torch.float64) * 10.0 ** torch.randint(-6, 6, (n, 1), generator=g)
    d["sum"], d["sq"] = s, s * s
    return d


@needs_cc
@pytest.mark.parametrize(
    ("m", "count_max", "rec"),
    [(7, 3, 50), (20, 4, 300), (40, 3, 20)],  # 64-bit keys; 128-bit keys; unique(dim=0) multiset order
)
def test_tile_reduction_equals_torch(m, count_max, rec):
    g = torch.Generator().manual_seed(m)
    sizes = {"rec": rec, "obj": 3, "bounce": 5, "j": 4, "w": 2, "path": 1}
    bits = native_bits(sizes, m, count_max)
    assert bits is not None
    groups = [_sums(g, 4000, m, count_max, sizes) for _ in range(3)]
    cat = {k: torch.cat([x[k] for x in groups]) for k in groups[0]}
    cat["weight"] = cat.pop("sum")
    want = _reduce(cat, sizes, by_path=False)
    got = _reduce_groups(LIB, groups, m, bits)
    assert len(got["rec"]) < 12000  # keys repeat: sums over several rows in their order
    assert _code_fits(m, count_max) == (m != 40)
    _equal(want, got)


def _tile(kind: str, m: int, bits: list[int]):
    """A tile's accumulator: the default (per-record sums, :class:`_native.TileSums`) or the
    sorted runs it falls back to (an :class:`_native.Accumulator`, merged at the end)."""
    if kind == "runs":
        return _native.Accumulator(LIB, m, 6, bits[:-1] + [0])
    tile = tile_accumulator(LIB, m, bits)
    assert isinstance(tile, _native.TileSums)
    return tile


@needs_cc
@pytest.mark.parametrize("kind", ["records", "runs"])
@pytest.mark.parametrize(("m", "count_max"), [(7, 3), (40, 3)])  # last-object-first and first-object-first order
def test_tile_runs_merge_like_the_sort(m, count_max, kind):
    """A tile's sums from its pass groups (summed record by record, or their sorted runs merged;
    ``reduce_into``) equal those of the same rows re-sorted (``_reduce_groups``): same keys, same
    sums in the same order."""
    g = torch.Generator().manual_seed(3 + m)
    sizes = {"rec": 4, "obj": 2, "bounce": 3, "j": 2, "w": 1, "path": 4}  # few keys: ~16 terms per sum
    bits = native_bits(sizes, m, count_max)
    tile, exports = _tile(kind, m, bits), []
    rows = _sums(g, 9501, m, count_max, sizes)  # one pool of multisets: keys repeat across groups
    for a, n in ((0, 3000), (3000, 1), (3001, 0), (3001, 2500), (5501, 4000)):  # an empty group among them
        acc = _native.Accumulator(LIB, m, 3, bits)
        d = {k: v[a : a + n] for k, v in rows.items()}
        acc.add_sums(d["rec"], d["obj"], d["bounce"], d["j"], d["w"], d["counts"], d["sum"])
        if n:
            exports.append(_exported(acc))
        acc.reduce_into(not _code_fits(m, acc.max_count()), tile)
    got = _exported(tile)
    assert len(got["rec"]) < 1000  # keys repeat across the runs
    _equal(_reduce_groups(LIB, exports, m, bits), got)


@needs_cc
@pytest.mark.parametrize("kind", ["records", "runs"])
@pytest.mark.parametrize(("m", "count_max", "adaptive"), [(7, 3, False), (7, 2, True), (40, 3, False)])
def test_blocks_equal_torch(m, count_max, adaptive, kind):
    """A tile's sparse blocks made in the kernel (from its per-record sums, or from its merged
    runs' export) equal _local_blocks of its exported sums: same records, terms (both multiset
    orders), keys, means and variances (a NaN and negative variances among them), with one spp
    or an spp per record."""
    g = torch.Generator().manual_seed(11 + m)
    sizes = {"rec": 40, "obj": 3, "bounce": 5, "j": 6, "w": 3, "path": 4}
    bits = native_bits(sizes, m, count_max)
    tile = _tile(kind, m, bits)
    rows = _sums(g, 6000, m, count_max, sizes)
    rows["sum"][5, 1] = float("nan")
    for a in (0, 2000, 4500):
        acc = _native.Accumulator(LIB, m, 3, bits)
        d = {k: v[a : a + 2000] for k, v in rows.items()}
        acc.add_sums(d["rec"], d["obj"], d["bounce"], d["j"], d["w"], d["counts"], d["sum"])
        acc.reduce_into(not _code_fits(m, acc.max_count()), tile)
    bases = [None, SimpleNamespace(size=6), None]  # J: 1 without a basis, else the basis's size
    spp = torch.randint(1, 5, (sizes["rec"],), generator=g) if adaptive else 3
    red = _exported(tile)
    want = _local_blocks(red, bases, spp[red["rec"]][:, None] if adaptive else spp)
    got = native_local_blocks(tile, bases, spp)
    assert len(want) == len(got) > 5
    for w_, g_ in zip(want, got, strict=True):
        assert sorted(w_) == sorted(g_)
        for k in w_:
            assert w_[k].dtype == g_[k].dtype and w_[k].shape == g_[k].shape, k
            assert torch.equal(w_[k].nan_to_num(7.0), g_[k].nan_to_num(7.0)), k
    assert any(bool(b["vals"].isnan().any()) for b in got)


def _state(g, tracer: _Tracer, n: int, sizes: dict) -> PathState:
    """A random path state: slots and weights at both banded levels (zeros, a NaN and huge
    values among them), counts of earlier diffuse-equivalent vertices, throughputs."""
    m = tracer.num_objects
    st = PathState.start(torch.randperm(3 * n, generator=g)[:n], torch.randint(0, m, (n,), generator=g), m, False)
    st.raw = torch.rand(n, 3, generator=g) * 4
    st.A_i = torch.randint(0, sizes["j"], (n, 2), generator=g)
    st.A_w = torch.randn(n, 2, 3, generator=g) * (torch.rand(n, 2, 1, generator=g) > 0.2)
    st.A_w[3, 0, 1] = float("nan")
    two_level = tracer.level2 is not None
    st.B_i = torch.randint(0, sizes["w"], (n, 2), generator=g) if two_level else torch.full((n, 1), -1)
    st.B_w = torch.randn(n, st.B_i.shape[1], 3, generator=g).abs() * 1e3
    st.counts = torch.zeros(n, m, dtype=torch.int8)  # up to two earlier diffuse-equivalent vertices
    for _ in range(2):
        st.counts[torch.arange(n), torch.randint(0, m, (n,), generator=g)] += torch.randint(0, 2, (n,), generator=g).to(
            torch.int8
        )
    return st


def _hit(g, tracer: _Tracer, n: int, k: int) -> LightHit:
    kk = torch.sort(torch.randperm(n, generator=g)[:k]).values
    wl = torch.nn.functional.normalize(torch.randn(k, 3, generator=g), dim=-1)
    wo = torch.nn.functional.normalize(torch.randn(k, 3, generator=g), dim=-1)
    wl[:, 2], wo[:, 2] = wl[:, 2].abs(), wo[:, 2].abs()
    ob = torch.randint(0, tracer.num_objects, (k,), generator=g)
    lw = torch.rand(k, 3, generator=g) * (torch.rand(k, 1, generator=g) > 0.1)
    return LightHit(kk, wl, wo, ob, tracer.editable[ob], lw)


@needs_cc
@pytest.mark.parametrize("series", ["64,1,1,1", "16,8,1,1"])
def test_entries_equal_torch(series):
    """The tracer's entries at every kind of vertex (eye, banded second bounce, diffuse
    equivalents with fixed objects), made in the kernel and in torch, reduce to the same sums."""
    sc = cornell_box_glossy(8)
    sc.objects[sc.object_id("short_box")].editable = False  # a fixed object: its full BRDF
    T = precompute_polynomial(sc, PolynomialSettings(series, spp=1, guides=False), progress=False, processes=1)
    tracer = _Tracer(sc, T.bases, T.series, Mixture(), list(sc.lights))
    g = torch.Generator().manual_seed(7)
    n, p = 300, 200
    rec = torch.arange(3 * n)  # ray ids: record r % p, path r // p
    banded = [b for b in T.bases if b is not None]
    sizes = {
        "rec": p,
        "obj": tracer.num_objects,
        "bounce": T.series.bounces + 1,
        "j": max(b.size for b in banded),
        "w": sum(b.second_size for b in banded) if T.series.two_level else 1,
        "path": 3 * n // p + 1,
    }
    st = _state(g, tracer, n, sizes)
    bits = native_bits(sizes, tracer.num_objects, T.series.bounces)
    torch_ent, native_ent = _Entries(), NativeEntries(LIB, tracer.num_objects, p, bits)
    for v in (1, 2, 3, 4, 3):
        hit = _hit(g, tracer, n, 250)
        for ent in (torch_ent, native_ent):
            tracer._emit(ent, st, v, hit, None, rec)
    d = torch_ent.cat()
    ray = d.pop("path")
    d["rec"], d["path"] = ray % p, ray // p
    want = _reduce(d, sizes, by_path=True)
    got = native_ent.reduce()
    assert len(got["rec"]) > 500
    _equal(want, got)
    # a tile's sums: the groups' sums added in the kernel equal _reduce_groups of their exports
    tile = tile_accumulator(LIB, tracer.num_objects, bits)
    for _ in range(2):
        native_ent.reduce_into(tile)
    _equal(_reduce_groups(LIB, [got, got], tracer.num_objects, bits), _exported(tile))


@needs_cc
@pytest.mark.parametrize(("series", "group"), [("64,1,1,1", 2), ("16,8,1,1", None)])
def test_precompute_equals_torch_entries(series, group, monkeypatch):
    """The whole precomputation (several pass groups and tiles) gives the same arrays with the
    compiled entries as with the torch entries, on the same paths (both with the compiled
    per-vertex steps; tests/transport/test_vertex.py compares those with the torch steps)."""
    sc = cornell_box_glossy(16)
    settings = PolynomialSettings(series, spp=6, guides=False, tile_rows=8, group=group)
    kw = {"seed": 5, "progress": False, "processes": 1}
    native = precompute_polynomial(sc, settings, **kw).to_arrays()[0]
    monkeypatch.setattr(driver, "library", lambda: None)  # the entries in torch; the tracer keeps its kernel
    plain = precompute_polynomial(sc, settings, **kw).to_arrays()[0]
    assert sorted(native) == sorted(plain)
    for k in native:
        assert native[k].dtype == plain[k].dtype and (native[k] == plain[k]).all(), k


def test_missing_compiler_falls_back_with_one_warning(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(tmp_path))
    monkeypatch.setattr(_native, "_state", {"lib": None, "tried": False, "build_s": 0.0})
    monkeypatch.setattr(_native, "_compiler", lambda: None)
    with pytest.warns(UserWarning, match="torch path") as rec:
        assert _native.library() is None
        assert _native.library() is None
    assert len(rec) == 1
    T = precompute_polynomial(
        cornell_box_glossy(8), PolynomialSettings(spp=2, guides=False), progress=False, processes=1
    )
    assert T.num_entries > 0
    assert not (tmp_path / "native").exists() or not list((tmp_path / "native").glob("*.so"))


@needs_cc
def test_build_is_cached_by_source_hash(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(tmp_path))
    for _ in range(2):
        monkeypatch.setattr(_native, "_state", {"lib": None, "tried": False, "build_s": 0.0})
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert _native.library() is not None
        builds = list((tmp_path / "native").glob("polynomial_*.so"))
        assert len(builds) == 1
    assert _native.build_seconds() == 0.0  # the second process state loaded the cached build
    # another source (or compiler) gets another file: the name is the hash of both
    monkeypatch.setattr(_native, "_state", {"lib": None, "tried": False, "build_s": 0.0})
    monkeypatch.setattr(_native, "_FLAGS", [*_native._FLAGS, "-DTB_VARIANT=1"])
    assert _native.library() is not None
    assert len(list((tmp_path / "native").glob("polynomial_*.so"))) == 2
    assert math.isfinite(_native.build_seconds()) and _native.build_seconds() > 0


@needs_cc
def test_area_light_samples_equal_torch(monkeypatch):
    """Next-event samples of the area light (points on both sides of it, on its plane, far
    away; normals facing anywhere): the same uniforms give the same bits in the kernel."""
    from torch_brdf.transport.pathtrace import sample_light

    sc = cornell_box_glossy(8)
    light = sc.lights[0]
    g = torch.Generator().manual_seed(3)
    n = 5000
    lo, hi = light.triangles.reshape(-1, 3).amin(0), light.triangles.reshape(-1, 3).amax(0)
    pos = (lo + hi) / 2 + (hi - lo).amax() * torch.randn(n, 3, generator=g)  # around and across the light
    pos[:100, 1] = light.triangles[0, 0, 1]  # on the light's plane
    pos[100:200] *= 50
    ng = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    ns = torch.where(torch.rand(n, 1, generator=g) < 0.5, ng, torch.nn.functional.normalize(ng + 0.3, dim=-1))
    fast = _native.area_light_sample(light, pos, ng, ns, torch.Generator().manual_seed(9))
    assert fast is not None
    ls, cos, ok = fast
    want = light.sample(pos, torch.Generator().manual_seed(9))
    for k in ("direction", "distance", "weight", "pdf"):
        assert torch.equal(getattr(ls, k), getattr(want, k)), k
    want_cos = (want.direction * ns).sum(-1)
    assert torch.equal(cos, want_cos)
    assert torch.equal(ok, (want_cos > 0) & ((want.direction * ng).sum(-1) > 0) & (want.pdf > 0))
    assert 0 < int(ok.sum()) < n
    # sample_light takes the kernel and draws the same random numbers as the torch path
    a = sample_light(sc, light, pos, ng, ns, torch.Generator().manual_seed(4))
    monkeypatch.setenv(_native.ENV_VAR, "0")
    b = sample_light(sc, light, pos, ng, ns, torch.Generator().manual_seed(4))
    assert torch.equal(a[1], b[1]) and torch.equal(a[3], b[3]) and a[2] == b[2]
    assert _native.area_light_sample(light, pos.double(), ng.double(), ns.double(), g) is None  # float64: torch


@needs_cc
def test_eye_rays_equal_camera_rays_bit_for_bit():
    """The compiled eye rays are Camera.rays_through's, bit for bit, on rotated
    cameras and image sizes that are not powers of two; NaN offsets are refused by name."""
    from torch_brdf.errors import ValueRangeError
    from torch_brdf.scene.camera import Camera

    g = torch.Generator().manual_seed(7)
    cams = [
        cornell_box_glossy(64).camera,
        Camera((0.3, 1.2, -2.0), (0.1, 0.2, 0.7), (0.1, 1.0, 0.2), 47.0, 300, 170),
        Camera((5.0, -3.0, 2.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 12.5, 97, 311),
    ]
    for cam in cams:
        P = cam.width * cam.height
        pixels = torch.randperm(P, generator=g)[:3000].sort().values
        rec = torch.randint(0, 3000, (50000,), generator=g)
        off = torch.rand(50000, 2, generator=g, dtype=torch.float64)
        pix = pixels[rec]
        o0, d0 = cam.rays_through((pix % cam.width).double() + off[:, 1], (pix // cam.width).double() + off[:, 0])
        o1, d1 = driver.eye_rays(cam, pixels, rec, off)
        assert o1.dtype == d1.dtype == torch.float32
        assert torch.equal(o0, o1) and torch.equal(d0, d1)
        # the float64 raster step too (float32 rounding would hide its last bits)
        x, y = (pix % cam.width).double() + off[:, 1], (pix // cam.width).double() + off[:, 0]
        tan_half = math.tan(math.radians(cam.fov_deg) / 2)
        sx = (2 * x / cam.width - 1) * tan_half * (cam.width / cam.height)
        sy = (1 - 2 * y / cam.height) * tan_half
        local = torch.empty(rec.numel(), 3, dtype=torch.float64)
        assert LIB.tb_camera_local(
            rec.numel(), rec.data_ptr(), pixels.data_ptr(), cam.width, cam.height, off.data_ptr(), tan_half,
            cam.width / cam.height, local.data_ptr(),
        ) == 0  # fmt: skip
        assert torch.equal(local, torch.stack((sx, sy, torch.ones_like(sx)), -1))
    off[123, 1] = float("nan")
    with pytest.raises(ValueRangeError, match="raster position 123 "):
        driver.eye_rays(cams[1], pixels, rec, off)


@needs_cc
def test_pixel_offsets_are_torch_rand():
    """The eye rays' offsets drawn by the kernel are torch.rand's numbers, and the
    generator goes on as torch's would (the paths draw from it next)."""
    for n in (1, 311, 70000):
        g1, g2 = torch.Generator().manual_seed(n), torch.Generator().manual_seed(n)
        torch.rand(5, generator=g1), torch.rand(5, generator=g2)
        assert torch.equal(driver._offsets(n, g1), torch.rand(n, 2, generator=g2, dtype=torch.float64))
        assert torch.equal(torch.rand(9, generator=g1), torch.rand(9, generator=g2))
