"""Shading frames and Rusinkiewicz half/difference angles."""

from __future__ import annotations

import math

import torch

from torch_brdf.frame import (
    Frame,
    half_diff_angles,
    half_diff_to_directions,
    half_terms,
    half_vector,
    orthonormal_basis,
    polar_angle,
)


def _hemi(n, g, dtype=torch.float64):
    w = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=dtype), dim=-1)
    return torch.cat((w[:, :2], w[:, 2:].abs()), -1)


def test_orthonormal_basis_is_orthonormal_and_right_handed(gen):
    n = torch.nn.functional.normalize(torch.randn(1000, 3, generator=gen, dtype=torch.float64), dim=-1)
    n[0] = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)  # the pole of the branch
    s, t = orthonormal_basis(n)
    m = torch.stack((s, t, n), -2)
    torch.testing.assert_close(m @ m.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(1000, 3, 3))
    torch.testing.assert_close(torch.linalg.det(m), torch.ones(1000, dtype=torch.float64))


def test_frame_from_tangent_and_round_trip(gen):
    n = torch.nn.functional.normalize(torch.randn(64, 3, generator=gen, dtype=torch.float64), dim=-1)
    tangent = torch.randn(64, 3, generator=gen, dtype=torch.float64)
    f = Frame.from_normal(n, tangent)
    assert float((f.s * n).sum(-1).abs().max()) < 1e-12
    v = torch.randn(64, 3, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(f.to_world(f.to_local(v)), v)
    torch.testing.assert_close(f.to_local(n), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(64, 3))
    # s is the tangent's component orthogonal to n
    proj = tangent - (tangent * n).sum(-1, keepdim=True) * n
    torch.testing.assert_close(f.s, torch.nn.functional.normalize(proj, dim=-1))


def test_half_diff_round_trip_and_known_values(gen):
    wi, wo = _hemi(2000, gen), _hemi(2000, gen)
    th, ph, td, pd = half_diff_angles(wi, wo)
    a, b = half_diff_to_directions(th, ph, td, pd)
    torch.testing.assert_close(a, wi, atol=1e-12, rtol=0)
    torch.testing.assert_close(b, wo, atol=1e-12, rtol=0)
    # reciprocity swaps wi and wo: same theta_h, theta_d; phi_d shifts by pi
    th2, _, td2, pd2 = half_diff_angles(wo, wi)
    torch.testing.assert_close(th2, th)
    torch.testing.assert_close(td2, td)
    torch.testing.assert_close(torch.remainder(pd2 - pd, 2 * math.pi), torch.full_like(pd, math.pi), atol=1e-9, rtol=0)
    # mirror configuration: theta_h = 0, theta_d = incidence angle
    wi1 = torch.tensor([[math.sin(0.7), 0.0, math.cos(0.7)]], dtype=torch.float64)
    wo1 = torch.tensor([[-math.sin(0.7), 0.0, math.cos(0.7)]], dtype=torch.float64)
    th1, _, td1, _ = half_diff_angles(wi1, wo1)
    assert abs(float(th1)) < 1e-12 and abs(float(td1) - 0.7) < 1e-12


def test_half_vector_of_opposite_directions_is_finite():
    w = torch.tensor([[0.3, 0.4, math.sqrt(1 - 0.25)]])
    h = half_vector(w, -w)
    assert torch.equal(h, torch.tensor([[0.0, 0.0, 1.0]]))
    angles = half_diff_angles(w, -w)
    assert all(bool(torch.isfinite(a).all()) for a in angles)


def test_half_terms_agree_with_the_plain_formulas_and_are_reciprocal(gen):
    wi, wo = _hemi(2000, gen), _hemi(2000, gen)
    ht = half_terms(wi, wo)
    h = (wi + wo) / (wi + wo).norm(dim=-1, keepdim=True)
    torch.testing.assert_close(ht.h, h, atol=1e-13, rtol=0)
    torch.testing.assert_close(half_vector(wi, wo), ht.h, atol=1e-15, rtol=0)
    torch.testing.assert_close(ht.cos_h, h[:, 2], atol=1e-13, rtol=0)
    cos_d = (wi * h).sum(-1)
    torch.testing.assert_close(ht.cos_d, cos_d, atol=1e-13, rtol=0)
    torch.testing.assert_close(ht.one_minus_cos_d, 1 - cos_d, atol=1e-13, rtol=0)
    torch.testing.assert_close(ht.sin_d, (1 - cos_d**2).clamp_min(0).sqrt(), atol=1e-7, rtol=0)
    torch.testing.assert_close(ht.tan2, (h[:, 0] ** 2 + h[:, 1] ** 2) / h[:, 2] ** 2, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(ht.theta_d, half_diff_angles(wi, wo)[2], atol=1e-12, rtol=0)
    back = half_terms(wo, wi)  # symmetric bit for bit
    for name in ("h", "tan2", "cos_d", "one_minus_cos_d", "sin_d"):
        assert torch.equal(getattr(back, name), getattr(ht, name)), name


def test_half_vector_epsilon_policy():
    """h = s/|s| above eps(dtype), +z at or below it (documented in torch_brdf.frame)."""
    for dt in (torch.float32, torch.float64):
        eps = torch.finfo(dt).eps
        w = torch.tensor([[0.6, 0.0, 0.8]], dtype=dt)
        below = torch.tensor([[-0.6, 0.0, -0.8 + 0.5 * eps]], dtype=dt)  # |wi + wo| = eps/2
        above = torch.tensor([[-0.6, 0.0, -0.8 + 4 * eps]], dtype=dt)  # |wi + wo| = 4 eps
        assert torch.equal(half_vector(w, below), torch.tensor([[0.0, 0.0, 1.0]], dtype=dt))
        assert torch.equal(half_terms(w, below).h, torch.tensor([[0.0, 0.0, 1.0]], dtype=dt))
        torch.testing.assert_close(half_vector(w, above), torch.tensor([[0.0, 0.0, 1.0]], dtype=dt))
        assert float(half_terms(w, above).cos_d) > 0


def test_frame_matrix_and_tangent_along_the_normal(gen):
    n = torch.nn.functional.normalize(torch.randn(64, 3, generator=gen, dtype=torch.float64), dim=-1)
    f = Frame.from_normal(n, torch.randn(64, 3, generator=gen, dtype=torch.float64))
    v = torch.randn(64, 3, generator=gen, dtype=torch.float64)
    torch.testing.assert_close((f.matrix() @ v[:, :, None])[..., 0], f.to_local(v))
    # a tangent (e.g. a view) along the normal has no tangential part: Duff's basis instead
    g = Frame.from_normal(n, 2.0 * n)
    duff = Frame.from_normal(n)
    torch.testing.assert_close(g.s, duff.s)
    torch.testing.assert_close(g.t, duff.t)
    m = g.matrix()
    torch.testing.assert_close(m @ m.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(64, 3, 3))


def test_polar_angle(gen):
    w = _hemi(100, gen)
    torch.testing.assert_close(polar_angle(w), torch.acos(w[:, 2]), atol=1e-7, rtol=0)
    assert float(polar_angle(torch.tensor([0.0, 1e-20, 1.0], dtype=torch.float64))) == 1e-20


def test_half_and_angle_gradients_are_finite_where_the_functions_are_singular():
    # the module's epsilon policy promises finite gradients: sqrt(0) at wi = -wo (the sum's
    # length), at wi = wo (sin theta_d) and atan2(0, 0) at the pole gave NaN
    z, x = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    wi = torch.stack([-z, z, x, -x]).requires_grad_(True)
    wo = torch.stack([z, z, -x, x]).requires_grad_(True)
    ht = half_terms(wi, wo)
    loss = sum(t.sum() for t in (ht.h, ht.cos_d, ht.sin_d, ht.one_minus_cos_d)) + half_vector(wi, wo).sum()
    loss = loss + sum(a.sum() for a in half_diff_angles(wi, wo))
    gi, go = torch.autograd.grad(loss, (wi, wo))
    assert bool(torch.isfinite(gi).all()) and bool(torch.isfinite(go).all())
    assert ht.cos_d[0] == 0 and ht.sin_d[1] == 0  # the values at the singular points are exact
