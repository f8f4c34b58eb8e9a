"""EnvironmentMap: pdf/sampling consistency, exact sums, rotation, median cut, bad input.

Tests of the piecewise-constant reading pass ``lookup="nearest"``; the bilinear (default)
reading has its own oracles in ``test_envmap_bilinear.py`` and shares the lookup-agnostic ones
here through the ``env`` fixture.

Real maps come from the data folder (``$TORCH_BRDF_DATA``)
and are skipped when it is absent; every other test uses procedural maps.
"""

from __future__ import annotations

import math

import numpy as np
import OpenEXR
import pytest
import torch

from tests._stats import assert_chi2
from torch_brdf.data import data_path
from torch_brdf.errors import FileFormatError, ShapeError, TorchBRDFError, ValueRangeError
from torch_brdf.io.exr import write_exr
from torch_brdf.scene.envmap import EnvironmentMap, PointLightSet
from torch_brdf.scene.lights import Light, luminance
from torch_brdf.sphere import (
    direction_to_texel,
    row_cos_bounds,
    square_to_uniform_sphere,
    texel_centers,
)

N_IS = 65_536  # importance samples for the 1 % integral check
K_LIGHTS = 256  # median-cut lights for the 2 % irradiance check
N_NORMALS = 50
QUARRY, OVERCAST = "quarry_01_sun_512x256.exr", "overcast_soil_puresky_512x256.exr"


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def load(name: str) -> EnvironmentMap:
    path = data_path("envmaps", name, required=False)
    if path is None:
        pytest.skip(f"shared data not found: envmaps/{name} (set TORCH_BRDF_DATA)")
    return EnvironmentMap.from_exr(path)


@pytest.fixture(scope="module")
def sky():
    return EnvironmentMap.sky()


@pytest.fixture(
    scope="module",
    params=[
        "sky",
        "sky-nearest",
        pytest.param(QUARRY, marks=pytest.mark.data),
        pytest.param(OVERCAST, marks=pytest.mark.data),
    ],
)
def env(request, sky):
    """The acceptance maps: procedural sky with sun (both lookups), sunny quarry, overcast sky."""
    if request.param == "sky-nearest":
        return EnvironmentMap.sky(lookup="nearest")
    return sky if request.param == "sky" else load(request.param)


def random_map(H=8, seed=0, sparse=False):
    g = gen(seed)
    L = torch.rand(H, 2 * H, 3, generator=g) * 2
    if sparse:  # most texels black
        L = L * (torch.rand(H, 2 * H, 1, generator=g) < 0.15)
    return L


def texel_pdf_sum(e: EnvironmentMap) -> float:
    c = texel_centers(e.height, e.width).reshape(-1, 3)
    return float((e.pdf(c) * e.solid_angle.reshape(-1)).sum())


# ---------------------------------------------------------------- pdf and sampling
@pytest.mark.parametrize(
    "make",
    [
        lambda: EnvironmentMap.sky(height=64, lookup="nearest"),
        lambda: EnvironmentMap(random_map(16), lookup="nearest"),
        lambda: EnvironmentMap(random_map(16, sparse=True), lookup="nearest"),
        lambda: EnvironmentMap.constant(0.0, height=8, lookup="nearest"),
    ],
    ids=["sky", "random", "sparse", "black"],
)
def test_pdf_sums_to_one_over_texels(make):
    e = make()
    assert abs(texel_pdf_sum(e) - 1) < 1e-6


def test_pdf_sums_to_one_on_real_map(env):
    if env.bilinear:
        env = EnvironmentMap(env.radiance, lookup="nearest")
    assert abs(texel_pdf_sum(env) - 1) < 1e-6


@pytest.mark.parametrize("lookup", ["bilinear", "nearest"])
@pytest.mark.parametrize("which", ["random", pytest.param(OVERCAST, marks=pytest.mark.data)])
def test_pdf_mc_with_uniform_directions(which, lookup):
    """E[4 pi pdf(w)] over uniform directions = integral of the pdf = 1 (within 5 sigma)."""
    e = EnvironmentMap(random_map(16, seed=5) if which == "random" else load(which).radiance, lookup=lookup)
    n = 200_000
    w = square_to_uniform_sphere(torch.rand(n, 2, generator=gen(6), dtype=torch.float64))
    f = 4 * math.pi * e.pdf(w)
    err = abs(float(f.mean()) - 1)
    assert err < 5 * float(f.std()) / math.sqrt(n) and err < 0.02, err


def test_importance_sampled_integral_within_one_percent(env):
    """64k seeded samples of weight = L / pdf estimate int L dw per channel within 1 %."""
    s = env.sample(torch.zeros(N_IS, 3, dtype=torch.float64), gen(1))
    est = s.weight.mean(0)
    exact = env.integral()
    rel = ((est - exact).abs() / exact).max()
    assert rel < 0.01, (est, exact)


def test_samples_land_in_texels_with_positive_pdf(env):
    d, p = env.sample_directions(20_000, gen(2), dtype=torch.float64)
    assert torch.allclose(d.norm(dim=-1), torch.ones((), dtype=d.dtype), atol=1e-14)
    assert bool((p > 0).all())
    assert torch.equal(env.pdf(d), p)  # the lookup finds the density that was sampled
    assert bool((luminance(env.eval_miss(d)) > 0).all())


def test_sampling_chi2_texels_and_within_texel():
    """Histogram over 2x2 equal-solid-angle sub-cells of every texel of a sparse map."""
    H, W, n = 4, 8, 200_000
    L = random_map(H, seed=3, sparse=True) + torch.tensor([0.0, 0.02, 0.0])
    L[1, 2] = 0.0  # one texel exactly black: must never be sampled
    e = EnvironmentMap(L, lookup="nearest")
    d, _ = e.sample_directions(n, gen(4), dtype=torch.float64)
    row, col = direction_to_texel(d, H, W)
    assert not bool(((row == 1) & (col == 2)).any())
    c = row_cos_bounds(H)
    a = ((c[row] - d[:, 1]) / (c[row] - c[row + 1]) * 2).floor().long().clamp(0, 1)
    phi = torch.remainder(torch.atan2(d[:, 0], -d[:, 2]), 2 * math.pi)
    b = (phi * W / (2 * math.pi) - col).mul(2).floor().long().clamp(0, 1)
    counts = torch.bincount(((row * W + col) * 2 + a) * 2 + b, minlength=H * W * 4).double()
    prob = (e.texel_pdf * e.solid_angle).reshape(-1, 1).expand(-1, 4).reshape(-1) / 4
    assert_chi2(counts, n * prob, n)


def test_black_map_falls_back_to_uniform_sphere():
    e = EnvironmentMap.constant(0.0, height=8, lookup="nearest")
    d, p = e.sample_directions(50_000, gen(7), dtype=torch.float64)
    assert torch.allclose(p, torch.full_like(p, 1 / (4 * math.pi)))
    assert abs(float(d[:, 1].mean())) < 5 / math.sqrt(3 * 50_000)  # y uniform in [-1, 1]
    s = e.sample(torch.zeros(10, 3), gen(8))
    assert bool((s.weight == 0).all()) and bool((s.pdf > 0).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_light_interface(dtype):
    e = EnvironmentMap(random_map(8))
    assert isinstance(e, Light) and e.is_infinite and not e.is_delta
    s = e.sample(torch.randn(100, 3, generator=gen(9)).to(dtype), gen(10))
    for t in (s.direction, s.distance, s.weight, s.pdf):
        assert t.dtype == dtype and t.shape[0] == 100
    assert bool(torch.isinf(s.distance).all())
    L = e.eval_miss(s.direction)
    assert L.dtype == dtype and L.shape == (100, 3)
    assert torch.allclose(s.weight * s.pdf[:, None], L, rtol=1e-5 if dtype == torch.float32 else 1e-12)
    assert e.power_estimate() > 0
    assert e.eval_miss(torch.zeros(2, 5, 3, dtype=dtype) + 1).shape == (2, 5, 3)


def test_eval_miss_is_nearest_texel():
    L = random_map(8)
    e = EnvironmentMap(L, lookup="nearest")
    c = texel_centers(8, 16)
    assert torch.equal(e.eval_miss(c), L.double())
    assert torch.equal(e.eval_miss(c.float()), L)


# ---------------------------------------------------------------- rotation
@pytest.mark.parametrize("lookup", ["bilinear", "nearest"])
@pytest.mark.parametrize("k", [1, 5, -3])
def test_rotation_by_k_columns_is_roll_by_minus_k(k, lookup):
    """rotation_y = 2 pi k / W turns features from azimuth phi to phi - 2 pi k / W."""
    H, W = 8, 16
    L = random_map(H, seed=11)
    alpha = 2 * math.pi * k / W
    rot = EnvironmentMap(L, rotation_y=alpha, lookup=lookup)
    rolled = EnvironmentMap(torch.roll(L, -k, dims=1), lookup=lookup)
    c = texel_centers(H, W).reshape(-1, 3)
    same = torch.equal if lookup == "nearest" else lambda a, b: torch.allclose(a, b, rtol=1e-6, atol=1e-6)
    assert same(rot.eval_miss(c), rolled.eval_miss(c))
    assert torch.allclose(rot.pdf(c), rolled.pdf(c), rtol=1e-9)
    assert torch.equal(EnvironmentMap(L, lookup=lookup).rotated(alpha).eval_miss(c), rot.eval_miss(c))
    assert torch.allclose(rot.integral(), rolled.integral(), rtol=1e-12)
    # same seed: rotated samples are the unrotated ones turned by R_y(alpha)
    d0, p0 = EnvironmentMap(L, lookup=lookup).sample_directions(1000, gen(12), dtype=torch.float64)
    d1, p1 = rot.sample_directions(1000, gen(12), dtype=torch.float64)
    ca, sa = math.cos(alpha), math.sin(alpha)
    R = torch.tensor([[ca, 0, sa], [0, 1, 0], [-sa, 0, ca]], dtype=torch.float64)
    assert torch.allclose(d1, d0 @ R.T, atol=1e-14) and torch.allclose(p0, p1, rtol=1e-9)
    n = square_to_uniform_sphere(torch.rand(20, 2, generator=gen(13), dtype=torch.float64))
    assert torch.allclose(rot.irradiance(n), rolled.irradiance(n), rtol=1e-10)
    pl0, pl1 = (
        EnvironmentMap(L, lookup=lookup).point_lights(16, torch.float64),
        rot.point_lights(16, torch.float64),
    )
    assert torch.allclose(pl1.directions, pl0.directions @ R.T, atol=1e-14)


def test_rotation_moves_a_bright_texel_to_lower_azimuth():
    H, W, j0, k = 8, 16, 6, 2
    L = torch.zeros(H, W, 3)
    L[3, j0] = 1.0
    e = EnvironmentMap(L, rotation_y=2 * math.pi * k / W, lookup="nearest")
    lit = luminance(e.eval_miss(texel_centers(H, W))) > 0
    assert lit.nonzero().tolist() == [[3, j0 - k]]


# ---------------------------------------------------------------- exact sums, point lights
def test_constant_map_sums():
    e = EnvironmentMap.constant((1.0, 0.5, 0.25), height=64)
    assert torch.allclose(e.integral(), 4 * math.pi * torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64))
    n = square_to_uniform_sphere(torch.rand(10, 2, generator=gen(14), dtype=torch.float64))
    assert torch.allclose(e.irradiance(n), math.pi * torch.tensor([1.0, 0.5, 0.25]).double(), rtol=1e-3)


@pytest.mark.parametrize("lookup", ["bilinear", "nearest"])
def test_sky_sun_power_independent_of_resolution(lookup):
    r = 1.5
    for height in (64, 128, 256):
        with_sun = EnvironmentMap.sky(height=height, sun_angular_radius_deg=r, lookup=lookup).integral()
        no_sun = EnvironmentMap.sky(height=height, sun_radiance=0.0, sun_angular_radius_deg=r, lookup=lookup).integral()
        want = (
            torch.tensor([3000.0, 2850.0, 2600.0], dtype=torch.float64) * 2 * math.pi * (1 - math.cos(math.radians(r)))
        )
        assert torch.allclose(with_sun - no_sun, want, rtol=0.03), height


def test_point_lights_are_exact_and_deterministic(env):
    pl = env.point_lights(K_LIGHTS, dtype=torch.float64)
    assert isinstance(pl, PointLightSet) and pl.directions.shape == (K_LIGHTS, 3)
    assert torch.allclose(pl.intensity.sum(0), env.integral(), rtol=1e-6, atol=0)
    assert abs(float(pl.solid_angle.sum()) - 4 * math.pi) < 1e-9
    assert torch.allclose(pl.directions.norm(dim=-1), torch.ones((), dtype=torch.float64), atol=1e-12)
    pl2 = env.point_lights(K_LIGHTS, dtype=torch.float64)
    assert torch.equal(pl.directions, pl2.directions) and torch.equal(pl.radiance, pl2.radiance)
    pl32 = env.point_lights(K_LIGHTS)
    assert pl32.radiance.dtype == torch.float32
    assert torch.allclose(pl32.intensity.double().sum(0), env.integral(), rtol=1e-5, atol=0)


def test_point_lights_one_per_texel():
    H, W = 4, 8
    L = random_map(H, seed=15)
    pl = EnvironmentMap(L, lookup="nearest").point_lights(H * W, dtype=torch.float64)
    got = {tuple(torch.round(d, decimals=9).tolist()) for d in pl.directions}
    want = {tuple(torch.round(d, decimals=9).tolist()) for d in texel_centers(H, W).reshape(-1, 3)}
    assert got == want
    assert torch.allclose(pl.radiance.sum(0), L.double().sum((0, 1)), rtol=1e-12)


def test_point_lights_irradiance_within_two_percent(env):
    r"""K = 256 median-cut lights against the dense texel sum, for 50 seeded normals.

    Metric, per channel: max over normals of |E_K(n) - E(n)| / max_n E(n) (the error
    relative to the brightest irradiance in the set) must be < 2 %; and per normal, where
    E(n) >= 10 % of that maximum, |E_K - E| / E must also be < 2 %.
    """
    n = square_to_uniform_sphere(torch.rand(N_NORMALS, 2, generator=gen(16), dtype=torch.float64))
    ref = env.irradiance(n)
    got = env.point_lights(K_LIGHTS, dtype=torch.float64).irradiance(n)
    err = (got - ref).abs()
    assert bool((err.amax(0) / ref.amax(0) < 0.02).all()), err.amax(0) / ref.amax(0)
    big = ref >= 0.1 * ref.amax(0)
    assert float((err / ref)[big].max()) < 0.02


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("value", "words"),
    [(math.nan, "1 NaN"), (math.inf, "1 Inf"), (-1.0, "1 negative")],
)
def test_bad_texel_values_raise(value, words):
    L = random_map(8)
    L[2, 3, 1] = value
    with pytest.raises(ValueRangeError, match=words):
        EnvironmentMap(L)


@pytest.mark.parametrize(
    ("shape", "words"),
    [
        ((8, 16, 4), r"\(H, W, 3\)"),
        ((8, 16), r"\(H, W, 3\)"),
        ((8, 12, 3), "W == 2H"),
        ((1, 2, 3), "H >= 2"),
    ],
)
def test_bad_shapes_raise(shape, words):
    with pytest.raises(ShapeError, match=words):
        EnvironmentMap(torch.ones(shape))


def test_bad_files_raise(tmp_path):
    missing = tmp_path / "nope.exr"
    with pytest.raises(FileFormatError, match=r"nope\.exr"):
        EnvironmentMap.from_exr(missing)
    L = random_map(8)
    L[0, 0, 0], L[1, 1, 2], L[2, 2] = math.nan, -2.0, math.inf
    write_exr(tmp_path / "bad.exr", L)
    with pytest.raises(ValueRangeError, match=r"bad\.exr.*1 NaN, 1 Inf and 1 negative"):
        EnvironmentMap.from_exr(tmp_path / "bad.exr")
    write_exr(tmp_path / "square.exr", torch.ones(8, 8, 3))
    with pytest.raises(ShapeError, match=r"square\.exr.*W == 2H"):
        EnvironmentMap.from_exr(tmp_path / "square.exr")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Z": np.ones((8, 16), np.float32)}) as f:
        f.write(str(tmp_path / "depth.exr"))
    with pytest.raises(FileFormatError, match="channels"):
        EnvironmentMap.from_exr(tmp_path / "depth.exr")
    with pytest.raises(ValueRangeError, match="scale"):
        EnvironmentMap.from_exr(tmp_path / "square.exr", scale=-1.0)


def test_bad_arguments_raise():
    e = EnvironmentMap(random_map(4))
    with pytest.raises(ValueRangeError, match="k must be"):
        e.point_lights(0)
    with pytest.raises(ShapeError, match="directions"):
        e.eval_miss(torch.zeros(3, 2))
    with pytest.raises(ValueRangeError, match="non-finite"):
        e.pdf(torch.tensor([[math.nan, 0.0, 1.0]]))
    with pytest.raises(TorchBRDFError):
        EnvironmentMap.constant((1.0, 2.0))


def test_texels_beyond_float32_are_refused_with_a_clear_message():
    L = np.ones((4, 8, 3))
    L[1, 2] = 1e300  # finite in float64, Inf in float32
    with pytest.raises(ValueRangeError, match="1 texels exceed the float32 range"):
        EnvironmentMap(L)


def test_exr_scale_beyond_float32_is_refused(tmp_path):
    write_exr(tmp_path / "env.exr", torch.ones(4, 8, 3))
    with pytest.raises(ValueRangeError, match="float32 range"):
        EnvironmentMap.from_exr(tmp_path / "env.exr", scale=1e300)
    with pytest.raises(ValueRangeError, match="scale"):
        EnvironmentMap.from_exr(tmp_path / "env.exr", scale=float("nan"))


@pytest.mark.parametrize("angle", [float("nan"), float("inf"), "half"])
def test_non_finite_rotations_are_refused(angle):
    env = EnvironmentMap.constant(1.0, height=4)
    with pytest.raises(ValueRangeError, match="angle_rad"):
        env.rotated(angle)
    with pytest.raises(ValueRangeError, match="rotation_y"):
        EnvironmentMap(env.radiance, rotation_y=angle)


def test_procedural_sizes_are_bounded():
    with pytest.raises(ValueRangeError, match="height must be <= 2048"):
        EnvironmentMap.constant(1.0, height=100000)
    with pytest.raises(ValueRangeError, match="height must be an integer"):
        EnvironmentMap.sky(height=16.5)
    with pytest.raises(ValueRangeError, match="supersample must be >= 1"):
        EnvironmentMap.sky(height=8, supersample=-1)
