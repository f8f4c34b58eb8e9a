"""Lat-long geometry: the Mitsuba-compatible convention, texel lookup and solid angles."""

from __future__ import annotations

import math

import pytest
import torch

from torch_brdf.errors import ShapeError
from torch_brdf.sphere import (
    direction_to_latlong,
    direction_to_texel,
    latlong_to_direction,
    row_cos_bounds,
    square_to_uniform_sphere,
    texel_centers,
    texel_solid_angles,
)

ROUND_TRIP_TOL = {torch.float32: 2e-6, torch.float64: 1e-13}


def random_dirs(n=10_000, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return square_to_uniform_sphere(torch.rand(n, 2, generator=g, dtype=torch.float64)).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_round_trip(dtype):
    d = random_dirs(dtype=dtype)
    theta, phi = direction_to_latlong(d)
    assert theta.dtype == dtype and phi.dtype == dtype
    assert bool((theta >= 0).all() and (theta <= math.pi).all())
    assert bool((phi >= 0).all() and (phi < 2 * math.pi).all())
    back = latlong_to_direction(theta, phi)
    assert (back - d).abs().max() < ROUND_TRIP_TOL[dtype]


def test_mitsuba_convention():
    """theta = acos(y), phi = atan2(x, -z) mod 2 pi (Mitsuba 3 envmap, identity to_world)."""
    d = random_dirs()
    theta, phi = direction_to_latlong(d)
    x, y, z = d.unbind(-1)
    assert torch.allclose(theta, y.clamp(-1, 1).acos(), atol=1e-7)
    assert torch.allclose(phi, torch.remainder(torch.atan2(x, -z), 2 * math.pi), atol=1e-12)
    pi = math.pi
    cases = {  # (theta, phi) -> direction
        (pi / 2, 0.0): (0.0, 0.0, -1.0),  # phi = 0 looks down -z
        (pi / 2, pi / 2): (1.0, 0.0, 0.0),  # phi = pi/2 looks down +x
        (pi / 2, pi): (0.0, 0.0, 1.0),
        (pi / 2, 3 * pi / 2): (-1.0, 0.0, 0.0),
        (0.0, 1.234): (0.0, 1.0, 0.0),  # theta = 0 is +y (up)
    }
    for (t, p), want in cases.items():
        got = latlong_to_direction(torch.tensor(t, dtype=torch.float64), torch.tensor(p, dtype=torch.float64))
        assert torch.allclose(got, torch.tensor(want, dtype=torch.float64), atol=1e-15), (t, p)
    t, p = direction_to_latlong(torch.tensor([[0.0, 0, -1], [1, 0, 0], [0, 0, 1], [-1, 0, 0]]))
    assert torch.allclose(t, torch.full((4,), pi / 2))
    assert torch.allclose(p, torch.tensor([0, pi / 2, pi, 3 * pi / 2]))


def test_texel_centres_and_lookup():
    H, W = 8, 16
    c = texel_centers(H, W)
    assert c.shape == (H, W, 3) and c.dtype == torch.float64
    assert torch.allclose(c.norm(dim=-1), torch.ones((), dtype=c.dtype), atol=1e-15)
    # row 0 is at the zenith: its centres are within pi/H of +y
    assert bool((c[0, :, 1] > math.cos(math.pi / H)).all())
    assert torch.allclose(c[0, :, 1], torch.full((W,), math.cos(math.pi / (2 * H)), dtype=c.dtype))
    assert bool((c[-1, :, 1] < -math.cos(math.pi / H)).all())
    row, col = direction_to_texel(c, H, W)
    assert torch.equal(row, torch.arange(H)[:, None].expand(H, W))
    assert torch.equal(col, torch.arange(W)[None, :].expand(H, W))
    # float32 centres map to the same texels; poles and phi -> 2 pi are clamped into the map
    row32, col32 = direction_to_texel(c.float(), H, W)
    assert torch.equal(row32, row) and torch.equal(col32, col)
    r, k = direction_to_texel(torch.tensor([[0.0, 1, 0], [0, -1, 0], [-1e-300, 0, -1]]), H, W)
    assert r.tolist() == [0, H - 1, H // 2] and k[2] in (0, W - 1)


def test_lookup_of_random_directions_matches_angles():
    H, W = 32, 64
    d = random_dirs()
    row, col = direction_to_texel(d, H, W)
    theta, phi = direction_to_latlong(d)
    edges_t = torch.arange(H + 1, dtype=torch.float64) * math.pi / H
    edges_p = torch.arange(W + 1, dtype=torch.float64) * 2 * math.pi / W
    assert bool(((edges_t[row] <= theta) & (theta <= edges_t[row + 1])).all())
    assert bool(((edges_p[col] <= phi) & (phi <= edges_p[col + 1])).all())


@pytest.mark.parametrize("H", [2, 7, 64, 256, 1024])
def test_solid_angles_exact(H):
    W = 2 * H
    omega = texel_solid_angles(H, W)
    assert omega.shape == (H, W) and omega.dtype == torch.float64 and bool((omega > 0).all())
    assert abs(float(omega.sum()) - 4 * math.pi) < 1e-12
    assert torch.allclose(omega, omega.flip(0), rtol=1e-12, atol=0)  # north/south symmetric
    c = row_cos_bounds(H)
    assert c[0] == 1 and c[-1] == -1 and bool((c[1:] < c[:-1]).all())
    # close to the small-texel approximation sin(theta) dtheta dphi
    theta_c = (torch.arange(H, dtype=torch.float64) + 0.5) * math.pi / H
    approx = theta_c.sin() * (math.pi / H) * (2 * math.pi / W)
    assert torch.allclose(omega[:, 0], approx, rtol=(math.pi / H) ** 2 / 20)


def test_bad_shapes_raise():
    with pytest.raises(ShapeError, match=r"\(\.\.\., 3\)"):
        direction_to_latlong(torch.zeros(4, 2))
    with pytest.raises(ShapeError, match="positive"):
        texel_solid_angles(0, 4)
