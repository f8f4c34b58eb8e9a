r"""Microfacet pieces and the Cook-Torrance BRDF.

Plain functions first (normal distributions :math:`D`, Smith masking :math:`G_1`,
Schlick's Fresnel, half-vector sampling, lobe mixtures); :class:`CookTorrance` and the
models of :mod:`torch_brdf.brdf.analytic` are thin modules on top of them.

Conventions (see :mod:`torch_brdf.brdf.base`): local directions ``(*B, 3)`` with
:math:`z` = normal, pointing away from the surface. Every normal distribution here is
normalised over projected microfacet area,

.. math:: \int_{\Omega} D(h)\,(h\cdot n)\,d\omega_h = 1,

so that drawing :math:`h` with density :math:`D(h)(h\cdot n)` and reflecting
:math:`\omega_o` about it gives :math:`\omega_i` with the solid-angle density
:math:`D(h)(h\cdot n) / (4\,|\omega_o\cdot h|)` (Walter et al. 2007, "Microfacet Models for Refraction
through Rough Surfaces").

Numerical stability (the models must stay finite in float32 at Blinn exponents
:math:`10^4`, GGX roughness :math:`10^{-4}` and :math:`\cos\theta \approx 10^{-7}`):
angles of the half vector are read from the *unnormalised* sum
:math:`s = \omega_i + \omega_o` as :math:`\tan^2\theta_h = (s_x^2 + s_y^2)/s_z^2`, which is
accurate near the mirror direction where :math:`1 - \cos\theta_h` would cancel; powers are
taken in log space (:math:`\cos^n\theta_h = \exp(-\tfrac n2 \log(1 + \tan^2\theta_h))`);
:math:`\omega_i\cdot h = |s|/2` and :math:`1 - \omega_i\cdot h` is computed from
:math:`|\omega_i - \omega_o|` without cancellation. Inputs are assumed unit length.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ..errors import ValueRangeError
from ..frame import Frame, HalfTerms, half_terms, orthonormal_basis
from ..sphere.warps import square_to_cosine_hemisphere, square_to_cosine_power_hemisphere
from .base import BRDF, Clamped, Positive, register

__all__ = [
    "GGXNDF",
    "AnisotropicPhongNDF",
    "BeckmannNDF",
    "BlinnNDF",
    "CookTorrance",
    "MicrofacetDistribution",
    "MicrofacetMixture",
    "beckmann_d",
    "beckmann_g1_over_cos",
    "blinn_d",
    "ggx_d",
    "ggx_g1_over_cos",
    "ggx_log_d",
    "half_vector_pdf",
    "lobe_weight",
    "mixture_pdf",
    "mixture_sample",
    "reflect",
    "safe_pair",
    "sample_around",
    "sample_beckmann_h",
    "sample_blinn_h",
    "sample_ggx_vndf",
    "schlick_fresnel",
]


#: Safety clamp of roughness inside the math (below the documented 1e-4): finite in float32.
ALPHA_MIN = 1e-5

#: Smallest cosine the models divide by (Ward's, Ashikhmin-Shirley's and the distribution-based
#: BRDF's 1/cos factors), the same in every dtype: at theta = 90 degrees cos(pi/2) rounds to
#: 6e-17, and a dtype's own floor would let float32 and float64 give values 1e13 apart there.
#: Below it (theta > 89.99994 degrees) those factors stop growing.
GRAZING_COS = 1e-6


# -- small numerical helpers ---------------------------------------------------------------
def _tiny(dtype: torch.dtype) -> float:
    return torch.finfo(dtype).tiny


def _floor(dtype: torch.dtype) -> float:
    """sqrt(tiny): a floor for squared quantities whose reciprocal must stay finite."""
    return math.sqrt(torch.finfo(dtype).tiny)


def check_range(owner: str, name: str, value, lo: float, hi: float) -> None:
    """Raise :class:`ValueRangeError` unless every entry of ``value`` lies in [lo, hi]."""
    try:
        v = torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):  # a string, a ragged list, ...
        raise ValueRangeError(f"{owner}.{name} must be a number or a list of numbers; got {value!r}") from None
    if not bool(torch.isfinite(v).all()) or bool(((v < lo) | (v > hi)).any()):
        raise ValueRangeError(f"{owner}.{name} must lie in [{lo:g}, {hi:g}]; got {value!r}")


def safe_pair(wi: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Replace pairs with a direction at or below the horizon by (+z, +z).

    The models evaluate their formulas on the returned pair and mask the result with ``up``:
    the formulas never see the 0/0 of an invalid pair, so that neither the values nor the
    gradients (``where`` passes 0 * inf = NaN back through a masked branch) become NaN.

    Returns:
        wi, wo: (*B, 3) safe local directions; up: (*B,) bool, both strictly above the horizon.
    """
    up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    z = torch.zeros((3,), dtype=wi.dtype)
    z[2] = 1.0
    m = up.unsqueeze(-1)
    return torch.where(m, wi, z), torch.where(m, wo, z), up


def schlick_fresnel(f0: torch.Tensor, one_minus_cos: torch.Tensor) -> torch.Tensor:
    r"""Schlick's approximation :math:`F_0 + (1 - F_0)(1 - \cos\theta_d)^5` (Schlick 1994).

    Args:
        f0: (3,) or (*B, 3) reflectance at normal incidence.
        one_minus_cos: (*B,) :math:`1 - \cos\theta_d` in [0, 1].
    Returns:
        (*B, 3).
    """
    return f0 + (1.0 - f0) * (one_minus_cos.clamp(0.0, 1.0) ** 5).unsqueeze(-1)


# -- normal distributions --------------------------------------------------------------------
def blinn_d(tan2: torch.Tensor, exponent: torch.Tensor) -> torch.Tensor:
    r"""Normalised Blinn distribution :math:`D_n(h) = \frac{n+2}{2\pi}\cos^n\theta_h`
    (Blinn 1977 with the projected-area normalisation, Walter et al. 2007).

    Args:
        tan2: (*B,) :math:`\tan^2\theta_h`.
        exponent: () or (*B,) :math:`n > 0`.
    Returns:
        (*B,) :math:`D_n(h)`.
    """
    return (exponent + 2.0) / (2.0 * math.pi) * torch.exp(-0.5 * exponent * torch.log1p(tan2))


def beckmann_d(h: torch.Tensor, alpha_x: torch.Tensor, alpha_y: torch.Tensor | None = None) -> torch.Tensor:
    r"""(Anisotropic) Beckmann distribution, the one of Ward 1992 and Cook-Torrance 1982:

    .. math:: D(h) = \frac{\exp\!\big(-\tan^2\theta_h(\cos^2\phi_h/\alpha_x^2 + \sin^2\phi_h/\alpha_y^2)\big)}
              {\pi\alpha_x\alpha_y\cos^4\theta_h},

    evaluated as :math:`\exp(-(h_x^2/\alpha_x^2 + h_y^2/\alpha_y^2)/h_z^2 + 2\log(1+\tan^2\theta_h))`
    so that the horizon gives 0 rather than 0/0.

    Args:
        h: (*B, 3) half vectors with :math:`h_z > 0`, any positive length.
        alpha_x: () or (*B,) roughness along the tangent.
        alpha_y: () or (*B,) roughness along the bitangent (None: ``alpha_x``, isotropic).
    Returns:
        (*B,).
    """
    ay = alpha_x if alpha_y is None else alpha_y
    h = _unit_scale(h)
    hz2 = (h[..., 2] ** 2).clamp_min(_floor(h.dtype))
    hx2, hy2 = h[..., 0] ** 2, h[..., 1] ** 2
    expo = -(hx2 / alpha_x**2 + hy2 / ay**2) / hz2 + 2.0 * torch.log1p((hx2 + hy2) / hz2)
    return torch.exp(expo) / (math.pi * alpha_x * ay)


def _unit_scale(h: torch.Tensor) -> torch.Tensor:
    """``h`` (*B, 3) rescaled so its largest component is 1 where its squared length would fall
    under the dtype's floor (the sum of a nearly opposite pair, 1e-16 long at theta = 90 degrees),
    +z where it is 0 (the half-vector policy of :mod:`torch_brdf.frame`); else unchanged, bit for bit."""
    small = ((h * h).sum(-1) < _floor(h.dtype)).unsqueeze(-1)
    m = h.abs().amax(-1, keepdim=True)
    z = torch.zeros((3,), dtype=h.dtype, device=h.device)
    z[2] = 1.0
    scaled = torch.where(m > 0, h / m.clamp_min(_tiny(h.dtype)), z)
    return torch.where(small, scaled, h)


def ggx_d(h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    r"""Isotropic GGX / Trowbridge-Reitz distribution (Walter et al. 2007):
    :math:`D(h) = \alpha^2 / \big(\pi(\alpha^2\cos^2\theta_h + \sin^2\theta_h)^2\big)`.

    Args:
        h: (*B, 3) half vectors with :math:`h_z > 0`, any positive length.
        alpha: () or (*B,) roughness.
    Returns:
        (*B,).
    """
    h = _unit_scale(h)
    hz2 = h[..., 2] ** 2
    hxy2 = h[..., 0] ** 2 + h[..., 1] ** 2
    len2 = (hz2 + hxy2).clamp_min(_floor(h.dtype))
    a2 = alpha * alpha
    den = (a2 * hz2 + hxy2) / len2
    return a2 / (math.pi * (den * den).clamp_min(_tiny(h.dtype)))


def ggx_log_d(s: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    r""":math:`\log D` of :func:`ggx_d` in a form whose gradient stays finite where
    :math:`D` is huge (float32, :math:`\alpha = 10^{-5}`, grazing mirror pairs), for models that
    multiply :math:`D` by a large visibility (the height-correlated :math:`V` grows like
    :math:`1/(\alpha\cos\theta)` at grazing angles):

    .. math:: \log D = 2\log(1 + \tan^2\theta_h) - 2\log(1 + \tan^2\theta_h/\alpha^2) - \log(\pi\alpha^2),

    with :math:`\tan^2\theta_h/\alpha^2 = (s_x/(\alpha s_z))^2 + (s_y/(\alpha s_z))^2`: squaring
    last keeps :math:`0 \cdot \infty` out of the gradient where :math:`s_x = 0` (as in Ward).

    Args:
        s: (*B, 3) half vectors with :math:`s_z > 0`, any positive length (the unnormalised sum).
        alpha: () or (*B,) roughness.
    Returns:
        (*B,).
    """
    sz = s[..., 2].clamp_min(_floor(s.dtype))
    tan2 = (s[..., 0] / sz) ** 2 + (s[..., 1] / sz) ** 2
    t = (s[..., 0] / (alpha * sz)) ** 2 + (s[..., 1] / (alpha * sz)) ** 2
    return 2.0 * torch.log1p(tan2) - 2.0 * torch.log1p(t) - torch.log(math.pi * alpha * alpha)


def ggx_g1_over_cos(w: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    r"""Exact Smith masking of GGX divided by :math:`\cos\theta` (Heitz 2014, "Understanding
    the Masking-Shadowing Function in Microfacet-Based BRDFs", JCGT 3(2)):
    :math:`G_1/\cos\theta = 2 / (\cos\theta + \sqrt{\cos^2\theta + \alpha^2\sin^2\theta})`,
    finite at grazing angles. Args: w (*B, 3) with :math:`w_z \ge 0`; alpha () or (*B,).
    Returns: (*B,)."""
    c = w[..., 2].clamp_min(0.0)
    s2 = w[..., 0] ** 2 + w[..., 1] ** 2
    root = (c * c + alpha * alpha * s2).clamp_min(_floor(w.dtype)).sqrt()
    return 2.0 / (c + root)


def beckmann_g1_over_cos(w: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    r"""Exact Smith masking of Beckmann divided by :math:`\cos\theta` (Heitz 2014):
    with :math:`a = \cot\theta/\alpha` and :math:`\Lambda(a) = (\mathrm{erf}(a) - 1)/2 +
    e^{-a^2}/(2a\sqrt\pi)`, :math:`G_1 = 1/(1+\Lambda)`, so

    .. math:: G_1/\cos\theta = 1 \Big/ \Big(\cos\theta\,\frac{1 + \mathrm{erf}(a)}{2}
              + \frac{\alpha\sin\theta\,e^{-a^2}}{2\sqrt\pi}\Big),

    which is finite at grazing angles. Args: w (*B, 3) with :math:`w_z \ge 0`; alpha ()
    or (*B,). Returns: (*B,)."""
    c = w[..., 2].clamp_min(0.0)
    # sin >= 1e-10 changes nothing (a is clamped at 30 long before) and keeps (alpha sin)^2,
    # which the gradient of c / (alpha sin) needs, a normal float32 number.
    sin = (w[..., 0] ** 2 + w[..., 1] ** 2).clamp_min(1e-20).sqrt()
    a = (c / (alpha * sin)).clamp_max(30.0)  # erf(30) = 1 and exp(-900) = 0 in float64
    den = c * 0.5 * (1.0 + torch.erf(a)) + alpha * sin * torch.exp(-a * a) / (2.0 * math.sqrt(math.pi))
    return 1.0 / den.clamp_min(_tiny(w.dtype))


# -- sampling --------------------------------------------------------------------------------
def reflect(wo: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    r"""Mirror :math:`\omega_o` about unit ``h``: :math:`2(\omega_o\cdot h)h - \omega_o`,
    renormalised. Args: wo, h (*B, 3). Returns: (*B, 3)."""
    wi = 2.0 * (wo * h).sum(-1, keepdim=True) * h - wo
    return wi / torch.linalg.vector_norm(wi, dim=-1, keepdim=True).clamp_min(_floor(wi.dtype))


def _polar(sin2: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Unit vector from sin^2(theta) (upper hemisphere) and phi: (*B,) -> (*B, 3)."""
    sin2 = sin2.clamp(0.0, 1.0)
    st = sin2.sqrt()
    return torch.stack((st * torch.cos(phi), st * torch.sin(phi), (1.0 - sin2).sqrt()), -1)


def _open_unit(u: torch.Tensor) -> torch.Tensor:
    """Map uniforms in [0, 1) to (0, 1] so their logarithm is finite."""
    return (1.0 - u).clamp(_tiny(u.dtype), 1.0)


def sample_blinn_h(u: torch.Tensor, exponent: torch.Tensor) -> torch.Tensor:
    r"""Half vectors with density :math:`D_n(h)\cos\theta_h = \frac{n+2}{2\pi}\cos^{n+1}\theta_h`:
    the cosine-power warp with exponent :math:`n + 1`
    (:func:`~torch_brdf.sphere.warps.square_to_cosine_power_hemisphere`).
    Args: u (*B, 2); exponent () or (*B,). Returns: (*B, 3)."""
    return square_to_cosine_power_hemisphere(u, exponent + 1.0)


def sample_beckmann_h(u: torch.Tensor, alpha_x: torch.Tensor, alpha_y: torch.Tensor | None = None) -> torch.Tensor:
    r"""Half vectors with density :math:`D(h)\cos\theta_h` of :func:`beckmann_d` (Walter 2005,
    "Notes on the Ward BRDF", Tech. Rep. PCG-05-06): :math:`\phi_h = \mathrm{atan2}(\alpha_y\sin 2\pi\xi_2,
    \alpha_x\cos 2\pi\xi_2)`, :math:`\tan^2\theta_h = -\log\xi_1 / (\cos^2\phi_h/\alpha_x^2 +
    \sin^2\phi_h/\alpha_y^2)`. Args: u (*B, 2); alphas () or (*B,). Returns: (*B, 3)."""
    ay = alpha_x if alpha_y is None else alpha_y
    psi = 2.0 * math.pi * u[..., 1]
    phi = torch.atan2(ay * torch.sin(psi), alpha_x * torch.cos(psi))
    inv = torch.cos(phi) ** 2 / alpha_x**2 + torch.sin(phi) ** 2 / ay**2
    t2 = -torch.log(_open_unit(u[..., 0])) / inv
    return _polar(t2 / (1.0 + t2), phi)


def sample_ggx_vndf(wo: torch.Tensor, u: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    r"""Visible GGX normals for ``wo`` (Heitz 2018, "Sampling the GGX Distribution of Visible
    Normals", JCGT 7(4), Listing 1): density :math:`G_1(\omega_o)\max(0,\omega_o\cdot h)D(h)/\cos\theta_o`.

    Args:
        wo: (*B, 3) local, :math:`\cos\theta_o > 0`.
        u: (*B, 2) uniforms.
        alpha: () or (*B,) roughness.
    Returns:
        (*B, 3) unit half vectors.
    """
    a = alpha
    v = torch.stack((a * wo[..., 0], a * wo[..., 1], wo[..., 2].clamp_min(0.0)), -1)
    v = v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(_floor(v.dtype))
    lensq = v[..., 0] ** 2 + v[..., 1] ** 2
    inv = torch.rsqrt(lensq.clamp_min(_floor(v.dtype)))
    t1 = torch.stack((-v[..., 1] * inv, v[..., 0] * inv, torch.zeros_like(lensq)), -1)
    t1 = torch.where((lensq > _floor(v.dtype)).unsqueeze(-1), t1, torch.tensor([1.0, 0.0, 0.0], dtype=v.dtype))
    t2 = torch.linalg.cross(v, t1, dim=-1)
    r = u[..., 0].clamp_min(0.0).sqrt()
    phi = 2.0 * math.pi * u[..., 1]
    p1, p2 = r * torch.cos(phi), r * torch.sin(phi)
    sv = 0.5 * (1.0 + v[..., 2])
    p2 = (1.0 - sv) * (1.0 - p1 * p1).clamp_min(0.0).sqrt() + sv * p2
    p3 = (1.0 - p1 * p1 - p2 * p2).clamp_min(0.0).sqrt()
    nh = p1.unsqueeze(-1) * t1 + p2.unsqueeze(-1) * t2 + p3.unsqueeze(-1) * v
    ne = torch.stack((a * nh[..., 0], a * nh[..., 1], nh[..., 2].clamp_min(0.0)), -1)
    return ne / torch.linalg.vector_norm(ne, dim=-1, keepdim=True).clamp_min(_floor(ne.dtype))


def sample_around(axis: torch.Tensor, u: torch.Tensor, exponent: torch.Tensor) -> torch.Tensor:
    r"""Directions with density :math:`\frac{n+1}{2\pi}\cos^n\gamma` about unit ``axis``
    (:math:`\gamma` the angle to it; the hemisphere around ``axis``), as for the Phong lobe
    (Lafortune & Willems 1994). Args: axis (*B, 3); u (*B, 2); exponent () or (*B,).
    Returns: (*B, 3)."""
    return Frame(*orthonormal_basis(axis), axis).to_world(square_to_cosine_power_hemisphere(u, exponent))


# -- lobe mixtures -----------------------------------------------------------------------------
def lobe_weight(spec: torch.Tensor, diffuse: torch.Tensor, floor: float = 0.05) -> torch.Tensor:
    r"""Probability of sampling the specular lobe in a diffuse + specular mixture,
    :math:`s/(s+d)` from albedo estimates, kept in :math:`[\epsilon, 1-\epsilon]` while both
    lobes are present (so neither lobe ever goes unsampled) and exactly 0 or 1 when one is
    absent. Args: spec, diffuse (*B,) non-negative estimates. Returns: (*B,)."""
    total = spec + diffuse
    p = torch.where(total > 0, spec / total.clamp_min(_tiny(total.dtype)), torch.full_like(total, 0.5))
    p = torch.where(spec > 0, p.clamp_min(floor), p)
    return torch.where(diffuse > 0, p.clamp_max(1.0 - floor), p)


def mixture_sample(
    wo: torch.Tensor,
    u: torch.Tensor,
    p_spec: torch.Tensor,
    sample_spec: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
) -> torch.Tensor:
    r"""Draw :math:`\omega_i` from :math:`(1-p)\,\cos\theta_i/\pi + p\,\mathrm{pdf}_s`: the first
    uniform picks the lobe and is rescaled to [0, 1) for it (one sample per query).

    Args:
        wo: (*B, 3) local directions.
        u: (*B, 2) uniforms.
        p_spec: (*B,) probability of the specular lobe.
        sample_spec: ``(wo, u) -> wi`` (*B, 3) for the specular lobe.
    Returns:
        (*B, 3) unit directions (possibly below the horizon: then their pdf is 0).
    """
    p = p_spec.detach()
    pick = u[..., 0] < p
    one = 1.0 - torch.finfo(u.dtype).eps
    us0 = torch.where(pick, u[..., 0] / p.clamp_min(_tiny(u.dtype)), u[..., 0]).clamp(0.0, one)
    ud0 = torch.where(pick, u[..., 0], (u[..., 0] - p) / (1.0 - p).clamp_min(_tiny(u.dtype))).clamp(0.0, one)
    wi_s = sample_spec(wo, torch.stack((us0, u[..., 1]), -1))
    ud = torch.stack((ud0, u[..., 1]), -1)
    wi_d = square_to_cosine_hemisphere(ud.reshape(-1, 2)).reshape(ud.shape[:-1] + (3,))
    return torch.where(pick.unsqueeze(-1), wi_s, wi_d)


def mixture_pdf(wi: torch.Tensor, wo: torch.Tensor, p_spec: torch.Tensor, pdf_spec: torch.Tensor) -> torch.Tensor:
    r"""Density of :func:`mixture_sample`: :math:`(1-p)\cos\theta_i/\pi + p\,\mathrm{pdf}_s`
    where both directions are above the horizon, else 0. Args: wi, wo (*B, 3); p_spec,
    pdf_spec (*B,). Returns: (*B,)."""
    up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    val = (1.0 - p_spec) * wi[..., 2].clamp_min(0.0) / math.pi + p_spec * pdf_spec
    return torch.where(up, val, torch.zeros((), dtype=wi.dtype))


def half_vector_pdf(pdf_h: torch.Tensor, cos_d: torch.Tensor) -> torch.Tensor:
    r"""Solid-angle density of :math:`\omega_i = \mathrm{reflect}(\omega_o, h)` from a
    half-vector density: :math:`\mathrm{pdf}_h / (4\,\omega_o\cdot h)` (Walter et al. 2007)."""
    return pdf_h / (4.0 * cos_d.clamp_min(_floor(cos_d.dtype)))


# -- the microfacet distribution protocol -----------------------------------------------------
def _tan2(h: torch.Tensor) -> torch.Tensor:
    """tan^2(theta) of vectors (*B, 3) of any positive length (floored denominator): (*B,)."""
    return (h[..., 0] ** 2 + h[..., 1] ** 2) / (h[..., 2] ** 2).clamp_min(_floor(h.dtype))


class MicrofacetDistribution:
    r"""The one interface of a distribution of microfacet normals, after pbrt-v4's
    ``TrowbridgeReitzDistribution``: :meth:`D`, :meth:`G1_over_cos`, :meth:`sample`,
    :meth:`pdf`. Every microfacet model takes one (:class:`CookTorrance`: :class:`GGXNDF` or :class:`BeckmannNDF`,
    :class:`~torch_brdf.brdf.analytic.BlinnPhong`: :class:`BlinnNDF`,
    :class:`~torch_brdf.brdf.analytic.Ward`: :class:`BeckmannNDF`,
    :class:`~torch_brdf.brdf.analytic.AshikhminShirley` its anisotropic Phong lobe, and
    :class:`~torch_brdf.brdf.analytic.DistributionBased`'s Blinn distribution and fallback
    sampler).

    Distributions are small frozen value objects built per evaluation from a model's
    constrained parameters (tensors, so gradients flow to the model's raw Parameters and
    ``state_dict`` is the model's). :math:`D` is normalised over projected microfacet area,
    :math:`\int D(h)(h\cdot n)\,d\omega_h = 1`; reflecting :math:`\omega_o` about a sampled
    :math:`h` gives :math:`\omega_i` with density ``pdf(wo, h) / (4 wo.h)``
    (:meth:`sample_reflection`, :meth:`reflection_pdf`).
    """

    #: True if D depends on the azimuth of h (needs a tangent frame).
    anisotropic: bool = False

    def D(self, h: torch.Tensor) -> torch.Tensor:
        """Normal distribution at half vectors h (*B, 3) with h_z > 0, any positive length: (*B,)."""
        raise NotImplementedError

    def G1_over_cos(self, w: torch.Tensor) -> torch.Tensor:
        r"""Smith masking :math:`G_1(\omega)/\cos\theta` (finite at grazing angles) of local
        directions (*B, 3) with :math:`w_z \ge 0`: (*B,)."""
        raise NotImplementedError

    def sample(self, wo: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Unit half vectors (*B, 3) for local ``wo`` (*B, 3) and uniforms ``u`` (*B, 2)."""
        raise NotImplementedError

    def pdf(self, wo: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """Solid-angle density (*B,) with which :meth:`sample` draws the unit half vector ``h``
        (*B, 3) given ``wo`` (*B, 3). Default: :math:`D(h)\\cos\theta_h` (all normals)."""
        return self.D(h) * h[..., 2].clamp_min(0.0)

    def sample_reflection(self, wo: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """``wi`` (*B, 3): ``wo`` reflected about a sampled half vector."""
        return reflect(wo, self.sample(wo, u))

    def reflection_pdf(self, wo: torch.Tensor, ht: HalfTerms) -> torch.Tensor:
        r"""Solid-angle density (*B,) of :meth:`sample_reflection` at the pair whose
        :func:`~torch_brdf.frame.half_terms` are ``ht``: :math:`\mathrm{pdf}_h/(4\,\omega_o\cdot h)`."""
        return half_vector_pdf(self.pdf(wo, ht.h), ht.cos_d)


@dataclass(frozen=True)
class BlinnNDF(MicrofacetDistribution):
    r"""Normalised Blinn distribution :math:`D_n = \frac{n+2}{2\pi}\cos^n\theta_h`
    (:func:`blinn_d`), sampled as :math:`D_n\cos\theta_h` (:func:`sample_blinn_h`). It has no
    exact Smith masking; :meth:`G1_over_cos` is the implicit :math:`G_1 = \cos\theta`
    (i.e. 1), under which :math:`DG/(4\cos\theta_i\cos\theta_o) = D/4` is Blinn-Phong's lobe.

    Attributes:
        exponent: () or (*B,) :math:`n > 0`.
    """

    exponent: torch.Tensor

    def D(self, h):
        return blinn_d(_tan2(h), self.exponent)

    def G1_over_cos(self, w):
        return torch.ones_like(w[..., 2])

    def sample(self, wo, u):
        return sample_blinn_h(u, self.exponent)


@dataclass(frozen=True)
class BeckmannNDF(MicrofacetDistribution):
    r"""(Anisotropic) Beckmann distribution (:func:`beckmann_d`), sampled as
    :math:`D(h)\cos\theta_h` (:func:`sample_beckmann_h`); exact Smith :math:`G_1`
    (:func:`beckmann_g1_over_cos`) with the roughness projected on the direction's azimuth,
    :math:`\alpha^2(\phi) = \alpha_x^2\cos^2\phi + \alpha_y^2\sin^2\phi` (Heitz 2014).

    Attributes:
        alpha_x: () or (*B,) roughness along the tangent.
        alpha_y: None (isotropic) or roughness along the bitangent.
    """

    alpha_x: torch.Tensor
    alpha_y: torch.Tensor | None = None

    @property
    def anisotropic(self) -> bool:
        return self.alpha_y is not None

    def D(self, h):
        return beckmann_d(h, self.alpha_x, self.alpha_y)

    def G1_over_cos(self, w):
        if self.alpha_y is None:
            return beckmann_g1_over_cos(w, self.alpha_x)
        x2, y2 = w[..., 0] ** 2, w[..., 1] ** 2
        r2 = x2 + y2
        a2 = (x2 * self.alpha_x**2 + y2 * self.alpha_y**2) / r2.clamp_min(_tiny(w.dtype))
        a2 = torch.where(r2 > 0, a2, self.alpha_x**2 * torch.ones_like(r2))
        return beckmann_g1_over_cos(w, a2.sqrt())

    def sample(self, wo, u):
        return sample_beckmann_h(u, self.alpha_x, self.alpha_y)


@dataclass(frozen=True)
class GGXNDF(MicrofacetDistribution):
    r"""Isotropic GGX / Trowbridge-Reitz (:func:`ggx_d`, exact :func:`ggx_g1_over_cos`),
    sampled by its visible normals (:func:`sample_ggx_vndf`, Heitz 2018):
    :math:`\mathrm{pdf}_h = G_1(\omega_o)\max(0, \omega_o\cdot h)D(h)/\cos\theta_o`.

    Attributes:
        alpha: () or (*B,) roughness.
    """

    alpha: torch.Tensor

    def D(self, h):
        return ggx_d(h, self.alpha)

    def G1_over_cos(self, w):
        return ggx_g1_over_cos(w, self.alpha)

    def sample(self, wo, u):
        return sample_ggx_vndf(wo, u, self.alpha)

    def pdf(self, wo, h):
        return self.G1_over_cos(wo) * (wo * h).sum(-1).clamp_min(0.0) * self.D(h)


def _log1p_over(t: torch.Tensor) -> torch.Tensor:
    """log(1 + t)/t, continuous at t = 0 (t >= 0)."""
    small = t < 1e-4
    ts = torch.where(small, torch.ones_like(t), t)
    return torch.where(small, 1.0 - 0.5 * t + t * t / 3.0, torch.log1p(ts) / ts)


@dataclass(frozen=True)
class AnisotropicPhongNDF(MicrofacetDistribution):
    r"""The anisotropic Phong lobe of Ashikhmin & Shirley 2000: their half-vector density
    :math:`p_h = \frac{\sqrt{(n_u+1)(n_v+1)}}{2\pi}(n\cdot h)^{e(h)}`,
    :math:`e(h) = (n_u h_x^2 + n_v h_y^2)/(1 - h_z^2)`, is :math:`D(h)\cos\theta_h`
    (so :math:`D = p_h/\cos\theta_h` has unit projected area) and is what :meth:`sample`
    draws (their importance-sampling section; :math:`\phi_h = \mathrm{atan2}(\sqrt{n_u+1}
    \sin\psi, \sqrt{n_v+1}\cos\psi)`, :math:`\cos\theta_h = (1-\xi)^{1/(e+1)}`). The
    exponent is evaluated as :math:`-\frac12 (n_u h_x^2 + n_v h_y^2)/h_z^2\cdot\log(1+t)/t`,
    :math:`t = \tan^2\theta_h` (no 0/0 at :math:`h = n`). Not a Smith model: no :math:`G_1`.

    Attributes:
        nu, nv: () or (*B,) exponents along the tangent and bitangent.
    """

    nu: torch.Tensor
    nv: torch.Tensor
    anisotropic = True

    def log_lobe(self, h: torch.Tensor) -> torch.Tensor:
        r""":math:`\log (n\cdot h)^{e(h)}` for half vectors (*B, 3) of any positive length: (*B,)."""
        hz2 = (h[..., 2] ** 2).clamp_min(_floor(h.dtype))
        return -0.5 * (self.nu * h[..., 0] ** 2 + self.nv * h[..., 1] ** 2) / hz2 * _log1p_over(_tan2(h))

    def pdf(self, wo, h):
        return torch.sqrt((self.nu + 1.0) * (self.nv + 1.0)) / (2.0 * math.pi) * torch.exp(self.log_lobe(h))

    def D(self, h):
        cos_h = h[..., 2] / torch.linalg.vector_norm(h, dim=-1).clamp_min(_floor(h.dtype))
        return self.pdf(None, h) / cos_h.clamp_min(_floor(h.dtype))

    def G1_over_cos(self, w):
        raise NotImplementedError("the Ashikhmin-Shirley lobe is not a Smith microfacet model")

    def sample(self, wo, u):
        psi = 2.0 * math.pi * u[..., 0]
        phi = torch.atan2(torch.sqrt(self.nu + 1.0) * torch.sin(psi), torch.sqrt(self.nv + 1.0) * torch.cos(psi))
        e = self.nu * torch.cos(phi) ** 2 + self.nv * torch.sin(phi) ** 2
        lg = torch.log(_open_unit(u[..., 1]))
        return _polar(-torch.expm1(2.0 * lg / (e + 1.0)), phi)


class MicrofacetMixture(BRDF):
    """Sampling shared by the microfacet models: with the probability ``_p_spec(wo)`` (*B,)
    reflect ``wo`` about a half vector of :meth:`microfacet_distribution`, else the cosine
    lobe (:func:`mixture_sample`); ``pdf_local`` is the mixture's exact density."""

    def microfacet_distribution(self, dtype: torch.dtype) -> MicrofacetDistribution:
        """The model's distribution of microfacet normals, built from its current parameters."""
        raise NotImplementedError

    def _p_spec(self, wo: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def sample_local(self, wo, u):
        dist = self.microfacet_distribution(wo.dtype)
        wi = mixture_sample(wo, u, self._p_spec(wo), dist.sample_reflection)
        return wi, self.pdf_local(wi, wo)

    def pdf_local(self, wi, wo):
        si, so, _ = safe_pair(wi, wo)
        pdf_s = self.microfacet_distribution(wi.dtype).reflection_pdf(so, half_terms(si, so))
        return mixture_pdf(wi, wo, self._p_spec(so), pdf_s)


# -- Cook-Torrance ---------------------------------------------------------------------------
_DISTRIBUTIONS = ("beckmann", "ggx")


@register("cook_torrance")
class CookTorrance(MicrofacetMixture):
    r"""Cook-Torrance microfacet BRDF with an optional Lambertian base,

    .. math:: f = \frac{k_d}{\pi} + \frac{F(\omega_i\cdot h)\,D(h)\,G_1(\omega_i)G_1(\omega_o)}
              {4\cos\theta_i\cos\theta_o}

    (Cook & Torrance 1982, in the form of Walter et al. 2007): :math:`D` Beckmann or GGX
    (:func:`beckmann_d`, :func:`ggx_d`), the separable Smith masking-shadowing with the
    exact :math:`G_1` of each distribution (Heitz 2014), Schlick's Fresnel with RGB
    :math:`F_0`. The specular part conserves energy for every :math:`F_0, \alpha` (its
    albedo is at most :math:`\max F \le 1`; with :math:`F_0 = 1` the loss is the missing
    multiple scattering, small for small :math:`\alpha`), but :math:`k_d` is simply added
    (no Fresnel coupling), so the documented bound is :math:`k_d + 1`
    (:meth:`albedo_bound`).

    Sampling: with probability from :func:`lobe_weight` the specular lobe, else the cosine
    lobe. The distribution (:meth:`microfacet_distribution`, a :class:`GGXNDF` or
    :class:`BeckmannNDF`) samples the half vector: GGX its visible normals (Heitz 2018):
    :math:`\mathrm{pdf} = G_1(\omega_o)D(h)/(4\cos\theta_o)`; Beckmann
    :math:`D(h)\cos\theta_h`: :math:`\mathrm{pdf} = D(h)\cos\theta_h/(4\,\omega_o\cdot h)`.

    Args:
        distribution: ``"beckmann"`` or ``"ggx"``.
        roughness: :math:`\alpha` in :math:`[10^{-4}, 1]` (Positive; clamped at :math:`10^{-5}` in the math).
        f0: RGB Fresnel reflectance at normal incidence in [0, 1].
        kd: RGB Lambertian albedo in [0, 1] (default 0: no diffuse base).
    """

    ROUGHNESS_RANGE = (1e-4, 1.0)  # documented; the math clamps only below at ALPHA_MIN

    def __init__(self, distribution: str = "ggx", roughness=0.2, f0=0.04, kd=0.0):
        super().__init__()
        if distribution not in _DISTRIBUTIONS:
            raise ValueRangeError(f"CookTorrance.distribution must be one of {_DISTRIBUTIONS}; got {distribution!r}")
        check_range("CookTorrance", "roughness", roughness, *self.ROUGHNESS_RANGE)
        self.distribution = distribution
        self.register_constrained("roughness", roughness, Positive())
        self.register_constrained("f0", f0, Clamped(0.0, 1.0), shape=(3,))
        self.register_constrained("kd", kd, Clamped(0.0, 1.0), shape=(3,))

    def microfacet_distribution(self, dtype: torch.dtype) -> GGXNDF | BeckmannNDF:
        """The :class:`MicrofacetDistribution` of the current roughness (clamped at ``ALPHA_MIN``)."""
        a = self.roughness.to(dtype).clamp_min(ALPHA_MIN)
        return GGXNDF(a) if self.distribution == "ggx" else BeckmannNDF(a)

    def eval_local(self, wi, wo):
        dt = wi.dtype
        dist = self.microfacet_distribution(dt)
        wi, wo, up = safe_pair(wi, wo)
        ht = half_terms(wi, wo)
        fr = schlick_fresnel(self.f0.to(dt), ht.one_minus_cos_d)
        spec = (0.25 * dist.D(ht.s) * dist.G1_over_cos(wi) * dist.G1_over_cos(wo)).unsqueeze(-1) * fr
        f = self.kd.to(dt) / math.pi + spec
        return torch.where(up.unsqueeze(-1), f, torch.zeros((), dtype=dt))

    def _p_spec(self, wo):
        dt = wo.dtype
        one_minus = (1.0 - wo[..., 2].clamp(0.0, 1.0)).unsqueeze(-1)
        f0 = self.f0.to(dt)
        spec = (f0 + (1.0 - f0) * one_minus**5).mean(-1)
        return lobe_weight(spec, self.kd.to(dt).mean().expand_as(spec))

    def albedo_bound(self, wo: torch.Tensor) -> torch.Tensor:
        """Documented upper bound of the directional albedo: kd + 1, shape (*B, 3)."""
        return (self.kd.to(wo.dtype) + 1.0).expand(wo.shape[:-1] + (3,))
