"""The microfacet distribution protocol (D, G1, pdf, sample; pbrt-v4's pattern)."""

from __future__ import annotations

import math

import pytest
import torch

from tests._stats import assert_chi2
from tests.brdf.common import adaptive_cell_integrals, direction, half_vector_grid
from torch_brdf.brdf import (
    GGXNDF,
    AnisotropicPhongNDF,
    BeckmannNDF,
    BlinnNDF,
    MicrofacetDistribution,
    create,
)
from torch_brdf.brdf.microfacet import beckmann_g1_over_cos

F64 = torch.float64
T = lambda x: torch.tensor(x, dtype=F64)  # noqa: E731

NDFS = {
    "blinn": BlinnNDF(T(30.0)),
    "beckmann": BeckmannNDF(T(0.3)),
    "beckmann_aniso": BeckmannNDF(T(0.15), T(0.45)),
    "ggx": GGXNDF(T(0.3)),
    "ashikhmin_shirley": AnisotropicPhongNDF(T(20.0), T(200.0)),
}


@pytest.mark.parametrize("name", list(NDFS))
def test_projected_area_is_one(name):
    r""":math:`\int D(h)\cos\theta_h\,d\omega_h = 1`."""
    h, w = half_vector_grid(panels=48, order=8, n_phi=256)
    total = float((NDFS[name].D(h) * h[:, 2] * w).sum())
    assert abs(total - 1) < 2e-3, total


@pytest.mark.parametrize("name", list(NDFS))
def test_sample_follows_pdf(name):
    """Half vectors from ``sample`` against ``pdf`` integrated per cell (cos theta x phi rings)."""
    ndf = NDFS[name]
    wo = direction(math.radians(40.0)).expand(100_000, 3)
    u = torch.rand(100_000, 2, generator=torch.Generator().manual_seed(5), dtype=F64)
    h = ndf.sample(wo, u)
    torch.testing.assert_close(h.norm(dim=-1), torch.ones(100_000, dtype=F64))
    nr, na = 24, 16
    radial = (math.pi / 2) * (torch.arange(nr + 1, dtype=F64) / nr) ** 2  # dense near the normal
    azim = torch.linspace(0, 2 * math.pi, na + 1, dtype=F64)
    ir = (torch.searchsorted(radial, torch.acos(h[:, 2].clamp(-1, 1)).contiguous(), right=True) - 1).clamp(0, nr - 1)
    psi = torch.remainder(torch.atan2(h[:, 1], h[:, 0]), 2 * math.pi)
    ia = (torch.searchsorted(azim, psi.contiguous(), right=True) - 1).clamp(0, na - 1)
    obs = torch.bincount(ir * na + ia, minlength=nr * na)

    def density(x):
        t, p = x[:, 0], x[:, 1]
        g = torch.stack((t.sin() * p.cos(), t.sin() * p.sin(), t.cos()), -1)
        return ndf.pdf(wo[:1].expand_as(g), g) * t.sin()

    gi, ai = torch.meshgrid(torch.arange(nr), torch.arange(na), indexing="ij")
    lo = torch.stack((radial[gi.reshape(-1)], azim[ai.reshape(-1)]), -1)
    hi = torch.stack((radial[gi.reshape(-1) + 1], azim[ai.reshape(-1) + 1]), -1)
    expected = adaptive_cell_integrals(density, lo, hi, nr * na, tol=1e-7) * 100_000
    assert_chi2(obs, expected, 100_000, family_size=len(NDFS), what=f"{name}: ")


def test_anisotropic_beckmann_masking_projects_the_roughness():
    w = torch.nn.functional.normalize(T([[0.7, 0.0, 0.3], [0.0, 0.6, 0.2], [0.0, 0.0, 1.0], [0.5, 0.5, 0.1]]), dim=-1)
    aniso = BeckmannNDF(T(0.1), T(0.4)).G1_over_cos(w)
    torch.testing.assert_close(aniso[0], beckmann_g1_over_cos(w[0], T(0.1)))
    torch.testing.assert_close(aniso[1], beckmann_g1_over_cos(w[1], T(0.4)))
    torch.testing.assert_close(aniso[2], T(1.0))  # at the normal G1/cos = 1
    torch.testing.assert_close(aniso[3], beckmann_g1_over_cos(w[3], T(math.sqrt((0.1**2 + 0.4**2) / 2))))
    iso = BeckmannNDF(T(0.25))
    torch.testing.assert_close(BeckmannNDF(T(0.25), T(0.25)).G1_over_cos(w), iso.G1_over_cos(w))


@pytest.mark.parametrize(
    "name, kwargs, kind",
    [
        ("cook_torrance", {"distribution": "ggx"}, GGXNDF),
        ("cook_torrance", {"distribution": "beckmann"}, BeckmannNDF),
        ("blinn_phong", {}, BlinnNDF),
        ("ward", {}, BeckmannNDF),
        ("ward_aniso", {}, BeckmannNDF),
        ("ashikhmin_shirley", {}, AnisotropicPhongNDF),
    ],
)
def test_models_take_a_distribution_built_from_their_parameters(name, kwargs, kind):
    brdf = create(name, **kwargs)
    dist = brdf.microfacet_distribution(F64)
    assert isinstance(dist, MicrofacetDistribution) and isinstance(dist, kind)
    # the distribution holds the model's parameters: gradients reach the raw Parameters
    h = torch.nn.functional.normalize(T([[0.1, 0.2, 0.9]]), dim=-1)
    dist.D(h).sum().backward()
    grads = [p.grad for n, p in brdf.named_parameters() if p.grad is not None]
    assert grads and all(bool(torch.isfinite(g).all()) for g in grads)
