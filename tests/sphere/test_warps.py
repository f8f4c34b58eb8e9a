"""Sampling warps: support, dtype, pdf normalisation and chi-square histograms."""

from __future__ import annotations

import math

import pytest
import torch

from tests._stats import assert_chi2
from torch_brdf.errors import ShapeError
from torch_brdf.sphere import warps

N = 200_000
COS_POWER = 7.5  # exponent of the cosine-power (Blinn lobe) warp under test
NORM_TOL = {torch.float32: 1e-6, torch.float64: 1e-14}

DIRECTIONAL = {  # warp -> (pdf of a direction, half-space only?)
    "sphere": (warps.square_to_uniform_sphere, warps.uniform_sphere_pdf, False),
    "hemisphere": (warps.square_to_uniform_hemisphere, warps.uniform_hemisphere_pdf, True),
    "cosine": (
        warps.square_to_cosine_hemisphere,
        lambda v: warps.cosine_hemisphere_pdf(v[..., 2]),
        True,
    ),
    "cosine_power": (
        lambda u: warps.square_to_cosine_power_hemisphere(u, COS_POWER),
        lambda v: warps.cosine_power_hemisphere_pdf(v[..., 2], COS_POWER),
        True,
    ),
}

#: the chi-square tests of this file form one family (Šidák correction of the one threshold)
CHI2_FAMILY = len(DIRECTIONAL) + 2


def uniforms(n=N, dtype=torch.float64, seed=0):
    return torch.rand(n, 2, generator=torch.Generator().manual_seed(seed), dtype=dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", list(DIRECTIONAL))
def test_directions_unit_and_follow_dtype(name, dtype):
    warp, pdf, half = DIRECTIONAL[name]
    v = warp(uniforms(10_000, dtype))
    assert v.shape == (10_000, 3) and v.dtype == dtype
    assert torch.allclose(v.norm(dim=-1), torch.ones((), dtype=dtype), atol=NORM_TOL[dtype] * 10)
    if half:
        assert bool((v[:, 2] >= 0).all())
    p = pdf(v)
    assert p.shape == (10_000,) and p.dtype == dtype and bool((p > 0).all())


@pytest.mark.parametrize("name", list(DIRECTIONAL))
def test_pdf_integrates_to_one(name):
    """E[4 pi pdf(w)] over uniform sphere directions is the integral of the pdf, 1."""
    _, pdf, _ = DIRECTIONAL[name]
    w = warps.square_to_uniform_sphere(uniforms(seed=1))
    f = 4 * math.pi * pdf(w)
    err = abs(float(f.mean()) - 1)
    assert err <= 5 * float(f.std()) / math.sqrt(N) + 1e-12, err


@pytest.mark.parametrize("name", list(DIRECTIONAL))
def test_chi2_directions(name):
    """Histogram over (cos theta, phi) cells against the pdf integrated exactly per cell."""
    warp, _, _ = DIRECTIONAL[name]
    v = warp(uniforms(seed=2))
    nz, nphi = 16, 24
    iz = ((1 - v[:, 2]) / 2 * nz).floor().long().clamp(0, nz - 1)  # z from 1 down to -1
    phi = torch.remainder(torch.atan2(v[:, 1], v[:, 0]), 2 * math.pi)
    ip = (phi / (2 * math.pi) * nphi).floor().long().clamp(0, nphi - 1)
    counts = torch.bincount(iz * nphi + ip, minlength=nz * nphi).reshape(nz, nphi)
    z = 1 - 2 * torch.arange(nz + 1, dtype=torch.float64) / nz  # cell edges in z
    a, b = z[1:], z[:-1]
    dphi = 2 * math.pi / nphi
    if name == "sphere":
        mass = (b - a) * dphi / (4 * math.pi)
    elif name == "hemisphere":
        mass = (b.clamp_min(0) - a.clamp_min(0)) * dphi / (2 * math.pi)
    elif name == "cosine":  # int cos/pi dw over the cell = dphi/pi * (b^2 - a^2)/2 on z >= 0
        mass = (b.clamp_min(0) ** 2 - a.clamp_min(0) ** 2) / 2 * dphi / math.pi
    else:  # int (n+1)/(2 pi) cos^n dw over the cell = dphi/(2 pi) * (b^(n+1) - a^(n+1)) on z >= 0
        mass = (b.clamp_min(0) ** (COS_POWER + 1) - a.clamp_min(0) ** (COS_POWER + 1)) * dphi / (2 * math.pi)
    expected = N * mass[:, None].expand(nz, nphi)
    assert abs(float(expected.sum()) - N) < 1e-6 * N
    assert_chi2(counts, expected, family_size=CHI2_FAMILY)


def test_concentric_disk_uniform():
    p = warps.square_to_uniform_disk_concentric(uniforms(seed=3))
    r2 = (p * p).sum(-1)
    assert bool((r2 <= 1 + 1e-12).all())
    nr, na = 10, 16  # equal-area cells: uniform in r^2 and angle
    ir = (r2 * nr).floor().long().clamp(0, nr - 1)
    ang = torch.remainder(torch.atan2(p[:, 1], p[:, 0]), 2 * math.pi)
    ia = (ang / (2 * math.pi) * na).floor().long().clamp(0, na - 1)
    counts = torch.bincount(ir * na + ia, minlength=nr * na)
    assert_chi2(counts, torch.full((nr * na,), N / (nr * na)), family_size=CHI2_FAMILY)
    # the centre of the square maps to the centre of the disk
    c = warps.square_to_uniform_disk_concentric(torch.full((1, 2), 0.5, dtype=torch.float64))
    assert float(c.abs().max()) == 0.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_triangle_barycentrics_uniform(dtype):
    b = warps.square_to_uniform_triangle(uniforms(dtype=dtype, seed=4))
    assert b.dtype == dtype and bool((b >= 0).all())
    assert torch.allclose(b.sum(-1), torch.ones((), dtype=dtype), atol=NORM_TOL[dtype] * 10)
    # the midpoints split the triangle into 4 triangles of equal area
    corner = (b > 0.5).long()
    cell = torch.where(corner.any(-1), corner.argmax(-1), torch.full_like(corner[:, 0], 3))
    counts = torch.bincount(cell, minlength=4)
    assert_chi2(counts, torch.full((4,), N / 4), family_size=CHI2_FAMILY)


@pytest.mark.parametrize(
    "warp",
    [
        warps.square_to_uniform_sphere,
        warps.square_to_uniform_hemisphere,
        warps.square_to_cosine_hemisphere,
        warps.square_to_uniform_disk_concentric,
        warps.square_to_uniform_triangle,
    ],
)
def test_bad_u_raises(warp):
    with pytest.raises(ShapeError, match=r"\(N, 2\)"):
        warp(torch.rand(5, 3))
    with pytest.raises(ShapeError, match=r"\(N, 2\)"):
        warp(torch.zeros(5, 2, dtype=torch.long))
