"""Light lobes (``light_lobe_images``): the unoccluded direct light of the area lights through
each prefix of an object's eye bands, by quadrature. Oracles: Lambert's closed form for the
irradiance of a polygon (the sum over every band) and a Monte Carlo histogram of the bands;
and ``CumulativeOIDN(lobes=...)``'s demodulation, checked with stand-in denoisers."""

from __future__ import annotations

import pytest
import torch

from torch_brdf.denoise import CumulativeOIDN, EdgeAwareFilter, guide_buffers
from torch_brdf.errors import ShapeError, ValueRangeError
from torch_brdf.records.polynomial import ObjectBasis
from torch_brdf.scene.builtin import cornell_box
from torch_brdf.scene.gbuffer import trace_gbuffer
from torch_brdf.transport.guides import light_lobe_images

from .test_denoise import gaussian_within_brute

SIZE = 20


@pytest.fixture(scope="module")
def box():
    sc = cornell_box(SIZE)
    gb = trace_gbuffer(sc)
    return sc, gb


def _lambert_cosine_integral(p: torch.Tensor, n: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """Lambert's formula: the integral of cos(theta) over the solid angle of triangle ``tri``
    (3, 3) seen from points ``p`` (P, 3) with normals ``n``, the triangle fully above them."""
    total = torch.zeros(p.shape[0], dtype=torch.float64)
    for i in range(3):
        a = torch.nn.functional.normalize(tri[i] - p, dim=-1)
        b = torch.nn.functional.normalize(tri[(i + 1) % 3] - p, dim=-1)
        theta = torch.acos((a * b).sum(-1).clamp(-1, 1))
        g = torch.nn.functional.normalize(torch.linalg.cross(a, b), dim=-1)
        total += theta * (g * n).sum(-1)
    return 0.5 * total.abs()


def _wall(sc, gb, name="back"):
    on = gb.object_id == sc.object_id(name)
    wo, n = gb.wo[on].double(), gb.normal[on].double()
    n = torch.where(((n * wo).sum(-1) < 0)[:, None], -n, n)
    return gb.pixels[on], gb.position[on].double(), n, wo


def test_all_bands_sum_to_the_irradiance_of_the_light(box):
    """With the quotient 1 the last prefix is L_e times the light's cosine-weighted solid
    angle: Lambert's closed form, pixel by pixel, on two walls."""
    sc, gb = box
    light = sc.lights[0]
    for name in ("back", "left"):
        U = light_lobe_images(sc, ObjectBasis(J=8), name, samples=64)
        assert U.shape == (8, 3, SIZE, SIZE) and U.dtype == torch.float32
        pix, p, n, _ = _wall(sc, gb, name)
        want = sum(_lambert_cosine_integral(p, n, t) for t in light.triangles.double())
        got = U[-1].reshape(3, -1)[:, pix].double()
        torch.testing.assert_close(got, want[None] * light.radiance.double()[:, None], rtol=2e-3, atol=0)
        off = torch.ones(SIZE * SIZE, dtype=torch.bool)
        off[pix] = False
        assert float(U.reshape(8, 3, -1)[:, :, off].abs().max()) == 0.0  # only the object's pixels
        assert bool((U[1:] >= U[:-1] - 1e-6).all())  # prefix sums of non-negative bands


def test_each_band_matches_a_monte_carlo_histogram(box, gen):
    """Per band: uniform random points on the light, their theta_h band, the same integrand:
    the quadrature's band shares agree within the Monte Carlo error."""
    sc, gb = box
    light = sc.lights[0]
    basis = ObjectBasis(J=8, spacing="lobe:100")
    U = light_lobe_images(sc, basis, "back", samples=32)
    pix, p, n, wo = _wall(sc, gb, "back")
    bands = basis.band_basis()
    pick = torch.randperm(pix.numel(), generator=gen)[:6]
    N = 200_000
    for i in pick.tolist():
        u = torch.rand(N, 3, generator=gen, dtype=torch.float64)
        y, ny = light.sample_points(N, dtype=torch.float64, u=u)
        d = y - p[i]
        r2 = (d * d).sum(-1)
        wi = d / r2.sqrt()[:, None]
        w = (wi @ n[i]).clamp_min(0) * (-(wi * ny).sum(-1)).clamp_min(0) / r2 * light.total_area
        h = torch.nn.functional.normalize(wi + wo[i], dim=-1)
        j = bands.index(torch.acos((h @ n[i]).clamp(-1, 1)))
        per = torch.zeros(8, dtype=torch.float64).scatter_add_(0, j, w) / N
        se = torch.zeros(8, dtype=torch.float64).scatter_add_(0, j, w * w) / N
        se = ((se - per**2).clamp_min(0) / N).sqrt()
        got = U[:, 0].reshape(8, -1)[:, pix[i]].double() / float(light.radiance[0])
        want = per.cumsum(0)
        assert bool(((got - want).abs() <= 5 * se.cumsum(0) + 2e-3 * want[-1]).all()), (got, want)
    assert float(U[0].max()) < 0.9 * float(U[-1].max())  # the bands do split the light


def test_light_lobes_do_not_depend_on_the_chunking(box):
    sc, _ = box
    whole = light_lobe_images(sc, ObjectBasis(J=8), "back", samples=8)
    torch.testing.assert_close(light_lobe_images(sc, ObjectBasis(J=8), "back", samples=8, chunk=7), whole)


def test_light_lobes_refuse_what_they_cannot_model(box):
    sc, _ = box
    with pytest.raises(ValueRangeError, match="one-layer"):
        light_lobe_images(sc, None, "back")
    with pytest.raises(ValueRangeError, match="one-layer"):
        light_lobe_images(sc, ObjectBasis(J=4, fresnel=True), "back")
    with pytest.raises(ValueRangeError, match="samples"):
        light_lobe_images(sc, ObjectBasis(J=4), "back", samples=0)
    dark = cornell_box(8)
    dark.lights = []
    assert light_lobe_images(dark, ObjectBasis(J=4), "back") is None  # nothing to demodulate


def test_cumulative_oidn_demodulates_each_prefix_sum_by_its_lobe(box, gen):
    """With lobes U, the image denoiser sees S_k / M_k, M_k = U_k + G(S_k), and its output is
    multiplied by M_k: an identity denoiser returns the bands unchanged, one that flattens the
    ratio to its mean returns M_k times that mean (G by brute force)."""
    sc, _ = box
    g = guide_buffers(sc)
    fallback = EdgeAwareFilter(g)
    occupied = torch.rand(4, 1, SIZE, SIZE, generator=gen) < 0.6
    imgs = torch.rand(4, 3, SIZE, SIZE, generator=gen, dtype=torch.float64) * occupied * (g.object_id >= 0)
    groups = torch.zeros(4, dtype=torch.long)
    lobes = torch.rand(4, 3, SIZE, SIZE, generator=gen).cumsum(0) * (torch.rand(SIZE, SIZE, generator=gen) < 0.5)
    keep = fallback.interior & (imgs != 0).any(0).any(0)
    same = CumulativeOIDN(g, fallback, image_denoiser=lambda x: x, keep_mean=0, lobes=lobes)(imgs, groups)
    torch.testing.assert_close(same[..., keep], imgs[..., keep], rtol=1e-12, atol=1e-12)

    def flat(img):
        return torch.where(keep[..., None], img[keep].mean(0), img)

    sigma = 1.5
    out = CumulativeOIDN(g, fallback, image_denoiser=flat, keep_mean=0, lobes=lobes, lobe_floor=sigma)(imgs, groups)
    sums = imgs.cumsum(0)
    for k in range(4):
        m = lobes[k].double() + gaussian_within_brute(sums[k], keep, sigma)
        want = m * (sums[k] / m)[:, keep].mean(1)[:, None, None]
        torch.testing.assert_close(out[: k + 1].sum(0)[:, keep], want[:, keep], rtol=1e-9, atol=1e-12)
    plain = CumulativeOIDN(g, fallback, image_denoiser=flat, keep_mean=0)(imgs, groups)
    assert float((plain - out)[..., keep].abs().max()) > 1e-3  # the lobes change what it sees
    # lobes and the kept local mean at one sigma share the blur of S_k: the same as brute force
    kw = {"keep_mean": sigma, "lobes": lobes, "lobe_floor": sigma}
    both = CumulativeOIDN(g, fallback, image_denoiser=flat, **kw)(imgs, groups)
    for k in range(4):
        gs = gaussian_within_brute(sums[k], keep, sigma)
        m = lobes[k].double() + gs
        d = m * (sums[k] / m)[:, keep].mean(1)[:, None, None]
        want = d * gs / gaussian_within_brute(d, keep, sigma)
        torch.testing.assert_close(both[: k + 1].sum(0)[:, keep], want[:, keep], rtol=1e-9, atol=1e-12)
    with pytest.raises(ShapeError, match="another object"):
        CumulativeOIDN(g, fallback, lobes=lobes[:3])(imgs, groups)
    with pytest.raises(ShapeError, match=">= 0"):
        CumulativeOIDN(g, lobes=-lobes)
    with pytest.raises(ShapeError, match=r"\(J, 3, H, W\)"):
        CumulativeOIDN(g, lobes=lobes[0])
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueRangeError, match="lobe_floor"):
            CumulativeOIDN(g, lobe_floor=bad)
