from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.manifold.common import SMALL_GRID, small_model
from torch_brdf.errors import ValueRangeError
from torch_brdf.manifold.data import analytic_rows
from torch_brdf.manifold.paths import (
    best_path,
    directional_albedo,
    interpolant_diagnostics,
    latent_slice,
    resample_path,
)


def test_slice_points_and_variance():
    model, _, _ = small_model(q=3)
    c = model.latents[4]
    sl = latent_slice(model, dims=(0, 2), center=c, resolution=9)
    assert sl.points.shape == (9, 9, 3) and sl.variance.shape == (9, 9)
    assert torch.equal(sl.points[..., 1], torch.full((9, 9), float(c[1]), dtype=torch.float64))
    torch.testing.assert_close(sl.variance, model.variance(sl.points.reshape(-1, 3)).reshape(9, 9))
    assert float(sl.variance.min()) >= 0
    with pytest.raises(ValueRangeError):
        latent_slice(model, dims=(1, 1))


def _brute_force_shortest(costs: dict, n: int, s: int, e: int) -> float:
    dist = [math.inf] * n
    dist[s] = 0.0
    for _ in range(n):
        for (u, v), c in costs.items():
            if dist[u] + c < dist[v]:
                dist[v] = dist[u] + c
    return dist[e]


def test_best_path_cost_matches_bellman_ford_and_variance_weight_helps():
    model, _, _ = small_model(q=2)
    res = 6
    p = best_path(model, 0, 5, variance_weight=3.0, resolution=res)
    # rebuild the graph by hand
    lo = torch.minimum(model.latents.min(0).values, model.latents.min(0).values)
    from torch_brdf.manifold.paths import latent_bounds

    lo, hi = latent_bounds(model.latents)
    axes = [torch.linspace(float(lo[k]), float(hi[k]), res, dtype=torch.float64) for k in range(2)]
    nodes = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
    var = model.variance(nodes)
    costs = {}
    for i in range(res):
        for j in range(res):
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    a, b = i + di, j + dj
                    if (di or dj) and 0 <= a < res and 0 <= b < res:
                        u, v = i * res + j, a * res + b
                        length = float((nodes[u] - nodes[v]).norm())
                        costs[(u, v)] = length * (1 + 3.0 * float(max(var[u], var[v])))
    s = int(torch.cdist(model.latents[:1], nodes).argmin())
    e = int(torch.cdist(model.latents[5:6], nodes).argmin())
    assert abs(_brute_force_shortest(costs, res * res, s, e) - p.cost) < 1e-9 * max(1.0, p.cost)
    assert torch.equal(p.waypoints[0], model.latents[0]) and torch.equal(p.waypoints[-1], model.latents[5])
    torch.testing.assert_close(p.weights, model.weights(p.waypoints))
    # optimality on the same grid: w > 0 trades length for variance, never the reverse
    lazy = best_path(model, 0, 5, variance_weight=0.0, resolution=24)
    careful = best_path(model, 0, 5, variance_weight=100.0, resolution=24)

    def length_and_variance(path):
        g = path.waypoints[1:-1]
        var = model.variance(g)
        seg = (g[1:] - g[:-1]).norm(dim=1)
        return float(seg.sum()), float((seg * torch.maximum(var[1:], var[:-1])).sum())

    (l_lazy, v_lazy), (l_care, v_care) = length_and_variance(lazy), length_and_variance(careful)
    assert abs(l_lazy - lazy.cost) < 1e-9 * max(1.0, l_lazy)
    assert l_care >= l_lazy - 1e-9
    assert v_care <= v_lazy + 1e-9


def test_directional_albedo_of_lambert_and_linearity():
    kd = torch.tensor([[0.2, 0.9]], dtype=torch.float64)  # t2 -> kd; t1 -> sharp lobe
    rows = analytic_rows(kd, SMALL_GRID)
    # a pure constant table: albedo = pi * rho = 0.3 wherever the lookup finds valid bins
    const = torch.full_like(rows, 0.3 / math.pi)
    a = directional_albedo(const, SMALL_GRID, theta_i=torch.tensor([0.0, 0.3]))
    assert a.shape == (1, 2, 3)
    np.testing.assert_allclose(a.numpy(), 0.3, rtol=2e-2)
    two = torch.cat([rows, const])
    w = torch.tensor([[0.3, 0.7], [-0.5, 1.5]], dtype=torch.float64)
    alb = directional_albedo(two, SMALL_GRID)
    torch.testing.assert_close(directional_albedo(w @ two, SMALL_GRID), torch.einsum("mn,nkc->mkc", w, alb))
    d = interpolant_diagnostics(w, two, alb)
    assert float(d.negative_fraction[0]) == 0.0  # a convex blend of non-negative rows
    # the extrapolating blend goes negative where half the specular lobe exceeds 1.5 x the constant
    want = float(((w[1:] @ two) < 0).double().mean())
    assert want > 0 and abs(float(d.negative_fraction[1]) - want) < 1e-15


def test_resample_path_is_even_by_arc_length_and_keeps_the_ends():
    way = torch.tensor([[0.1, 0.3], [3.1, 0.3], [3.1, 1.3]], dtype=torch.float64)  # lengths 3 and 1
    pts = resample_path(way, 5)
    assert torch.equal(pts[0], way[0]) and torch.equal(pts[-1], way[-1])
    steps = (pts[1:] - pts[:-1]).norm(dim=1)
    torch.testing.assert_close(steps, torch.full((4,), 1.0, dtype=torch.float64))
    torch.testing.assert_close(pts[3], torch.tensor([3.1, 0.3], dtype=torch.float64))  # the corner
    assert torch.equal(resample_path(way[:1], 3), way[:1].expand(3, 2))  # one point: a still path
    with pytest.raises(ValueRangeError):
        resample_path(way, 0)
