"""Stratified eye-vertex samples (:class:`EyeStrata`, ``LobeMixture(stratified=True)``): one
path per cell, uniform points (so unbiased estimates), exact bookkeeping, the same tensors in
expectation, and less noise where the integrand is smooth (an area light's highlight)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from torch_brdf.errors import ValueRangeError
from torch_brdf.render.polynomial import PolynomialRenderer
from torch_brdf.scene.lights import AreaLight
from torch_brdf.transport.polynomial import EyeStrata, LobeMixture, PolynomialSettings, precompute_polynomial
from torch_brdf.transport.polynomial.driver import eye_strata

from .test_polynomial import check_oracle, glossy_box


def _strata(count: int, pixels: int) -> EyeStrata:
    """Every path of ``pixels`` pixels of ``count`` paths each, pixel-major."""
    s = torch.arange(count).repeat(pixels)
    key = torch.arange(pixels).repeat_interleave(count) * 7919 + 11
    return EyeStrata(s, torch.full_like(s, count), key)


@pytest.mark.parametrize(("count", "m", "n"), [(64, 8, 8), (12, 3, 4), (7, 2, 3), (1, 1, 1), (1024, 32, 32)])
def test_square_puts_one_path_in_each_cell(count, m, n, gen):
    pixels = 5
    st = _strata(count, pixels)
    ux = torch.rand(st.sample.numel(), generator=gen, dtype=torch.float64)
    uy = torch.rand(st.sample.numel(), generator=gen, dtype=torch.float64)
    x, y = st.square(ux, uy, salt=3)
    assert bool(((x >= 0) & (x < 1) & (y >= 0) & (y < 1)).all())
    cells = m * n
    for p in range(pixels):
        rows = slice(p * count, p * count + cells)
        cx, cy = (x[rows] * m).floor().long(), (y[rows] * n).floor().long()
        assert sorted((cy * m + cx).tolist()) == list(range(cells)), p
        # the jitter inside the cell is the path's own uniform
        torch.testing.assert_close(x[rows] * m - cx, ux[rows], rtol=0, atol=1e-12)
        torch.testing.assert_close(y[rows] * n - cy, uy[rows], rtol=0, atol=1e-12)
        rest = slice(p * count + cells, (p + 1) * count)  # beyond m x n: the uniforms as drawn
        assert torch.equal(x[rest], ux[rest]) and torch.equal(y[rest], uy[rest])
    # pixels (and salts) visit the cells in different orders
    c0 = (x[:count] * m).floor() + m * (y[:count] * n).floor()
    c1 = (x[count : 2 * count] * m).floor() + m * (y[count : 2 * count] * n).floor()
    x2, y2 = st.square(ux, uy, salt=4)
    c2 = (x2[:count] * m).floor() + m * (y2[:count] * n).floor()
    if cells > 1:
        assert not torch.equal(c0, c1) and not torch.equal(c0, c2)


def _light() -> AreaLight:
    """A quad of two unequal triangles and a third small one (area shares 0.5, 0.3, 0.2)."""
    v = torch.tensor(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [1.6, 0, 0], [1.6, 1, 0], [2.0, 0, 0]], dtype=torch.float32
    )
    # triangles: (0,1,2) area 0.5, (1,4,5) area 0.3, (4,6,5) area 0.2
    f = torch.tensor([[0, 1, 2], [1, 4, 5], [4, 6, 5]])
    return AreaLight(v, f, (1.0, 1.0, 1.0))


def test_light_uniforms_are_uniform_on_the_light_and_cut_its_noise(gen):
    """Per pixel, the mean of a smooth function over the stratified points estimates its mean
    over the light without bias (against the analytic value; z-test over 3000 pixels) and
    with far less spread than independent points; each triangle gets its area's share of
    every pixel's 64 paths (+-1)."""
    light = _light()
    count, pixels = 64, 3000
    st = _strata(count, pixels)
    u = torch.rand(st.sample.numel(), 3, generator=gen, dtype=torch.float64)
    us = st.light_uniforms(light, u, salt=2)
    assert bool(((us >= 0) & (us < 1)).all())
    k = torch.searchsorted(light.cdf, us[:, 0].contiguous(), right=True).clamp_max(2)
    share = torch.stack([(k.view(pixels, count) == t).sum(1) for t in range(3)], 1).double() / count
    # the first triangle's share ends on a cell border (4 of 8 columns): exactly 32 paths per
    # pixel; the others' borders cut a column, whose 8 cells split at random (unbiased)
    assert bool((share[:, 0] == 0.5).all())
    assert float((share - share.new_tensor([0.5, 0.3, 0.2])).abs().max()) <= 8 / count + 1e-12
    torch.testing.assert_close(share.mean(0), share.new_tensor([0.5, 0.3, 0.2]), rtol=0, atol=0.005)
    fine = torch.rand(2_000_000, 3, generator=gen, dtype=torch.float64)  # a brute-force mean of f
    want = _f(light, fine).mean()
    for uu, name in ((us, "stratified"), (u, "independent")):
        per_pixel = _f(light, uu).view(pixels, count).mean(1)
        z = (per_pixel.mean() - want) / (per_pixel.std() / math.sqrt(pixels))
        assert abs(float(z)) < 4.5, (name, float(z))
    spread = [float(_f(light, uu).view(pixels, count).mean(1).std()) for uu in (us, u)]
    assert spread[0] < 0.35 * spread[1], spread  # measured 0.25: 16x less variance


def _f(light, u):
    p, _ = light.sample_points(u.shape[0], u=u, dtype=torch.float64)
    return p[:, 0] ** 2 + p[:, 1]


def test_mixture_stratify_keeps_the_density(gen):
    """Stratified mixture uniforms are still samples of the mixture's density (E[1/pdf] = 2 pi
    per object, E[1{cone}/pdf] = the cone's solid angle), and each pixel's components get
    their weights' share of its paths."""
    mix = LobeMixture(0.4, ((0.3, 200.0), (0.3, 2000.0)), ids=(1,), stratified=True)
    count, pixels = 64, 4000
    st = _strata(count, pixels)
    n = st.sample.numel()
    wo = torch.tensor([[0.3, 0.1, 0.948683]], dtype=torch.float32).expand(n, 3)
    wo = wo / wo.norm(dim=-1, keepdim=True)
    oid = torch.randint(0, 3, (pixels,), generator=gen).repeat_interleave(count)  # one object per pixel
    u = mix.stratify(torch.rand(n, 3, generator=gen), st, oid)
    assert u.dtype == torch.float32 and bool(((u >= 0) & (u < 1)).all())
    wi, pdf = mix.sample(wo, u, oid)
    mirror = torch.tensor([-0.3, -0.1, 0.948683])
    mirror = mirror / mirror.norm()
    inv = ((pdf > 0).double() / pdf.double().clamp_min(1e-300)).view(pixels, count)
    first = torch.arange(pixels) * count
    for o in range(3):
        m = oid[first] == o
        checks = [(inv, 2 * math.pi)]
        for angle in (0.05, 0.2):
            cone = ((wi @ mirror) > math.cos(angle)).view(pixels, count)
            checks.append((cone * inv, 2 * math.pi * (1 - math.cos(angle))))
        for k, (x, want) in enumerate(checks):  # z-test over the pixels' means (independent)
            per_pixel = x[m].mean(1)
            z = (per_pixel.mean() - want) / (per_pixel.std() / math.sqrt(int(m.sum())))
            assert abs(float(z)) < 4.5, (o, k, float(per_pixel.mean()), want)
    # per pixel of object 1: the cosine lobe (x < 0.4) takes columns 0-2 of 8 (24 paths) and
    # a share of column 3's 8: 24-32 paths, 25.6 on average; independent uniforms spread wider
    mine = oid[first] == 1
    diffuse = (u[:, 0] < 0.4).view(pixels, count).sum(1)[mine]
    assert int(diffuse.min()) >= 24 and int(diffuse.max()) <= 32, (diffuse.min(), diffuse.max())
    assert float(diffuse.double().mean()) == pytest.approx(25.6, abs=0.15)


def test_tensors_equal_explicit_path_tracer_when_stratified(gen):
    """The exactness oracle with stratified eye samples (and MIS)."""
    sc = glossy_box()
    paths: dict = {}
    spp = 4
    mix = LobeMixture(0.4, ((0.3, 200.0), (0.3, 2000.0)), stratified=True)
    T = precompute_polynomial(
        sc,
        PolynomialSettings("8,1,1,1", spp=spp, mixture=mix, tile_rows=sc.camera.height),
        seed=3,
        progress=False,
        paths=paths,
    )
    assert T.meta["mixture"][-1] == "stratified"
    check_oracle(sc, T, paths, spp, gen, repeats=2)
    plain = precompute_polynomial(
        sc,
        PolynomialSettings("8,1,1,1", spp=spp, mixture=dataclasses.replace(mix, stratified=False)),
        seed=3,
        progress=False,
    )
    assert not torch.equal(T.blocks[0].values, plain.blocks[0].values)  # the samples did move


def test_stratified_equals_unstratified_in_expectation_with_less_noise():
    """Same scene, independent seeds: the glossy wall's mean radiance under the default
    material and under a sharp edit agrees between the stratified and the independent eye
    samples (Welch t-test over per-seed means, |t| < 4.5); per pixel, the stratified frames
    scatter less about the mean of all runs under the sharp edit."""
    sc = glossy_box(8)
    back = sc.object_id("back")
    mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
    edit = {"type": "blinn_phong", "kd": (0.05, 0.04, 0.03), "ks": (0.5, 0.6, 0.7), "exponent": 1000.0}
    stats, frames = {}, {}
    for strat in (False, True):
        rows, fr = [], []
        for seed in range(10):
            T = precompute_polynomial(
                sc,
                PolynomialSettings("8,1,1", spp=16, mixture=LobeMixture(stratified=strat)),
                seed=200 + seed,
                progress=False,
            )
            wall = T.guides.object_id == back
            R = PolynomialRenderer(T, mats, dtype=torch.float64)
            a = R.evaluate()
            R.set_material("back", edit)
            b = R.evaluate()
            rows.append(torch.stack([a[wall].mean(), b[wall].mean()]))
            fr.append(b[wall])
        stats[strat], frames[strat] = torch.stack(rows), torch.stack(fr)
    a, b = stats[False], stats[True]
    se = (a.var(0) / a.shape[0] + b.var(0) / b.shape[0]).sqrt()
    t = (a.mean(0) - b.mean(0)) / se
    assert bool((t.abs() < 4.5).all()), (t, a.mean(0), b.mean(0))
    mean = (frames[False].mean(0) + frames[True].mean(0)) / 2
    spread = {k: float(((f - mean) ** 2).mean().sqrt()) for k, f in frames.items()}
    assert spread[True] < spread[False], spread


def test_stratified_spp_map_runs(gen):
    """An adaptive spp map: each pixel's cells follow its own count."""
    sc = glossy_box(8)
    spp = torch.tensor([1, 2, 5, 9], dtype=torch.long).repeat(16)[:64].view(8, 8)
    T = precompute_polynomial(
        sc, PolynomialSettings("4,1", spp=spp, mixture=LobeMixture(stratified=True)), seed=1, progress=False
    )
    img = PolynomialRenderer(T, {o.name: sc.materials[o.material] for o in sc.objects if o.editable}).evaluate()
    assert bool(torch.isfinite(img).all()) and float(img.sum()) > 0


def test_complementary_shares_cover_the_cells_of_one_stratification(gen):
    """``share=(k, of)``: the paths of ``of`` shares of ``count`` paths each take every cell of
    the ``of * count`` grid exactly once (two 32-spp shares: the 8 x 8 grid of 64 spp, not two
    5 x 6 grids); a share's own paths are one per cell too."""
    count, pixels, m = 32, 4, 8
    cells: list[list[int]] = [[] for _ in range(pixels)]
    for k in range(2):
        mix = LobeMixture(stratified=True, share=(k, 2))
        s = torch.arange(count).repeat(pixels)
        key = torch.arange(pixels).repeat_interleave(count) * 7919 + 11
        st = eye_strata(mix, s, torch.full_like(s, count), key)
        u = torch.rand(2, s.numel(), generator=gen, dtype=torch.float64)
        x, y = st.square(u[0], u[1], salt=5)
        c = ((y * m).floor() * m + (x * m).floor()).long()
        for p in range(pixels):
            cells[p] += c[p * count : (p + 1) * count].tolist()
    for p in range(pixels):
        assert sorted(cells[p]) == list(range(64)), p
    single = eye_strata(LobeMixture(stratified=True), s, torch.full_like(s, count), key)
    assert torch.equal(single.count, torch.full_like(s, count)) and torch.equal(single.sample, s)


def test_shares_reach_the_tracer_and_the_key():
    """Two shares of the same seed trace different eye samples (the driver passes the share),
    record it in the settings key, and a share needs stratification."""
    sc = glossy_box(8)
    out = []
    for k in range(2):
        mix = LobeMixture(stratified=True, share=(k, 2))
        T = precompute_polynomial(sc, PolynomialSettings("4,1", spp=4, mixture=mix), seed=9, progress=False)
        assert T.meta["mixture"][-1] == ["share", k, 2]
        out.append(T)
    assert not torch.equal(out[0].blocks[0].values, out[1].blocks[0].values)
    assert LobeMixture(stratified=True).spec()[-1] == "stratified"  # one share: the key as before
    for bad in ({"share": (1, 2)}, {"share": (2, 2), "stratified": True}, {"share": (0, 0), "stratified": True}):
        with pytest.raises(ValueRangeError, match="share"):
            LobeMixture(**bad)
