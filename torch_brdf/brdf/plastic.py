r"""Mitsuba 3's ``roughplastic`` (and ``plastic`` as its smooth limit): a rough dielectric coat
over a diffuse base, evaluated as Mitsuba evaluates it, so that an imported Mitsuba scene
shades the same.

.. math::
    f = s\,\frac{F(\omega_i\cdot h, \eta)\,D(h)\,G_1(\omega_i)G_1(\omega_o)}{4\cos\theta_i\cos\theta_o}
      + \frac{\rho}{1 - F_{dr}}\,\frac{T(\cos\theta_i)\,T(\cos\theta_o)}{\pi\,\eta^2},

with the exact unpolarised dielectric Fresnel reflectance :math:`F` of the relative IOR
:math:`\eta` = interior / exterior IOR, :math:`D` GGX or Beckmann of roughness
:math:`\alpha`, the separable Smith masking :math:`G_1` of that distribution (Heitz 2014),
specular reflectance :math:`s` and diffuse reflectance :math:`\rho` (Mitsuba's
``nonlinear = true`` divides by :math:`1 - \rho F_{dr}` instead); Beckmann's :math:`G_1` is
Mitsuba's rational approximation (:class:`MitsubaBeckmannNDF`). The coat's external
transmittance :math:`T(\mu)` is the single-scattering transmittance of the rough interface
(:func:`coat_transmittance`; below :math:`1 - R` at high roughness, as masking loses energy),
and the internal diffuse reflectance
:math:`F_{dr} = 2\int_0^1 R_\alpha(\mu, 1/\eta)\,\mu\,d\mu` that of its underside. Like
Mitsuba (``roughplastic.cpp``), :math:`T` is tabulated at the 64 cosines
:math:`\mu_k = \max(10^{-6}, k/63)` and interpolated linearly in :math:`\cos\theta`, and
:math:`F_{dr}` is twice the plain mean of :math:`R(\mu_k, 1/\eta)\,\mu_k` over the same
cosines (a coarse rule; keeping it keeps the diffuse level of Mitsuba's). The albedos
:math:`R_\alpha` come from a tensor-product Gauss-Legendre rule in float64 (:func:`coat_albedo`),
over GGX's visible normals (Heitz 2018) or Beckmann's :math:`D(h)\cos\theta_h`; Mitsuba's
rule (float32, its own visible-normal warps) differs by the residual that
``tests/brdf/test_plastic.py`` measures against Mitsuba's own ``eval``: below 0.2% at every
pair tested.

``smooth=True`` is Mitsuba's ``plastic``: the diffuse weights become the exact
:math:`T(\mu) = 1 - F(\mu, \eta)` and :math:`F_{dr}` the accurate hemispherical integral of
:math:`F(\mu, 1/\eta)` (Mitsuba uses a polynomial fit of it); the delta coat, which a BRDF
evaluated at direction pairs cannot hold, is a sharp GGX lobe of the given roughness.

Gradients reach every parameter: the tables are cached per (distribution, :math:`\alpha`,
:math:`\eta`) with their derivatives, and enter the graph as a first-order expansion about
the cached point (exact value; the derivative is a central difference of the tables, whose
quadrature is piecewise smooth in :math:`\alpha, \eta` where nodes cross the critical angle).
A new (:math:`\alpha`, :math:`\eta`) costs five table integrations (about a second).

Energy: Mitsuba's diffuse weights do not close the energy balance (the coat's single
scattering loses energy, and :math:`(1 - F_{dr})\,\eta^2` is not the hemispherical mean of
:math:`T`): a white plastic reflects less than it receives (about 0.8 at normal incidence for
GGX, :math:`\alpha = 0.2`, :math:`\eta = 1.5`; ``tests/brdf/test_plastic.py``).
:meth:`RoughPlastic.albedo_bound` documents 1.02 to leave room for the quadrature.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..errors import ValueRangeError
from ..frame import half_terms
from .base import Clamped, Positive, register
from .microfacet import (
    ALPHA_MIN,
    GGXNDF,
    BeckmannNDF,
    MicrofacetMixture,
    check_range,
    lobe_weight,
    safe_pair,
    sample_ggx_vndf,
)
from .textured import TEXTURE_RULES

__all__ = [
    "TABLE_SIZE",
    "MitsubaBeckmannNDF",
    "RoughPlastic",
    "coat_albedo",
    "coat_transmittance",
    "dielectric_fresnel",
]

#: cosines of Mitsuba's transmittance table (``MI_ROUGH_TRANSMITTANCE_RES``)
TABLE_SIZE = 64
#: Gauss-Legendre order per dimension of the coat-albedo rule
QUADRATURE_ORDER = 64
_DISTRIBUTIONS = ("beckmann", "ggx")
_CACHE_SIZE = 16
_FD_STEP = 1e-3  # wide: steps over the kinks of the internal reflectance's quadrature
#: (distribution, smooth, alpha, eta) -> (tables, their Jacobian): shared by every model, so
#: that copies and re-created materials do not integrate again
_TABLE_CACHE: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}


def dielectric_fresnel(cos_i: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    r"""Unpolarised Fresnel reflectance of a dielectric interface with relative IOR
    :math:`\eta` (transmitted over incident side), light arriving at :math:`\cos\theta_i \ge 0`;
    1 under total internal reflection (:math:`\eta < 1`).

    Args:
        cos_i: (*B,) cosines in [0, 1].
        eta: () relative IOR.
    Returns:
        (*B,).
    """
    c = cos_i.clamp(0.0, 1.0)
    cos_t2 = 1.0 - (1.0 - c * c) / (eta * eta)
    tir = cos_t2 <= 0
    ct = cos_t2.clamp_min(1e-30).sqrt()
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return torch.where(tir, torch.ones_like(c), 0.5 * (rs * rs + rp * rp))


@dataclass(frozen=True)
class MitsubaBeckmannNDF(BeckmannNDF):
    r"""Isotropic Beckmann with Mitsuba's rational Smith masking (Walter et al. 2007, Eq. 27;
    within 0.35% of the exact :math:`G_1`): with :math:`a = \cot\theta/\alpha`,
    :math:`G_1 = (3.535a + 2.181a^2)/(1 + 2.276a + 2.577a^2)` below :math:`a = 1.6`, else 1.
    Mitsuba's ``roughplastic`` uses it in ``eval`` and in its tables."""

    def G1_over_cos(self, w):
        c = w[..., 2].clamp_min(0.0)
        sin = (w[..., 0] ** 2 + w[..., 1] ** 2).clamp_min(1e-20).sqrt()
        inv = 1.0 / (self.alpha_x * sin)
        a = c * inv
        small = a < 1.6
        a_s = torch.where(small, a, torch.zeros_like(a))
        rational = inv * (3.535 + 2.181 * a_s) / (1.0 + 2.276 * a_s + 2.577 * a_s * a_s)
        return torch.where(small, rational, 1.0 / torch.where(small, torch.ones_like(c), c))


def _gauss_legendre01(order: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    import numpy as np

    x, w = np.polynomial.legendre.leggauss(order)
    return torch.as_tensor(0.5 * (x + 1.0), dtype=dtype), torch.as_tensor(0.5 * w, dtype=dtype)


def coat_albedo(
    distribution: str, alpha: torch.Tensor, eta: torch.Tensor, mu: torch.Tensor, order: int = QUADRATURE_ORDER
) -> torch.Tensor:
    r"""Directional albedo :math:`R_\alpha(\mu, \eta)` of a rough dielectric interface in
    reflection (single scattering, separable Smith masking), for light arriving at
    :math:`\cos\theta = \mu`:

    .. math:: R = \int F(\omega\cdot h, \eta)\,G_1(\omega)G_1(\omega')\,
              \frac{(\omega\cdot h)_+ D(h)}{\cos\theta}\,d\omega_h,
              \quad \omega' = \mathrm{reflect}(\omega, h),\ \omega'_z > 0,

    by an ``order`` x ``order`` Gauss-Legendre rule in the uniforms that map to half vectors:
    GGX's visible normals of :math:`\omega` (:func:`~torch_brdf.brdf.microfacet.sample_ggx_vndf`),
    Beckmann's density :math:`D(h)\cos\theta_h` (inverse CDF in :math:`\theta_h`, uniform
    :math:`\phi_h`).

    Args:
        distribution: ``"ggx"`` or ``"beckmann"``.
        alpha: () roughness.
        eta: () relative IOR.
        mu: (K,) cosines in (0, 1].
    Returns:
        (K,).
    """
    return _coat_integral(distribution, alpha, eta, mu, order, transmit=False)


def coat_transmittance(
    distribution: str, alpha: torch.Tensor, eta: torch.Tensor, mu: torch.Tensor, order: int = QUADRATURE_ORDER
) -> torch.Tensor:
    r"""Directional transmittance :math:`T_\alpha(\mu, \eta)` of a rough dielectric interface
    (single scattering, separable Smith masking) for light arriving at :math:`\cos\theta = \mu`:

    .. math:: T = \int (1 - F(\omega\cdot h, \eta))\,G_1(\omega)G_1(\omega_t)\,
              \frac{(\omega\cdot h)_+ D(h)}{\cos\theta}\,d\omega_h,

    :math:`\omega_t` the refraction of :math:`\omega` about :math:`h` (kept where it points
    below the surface), by the rule of :func:`coat_albedo`. Less than :math:`1 - R_\alpha` at
    high roughness: single scattering loses what the masking stops.

    Args:
        distribution: ``"ggx"`` or ``"beckmann"``.
        alpha: () roughness.
        eta: () relative IOR (> 1).
        mu: (K,) cosines in (0, 1].
    Returns:
        (K,).
    """
    return _coat_integral(distribution, alpha, eta, mu, order, transmit=True)


def _coat_integral(distribution, alpha, eta, mu, order, transmit):
    dt = mu.dtype
    x, w = _gauss_legendre01(order, dt)
    # wi lies in the xz-plane: the integrand is even in phi, so phi runs over [0, pi] only
    u1, u2 = x[:, None], 0.5 * x[None, :]
    wi = torch.stack(((1.0 - mu * mu).clamp_min(0.0).sqrt(), torch.zeros_like(mu), mu), -1)  # (K, 3)
    if distribution == "ggx":
        # over GGX's visible normals (Heitz 2018), as Mitsuba integrates: a smooth integrand
        # F G1(wo) where the D cos(theta_h) rule converged slowly in GGX's long tail
        ndf = GGXNDF(alpha)
        uu = torch.stack(torch.meshgrid(x, x, indexing="ij"), -1)  # (N, N, 2)
        shape = (mu.shape[0], order, order)
        wi_ = wi[:, None, None, :].expand(*shape, 3)
        h_ = sample_ggx_vndf(wi_, uu.expand(*shape, 2), alpha)
        weight = w[:, None] * w[None, :]
        cos_h = None
    else:
        tan2 = -alpha * alpha * torch.log1p(-u1)
        ndf = MitsubaBeckmannNDF(alpha)
        cos_h = torch.rsqrt(1.0 + tan2)
        sin_h = (tan2 / (1.0 + tan2)).sqrt()
        phi = 2.0 * math.pi * u2
        h = torch.stack(torch.broadcast_tensors(sin_h * torch.cos(phi), sin_h * torch.sin(phi), cos_h), -1)
        weight = w[:, None] * w[None, :]
        wi_, h_ = wi[:, None, None, :], h[None]
    d = (wi_ * h_).sum(-1)  # (K, N, N)
    dc = d.clamp_min(0.0)
    fr = dielectric_fresnel(dc, eta)
    if transmit:
        cos_t = (1.0 - (1.0 - dc * dc) / (eta * eta)).clamp_min(0.0).sqrt()
        wo = (dc / eta - cos_t).unsqueeze(-1) * h_ - wi_ / eta
        wo = -wo  # mirrored to the upper hemisphere: G1 depends on the direction's slope only
        fr = 1.0 - fr
    else:
        wo = 2.0 * d.unsqueeze(-1) * h_ - wi_
    ok = (d > 0) & (wo[..., 2] > 0)
    wo_safe = torch.where(ok.unsqueeze(-1), wo, torch.tensor([0.0, 0.0, 1.0], dtype=dt))
    g_o = ndf.G1_over_cos(wo_safe) * wo_safe[..., 2]
    if cos_h is None:  # visible normals: the density already holds G1(wi) (wi.h) D / cos(theta_i)
        val = fr * g_o
    else:
        # the density of visible normals that Mitsuba draws from holds the exact G1(wi)
        g_i = BeckmannNDF(alpha).G1_over_cos(wi)[:, None, None]
        val = fr * g_i * g_o * dc / cos_h
    return (torch.where(ok, val, torch.zeros((), dtype=dt)) * weight).sum((-1, -2))


def _table_cosines(dtype: torch.dtype) -> torch.Tensor:
    return torch.linspace(0.0, 1.0, TABLE_SIZE, dtype=dtype).clamp_min(1e-6)


def _tables(distribution: str, smooth: bool, alpha: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """(TABLE_SIZE + 1,) float64: the external transmittance T(mu_k) then F_dr."""
    mu = _table_cosines(torch.float64)
    if smooth:
        # exact interface weights; F_dr as a fine Gauss-Legendre integral in mu
        x, w = _gauss_legendre01(512, torch.float64)
        fdr = 2.0 * (dielectric_fresnel(x, 1.0 / eta) * x * w).sum()
        return torch.cat((1.0 - dielectric_fresnel(mu, eta), fdr.reshape(1)))
    t = coat_transmittance(distribution, alpha, eta, mu, QUADRATURE_ORDER)
    fdr = 2.0 * (coat_albedo(distribution, alpha, 1.0 / eta, mu, QUADRATURE_ORDER) * mu).mean()
    return torch.cat((t.clamp_min(0.0), fdr.reshape(1)))


@register("rough_plastic")
class RoughPlastic(MicrofacetMixture):
    r"""Mitsuba 3's ``roughplastic`` (``smooth=True``: ``plastic``); see the module docstring.

    Sampling: the coat's distribution (GGX visible normals, Beckmann :math:`D\cos\theta_h`)
    with Mitsuba's probability :math:`(1 - T)\,\bar s / ((1 - T)\,\bar s + T\,\bar\rho)` at
    :math:`\theta_o` (kept in [0.05, 0.95] by :func:`~torch_brdf.brdf.microfacet.lobe_weight`),
    else the cosine lobe.

    Args:
        distribution: ``"beckmann"`` (Mitsuba's default) or ``"ggx"``.
        roughness: :math:`\alpha` in :math:`[10^{-4}, 1]`.
        eta: relative IOR (interior / exterior) in [1, 4]; default polypropylene in air.
        diffuse_reflectance: RGB :math:`\rho` in [0, 1].
        specular_reflectance: RGB :math:`s` in [0, 1] (Mitsuba's default 1).
        nonlinear: Mitsuba's ``nonlinear`` (divide by :math:`1 - \rho F_{dr}`).
        smooth: Mitsuba's ``plastic`` (exact Fresnel transmittance, a sharp coat lobe).
    """

    ROUGHNESS_RANGE = (1e-4, 1.0)
    #: relative IOR bounds (Clamped: the editor's slider); at 1 the coat vanishes
    ETA_RANGE = (1.0, 4.0)

    def __init__(
        self,
        distribution: str = "beckmann",
        roughness=0.1,
        eta=1.49 / 1.000277,
        diffuse_reflectance=0.5,
        specular_reflectance=1.0,
        nonlinear: bool = False,
        smooth: bool = False,
    ):
        super().__init__()
        if distribution not in _DISTRIBUTIONS:
            raise ValueRangeError(f"RoughPlastic.distribution must be one of {_DISTRIBUTIONS}; got {distribution!r}")
        check_range("RoughPlastic", "roughness", roughness, *self.ROUGHNESS_RANGE)
        self.distribution, self.nonlinear, self.smooth = distribution, bool(nonlinear), bool(smooth)
        self.register_constrained("roughness", roughness, Positive())
        self.register_constrained("eta", eta, Clamped(*self.ETA_RANGE))
        self.register_constrained("diffuse_reflectance", diffuse_reflectance, Clamped(0.0, 1.0), shape=(3,))
        self.register_constrained("specular_reflectance", specular_reflectance, Clamped(0.0, 1.0), shape=(3,))

    def microfacet_distribution(self, dtype: torch.dtype) -> GGXNDF | BeckmannNDF:
        """The coat's distribution of the current roughness (clamped at ``ALPHA_MIN``)."""
        a = self.roughness.to(dtype).clamp_min(ALPHA_MIN)
        return GGXNDF(a) if self.distribution == "ggx" else MitsubaBeckmannNDF(a)

    def tables(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        r"""The transmittance table :math:`T(\mu_k)` (TABLE_SIZE,) and :math:`F_{dr}` ()
        of the current roughness and IOR, in ``dtype``, differentiable in both."""
        a = self.roughness.clamp_min(ALPHA_MIN)
        e = self.eta
        key = (self.distribution, self.smooth, float(a.detach()), float(e.detach()))
        hit = _TABLE_CACHE.get(key)
        if hit is None:
            p0 = torch.tensor([key[2], key[3]], dtype=torch.float64)

            def fn(p):
                return _tables(self.distribution, self.smooth, p[0], p[1])

            # central differences: the tables are smooth in both (forward-mode autograd
            # through the quadrature costs several times more)
            with torch.no_grad():
                value = fn(p0)
                cols = []
                for k in range(2):
                    step = torch.zeros(2, dtype=torch.float64)
                    step[k] = _FD_STEP * max(1.0, float(p0[k]))
                    cols.append((fn(p0 + step) - fn(p0 - step)) / (2.0 * float(step[k])))
            jac = torch.stack(cols, -1)  # (TABLE_SIZE + 1, 2)
            if len(_TABLE_CACHE) >= _CACHE_SIZE:
                _TABLE_CACHE.pop(next(iter(_TABLE_CACHE)))
            hit = _TABLE_CACHE[key] = (value, jac)
        value, jac = hit
        # exact value at the cached point; the gradient flows through the first-order term
        delta = torch.stack((a - a.detach(), e - e.detach())).to(torch.float64)
        out = (value + jac @ delta).to(dtype)
        return out[:-1], out[-1]

    @staticmethod
    def _lerp(table: torch.Tensor, cos: torch.Tensor) -> torch.Tensor:
        x = cos.clamp(0.0, 1.0) * (TABLE_SIZE - 1)
        idx = x.detach().floor().clamp_max(TABLE_SIZE - 2).long()
        w1 = x - idx.to(x.dtype)
        return table[idx] * (1.0 - w1) + table[idx + 1] * w1

    def eval_local(self, wi, wo):
        return self.eval_with_diffuse(wi, wo, self.diffuse_reflectance)

    def eval_with_diffuse(self, wi: torch.Tensor, wo: torch.Tensor, rho: torch.Tensor) -> torch.Tensor:
        """f (*B, 3) for local wi, wo (*B, 3) with the diffuse reflectance ``rho`` ((3,) or
        (*B, 3), e.g. scaled by a texture) in place of the model's."""
        dt = wi.dtype
        dist = self.microfacet_distribution(dt)
        eta = self.eta.to(dt)
        t, fdr = self.tables(dt)
        wi, wo, up = safe_pair(wi, wo)
        ht = half_terms(wi, wo)
        fr = dielectric_fresnel(ht.cos_d, eta)
        spec = 0.25 * dist.D(ht.s) * dist.G1_over_cos(wi) * dist.G1_over_cos(wo) * fr
        rho = rho.to(dt)
        denom = 1.0 - (rho * fdr if self.nonlinear else fdr)
        trans = self._lerp(t, wi[..., 2]) * self._lerp(t, wo[..., 2]) / (math.pi * eta * eta)
        f = spec.unsqueeze(-1) * self.specular_reflectance.to(dt) + (rho / denom) * trans.unsqueeze(-1)
        return torch.where(up.unsqueeze(-1), f, torch.zeros((), dtype=dt))

    def _p_spec(self, wo):
        dt = wo.dtype
        t, _ = self.tables(dt)
        t_o = self._lerp(t, wo[..., 2])
        s_mean = self.specular_reflectance.to(dt).mean()
        d_mean = self.diffuse_reflectance.to(dt).mean()
        return lobe_weight((1.0 - t_o) * s_mean, t_o * d_mean)

    def albedo_bound(self, wo: torch.Tensor) -> torch.Tensor:
        """Documented upper bound of the directional albedo: 1.02, shape (*B, 3)."""
        return torch.full(wo.shape[:-1] + (3,), 1.02, dtype=wo.dtype)


def _texture_rule(brdf: RoughPlastic, wi: torch.Tensor, wo: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """A texture scales the diffuse reflectance (Mitsuba's textured ``diffuse_reflectance``):
    exact, also for ``nonlinear``."""
    return brdf.eval_with_diffuse(wi, wo, brdf.diffuse_reflectance.to(wi.dtype) * scale.to(wi.dtype))


TEXTURE_RULES["rough_plastic"] = _texture_rule
