r"""The glTF 2.0 metallic-roughness BRDF: the reference model of the glTF 2.0 specification
(Khronos, "glTF 2.0 Specification", Appendix B "BRDF Implementation"), the parametrisation
of glTF files, Blender's Principled BSDF base layer and most game engines.

.. math::
    f = (1 - m)\Big[\frac{c}{\pi}(1 - F_{0.04}) + F_{0.04}\,S\Big] + m\,F_c\,S
      = (1 - m)(1 - F_{0.04})\frac{c}{\pi} + F_{f_0}\,S,

    F_{x} = x + (1 - x)(1 - |\omega_o\cdot h|)^5, \qquad f_0 = (1 - m)\,0.04 + m\,c,
    \qquad S = D(h)\,V(\omega_i, \omega_o),

the specification's ``mix(dielectric_brdf, metal_brdf, metallic)`` of a dielectric
(``fresnel_mix`` with IOR 1.5, :math:`F_{0.04}`, of the Lambert base and the GGX layer) and
a metal (``conductor_fresnel``, :math:`F_c`), with base colour :math:`c`, metallic :math:`m`,
and the GGX distribution :math:`D` of :math:`\alpha = r^2` (the specification squares the
perceptual roughness :math:`r` stored in the file: "alphaRoughness = roughness *
roughness"). The two specular Fresnel terms sum to one Schlick term of :math:`f_0`; the
diffuse keeps the dielectric's :math:`1 - F_{0.04}`. (The specification's sample code writes
the diffuse weight as :math:`1 - F_{f_0}`, which differs from its own ``mix`` only for
:math:`0 < m < 1`; we follow the ``mix``, which is linear in :math:`m`.)
:math:`V = G_2/(4\cos\theta_i\cos\theta_o)` is the height-correlated Smith visibility of
GGX (Heitz 2014, Eq. 99),

.. math:: V = \frac{1/2}{\cos\theta_o\sqrt{\cos^2\theta_i + \alpha^2\sin^2\theta_i}
              + \cos\theta_i\sqrt{\cos^2\theta_o + \alpha^2\sin^2\theta_o}},

the specification's formula with :math:`\cos^2(1-\alpha^2)+\alpha^2` written as
:math:`\cos^2 + \alpha^2\sin^2` (no cancellation at grazing angles). It is reciprocal
(:math:`|\omega_o\cdot h| = |\omega_i\cdot h|`).

Energy: the specification's model does not conserve energy exactly. Its diffuse weight
:math:`1 - F_{0.04}` uses the Fresnel term at :math:`\omega\cdot h`, not the layer's directional albedo,
so a white dielectric (:math:`c = 1, m = 0`) with a near-mirror coat reflects up to 2.5%
more than it receives near :math:`\theta_o = 60°`; the single-scattering GGX loses energy at
high roughness (no multiple-scattering compensation, as in the specification). The
documented bound, :meth:`MetallicRoughness.albedo_bound`, is
:math:`0.96\,c_{diff} + 1` (:math:`1 - F_{0.04} \le 0.96`, and the GGX layer's albedo
with :math:`F \le 1` is at most 1).
"""

from __future__ import annotations

import math

import torch

from ..frame import half_terms
from .base import Clamped, register
from .microfacet import (
    ALPHA_MIN,
    GGXNDF,
    GRAZING_COS,
    MicrofacetMixture,
    _floor,
    ggx_log_d,
    lobe_weight,
    safe_pair,
    schlick_fresnel,
)

__all__ = ["DIELECTRIC_F0", "MetallicRoughness", "ggx_correlated_visibility"]

#: Normal-incidence reflectance of the dielectric layer (IOR 1.5): ((1.5 - 1)/(1.5 + 1))^2.
DIELECTRIC_F0 = 0.04


def ggx_correlated_visibility(wi: torch.Tensor, wo: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    r"""Height-correlated Smith visibility of GGX, :math:`V = G_2/(4\cos\theta_i\cos\theta_o)`
    (Heitz 2014, "Understanding the Masking-Shadowing Function", Eq. 99; the glTF 2.0
    specification's ``V_GGX``), finite at grazing angles (floored denominator).

    Args:
        wi: (*B, 3) local incident directions with :math:`z \ge 0`.
        wo: (*B, 3) local outgoing directions with :math:`z \ge 0`.
        alpha: () or (*B,) GGX roughness :math:`\alpha`.
    Returns:
        (*B,).
    """
    a2 = alpha * alpha
    ci, co = wi[..., 2].clamp_min(0.0), wo[..., 2].clamp_min(0.0)
    si2 = wi[..., 0] ** 2 + wi[..., 1] ** 2
    so2 = wo[..., 0] ** 2 + wo[..., 1] ** 2
    fl = _floor(wi.dtype)
    root_i = (ci * ci + a2 * si2).clamp_min(fl).sqrt()
    root_o = (co * co + a2 * so2).clamp_min(fl).sqrt()
    # the denominator shrinks like cos at grazing mirror pairs (V grows like 1/cos): its floor is
    # one value in every dtype (GRAZING_COS), so float32 and float64 agree at theta = 90 degrees
    return 0.5 / (co * root_i + ci * root_o).clamp_min(GRAZING_COS**2)


@register("metallic_roughness")
class MetallicRoughness(MicrofacetMixture):
    r"""The glTF 2.0 metallic-roughness BRDF (see the module docstring for the formula).

    Sampling: GGX visible normals (Heitz 2018) mixed with the cosine lobe, weighted by the
    Fresnel reflectance at :math:`\theta_o` against the diffuse colour
    (:func:`~torch_brdf.brdf.microfacet.lobe_weight`).

    Args:
        base_color: RGB base colour :math:`c` in [0, 1] (linear, not sRGB).
        metallic: :math:`m` in [0, 1].
        roughness: perceptual roughness :math:`r` in [0, 1]; the GGX :math:`\alpha = r^2`
            (clamped at ``ALPHA_MIN`` = 1e-5 inside the math, so :math:`r = 0` is a
            near-mirror, finite in float32).
    """

    def __init__(self, base_color=0.8, metallic=0.0, roughness=0.5):
        super().__init__()
        self.register_constrained("base_color", base_color, Clamped(0.0, 1.0), shape=(3,))
        self.register_constrained("metallic", metallic, Clamped(0.0, 1.0))
        self.register_constrained("roughness", roughness, Clamped(0.0, 1.0))

    def alpha(self, dtype: torch.dtype) -> torch.Tensor:
        r"""The GGX :math:`\alpha = r^2`, clamped at ``ALPHA_MIN``: () tensor of ``dtype``."""
        r = self.roughness.to(dtype)
        return (r * r).clamp_min(ALPHA_MIN)

    def f0_and_diffuse(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        r""":math:`f_0 = (1-m)\,0.04 + m\,c` and :math:`c_{diff} = (1-m)\,c`: two (3,) tensors."""
        c, m = self.base_color.to(dtype), self.metallic.to(dtype)
        return (1.0 - m) * DIELECTRIC_F0 + m * c, (1.0 - m) * c

    def microfacet_distribution(self, dtype: torch.dtype) -> GGXNDF:
        """The :class:`~torch_brdf.brdf.microfacet.GGXNDF` of :math:`\\alpha = r^2` (sampling)."""
        return GGXNDF(self.alpha(dtype))

    def eval_local(self, wi, wo):
        dt = wi.dtype
        a = self.alpha(dt)
        f0, c_diff = self.f0_and_diffuse(dt)
        wi, wo, up = safe_pair(wi, wo)
        ht = half_terms(wi, wo)
        fr = schlick_fresnel(f0, ht.one_minus_cos_d)  # (*B, 3)
        fr_dielectric = schlick_fresnel(torch.full((1,), DIELECTRIC_F0, dtype=dt), ht.one_minus_cos_d)
        # D in log space: its gradient times the large V overflowed float32 at grazing mirror pairs
        spec = (torch.exp(ggx_log_d(ht.s, a)) * ggx_correlated_visibility(wi, wo, a)).unsqueeze(-1)
        f = (1.0 - fr_dielectric) * (c_diff / math.pi) + fr * spec
        return torch.where(up.unsqueeze(-1), f, torch.zeros((), dtype=dt))

    def _p_spec(self, wo):
        dt = wo.dtype
        f0, c_diff = self.f0_and_diffuse(dt)
        one_minus = (1.0 - wo[..., 2].clamp(0.0, 1.0)).unsqueeze(-1)
        fr = f0 + (1.0 - f0) * one_minus**5  # (*B, 3)
        return lobe_weight(fr.mean(-1), (1.0 - DIELECTRIC_F0) * c_diff.mean().expand(wo.shape[:-1]))

    def albedo_bound(self, wo: torch.Tensor) -> torch.Tensor:
        r"""Documented albedo bound :math:`0.96\,c_{diff} + 1`: (*B, 3)."""
        _, c_diff = self.f0_and_diffuse(wo.dtype)
        return ((1.0 - DIELECTRIC_F0) * c_diff + 1.0).expand(wo.shape[:-1] + (3,))
