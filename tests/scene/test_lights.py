r"""Lights: AreaLight sampling against Lambert's polygon formula, pdf/weight consistency,
one-sided emission, DirectionalLight's delta sample, and finite samples on the emitter plane.

The oracle is Lambert's formula for the irradiance from a uniform Lambertian polygon
(e.g. Arvo 1995, "Applications of Irradiance Tensors", eq. 7):
:math:`E = \frac{L}{2}\sum_i \Theta_i\,(\mathbf n\cdot\boldsymbol\Gamma_i)` with
:math:`\Theta_i` the angle subtended by edge :math:`i` and :math:`\boldsymbol\Gamma_i`
the unit normal of the plane through the point and that edge. It is itself checked
against the closed-form point-to-parallel-rectangle form factor.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_brdf.errors import MeshError, ValueRangeError
from torch_brdf.scene import AreaLight, DirectionalLight, LightSample
from torch_brdf.scene.builtin import CORNELL_RGB, cornell_box_meshes

N_MC = 200_000  # samples per irradiance estimate: std error ~0.05 %, test at 1 %

# A unit square at y = 1 facing down (-y), fanned from (0.3, 1, 0) on one edge into three
# triangles of unequal area (0.35, 0.5, 0.15), so area-proportional triangle choice matters.
SQUARE_V = np.array([[0.3, 1, 0], [1, 1, 0], [1, 1, 1], [0, 1, 1], [0, 1, 0]], dtype=np.float64)
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4]])
SQUARE_OUTLINE = SQUARE_V  # the fan vertices in order are the polygon outline
RADIANCE = (2.0, 1.0, 0.5)


def lambert_polygon_irradiance(point, normal, polygon, radiance=1.0) -> float:
    """Irradiance at ``point`` (normal ``normal``) from a uniform polygon (K, 3) that lies
    wholly above the point's horizon. Vertex order may be either way round."""
    p = np.asarray(point, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    u = np.asarray(polygon, dtype=np.float64) - p
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    total = 0.0
    for i in range(len(u)):
        a, b = u[i], u[(i + 1) % len(u)]
        theta = math.acos(float(np.clip(a @ b, -1.0, 1.0)))
        g = np.cross(a, b)
        total += theta * float(n @ (g / np.linalg.norm(g)))
    return 0.5 * radiance * abs(total)


def parallel_rectangle_corner_irradiance(a: float, b: float, h: float, radiance=1.0) -> float:
    """Closed form: irradiance below one corner of an a x b rectangle at height h, parallel
    to the receiver (Howell's catalogue of configuration factors, C-11)."""
    x, y = a / h, b / h
    sx, sy = math.sqrt(1 + x * x), math.sqrt(1 + y * y)
    f = (x / sx * math.atan(y / sx) + y / sy * math.atan(x / sy)) / (2 * math.pi)
    return math.pi * radiance * f


def _square_light() -> AreaLight:
    return AreaLight(SQUARE_V, SQUARE_F, RADIANCE)


def _mc_irradiance(light: AreaLight, point, normal, n: int, seed: int, dtype=torch.float64):
    """Mean (3,) and its standard error (3,) of weight * cos over ``n`` light samples at one point."""
    g = torch.Generator().manual_seed(seed)
    p = torch.as_tensor(point, dtype=dtype).expand(n, 3).contiguous()
    nn = torch.as_tensor(normal, dtype=dtype)
    nn = nn / nn.norm()
    s = light.sample(p, generator=g)
    cos = (s.direction @ nn).clamp_min(0)
    x = (s.weight * cos[:, None]).to(torch.float64)
    return x.mean(0), x.std(0) / math.sqrt(n)


def _check_irradiance(est, stderr, want):
    """Within 1 %, and the 1 % test is meaningful: the standard error is below 0.25 %."""
    assert bool((stderr < 2.5e-3 * want).all()), f"too noisy for a 1 % check: stderr {stderr}, value {want}"
    torch.testing.assert_close(est, want, rtol=1e-2, atol=0)


# -- the oracle itself ----------------------------------------------------------------------
@pytest.mark.parametrize(("a", "b", "h"), [(1.0, 1.0, 1.0), (0.5, 2.0, 0.7), (3.0, 0.2, 2.0)])
def test_lambert_oracle_matches_parallel_rectangle_form_factor(a, b, h):
    rect = [[0, h, 0], [a, h, 0], [a, h, b], [0, h, b]]
    got = lambert_polygon_irradiance([0, 0, 0], [0, 1, 0], rect)
    assert got == pytest.approx(parallel_rectangle_corner_irradiance(a, b, h), rel=1e-12)


def test_lambert_oracle_tends_to_pi_l_under_a_huge_emitter():
    big = [[-1e4, 1, -1e4], [1e4, 1, -1e4], [1e4, 1, 1e4], [-1e4, 1, 1e4]]
    assert lambert_polygon_irradiance([0, 0, 0], [0, 1, 0], big, 2.0) == pytest.approx(2 * math.pi, rel=1e-3)


# -- Monte Carlo irradiance -------------------------------------------------------------------
@pytest.mark.parametrize(
    ("point", "normal"),
    [
        pytest.param((0.5, 0.0, 0.5), (0.0, 1.0, 0.0), id="below-centre"),
        pytest.param((1.3, 0.2, -0.4), (0.0, 1.0, 0.0), id="off-centre"),
        pytest.param((0.5, 0.0, 0.5), (0.3, 1.0, 0.2), id="tilted-receiver"),
        pytest.param((0.2, 0.5, 0.7), (0.0, 1.0, 0.0), id="close"),
    ],
)
def test_area_light_irradiance_matches_lambert_polygon(point, normal):
    light = _square_light()
    assert light.total_area == pytest.approx(1.0)
    est, err = _mc_irradiance(light, point, normal, N_MC, seed=11)
    ref = lambert_polygon_irradiance(point, normal, SQUARE_OUTLINE)
    _check_irradiance(est, err, torch.tensor(RADIANCE, dtype=torch.float64) * ref)


def test_area_light_irradiance_float32():
    light = _square_light()
    est, err = _mc_irradiance(light, (0.5, 0.0, 0.5), (0.0, 1.0, 0.0), N_MC, seed=5, dtype=torch.float32)
    ref = lambert_polygon_irradiance((0.5, 0.0, 0.5), (0.0, 1.0, 0.0), SQUARE_OUTLINE)
    _check_irradiance(est, err, torch.tensor(RADIANCE, dtype=torch.float64) * ref)


def test_cornell_light_irradiance_on_the_floor_matches_closed_form():
    """The built-in Cornell light (130 x 105 mm at y = 548.3) seen from the floor below its centre."""
    m = cornell_box_meshes()["light"]
    light = AreaLight(m.vertices, m.faces, CORNELL_RGB["light"])
    assert light.total_area == pytest.approx(130.0 * 105.0)
    lo, hi = m.bounds
    centre = (lo + hi) / 2
    p = (float(centre[0]), 0.0, float(centre[2]))
    est, err = _mc_irradiance(light, p, (0.0, 1.0, 0.0), N_MC, seed=3)
    ref = 4 * parallel_rectangle_corner_irradiance(65.0, 52.5, 548.3)
    _check_irradiance(est, err, torch.tensor(CORNELL_RGB["light"], dtype=torch.float64) * ref)


def test_triangles_are_chosen_in_proportion_to_area(gen):
    light = _square_light()
    pts, nrm = light.sample_points(100_000, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(pts[:, 1], torch.ones(100_000, dtype=torch.float64))
    torch.testing.assert_close(nrm, torch.tensor([[0.0, -1.0, 0.0]], dtype=torch.float64).expand(100_000, 3))
    x, z = pts[:, 0], pts[:, 2]
    assert bool(((x >= 0) & (x <= 1) & (z >= 0) & (z <= 1)).all())
    # which fan triangle: left of the line (0.3, 0)-(1, 1) -> first; left of (0.3, 0)-(0, 1) -> third
    first = (z - (x - 0.3) / 0.7) < 0
    third = (x - 0.3 * (1 - z)) < 0
    frac = torch.stack((first.double().mean(), (~first & ~third).double().mean(), third.double().mean()))
    torch.testing.assert_close(frac, torch.tensor([0.35, 0.5, 0.15], dtype=torch.float64), atol=6e-3, rtol=0)
    # uniform within the square: each quadrant gets a quarter
    q = (x < 0.5).long() * 2 + (z < 0.5).long()
    counts = torch.bincount(q, minlength=4).double() / 100_000
    torch.testing.assert_close(counts, torch.full((4,), 0.25, dtype=torch.float64), atol=6e-3, rtol=0)


# -- validity and pdf -------------------------------------------------------------------------
def test_points_behind_the_emitter_get_zero_weight(gen):
    light = _square_light()
    n = 5000
    pts = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 4 - 1.5
    pts[:, 1] = 1.0 + 1e-3 + 2 * torch.rand(n, generator=gen, dtype=torch.float64)  # above: the back side
    s = light.sample(pts, generator=gen)
    assert bool((s.weight == 0).all())
    assert bool((s.pdf == 0).all())
    assert bool(torch.isfinite(s.direction).all() & torch.isfinite(s.distance).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_solid_angle_pdf_is_area_pdf_times_r2_over_cos(gen, dtype):
    light = _square_light()
    n = 4000
    pts = (torch.rand(n, 3, generator=gen, dtype=torch.float64) * 3 - 1).to(dtype)
    pts[:, 1] = pts[:, 1] - 0.5  # y in [-1.5, 1.5): both sides of the emitter plane y = 1
    s = light.sample(pts, generator=gen)
    assert isinstance(s, LightSample)
    for field in (s.direction, s.distance, s.weight, s.pdf):
        assert field.dtype == dtype
    assert s.direction.shape == (n, 3) and s.weight.shape == (n, 3) and s.pdf.shape == (n,) == s.distance.shape
    d, r, pdf, w = (t.double() for t in (s.direction, s.distance, s.pdf, s.weight))
    tol = {torch.float32: 1e-4, torch.float64: 1e-10}[dtype]
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(n, dtype=torch.float64), atol=tol, rtol=0)
    y = pts.double() + r[:, None] * d  # the sampled light point
    torch.testing.assert_close(y[:, 1], torch.ones(n, dtype=torch.float64), atol=10 * tol, rtol=0)
    assert bool(((y[:, 0] > -tol) & (y[:, 0] < 1 + tol) & (y[:, 2] > -tol) & (y[:, 2] < 1 + tol)).all())
    cos_l = d[:, 1]  # -d . n with n = -y
    front = cos_l > 0
    assert int(front.sum()) > n // 3 and int((~front).sum()) > n // 10
    p_area = 1.0 / light.total_area
    torch.testing.assert_close(pdf[front], p_area * r[front] ** 2 / cos_l[front], rtol=10 * tol, atol=0)
    torch.testing.assert_close(
        w[front], torch.tensor(RADIANCE, dtype=torch.float64) / pdf[front, None], rtol=10 * tol, atol=0
    )
    assert bool((pdf[~front] == 0).all() & (w[~front] == 0).all())


def test_sampling_is_reproducible_with_a_seed():
    light = _square_light()
    pts = torch.zeros(64, 3)
    a = light.sample(pts, generator=torch.Generator().manual_seed(3))
    b = light.sample(pts, generator=torch.Generator().manual_seed(3))
    c = light.sample(pts, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a.direction, b.direction) and torch.equal(a.weight, b.weight)
    assert not torch.equal(a.direction, c.direction)


def test_emitted_is_one_sided():
    light = _square_light()
    normals = torch.tensor([[0.0, -1.0, 0.0]]).expand(4, 3)
    dirs = torch.tensor([[0.0, 1.0, 0.0], [0.6, 0.8, 0.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
    out = light.emitted(dirs, normals)
    assert out.shape == (4, 3)
    torch.testing.assert_close(out[:2], torch.tensor([RADIANCE, RADIANCE]))
    assert bool((out[2:] == 0).all()), "back side and grazing rays see no emission"


def _tilted_emitter() -> tuple[np.ndarray, np.ndarray]:
    """A 2 x 1 rectangle turned to a general orientation (so plane coordinates round)."""
    c, s = math.cos(0.7), math.sin(0.7)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, c, s], [0, -s, c]])
    v = np.array([[0, 0, 0], [2, 0, 0], [2, 0, 1], [0, 0, 1]], dtype=np.float64) @ rot.T + [0.3, 1.7, -0.2]
    return v, np.array([[0, 1, 2], [0, 2, 3]])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("emitter", ["square", "tilted"])
def test_samples_are_finite_for_points_on_the_emitter_plane(gen, dtype, emitter):
    v, f = (SQUARE_V, SQUARE_F) if emitter == "square" else _tilted_emitter()
    light = AreaLight(v, f, RADIANCE)
    # points in the emitter's plane: inside, on edges, at vertices and outside the polygon
    a = torch.rand(3000, 2, generator=gen, dtype=torch.float64) * 3 - 1
    a = torch.cat((a, torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.5, 0.0], [1.0, 1.0], [0.5, 0.5]], dtype=torch.float64)))
    base = torch.as_tensor(v[f[0]], dtype=torch.float64)
    pts = base[0] + a[:, :1] * (base[1] - base[0]) + a[:, 1:] * (base[2] - base[0])
    s = light.sample(pts.to(dtype), generator=gen)
    for name in ("direction", "distance", "weight", "pdf"):
        t = getattr(s, name)
        assert bool(torch.isfinite(t).all()), f"{name} has non-finite values for points on the emitter plane"
    assert bool((s.weight >= 0).all() & (s.pdf >= 0).all())
    # in exact arithmetic these see the emitter edge-on: whatever rounding lets through is tiny
    assert float(s.weight.abs().max()) < 1e-3 * max(RADIANCE)


def test_point_on_a_sampled_vertex_is_finite():
    # a one-triangle emitter whose samples can land arbitrarily close to the shading point
    light = AreaLight([[0.0, 0.0, 0.0], [1e-20, 0.0, 0.0], [0.0, 0.0, 1e-20]], [[0, 1, 2]], 1.0)
    s = light.sample(torch.zeros(100, 3, dtype=torch.float64), generator=torch.Generator().manual_seed(0))
    for t in (s.direction, s.distance, s.weight, s.pdf):
        assert bool(torch.isfinite(t).all())


def test_area_light_rejects_bad_input():
    with pytest.raises(MeshError):
        AreaLight([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], 1.0)  # no area
    with pytest.raises(MeshError):
        AreaLight([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.zeros((0, 3), dtype=np.int64), 1.0)
    with pytest.raises(ValueRangeError):
        AreaLight(SQUARE_V, SQUARE_F, -1.0)


def test_area_light_drops_zero_area_triangles_from_sampling(gen):
    v = np.vstack((SQUARE_V, [[5, 1, 5], [6, 1, 5]]))
    f = np.vstack((SQUARE_F, [[5, 6, 5]]))  # a zero-area triangle far away
    light = AreaLight(v, f, 1.0)
    pts, _ = light.sample_points(2000, generator=gen, dtype=torch.float64)
    assert float(pts[:, 0].max()) <= 1.0
    assert light.total_area == pytest.approx(1.0)


# -- DirectionalLight -------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_directional_light_sample_is_a_delta(gen, dtype):
    light = DirectionalLight((1.0, 2.0, 2.0), (3.0, 2.0, 1.0))
    assert light.is_delta and light.is_infinite
    pts = torch.randn(10, 3, generator=gen, dtype=torch.float64).to(dtype)
    s = light.sample(pts, generator=gen)
    for t in (s.direction, s.distance, s.weight, s.pdf):
        assert t.dtype == dtype
    assert s.direction.shape == (10, 3) and s.weight.shape == (10, 3)
    assert s.distance.shape == (10,) and s.pdf.shape == (10,)
    torch.testing.assert_close(s.direction, torch.tensor([[1 / 3, 2 / 3, 2 / 3]], dtype=dtype).expand(10, 3))
    torch.testing.assert_close(s.weight, torch.tensor([[3.0, 2.0, 1.0]], dtype=dtype).expand(10, 3))
    assert bool(torch.isposinf(s.distance).all() & torch.isposinf(s.pdf).all())
    assert bool(torch.isfinite(s.direction).all() & torch.isfinite(s.weight).all())
    assert bool((light.eval_miss(s.direction) == 0).all())


def test_directional_light_scalar_irradiance_and_bad_direction():
    light = DirectionalLight((0.0, 0.0, -5.0), 2.0)
    s = light.sample(torch.zeros(2, 3))
    torch.testing.assert_close(s.direction, torch.tensor([[0.0, 0.0, -1.0]] * 2))
    torch.testing.assert_close(s.weight, torch.full((2, 3), 2.0))
    with pytest.raises(ValueRangeError):
        DirectionalLight((0.0, 0.0, 0.0), 1.0)
    with pytest.raises(ValueRangeError):
        DirectionalLight((0.0, float("nan"), 1.0), 1.0)
