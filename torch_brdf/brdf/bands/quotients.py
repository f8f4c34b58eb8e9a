r"""Quotients :math:`\rho_q(\omega_i, \omega_o)` of the factored BRDFs (Ben-Artzi et al.
2008, Eq. 30-35): fixed, non-negative, reciprocal factors; see :mod:`torch_brdf.brdf.bands`
for the list and where each comes from.
"""

from __future__ import annotations

import torch

from ...errors import ValueRangeError
from ..microfacet import beckmann_g1_over_cos, ggx_g1_over_cos
from ._geometry import eps, half_and_diff, log_cos_over_sin2

__all__ = ["AnisotropicLobe", "Quotient", "SchlickFresnel", "SmithQuotient", "make_quotient"]


class Quotient:
    r"""A fixed, non-negative, reciprocal factor :math:`\rho_q(\omega_i, \omega_o)` (Eq. 30).

    Subclasses implement :meth:`value` for local directions above the horizon (cosines are
    clamped to ``eps`` so the result is finite everywhere); ``__call__`` returns it as is
    (the factored BRDF zeroes pairs below the horizon). ``channels`` is 1 (returns ``(*B,)``)
    or 3 (``(*B, 3)``); ``key`` identifies the quotient in the equivalent-albedo cache keys
    (``name``, else the class's qualified name): a subclass with parameters must include
    them in ``key``.
    """

    name = "quotient"
    anisotropic = False
    channels = 1

    @property
    def key(self) -> str:
        if self.name != "quotient":
            return self.name
        return f"{type(self).__module__}.{type(self).__qualname__}"

    def value(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def __call__(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """Quotient value: wi, wo (*B, 3) local -> (*B,) or (*B, 3)."""
        return self.value(wi, wo)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.key})"


class _One(Quotient):
    name = "one"

    def value(self, wi, wo):
        return torch.ones_like(wi[..., 2])


class _Distribution(Quotient):
    name = "distribution"

    def value(self, wi, wo):
        ci, co = wi[..., 2].clamp_min(eps(wi)), wo[..., 2].clamp_min(eps(wo))
        return 1.0 / (ci + co - ci * co)


class _Microfacet(Quotient):
    name = "microfacet"

    def value(self, wi, wo):
        ci, co = wi[..., 2].clamp_min(eps(wi)), wo[..., 2].clamp_min(eps(wo))
        return 0.25 / (ci * co)


class _CookTorrance(Quotient):
    name = "cook_torrance"

    def value(self, wi, wo):
        e = eps(wi)
        ci, co = wi[..., 2].clamp_min(e), wo[..., 2].clamp_min(e)
        h, cd, _ = half_and_diff(wi, wo)
        ch, cd = h[..., 2].clamp_min(0.0), cd.clamp_min(e)
        g = torch.minimum(torch.ones_like(ci), 2 * ch * torch.minimum(ci, co) / cd)
        return 0.25 * g / (ci * co)


class _AshikhminShirley(Quotient):
    name = "ashikhmin_shirley"

    def value(self, wi, wo):
        e = eps(wi)
        _, cd, _ = half_and_diff(wi, wo)
        return 1.0 / (cd.clamp_min(e) * torch.maximum(wi[..., 2], wo[..., 2]).clamp_min(e))


_QUOTIENTS: dict[str, type[Quotient]] = {
    q.name: q for q in (_One, _Distribution, _Microfacet, _CookTorrance, _AshikhminShirley)
}


def make_quotient(spec: str | Quotient) -> Quotient:
    """A :class:`Quotient` from its name (``"one"``, ``"distribution"``, ``"microfacet"``,
    ``"cook_torrance"``, ``"ashikhmin_shirley"``) or an instance (returned as is)."""
    if isinstance(spec, Quotient):
        return spec
    if spec not in _QUOTIENTS:
        raise ValueRangeError(f"unknown quotient {spec!r}; expected one of {sorted(_QUOTIENTS)} or a Quotient")
    return _QUOTIENTS[spec]()


class SchlickFresnel(Quotient):
    r"""Fresnel two-layer quotients (Eq. 31-32) on top of a base quotient.

    With ``f0=None``: :math:`\rho_{q2} = (1 - \cos\theta_d)^5\rho_q`, the quotient of the
    second layer whose editable factor is :math:`f_2 = (1 - F)f`. With an RGB ``f0``:
    the whole Schlick factor :math:`\rho_q(F_0 + (1 - F_0)(1 - \cos\theta_d)^5)`, ``(*B, 3)``,
    used to project a BRDF with a known :math:`F_0` onto :math:`f(\theta_h)`.

    Args:
        base: base quotient (name or :class:`Quotient`).
        f0: None, or the normal-incidence reflectance (scalar or 3 values in [0, 1]).
    """

    def __init__(self, base: str | Quotient = "one", f0=None):
        self.base = make_quotient(base)
        self.anisotropic = self.base.anisotropic
        if f0 is None:
            self.f0 = None
            self.channels = self.base.channels
        else:
            t = torch.as_tensor(f0, dtype=torch.float64).reshape(-1).expand(3).clone()
            if bool(((t < 0) | (t > 1)).any()):
                raise ValueRangeError(f"f0 must lie in [0, 1]; got {t.tolist()}")
            self.f0 = t
            self.channels = 3

    @property
    def key(self) -> str:
        if self.f0 is None:
            return f"schlick({self.base.key})"
        return f"fresnel(f0={[float(v).hex() for v in self.f0]},{self.base.key})"

    def value(self, wi, wo):
        _, cd, _ = half_and_diff(wi, wo)
        s = (1 - cd.clamp(0.0, 1.0)) ** 5
        q = self.base(wi, wo)
        if self.f0 is None:
            return q * s if q.ndim == s.ndim else q * s.unsqueeze(-1)
        f0 = self.f0.to(wi.dtype)
        fr = f0 + (1 - f0) * s.unsqueeze(-1)
        return fr * (q if q.ndim == fr.ndim else q.unsqueeze(-1))


class SmithQuotient(Quotient):
    r"""Microfacet quotient with a separable Smith masking of known roughness,
    :math:`G_1(\omega_i)G_1(\omega_o)/(4\cos\theta_i\cos\theta_o)` (the GAF of
    :class:`~torch_brdf.brdf.microfacet.CookTorrance`, Heitz 2014): with it and
    ``theta_h`` bands, :math:`f` is the distribution :math:`D(\theta_h)` of a Cook-Torrance
    BRDF of that roughness (Fresnel via :class:`SchlickFresnel`).

    Args:
        distribution: ``"ggx"`` or ``"beckmann"`` (whose exact :math:`G_1` is used).
        roughness: :math:`\alpha > 0`.
    """

    def __init__(self, distribution: str = "ggx", roughness: float = 0.2):
        if distribution not in ("ggx", "beckmann"):
            raise ValueRangeError(f"distribution must be 'ggx' or 'beckmann'; got {distribution!r}")
        if not roughness > 0:
            raise ValueRangeError(f"roughness must be > 0; got {roughness}")
        self.distribution, self.roughness = distribution, float(roughness)

    @property
    def key(self) -> str:
        return f"smith({self.distribution},{self.roughness.hex()})"

    def value(self, wi, wo):
        g1c = ggx_g1_over_cos if self.distribution == "ggx" else beckmann_g1_over_cos
        a = torch.tensor(self.roughness, dtype=wi.dtype)
        return 0.25 * g1c(wi, a) * g1c(wo, a)


class AnisotropicLobe(Quotient):
    r"""Eq. 35's :math:`\rho_{qu} = \rho_q(\cos\theta_h)^{n_u\cos^2\phi_h}` (the AS lobe's
    width along the tangent; :math:`\phi_h` from local +x). Pair it with the
    ``"anisotropy_ratio"`` basis of the same :math:`n_u`: then
    :math:`\rho_{AS} \propto \rho_{qu}\,\gamma_r^{\,n_v/n_u}` (Eq. 34).

    Args:
        n_u: AS exponent along the tangent (> 0).
        base: base quotient (default ``"ashikhmin_shirley"``).
    """

    anisotropic = True

    def __init__(self, n_u: float, base: str | Quotient = "ashikhmin_shirley"):
        if not n_u > 0:
            raise ValueRangeError(f"n_u must be > 0; got {n_u}")
        self.n_u = float(n_u)
        self.base = make_quotient(base)
        self.channels = self.base.channels

    @property
    def key(self) -> str:
        return f"as_lobe(n_u={self.n_u.hex()},{self.base.key})"

    def value(self, wi, wo):
        h, _, _ = half_and_diff(wi, wo)
        ratio, _ = log_cos_over_sin2(h)
        lobe = torch.exp(self.n_u * h[..., 0] ** 2 * ratio) * (h[..., 2] > 0)
        q = self.base(wi, wo)
        return q * lobe if q.ndim == lobe.ndim else q * lobe.unsqueeze(-1)
