"""The bilinear (Mitsuba 3) reading of environment maps: lookup, sampling density, sums.

Oracles: a map that is exactly bilinear in (phi, theta) between the nodes (so the lookup must
reproduce it in every direction), a smooth analytic map (second-order convergence), the
exact cell probabilities of the bilinear sampling density (chi-square) and a dense quadrature
of the pdf. Mitsuba itself is the peer in ``tests/transport/test_mitsuba.py``.
"""

from __future__ import annotations

import math

import pytest
import torch

from tests._stats import assert_chi2
from torch_brdf.errors import ValueRangeError
from torch_brdf.scene.envmap import EnvironmentMap
from torch_brdf.sphere import square_to_uniform_sphere
from torch_brdf.sphere.latlong import (
    bilinear_lookup,
    direction_to_latlong,
    latlong_to_direction,
    node_directions,
    node_solid_angles,
)


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def uniform_dirs(n: int, seed: int) -> torch.Tensor:
    return square_to_uniform_sphere(torch.rand(n, 2, generator=gen(seed), dtype=torch.float64))


def piecewise_bilinear(theta: torch.Tensor, phi: torch.Tensor, W: int) -> torch.Tensor:
    """1 + (theta / pi) * tri(phi): bilinear in (phi, theta) inside every node cell, because
    the triangle wave tri has its kinks at phi_0 = pi / W and phi_0 + pi, both node columns."""
    phi0 = math.pi / W
    tri = (torch.remainder(phi - phi0, 2 * math.pi) - math.pi).abs()
    base = 1 + theta / math.pi * tri
    return torch.stack([base, 2 * base, 0.5 + 0 * base], -1)


def test_lookup_reproduces_a_map_bilinear_between_nodes():
    H, W = 9, 18
    theta = torch.arange(H, dtype=torch.float64)[:, None] * (math.pi / (H - 1))
    phi = (torch.arange(W, dtype=torch.float64)[None, :] + 0.5) * (2 * math.pi / W)
    L = piecewise_bilinear(theta.expand(H, W), phi.expand(H, W), W)
    e = EnvironmentMap(L)
    d = uniform_dirs(20_000, 0)
    t, p = direction_to_latlong(d)
    torch.testing.assert_close(e.eval_miss(d), piecewise_bilinear(t, p, W).float().double(), rtol=1e-5, atol=1e-5)
    # the nearest reading of the same array misses it by a texel's worth
    near = EnvironmentMap(L, lookup="nearest").eval_miss(d)
    assert float((near - e.eval_miss(d)).abs().max()) > 0.1


def test_lookup_converges_on_a_smooth_map_at_second_order():
    """L = exp(cos(angle to a)) sampled at the nodes: the max error falls ~4x per doubling."""
    a = torch.nn.functional.normalize(torch.tensor([0.3, 0.5, -0.8], dtype=torch.float64), dim=0)
    d = uniform_dirs(20_000, 1)
    errs = []
    for H in (16, 32, 64):
        L = torch.exp(node_directions(H, 2 * H) @ a)[..., None].expand(-1, -1, 3)
        got = bilinear_lookup(L, d)[:, 0]
        errs.append(float((got - torch.exp(d @ a)).abs().max()))
    assert 3.0 < errs[0] / errs[1] < 5.0 and 3.0 < errs[1] / errs[2] < 5.0, errs


def test_integral_is_exact_for_the_interpolated_map():
    """sum L Omega against a dense midpoint quadrature of the bilinear function."""
    H, W = 6, 12
    L = torch.rand(H, W, 3, generator=gen(2), dtype=torch.float64) + 0.1
    e = EnvironmentMap(L)
    n = 800
    theta = (torch.arange(n, dtype=torch.float64) + 0.5) * (math.pi / n)
    phi = (torch.arange(2 * n, dtype=torch.float64) + 0.5) * (math.pi / n)
    d = latlong_to_direction(theta[:, None], phi[None, :])
    dense = (e.eval_miss(d) * (theta.sin() * (math.pi / n) ** 2)[:, None, None]).sum((0, 1))
    torch.testing.assert_close(e.integral(), dense, rtol=2e-5, atol=0.0)
    assert abs(float(node_solid_angles(H, W).sum()) - 4 * math.pi) < 1e-12


def sparse_map(H: int, seed: int) -> torch.Tensor:
    g = gen(seed)
    L = torch.rand(H, 2 * H, 3, generator=g) * 2
    return L * (torch.rand(H, 2 * H, 1, generator=g) < 0.3) + torch.tensor([0.0, 0.01, 0.0])


@pytest.mark.parametrize("kind", ["random", "sparse", "sky", "black"])
def test_pdf_integrates_to_one(kind):
    e = {
        "random": lambda: EnvironmentMap(torch.rand(8, 16, 3, generator=gen(3))),
        "sparse": lambda: EnvironmentMap(sparse_map(8, 4)),
        "sky": lambda: EnvironmentMap.sky(height=32, sun_angular_radius_deg=4.0),
        "black": lambda: EnvironmentMap.constant(0.0, height=8),
    }[kind]()
    n = 1200
    theta = (torch.arange(n, dtype=torch.float64) + 0.5) * (math.pi / n)
    phi = (torch.arange(2 * n, dtype=torch.float64) + 0.5) * (math.pi / n)
    d = latlong_to_direction(theta[:, None], phi[None, :])
    total = float((e.pdf(d) * (theta.sin() * (math.pi / n) ** 2)[:, None]).sum())
    assert abs(total - 1) < 2e-4, total


def test_sampling_chi2_against_the_exact_cell_probabilities():
    r"""Histogram over 2 x 2 sub-cells (in (u, v)) of every cell between nodes. The sampling
    density is bilinear in (u, v) inside a cell, so a sub-cell's probability is exactly its
    centre's density times its (u, v) area: :math:`p_\omega\,2\pi^2\sin\theta\,\Delta u\Delta v`."""
    H, W, n = 5, 10, 300_000
    L = sparse_map(H, 5)
    L[2, 3] = 0.0
    e = EnvironmentMap(L)
    d, p = e.sample_directions(n, gen(6), dtype=torch.float64)
    torch.testing.assert_close(p, e.pdf(d), rtol=1e-12, atol=0.0)
    theta, phi = direction_to_latlong(d)
    v = (theta / math.pi * (H - 1) * 2).floor().long().clamp(0, 2 * (H - 1) - 1)
    u = (torch.remainder(phi / (2 * math.pi) * W - 0.5, W) * 2).floor().long().clamp(0, 2 * W - 1)
    counts = torch.bincount(v * 2 * W + u, minlength=4 * (H - 1) * W).double()
    vc = (torch.arange(2 * (H - 1), dtype=torch.float64) + 0.5) / (2 * (H - 1))
    uc = (torch.arange(2 * W, dtype=torch.float64) + 0.5) / (2 * W) + 0.5 / W
    centre = latlong_to_direction(vc[:, None] * math.pi, uc[None, :] * 2 * math.pi)
    prob = e.pdf(centre) * 2 * math.pi**2 * (vc * math.pi).sin()[:, None] / (4 * (H - 1) * W)
    assert abs(float(prob.sum()) - 1) < 1e-12
    assert_chi2(counts, n * prob.reshape(-1), n, what="bilinear envmap sampler")


def test_importance_sampling_estimates_the_integral():
    e = EnvironmentMap.sky(height=32, sun_angular_radius_deg=3.0)
    s = e.sample(torch.zeros(65_536, 3, dtype=torch.float64), gen(7))
    torch.testing.assert_close(s.weight.mean(0), e.integral(), rtol=0.01, atol=0.0)


def sun_centroid_error_deg(e: EnvironmentMap, no_sun: EnvironmentMap, sun: torch.Tensor) -> float:
    """Angle between ``sun`` and the centroid of the looked-up radiance excess (dense quadrature)."""
    n, ts, ps = 1500, math.acos(float(sun[1])), math.atan2(float(sun[0]), -float(sun[2]))
    f = (torch.arange(n, dtype=torch.float64) + 0.5) / n - 0.5
    th, ph = ts + 0.2 * f, ps + 0.3 * f
    d = latlong_to_direction(th[:, None], ph[None, :])
    w = (e.eval_miss(d) - no_sun.eval_miss(d)).mean(-1) * th.sin()[:, None]
    c = torch.nn.functional.normalize((w[..., None] * d).sum((0, 1)), dim=0)
    return math.degrees(math.acos(min(1.0, float(c @ sun))))


def test_sky_sun_sits_where_it_was_put():
    """The bilinear sky's sun, as the bilinear lookup (and Mitsuba) sees it, is centred on the
    requested direction; a texel-centred sky read bilinearly (its array handed to Mitsuba as
    it is) is not."""
    sun = torch.nn.functional.normalize(torch.tensor([0.5, 0.6, -0.62], dtype=torch.float64), dim=0)
    kw = {"height": 128, "sun_direction": sun.tolist(), "sun_angular_radius_deg": 1.5}
    e, no_sun = EnvironmentMap.sky(**kw), EnvironmentMap.sky(**kw, sun_radiance=0.0)
    assert sun_centroid_error_deg(e, no_sun, sun) < 0.03
    near, near_no_sun = (EnvironmentMap.sky(**kw, sun_radiance=r, lookup="nearest") for r in (3000.0, 0.0))
    as_is = [EnvironmentMap(x.radiance) for x in (near, near_no_sun)]
    assert sun_centroid_error_deg(*as_is, sun) > 0.1


def test_unknown_lookup_is_refused():
    with pytest.raises(ValueRangeError, match="lookup must be one of"):
        EnvironmentMap(torch.ones(4, 8, 3), lookup="bicubic")


def test_lookup_is_part_of_the_scene_content():
    """Records made under one lookup are not resumed under the other."""
    import trimesh

    from torch_brdf.scene import Camera, Scene, SceneObject, mesh_from_arrays

    ball = trimesh.creation.icosphere(subdivisions=1)
    objects = [SceneObject("ball", mesh_from_arrays(ball.vertices, ball.faces), "m")]
    cam = Camera((0, 0, 3), (0, 0, 0), width=4, height=4)
    keys = {
        lk: Scene(objects, {"m": {"type": "lambert"}}, [EnvironmentMap.constant(1.0, 4, lookup=lk)], cam)
        for lk in ("bilinear", "nearest")
    }
    assert keys["bilinear"].content_digest() != keys["nearest"].content_digest()
