"""Haar wavelets on cubemap faces and the Ng et al. 2004 triple product, against brute-force oracles."""

from __future__ import annotations

import math

import pytest
import torch

from tests.conftest import RTOL
from torch_brdf.errors import ShapeError, TorchBRDFError, ValueRangeError
from torch_brdf.sphere import (
    HaarTripleProduct,
    SparseHaar,
    haar2d,
    haar_tripling_coefficients,
    ihaar2d,
    keep_largest,
)

DTYPES = [torch.float32, torch.float64]


def seeded(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def basis(size: int) -> torch.Tensor:
    """(R*R, R*R) float64: row p is the basis image of coefficient p, from unit coefficient vectors."""
    eye = torch.eye(size * size, dtype=torch.float64).reshape(-1, size, size)
    return ihaar2d(eye).reshape(size * size, -1)


def explicit_basis(size: int) -> torch.Tensor:
    """(R*R, R*R) float64: the basis as the module docstring describes it, built texel by texel."""
    out = torch.zeros(size * size, size, size, dtype=torch.float64)
    out[0] = 1.0 / size
    for lv in range(size.bit_length() - 1):
        h, s = 1 << lv, size >> lv
        for u in range(h):
            for v in range(h):
                node = (slice(u * s, (u + 1) * s), slice(v * s, (v + 1) * s))
                half = s // 2
                sign_h = torch.ones(s, s, dtype=torch.float64)
                sign_h[:, half:] = -1  # left minus right
                sign_v = torch.ones(s, s, dtype=torch.float64)
                sign_v[half:, :] = -1  # top minus bottom
                for (r, c), sign in (((u, h + v), sign_h), ((h + u, v), sign_v), ((h + u, h + v), sign_h * sign_v)):
                    out[r * size + c][node] = sign / s
    return out.reshape(size * size, -1)


def random_scene(size, n_vert, channels=3, binary=True, seed=0, dtype=torch.float64):
    """Lighting (6, R, R, C) with a few bright spots, visibility (P, 6, R, R), BRDF (P, 6, R, R, C)."""
    g = seeded(seed)
    light = torch.rand(cube_shape(size, channels), generator=g, dtype=torch.float64) * 0.1
    light.view(-1, channels)[torch.randint(0, 6 * size * size, (5,), generator=g)] += 5.0
    vis = torch.rand(n_vert, 6, size, size, generator=g, dtype=torch.float64)
    if binary:
        vis = (vis > 0.5).to(torch.float64)
    rho = torch.rand(n_vert, *cube_shape(size, channels), generator=g, dtype=torch.float64)
    rho = rho * torch.linspace(0.0, 1.0, size, dtype=torch.float64)[:, None, None]  # a smooth-ish lobe
    return light.to(dtype), vis.to(dtype), rho.to(dtype)


def cube_shape(size, channels):
    return (6, size, size, channels)


def cube_pixels(coeffs_dense: torch.Tensor) -> torch.Tensor:
    """(..., 6, R, R, C) Haar coefficients -> texels."""
    return ihaar2d(coeffs_dense.movedim(-1, -3)).movedim(-3, -1)


def pixel_oracle(lit: SparseHaar, vis: torch.Tensor, rho: SparseHaar) -> tuple[torch.Tensor, torch.Tensor]:
    """Dense texel sum of the reconstructed truncated lighting x exact V x reconstructed truncated BRDF.

    Returns the sum (P, C) and its magnitude (the same sum of absolute values), the scale of rounding errors.
    """
    light = cube_pixels(lit.to_dense().double())
    brdf = cube_pixels(rho.to_dense().double())
    want = torch.einsum("fxyc,pfxy,pfxyc->pc", light, vis.double(), brdf)
    return want, torch.einsum("fxyc,pfxy,pfxyc->pc", light.abs(), vis.double().abs(), brdf.abs())


def assert_rel(got, want, rtol, scale=None):
    """max |got - want| < rtol * max(scale or |want|); scale is the magnitude where terms may cancel."""
    scale = (want if scale is None else scale).abs().max().clamp_min(1e-300)
    assert float((got.double() - want.double()).abs().max() / scale) < rtol


# --- transform -------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("size", [1, 2, 8, 16])
def test_parseval_and_reconstruction(dtype, size):
    x = torch.randn(2, 3, size, size, generator=seeded(size), dtype=torch.float64).to(dtype)
    c = haar2d(x)
    assert c.dtype == dtype and c.shape == x.shape
    assert_rel(c.pow(2).sum((-1, -2)), x.pow(2).sum((-1, -2)), RTOL[dtype])
    assert_rel(ihaar2d(c), x, RTOL[dtype])
    assert_rel(c[..., 0, 0], x.mean((-1, -2)) * size, RTOL[dtype])  # scaling coefficient


@pytest.mark.parametrize("size", [2, 4, 8])
def test_layout_matches_explicit_basis(size):
    b = basis(size)
    torch.testing.assert_close(b @ b.T, torch.eye(size * size, dtype=torch.float64), rtol=0, atol=1e-14)
    torch.testing.assert_close(b, explicit_basis(size), rtol=0, atol=1e-15)
    # the forward transform is the analysis with the same basis
    x = torch.randn(size, size, generator=seeded(1), dtype=torch.float64)
    torch.testing.assert_close(haar2d(x).reshape(-1), b @ x.reshape(-1), rtol=0, atol=1e-13)


def test_noncontiguous_and_integer_input():
    x = torch.arange(2 * 4 * 4).reshape(4, 4, 2).movedim(-1, 0)  # integer, non-contiguous
    c = haar2d(x)
    assert c.dtype == torch.get_default_dtype()
    torch.testing.assert_close(ihaar2d(c), x.to(c.dtype))


# --- tripling coefficients ---------------------------------------------------------------


@pytest.mark.parametrize("size", [2, 4, 8])
def test_tripling_rules_match_brute_force(size):
    b = basis(size)
    brute = torch.einsum("it,jt,kt->ijk", b, b, b)
    n = size * size
    idx = torch.arange(n)
    rules = haar_tripling_coefficients(size, idx[:, None, None], idx[None, :, None], idx[None, None, :])
    nonzero = brute.abs() > 1e-12
    assert torch.equal(nonzero, rules != 0)  # nothing outside the three cases is non-zero
    torch.testing.assert_close(rules, brute, rtol=0, atol=1e-14)
    if size == 4:
        # count the cases of Ng et al. Sec. 4: 1 (phi^3) + case 2 (3 orderings of (psi, psi, coarser)
        # for each wavelet and each of its 1 + 3 l ancestors) + case 3 (3! orderings per node)
        n_case2 = 3 * sum(3 * 4**lv * (1 + 3 * lv) for lv in range(2))
        n_case3 = 6 * sum(4**lv for lv in range(2))
        assert int(nonzero.sum()) == 1 + n_case2 + n_case3


def test_tripling_coefficient_values():
    size = 4
    # case 1: phi^3 = 1/R; case 3 at the level-0 node: 1/S = 1/4; at a level-1 node: 1/2
    assert float(haar_tripling_coefficients(size, 0, 0, 0)) == 0.25
    assert float(haar_tripling_coefficients(size, 1, 4, 5)) == 0.25
    assert float(haar_tripling_coefficients(size, 2, 8, 10)) == 0.5
    # case 2: the finest D at (3, 3) twice, with the level-0 H, whose value on the bottom-right quarter is -1/4
    assert float(haar_tripling_coefficients(size, 15, 1, 15)) == -0.25
    with pytest.raises(ValueRangeError):
        haar_tripling_coefficients(size, 16, 0, 0)
    with pytest.raises(ShapeError):
        haar_tripling_coefficients(3, 0, 0, 0)


# --- non-linear approximation --------------------------------------------------------------


def test_keep_largest_ranks_by_channel_l1_and_breaks_ties_low():
    size = 2
    c = torch.zeros(2, 6, size, size, 3, dtype=torch.float64)
    c[0, 1, 0, 1] = torch.tensor([3.0, 0.0, 0.0])  # L1 3, max 3
    c[0, 2, 1, 1] = torch.tensor([-1.5, 1.5, 1.5])  # L1 4.5, max 1.5: ranks first by L1
    c[1, 3, 0, 0, 0] = 1.0  # item 1: one non-zero, then ties among zeros -> lowest positions
    sp = keep_largest(c, 3 / 24)
    assert sp.k == 3 and sp.indices.shape == (2, 3) and sp.values.shape == (2, 3, 3)
    assert sp.indices[0].tolist() == [0, 1 * 4 + 1, 2 * 4 + 3]  # tie among zeros: position 0
    assert sp.indices[1].tolist() == [0, 1, 3 * 4]
    torch.testing.assert_close(sp.to_dense()[0, 2, 1, 1], c[0, 2, 1, 1])
    # k = 2: the two largest of item 0 by L1
    assert keep_largest(c, 2 / 24).indices[0].tolist() == [5, 11]
    assert torch.equal(keep_largest(c, 1.0).to_dense(), c)


def test_keep_largest_counts_and_no_channels():
    size = 4
    x = torch.randn(3, 6, size, size, generator=seeded(2), dtype=torch.float64)
    for fraction, k in ((1e-9, 1), (0.01, 1), (0.1, 10), (0.5, 48), (1.0, 96)):
        sp = keep_largest(x, fraction, channels=False)
        assert sp.k == k == max(1, math.ceil(fraction * 96 - 1e-9))
        assert sp.values.shape == (3, k) and not sp.has_channels
        dense = sp.to_dense()
        assert dense.shape == x.shape
        # the kept ones are the largest: every dropped magnitude <= every kept magnitude
        for item in range(3):
            dropped = x[item].abs()[dense[item] == 0]
            if dropped.numel():
                assert float(dropped.max()) <= float(sp.values[item].abs().min())


# --- triple product ------------------------------------------------------------------------


def run(size, fraction_l, fraction_r, binary=True, channels=3, n_vert=4, seed=0, dtype=torch.float64, chunk=1 << 22):
    light, vis, rho = random_scene(size, n_vert, channels, binary, seed, dtype)
    tp = HaarTripleProduct(chunk_elements=chunk)
    lit = tp.set_lighting(light, fraction_l)
    rc = tp.brdf_coefficients(rho, fraction_r)
    got = tp.product(tp.visibility_coefficients(vis), rc)
    want, mag = pixel_oracle(lit, vis, rc)
    return got, want, mag, (light, vis, rho)


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("size", [8, 16])
@pytest.mark.parametrize("fractions", [(0.01, 0.02), (0.05, 0.1), (0.3, 0.05), (1.0, 0.1), (1.0, 1.0)])
def test_product_matches_pixel_sum(size, fractions, binary):
    got, want, mag, (light, vis, rho) = run(size, *fractions, binary=binary, seed=size)
    assert got.shape == (4, 3) and got.dtype == torch.float64
    assert_rel(got, want, RTOL[torch.float64], mag)
    if fractions == (1.0, 1.0):  # nothing dropped: the plain dense sum of L V rho
        assert_rel(got, torch.einsum("fxyc,pfxy,pfxyc->pc", light, vis, rho), RTOL[torch.float64])


def test_product_matches_tripling_tensor():
    """sum_ijk C_ijk L_i V_j rho_k per face with the brute-force tensor: an oracle in coefficient space."""
    size = 4
    light, vis, rho = random_scene(size, 3, binary=False, seed=5)
    tp = HaarTripleProduct()
    lit = tp.set_lighting(light, 0.2)
    rc = tp.brdf_coefficients(rho, 0.3)
    vc = tp.visibility_coefficients(vis)
    b = basis(size)
    tensor = torch.einsum("it,jt,kt->ijk", b, b, b)
    lc = lit.to_dense().reshape(6, 16, 3)
    want = torch.einsum("ijk,fic,pfj,pfkc->pc", tensor, lc, vc.reshape(3, 6, 16), rc.to_dense().reshape(3, 6, 16, 3))
    assert_rel(tp.product(vc, rc), want, RTOL[torch.float64])


def test_chunking_and_grey_brdf():
    got, want, mag, _ = run(8, 0.1, 0.1, n_vert=7, chunk=1)  # one vertex per chunk
    assert_rel(got, want, RTOL[torch.float64], mag)
    light, vis, rho = random_scene(8, 3, channels=1, seed=3)
    tp = HaarTripleProduct()
    lit = tp.set_lighting(light.expand(-1, -1, -1, 3) * torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64), 0.1)
    rc = tp.brdf_coefficients(rho, 0.1)  # C = 1 against RGB lighting
    got = tp.product(tp.visibility_coefficients(vis), rc)
    assert got.shape == (3, 3)
    want, mag = pixel_oracle(lit, vis, rc)
    assert_rel(got, want, RTOL[torch.float64], mag)


def test_edge_cases():
    size = 8
    light, vis, rho = random_scene(size, 3, seed=7)
    tp = HaarTripleProduct()
    rc = tp.brdf_coefficients(rho, 0.05)
    tp.set_lighting(torch.zeros_like(light), 0.05)  # all-zero lighting
    assert torch.equal(tp.product(tp.visibility_coefficients(vis), rc), torch.zeros(3, 3, dtype=torch.float64))
    lit = tp.set_lighting(light, 0.05)
    assert torch.equal(tp.product(tp.visibility_coefficients(torch.zeros_like(vis)), rc), torch.zeros(3, 3).double())
    ones = torch.ones_like(vis)  # V = 1: the product is the per-face inner product of L and rho coefficients
    want = torch.einsum("fxyc,pfxyc->pc", lit.to_dense(), rc.to_dense())
    got = tp.product(tp.visibility_coefficients(ones), rc)
    assert_rel(got, want, RTOL[torch.float64], pixel_oracle(lit, ones, rc)[1])
    # tiny fraction: one coefficient each
    got, want, mag, _ = run(size, 1e-6, 1e-6, seed=8)
    assert_rel(got, want, RTOL[torch.float64], mag)
    # R = 1 and R = 2 cubemaps (scaling function only / one level)
    for tiny in (1, 2):
        got, want, mag, _ = run(tiny, 0.5, 0.5, seed=tiny)
        assert_rel(got, want, RTOL[torch.float64], mag)


def test_float32_agrees_with_float64():
    got32, _, _, _ = run(16, 0.05, 0.05, binary=False, seed=9, dtype=torch.float32)
    got64, want, mag, _ = run(16, 0.05, 0.05, binary=False, seed=9, dtype=torch.float64)
    assert got32.dtype == torch.float32
    assert_rel(got64, want, RTOL[torch.float64], mag)
    # the same coefficients are kept unless two magnitudes round together; compare to the float64 result
    assert_rel(got32, got64, 10 * RTOL[torch.float32])


def test_module_to_dtype():
    light, vis, rho = random_scene(8, 2, seed=10, dtype=torch.float32)
    tp = HaarTripleProduct()
    tp.set_lighting(light, 0.1)
    tp64 = tp.to(torch.float64)
    assert tp64.light_values.dtype == torch.float64 and tp64.slots.dtype == torch.long
    rc = tp64.brdf_coefficients(rho.double(), 0.1)
    assert tp64.product(tp64.visibility_coefficients(vis.double()), rc).dtype == torch.float64


# --- bad input ------------------------------------------------------------------------------


def test_bad_input():
    with pytest.raises(ShapeError):
        haar2d(torch.zeros(4, 8))
    with pytest.raises(ShapeError):
        haar2d(torch.zeros(6, 6))
    with pytest.raises(ShapeError):
        ihaar2d(torch.zeros(3, 12, 12))
    with pytest.raises(ShapeError):
        haar2d(torch.zeros(4))
    c = torch.zeros(6, 4, 4, 3)
    for bad in (0.0, -0.1, 1.5, float("nan"), float("inf")):
        with pytest.raises(ValueRangeError):
            keep_largest(c, bad)
    with pytest.raises(ShapeError):
        keep_largest(torch.zeros(5, 4, 4, 3), 0.1)
    with pytest.raises(ShapeError):
        keep_largest(torch.zeros(6, 4, 4), 0.1)  # channels=True needs (..., 6, R, R, C)
    with pytest.raises(ValueRangeError):
        keep_largest(torch.full((6, 4, 4, 3), float("nan")), 0.1)

    tp = HaarTripleProduct()
    light, vis, rho = random_scene(8, 2, seed=11)
    with pytest.raises(TorchBRDFError):  # no lighting yet
        tp.product(tp.visibility_coefficients(vis), tp.brdf_coefficients(rho, 0.1))
    with pytest.raises(ShapeError):
        tp.set_lighting(light[..., 0], 0.1)
    with pytest.raises(ShapeError):
        tp.set_lighting(torch.zeros(6, 6, 6, 3), 0.1)
    with pytest.raises(ValueRangeError):
        tp.set_lighting(light, 0.0)
    bad = light.clone()
    bad[0, 0, 0, 0] = float("inf")
    with pytest.raises(ValueRangeError):
        tp.set_lighting(bad, 0.1)
    with pytest.raises(ValueRangeError):
        tp.brdf_coefficients(rho, 2.0)
    with pytest.raises(ShapeError):
        tp.visibility_coefficients(vis[0])
    tp.set_lighting(light, 0.1)
    vc, rc = tp.visibility_coefficients(vis), tp.brdf_coefficients(rho, 0.1)
    with pytest.raises(ShapeError):  # vertex count
        tp.product(vc[:1], rc)
    with pytest.raises(ShapeError):  # resolution
        tp.product(tp.visibility_coefficients(vis[:, :, :4, :4]), tp.brdf_coefficients(rho[:, :, :4, :4], 0.1))
    with pytest.raises(ShapeError):  # channels
        tp.product(vc, tp.brdf_coefficients(rho[..., :2], 0.1))
    with pytest.raises(ShapeError):  # not sparse BRDF coefficients
        tp.product(vc, rc.to_dense())
    with pytest.raises(ValueRangeError):
        HaarTripleProduct(chunk_elements=0)
