"""Adaptive sampling in the multibounce precomputation: a per-pixel spp map, and light
splitting at the eye vertex.

Tiles are row bands whatever the map; pass s of a tile traces the pixels with more than s
paths. A tile whose pixels all take s paths must be, entry for entry, the same tile of a
uniform run at s (same random numbers); in a tile of mixed spp each pixel is the plain average
over its own paths (unbiased, its variance over its own paths) and the tensors stay exact
polynomials (the oracle re-evaluates every path)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from torch_brdf.errors import ShapeError, ValueRangeError
from torch_brdf.records.polynomial import PolynomialTensors
from torch_brdf.render.polynomial import PolynomialRenderer
from torch_brdf.scene.builtin import cornell_box_glossy, teatray
from torch_brdf.scene.lights import DirectionalLight
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial, spp_map_of

from .test_polynomial import _oracle

SIZE, ROWS = 12, 4
SETTINGS = PolynomialSettings(series="8,1,1", tile_rows=ROWS, guides=False)
RUN = {"seed": 3, "progress": False}


def _band_map(levels: list[int]) -> torch.Tensor:
    """(SIZE, SIZE): row band b (ROWS rows each) at ``levels[b]`` spp."""
    return torch.tensor(levels).repeat_interleave(ROWS)[:, None].expand(SIZE, SIZE).clone()


def _entries(T: PolynomialTensors, rows: range) -> dict[tuple, tuple[torch.Tensor, torch.Tensor]]:
    """(object, bounce, pixel, j, w, *counts) -> (value (C,), variance (C,)) of the entries of
    the pixels in ``rows`` (term ids are numbered per run, so entries are keyed by the term)."""
    lo, hi = rows.start * T.width, rows.stop * T.width
    out = {}
    for b in T.blocks:
        j, z, p = b.coordinates()
        table = T.terms[b.bounce]
        for e in range(j.numel()):
            pix = int(b.pixels[p[e]])
            if lo <= pix < hi:
                t = int(b.terms[z[e]])
                key = (b.object_id, b.bounce, pix, int(j[e]), int(table.w[t]), *table.counts[t].tolist())
                out[key] = (b.values[:, e], b.variance[:, e])
    return out


@pytest.fixture(scope="module")
def runs():
    sc = cornell_box_glossy(SIZE)
    spp = _band_map([3, 5, 2])
    adaptive = precompute_polynomial(sc, SETTINGS.replace(spp=spp), **RUN)
    uniform = {s: precompute_polynomial(sc, SETTINGS.replace(spp=s), **RUN) for s in (2, 3, 5)}
    return sc, spp, adaptive, uniform


def test_each_tile_equals_the_uniform_run_at_its_spp(runs):
    adaptive, uniform = runs[2:]
    for band, s in enumerate([3, 5, 2]):
        rows = range(band * ROWS, (band + 1) * ROWS)
        ours, theirs = _entries(adaptive, rows), _entries(uniform[s], rows)
        assert ours and ours.keys() == theirs.keys()
        for key, (v, var) in ours.items():
            assert torch.equal(v, theirs[key][0]) and torch.equal(var, theirs[key][1]), key
        px = slice(rows.start * SIZE, rows.stop * SIZE)
        assert torch.equal(adaptive.emission[:, px], uniform[s].emission[:, px])
    # the comparison can fail: another spp's run differs in these rows
    ours, other = _entries(adaptive, range(ROWS)), _entries(uniform[5], range(ROWS))
    assert ours.keys() != other.keys() or any(not torch.equal(v, other[k][0]) for k, (v, _) in ours.items())


def test_the_map_travels_with_the_record(runs, tmp_path):
    _, spp, adaptive, uniform = runs
    assert torch.equal(spp_map_of(adaptive), spp)
    assert adaptive.meta["spp"] == pytest.approx(float(spp.double().mean()))
    adaptive.save(tmp_path / "a.npz")
    assert torch.equal(spp_map_of(PolynomialTensors.load(tmp_path / "a.npz")), spp)
    assert torch.equal(spp_map_of(uniform[3]), torch.full((SIZE, SIZE), 3))
    assert adaptive.meta["rays"]["closest"] < uniform[5].meta["rays"]["closest"]


def test_levels_scattered_over_the_image_trace_each_pixel_at_its_spp():
    """A checkerboard of two levels: one bounce casts exactly one closest-hit ray per path."""
    sc = cornell_box_glossy(8)
    spp = 1 + 3 * ((torch.arange(8)[:, None] + torch.arange(8)) % 2)
    T = precompute_polynomial(sc, PolynomialSettings("1", spp=spp, guides=False), seed=0, progress=False)
    assert T.meta["rays"]["closest"] == int(spp.sum()) == 160
    assert torch.equal(spp_map_of(T), spp)


def _checkerboard(size: int, low: int, high: int) -> torch.Tensor:
    return torch.where((torch.arange(size)[:, None] + torch.arange(size)) % 2 == 0, low, high)


def test_mixed_spp_tiles_are_exact_on_the_same_paths(gen):
    """Tiles of mixed spp (a checkerboard of 1 and 3 paths, three row bands) with two light
    samples per eye vertex: the tensors equal the explicit path tracer on the same paths, each
    pixel divided by its own paths."""
    sc = teatray(10)
    spp = _checkerboard(10, 1, 3)
    paths: dict = {}
    T = precompute_polynomial(
        sc, PolynomialSettings("8,1,1", spp=spp, light_samples=2, tile_rows=4), seed=2, progress=False, paths=paths
    )
    assert torch.equal(spp_map_of(T), spp)
    R, coef, d = _renderer_at_random_coefficients(T, gen)
    with torch.no_grad():
        want = _oracle(sc, T, paths, coef, {}, d, spp.reshape(-1, 1).double())
        got = R.evaluate()
    assert float(want.sum()) > 0
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6 * float(want.abs().max()))
    # the oracle can fail: dividing every pixel by the mean spp differs
    wrong = _oracle(sc, T, paths, coef, {}, d, float(spp.double().mean()))
    assert not torch.allclose(got, wrong, rtol=1e-2, atol=0)


def test_mixed_spp_tiles_take_each_pixels_own_variance():
    """A pixel of one path has variance 0 exactly (its one path is its mean); its neighbours
    of 4 paths in the same tile do not, and the closest-hit rays are one per path."""
    sc = cornell_box_glossy(8)
    spp = _checkerboard(8, 1, 4)
    T = precompute_polynomial(sc, PolynomialSettings("4,1", spp=spp, tile_rows=4, guides=False), seed=0, progress=False)
    one = spp.reshape(-1) == 1
    seen = torch.zeros(64, dtype=torch.bool)
    for b in T.blocks:
        _, _, p = b.coordinates()
        pix = b.pixels[p]
        assert not bool(b.variance[:, one[pix]].any())
        seen[pix[~one[pix]][b.variance[:, ~one[pix]].amax(0) > 0]] = True
    assert int(seen.sum()) > 16  # many pixels of 4 paths have a variance
    assert T.meta["rays"]["closest"] >= int(spp.sum())


def test_resume_key_includes_the_map(tmp_path):
    sc = cornell_box_glossy(SIZE)
    a, b = _band_map([2, 3, 2]), _band_map([3, 2, 2])
    first = precompute_polynomial(sc, SETTINGS.replace(spp=a), checkpoint=tmp_path, keep_checkpoint=True, **RUN)
    again = precompute_polynomial(sc, SETTINGS.replace(spp=a), checkpoint=tmp_path, keep_checkpoint=True, **RUN)
    assert again.meta["tiles_cached"] == 3
    assert torch.equal(again.emission, first.emission)
    other = precompute_polynomial(sc, SETTINGS.replace(spp=b), checkpoint=tmp_path, keep_checkpoint=True, **RUN)
    assert other.meta["tiles_cached"] == 0
    # tiles of mixed spp resume bit for bit: one of three tiles lost, two loaded
    mixed, folder = _checkerboard(SIZE, 2, 3), tmp_path / "mixed"
    full = precompute_polynomial(sc, SETTINGS.replace(spp=mixed), checkpoint=folder, keep_checkpoint=True, **RUN)
    tiles = sorted(folder.glob("tile*.npz"))
    assert len(tiles) == 3
    tiles[1].unlink()
    again = precompute_polynomial(sc, SETTINGS.replace(spp=mixed), checkpoint=folder, **RUN)
    assert again.meta["tiles_cached"] == 2
    assert torch.equal(again.emission, full.emission) and len(again.blocks) == len(full.blocks)
    for x, y in zip(full.blocks, again.blocks, strict=True):
        assert torch.equal(x.values, y.values) and torch.equal(x.variance, y.variance)


def test_bad_maps_are_refused():
    sc = cornell_box_glossy(8)
    with pytest.raises(ShapeError):
        precompute_polynomial(sc, PolynomialSettings("1,1", spp=torch.ones(8, 7, dtype=torch.long)), progress=False)
    with pytest.raises(ShapeError):
        precompute_polynomial(sc, PolynomialSettings("1,1", spp=torch.ones(8, 8)), progress=False)  # float
    with pytest.raises(ValueRangeError):
        precompute_polynomial(sc, PolynomialSettings("1,1", spp=torch.zeros(8, 8, dtype=torch.long)), progress=False)


# -- light splitting at the eye vertex ---------------------------------------------------------
def _renderer_at_random_coefficients(T: PolynomialTensors, gen: torch.Generator):
    """(renderer, eye coefficients per object, diffuse equivalents (M, 3)) at random values."""
    R = PolynomialRenderer(T, dtype=torch.float64)
    coef, d = {}, torch.zeros(T.num_objects, 3, dtype=torch.float64)
    for m, b in enumerate(T.bases):
        if b is not None:
            coef[m], d[m] = torch.rand(b.size, 3, generator=gen, dtype=torch.float64), torch.rand(3, generator=gen)
            R.set_coefficients(m, coef[m], d=d[m])
    return R, coef, d


def test_light_splitting_is_exact_on_the_same_paths(gen):
    """k light samples per eye vertex, each weighted 1/k: the exactness oracle still holds."""
    sc = teatray(10)
    paths: dict = {}
    T = precompute_polynomial(
        sc, PolynomialSettings("8,1,1", spp=2, light_samples=3, tile_rows=10), seed=1, progress=False, paths=paths
    )
    assert T.meta["light_samples"] == 3
    R, coef, d = _renderer_at_random_coefficients(T, gen)
    with torch.no_grad():
        want = _oracle(sc, T, paths, coef, {}, d, 2)
    assert float(want.sum()) > 0
    torch.testing.assert_close(R.evaluate(), want, rtol=1e-4, atol=1e-6 * float(want.abs().max()))


def test_light_splitting_weights_average_to_one_sample():
    """A directional light is sampled without random numbers: k copies of the same sample
    weighted 1/k give the 1-sample record up to rounding, on the same paths."""
    sc = dataclasses.replace(teatray(10), lights=[DirectionalLight((0.3, 1.0, 0.4), 2.0)])
    settings = PolynomialSettings(series="4,1,1", spp=2, guides=False)
    one, three = (precompute_polynomial(sc, settings.replace(light_samples=k), seed=1, progress=False) for k in (1, 3))
    with torch.no_grad():
        a, b = (
            torch.stack(
                _renderer_at_random_coefficients(T, torch.Generator().manual_seed(5))[0].evaluate(per_bounce=True)
            )
            for T in (one, three)
        )
    assert float(a[1].abs().max()) > 0 and float(a[2].abs().max()) > 0
    torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-7 * float(a.abs().max()))
    assert three.meta["rays"]["shadow"] > one.meta["rays"]["shadow"]
    assert "light_samples" not in one.meta  # k = 1 keeps the key (and bits) of before
