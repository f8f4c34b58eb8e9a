r"""The editable factored BRDFs :class:`Factored1D` and :class:`FresnelFactored1D`
(Ben-Artzi et al. 2008, Eq. 30-32) and the albedo-weighted coarsening of their coefficients.
"""

from __future__ import annotations

import math

import torch

from ...errors import ShapeError, ValueRangeError
from ...frame import Frame, orthonormal_basis, polar_angle
from ...sphere.warps import (
    cosine_hemisphere_pdf,
    cosine_power_hemisphere_pdf,
    square_to_cosine_hemisphere,
    square_to_cosine_power_hemisphere,
)
from ..base import BRDF, Clamped, register
from ._geometry import eps, half_and_diff
from .albedo import band_albedos
from .basis import BandBasis
from .projection import project
from .quotients import Quotient, SchlickFresnel, make_quotient

__all__ = ["Factored1D", "FresnelFactored1D", "coarsen_coefficients"]


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
            Stored raw behind ``Clamped(0, inf)`` and exposed as ``coefficients``.
            (non-negative, differentiable; :meth:`set_coefficients` edits in place).
        quotient: name or :class:`Quotient` (see the module docstring).
        variable: the basis, when ``basis`` is None.
        J: as ``variable``.
        spacing: as ``variable``.
        n_u: as ``variable``.
        symmetric: as ``variable``.
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
        """Overwrite :math:`c` in place: (J, 3) (or scalar, (J,), (3,)), values >= 0
        (``self.coefficients = c`` does the same for (J, 3) or broadcastable values)."""
        self.set_constrained("coefficients", _as_coefficients(c, self.J))

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
            h = square_to_cosine_power_hemisphere(torch.stack((v0, u1), -1), self.basis.n_u)
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
            return Frame(*orthonormal_basis(wo), wo).to_world(local)
        return local

    def pdf_local(self, wi, wo):
        kind, w, alpha = self._components()
        pdf = alpha * cosine_hemisphere_pdf(wi[..., 2])
        if kind == "blinn":
            h, cd, _ = half_and_diff(wi, wo)
            ph = cosine_power_hemisphere_pdf(h[..., 2], self.basis.n_u)
            pdf = pdf + (1 - alpha) * ph / (4 * cd.clamp_min(eps(wi)))
        elif kind == "bands":
            omega = self.basis.band_solid_angles().to(wi.device)
            dens = (w / omega).nan_to_num(0.0).to(wi.dtype)  # per-band density of the ring sample
            var = self.basis.variable
            if var == "theta_h":
                h, cd, _ = half_and_diff(wi, wo)
                band = dens[self.basis.index(polar_angle(h))] / (4 * cd.clamp_min(eps(wi)))
            elif var == "theta_d":
                band = dens[self.basis.index(half_and_diff(wi, wo)[2])]
            else:
                band = dens[self.basis.index(polar_angle(wi))]
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
            weights: (J,) or (J, 3) :math:`e_j`; default :func:`.albedo.band_albedos`
                of this basis and quotient (cached on disk), with ``albedo_kwargs``.
        Returns:
            A new :class:`Factored1D` on :meth:`BandBasis.coarsened` with the same quotient.
        """
        if weights is None:
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
        basis: as :class:`Factored1D` (:math:`f` and :math:`\rho_q`).
        coefficients: as ``basis``.
        quotient: as ``basis``.
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
