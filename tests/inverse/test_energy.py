"""Energy rows g_j^l (Eq. 15) against the BRDF's own albedo integral."""

from __future__ import annotations

import math

import pytest
import torch

from torch_brdf.brdf.analytic import DistributionBased
from torch_brdf.brdf.srbf import SRBFDistribution
from torch_brdf.errors import ShapeError, ValueRangeError
from torch_brdf.frame import orthonormal_basis
from torch_brdf.inverse import energy_rows, outgoing_directions
from torch_brdf.inverse.energy import default_basis


def test_outgoing_directions_are_192_on_the_hemisphere():
    d = outgoing_directions()
    assert d.shape == (192, 3)
    assert bool((d[:, 2] > 0).all())
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(192, dtype=torch.float64))


def _albedo_around(brdf, wo: torch.Tensor, axis: torch.Tensor, n: int = 400) -> float:
    """Oracle: int f(wi, wo) max(0, cos theta_i) d wi on an n x n midpoint grid in polar
    coordinates about ``axis`` (the lobe's mirror direction), i.e. in the wi domain, not the
    half-vector domain of energy_rows."""
    t = (torch.arange(n, dtype=torch.float64) + 0.5) * (math.pi / n)
    p = (torch.arange(n, dtype=torch.float64) + 0.5) * (2 * math.pi / n)
    T, P = torch.meshgrid(t, p, indexing="ij")
    s_, t_ = orthonormal_basis(axis)
    local = torch.stack((torch.sin(T) * torch.cos(P), torch.sin(T) * torch.sin(P), torch.cos(T)), -1)
    wi = local[..., :1] * s_ + local[..., 1:2] * t_ + local[..., 2:] * axis
    dw = torch.sin(T) * (math.pi / n) * (2 * math.pi / n)
    with torch.no_grad():
        f = brdf.eval_local(wi.reshape(-1, 3), wo.expand(n * n, 3))[:, 0]
    return float((f * wi.reshape(-1, 3)[:, 2].clamp_min(0) * dw.reshape(-1)).sum())


def test_rows_match_an_incident_direction_quadrature():
    f0 = 0.25  # exercises both Fresnel parts
    basis = default_basis()
    rows = energy_rows(basis).rows([f0])[0]
    wo = outgoing_directions()
    for j, l in [(0, 0), (60, 100), (146, 191)]:
        c = torch.zeros(147, dtype=torch.float64)
        c[j] = 1.0
        brdf = DistributionBased(SRBFDistribution(basis, c), kd=0.0, f0=f0).double()
        xi = basis.centers[j]
        mirror = 2 * (wo[l] @ xi) * xi - wo[l]
        a = _albedo_around(brdf, wo[l], mirror)
        assert float(rows[l, j]) == pytest.approx(a, rel=3e-4, abs=1e-9)


def test_rows_are_cached_and_fresnel_linear():
    e1, e2 = energy_rows(), energy_rows()
    assert e1 is e2
    g = e1.rows([1.0, 0.0, 0.5])
    torch.testing.assert_close(g[0], e1.plain)
    torch.testing.assert_close(g[1], e1.schlick)
    torch.testing.assert_close(g[2], 0.5 * (e1.plain + e1.schlick))
    assert bool((e1.schlick <= e1.plain).all())


def test_bad_directions_and_f0():
    with pytest.raises(ValueRangeError):
        energy_rows(directions=torch.tensor([[0.0, 0.0, -1.0]]))
    with pytest.raises(ShapeError):
        energy_rows(directions=torch.zeros(4, 2))
    with pytest.raises(ValueRangeError):
        energy_rows().rows([1.5])
