"""Multibounce polynomial tensors: exact bookkeeping, storage, resume, extremes."""

from __future__ import annotations

import math

import pytest
import torch

from torch_brdf.brdf import create
from torch_brdf.brdf.bands import Factored1D
from torch_brdf.errors import FileFormatError, SceneError, ValueRangeError
from torch_brdf.render.polynomial import PolynomialRenderer
from torch_brdf.scene.builtin import cornell_box
from torch_brdf.transport import polynomial as poly
from torch_brdf.transport.pathtrace import PathTraceSettings, material_brdfs, path_trace
from torch_brdf.transport.polynomial import (
    Mixture,
    ObjectBasis,
    PolynomialSettings,
    PolynomialTensors,
    Series,
    driver,
    precompute_polynomial,
)


def glossy_box(res=12, fixed_box=True):
    """Cornell box, Blinn-Phong back wall; the short box fixed with a glossy BRDF of its own."""
    sc = cornell_box(res)
    sc.materials["glossy"] = {"type": "blinn_phong", "kd": 0.2, "ks": 0.6, "exponent": 100.0}
    sc.materials["fixed_gloss"] = {"type": "blinn_phong", "kd": 0.3, "ks": 0.4, "exponent": 20.0}
    sc.objects[sc.object_id("back")].material = "glossy"
    if fixed_box:
        box = sc.objects[sc.object_id("short_box")]
        box.material, box.editable = "fixed_gloss", False
    return sc


# -- the exactness oracle --------------------------------------------------------------------
def _oracle(sc, T, paths, c, c_hat, d, spp):
    """Re-evaluate every recorded light sample with explicit BRDFs: Factored1D(c) at the eye
    vertex, Factored1D(c_hat) at a banded second vertex, d/pi at diffuse-equivalent vertices,
    the scene BRDF at fixed objects (already in ``raw``)."""
    brdfs = material_brdfs(sc)
    p = T.height * T.width
    img = torch.zeros(p, 3, dtype=torch.float64)

    def f(level, ob, wi, wo):
        out = torch.zeros(ob.numel(), 3, dtype=torch.float64)
        for o in ob.unique().tolist():
            m = ob == o
            b = T.bases[o]
            if b is None:
                out[m] = brdfs[o].eval_local(wi[m], wo[m]).double()
            else:
                basis = b.band_basis() if level == 1 else b.second_basis()
                coef = c[o] if level == 1 else c_hat[o]
                for k, q in enumerate(b.quotients()):  # one layer, or two with Fresnel (Eq. 32)
                    part = coef[k * basis.J : (k + 1) * basis.J]
                    out[m] += Factored1D(basis, part, q).eval_local(wi[m].double(), wo[m].double())
        return out

    for r in paths["rows"]:  # one row per light sample batch
        v = int(r["bounce"][0])
        val = r["raw"].double()
        if v == 1:
            val = val * f(1, r["ob"], r["wl"], r["wo"])
        else:
            val = val * f(1, r["m1"], r["wi1"], r["wo1"])
            if T.series.two_level:
                val = val * (f(2, r["ob"], r["wl"], r["wo"]) if v == 2 else f(2, r["m2"], r["wi2"], r["wo2"]))
        objs = r["objs"]
        for k in range(objs.shape[1]):
            col = objs[:, k]
            fac = torch.where((col >= 0)[:, None], d[col.clamp_min(0)] / math.pi, torch.ones(1, 3, dtype=torch.float64))
            val = val * fac
        img.index_add_(0, r["rec"] % p, val)
    return (img / spp + T.emission.double().T).reshape(T.height, T.width, 3)


@pytest.mark.parametrize("series,fresnel", [("8,1,1,1", False), ("8,4,1", False), ("8,4,1", True)])
def test_tensors_equal_explicit_path_tracer_on_the_same_paths(series, fresnel, gen):
    sc = glossy_box()
    paths: dict = {}
    spp = 4
    over = {"back": {"fresnel": True}} if fresnel else None
    T = precompute_polynomial(
        sc,
        PolynomialSettings(series, spp=spp, bases=over, tile_rows=sc.camera.height),
        seed=3,
        progress=False,
        paths=paths,
    )
    assert T.bases[T.object_id("back")].fresnel == fresnel
    check_oracle(sc, T, paths, spp, gen)


def check_oracle(sc, T, paths, spp, gen, repeats=3):
    """The tensors at ``repeats`` random coefficients equal :func:`_oracle` on the same paths."""
    assert paths["rows"]
    R = PolynomialRenderer(T, dtype=torch.float64)
    for _ in range(repeats):  # coefficients that were not known at precomputation
        c, c_hat, d = {}, {}, torch.zeros(len(sc.objects), 3, dtype=torch.float64)
        for m, b in enumerate(T.bases):
            if b is None:
                continue
            c[m] = torch.rand(b.size, 3, generator=gen, dtype=torch.float64)
            c_hat[m] = torch.rand(b.second_size, 3, generator=gen, dtype=torch.float64)
            d[m] = torch.rand(3, generator=gen, dtype=torch.float64)
            R.set_coefficients(m, c[m], d=d[m], c_hat=c_hat[m] if T.series.two_level else None)
        with torch.no_grad():
            want = _oracle(sc, T, paths, c, c_hat, d, spp)
        got = R.evaluate()
        scale = want.abs().amax()
        assert float(scale) > 0
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6 * float(scale))


def test_per_bounce_images_sum_and_direct_only(gen):
    sc = glossy_box()
    T = precompute_polynomial(sc, PolynomialSettings("8,1,1", spp=2), seed=0, progress=False)
    R = PolynomialRenderer(T, {o.name: sc.materials[o.material] for o in sc.objects if o.editable})
    parts = R.evaluate(per_bounce=True)
    assert len(parts) == 4
    torch.testing.assert_close(sum(parts[1:], parts[0]), R.evaluate())
    direct = PolynomialRenderer(T, {o.name: sc.materials[o.material] for o in sc.objects if o.editable}, max_bounces=1)
    torch.testing.assert_close(direct.evaluate(), parts[0] + parts[1])
    with pytest.raises(ValueRangeError):
        PolynomialRenderer(T, max_bounces=4)


# -- unbiasedness against the plain path tracer ------------------------------------------------
def test_lambert_scene_matches_path_tracer():
    """All objects Lambertian with one band each: the polynomial at c = albedo/pi, d = albedo
    estimates exactly what the path tracer estimates (different sampling, same integral)."""
    sc = cornell_box(8)
    spp = 256
    T = precompute_polynomial(sc, PolynomialSettings("1,1,1", spp=spp), seed=1, progress=False)
    mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
    img = PolynomialRenderer(T, mats, dtype=torch.float64).evaluate()
    ref = path_trace(sc, PathTraceSettings(spp=spp, max_bounces=3), seed=2, progress=False).double()
    # rows 0-1 see the light itself, whose few jittered hits dominate the noise: compare the rest.
    # Two seeds of each estimator differ by ~0.5% in the mean of these 48 pixels x 256 paths.
    img, ref = img[2:], ref[2:]
    rel = float((img.mean() - ref.mean()).abs() / ref.mean())
    assert rel < 0.02, rel
    for half in (slice(0, 4), slice(4, 8)):  # red left wall, green right wall
        a, b = img[:, half].mean((0, 1)), ref[:, half].mean((0, 1))
        assert torch.allclose(a, b, rtol=0.05), (a, b)


# -- storage, checkpoints ------------------------------------------------------------------------
def test_save_load_roundtrip_and_float16(tmp_path):
    sc = glossy_box()
    T = precompute_polynomial(sc, PolynomialSettings("8,4,1", spp=2), seed=0, progress=False)
    back = PolynomialTensors.load(T.save(tmp_path / "t.npz"))
    R1, R2 = PolynomialRenderer(T), PolynomialRenderer(back)
    torch.testing.assert_close(R1.evaluate(), R2.evaluate(), rtol=0, atol=0)
    half = PolynomialTensors.load(T.save(tmp_path / "h.npz", storage="float16"))
    a, b = R1.evaluate(), PolynomialRenderer(half).evaluate()
    assert float(((a - b).abs() / a.abs().clamp_min(1e-3)).max()) < 2e-3
    assert (tmp_path / "h.npz").stat().st_size < (tmp_path / "t.npz").stat().st_size
    raw = bytearray((tmp_path / "t.npz").read_bytes())
    raw[len(raw) // 3] ^= 0x55
    (tmp_path / "bad.npz").write_bytes(bytes(raw))
    with pytest.raises(FileFormatError):
        PolynomialTensors.load(tmp_path / "bad.npz")


def test_interrupted_run_resumes_bit_exactly(tmp_path, monkeypatch):
    sc = glossy_box()
    # processes=1: the monkeypatch below counts tile calls in this process
    kw = dict(settings=PolynomialSettings(series="8,1,1", spp=3, tile_rows=4), seed=5, progress=False, processes=1)
    full = precompute_polynomial(sc, **kw)
    calls = {"n": 0}
    real = driver._tile_entries

    def flaky(*a, **k):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(driver, "_tile_entries", flaky)
    with pytest.raises(KeyboardInterrupt):
        precompute_polynomial(sc, checkpoint=tmp_path, **kw)
    assert len(list(tmp_path.glob("tile*.npz"))) == 1
    calls["n"] = -100
    resumed = precompute_polynomial(sc, checkpoint=tmp_path, **kw)
    assert calls["n"] == -100 + 2  # the finished tile was not traced again
    assert len(resumed.blocks) == len(full.blocks)
    for a, b in zip(full.blocks, resumed.blocks, strict=True):
        assert torch.equal(a.values, b.values) and torch.equal(a.pixels, b.pixels) and torch.equal(a.terms, b.terms)
    assert torch.equal(full.emission, resumed.emission)


def test_deterministic_and_tiling_independent_structure():
    sc = glossy_box()
    a = precompute_polynomial(sc, PolynomialSettings("8,1", spp=2), seed=9, progress=False)
    b = precompute_polynomial(sc, PolynomialSettings("8,1", spp=2), seed=9, progress=False)
    assert all(torch.equal(x.values, y.values) for x, y in zip(a.blocks, b.blocks, strict=True))
    assert a.meta["rays"]["closest"] > 0 and a.meta["rays"]["shadow"] > 0


def _entries(T) -> dict:
    """Every stored entry of a record by what it means: (object, bounce, pixel, j, the term's
    (w, *counts)) -> (values, variances), independent of how the terms are numbered."""
    out = {}
    for blk in T.blocks:
        tt = T.terms[blk.bounce]
        terms = [(int(tt.w[t]), *tt.counts[t].tolist()) for t in blk.terms.tolist()]
        Z, P = blk.terms.numel(), blk.pixels.numel()
        for e, k in enumerate(blk.index.tolist()):
            key = (blk.object_id, blk.bounce, int(blk.pixels[k % P]), k // (Z * P), terms[(k // P) % Z])
            assert key not in out
            out[key] = (blk.values[:, e].tolist(), blk.variance[:, e].tolist())
    return out


def test_terms_are_numbered_in_one_canonical_order_without_moving_entries():
    """Each bounce's terms are numbered once every tile is in, ascending (w, c_M-1, ...,
    c_0), the order the tiles' blocks already hold them in: every block's term ids and entry
    indices are increasing as the tiles left them, whatever the tiling."""
    sc = glossy_box(16)
    a = precompute_polynomial(sc, PolynomialSettings("8,2,1,1", spp=3, tile_rows=3), seed=4, progress=False)
    b = precompute_polynomial(
        sc, PolynomialSettings("8,2,1,1", spp=3, tile_rows=3), seed=4, progress=False, processes=1
    )
    for n, tt in a.terms.items():
        rows = [(w, *reversed(c)) for w, c in zip(tt.w.tolist(), tt.counts.tolist(), strict=True)]
        assert rows == sorted(set(rows)), n  # canonical and distinct
    assert len({blk.object_id for blk in a.blocks}) > 1 and max(blk.bounce for blk in a.blocks) == 4
    for blk in a.blocks:
        assert bool((blk.terms[1:] > blk.terms[:-1]).all()) and bool((blk.index[1:] > blk.index[:-1]).all())
    assert _entries(a) == _entries(b)  # forked tiles or one process: the same record


def test_numbering_re_sorts_a_block_whose_terms_are_out_of_canonical_order():
    """A block in another order (multiset codes too wide for 62 bits keep the rows' own order)
    gets increasing ids and its entries re-sorted with them, meaning unchanged."""
    from torch_brdf.transport.polynomial.reduce import TermNumbering

    tw = torch.tensor([-1, -1, 0])
    tc = torch.tensor([[0, 1], [1, 0], [0, 0]], dtype=torch.int8)  # forward order: c_0 most significant
    Z, P = 3, 2
    key = torch.tensor([(j * Z + z) * P + p for j in range(2) for z in range(Z) for p in range(P)])
    vals = torch.arange(3 * key.numel(), dtype=torch.float32).reshape(3, -1)
    block = {"head": torch.tensor([0, 2, 2]), "upix": torch.tensor([0, 1]), "tw": tw, "tc": tc,
             "key": key, "vals": vals, "var": vals + 0.5}  # fmt: skip
    numbering = TermNumbering(2, 2)
    numbering.add([block], torch.tensor([10, 11]))
    terms, (blk,) = numbering.finish()
    assert terms[1].size == 0 and terms[2].w.tolist() == [-1, -1, 0]
    assert terms[2].counts.tolist() == [[1, 0], [0, 1], [0, 0]]  # c_1 most significant
    assert blk.terms.tolist() == [0, 1, 2] and blk.pixels.tolist() == [10, 11]
    assert bool((blk.terms[1:] > blk.terms[:-1]).all()) and bool((blk.index[1:] > blk.index[:-1]).all())
    got = {}
    for e, k in enumerate(blk.index.tolist()):
        t = int(blk.terms[(k // P) % Z])
        got[(k // (Z * P), (int(terms[2].w[t]), *terms[2].counts[t].tolist()), int(blk.pixels[k % P]))] = (
            blk.values[:, e].tolist(), blk.variance[:, e].tolist())  # fmt: skip
    want = {}
    for e, k in enumerate(key.tolist()):
        z = (k // P) % Z
        want[(k // (Z * P), (int(tw[z]), *tc[z].tolist()), 10 + k % P)] = (
            vals[:, e].tolist(),
            (vals[:, e] + 0.5).tolist(),
        )
    assert got == want


# -- series, plans, input errors -----------------------------------------------------------------
def test_series_parsing_and_rules():
    assert Series.parse("64,1,1,1").bands == (64, 1, 1, 1)
    assert Series.parse((64, 16)).two_level and not Series.parse("128,1,1,1").two_level
    for bad in ("", "1,8", "64,16,4", "0,1", "a,b"):
        with pytest.raises(ValueRangeError):
            Series.parse(bad)


def test_plan_follows_materials():
    sc = glossy_box()
    plan = poly.plan_bases(sc, Series.parse("64,16,1"))
    names = [o.name for o in sc.objects]
    assert plan[names.index("short_box")] is None and plan[names.index("light")] is None
    assert plan[names.index("left")].J == 1 and plan[names.index("left")].second == 1
    back = plan[names.index("back")]
    assert back.J == 64 and back.second == 16 and back.spacing == "lobe:100"
    over = poly.plan_bases(sc, Series.parse("64,1"), {"left": {"J": 8, "spacing": "sqrt"}})
    assert over[names.index("left")].J == 8
    with pytest.raises(SceneError):
        poly.plan_bases(sc, Series.parse("64,1"), {"nope": {"J": 2}})
    with pytest.raises(SceneError):
        poly.plan_bases(sc, Series.parse("64,1"), {"short_box": {"J": 2}})
    with pytest.raises(SceneError, match="unknown key\\(s\\) \\['zzz'\\]"):  # was a bare TypeError
        poly.plan_bases(sc, Series.parse("64,1"), {"left": {"zzz": 1}})
    with pytest.raises(SceneError, match="must be a table"):
        poly.plan_bases(sc, Series.parse("64,1"), {"left": 8})
    with pytest.raises(ValueRangeError, match=r"basis override left\.J must be <= 4096"):  # as --bases
        poly.plan_bases(sc, Series.parse("64,1"), {"left": {"J": 10**9}})
    with pytest.raises(ValueRangeError):
        ObjectBasis(J=8, variable="theta_i")


def test_mixture_pdf_integrates_to_one_and_matches_samples(gen):
    mix = Mixture()
    wo = torch.tensor([[0.3, 0.1, 0.948683]]).expand(200000, 3)
    wo = wo / wo.norm(dim=-1, keepdim=True)
    u = torch.rand(200000, 3, generator=gen, dtype=torch.float64)
    wi, pdf = mix.sample(wo.double(), u)
    valid = pdf > 0
    # E[1/pdf] over the hemisphere = 2 pi (solid angle) for the part of the mass above it
    est = float((valid.double() / pdf.clamp_min(1e-300)).mean())
    assert est == pytest.approx(2 * math.pi, rel=0.03)
    torch.testing.assert_close(mix.pdf(wi[valid], wo.double()[valid]), pdf[valid])


# -- extremes ----------------------------------------------------------------------------------
@pytest.mark.parametrize("series", ["4", "4,1,1,1,1,1"])
def test_extremes_finite(series):
    sc = glossy_box(8)
    T = precompute_polynomial(sc, PolynomialSettings(series, spp=2), seed=0, progress=False)
    R = PolynomialRenderer(T)
    for mat in (
        {"type": "lambert", "albedo": 0.0},
        {"type": "lambert", "albedo": 1.0},
        {"type": "blinn_phong", "kd": 0.0, "ks": 1.0, "exponent": 1e4},
    ):
        for o, b in zip(T.object_names, T.bases, strict=True):
            if b is not None:
                R.set_material(o, mat)
        img = R.evaluate()
        assert bool(torch.isfinite(img).all())
        R.freeze("back")
        torch.testing.assert_close(R(), img, rtol=1e-4, atol=1e-5 * float(img.abs().max()) + 1e-12)
    with pytest.raises(SceneError):
        R.set_material("short_box", {"type": "lambert", "albedo": 0.5})


def test_bad_input():
    sc = glossy_box(8)
    with pytest.raises(ValueRangeError):
        precompute_polynomial(sc, PolynomialSettings("4,1", spp=0), progress=False)
    T = precompute_polynomial(sc, PolynomialSettings("4,1", spp=1), seed=0, progress=False)
    R = PolynomialRenderer(T)
    with pytest.raises(ValueRangeError):
        R.set_coefficients("back", torch.full((4, 3), float("nan")))
    with pytest.raises(SceneError):
        R.set_material("nope", create("lambert"))
    with pytest.raises(ValueRangeError):
        R.stream()


def test_fresnel_layers_follow_f0():
    """A Fresnel-layered object (Eq. 31-32): f0 = 1 renders the BRDF as given, lower f0 dims
    normal incidence more than grazing angles, and f0 outside [0, 1] is refused."""
    sc = glossy_box(8)
    T = precompute_polynomial(
        sc, PolynomialSettings("8,1", spp=2, bases={"back": {"fresnel": True}}), seed=0, progress=False
    )
    plain = precompute_polynomial(sc, PolynomialSettings("8,1", spp=2), seed=0, progress=False)
    mat = {"type": "blinn_phong", "kd": 0.0, "ks": 1.0, "exponent": 50.0}
    R, P = PolynomialRenderer(T, dtype=torch.float64), PolynomialRenderer(plain, dtype=torch.float64)
    R.set_material("back", mat)
    P.set_material("back", mat)
    torch.testing.assert_close(R.evaluate(), P.evaluate(), rtol=1e-6, atol=1e-9)
    R.set_material("back", mat, f0=0.04)
    dim = R.evaluate()
    assert float(dim.sum()) < float(P.evaluate().sum())
    with pytest.raises(ValueRangeError):
        R.set_material("back", mat, f0=1.5)
    with pytest.raises(ValueRangeError):
        P.set_material("back", mat, f0=0.5)


@pytest.mark.parametrize("points", [None, 16])
def test_environment_lit_scene_bookkeeping_is_exact(points, gen):
    """The teatray (environment map; a fixed floor): NEE to the map itself or to its K median-cut
    point lights; same exactness oracle."""
    from torch_brdf.scene.builtin import teatray

    sc = teatray(10)
    paths: dict = {}
    T = precompute_polynomial(
        sc,
        PolynomialSettings("8,1,1", spp=2, env_point_lights=points, tile_rows=10),
        seed=1,
        progress=False,
        paths=paths,
    )
    R = PolynomialRenderer(T, dtype=torch.float64)
    c, c_hat, d = {}, {}, torch.zeros(len(sc.objects), 3, dtype=torch.float64)
    for m, b in enumerate(T.bases):
        if b is not None:
            c[m] = torch.rand(b.size, 3, generator=gen, dtype=torch.float64)
            d[m] = torch.rand(3, generator=gen, dtype=torch.float64)
            R.set_coefficients(m, c[m], d=d[m])
    with torch.no_grad():
        want = _oracle(sc, T, paths, c, c_hat, d, 2)
    assert float(want.sum()) > 0
    torch.testing.assert_close(R.evaluate(), want, rtol=1e-4, atol=1e-6 * float(want.abs().max()))


@pytest.mark.parametrize("m", [3, 40])  # 40 objects of counts <= 3: codes too wide, unique(dim=0)
def test_canonical_term_rows_by_code_and_by_rows_agree_with_a_sort(m, gen):
    from torch_brdf.transport.polynomial.reduce import _canonical_rows

    w = torch.randint(-1, 3, (200,), generator=gen)
    c = torch.randint(0, 4, (200, m), generator=gen)
    rows, inv = _canonical_rows(w, c)
    want = sorted({(int(a), *reversed(b)) for a, b in zip(w.tolist(), c.tolist(), strict=True)})
    assert [(r[0], *reversed(r[1:])) for r in rows.tolist()] == want
    assert torch.equal(rows[inv], torch.cat([w[:, None], c], 1))
