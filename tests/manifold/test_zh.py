from __future__ import annotations

import math

import numpy as np
import torch

from tests.manifold.common import SMALL_GRID, small_family
from torch_brdf.manifold.zh import (
    _quadrature,
    env_sh,
    legendre,
    rows_brdf,
    sh_basis,
    zh_coefficients,
    zh_convolution,
    zh_shade,
)
from torch_brdf.scene.envmap import EnvironmentMap


def _sphere_rule(n_theta=40, n_phi=80):
    d, w = _quadrature(n_theta, n_phi)
    return torch.cat([d, d * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)]), torch.cat([w, w])


def test_sh_orthonormal_and_known_values():
    d, w = _sphere_rule()
    y = sh_basis(d, 6)
    torch.testing.assert_close((y * w[:, None]).T @ y, torch.eye(49, dtype=torch.float64), atol=1e-12, rtol=0)
    z = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    x = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    assert abs(float(sh_basis(z, 0)[0, 0]) - 0.5 / math.sqrt(math.pi)) < 1e-15
    assert abs(float(sh_basis(z, 1)[0, 2]) - math.sqrt(3 / (4 * math.pi))) < 1e-15
    # Condon-Shortley phase: Y_11 = -sqrt(3/4pi) x
    assert abs(float(sh_basis(x, 1)[0, 3]) + math.sqrt(3 / (4 * math.pi))) < 1e-15


def test_addition_theorem(gen):
    a = torch.nn.functional.normalize(torch.randn(5, 3, generator=gen, dtype=torch.float64), dim=-1)
    b = torch.nn.functional.normalize(torch.randn(5, 3, generator=gen, dtype=torch.float64), dim=-1)
    ya, yb = sh_basis(a, 8), sh_basis(b, 8)
    p = legendre((a * b).sum(-1), 8)
    for l in range(9):
        s = (ya[:, l * l : (l + 1) ** 2] * yb[:, l * l : (l + 1) ** 2]).sum(-1)
        torch.testing.assert_close(s, (2 * l + 1) / (4 * math.pi) * p[:, l], rtol=1e-12, atol=1e-12)


def test_funk_hecke_zh_convolution_equals_direct_integral(gen):
    """C_l(a) = int f(w) Y_l^0(w . a) dw for a band-limited f, by brute-force quadrature."""
    order = 5
    coef = torch.randn(36, 3, generator=gen, dtype=torch.float64)
    d, w = _sphere_rule(60, 120)
    f = sh_basis(d, order) @ coef
    a = torch.nn.functional.normalize(torch.randn(4, 3, generator=gen, dtype=torch.float64), dim=-1)
    for l in range(order + 1):
        zh = math.sqrt((2 * l + 1) / (4 * math.pi)) * legendre(d @ a.T, l)[..., l]  # (Q, 4)
        direct = torch.einsum("qc,qa,q->ac", f, zh, w)
        torch.testing.assert_close(zh_convolution(coef, a, l), direct, rtol=1e-10, atol=1e-10)


def test_zh_shading_equals_quadrature_for_band_limited_light(gen):
    """Band-limited lighting: Parseval makes ZH shading exact up to the BRDF projection's quadrature."""
    order = 6
    e_lm = torch.randn(49, 3, generator=gen, dtype=torch.float64)

    def glossy(wi, wo):
        h = torch.nn.functional.normalize(wi + wo, dim=-1)
        val = 0.2 / math.pi + 0.3 * h[..., 2].clamp_min(0) ** 4
        return val[None, :, None].expand(1, wi.shape[0], 3) * torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64)

    zc = zh_coefficients(glossy, order, n_view=16, n_theta=48, n_phi=96, max_view_deg=80.0)
    n = torch.nn.functional.normalize(torch.randn(6, 3, generator=gen, dtype=torch.float64), dim=-1)
    # views at exactly tabulated elevations so no theta_o interpolation error enters
    th = zc.theta_o[torch.tensor([0, 3, 6, 9, 12, 15])]
    t = torch.nn.functional.normalize(
        torch.linalg.cross(n, torch.randn(6, 3, generator=gen, dtype=torch.float64)), dim=-1
    )
    v = th.cos()[:, None] * n + th.sin()[:, None] * t
    got = zh_shade(n, v, zc.mu[0], zc.theta_o, e_lm, order)
    d, w = _quadrature(96, 192)
    from torch_brdf.frame import orthonormal_basis

    for p in range(6):
        s, b2 = orthonormal_basis(n[p : p + 1])
        rot = torch.stack((s[0], b2[0], n[p]), -1)  # local -> world
        wo_local = rot.T @ v[p]
        world = d @ rot.T
        e = sh_basis(world, order) @ e_lm
        f = glossy(d, wo_local.expand_as(d))[0]
        ref = (e * f * d[:, 2:3] * w[:, None]).sum(0)
        np.testing.assert_allclose(got[p].numpy(), ref.numpy(), rtol=1e-6, atol=1e-6 * float(ref.abs().max()))


def test_lambert_zh_shading_converges_to_irradiance():
    env = EnvironmentMap.sky(sun_radiance=(600.0, 570.0, 520.0), height=32, supersample=2)
    order = 10
    e_lm = env_sh(env, order)
    alb = 0.5
    zc = zh_coefficients(lambda wi, wo: torch.full((1, wi.shape[0], 3), alb / math.pi, dtype=torch.float64), order, 4)
    g = torch.Generator().manual_seed(5)
    n = torch.nn.functional.normalize(torch.randn(10, 3, generator=g, dtype=torch.float64), dim=-1)
    got = zh_shade(n, n, zc.mu[0], zc.theta_o, e_lm, order)
    ref = env.irradiance(n) * alb / math.pi
    assert float(((got - ref).abs() / ref.abs()).max()) < 0.03  # SH truncation of the clamped cosine


def test_zh_vectors_are_linear_in_the_rows():
    obs, _ = small_family(3)
    z = obs.z.double()
    b = torch.tensor([0.7, -0.2, 0.5], dtype=torch.float64)
    zc = zh_coefficients(rows_brdf(z, SMALL_GRID), 4, n_view=3, n_theta=16, n_phi=32)
    one = zh_coefficients(rows_brdf((b @ z)[None], SMALL_GRID), 4, n_view=3, n_theta=16, n_phi=32)
    torch.testing.assert_close(zc.blend(b), one.mu[0], rtol=1e-10, atol=1e-12)
