"""Shading frames and Rusinkiewicz half/difference angles."""

from __future__ import annotations

import math

import torch

from torch_brdf.frame import Frame, half_diff_angles, half_diff_to_directions, half_vector, orthonormal_basis


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
