"""1-D factored BRDFs on box bands (Ben-Artzi et al. 2008, Appendices A and B)."""

from __future__ import annotations

import importlib
import itertools
import math
import warnings
from functools import cache

import pytest
import torch

from tests.brdf.common import BRDFContract
from torch_brdf.brdf import create
from torch_brdf.brdf.bands import (
    AnisotropicLobe,
    BandBasis,
    EquivalentAlbedoCacheWarning,
    Factored1D,
    FresnelFactored1D,
    PairQuadrature,
    Projector,
    SchlickFresnel,
    SmithQuotient,
    band_albedos,
    band_edges,
    cache_dir,
    equivalent_albedo,
    half_and_diff,
    make_quotient,
    project,
    projection_error,
)
from torch_brdf.errors import ShapeError, ValueRangeError

F32, F64 = torch.float32, torch.float64
#: a light quadrature for the tests (the projections of smooth lobes converge at far coarser grids)
QUAD = dict(n_theta_h=64, n_theta_d=4, n_phi_d=8)
#: for BRDFs of theta_h alone (the errors agree with a 40x denser rule to 6 digits)
QUAD_H = dict(n_theta_h=32, n_theta_d=2, n_phi_d=4)
QUAD_ANISO = dict(n_theta_h=24, n_theta_d=2, n_phi_d=4, n_phi_h=2)


def blinn(n: float, kd: float = 0.0, ks: float = 1.0):
    import torch_brdf.brdf.analytic  # noqa: F401  (registers the model)

    return create("blinn_phong", kd=kd, ks=ks, exponent=float(n))


def pairs(n: int, seed: int, dtype=F64, min_cos: float = 0.02) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(2, n, 3, generator=g, dtype=F64)
    v[..., 2] = v[..., 2].abs() + min_cos
    v = v / v.norm(dim=-1, keepdim=True)
    return v[0].to(dtype), v[1].to(dtype)


class AnisoLobe:
    """In-test Ashikhmin-Shirley specular lobe without Fresnel (tangent = local +x)."""

    anisotropic = True

    def __init__(self, nu: float, nv: float):
        self.nu, self.nv = nu, nv

    def eval_local(self, wi, wo):
        h, cd, _ = half_and_diff(wi, wo)
        r2 = (h[..., 0] ** 2 + h[..., 1] ** 2).clamp_min(1e-300)
        e = (self.nu * h[..., 0] ** 2 + self.nv * h[..., 1] ** 2) / r2
        norm = math.sqrt((self.nu + 1) * (self.nv + 1)) / (8 * math.pi)
        v = norm * h[..., 2].clamp_min(1e-300) ** e / (cd * torch.maximum(wi[..., 2], wo[..., 2]))
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        return torch.where(up, v, 0.0).unsqueeze(-1).expand(*v.shape, 3)


@cache
def projected_blinn(J: int = 32, spacing: str = "sqrt", n: float = 50.0, kd: float = 0.2, ks: float = 0.6):
    return project(blinn(n, kd, ks), BandBasis("theta_h", J, spacing), "one", **QUAD_H)


# -- the band basis ----------------------------------------------------------------------------
@pytest.mark.parametrize("spacing", ["uniform", "sqrt", 3.0, "log:0.02", "lobe:100", "top:sqrt"])
def test_band_edges_cover_the_domain(spacing):
    e = band_edges(16, spacing)
    assert e.shape == (17,) and e.dtype == F64
    assert float(e[0]) == 0.0 and float(e[-1]) == math.pi / 2
    assert bool((e[1:] > e[:-1]).all())
    if spacing == "sqrt":  # MERL's half-angle mapping: edges (pi/2)(k/J)^2
        torch.testing.assert_close(e, (math.pi / 2) * (torch.arange(17, dtype=F64) / 16) ** 2)


@pytest.mark.parametrize(
    ("J", "spacing", "words"),
    [
        (16, "lobe:inf", "zero width"),  # 12 of 16 bands were [6e-25, 6e-25]
        (16, 1e300, "zero width"),
        (16, "log:inf", "NaN edges"),
        (10**9, "uniform", "J must be <= 4096"),  # allocated until the process was killed
        (16.7, "uniform", "J must be an integer"),  # was cut to 16 bands
    ],
)
def test_band_edges_refuse_empty_bands_and_huge_or_fractional_J(J, spacing, words):
    from torch_brdf.errors import ValueRangeError

    with pytest.raises(ValueRangeError, match=words):
        band_edges(J, spacing)
    with pytest.raises(ValueRangeError, match=words):
        BandBasis("theta_h", J, spacing)


def test_band_index_and_evaluate():
    b = BandBasis("theta_h", 8, "uniform")
    e = b.edges
    mids = 0.5 * (e[1:] + e[:-1])
    assert b.index(mids).tolist() == list(range(8))
    assert b.index(e[:-1]).tolist() == list(range(8))  # a band includes its lower edge
    assert int(b.index(torch.tensor([10.0], dtype=F64))) == 7 and int(b.index(torch.tensor([-1.0], dtype=F64))) == 0
    for var in ("theta_h", "theta_d", "theta_i", "anisotropy_ratio"):
        basis = BandBasis(var, 12, n_u=30.0 if var == "anisotropy_ratio" else None)
        wi, wo = pairs(300, 1)
        c = torch.rand(12, 3, generator=torch.Generator().manual_seed(2), dtype=F64)
        torch.testing.assert_close(basis.evaluate(c, wi, wo), basis.design(wi, wo) @ c)
        assert torch.allclose(basis.design(wi, wo).sum(-1), torch.ones(300, dtype=F64))


def test_symmetric_theta_i_basis_is_reciprocal_and_one_sided_is_not():
    wi, wo = pairs(200, 3)
    c = torch.rand(10, 3, generator=torch.Generator().manual_seed(4), dtype=F64)
    sym, one = BandBasis("theta_i", 10), BandBasis("theta_i", 10, symmetric=False)
    torch.testing.assert_close(sym.evaluate(c, wi, wo), sym.evaluate(c, wo, wi), rtol=0, atol=0)
    assert not torch.allclose(one.evaluate(c, wi, wo), one.evaluate(c, wo, wi))


def test_bad_arguments_raise():
    with pytest.raises(ValueRangeError):
        BandBasis("theta_x", 8)
    with pytest.raises(ValueRangeError):
        BandBasis("anisotropy_ratio", 8)  # needs n_u
    with pytest.raises(ValueRangeError):
        BandBasis("theta_h", 8, spacing="cubic")
    with pytest.raises(ValueRangeError):
        BandBasis("theta_h", edges=[0.0, 0.5, 0.4, math.pi / 2])
    with pytest.raises(ValueRangeError):
        make_quotient("phong")
    with pytest.raises(ShapeError):
        Factored1D(BandBasis("theta_h", 8), coefficients=torch.ones(7, 3))
    with pytest.raises(ValueRangeError):
        create("factored_1d", J=4, bogus=1)


# -- the quadrature and the projection ---------------------------------------------------------
def test_pair_quadrature_integrates_known_moments():
    q = PairQuadrature.build(BandBasis("theta_h", 16), **QUAD)
    tot = m2 = 0.0
    for wi, _wo, w in q.chunks(1 << 16):
        tot += float(w.sum())
        m2 += float((w * wi[:, 2]).sum())
    assert abs(tot - math.pi**2) < 1e-4 * math.pi**2  # int int cos cos = pi^2
    assert abs(m2 - 2 * math.pi**2 / 3) < 1e-4 * m2  # int int cos^2 cos = (2 pi / 3) pi


def test_projection_reproduces_a_lambertian_exactly():
    lam = create("lambert", albedo=[0.2, 0.5, 0.8])
    for var in ("theta_h", "theta_d", "theta_i"):
        c = project(lam, BandBasis(var, 16), "one", **QUAD_H)
        torch.testing.assert_close(c, torch.tensor([0.2, 0.5, 0.8], dtype=F64).expand(16, 3) / math.pi)


@pytest.mark.parametrize(
    "var,quotient",
    [
        ("theta_h", "distribution"),
        ("theta_d", "cook_torrance"),
        ("theta_i", "ashikhmin_shirley"),
        ("anisotropy_ratio", "one"),
    ],
)
def test_projection_recovers_coefficients_in_the_span(var, quotient):
    """A BRDF inside the span (quotient x bands) is recovered exactly, also for the coupled
    symmetric theta_i basis and the anisotropic variable."""
    basis = BandBasis(var, 12, n_u=40.0 if var == "anisotropy_ratio" else None)
    c = 0.1 + torch.rand(12, 3, generator=torch.Generator().manual_seed(5), dtype=F64)
    truth = Factored1D(basis, c, quotient).double()
    got = project(truth, basis, quotient, **(QUAD_ANISO if var == "anisotropy_ratio" else QUAD))
    torch.testing.assert_close(got, truth.coefficients.double(), rtol=1e-8, atol=1e-10)


def test_projection_error_falls_with_J_and_meets_the_target():
    bp = blinn(100.0)
    errs = {}
    for J in (8, 16, 32, 64):
        f = Factored1D.from_brdf(bp, BandBasis("theta_h", J), "one", **QUAD_H)
        errs[J] = projection_error(bp, f, **QUAD_H)
    assert errs[8] > errs[16] > errs[32] > errs[64]
    assert errs[64] < 0.55 * errs[32]  # first order: the error halves with J
    # MERL's sqrt spacing: 4.1% at n = 100, J = 64 (a pure lobe); the error of box bands is
    # ~ band width x slope, so <= 2% at J = 64 needs bands adapted to the lobe ("lobe:100")
    assert errs[64] < 0.045
    f = Factored1D.from_brdf(bp, BandBasis("theta_h", 64, "lobe:100"), "one", **QUAD_H)
    assert projection_error(bp, f, **QUAD_H) <= 0.02


def test_projected_brdfs_are_reciprocal():
    ct = create("cook_torrance", distribution="ggx", roughness=0.3, f0=0.1, kd=0.1)
    cases = [
        (blinn(100.0, 0.3, 0.6), BandBasis("theta_h", 32), "one"),
        (ct, BandBasis("theta_h", 32), SchlickFresnel(SmithQuotient("ggx", 0.3), 0.1)),
        (ct, BandBasis("theta_d", 16), "cook_torrance"),
        (ct, BandBasis("theta_i", 16), "distribution"),
    ]
    for brdf, basis, q in cases:
        c = project(brdf, basis, q, n_theta_h=16, n_theta_d=2, n_phi_d=4)
        for dt in (F32, F64):
            f = Factored1D(basis, c, q).to(dt)
            wi, wo = pairs(500, 6, dt)
            a, b = f.eval(wi, wo), f.eval(wo, wi)
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)


def test_projector_is_project_for_every_brdf_it_is_given():
    """The kept nodes and the factorised matrix give project's coefficients (same rule), for
    one-hot and coupled bases, plain and parameterised quotients, isotropic and anisotropic."""
    ct = create("cook_torrance", distribution="ggx", roughness=0.3, f0=0.1, kd=0.1)
    cases = [
        (BandBasis("theta_h", 32), "one", False, [blinn(100.0, 0.3, 0.6), ct]),
        (BandBasis("theta_d", 16), "cook_torrance", False, [ct, blinn(10.0)]),
        (BandBasis("theta_i", 16), "distribution", False, [ct]),
        (BandBasis("theta_h", 12), "one", True, [AnisoLobe(40.0, 5.0)]),
    ]
    for basis, q, aniso, brdfs in cases:
        rule = PairQuadrature.build(basis, aniso, **QUAD_ANISO)
        proj = Projector(basis, q, quadrature=rule)
        assert proj.pairs <= rule.size and proj.reached.shape == (basis.J, 3)
        for brdf in brdfs:
            for nonneg in (True, False):
                ref = project(brdf, basis, q, quadrature=rule, nonnegative=nonneg)
                got = proj(brdf, nonnegative=nonneg)
                assert float(ref.abs().max()) > 0
                torch.testing.assert_close(got, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))
    # without a rule it builds the one project would (quad_kwargs), anisotropic on request
    basis = BandBasis("theta_h", 16)
    ref = project(blinn(50.0), basis, **QUAD_H)
    torch.testing.assert_close(Projector(basis, **QUAD_H)(blinn(50.0)), ref, rtol=1e-9, atol=1e-14)
    assert Projector(basis, anisotropic=True, **QUAD_ANISO).pairs > Projector(basis, **QUAD_ANISO).pairs


def test_fresnel_quotient_helps_cook_torrance():
    ct = create("cook_torrance", distribution="ggx", roughness=0.2, f0=0.04)
    basis = BandBasis("theta_h", 32)
    plain = projection_error(ct, Factored1D.from_brdf(ct, basis, SmithQuotient("ggx", 0.2), **QUAD), **QUAD)
    two = FresnelFactored1D.from_brdf(ct, basis, SmithQuotient("ggx", 0.2), f0=0.04, **QUAD)
    assert projection_error(ct, two, **QUAD) < 0.06 < plain


def test_fresnel_two_layers_sum_to_the_brdf():
    c = projected_blinn()
    f = FresnelFactored1D(BandBasis("theta_h", 32), c, "one", f0=[0.05, 0.3, 0.9]).double()
    one, two = f.layers()
    wi, wo = pairs(400, 7)
    torch.testing.assert_close(one.eval(wi, wo) + two.eval(wi, wo), f.eval(wi, wo))
    # editing F is the runtime Fresnel edit: at normal incidence of h (theta_d = 0) f = F rho_q f
    wn = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    base = Factored1D(BandBasis("theta_h", 32), c, "one").double()
    torch.testing.assert_close(f.eval(wn, wn), base.eval(wn, wn) * torch.tensor([0.05, 0.3, 0.9], dtype=F64))


def test_anisotropy_ratio_factor_of_ashikhmin_shirley():
    """Eq. 33-35: with the quotient rho_q (cos theta_h)^(n_u cos^2 phi_h) the AS lobe is
    rho_qu gamma_r^r, so the projected curve is C gamma^r and the error falls with J."""
    nu, nv = 20.0, 80.0
    lobe = AnisoLobe(nu, nv)
    q = AnisotropicLobe(nu, "ashikhmin_shirley")
    errs = []
    for J in (4, 16):
        basis = BandBasis("anisotropy_ratio", J, n_u=nu)
        f = Factored1D.from_brdf(lobe, basis, q, **QUAD_ANISO)
        errs.append(projection_error(lobe, f, **QUAD_ANISO))
        c = f.coefficients.detach().double()[:, 0]
        assert bool((c[1:] > c[:-1]).all())  # gamma^r increases (r = 4)
    assert errs[1] < 0.3 * errs[0] and errs[1] < 0.05
    # the exact curve C gamma^4, averaged over the top band [g, 1], bounds its coefficient
    C = math.sqrt((nu + 1) * (nv + 1)) / (8 * math.pi)
    assert C * float(basis.edges[-2]) ** 4 <= float(c[-1]) <= C * (1 + 1e-6)
    ref = create("ashikhmin_shirley", rd=0.0, rs=1.0, nu=nu, nv=nv)  # the repo's model, F = 1
    wi, wo = pairs(200, 8)
    torch.testing.assert_close(ref.eval(wi, wo).double(), lobe.eval_local(wi, wo), rtol=1e-4, atol=1e-8)


def test_coefficients_are_editable_and_differentiable():
    f = create("factored_1d", J=16)  # default: Lambert of albedo 0.5
    wi, wo = pairs(50, 9, F32)
    torch.testing.assert_close(f.eval(wi, wo), torch.full((50, 3), 0.5 / math.pi))
    f.eval(wi, wo).sum().backward()
    assert f.raw_coefficients.grad is not None and bool((f.raw_coefficients.grad.abs().sum(-1) > 0).any())
    f.set_coefficients(torch.linspace(0, 0.3, 16))
    assert torch.allclose(f.coefficients[:, 1], torch.linspace(0, 0.3, 16))


# -- equivalent albedo and the hierarchy -------------------------------------------------------
@pytest.fixture
def cache_tmp(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(tmp_path))
    return tmp_path


def test_equivalent_albedo_of_a_constant_curve_is_its_albedo(cache_tmp):
    a = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    for var in ("theta_h", "theta_d", "theta_i"):
        basis = BandBasis(var, 16)
        e = band_albedos(basis, "one", samples_per_band=2048, progress=False)
        assert abs(float(e.sum()) - math.pi**2) < 5e-3 * math.pi**2
        f = Factored1D(basis, a.expand(16, 3) / math.pi)
        torch.testing.assert_close(equivalent_albedo(f, e).double(), a, rtol=5e-3, atol=0)


def test_equivalent_albedo_matches_quadrature_of_the_brdf(cache_tmp):
    """d = (1/pi) sum c_j e_j (MC e_j) against (1/pi) int int rho cos cos (quadrature)."""
    basis = BandBasis("theta_h", 32)
    f = Factored1D(basis, projected_blinn(), "one").double()
    tot = torch.zeros(3, dtype=F64)
    for wi, wo, w in PairQuadrature.build(basis, **QUAD).chunks():
        tot += (f.eval_local(wi, wo) * w[:, None]).sum(0)
    d = equivalent_albedo(f, samples_per_band=4096, progress=False).detach().double()
    torch.testing.assert_close(d, tot / math.pi, rtol=5e-3, atol=0)


def test_band_albedo_cache_hit_and_corrupt_entry(cache_tmp, monkeypatch):
    ea = importlib.import_module("torch_brdf.brdf.bands.albedo")

    basis = BandBasis("theta_d", 8)
    e1 = band_albedos(basis, "cook_torrance", samples_per_band=512, progress=False)
    files = list((cache_dir() / "equivalent_albedo").glob("*.npz"))
    assert len(files) == 1 and cache_dir() == cache_tmp

    def boom(*args, **kwargs):
        raise AssertionError("recomputed although cached")

    real = ea._compute
    monkeypatch.setattr(ea, "_compute", boom)
    e2 = band_albedos(basis, "cook_torrance", samples_per_band=512, progress=False)
    assert torch.equal(e1, e2)
    files[0].write_bytes(files[0].read_bytes()[:100])  # truncate: corrupt entry
    monkeypatch.setattr(ea, "_compute", real)
    with pytest.warns(EquivalentAlbedoCacheWarning):
        e3 = band_albedos(basis, "cook_torrance", samples_per_band=512, progress=False)
    assert torch.equal(e1, e3)  # seeded: the recomputation is identical, and rewritten
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        monkeypatch.setattr(ea, "_compute", boom)
        assert torch.equal(band_albedos(basis, "cook_torrance", samples_per_band=512, progress=False), e1)
    # another parameterisation (seed) is another entry; cache=False neither reads nor writes
    monkeypatch.setattr(ea, "_compute", real)
    e4 = band_albedos(basis, "cook_torrance", samples_per_band=512, seed=1, progress=False)
    band_albedos(basis, "cook_torrance", samples_per_band=256, progress=False, cache=False)
    assert not torch.equal(e4, e1) and len(list((cache_dir() / "equivalent_albedo").glob("*.npz"))) == 2


def test_coarsening_keeps_the_equivalent_albedo(cache_tmp):
    basis = BandBasis("theta_h", 32)
    f = Factored1D(basis, projected_blinn(), "one")
    e = band_albedos(basis, "one", samples_per_band=1024, progress=False)
    d = equivalent_albedo(f, e).detach().double()
    levels = f.hierarchy(samples_per_band=1024, progress=False)
    assert [g.J for g in levels] == [32, 16, 8, 4, 2, 1]
    for g in levels[1:]:
        eg = torch.zeros(g.J, dtype=F64).index_add_(0, basis.groups(g.J), e)
        torch.testing.assert_close(equivalent_albedo(g, eg).detach().double(), d, rtol=1e-6, atol=0)
    # the last level is the Lambertian of albedo d (Sec. 4.2): c = pi d / sum(e), and sum(e) = pi^2
    # up to the Monte Carlo error of e
    c1 = levels[-1].coefficients.detach().double()[0]
    torch.testing.assert_close(c1, math.pi * d / e.sum(), rtol=1e-6, atol=0)
    torch.testing.assert_close(c1, d / math.pi, rtol=1e-2, atol=0)
    # coarse levels are lower-frequency approximations: the error against the fine BRDF grows
    errs = [projection_error(f, g, **QUAD) for g in levels]
    assert errs[0] == 0.0 and all(a <= b + 1e-12 for a, b in itertools.pairwise(errs))
    odd = f.coarsen(5, weights=e)  # any J_new: contiguous groups of nearly equal size
    assert odd.J == 5 and odd.basis.edges[0] == 0 and odd.basis.edges[-1] == basis.edges[-1]


# -- the shared BRDF contract ------------------------------------------------------------------
class TestFactoredThetaH(BRDFContract):
    """Blinn-Phong (kd 0.2, ks 0.6, n = 50) projected onto 32 sqrt-spaced theta_h bands."""

    def make(self, dtype):
        return Factored1D(BandBasis("theta_h", 32), projected_blinn(), "one").to(dtype)


class TestFactoredThetaD(BRDFContract):
    """A Fresnel-like rising curve on uniform theta_d bands (quotient 1)."""

    def make(self, dtype):
        t = (torch.arange(16, dtype=F64) + 0.5) / 16
        c = (0.3 + 0.5 * t**4)[:, None] * torch.tensor([0.9, 0.7, 0.5], dtype=F64) / math.pi
        return Factored1D(BandBasis("theta_d", 16), c, "one").to(dtype)


class TestFactoredThetaISymmetric(BRDFContract):
    """A curve on the reciprocal (symmetrised) theta_i/theta_o basis."""

    def make(self, dtype):
        t = (torch.arange(12, dtype=F64) + 0.5) / 12
        c = (0.6 - 0.4 * t**2)[:, None].expand(12, 3) / math.pi
        return Factored1D(BandBasis("theta_i", 12), c, "one").to(dtype)


class TestFresnelFactored(BRDFContract):
    """The Fresnel two-layer form on the projected Blinn-Phong curve."""

    def make(self, dtype):
        return FresnelFactored1D(BandBasis("theta_h", 32), projected_blinn(), "one", f0=[0.04, 0.5, 0.9]).to(dtype)


class TestFactoredAnisotropyRatio(BRDFContract):
    """The AS anisotropy-ratio form (n_u = 20, r = 3) with half the AS normalisation."""

    def make(self, dtype):
        nu, r = 20.0, 3.0
        basis = BandBasis("anisotropy_ratio", 16, n_u=nu)
        g = 0.5 * (basis.edges[1:] + basis.edges[:-1])
        c = 0.5 * math.sqrt((nu + 1) * (r * nu + 1)) / (8 * math.pi) * g**r
        return Factored1D(basis, c, AnisotropicLobe(nu, "ashikhmin_shirley")).to(dtype)
