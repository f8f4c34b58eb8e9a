r"""The shared BRDF test case: :class:`BRDFContract`.

Every BRDF model's tests subclass it once per parameter setting and implement
:meth:`BRDFContract.make`::

    class TestBlinnGlossy(BRDFContract):
        def make(self, dtype):
            return BlinnPhong(kd=0.2, ks=0.6, exponent=50.0).to(dtype)

and pytest collects the whole contract for that model (the base class is not collected:
its name does not start with ``Test``). The checks follow the package's conventions
(:mod:`torch_brdf.brdf.base`: local directions, ``eval`` without the cosine, ``sample``
returns ``(wi, pdf)`` with ``pdf = 0`` for invalid samples):

* ``test_non_negative_finite_and_one_sided``: f >= 0, finite, (*B, 3), 0 below the horizon;
* ``test_reciprocity``: f(wi, wo) = f(wo, wi) to ``reciprocity_rtol`` (table);
* ``test_albedo_bound``: the directional albedo by dense quadrature is at most
  :meth:`~BRDFContract.albedo_bound` (1 unless the model documents another bound) over
  the model and its :meth:`~BRDFContract.extremes`, from normal to grazing :math:`\omega_o`;
* ``test_batch_equals_loop``: batched eval/pdf/sample equal a loop over single directions,
  and extra batch dimensions are kept;
* ``test_float32_matches_float64``: within ``vs_float64_rtol`` where values exceed
  ``value_floor`` (same inputs, rounded to float32 first);
* ``test_gradcheck``: :func:`torch.autograd.gradcheck` in float64 of eval and pdf with
  respect to every raw parameter (skipped only for models without parameters; the flag
  ``check_gradients = False`` is refused for a model that has parameters);
* ``test_sampling_matches_quadrature``: :math:`E[f\cos\theta_i/\mathrm{pdf}]` over seeded
  samples equals the quadrature albedo within ``mc_rtol`` (1%);
* ``test_sampling_chi2``: Pearson's chi-square test of ``sample`` against ``pdf`` (the
  suite's one helper, :func:`tests._stats.assert_chi2`: Mitsuba 3's ``chi2.py`` pooling,
  significance 0.01 with the Šidák factor ``chi2_family_size``);
* ``test_sample_returns_its_pdf``: the returned pdf equals ``pdf(wi, wo)``, samples are
  unit vectors, ``pdf > 0`` only above the horizon;
* ``test_extremes_are_finite``: eval, pdf, sample and parameter gradients are finite in
  float32 and float64 at :meth:`~BRDFContract.extremes` and at extreme directions
  (normal, :math:`\cos\theta = 10^{-7}`, on and below the horizon, :math:`\omega_i = -\omega_o`,
  :math:`\omega_i = \omega_o`, mirror pairs, u at 0 and 1);
* ``test_direction_gradients_are_finite``: so are the gradients of eval with respect to
  the directions at those pairs;
* ``test_world_frame_matches_local``: eval/sample through a :class:`~torch_brdf.frame.Frame`
  (with a tangent) match the local versions; isotropic models (``anisotropic = False``) are
  invariant under a rotation about the normal.

The quadratures are independent of the model's sampler. The albedo integral is taken over
half vectors, :math:`\int f\cos\theta_i\,d\omega_i = \int f\cos\theta_i\,4(\omega_o\cdot h)\,
d\omega_h` (Walter et al. 2007), on a Gauss-Legendre grid in :math:`\log\theta_h`
(from :math:`10^{-7}`) times a uniform grid in :math:`\phi_h`: it resolves specular lobes
down to mirror-like widths (they all peak at :math:`h = n`) as well as broad ones. The
chi-square cells are polar cells around the mirror direction of :math:`\omega_o` with
log-spaced radii (so near-mirror lobes spread over several cells), integrated by adaptive
Gauss-Legendre cubature. Subclasses whose lobes peak elsewhere can override
:meth:`~BRDFContract.albedo_quadrature` or the class attributes below.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np
import pytest
import torch
from torch import nn

from tests._stats import assert_chi2
from torch_brdf.brdf.base import BRDF, Clamped
from torch_brdf.errors import ValueRangeError
from torch_brdf.frame import Frame, orthonormal_basis
from torch_brdf.parallel.threads import single_thread

F32, F64 = torch.float32, torch.float64


@dataclass(frozen=True)
class Tolerances:
    """Per-dtype tolerances of the contract (relative unless named otherwise)."""

    reciprocity_rtol: float
    batch_rtol: float
    vs_float64_rtol: float  # float32 against float64 on the same inputs
    value_floor: float  # absolute: values below it are compared with this absolute tolerance
    frame_rtol: float  # world-space (through a Frame) against local evaluation
    pdf_rtol: float  # sample()'s pdf against pdf()


TOLERANCES = {
    F32: Tolerances(
        reciprocity_rtol=1e-5, batch_rtol=1e-6, vs_float64_rtol=1e-4, value_floor=1e-6, frame_rtol=1e-3, pdf_rtol=1e-5
    ),
    F64: Tolerances(
        reciprocity_rtol=1e-5, batch_rtol=1e-12, vs_float64_rtol=0.0, value_floor=1e-12, frame_rtol=1e-7, pdf_rtol=1e-10
    ),
}

#: Statistical tests (always float64)
MC_RTOL = 0.01  # MC albedo against quadrature
MC_ATOL = 1e-4  # ... plus this absolute slack for albedos near 0


# -- directions ---------------------------------------------------------------------------------
def direction(theta: float, phi: float = 0.7, dtype: torch.dtype = F64) -> torch.Tensor:
    """Unit local direction (3,) at polar angle ``theta`` and azimuth ``phi`` (radians)."""
    st = math.sin(theta)
    return torch.tensor([st * math.cos(phi), st * math.sin(phi), math.cos(theta)], dtype=dtype)


def hemisphere(n: int, generator: torch.Generator, dtype: torch.dtype = F64, min_cos: float = 0.0) -> torch.Tensor:
    """(n, 3) random unit directions with z > min_cos (float64 draws, then cast): Gaussian
    draws folded to z >= 0; the few at or below ``min_cos`` are tilted up towards the normal
    (to z >= 0.87), which keeps the draw deterministic and vectorised."""
    v = torch.randn(n, 3, generator=generator, dtype=F64)
    v[:, 2] = v[:, 2].abs()
    v = v / v.norm(dim=-1, keepdim=True)
    lo = max(min_cos, 1e-6)
    v = torch.where(v[:, 2:3] > lo, v, torch.cat([v[:, :2] * 0.5, torch.full((n, 1), 0.9, dtype=F64)], -1))
    return (v / v.norm(dim=-1, keepdim=True)).to(dtype)


def extreme_pairs(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """(M, 3) pairs (wi, wo) at the hard cases: normal, cos = 1e-7, on and below the
    horizon, wi = -wo, wi = wo, mirror pairs, mixed."""
    c = 1e-7
    s = math.sqrt(1 - c * c)
    base = [
        (0.0, 0.0, 1.0),
        (s, 0.0, c),
        (-s * 0.6, s * 0.8, c),
        (1.0, 0.0, 0.0),
        (0.0, -1.0, 0.0),
        (0.6, 0.0, -0.8),
        (0.0, 0.0, -1.0),
        (math.sin(1.2), 0.0, math.cos(1.2)),
        (0.0, math.sin(0.3), math.cos(0.3)),
    ]
    d = torch.tensor(base, dtype=F64)
    wi, wo = [], []
    for a in d:
        for b in d:
            wi.append(a)
            wo.append(b)
        wi.append(-a)  # wi = -wo
        wo.append(a)
        wi.append(a * torch.tensor([-1.0, -1.0, 1.0], dtype=F64))  # mirror pair
        wo.append(a)
    return torch.stack(wi).to(dtype), torch.stack(wo).to(dtype)


def extreme_uniforms(dtype: torch.dtype) -> torch.Tensor:
    """(K, 2) uniforms at the corners of [0, 1)^2 and in between."""
    one = 1.0 - torch.finfo(dtype).eps
    vals = [0.0, 1e-12, 0.5, one]
    return torch.tensor([(a, b) for a in vals for b in vals], dtype=dtype)


# -- quadratures ----------------------------------------------------------------------------------
@cache
def _gauss_legendre(order: int) -> tuple[torch.Tensor, torch.Tensor]:
    x, w = np.polynomial.legendre.leggauss(order)
    return torch.tensor(x, dtype=F64), torch.tensor(w, dtype=F64)


@cache
def half_vector_grid(panels: int = 48, order: int = 8, n_phi: int = 192, theta_min: float = 1e-7):
    r"""Nodes and weights of the half-vector quadrature: composite Gauss-Legendre in
    :math:`\log\theta_h \in [\log\theta_{min}, \log(\pi/2)]` times the midpoint rule in
    :math:`\phi_h`. Returns h (M, 3) and weights (M,) of :math:`d\omega_h`."""
    x, w = _gauss_legendre(order)
    edges = torch.linspace(math.log(theta_min), math.log(math.pi / 2), panels + 1, dtype=F64)
    a, b = edges[:-1, None], edges[1:, None]
    t = ((a + b) / 2 + (b - a) / 2 * x).reshape(-1)
    wt = ((b - a) / 2 * w).reshape(-1)
    theta = t.exp()
    w_theta = wt * theta * torch.sin(theta)  # d(theta) = theta d(log theta); sin(theta) of d(omega)
    phi = (torch.arange(n_phi, dtype=F64) + 0.5) * (2 * math.pi / n_phi)
    th, ph = torch.meshgrid(theta, phi, indexing="ij")
    h = torch.stack((th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()), -1).reshape(-1, 3)
    weights = (w_theta[:, None] * (2 * math.pi / n_phi)).expand(-1, n_phi).reshape(-1)
    return h, weights


def half_vector_albedo(
    brdf: BRDF, wo: torch.Tensor, panels: int = 48, order: int = 8, n_phi: int = 192, theta_min: float = 1e-7
) -> torch.Tensor:
    r"""Directional albedo (3,) of local ``wo`` (3,) by quadrature over half vectors (float64):

    .. math:: \int f(\omega_i,\omega_o)\cos\theta_i\,d\omega_i
              = \int f\,\cos\theta_i\,4(\omega_o\cdot h)\,d\omega_h,
              \qquad \omega_i = 2(\omega_o\cdot h)h - \omega_o .

    For each of ``n_phi`` azimuths (midpoint rule) the polar integral runs from
    ``theta_min`` to the horizon of :math:`\omega_i`, :math:`\theta_{max}(\phi_h) =
    (\delta + \pi/2)/2` with :math:`\delta = \mathrm{atan2}(\sin\theta_o\cos(\phi_h-\phi_o),
    \cos\theta_o)` (where :math:`\cos\theta_i = \sin\theta_o\cos(\phi_h-\phi_o)\sin 2\theta_h +
    \cos\theta_o\cos 2\theta_h` vanishes), by composite Gauss-Legendre in
    :math:`\log\theta_h`: the horizon is a panel end, so the integrand is smooth on every
    panel, and lobes peaking at :math:`h = n` are resolved down to mirror-like widths."""
    x, w = _gauss_legendre(order)
    wo = wo.to(F64)
    theta_o = math.acos(max(-1.0, min(1.0, float(wo[2]))))
    phi_o = math.atan2(float(wo[1]), float(wo[0]))
    phi = (torch.arange(n_phi, dtype=F64) + 0.5) * (2 * math.pi / n_phi)
    delta = torch.atan2(math.sin(theta_o) * torch.cos(phi - phi_o), torch.full_like(phi, math.cos(theta_o)))
    theta_max = ((delta + math.pi / 2) / 2).clamp_min(2 * theta_min)
    lo, hi = math.log(theta_min), theta_max.log()  # (n_phi,)
    tau = torch.linspace(0, 1, panels + 1, dtype=F64)
    a, b = tau[:-1, None], tau[1:, None]
    t01 = ((a + b) / 2 + (b - a) / 2 * x).reshape(-1)  # (panels * order,) in [0, 1]
    w01 = ((b - a) / 2 * w).reshape(-1)
    log_t = lo + t01[None, :] * (hi - lo)[:, None]  # (n_phi, K)
    theta = log_t.exp()
    weights = w01[None, :] * (hi - lo)[:, None] * theta * torch.sin(theta) * (2 * math.pi / n_phi)
    ph = phi[:, None].expand_as(theta)
    h = torch.stack((theta.sin() * ph.cos(), theta.sin() * ph.sin(), theta.cos()), -1).reshape(-1, 3)
    weights = weights.reshape(-1)
    wo_b = wo.expand_as(h)
    d = (h * wo_b).sum(-1, keepdim=True)
    wi = 2 * d * h - wo_b
    wi = wi / wi.norm(dim=-1, keepdim=True)
    ok = (wi[:, 2] > 0) & (d[:, 0] > 0)
    with torch.no_grad():
        f = brdf.eval_local(wi, wo_b).to(F64)
    val = f * (wi[:, 2].clamp_min(0) * 4 * d[:, 0] * weights * ok).unsqueeze(-1)
    return val.sum(0)


def _rect_rule(fn, lo: torch.Tensor, hi: torch.Tensor, order: int) -> torch.Tensor:
    """Tensor-product Gauss-Legendre estimate of the integral of fn over rectangles (R, 2)."""
    x, w = _gauss_legendre(order)
    xy = torch.stack(torch.meshgrid(x, x, indexing="ij"), -1).reshape(-1, 2)
    ww = (w[:, None] * w[None, :]).reshape(-1)
    c, r = (lo + hi) / 2, (hi - lo) / 2
    pts = c[:, None, :] + r[:, None, :] * xy[None]
    vals = fn(pts.reshape(-1, 2)).reshape(len(lo), -1)
    return (vals * ww).sum(-1) * r[:, 0] * r[:, 1]


def adaptive_cell_integrals(
    fn, lo: torch.Tensor, hi: torch.Tensor, n_cells: int, tol: float = 1e-7, max_depth: int = 9, order: int = 4
) -> torch.Tensor:
    """Integrals of ``fn`` ((M, 2) points -> (M,)) over the rectangles ``lo, hi`` (n_cells, 2),
    by quadtree refinement until a rectangle's estimate and its four children's agree to
    ``tol`` (absolute; at least two levels, at most ``max_depth``). Returns (n_cells,)."""
    out = torch.zeros(n_cells, dtype=F64)
    cell = torch.arange(n_cells)
    est = _rect_rule(fn, lo, hi, order)
    for depth in range(max_depth + 1):
        mid = (lo + hi) / 2
        clo = torch.cat([lo, torch.stack((mid[:, 0], lo[:, 1]), -1), torch.stack((lo[:, 0], mid[:, 1]), -1), mid])
        chi = torch.cat([mid, torch.stack((hi[:, 0], mid[:, 1]), -1), torch.stack((mid[:, 0], hi[:, 1]), -1), hi])
        cest = _rect_rule(fn, clo, chi, order)
        total = cest.reshape(4, -1).sum(0)
        done = ((total - est).abs() <= tol) & (depth >= 2) | (depth == max_depth)
        out.index_add_(0, cell[done], total[done])
        keep = (~done).repeat(4)
        lo, hi, est, cell = clo[keep], chi[keep], cest[keep], cell.repeat(4)[keep]
        if len(lo) == 0:
            break
    return out


class _EvalAndPdf(nn.Module):
    """Wrap a BRDF so torch.func.functional_call can swap its raw parameters."""

    def __init__(self, brdf: BRDF):
        super().__init__()
        self.brdf = brdf

    def forward(self, wi, wo):
        return torch.cat([self.brdf.eval_local(wi, wo).reshape(-1), self.brdf.pdf_local(wi, wo).reshape(-1)])


def _clamped_bounds(module: nn.Module, name: str):
    """(lo, hi) if parameter ``name`` ('a.b.raw_x') is stored behind Clamped, else None."""
    *path, leaf = name.split(".")
    owner = module.get_submodule(".".join(path)) if path else module
    cons = getattr(owner, "__dict__", {}).get("_constraints", {})
    t = cons.get(leaf[4:]) if leaf.startswith("raw_") else None
    return (t.lo, t.hi) if isinstance(t, Clamped) else None


# -- the contract ---------------------------------------------------------------------------------
class BRDFContract:
    """The shared checks of every BRDF model (see the module docstring).

    Hooks (override in subclasses):
        make(dtype): the model under test, parameters in ``dtype`` (required).
        extremes(dtype): models at the corners of the parameter ranges (default: [make]).
        albedo_bound(brdf, wo): (3,) documented bound of the directional albedo (default 1).
        albedo_quadrature(brdf, wo): (3,) reference albedo (default: half-vector quadrature).

    Class attributes:
        check_gradients: run gradcheck (may be False only for models without parameters).
        albedo_thetas, mc_thetas, chi2_thetas: outgoing polar angles (degrees) tested.
        mc_samples, mc_max_samples, chi2_samples: sample counts (float64, seeded).
        chi2_family_size: number of chi-square tests in the suite (Bonferroni factor).
        chi2_min_angle, chi2_radial_bins, chi2_azimuth_bins: the chi-square cells.
        seed: base seed of every random draw.
    """

    check_gradients: bool = True
    albedo_thetas: tuple[float, ...] = (0.0, 30.0, 60.0, 80.0, 89.9)
    mc_thetas: tuple[float, ...] = (0.0, 40.0, 75.0)
    chi2_thetas: tuple[float, ...] = (30.0, 70.0)
    mc_samples: int = 1 << 16
    mc_max_samples: int = 1 << 20
    chi2_samples: int = 100_000
    chi2_family_size: int = 1
    chi2_min_angle: float = 1e-3
    chi2_radial_bins: int = 10
    chi2_azimuth_bins: int = 12
    seed: int = 20240601

    @pytest.fixture(autouse=True)
    def _one_thread(self):
        """Run the contract on one intra-op thread: its tensors are small (1e5 elements), and on
        a shared 2-core machine OpenMP's spinning second thread made the suite 3-4x slower."""
        with single_thread():
            yield

    # -- hooks ------------------------------------------------------------------------------------
    def make(self, dtype: torch.dtype) -> BRDF:
        raise NotImplementedError

    def extremes(self, dtype: torch.dtype) -> list[BRDF]:
        return [self.make(dtype)]

    def albedo_bound(self, brdf: BRDF, wo: torch.Tensor) -> torch.Tensor:
        return torch.ones(3, dtype=F64)

    def albedo_quadrature(self, brdf: BRDF, wo: torch.Tensor) -> torch.Tensor:
        return half_vector_albedo(brdf, wo)

    # -- helpers ----------------------------------------------------------------------------------
    def gen(self, offset: int = 0) -> torch.Generator:
        return torch.Generator().manual_seed(self.seed + offset)

    def pairs(self, n: int, dtype: torch.dtype = F64, offset: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """(n, 3) pairs: half random, half drawn from the model's own lobe (so that narrow lobes
        are exercised where they are not ~0)."""
        g = self.gen(offset)
        wo = hemisphere(n, g, F64, min_cos=0.02)
        wi = hemisphere(n, g, F64, min_cos=0.02)
        m = n // 2
        u = torch.rand(m, 2, generator=g, dtype=F64)
        with torch.no_grad():
            ws, pdf = self.make(F64).sample_local(wo[:m], u)
        good = (pdf > 0) & (ws[:, 2] > 0.02)
        wi[:m] = torch.where(good.unsqueeze(-1), ws, wi[:m])
        return wi.to(dtype), wo.to(dtype)

    # -- the checks ---------------------------------------------------------------------------------
    def test_non_negative_finite_and_one_sided(self):
        for dt in (F32, F64):
            brdf = self.make(dt)
            wi, wo = self.pairs(400, dt, 1)
            f = brdf.eval(wi, wo)
            assert f.shape == (400, 3) and f.dtype == dt
            assert bool(torch.isfinite(f).all()) and bool((f >= 0).all())
            flip = torch.tensor([1.0, 1.0, -1.0], dtype=dt)
            assert not brdf.eval(wi * flip, wo).any() and not brdf.eval(wi, wo * flip).any()
            assert not brdf.pdf(wi, wo * flip).any() and not brdf.pdf(wi * flip, wo).any()

    def test_reciprocity(self):
        for dt in (F32, F64):
            brdf = self.make(dt)
            wi, wo = self.pairs(400, dt, 2)
            a, b = brdf.eval(wi, wo), brdf.eval(wo, wi)
            tol = TOLERANCES[dt]
            torch.testing.assert_close(a, b, rtol=tol.reciprocity_rtol, atol=tol.value_floor * 1e-3)

    def test_albedo_bound(self):
        for i, brdf in enumerate([self.make(F64), *self.extremes(F64)]):
            for th in self.albedo_thetas:
                wo = direction(math.radians(th))
                a = self.albedo_quadrature(brdf, wo)
                bound = self.albedo_bound(brdf, wo).to(F64)
                assert bool((a >= -1e-9).all()), (i, th, a)
                assert bool((a <= bound * (1 + 1e-3) + 1e-6).all()), f"model {i} theta_o={th}: albedo {a} > {bound}"

    def test_batch_equals_loop(self):
        for dt in (F32, F64):
            tol = TOLERANCES[dt].batch_rtol
            brdf = self.make(dt)
            wi, wo = self.pairs(24, dt, 3)
            u = torch.rand(24, 2, generator=self.gen(4), dtype=dt)
            f, p = brdf.eval(wi, wo), brdf.pdf(wi, wo)
            ws, ps = brdf.sample(wo, None, u)
            loop_f = torch.stack([brdf.eval(a, b) for a, b in zip(wi, wo, strict=True)])
            loop_p = torch.stack([brdf.pdf(a, b) for a, b in zip(wi, wo, strict=True)])
            loop_s = [brdf.sample(b, None, c) for b, c in zip(wo, u, strict=True)]
            torch.testing.assert_close(loop_f, f, rtol=tol, atol=0)
            torch.testing.assert_close(loop_p, p, rtol=tol, atol=0)
            torch.testing.assert_close(torch.stack([s[0] for s in loop_s]), ws, rtol=tol, atol=tol)
            torch.testing.assert_close(torch.stack([s[1] for s in loop_s]), ps, rtol=tol, atol=0)
            shaped = brdf.eval(wi.reshape(2, 3, 4, 3), wo.reshape(2, 3, 4, 3))
            assert shaped.shape == (2, 3, 4, 3)
            torch.testing.assert_close(shaped.reshape(24, 3), f, rtol=tol, atol=0)
            assert brdf.pdf(wi.reshape(4, 6, 3), wo.reshape(4, 6, 3)).shape == (4, 6)
            w2, p2 = brdf.sample(wo.reshape(6, 4, 3), None, u.reshape(6, 4, 2))
            assert w2.shape == (6, 4, 3) and p2.shape == (6, 4)

    def test_float32_matches_float64(self):
        tol = TOLERANCES[F32]
        wi, wo = self.pairs(2000, F32, 5)
        b32, b64 = self.make(F32), self.make(F64)
        for name, v32, v64 in (
            ("eval", b32.eval(wi, wo), b64.eval(wi.double(), wo.double())),
            ("pdf", b32.pdf(wi, wo), b64.pdf(wi.double(), wo.double())),
        ):
            assert v32.dtype == F32, name
            err = (v32.double() - v64).abs()
            allowed = torch.where(v64.abs() > tol.value_floor, tol.vs_float64_rtol * v64.abs(), tol.value_floor)
            worst = int(torch.argmax((err / allowed).reshape(-1)))
            assert bool((err <= allowed).all()), (
                f"{name}: float32 off by {err.reshape(-1)[worst]:.3g} at value {v64.reshape(-1)[worst]:.6g}"
            )

    def test_gradcheck(self):
        brdf = self.make(F64)
        names = [n for n, _ in brdf.named_parameters()]
        if not self.check_gradients:
            assert not names, f"check_gradients = False is only allowed for models without parameters; got {names}"
        if not names:
            pytest.skip("model has no parameters")
        raws = []
        for n, p in brdf.named_parameters():
            v = p.detach().clone().double()
            b = _clamped_bounds(brdf, n)
            if b is not None:  # a value exactly on a Clamped bound is a kink: check just inside
                lo, hi = b
                span = 1.0 if not math.isfinite(hi - lo) else hi - lo
                v = v.clamp(lo + 1e-3 * span, hi - 1e-3 * span)
            raws.append(v.requires_grad_(True))
        wi, wo = self.pairs(12, F64, 6)
        wrapper = _EvalAndPdf(brdf)

        def fn(*tensors):
            return torch.func.functional_call(
                wrapper, {"brdf." + n: t for n, t in zip(names, tensors, strict=True)}, (wi, wo)
            )

        assert torch.autograd.gradcheck(fn, tuple(raws), eps=1e-6, atol=1e-6, rtol=1e-4)

    def test_constrained_setters(self):
        """``model.<name> = value`` goes through the inverse transform into the same raw
        Parameter (gpytorch's setter): eval, ``state_dict`` and the optimiser's tensor all see
        the new value; out-of-range values raise and leave the parameter unchanged."""
        brdf = self.make(F64)
        owners = [(m, n) for m in brdf.modules() for n in getattr(m, "__dict__", {}).get("_constraints", {})]
        if not owners:
            pytest.skip("model has no constrained parameters")
        wi, wo = self.pairs(16, F64, 7)
        for owner, name in owners:
            transform = owner._constraints[name]
            raw = getattr(owner, "raw_" + name)
            old = getattr(owner, name).detach().clone()
            if isinstance(transform, Clamped) and math.isfinite(transform.hi):
                x = (old - transform.lo) / (transform.hi - transform.lo)
                new = transform.lo + (transform.hi - transform.lo) * torch.where(x < 0.5, x + 0.3, x - 0.3)
                too_big, too_small = transform.hi + 0.5, transform.lo - 0.5
            else:  # Positive, Clamped(lo, inf)
                new = 1.5 * old + 0.1
                too_big, too_small = None, getattr(transform, "lower", getattr(transform, "lo", 0.0)) - 1.0
            assert not torch.allclose(new, old), (name, old)
            raw_before = raw.detach().clone()
            setattr(owner, name, new)
            assert getattr(owner, "raw_" + name) is raw, f"{name}: the raw Parameter was replaced"
            assert isinstance(raw, nn.Parameter) and raw.requires_grad, name
            assert name not in owner.__dict__, f"{name} is shadowed by an instance attribute"
            assert torch.allclose(getattr(owner, name), new.expand_as(getattr(owner, name)), rtol=1e-12, atol=1e-12)
            sd_key = next(k for k, v in brdf.state_dict(keep_vars=True).items() if v is raw)
            assert torch.equal(brdf.state_dict()[sd_key], raw.detach())
            assert not torch.equal(raw.detach(), raw_before), f"{name}: raw_{name} kept its old value"
            # evaluation uses the assigned value: a fresh model loaded from the state_dict agrees
            fresh = self.make(F64)
            fresh.load_state_dict(brdf.state_dict())
            assert torch.equal(fresh.eval(wi, wo), brdf.eval(wi, wo)), name
            # out-of-range and non-finite values raise
            for bad in (too_small, too_big, float("nan")):
                if bad is None:
                    continue
                before = raw.detach().clone()
                with pytest.raises(ValueRangeError):
                    setattr(owner, name, bad)
                assert torch.equal(raw.detach(), before), f"{name}: a refused value changed the parameter"

    def _mc_albedo(self, brdf: BRDF, wo: torch.Tensor, n: int, offset: int) -> tuple[torch.Tensor, torch.Tensor]:
        u = torch.rand(n, 2, generator=self.gen(offset), dtype=F64)
        wo_b = wo.expand(n, 3)
        with torch.no_grad():
            wi, pdf = brdf.sample_local(wo_b, u)
            f = brdf.eval_local(wi, wo_b)
        w = torch.where(pdf > 0, wi[:, 2].clamp_min(0) / pdf.clamp_min(1e-300), 0.0)
        x = f * w.unsqueeze(-1)
        return x.mean(0), x.std(0) / math.sqrt(n)

    def test_sampling_matches_quadrature(self):
        """MC albedo with the model's sampler against the quadrature. The sample count doubles
        (from ``mc_samples``, seeded, at most ``mc_max_samples``) until the standard error is
        below a third of the tolerance, so that the 1% check is not decided by noise; a
        sampler too poor to get there within the cap fails."""
        brdf = self.make(F64)
        for k, th in enumerate(self.mc_thetas):
            wo = direction(math.radians(th))
            ref = self.albedo_quadrature(brdf, wo)
            n = self.mc_samples
            mc, se = self._mc_albedo(brdf, wo, n, 10 + k)
            while bool((se > (MC_RTOL * ref + MC_ATOL) / 3).any()) and 2 * n <= self.mc_max_samples:
                n *= 2
                mc, se = self._mc_albedo(brdf, wo, n, 10 + k)
            assert bool(torch.isfinite(mc).all())
            assert bool(((mc - ref).abs() <= MC_RTOL * ref + MC_ATOL).all()), (
                f"theta_o={th}: MC {mc.tolist()} (s.e. {se.tolist()}, {n} samples) vs quadrature {ref.tolist()}"
            )

    def _chi2_cells(self, wo: torch.Tensor):
        """Cell edges around the mirror direction r of wo: radii [0, g_min, log-spaced ...,
        pi/2, 3pi/4, pi] (pi/2 is a cell edge: lobes defined on the hemisphere about r end
        there), azimuths uniform about r (from a basis s_r, t_r)."""
        r = wo * torch.tensor([-1.0, -1.0, 1.0], dtype=F64)
        s, t = orthonormal_basis(r)
        logs = torch.logspace(
            math.log10(self.chi2_min_angle), math.log10(math.pi / 2), self.chi2_radial_bins, dtype=F64
        )
        radial = torch.cat([torch.zeros(1, dtype=F64), logs, torch.tensor([0.75 * math.pi, math.pi], dtype=F64)])
        radial[len(logs)] = math.pi / 2
        azim = torch.linspace(0, 2 * math.pi, self.chi2_azimuth_bins + 1, dtype=F64)
        return r, s, t, radial, azim

    def test_sampling_chi2(self):
        brdf = self.make(F64)
        for k, th in enumerate(self.chi2_thetas):
            wo = direction(math.radians(th))
            r, s, t, radial, azim = self._chi2_cells(wo)
            nr, na = len(radial) - 1, len(azim) - 1
            n = self.chi2_samples
            u = torch.rand(n, 2, generator=self.gen(20 + k), dtype=F64)
            with torch.no_grad():
                wi, pdf = brdf.sample_local(wo.expand(n, 3), u)
            valid = pdf > 0
            cos_g = (wi * r).sum(-1)
            sin_g = torch.linalg.cross(wi, r.expand_as(wi), dim=-1).norm(dim=-1)
            gamma = torch.atan2(sin_g, cos_g)
            psi = torch.atan2((wi * t).sum(-1), (wi * s).sum(-1)) % (2 * math.pi)
            ir = (torch.searchsorted(radial, gamma.contiguous(), right=True) - 1).clamp(0, nr - 1)
            ia = (torch.searchsorted(azim, psi.contiguous(), right=True) - 1).clamp(0, na - 1)
            obs = torch.bincount((ir * na + ia)[valid], minlength=nr * na).double()

            def density(x, wo=wo, r=r, s=s, t=t):
                g, p = x[:, 0], x[:, 1]
                w = torch.cos(g)[:, None] * r + torch.sin(g)[:, None] * (
                    torch.cos(p)[:, None] * s + torch.sin(p)[:, None] * t
                )
                with torch.no_grad():
                    return brdf.pdf_local(w, wo.expand_as(w)).to(F64) * torch.sin(g)

            gi, ai = torch.meshgrid(torch.arange(nr), torch.arange(na), indexing="ij")
            lo = torch.stack((radial[gi.reshape(-1)], azim[ai.reshape(-1)]), -1)
            hi = torch.stack((radial[gi.reshape(-1) + 1], azim[ai.reshape(-1) + 1]), -1)
            mass = adaptive_cell_integrals(density, lo, hi, nr * na, tol=1e-7)
            total = float(mass.sum())
            assert total <= 1 + 1e-3, f"pdf integrates to {total} > 1"
            observed = torch.cat([obs, torch.tensor([float((~valid).sum())], dtype=F64)])
            expected = torch.cat([mass * n, torch.tensor([max(1 - total, 0.0) * n], dtype=F64)])
            assert_chi2(observed, expected, n, self.chi2_family_size, what=f"theta_o={th}: ")

    def test_sample_returns_its_pdf(self):
        for dt in (F32, F64):
            brdf = self.make(dt)
            g = self.gen(7)
            wo = hemisphere(500, g, dt)
            u = torch.rand(500, 2, generator=g, dtype=dt)
            wi, pdf = brdf.sample(wo, None, u)
            assert wi.shape == (500, 3) and pdf.shape == (500,) and wi.dtype == dt and pdf.dtype == dt
            assert bool(torch.isfinite(wi).all()) and bool(torch.isfinite(pdf).all()) and bool((pdf >= 0).all())
            torch.testing.assert_close(wi.norm(dim=-1), torch.ones(500, dtype=dt), rtol=0, atol=1e-5)
            assert bool((wi[pdf > 0, 2] > 0).all())
            assert float((pdf > 0).double().mean()) > 0.5, "most samples of a reflection lobe should be valid"
            torch.testing.assert_close(pdf, brdf.pdf(wi, wo), rtol=TOLERANCES[dt].pdf_rtol, atol=0)

    def test_extremes_are_finite(self):
        for dt in (F32, F64):
            wi, wo = extreme_pairs(dt)
            us = extreme_uniforms(dt)
            for i, brdf in enumerate([self.make(dt), *self.extremes(dt)]):
                f, p = brdf.eval(wi, wo), brdf.pdf(wi, wo)
                assert bool(torch.isfinite(f).all()) and bool((f >= 0).all()), (dt, i, "eval")
                assert bool(torch.isfinite(p).all()) and bool((p >= 0).all()), (dt, i, "pdf")
                wo_s = wo.repeat_interleave(len(us), 0)
                u_s = us.repeat(len(wo), 1)
                ws, ps = brdf.sample(wo_s, None, u_s)
                assert bool(torch.isfinite(ws).all()) and bool(torch.isfinite(ps).all()), (dt, i, "sample")
                assert bool((ps >= 0).all()), (dt, i, "sample pdf")
                params = [q for q in brdf.parameters() if q.requires_grad]
                if params:
                    loss = brdf.eval(wi, wo).sum() + brdf.pdf(wi, wo).sum()
                    grads = torch.autograd.grad(loss, params, allow_unused=True)
                    for q, gr in zip(params, grads, strict=True):
                        assert gr is None or bool(torch.isfinite(gr).all()), (dt, i, "gradient", q.shape)

    def test_direction_gradients_are_finite(self):
        # d f / d(wi, wo) at the extreme pairs: sqrt at wi = -wo and at the horizon gave NaN
        for dt in (F32, F64):
            wi, wo = (w.clone().requires_grad_(True) for w in extreme_pairs(dt))
            for i, brdf in enumerate([self.make(dt), *self.extremes(dt)]):
                f = brdf.eval(wi, wo)
                if not f.requires_grad:  # a table lookup: not differentiable in the directions
                    continue
                gi, go = torch.autograd.grad(f.sum(), (wi, wo), allow_unused=True)
                for g in (gi, go):
                    assert g is None or bool(torch.isfinite(g).all()), (dt, i, int((~torch.isfinite(g)).sum()))

    def test_world_frame_matches_local(self):
        brdf = self.make(F64)
        wi, wo = self.pairs(200, F64, 8)
        g = self.gen(9)
        normal = torch.randn(200, 3, generator=g, dtype=F64)
        normal = normal / normal.norm(dim=-1, keepdim=True)
        frame = Frame.from_normal(normal, torch.randn(200, 3, generator=g, dtype=F64))
        tol = TOLERANCES[F64].frame_rtol
        f_world = brdf.eval(frame.to_world(wi), frame.to_world(wo), frame)
        torch.testing.assert_close(f_world, brdf.eval_local(wi, wo), rtol=tol, atol=1e-12)
        u = torch.rand(200, 2, generator=g, dtype=F64)
        ws, ps = brdf.sample(frame.to_world(wo), frame, u)
        wl, pl = brdf.sample_local(wo, u)
        torch.testing.assert_close(frame.to_local(ws), wl, rtol=tol, atol=1e-9)
        torch.testing.assert_close(ps, pl, rtol=tol, atol=1e-12)
        if not brdf.anisotropic:
            ang = torch.rand(200, generator=g, dtype=F64) * 2 * math.pi
            c, s = ang.cos(), ang.sin()

            def rot(v):
                return torch.stack((c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]), -1)

            torch.testing.assert_close(brdf.eval_local(rot(wi), rot(wo)), brdf.eval_local(wi, wo), rtol=tol, atol=1e-12)
