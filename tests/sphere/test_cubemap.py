"""Cubemap geometry and block DCT: analytic values and brute-force oracles."""

from __future__ import annotations

import math

import pytest
import torch

from torch_brdf.errors import ShapeError, ValueRangeError
from torch_brdf.sphere.cubemap import CubemapBlocks, cube_directions, direction_to_cube, texel_solid_angles_cube
from torch_brdf.sphere.dct import dct_basis, low_indices, sample_positions, subsampled_inverse


@pytest.mark.parametrize("R", [1, 4, 16, 64])
def test_solid_angles_sum_to_sphere(R):
    om = texel_solid_angles_cube(R)
    assert om.shape == (R, R)
    assert float(om.sum() * 6) == pytest.approx(4 * math.pi, rel=1e-12)
    assert bool((om > 0).all())


def test_solid_angle_matches_jacobian_at_small_texels():
    # dOmega = dA / (1 + a^2 + b^2)^(3/2) with dA = (2/R)^2 in face coordinates
    R = 256
    om = texel_solid_angles_cube(R)
    c = 2 * (torch.arange(R, dtype=torch.float64) + 0.5) / R - 1
    a, b = c[None, :], c[:, None]
    jac = (2.0 / R) ** 2 / (1 + a * a + b * b) ** 1.5
    assert torch.allclose(om, jac, rtol=1e-4)


def test_faces_point_along_their_axes_and_round_trip():
    cb = CubemapBlocks(32, 16)
    d = cb.directions.reshape(-1, 3)
    assert torch.allclose(d.norm(dim=-1), torch.ones(len(d), dtype=torch.float64))
    axes = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=torch.float64)
    face_of_block = torch.arange(cb.block_count) // cb.blocks_per_side**2
    cos = (cb.centers * axes[face_of_block]).sum(-1)
    assert bool((cos > 0.5).all())
    f, a, b = direction_to_cube(d)
    assert torch.allclose(cube_directions(f, a, b), d, atol=1e-12)
    # every texel is hit exactly once by its own centre direction
    R = cb.resolution
    j = ((a + 1) / 2 * R - 0.5).round().long()
    i = ((b + 1) / 2 * R - 0.5).round().long()
    flat = f * R * R + i * R + j
    assert torch.equal(flat, cb.texel_index.reshape(-1))


def test_faces_are_right_handed_views():
    # OpenGL convention spot checks: +x face, texel near a = +1 looks towards -z
    f, a, b = direction_to_cube(
        torch.tensor([[1.0, 0.0, -0.5], [0.2, 1.0, 0.7], [0.0, -0.3, -1.0]], dtype=torch.float64)
    )
    assert f.tolist() == [0, 2, 5]
    assert a[0] > 0 and b[1] > 0 and b[2] > 0


def test_block_layout_round_trip(gen):
    cb = CubemapBlocks(32, 16)
    x = torch.randn(2, 6, 32, 32, 3, generator=gen)
    blocks = cb.to_blocks(x)
    assert blocks.shape == (2, 24, 256, 3)
    assert torch.equal(cb.from_blocks(blocks, lead=1), x)
    # rows of a block are concatenated: texel t = r * 16 + c
    assert torch.equal(blocks[0, 1, 16 * 3 + 5], x[0, 0, 3, 16 + 5])


def test_bad_resolution_and_shapes():
    with pytest.raises(ValueRangeError):
        CubemapBlocks(40, 16)
    with pytest.raises(ShapeError):
        CubemapBlocks(32, 16).to_blocks(torch.zeros(6, 16, 16))


def test_supersampled_projection_of_linear_function_is_exact_mean():
    cb = CubemapBlocks(16, 16)
    # a constant projects to itself; the k x k means converge to the texel-centre value for smooth functions
    one = cb.project(lambda d: torch.ones(len(d), 1, dtype=d.dtype), samples=3)
    assert torch.allclose(one, torch.ones_like(one))
    y = cb.project(lambda d: d[:, 1:2], samples=8)
    assert torch.allclose(y[..., 0], cb.directions[..., 1], atol=2e-3)


def test_dct_basis_is_orthonormal_and_low_rows_match():
    B = dct_basis(16)
    assert torch.allclose(B @ B.T, torch.eye(256, dtype=torch.float64), atol=1e-12)
    low = dct_basis(16, 4)
    idx = low_indices(4, 16)
    assert torch.allclose(low, B[idx])


@pytest.mark.parametrize("l", [1, 2, 4, 16])
def test_subsampled_inverse_recovers_band_limited_functions(l, gen):
    # a function spanned by the p, q < l basis functions is recovered exactly from l x l samples
    A = torch.randn(l * l, generator=gen, dtype=torch.float64)
    full = dct_basis(16, l)  # (l^2, 256)
    f = A @ full  # values at texel centres
    x = sample_positions(l)
    # evaluate the same function at the fractional sample positions with the continuous basis
    u = torch.arange(l, dtype=torch.float64)
    c = torch.where(u == 0, math.sqrt(1 / 16), math.sqrt(2 / 16))
    b = c * torch.cos(math.pi * (2 * x[:, None] + 1) * u[None, :] / 32)  # (l, l)
    samples = torch.einsum("ip,jq,pq->ij", b, b, A.view(l, l)).reshape(-1)
    assert torch.allclose(subsampled_inverse(l) @ samples, A, atol=1e-10)
    if l == 16:  # the full grid is the texel grid itself
        assert torch.allclose(samples, f, atol=1e-12)


def test_constant_block_needs_one_sample():
    A = subsampled_inverse(1) @ torch.tensor([2.5], dtype=torch.float64)
    recon = A @ dct_basis(16, 1)
    assert torch.allclose(recon, torch.full((256,), 2.5, dtype=torch.float64))
    assert float(sample_positions(1)[0]) == 7.5


def test_nearest_point_in_block(gen):
    cb = CubemapBlocks(64, 16)
    # a direction inside a block maps to itself; the block's own centre is its own nearest point
    d = torch.randn(200, 3, generator=gen, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    f, a, b = direction_to_cube(d)
    R, S, n = 64, 16, 4
    j = ((a + 1) / 2 * R).clamp(max=R - 1e-9).floor().long()
    i = ((b + 1) / 2 * R).clamp(max=R - 1e-9).floor().long()
    blocks = f * n * n + (i // S) * n + (j // S)
    torch.testing.assert_close(cb.nearest_in_blocks(blocks, d), d)
    # another block: the result lies in that block and is at least as close as its centre
    other = (blocks + 7) % cb.block_count
    p = cb.nearest_in_blocks(other, d)
    fo, ao, bo = direction_to_cube(p)
    assert torch.equal(fo, other // (n * n))
    bi, bj = (other % (n * n)) // n, other % n
    for coord, k in ((ao, bj), (bo, bi)):  # inside the block's face-coordinate square
        assert bool((coord >= 2 * k * S / R - 1 - 1e-9).all() and (coord <= 2 * (k + 1) * S / R - 1 + 1e-9).all())
    cos_p, cos_c = (p * d).sum(-1), (cb.centers[other] * d).sum(-1)
    assert bool((cos_p >= cos_c - 1e-12).all())
