"""Gaussian SRBFs on the half vector (Iwasaki et al., Eq. 12): centres, bandwidth,
normalisation integrals, sampling, and use as the p(h) of the distribution-based BRDF."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests._stats import assert_chi2
from tests.brdf.common import BRDFContract
from torch_brdf.brdf import create
from torch_brdf.brdf.srbf import (
    SRBFBasis,
    SRBFDistribution,
    hemicube_centers,
    lambda_from_sigma,
    sigma_from_lambda,
)
from torch_brdf.errors import ShapeError, ValueRangeError

F64 = torch.float64


def sphere_grid(n_theta: int, n_phi: int, upper_only: bool = True, order: int = 6):
    """Composite Gauss-Legendre in theta x midpoint in phi: directions (M, 3), weights (M,)."""
    x, w = np.polynomial.legendre.leggauss(order)
    top = math.pi / 2 if upper_only else math.pi
    e = torch.linspace(0, top, n_theta + 1, dtype=F64)
    width = (e[1:] - e[:-1])[:, None]
    th = (e[:-1, None] + width * torch.from_numpy(0.5 * (x + 1))).reshape(-1)
    wt = (width * torch.from_numpy(0.5 * w)).reshape(-1)
    ph = (torch.arange(n_phi, dtype=F64) + 0.5) * (2 * math.pi / n_phi)
    T, P = torch.meshgrid(th, ph, indexing="ij")
    d = torch.stack((T.sin() * P.cos(), T.sin() * P.sin(), T.cos()), -1).reshape(-1, 3)
    wts = (wt[:, None] * T.sin() * (2 * math.pi / n_phi)).reshape(-1)
    return d, wts


# -- centres -------------------------------------------------------------------------------------
def test_hemicube_has_147_unit_upper_centres():
    c = hemicube_centers(7)
    assert c.shape == (147, 3) and c.dtype == F64
    torch.testing.assert_close(c.norm(dim=-1), torch.ones(147, dtype=F64))
    assert bool((c[:, 2] > 0).all())
    assert torch.cdist(c, c).add(torch.eye(147, dtype=F64)).min() > 0.05  # distinct, well spread
    assert bool((c == torch.tensor([0.0, 0.0, 1.0], dtype=F64)).all(-1).any())  # the top face's centre pixel
    flipped = c * torch.tensor([-1.0, -1.0, 1.0], dtype=F64)  # the layout is symmetric under 180 degrees
    assert (flipped[:, None] - c[None]).norm(dim=-1).min(-1).values.max() < 1e-12
    for n in range(1, 9):
        assert hemicube_centers(n).shape == (3 * n * n, 3)
    with pytest.raises(ValueRangeError):
        hemicube_centers(0)


# -- bandwidth -----------------------------------------------------------------------------------
def test_lambda_of_sigma_and_its_inverse():
    lam = lambda_from_sigma(math.pi / 40)
    assert abs(lam - 81.0569) < 1e-3
    assert abs(lam - 1 / (2 * (math.pi / 40) ** 2)) < 0.01 * lam  # sigma^2 ~ 1/(2 lambda)
    for s in (0.01, 0.1, math.pi / 40, 0.5, 0.9):
        assert abs(sigma_from_lambda(lambda_from_sigma(s)) - s) < 1e-10
    with pytest.raises(ValueRangeError):
        lambda_from_sigma(1.5)


@pytest.mark.parametrize("sigma", [math.pi / 40, 0.3])
def test_sigma_is_the_spherical_variance_of_g_squared(sigma):
    """sigma^2 = 1 - |E[h]| under the density |G|^2 / ||G||^2 on the sphere (Narcowich-Ward),
    by brute-force quadrature over the whole sphere for an off-axis centre."""
    basis = SRBFBasis(centers=[[0.3, -0.2, 0.8]], sigma=sigma)
    d, w = sphere_grid(400, 400, upper_only=False)
    g2 = basis.eval(d)[:, 0] ** 2 * w
    mean = (d * g2[:, None]).sum(0) / g2.sum()
    assert abs((1 - float(mean.norm())) - sigma**2) < 1e-6 * max(1.0, 1 / sigma**2) * sigma**2 + 1e-9


# -- the basis -----------------------------------------------------------------------------------
def test_basis_eval_shapes_and_values():
    b = SRBFBasis()
    assert b.K == 147
    h = torch.randn(4, 5, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    h = h / h.norm(dim=-1, keepdim=True)
    g = b.eval(h)
    assert g.shape == (4, 5, 147) and g.dtype == F64 and bool(((g > 0) & (g <= 1)).all())
    torch.testing.assert_close(torch.diagonal(b.eval(b.centers)), torch.ones(147, dtype=F64))
    assert b.eval(h.float()).dtype == torch.float32
    assert b.eval() is b and not b.training  # no argument: nn.Module.eval
    with pytest.raises(ShapeError):
        b.eval(torch.ones(4, 2))


def test_normalisation_integrals_closed_form_and_quadrature():
    b = SRBFBasis()
    lam = b.bandwidth
    ic, i0 = b.integrals(cosine=True), b.integrals(cosine=False)
    pole = int(torch.argmax(b.centers[:, 2]))
    assert abs(float(ic[pole]) - 2 * math.pi * ((lam - 1) + math.exp(-lam)) / lam**2) < 1e-12
    assert abs(float(i0[pole]) - 2 * math.pi * -math.expm1(-lam) / lam) < 1e-12
    d, w = sphere_grid(90, 360)
    g = b.eval(d)
    torch.testing.assert_close((g * (w * d[:, 2])[:, None]).sum(0), ic, rtol=1e-6, atol=0)
    torch.testing.assert_close((g * w[:, None]).sum(0), i0, rtol=1e-6, atol=0)
    # centres near the horizon lose part of their lobe below it
    assert float(i0.min()) < 0.75 * 2 * math.pi * -math.expm1(-2 * lam) / lam


# -- the distribution ------------------------------------------------------------------------------
def test_distribution_values_normalisation_and_protocol():
    p = SRBFDistribution()
    torch.testing.assert_close(p.normalization().detach(), torch.tensor(0.25, dtype=F64))
    assert abs(float(p.albedo_scale().detach()) - 1) < 1e-6
    c = torch.rand(147, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    prgb = SRBFDistribution(p.basis, c)
    h = torch.tensor([[0.1, 0.2, 0.97], [0.3, 0.0, -0.95]], dtype=F64)
    h = h / h.norm(dim=-1, keepdim=True)
    v = prgb(h)
    assert v.shape == (2, 3) and bool((v[0] > 0).all()) and bool((v[1] == 0).all())
    torch.testing.assert_close(v[0], p.basis.eval(h[0]) @ c)
    torch.testing.assert_close(prgb.normalized().normalization(), torch.ones(3, dtype=F64))
    with pytest.raises(ValueRangeError):
        SRBFDistribution(p.basis, -c)
    with pytest.raises(ShapeError):
        SRBFDistribution(p.basis, torch.ones(10))


def _sampled(seed: int, n: int):
    c = torch.zeros(147, dtype=F64)
    c[[0, 24, 60, 130, 146]] = torch.tensor([1.0, 2.0, 0.5, 1.5, 3.0], dtype=F64)  # incl. horizon-strip lobes
    p = SRBFDistribution(SRBFBasis(sigma=0.1), c)
    u = torch.rand(n, 2, generator=torch.Generator().manual_seed(seed), dtype=F64)
    h, pdf = p.sample(u)
    return p, h, pdf


def test_sampling_pdf_is_exact_and_normalised():
    p, h, pdf = _sampled(2, 2000)
    assert bool((h[:, 2] >= 0).all()) and bool((pdf > 0).all())
    torch.testing.assert_close(h.norm(dim=-1), torch.ones(2000, dtype=F64))
    torch.testing.assert_close(pdf, p.pdf(h))
    torch.testing.assert_close(p.pdf_h(h), pdf)
    assert p.sample_h(torch.rand(7, 2, dtype=F64)).shape == (7, 3)
    d, w = sphere_grid(120, 480)
    q = p.pdf(d).detach()
    assert abs(float((q * w).sum()) - 1) < 1e-6  # folded mixture: a density on the hemisphere
    # exactly the normalised vMF mixture of p's lobes, folded: q(h) = k (P(h) + P(h~)) with P the
    # unmasked sum of c_k G_k and k = lambda / (2 pi (1 - exp(-2 lambda)) sum c)
    lam, c = p.basis.bandwidth, p.coefficients.detach().double()
    k = lam / (2 * math.pi * -math.expm1(-2 * lam)) / float(c.sum())
    flip = torch.tensor([1.0, 1.0, -1.0], dtype=F64)
    torch.testing.assert_close(q, k * (p.basis.eval(d) @ c + p.basis.eval(d * flip) @ c), rtol=1e-10, atol=0)


def test_sampling_chi2_and_mc():
    n = 200_000
    p, h, pdf = _sampled(3, n)
    # cells: 16 rings uniform in cos(theta) x 32 azimuths; expectations by quadrature of the pdf
    nr, na = 16, 32
    ring = ((1 - h[:, 2]) * nr).long().clamp_max(nr - 1)
    az = ((torch.atan2(h[:, 1], h[:, 0]) % (2 * math.pi)) / (2 * math.pi) * na).long().clamp_max(na - 1)
    obs = torch.bincount(ring * na + az, minlength=nr * na).double()
    d, w = sphere_grid(128, 512)
    dr = ((1 - d[:, 2]) * nr).long().clamp_max(nr - 1)
    da = ((torch.atan2(d[:, 1], d[:, 0]) % (2 * math.pi)) / (2 * math.pi) * na).long().clamp_max(na - 1)
    exp = torch.zeros(nr * na, dtype=F64).index_add_(0, dr * na + da, p.pdf(d).detach() * w) * n
    assert_chi2(obs, exp, n)
    # MC: E[g / pdf] = integral of g over the hemisphere, for g = p(h) cos(theta_h)
    est = (p(h).detach() * h[:, 2] / pdf.detach()).mean()
    torch.testing.assert_close(est, p.normalization().detach(), rtol=1e-2, atol=0)


def test_fit_recovers_a_mixture_in_the_span():
    basis = SRBFBasis()
    c = torch.zeros(147, dtype=F64)
    c[[10, 24, 100]] = torch.tensor([0.5, 2.0, 1.0], dtype=F64)
    fit = SRBFDistribution.fit(lambda h: basis.eval(h) @ c, basis, n_theta=64, n_phi=64)
    torch.testing.assert_close(fit.coefficients.detach().double(), c, rtol=0, atol=1e-6)


def test_plugs_into_the_distribution_based_brdf():
    import torch_brdf.brdf.analytic  # noqa: F401  (registers "distribution_based")

    p = SRBFDistribution()
    brdf = create("distribution_based", distribution=p, kd=0.1, f0=0.5)
    assert brdf.anisotropic
    g = torch.Generator().manual_seed(4)
    wi = torch.randn(100, 3, generator=g, dtype=F64)
    wo = torch.randn(100, 3, generator=g, dtype=F64)
    wi[:, 2], wo[:, 2] = wi[:, 2].abs(), wo[:, 2].abs()
    wi, wo = wi / wi.norm(dim=-1, keepdim=True), wo / wo.norm(dim=-1, keepdim=True)
    brdf = brdf.double()
    torch.testing.assert_close(brdf.eval(wi, wo), brdf.eval(wo, wi))
    loss = brdf.eval(wi, wo).sum()
    loss.backward()
    assert p.raw_coefficients.grad is not None and float(p.raw_coefficients.grad.abs().sum()) > 0


@pytest.fixture(scope="module")
def fitted_blinn():
    from torch_brdf.brdf.analytic import BlinnDistribution

    target = BlinnDistribution(30.0)
    return SRBFDistribution.fit(lambda h: target(h), n_theta=48, n_phi=48).normalized().coefficients.detach() / 4


class TestDistributionBasedSRBF(BRDFContract):
    """The distribution-based BRDF with an SRBF p(h) (a Blinn n = 30 lobe fitted with the 147
    hemicube SRBFs, normalised to 4 int p cos = 1), sampled through the SRBF sampler."""

    chi2_thetas = (40.0,)
    mc_thetas = (0.0, 60.0)
    albedo_thetas = (0.0, 45.0, 80.0, 89.9)

    def extremes(self, dtype):
        return []  # one parameter setting: make() is already checked

    @pytest.fixture(autouse=True)
    def _coefficients(self, fitted_blinn):
        self._c = fitted_blinn

    def make(self, dtype):
        p = SRBFDistribution(SRBFBasis(), self._c)
        return create("distribution_based", distribution=p, kd=0.1, f0=0.3).to(dtype)
