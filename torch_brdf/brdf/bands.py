r"""Editable 1-D factorised BRDFs on box bands (Ben-Artzi et al. 2008, Appendix A).

A factored BRDF is a fixed *quotient* times an editable 1-D curve (Eq. 30):

.. math::
    \rho(\omega_i, \omega_o) = \rho_q(\omega_i, \omega_o)\, f(\gamma), \qquad
    f(\gamma) = \sum_{j=1}^{J} c_j\, b_j(\gamma(\omega_i, \omega_o)),

with :math:`b_j` the indicator ("box") of band :math:`j` of a 1-D parameterisation
:math:`\gamma` of the 4-D domain and :math:`c` an RGB ``(J, 3)`` tensor.

Parameterisations (:class:`BandBasis` ``variable``):

* ``"theta_h"``, ``"theta_d"``: Rusinkiewicz half / difference angles in :math:`[0, \pi/2]`;
  both are symmetric in :math:`(\omega_i, \omega_o)`, so the BRDF is reciprocal whenever
  the quotient is.
* ``"theta_i"``, ``"theta_o"``: polar angle of one direction. A factor of :math:`\theta_i`
  alone is *not* reciprocal; the paper (Appendix A) lists these parameterisations for a
  fixed view and does not discuss reciprocity. With ``symmetric=True`` (the default) we use
  the symmetrised basis :math:`b_j = \tfrac12(\mathbb 1_j(\theta_i) + \mathbb 1_j(\theta_o))`,
  still linear in :math:`c` and reciprocal by construction (then ``theta_i`` and
  ``theta_o`` coincide). ``symmetric=False`` gives the literal, one-sided factor.
* ``"anisotropy_ratio"``: :math:`\gamma_r = (\cos\theta_h)^{n_u \sin^2\phi_h}\in[0, 1]`, the
  Ashikhmin-Shirley anisotropy-ratio factor of Eq. 33-35 (read with the squares of the AS
  model, :math:`n_u\cos^2\phi_h + n_v\sin^2\phi_h`, which the printed equations drop). With
  the quotient :class:`AnisotropicLobe` the AS specular lobe is
  :math:`\rho_{qu}\,\gamma_r^{\,r}`, :math:`r = n_v/n_u`, so editing :math:`f(\gamma_r)`
  edits the elongation ratio at fixed width :math:`n_u`.

Quotients (:func:`make_quotient`; all non-negative and reciprocal). The paper puts
"normalization constants and the GAF" into :math:`\rho_q` but names no quotient per model;
we use:

* ``"one"``: :math:`1`. Blinn-Phong (:class:`~torch_brdf.brdf.analytic.BlinnPhong`,
  :math:`k_d/\pi + k_s\frac{n+2}{8\pi}\cos^n\theta_h`) is exactly a function of
  :math:`\theta_h`, so its normalisation and diffuse offset live in :math:`c` and only the
  banding error remains.
* ``"distribution"``: :math:`1/(\cos\theta_i + \cos\theta_o - \cos\theta_i\cos\theta_o)`,
  Ashikhmin's distribution-based BRDF (Iwasaki et al. Eq. 11 without Fresnel): :math:`f` is
  then the half-vector distribution :math:`p(h)`.
* ``"microfacet"``: :math:`1/(4\cos\theta_i\cos\theta_o)`: :math:`f` is :math:`D(h)`.
* ``"cook_torrance"``: :math:`G_{TS}/(4\cos\theta_i\cos\theta_o)` with the parameter-free
  V-groove GAF of Cook and Torrance, :math:`G_{TS} = \min(1, 2\cos\theta_h\cos\theta_o/
  \cos\theta_d, 2\cos\theta_h\cos\theta_i/\cos\theta_d)`.
* ``"ashikhmin_shirley"``: :math:`1/(\cos\theta_d\max(\cos\theta_i, \cos\theta_o))` (AS 2000,
  their :math:`(h\cdot k)\max(n\cdot k_1, n\cdot k_2)`).

Parameterised: :class:`SmithQuotient` (the Smith :math:`G_1G_1/(4\cos\cos)` of a
Cook-Torrance BRDF of known roughness). Wrappers: :class:`SchlickFresnel` -- the Fresnel
two-layer form of Eq. 31-32: the second layer's quotient
:math:`\rho_{q2} = (1-\cos\theta_d)^5\rho_q` (``f0=None``), or the full Schlick factor
:math:`F_0 + (1 - F_0)(1-\cos\theta_d)^5` for a known RGB :math:`F_0`
(:class:`FresnelFactored1D` sums the two layers); :class:`AnisotropicLobe` -- Eq. 35's
:math:`\rho_{qu} = \rho_q(\cos\theta_h)^{n_u\cos^2\phi_h}`.

Projection (:func:`project`) is cosine-weighted least squares over all pairs
:math:`(\omega_i, \omega_o)` with the weight :math:`\cos\theta_i\cos\theta_o\,d\omega_i
d\omega_o` (the measure of Appendix B's Eq. 36), by a dense deterministic quadrature in
Rusinkiewicz coordinates (:class:`PairQuadrature`), in float64. Coarsening merges adjacent
bands with the equivalent-albedo weights :math:`e_j` of :mod:`.equivalent_albedo`, which
keeps the equivalent albedo :math:`d = \frac1\pi\sum_j c_j e_j` of every level identical
(see :meth:`Factored1D.coarsen`).

Accuracy of box bands (cosine-weighted relative L2 error, quotient ``"one"``, a pure
Blinn-Phong lobe :math:`k_d = 0, k_s = 1`): the error of a piecewise-constant fit is about
band width x slope / :math:`\sqrt{12}`, so it halves with every doubling of J. At J = 64 MERL's
``"sqrt"`` spacing gives 2.1% / 4.1% / 7.3% for n = 10 / 100 / 1000; ``"log:0.02"`` 2.5% /
3.1% / 4.0%; ``"lobe:100"`` (bands adapted to n = 100) 6.4% / 1.4% / 7.8%. No fixed spacing
reaches 2% at J = 64 for all three; J = 128 with ``"sqrt"`` gives 1.1% / 2.0% / 3.7%.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ..errors import ShapeError, ValueRangeError
from ..frame import orthonormal_basis
from ..sphere.warps import cosine_hemisphere_pdf, square_to_cosine_hemisphere
from .base import BRDF, Clamped, register

__all__ = [
    "VARIABLES",
    "AnisotropicLobe",
    "BandBasis",
    "Factored1D",
    "FresnelFactored1D",
    "PairQuadrature",
    "Quotient",
    "SchlickFresnel",
    "SmithQuotient",
    "make_quotient",
    "project",
    "projection_error",
]

HALF_PI = math.pi / 2
#: The 1-D parameterisations and their domains.
VARIABLES = {
    "theta_h": (0.0, HALF_PI),
    "theta_d": (0.0, HALF_PI),
    "theta_i": (0.0, HALF_PI),
    "theta_o": (0.0, HALF_PI),
    "anisotropy_ratio": (0.0, 1.0),
}


# --------------------------------------------------------------------------------------------
# geometry shared by the bases and quotients (symmetric in wi <-> wo bit for bit)
# --------------------------------------------------------------------------------------------
def _eps(x: torch.Tensor) -> float:
    return float(torch.finfo(x.dtype).eps)


def half_and_diff(wi: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    r"""Half vector and difference angle, computed symmetrically in ``wi``, ``wo``.

    :math:`|\omega_i + \omega_o| = 2\cos\theta_d` and :math:`|\omega_i - \omega_o| =
    2\sin\theta_d`, so :math:`\theta_d = \operatorname{atan2}(|\omega_i-\omega_o|,
    |\omega_i+\omega_o|)` is accurate everywhere and bitwise reciprocal.

    Args:
        wi, wo: (*B, 3) local unit directions.
    Returns:
        h: (*B, 3) unit half vector (+z where undefined), cos_d: (*B,), theta_d: (*B,).
    """
    s = wi + wo
    ns = torch.linalg.vector_norm(s, dim=-1)
    nd = torch.linalg.vector_norm(wi - wo, dim=-1)
    tiny = _eps(s)
    z = torch.zeros_like(s)
    z[..., 2] = 1.0
    h = torch.where((ns > tiny).unsqueeze(-1), s / ns.clamp_min(tiny).unsqueeze(-1), z)
    return h, 0.5 * ns, torch.atan2(nd, ns)


def _polar(w: torch.Tensor) -> torch.Tensor:
    return torch.atan2(torch.linalg.vector_norm(w[..., :2], dim=-1), w[..., 2])


def _log_cos_over_sin2(h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    r""":math:`\ln\cos\theta_h / \sin^2\theta_h` (-> -1/2 at the pole) and :math:`\sin^2\theta_h`."""
    r2 = (h[..., 0] ** 2 + h[..., 1] ** 2).clamp(0.0, 1.0 - _eps(h))
    small = r2 < 1e-4
    safe = torch.where(small, torch.full_like(r2, 0.5), r2)
    ratio = torch.where(small, -0.5 - 0.25 * r2, 0.5 * torch.log1p(-safe) / safe)
    return ratio, r2


def anisotropy_ratio(h: torch.Tensor, n_u: float) -> torch.Tensor:
    r""":math:`\gamma_r = (\cos\theta_h)^{n_u\sin^2\phi_h}` (Eq. 35) for half vectors (*B, 3) -> (*B,).

    Uses :math:`\sin^2\phi_h\ln\cos\theta_h = h_y^2\,(\ln\cos\theta_h/\sin^2\theta_h)`, finite
    at the pole (:math:`\gamma_r = 1`)."""
    ratio, _ = _log_cos_over_sin2(h)
    return torch.exp(n_u * h[..., 1] ** 2 * ratio)


# --------------------------------------------------------------------------------------------
# quotients
# --------------------------------------------------------------------------------------------
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
        ci, co = wi[..., 2].clamp_min(_eps(wi)), wo[..., 2].clamp_min(_eps(wo))
        return 1.0 / (ci + co - ci * co)


class _Microfacet(Quotient):
    name = "microfacet"

    def value(self, wi, wo):
        ci, co = wi[..., 2].clamp_min(_eps(wi)), wo[..., 2].clamp_min(_eps(wo))
        return 0.25 / (ci * co)


class _CookTorrance(Quotient):
    name = "cook_torrance"

    def value(self, wi, wo):
        e = _eps(wi)
        ci, co = wi[..., 2].clamp_min(e), wo[..., 2].clamp_min(e)
        h, cd, _ = half_and_diff(wi, wo)
        ch, cd = h[..., 2].clamp_min(0.0), cd.clamp_min(e)
        g = torch.minimum(torch.ones_like(ci), 2 * ch * torch.minimum(ci, co) / cd)
        return 0.25 * g / (ci * co)


class _AshikhminShirley(Quotient):
    name = "ashikhmin_shirley"

    def value(self, wi, wo):
        e = _eps(wi)
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
        from .microfacet import beckmann_g1_over_cos, ggx_g1_over_cos

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
        ratio, _ = _log_cos_over_sin2(h)
        lobe = torch.exp(self.n_u * h[..., 0] ** 2 * ratio) * (h[..., 2] > 0)
        q = self.base(wi, wo)
        return q * lobe if q.ndim == lobe.ndim else q * lobe.unsqueeze(-1)


# --------------------------------------------------------------------------------------------
# band basis
# --------------------------------------------------------------------------------------------
def band_edges(J: int, spacing: str | float = "uniform", domain: tuple[float, float] = (0.0, HALF_PI)) -> torch.Tensor:
    r"""Band edges (J + 1,) float64 over ``domain`` = [lo, hi].

    ``spacing``:

    * ``"uniform"``: :math:`\gamma_k = lo + (hi - lo) k/J`;
    * ``"sqrt"``: MERL's half-angle mapping (index :math:`\propto\sqrt{\theta_h}`), edges
      :math:`lo + (hi - lo)(k/J)^2`, dense near ``lo``;
    * a number :math:`p > 0`: power law :math:`lo + (hi - lo)(k/J)^p` (``"sqrt"`` is p = 2);
    * ``"log:t0"`` (e.g. ``"log:0.02"``): uniform in :math:`\ln(1 + (\gamma - lo)/t_0)`,
      constant *relative* band width away from ``lo`` -- every lobe wider than :math:`t_0`
      is resolved with about the same relative error;
    * ``"lobe:n"`` or ``"lobe:n:beta"`` (e.g. ``"lobe:100"``): bands adapted to a Blinn-like
      lobe :math:`\cos^n\gamma \approx e^{-n\gamma^2/2}` -- the L2-optimal density of
      piecewise-constant bands, :math:`\propto (w\,f'^2)^{1/3}` with the near-pole measure
      :math:`w \propto \gamma`, is :math:`\propto \gamma e^{-n\gamma^2/3}`; a fraction
      ``beta`` (default 0.2) of the bands is spread uniformly so the whole domain stays
      editable. Edges: the CDF :math:`(1-\beta)\frac{1 - e^{-n\gamma^2/3}}{1 - e^{-n\,
      hi^2/3}} + \beta\frac{\gamma}{hi}` inverted at :math:`k/J` (for ``lo = 0``);
    * ``"top:..."``: any of the above mirrored so the bands are dense near ``hi``.
    """
    if J < 1:
        raise ValueRangeError(f"J must be >= 1; got {J}")
    lo, hi = float(domain[0]), float(domain[1])
    t = torch.arange(J + 1, dtype=torch.float64) / J
    mirror = isinstance(spacing, str) and spacing.startswith("top:")
    sp = spacing[4:] if mirror else spacing
    if isinstance(sp, (int, float)):
        if not sp > 0:
            raise ValueRangeError(f"power spacing must be > 0; got {sp}")
        g = t**sp
    elif sp == "uniform":
        g = t
    elif sp == "sqrt":
        g = t**2
    elif isinstance(sp, str) and sp.startswith("log:"):
        t0 = float(sp[4:]) / (hi - lo)
        if not t0 > 0:
            raise ValueRangeError(f"log spacing needs t0 > 0; got {sp!r}")
        g = torch.expm1(t * math.log1p(1 / t0)) * t0
    elif isinstance(sp, str) and sp.startswith("lobe:"):
        g = _lobe_grid(t, sp, hi - lo)
    else:
        want = "'uniform', 'sqrt', a power, 'log:t0', 'lobe:n[:beta]' or 'top:...'"
        raise ValueRangeError(f"unknown spacing {spacing!r}; expected {want}")
    if mirror:
        g = 1 - g.flip(0)
    g[0], g[-1] = 0.0, 1.0
    return lo + (hi - lo) * g


def _lobe_grid(t: torch.Tensor, spec: str, scale: float) -> torch.Tensor:
    parts = spec.split(":")
    try:
        n = float(parts[1])
        beta = float(parts[2]) if len(parts) > 2 else 0.2
    except (IndexError, ValueError) as exc:
        raise ValueRangeError(f"lobe spacing is 'lobe:n' or 'lobe:n:beta'; got {spec!r}") from exc
    if not (n > 0 and 0 <= beta <= 1):
        raise ValueRangeError(f"lobe spacing needs n > 0 and 0 <= beta <= 1; got {spec!r}")
    a = n * scale * scale / 3

    def cdf(x: torch.Tensor) -> torch.Tensor:  # x in [0, 1] (fraction of the domain)
        return (1 - beta) * torch.expm1(-a * x * x) / math.expm1(-a) + beta * x

    lo, hi = torch.zeros_like(t), torch.ones_like(t)
    for _ in range(80):  # bisection: cdf is increasing
        mid = 0.5 * (lo + hi)
        below = cdf(mid) < t
        lo, hi = torch.where(below, mid, lo), torch.where(below, hi, mid)
    return 0.5 * (lo + hi)


class BandBasis(nn.Module):
    r"""``J`` box bands over a 1-D parameterisation :math:`\gamma(\omega_i, \omega_o)` (Eq. 30).

    Band ``j`` is :math:`[\gamma_j, \gamma_{j+1})` (the last band includes the upper end);
    values outside the domain are clamped into the first/last band.

    Args:
        variable: one of :data:`VARIABLES`.
        J: number of bands (ignored when ``edges`` is given).
        spacing: see :func:`band_edges`; default ``"sqrt"`` for ``theta_h`` (dense near the
            specular peak, like MERL's mapping), ``"top:sqrt"`` for ``anisotropy_ratio``
            (dense near :math:`\gamma_r = 1`, the highlight), ``"uniform"`` otherwise.
        edges: explicit increasing edges (J + 1,) covering the domain.
        symmetric: for ``theta_i``/``theta_o``, use the reciprocal basis
            :math:`\frac12(\mathbb 1_j(\theta_i) + \mathbb 1_j(\theta_o))`.
        n_u: the AS exponent, required for ``anisotropy_ratio``.
    """

    def __init__(
        self,
        variable: str = "theta_h",
        J: int = 64,
        spacing: str | float | None = None,
        edges=None,
        symmetric: bool = True,
        n_u: float | None = None,
    ):
        super().__init__()
        if variable not in VARIABLES:
            raise ValueRangeError(f"unknown band variable {variable!r}; expected one of {sorted(VARIABLES)}")
        self.variable = variable
        self.domain = VARIABLES[variable]
        if variable == "anisotropy_ratio":
            if n_u is None or not n_u > 0:
                raise ValueRangeError(f"the 'anisotropy_ratio' basis needs n_u > 0; got {n_u}")
            self.n_u = float(n_u)
        else:
            self.n_u = None
        self.symmetric = bool(symmetric) and variable in ("theta_i", "theta_o")
        if edges is not None:
            e = torch.as_tensor(edges, dtype=torch.float64).reshape(-1).clone()
            lo, hi = self.domain
            if e.numel() < 2 or bool((e[1:] <= e[:-1]).any()):
                raise ValueRangeError("band edges must be strictly increasing with at least 2 values")
            if abs(float(e[0]) - lo) > 1e-9 or abs(float(e[-1]) - hi) > 1e-9:
                got = f"[{float(e[0])}, {float(e[-1])}]"
                raise ValueRangeError(f"band edges must span the domain [{lo}, {hi}]; got {got}")
            e[0], e[-1] = lo, hi
            self.spacing = "custom"
        else:
            if spacing is None:
                spacing = {"theta_h": "sqrt", "anisotropy_ratio": "top:sqrt"}.get(variable, "uniform")
            self.spacing = spacing
            e = band_edges(int(J), spacing, self.domain)
        self.register_buffer("edges", e)

    @property
    def J(self) -> int:
        return self.edges.numel() - 1

    @property
    def anisotropic(self) -> bool:
        return self.variable == "anisotropy_ratio"

    def _apply(self, fn, recurse=True):
        # the edges define the bands: keep them float64 under .to(dtype)/.float()/.half(), so a
        # model converted to float32 has the same bands (and cache key) as in float64
        super()._apply(fn, recurse)
        if self.edges.dtype != torch.float64:
            self.edges = self.edges.to(torch.float64)
        return self

    def extra_repr(self) -> str:
        s = f"variable={self.variable!r}, J={self.J}, spacing={self.spacing!r}"
        if self.symmetric:
            s += ", symmetric=True"
        if self.n_u is not None:
            s += f", n_u={self.n_u}"
        return s

    def spec(self) -> dict:
        """JSON-able identity of the basis (variable, edges digest, symmetry, n_u) for cache keys."""
        digest = hashlib.sha256(self.edges.detach().cpu().double().numpy().tobytes()).hexdigest()[:16]
        return {
            "variable": self.variable,
            "J": self.J,
            "edges_sha": digest,
            "symmetric": self.symmetric,
            "n_u": None if self.n_u is None else self.n_u.hex(),
        }

    # -- the parameterisation -----------------------------------------------------------------
    def gamma(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        r""":math:`\gamma(\omega_i, \omega_o)` for local directions (*B, 3) -> (*B,).

        For the symmetric ``theta_i``/``theta_o`` basis returns the pair
        :math:`(\theta_i, \theta_o)`."""
        v = self.variable
        if v == "theta_h":
            h, _, _ = half_and_diff(wi, wo)
            return _polar(h)
        if v == "theta_d":
            return half_and_diff(wi, wo)[2]
        if v == "anisotropy_ratio":
            h, _, _ = half_and_diff(wi, wo)
            return anisotropy_ratio(h, self.n_u)
        ti, to = _polar(wi), _polar(wo)
        if self.symmetric:
            return ti, to
        return ti if v == "theta_i" else to

    def index(self, gamma: torch.Tensor) -> torch.Tensor:
        """Band id (long, same shape) of values ``gamma``; clamped into [0, J - 1]."""
        inner = self.edges[1:-1].to(gamma.dtype).contiguous()
        return torch.bucketize(gamma.detach().contiguous(), inner, right=True)

    def membership(self, wi: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        r"""The bands of each pair as ``(a, b)``, long (*B,) each, with
        :math:`\sum_j c_j b_j = \frac12(c_a + c_b)` (``a == b`` for one-hot bases)."""
        g = self.gamma(wi, wo)
        if isinstance(g, tuple):
            return self.index(g[0]), self.index(g[1])
        k = self.index(g)
        return k, k

    def evaluate(self, c: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        r""":math:`f = \sum_j c_j b_j(\gamma(\omega_i, \omega_o))`.

        Args:
            c: (J, C) coefficients.
            wi, wo: (*B, 3) local directions.
        Returns:
            (*B, C), differentiable in ``c``.
        """
        a, b = self.membership(wi, wo)
        if self.symmetric:
            return 0.5 * (c[a] + c[b])
        return c[a]

    def design(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """Dense basis values :math:`b_j(\\omega_i, \\omega_o)`: (*B, J) (for tests and small problems)."""
        a, b = self.membership(wi, wo)
        eye = torch.eye(self.J, dtype=wi.dtype, device=wi.device)
        return 0.5 * (eye[a] + eye[b])

    # -- hierarchy ----------------------------------------------------------------------------
    def groups(self, J_new: int) -> torch.Tensor:
        """Coarse band of every fine band (J,) long, merging adjacent bands into ``J_new``
        contiguous groups of (nearly) equal count: fine band j -> floor(j J_new / J)."""
        if not 1 <= J_new <= self.J:
            raise ValueRangeError(f"J_new must lie in [1, {self.J}]; got {J_new}")
        return torch.arange(self.J) * J_new // self.J

    def coarsened(self, J_new: int) -> BandBasis:
        """The basis whose band g is the union of the fine bands of group g (:meth:`groups`)."""
        g = self.groups(J_new)
        first = torch.searchsorted(g, torch.arange(J_new))
        e = torch.cat([self.edges[first], self.edges[-1:]])
        return BandBasis(self.variable, edges=e, symmetric=self.symmetric, n_u=self.n_u)

    # -- sampling support ---------------------------------------------------------------------
    def band_solid_angles(self) -> torch.Tensor:
        r"""(J,) float64 solid angle of the direction set each band samples from
        (see :meth:`Factored1D.sample_local`): the ring :math:`\theta\in[\gamma_j,\gamma_{j+1})`
        about the normal for ``theta_h`` (half vectors) and ``theta_i``/``theta_o``, and the
        ring of angular radius :math:`[2\gamma_j, 2\gamma_{j+1})` about :math:`\omega_o` for
        ``theta_d`` (:math:`\omega_i\cdot\omega_o = \cos 2\theta_d`)."""
        e = self.edges
        if self.variable == "theta_d":
            e = 2 * e
        return 2 * math.pi * (torch.cos(e[:-1]) - torch.cos(e[1:]))


# --------------------------------------------------------------------------------------------
# the factored BRDF
# --------------------------------------------------------------------------------------------
def _as_coefficients(c, J: int) -> torch.Tensor:
    t = torch.as_tensor(c, dtype=torch.float64)
    if t.ndim == 0:
        t = t.expand(J, 3)
    elif t.ndim == 1 and t.shape[0] == J:
        t = t[:, None].expand(J, 3)
    elif t.ndim == 1 and t.shape[0] == 3:
        t = t[None, :].expand(J, 3)
    if t.shape != (J, 3):
        raise ShapeError(f"Expected coefficients of shape ({J}, 3) (or scalar, (J,), (3,)); got {tuple(t.shape)}")
    return t.clone()


def coarsen_coefficients(c: torch.Tensor, e: torch.Tensor, groups: torch.Tensor, J_new: int) -> torch.Tensor:
    r"""Albedo-weighted merge of band coefficients (:meth:`Factored1D.coarsen`, Sec. 4.1):
    :math:`c_G = \sum_{j\in G} c_j e_j / \sum_{j\in G} e_j`; a group with zero weight (it never
    reflects) keeps the plain mean of its coefficients. Differentiable in ``c``.

    Args:
        c: (J, C) coefficients; e: (J, C) band albedos; groups: (J,) coarse band of each band.
    Returns:
        (J_new, C) in ``c``'s dtype.
    """
    e = e.to(c)
    z = torch.zeros(J_new, c.shape[1], dtype=c.dtype)
    num, den = z.index_add(0, groups, c * e), z.index_add(0, groups, e)
    plain = z.index_add(0, groups, c) / z.index_add(0, groups, torch.ones_like(c))
    return torch.where(den > 0, num / den.clamp_min(1e-300), plain)


@register("factored_1d")
class Factored1D(BRDF):
    r"""Editable factored BRDF :math:`\rho = \rho_q(\omega_i, \omega_o)\sum_j c_j b_j(\gamma)`
    (Eq. 30), reciprocal by construction for the symmetric parameterisations.

    ``eval`` returns :math:`f_r` (*B, 3) without the cosine, 0 below the horizon (the
    package convention). Typical construction: ``Factored1D.from_brdf(brdf, basis, quotient)``
    (projection), or ``create("factored_1d", J=64, quotient="one", coefficients=c)``.

    Args:
        basis: a :class:`BandBasis`, or None to build one from ``variable``, ``J``,
            ``spacing``, ``n_u``, ``symmetric`` (see :class:`BandBasis`).
        coefficients: (J, 3) RGB coefficients :math:`c` (or a scalar, (J,), (3,));
            default :math:`0.5/\pi` (with quotient ``"one"``: Lambert of albedo 0.5).
            Stored raw behind ``Clamped(0, inf)`` and exposed as ``coefficients``
            (non-negative, differentiable; :meth:`set_coefficients` edits in place).
        quotient: name or :class:`Quotient` (see the module docstring).
        variable, J, spacing, n_u, symmetric: the basis, when ``basis`` is None.
        sample_mix: probability of cosine-hemisphere sampling in the sampling mixture; the
            rest samples the band mixture (:meth:`sample_local`).
    """

    def __init__(
        self,
        basis: BandBasis | None = None,
        coefficients=None,
        quotient: str | Quotient = "one",
        variable: str = "theta_h",
        J: int = 64,
        spacing: str | float | None = None,
        n_u: float | None = None,
        symmetric: bool = True,
        sample_mix: float = 0.25,
    ):
        super().__init__()
        if basis is None:
            basis = BandBasis(variable, J, spacing, symmetric=symmetric, n_u=n_u)
        if not isinstance(basis, BandBasis):
            raise ShapeError(f"basis must be a BandBasis; got {type(basis)!r}")
        self.basis = basis
        self.quotient = make_quotient(quotient)
        if not 0.0 <= sample_mix <= 1.0:
            raise ValueRangeError(f"sample_mix must lie in [0, 1]; got {sample_mix}")
        self.sample_mix = float(sample_mix)
        self.anisotropic = bool(basis.anisotropic or self.quotient.anisotropic)
        c = _as_coefficients(0.5 / math.pi if coefficients is None else coefficients, basis.J)
        self.register_constrained("coefficients", c, Clamped(0.0, math.inf), shape=(basis.J, 3))

    @property
    def J(self) -> int:
        return self.basis.J

    def extra_repr(self) -> str:
        return f"quotient={self.quotient.key!r}, J={self.J}, sample_mix={self.sample_mix}"

    def set_coefficients(self, c) -> None:
        """Overwrite :math:`c` in place: (J, 3) (or scalar, (J,), (3,)), values >= 0."""
        t = _as_coefficients(c, self.J)
        with torch.no_grad():
            self.raw_coefficients.copy_(self._constraints["coefficients"].inverse(t).to(self.raw_coefficients))

    # -- evaluation ---------------------------------------------------------------------------
    def _factor(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        return self.basis.evaluate(self.coefficients.to(wi.dtype), wi, wo)

    def _quotient(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        q = self.quotient(wi, wo)
        return q.unsqueeze(-1) if q.ndim == wi.ndim - 1 else q

    def eval_local(self, wi, wo):
        up = ((wi[..., 2] > 0) & (wo[..., 2] > 0)).unsqueeze(-1)
        val = self._quotient(wi, wo) * self._factor(wi, wo)
        return torch.where(up, val, torch.zeros((), dtype=val.dtype))

    # -- sampling -----------------------------------------------------------------------------
    def _band_weights(self) -> torch.Tensor | None:
        r"""Band selection probabilities (J,) float64 :math:`\propto \bar c_j\,\Omega_j`
        (differentiable in :math:`c`), or None when the band component is unused."""
        if self.basis.variable == "anisotropy_ratio" or (self.basis.variable == "theta_o" and not self.basis.symmetric):
            return None
        omega = self.basis.band_solid_angles().to(self.coefficients.device)
        w = self.coefficients.double().mean(-1).clamp_min(0) * omega
        tot = w.sum()
        t = float(tot.detach())
        return w / tot if t > 0 and math.isfinite(t) else None

    def _components(self) -> tuple[str | None, torch.Tensor | None, float]:
        """(kind of the lobe component, band weights, cosine probability)."""
        if self.basis.variable == "anisotropy_ratio":
            return "blinn", None, self.sample_mix
        w = self._band_weights()
        return ("bands", w, self.sample_mix) if w is not None else (None, None, 1.0)

    def sample_local(self, wo, u):
        r"""Mixture sampling with an exact pdf: with probability ``sample_mix`` the cosine
        lobe, otherwise a lobe component that depends on the parameterisation:

        * ``theta_h``: band :math:`j` with probability :math:`\propto \bar c_j\Omega_j`, then
          :math:`h` uniform in the band's ring about the normal and :math:`\omega_i` the
          reflection of :math:`\omega_o`; :math:`p(\omega_i) = p(h)/(4|\omega_o\cdot h|)`.
          The half-vector density is the piecewise-constant curve :math:`\bar c(\theta_h)`
          itself, normalised.
        * ``theta_d``: band as above, then :math:`\omega_i` uniform in the ring of angular
          radius :math:`[2\gamma_j, 2\gamma_{j+1})` about :math:`\omega_o`
          (:math:`\omega_i\cdot\omega_o = \cos 2\theta_d`).
        * ``theta_i`` (and the symmetric ``theta_o``): band as above, :math:`\omega_i` uniform
          in its ring about the normal.
        * ``anisotropy_ratio``: :math:`h` from the Blinn lobe
          :math:`\frac{n_u+1}{2\pi}\cos^{n_u}\theta_h` (the quotient's width along the
          tangent), reflected as for ``theta_h``.
        * one-sided ``theta_o``, or an all-zero curve: the cosine lobe only.

        Samples below the horizon get pdf 0 (the base-class convention). The first uniform
        selects the component and the band and is rescaled, so two uniforms suffice.
        """
        kind, w, alpha = self._components()
        shape = u.shape[:-1]
        u0, u1 = u[..., 0], u[..., 1]
        if kind is None:
            wi_cos = square_to_cosine_hemisphere(u.reshape(-1, 2)).reshape(shape + (3,))
            return wi_cos, self.pdf_local(wi_cos, wo)
        use_cos = u0 < alpha
        v0 = torch.where(use_cos, u0 / max(alpha, 1e-300), (u0 - alpha) / max(1 - alpha, 1e-300)).clamp(0.0, 1.0)
        uc = torch.stack((v0, u1), -1).reshape(-1, 2)
        wi_cos = square_to_cosine_hemisphere(uc).reshape(shape + (3,))
        if kind == "blinn":
            n = self.basis.n_u
            ct = v0 ** (1 / (n + 1))
            st = (1 - ct * ct).clamp_min(0).sqrt()
            phi = 2 * math.pi * u1
            h = torch.stack((st * torch.cos(phi), st * torch.sin(phi), ct), -1)
            wi_lobe = 2 * (wo * h).sum(-1, keepdim=True) * h - wo
        else:
            wd = w.detach().to(u.dtype)
            cdf = torch.cumsum(wd, 0)
            cdf[-1] = 1.0
            j = torch.searchsorted(cdf, v0.contiguous(), right=True).clamp_max(self.J - 1)
            # only v0 == 1 can land on a zero-probability band (the clamp): take the last used one
            last = int(torch.nonzero(wd > 0)[-1])
            j = torch.where(wd[j] > 0, j, torch.full_like(j, last))
            lo_cdf = torch.where(j > 0, cdf[(j - 1).clamp_min(0)], torch.zeros_like(v0))
            v0 = ((v0 - lo_cdf) / wd[j]).clamp(0.0, 1.0)
            e = self.basis.edges.to(u.dtype)
            wi_lobe = self._sample_ring(wo, e[j], e[j + 1], v0, u1)
        wi = torch.where(use_cos.unsqueeze(-1), wi_cos, wi_lobe)
        wi = wi / wi.norm(dim=-1, keepdim=True)
        return wi, self.pdf_local(wi, wo)

    def _sample_ring(self, wo, a, b, v0, v1):
        var = self.basis.variable
        phi = 2 * math.pi * v1
        if var == "theta_d":
            a, b = 2 * a, 2 * b
        ca, cb = torch.cos(a), torch.cos(b)
        ct = ca + (cb - ca) * v0
        st = (1 - ct * ct).clamp_min(0).sqrt()
        local = torch.stack((st * torch.cos(phi), st * torch.sin(phi), ct), -1)
        if var == "theta_h":
            h = local
            return 2 * (wo * h).sum(-1, keepdim=True) * h - wo
        if var == "theta_d":
            s, t = orthonormal_basis(wo)
            return local[..., :1] * s + local[..., 1:2] * t + local[..., 2:3] * wo
        return local

    def pdf_local(self, wi, wo):
        kind, w, alpha = self._components()
        pdf = alpha * cosine_hemisphere_pdf(wi[..., 2])
        if kind == "blinn":
            h, cd, _ = half_and_diff(wi, wo)
            n = self.basis.n_u
            ph = (n + 1) / (2 * math.pi) * h[..., 2].clamp_min(0) ** n
            pdf = pdf + (1 - alpha) * ph / (4 * cd.clamp_min(_eps(wi)))
        elif kind == "bands":
            omega = self.basis.band_solid_angles().to(wi.device)
            dens = (w / omega).nan_to_num(0.0).to(wi.dtype)  # per-band density of the ring sample
            var = self.basis.variable
            if var == "theta_h":
                h, cd, _ = half_and_diff(wi, wo)
                band = dens[self.basis.index(_polar(h))] / (4 * cd.clamp_min(_eps(wi)))
            elif var == "theta_d":
                band = dens[self.basis.index(half_and_diff(wi, wo)[2])]
            else:
                band = dens[self.basis.index(_polar(wi))]
            pdf = pdf + (1 - alpha) * band
        ok = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        return torch.where(ok, pdf, torch.zeros_like(pdf))

    # -- hierarchy ----------------------------------------------------------------------------
    def coarsen(self, J_new: int, weights: torch.Tensor | None = None, **albedo_kwargs) -> Factored1D:
        r"""A lower-frequency version with ``J_new`` bands (Sec. 4.1, Eq. 17).

        Adjacent bands are merged (:meth:`BandBasis.groups`) with the equivalent-albedo
        weights :math:`e_j` (Appendix B, Eq. 36):

        .. math:: c_G = \frac{\sum_{j\in G} c_j e_j}{\sum_{j\in G} e_j}, \qquad
                  e_G = \sum_{j \in G} e_j.

        Derivation: the coarse BRDF is used in place of the fine one for further bounces,
        where what must survive is reflected power; :math:`e_j` is the power band :math:`j`
        reflects for uniform incident radiance per unit :math:`c_j`, and since
        :math:`b_G = \sum_{j\in G} b_j`, :math:`e_G = \sum_{j\in G} e_j` exactly. So this rule
        conserves the cosine-weighted integral :math:`\iint\rho\cos\theta_i\cos\theta_o` over
        every merged region, hence the equivalent albedo :math:`d = \frac1\pi\sum c_j e_j` at
        every level, down to ``J_new = 1``, which (quotient ``"one"``) is the Lambertian
        :math:`d/\pi` of Sec. 4.2. (The L2-optimal merge would weight by
        :math:`\iint\rho_q^2 b_j\cos\cos` instead; the two agree when :math:`\rho_q` is constant.)

        Args:
            J_new: number of coarse bands, 1 <= J_new <= J.
            weights: (J,) or (J, 3) :math:`e_j`; default :func:`.equivalent_albedo.band_albedos`
                of this basis and quotient (cached on disk), with ``albedo_kwargs``.
        Returns:
            A new :class:`Factored1D` on :meth:`BandBasis.coarsened` with the same quotient.
        """
        if weights is None:
            from .band_albedo import band_albedos

            weights = band_albedos(self.basis, self.albedo_quotient(), **albedo_kwargs)
        e = torch.as_tensor(weights, dtype=torch.float64)
        e = e[:, None].expand(self.J, 3) if e.ndim == 1 else e
        if e.shape != (self.J, 3):
            raise ShapeError(f"Expected weights of shape ({self.J},) or ({self.J}, 3); got {tuple(e.shape)}")
        c_new = coarsen_coefficients(self.coefficients.detach().double().cpu(), e, self.basis.groups(J_new), J_new)
        return type(self)._like(self, self.basis.coarsened(J_new), c_new)

    def albedo_quotient(self) -> Quotient:
        r"""The quotient whose band albedos :math:`e_j` give this BRDF's equivalent albedo
        :math:`d = \frac1\pi\sum_j c_j e_j` (here :attr:`quotient`)."""
        return self.quotient

    @classmethod
    def _like(cls, other: Factored1D, basis: BandBasis, c: torch.Tensor) -> Factored1D:
        return Factored1D(basis, c, other.quotient, sample_mix=other.sample_mix)

    def hierarchy(self, **albedo_kwargs) -> list[Factored1D]:
        """``[self, J/2, J/4, ..., 1]`` by repeated halving (:meth:`coarsen`; the last step goes
        to 1 when a level is odd). Every level has the same equivalent albedo."""
        from .band_albedo import band_albedos

        e = band_albedos(self.basis, self.albedo_quotient(), **albedo_kwargs)
        out: list[Factored1D] = [self]
        cur, cur_e = self, e
        while cur.J > 1:
            J_new = cur.J // 2 if cur.J % 2 == 0 else 1
            g = cur.basis.groups(J_new)
            nxt = cur.coarsen(J_new, weights=cur_e)
            cur_e = torch.zeros((J_new,) + tuple(cur_e.shape[1:]), dtype=torch.float64).index_add_(0, g, cur_e)
            out.append(nxt)
            cur = nxt
        return out

    @classmethod
    def from_brdf(cls, brdf: BRDF, basis: BandBasis, quotient: str | Quotient = "one", **kwargs) -> Factored1D:
        """Project ``brdf`` onto ``basis`` (:func:`project`) and wrap the result."""
        sample_mix = kwargs.pop("sample_mix", 0.25)
        c = project(brdf, basis, quotient, **kwargs)
        return cls(basis, c, quotient, sample_mix=sample_mix)


@register("factored_1d_fresnel")
class FresnelFactored1D(Factored1D):
    r"""The Fresnel two-layer factored BRDF of Eq. 31-32:

    .. math:: \rho = \rho_q f(\gamma)\,(F + (1 - F)(1-\cos\theta_d)^5)
              = \rho_q f_1 + \rho_{q2} f_2,\quad f_1 = F f,\ f_2 = (1-F) f,\
              \rho_{q2} = (1-\cos\theta_d)^5\rho_q.

    Editing ``f0`` (:math:`F`, RGB, in [0, 1]) is the runtime Fresnel edit; :meth:`layers`
    returns the two single-factor BRDFs that the precomputation sees. Sampling is that of
    :class:`Factored1D` (the Fresnel factor is at most 1).

    Args:
        basis, coefficients, quotient, ...: as :class:`Factored1D` (:math:`f` and :math:`\rho_q`).
        f0: normal-incidence reflectance :math:`F` (scalar or RGB), exposed as ``f0``.
    """

    def __init__(self, basis: BandBasis | None = None, coefficients=None, quotient="one", f0=0.04, **kwargs):
        super().__init__(basis, coefficients, quotient, **kwargs)
        self.register_constrained("f0", f0, Clamped(0.0, 1.0), shape=(3,))

    def eval_local(self, wi, wo):
        _, cd, _ = half_and_diff(wi, wo)
        s = ((1 - cd.clamp(0.0, 1.0)) ** 5).unsqueeze(-1)
        f0 = self.f0.to(wi.dtype)
        return super().eval_local(wi, wo) * (f0 + (1 - f0) * s)

    def layers(self) -> tuple[Factored1D, Factored1D]:
        """``(rho_q f_1, rho_q2 f_2)`` of Eq. 32 as two :class:`Factored1D` (detached copies)."""
        c = self.coefficients.detach().double()
        f0 = self.f0.detach().double()
        one = Factored1D(self.basis, c * f0, self.quotient, sample_mix=self.sample_mix)
        two = Factored1D(self.basis, c * (1 - f0), SchlickFresnel(self.quotient), sample_mix=self.sample_mix)
        return one, two

    @classmethod
    def _like(cls, other, basis, c):
        return FresnelFactored1D(basis, c, other.quotient, f0=other.f0.detach(), sample_mix=other.sample_mix)

    def albedo_quotient(self) -> Quotient:
        r"""The full RGB quotient :math:`\rho_q(F + (1-F)(1-\cos\theta_d)^5)` (current ``f0``), so
        :meth:`coarsen` and the equivalent albedo see the Fresnel factor."""
        return SchlickFresnel(self.quotient, self.f0.detach())

    @classmethod
    def from_brdf(cls, brdf, basis, quotient="one", f0=0.04, **kwargs):
        """Project ``brdf`` onto :math:`f` with the Schlick factor of a known ``f0`` in the quotient."""
        sample_mix = kwargs.pop("sample_mix", 0.25)
        c = project(brdf, basis, SchlickFresnel(quotient, f0), **kwargs)
        return cls(basis, c, quotient, f0=f0, sample_mix=sample_mix)


# --------------------------------------------------------------------------------------------
# quadrature and projection
# --------------------------------------------------------------------------------------------
def _gauss_legendre(order: int) -> tuple[torch.Tensor, torch.Tensor]:
    x, w = np.polynomial.legendre.leggauss(order)
    return torch.from_numpy(0.5 * (x + 1)), torch.from_numpy(0.5 * w)  # on [0, 1]


def _composite(edges: torch.Tensor, order: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite Gauss-Legendre nodes and weights on the cells of ``edges`` (float64)."""
    x, w = _gauss_legendre(order)
    lo, width = edges[:-1, None], (edges[1:] - edges[:-1])[:, None]
    return (lo + width * x).reshape(-1), (width * w).reshape(-1)


def _merge_edges(*edge_sets: torch.Tensor, tol: float = 1e-12) -> torch.Tensor:
    e = torch.unique(torch.cat(edge_sets).double())
    keep = torch.cat([torch.ones(1, dtype=torch.bool), (e[1:] - e[:-1]) > tol])
    return e[keep]


@dataclass(frozen=True)
class PairQuadrature:
    r"""A deterministic quadrature over pairs :math:`(\omega_i, \omega_o)` of the upper
    hemisphere for the measure :math:`\cos\theta_i\cos\theta_o\,d\omega_i\,d\omega_o`
    (total :math:`\pi^2`), in Rusinkiewicz coordinates, where
    :math:`d\omega_i d\omega_o = 4\cos\theta_d\,\sin\theta_h\,d\theta_h\,d\phi_h\,
    \sin\theta_d\,d\theta_d\,d\phi_d`. All rules are composite Gauss-Legendre of ``order``:

    * :math:`\theta_h`: cells with edges :math:`\frac\pi2(k/n_h)^2` (dense near the specular
      peak, resolving lobes down to ~:math:`1/n_h^2` rad), merged with the band edges when the
      basis is in :math:`\theta_h` (box integrals are then exact per band);
    * :math:`\theta_d`: horizon-aware. Both directions are above the horizon iff
      :math:`\cos\theta_h\cos\theta_d > \sin\theta_h\sin\theta_d|\cos\phi_d|`
      (:math:`\cos\theta_{i,o} = \cos\theta_h\cos\theta_d \mp
      \sin\theta_h\sin\theta_d\cos\phi_d`), i.e. :math:`\theta_d < \theta_{max} =
      \operatorname{atan2}(\cos\theta_h, \sin\theta_h|\cos\phi_d|)`; the rule covers
      :math:`[0, \theta_{max}]` with ``n_theta_d`` cells, so the cosine weight's kink at the
      horizon is a cell end. For a :math:`\theta_d` basis the cells are the band edges merged
      with a uniform grid, clipped at :math:`\theta_{max}` instead;
    * :math:`\phi_d`: ``n_phi_d`` cells (a multiple of 4, so the kinks of
      :math:`\theta_{max}` at :math:`\phi_d = \pi/2, 3\pi/2` are cell ends);
    * :math:`\phi_h`: ``n_phi_h`` cells for anisotropic problems, else one node of weight
      :math:`2\pi`.

    Attributes:
        theta_h, w_h: (Nh,) nodes and weights (including :math:`\sin\theta_h`).
        d_nodes, d_weights: (Kd,) Gauss-Legendre nodes/weights of the :math:`\theta_d` cells on
            [0, 1] (relative to :math:`\theta_{max}`), or None with ``d_edges`` set.
        d_edges: (K + 1,) absolute :math:`\theta_d` cell edges (for a :math:`\theta_d` basis).
        phi_d, w_pd: (Npd,) nodes and weights; phi_h, w_ph: (Nph,) nodes and weights.
        order: Gauss-Legendre order per cell.
    """

    theta_h: torch.Tensor
    w_h: torch.Tensor
    d_nodes: torch.Tensor | None
    d_weights: torch.Tensor | None
    d_edges: torch.Tensor | None
    phi_d: torch.Tensor
    w_pd: torch.Tensor
    phi_h: torch.Tensor
    w_ph: torch.Tensor
    order: int

    @classmethod
    def build(
        cls,
        basis: BandBasis | None = None,
        anisotropic: bool = False,
        n_theta_h: int = 96,
        n_theta_d: int = 6,
        n_phi_d: int = 16,
        n_phi_h: int = 12,
        order: int = 3,
    ) -> PairQuadrature:
        """Build the rule; see the class docstring for what each resolution controls."""
        if n_phi_d % 4 or min(n_theta_h, n_theta_d, n_phi_d, n_phi_h, order) < 1:
            raise ValueRangeError("quadrature resolutions must be >= 1 and n_phi_d a multiple of 4")
        eh = HALF_PI * (torch.arange(n_theta_h + 1, dtype=torch.float64) / n_theta_h) ** 2
        if basis is not None and basis.variable == "theta_h":
            eh = _merge_edges(eh, basis.edges.double().cpu())
        th, wh = _composite(eh, order)
        d_nodes = d_weights = d_edges = None
        if basis is not None and basis.variable == "theta_d":
            ed = torch.linspace(0, HALF_PI, n_theta_d + 1, dtype=torch.float64)
            d_edges = _merge_edges(ed, basis.edges.double().cpu())
        else:
            d_nodes, d_weights = _composite(torch.linspace(0, 1, n_theta_d + 1, dtype=torch.float64), order)
        pd, wpd = _composite(torch.linspace(0, 2 * math.pi, n_phi_d + 1, dtype=torch.float64), order)
        if anisotropic:
            ph, wph = _composite(torch.linspace(0, 2 * math.pi, n_phi_h + 1, dtype=torch.float64), order)
        else:
            ph, wph = torch.zeros(1, dtype=torch.float64), torch.full((1,), 2 * math.pi, dtype=torch.float64)
        return cls(th, wh * torch.sin(th), d_nodes, d_weights, d_edges, pd, wpd, ph, wph, order)

    @property
    def _n_d(self) -> int:
        return self.d_nodes.numel() if self.d_nodes is not None else (self.d_edges.numel() - 1) * self.order

    @property
    def size(self) -> int:
        """Number of nodes."""
        return self.theta_h.numel() * self._n_d * self.phi_d.numel() * self.phi_h.numel()

    def chunks(self, max_points: int = 1 << 19) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        r"""Yield ``(wi, wo, weight)``: (N, 3), (N, 3), (N,) float64 in chunks over
        :math:`\theta_h`; ``weight`` includes :math:`\cos\theta_i^+\cos\theta_o^+` (0 below
        the horizon)."""
        inner = self._n_d * self.phi_d.numel() * self.phi_h.numel()
        step = max(1, max_points // inner)
        pd = self.phi_d[:, None]  # (Npd, 1)
        cpd, spd = torch.cos(pd), torch.sin(pd)
        cph, sph = torch.cos(self.phi_h), torch.sin(self.phi_h)  # (Nph,)
        if self.d_nodes is None:
            x, wx = _gauss_legendre(self.order)
            a, b = self.d_edges[:-1, None], self.d_edges[1:, None]  # (K, 1)
        for s in range(0, self.theta_h.numel(), step):
            th = self.theta_h[s : s + step, None, None]  # (n, 1, 1)
            wh = self.w_h[s : s + step, None, None]
            ct, st = torch.cos(th), torch.sin(th)
            tmax = torch.atan2(ct, st * cpd.abs())  # (n, Npd, 1)
            if self.d_nodes is not None:
                td = tmax * self.d_nodes  # (n, Npd, Kd)
                wd = tmax * self.d_weights
            else:
                lo, hi = torch.minimum(a, tmax[..., None]), torch.minimum(b, tmax[..., None])  # (n, Npd, K, 1)
                td = (lo + (hi - lo) * x).flatten(-2)
                wd = ((hi - lo) * wx).flatten(-2)
            sd, cd = torch.sin(td), torch.cos(td)
            wd = wd * 4 * cd * sd * self.w_pd[:, None] * wh  # (n, Npd, Kd)
            # d = (sin td cos pd, sin td sin pd, cos td); wi = Rz(phi_h) Ry(theta_h) d
            dx, dy, dz = sd * cpd, sd * spd, cd
            x0 = ct * dx + st * dz
            z0 = -st * dx + ct * dz
            x0, y0, z0 = x0[..., None], dy[..., None], z0[..., None]  # (n, Npd, Kd, 1)
            wi = torch.stack(torch.broadcast_tensors(cph * x0 - sph * y0, sph * x0 + cph * y0, z0), -1)
            h = torch.stack(torch.broadcast_tensors(st[..., None] * cph, st[..., None] * sph, ct[..., None]), -1)
            wo = 2 * (wi * h).sum(-1, keepdim=True) * h - wi
            cos_w = wi[..., 2].clamp_min(0) * wo[..., 2].clamp_min(0)
            w = wd[..., None] * self.w_ph * cos_w
            yield wi.reshape(-1, 3), wo.reshape(-1, 3), w.reshape(-1)


def _eval_rgb(brdf, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    f = brdf.eval_local(wi, wo) if hasattr(brdf, "eval_local") else brdf(wi, wo)
    f = f.to(torch.float64)
    if f.ndim == wi.ndim - 1:
        f = f.unsqueeze(-1).expand(*f.shape, 3)
    return f


def project(
    brdf,
    basis: BandBasis,
    quotient: str | Quotient = "one",
    quadrature: PairQuadrature | None = None,
    nonnegative: bool = True,
    **quad_kwargs,
) -> torch.Tensor:
    r"""Cosine-weighted least-squares coefficients of ``brdf`` on ``basis`` (float64).

    .. math:: c = \arg\min_c \iint \Big\|\rho - \rho_q \sum_j c_j b_j\Big\|^2
              \cos\theta_i\cos\theta_o\,d\omega_i\,d\omega_o,

    per channel, by the normal equations :math:`M c = r` with
    :math:`M_{jk} = \iint \rho_q^2 b_j b_k\cos\cos`, :math:`r_j = \iint\rho_q b_j\rho\cos\cos`
    accumulated over :class:`PairQuadrature`. For one-hot bases :math:`M` is diagonal and
    :math:`c_j` is the :math:`\rho_q`-weighted band average of :math:`\rho/\rho_q`. Bands the
    quadrature never reaches with :math:`\rho_q \ne 0` get :math:`c_j = 0`.

    Args:
        brdf: anything with ``eval_local(wi, wo) -> (*B, 3)`` (a :class:`BRDF`, analytic or
            measured) or a callable with that signature; evaluated in float64.
        basis: the bands.
        quotient: :math:`\rho_q`.
        quadrature: a prebuilt rule; default :meth:`PairQuadrature.build` with ``quad_kwargs``,
            anisotropic if the BRDF, basis or quotient is.
        nonnegative: clamp negative coefficients to 0 (they can only arise for the coupled
            symmetric ``theta_i``/``theta_o`` basis; this is a clamp, not an NNLS solve).
    Returns:
        c: (J, 3) float64.
    """
    q = make_quotient(quotient)
    if quadrature is None:
        aniso = bool(getattr(brdf, "anisotropic", False) or q.anisotropic or basis.anisotropic)
        quadrature = PairQuadrature.build(basis, aniso, **quad_kwargs)
    J = basis.J
    M = torch.zeros(J * J, 3, dtype=torch.float64)
    r = torch.zeros(J, 3, dtype=torch.float64)
    with torch.no_grad():
        for wi, wo, w in quadrature.chunks():
            keep = w > 0
            wi, wo, w = wi[keep], wo[keep], w[keep]
            rho = _eval_rgb(brdf, wi, wo)
            qv = q(wi, wo).to(torch.float64)
            qv = qv.unsqueeze(-1).expand(-1, 3) if qv.ndim == 1 else qv
            a, b = basis.membership(wi, wo)
            wq2 = (0.25 * w).unsqueeze(-1) * qv * qv
            for x, y in ((a, a), (a, b), (b, a), (b, b)):
                M.index_add_(0, x * J + y, wq2)
            wqr = (0.5 * w).unsqueeze(-1) * qv * rho
            r.index_add_(0, a, wqr)
            r.index_add_(0, b, wqr)
    M = M.reshape(J, J, 3).permute(2, 0, 1)  # (3, J, J)
    diag = torch.diagonal(M, dim1=-2, dim2=-1)
    scale = diag.amax(-1, keepdim=True).clamp_min(1e-300)
    ridge = 1e-13 * scale
    c = torch.linalg.solve(M + torch.diag_embed(ridge.expand_as(diag)), r.T.unsqueeze(-1)).squeeze(-1).T
    c = torch.where(diag.T > 1e-14 * scale.T, c, torch.zeros_like(c))
    return c.clamp_min(0) if nonnegative else c


def projection_error(
    brdf, factored, quadrature: PairQuadrature | None = None, per_channel: bool = False, **quad_kwargs
) -> float | torch.Tensor:
    r"""Cosine-weighted relative L2 error of an approximation:

    .. math:: \epsilon = \left(\frac{\iint \|\rho - \hat\rho\|^2\cos\theta_i\cos\theta_o\,
              d\omega_i d\omega_o}{\iint \|\rho\|^2\cos\theta_i\cos\theta_o\,d\omega_i
              d\omega_o}\right)^{1/2}

    (sums over RGB, or per channel), by the same quadrature as :func:`project` (float64).

    Args:
        brdf: the reference (``eval_local`` or callable).
        factored: the approximation (any BRDF; typically a :class:`Factored1D`).
        quadrature: prebuilt rule; default built from ``factored.basis`` when it has one.
        per_channel: return (3,) instead of one number.
    Returns:
        float, or (3,) float64 tensor.
    """
    if quadrature is None:
        aniso = bool(getattr(brdf, "anisotropic", False) or getattr(factored, "anisotropic", False))
        quadrature = PairQuadrature.build(getattr(factored, "basis", None), aniso, **quad_kwargs)
    num = torch.zeros(3, dtype=torch.float64)
    den = torch.zeros(3, dtype=torch.float64)
    with torch.no_grad():
        for wi, wo, w in quadrature.chunks():
            keep = w > 0
            wi, wo, w = wi[keep], wo[keep], w[keep]
            a = _eval_rgb(brdf, wi, wo)
            b = _eval_rgb(factored, wi, wo)
            num += (w[:, None] * (a - b) ** 2).sum(0)
            den += (w[:, None] * a * a).sum(0)
    if per_channel:
        return (num / den.clamp_min(1e-300)).sqrt()
    return math.sqrt(float(num.sum()) / max(float(den.sum()), 1e-300))
