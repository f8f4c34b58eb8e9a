"""Pixel coverage (a guide) and the silhouette fits of the selecting filter that use it."""

from __future__ import annotations

import pytest
import torch

from torch_brdf.denoise import (
    GuideWeights,
    SelectedRegressionFilter,
    SelectionSettings,
    guide_buffers,
    pixel_coverage,
    silhouette_signature,
)
from torch_brdf.denoise.selection import _SilhouetteFit, _SilhouetteMean
from torch_brdf.errors import ShapeError, ValueRangeError
from torch_brdf.scene.builtin import cornell_box
from torch_brdf.scene.gbuffer import trace_gbuffer

SIZE = 48


@pytest.fixture(scope="module")
def box():
    sc = cornell_box(SIZE)
    return sc, guide_buffers(sc)


def test_coverage_equals_a_finer_view_of_the_same_camera(box):
    """``samples`` = n: the fraction of the n x n subpixel cells whose centre ray hits the pixel
    centre's object, the same as the n-times-finer view's pixel-centre G-buffer pooled over n x n
    blocks (an independent trace: other rays, the same positions)."""
    sc, g = box
    n = 4
    cov = pixel_coverage(sc, n)
    assert cov.shape == (SIZE, SIZE) and cov.dtype == torch.float32
    fine = trace_gbuffer(sc, sc.camera.with_size(SIZE * n, SIZE * n))
    oid = torch.full((SIZE * n * SIZE * n,), -1, dtype=torch.int64)
    oid[fine.pixels] = fine.object_id.long()
    blocks = oid.reshape(SIZE, n, SIZE, n).permute(0, 2, 1, 3).reshape(SIZE, SIZE, n * n)
    want = (blocks == g.object_id[..., None]).double().mean(-1)
    diff = (cov.double() - want).abs()
    assert float(diff.max()) <= 1.0 / n**2 + 1e-7  # a cell's centre ray may round across an edge
    assert int((diff > 0).sum()) <= 3
    assert float(cov.min()) < 0.6 and float((cov < 1).double().mean()) > 0.05  # edges are seen
    assert torch.equal(pixel_coverage(sc, n, g.object_id), cov)  # the guides' ids skip a trace
    assert bool((pixel_coverage(sc, 1) == 1).all())  # one ray: the centre itself


def test_coverage_refuses_bad_arguments(box):
    sc, g = box
    for bad in (0, 65, 2.0, True, "8"):
        with pytest.raises(ValueRangeError, match="samples"):
            pixel_coverage(sc, bad)
    with pytest.raises(ShapeError, match="object_id"):
        pixel_coverage(sc, 2, g.object_id[:-1])
    with pytest.raises(ShapeError, match="coverage"):
        SelectedRegressionFilter(g, [(torch.zeros(SIZE, SIZE), torch.zeros(SIZE, SIZE))], coverage=torch.ones(3, 3))
    with pytest.raises(ShapeError, match="coverage"):
        SelectedRegressionFilter(
            g, [(torch.zeros(SIZE, SIZE), torch.zeros(SIZE, SIZE))], coverage=torch.full((SIZE, SIZE), 1.5)
        )
    with pytest.raises(ValueRangeError):
        SelectionSettings(silhouette_regression=(0,))


def _plane_on_edges(g, cov, gen):
    """(3, H, W): on silhouette pixels, a plane in coverage and position per signature (an edge
    whose objects mix in changing proportions along it); inside, a smooth ramp."""
    sig = silhouette_signature(g.object_id)
    inner = GuideWeights(g).interior
    h, w = g.object_id.shape
    yy, xx = (t.double() for t in torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij"))
    k = int(sig.max()) + 1
    c = torch.rand(4, k, generator=gen, dtype=torch.float64)
    edge = 0.3 + c[0][sig] + 2.0 * c[1][sig] * cov.double() + 0.02 * c[2][sig] * xx + 0.02 * c[3][sig] * yy
    img = torch.where(inner, 1.0 + 0.01 * yy, edge)
    img = torch.where(g.object_id >= 0, img, torch.where(inner, 0.0, img))
    return img.expand(3, h, w).clone(), sig, inner


def test_silhouette_fit_reproduces_a_coverage_plane_and_keeps_to_its_edge(box, gen):
    """Oracle: an image that is a plane in (coverage, x, y) on each edge's silhouette pixels is
    reproduced exactly by every fit candidate without a ridge (the means blur it); the fits'
    taps stay among the pixels of the same signature, interior pixels keep their value and the
    filter is linear."""
    sc, g = box
    cov = pixel_coverage(sc, 8, g.object_id)
    clean, sig, inner = _plane_on_edges(g, cov, gen)
    y = clean.clone()
    A = SelectedRegressionFilter(g, [(y, y)], coverage=cov)  # noiseless halves: any exact candidate
    names = A.names
    assert [n for n in names if n.startswith("silhouette_fit")] == [
        "silhouette_fit_r1",
        "silhouette_fit_r2",
        "silhouette_fit_r3",
        "silhouette_fit_r5",
    ]
    s = SelectionSettings(ridge=1e-9)  # the ridge is the fit's only bias
    for r in (1, 2, 3, 5):
        fit = _SilhouetteFit(g, inner, sig, cov, r, s)
        out = fit(clean)
        torch.testing.assert_close(out, clean, rtol=1e-5, atol=1e-5)  # float32 hat weights
        mean = _SilhouetteMean(g, inner, sig, r, s.sigma_normal)(clean)
        assert float((mean - clean)[:, ~inner].abs().max()) > 1e-2  # the mean does not
        # taps inside the signature's silhouette pixels; interior pixels untouched
        assert float(fit(inner.double())[~inner].abs().max()) == 0.0
        torch.testing.assert_close(fit(inner.double())[inner], torch.ones(int(inner.sum()), dtype=torch.float64))
        for k in torch.unique(sig[~inner]).tolist()[:20]:
            mine = ~inner & (sig == k)
            assert float(fit(mine.double())[~mine & ~inner].abs().max()) == 0.0, k
    x, z = torch.rand(2, 3, SIZE, SIZE, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(A(0.7 * x - 1.3 * z), 0.7 * A(x) - 1.3 * A(z), rtol=1e-12, atol=1e-12)


def test_selection_with_coverage_lowers_the_silhouettes_error(gen):
    """Noisy halves of a coverage-plane image: given the coverage, the pick takes fits on most
    silhouette pixels and their error drops well below that of the means-only filter; interior
    pixels are picked as without coverage."""
    sc = cornell_box(64)
    g = guide_buffers(sc)
    cov = pixel_coverage(sc, 8, g.object_id)
    clean, _, inner = _plane_on_edges(g, cov, gen)
    a, b = (clean + 0.05 * torch.randn(3, 64, 64, generator=gen, dtype=torch.float64) for _ in range(2))
    y = (a + b) / 2
    means = SelectedRegressionFilter(g, [(a, b)])
    fits = SelectedRegressionFilter(g, [(a, b)], coverage=cov)
    outer = ~inner & (g.object_id >= 0)

    def mse(img):
        return float((img - clean)[:, outer].square().mean())

    picked = torch.tensor([fits.names[k].startswith("silhouette_fit") for k in fits.pick[outer].tolist()])
    assert float(picked.double().mean()) > 0.3
    assert mse(fits(y)) < 0.8 * mse(means(y)), (mse(fits(y)), mse(means(y)))
    torch.testing.assert_close(fits(y)[:, inner], means(y)[:, inner])


def test_pixels_whose_centre_misses_are_filtered_along_their_edge(gen):
    """A pixel whose centre ray misses the scene but which an object partly covers (the box's
    open front) records that part: it has no normal, and its taps are the pixels of the same
    signature, so the means and the fits filter it (a normal weight alone would leave it as it is,
    with the error of the noisy pixel)."""
    sc = cornell_box(64)
    g = guide_buffers(sc)
    cov = pixel_coverage(sc, 8, g.object_id)
    clean, sig, inner = _plane_on_edges(g, cov, gen)
    miss = g.object_id < 0
    assert int(miss.sum()) > 100 and not bool(inner[miss].any())
    a, b = (clean + 0.05 * torch.randn(3, 64, 64, generator=gen, dtype=torch.float64) for _ in range(2))
    y = (a + b) / 2

    def mse(img):
        return float((img - clean)[:, miss].square().mean())

    for A in (SelectedRegressionFilter(g, [(a, b)]), SelectedRegressionFilter(g, [(a, b)], coverage=cov)):
        assert mse(A(y)) < 0.5 * mse(y), (A.names, mse(A(y)), mse(y))
        for k in torch.unique(sig[miss]).tolist():  # taps within the signature
            mine = miss & (sig == k)
            assert float(A(mine.double())[~mine & ~inner].abs().max()) == 0.0, k
