r"""Energy-conservation rows :math:`g_j^l` of the SRBF distribution-based BRDF (Iwasaki Eq. 14-16).

With :math:`f_s = p(h)\,s(\omega_i, \omega_o)`, :math:`p = \sum_j c_j G_j` and the static factor
:math:`s = F(\omega_i\cdot h)/\big((\omega_i\cdot n) + (\omega_o\cdot n) - (\omega_i\cdot n)(\omega_o\cdot n)\big)`
(Eq. 11), energy conservation at an outgoing direction :math:`\omega_o^l` reads

.. math:: \rho_d + \sum_j c_j g_j^l \le 1, \qquad
          g_j^l = \int_{\Omega} G_j(h)\,s(\omega_i, \omega_o^l)\,(\omega_i\cdot n)\,d\omega_i
          \quad\text{(Eq. 15, with the cosine of Eq. 13)}.

The paper's Eq. 15 prints the integrand without :math:`(\omega_i\cdot n)`; Eq. 13 and 14 (from
which it is defined) carry it, so we keep it: without it the constraint would not bound the
albedo.

Outgoing directions: :math:`N_l = 192` (the paper's value) are the pixel centres of an
:math:`8\times8` hemicube (:func:`~torch_brdf.brdf.srbf.hemicube_centers` with n = 8, exactly
:math:`3\cdot 8^2 = 192` equal-area cells) -- the paper does not say how it discretises.

Quadrature: the integral is taken over the half vector, :math:`d\omega_i = 4(\omega_o\cdot h)
\,d\omega_h`, on a Gauss-Legendre product grid in :math:`(\theta_h, \phi_h)` over the upper
hemisphere (``n_theta`` x ``n_phi`` nodes; :math:`\omega_i = 2(\omega_o\cdot h)h - \omega_o`,
zero where it falls below the horizon). The SRBF lobes (:math:`\lambda \approx 81`, half width
7.5 degrees) span about 30 nodes at the defaults, so the rule is converged to ~1e-6 relative;
the tests check it against :meth:`~torch_brdf.brdf.base.BRDF.albedo` of the same BRDF.

With Schlick's Fresnel :math:`F = F_0 + (1 - F_0)(1-\omega_i\cdot h)^5` the rows are
:math:`g = F_0\,g^{(0)} + (1 - F_0)\,g^{(5)}`; both parts are precomputed once per basis
(:func:`energy_rows`, cached per basis and direction set).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..brdf.srbf import SRBFBasis, hemicube_centers
from ..errors import ShapeError, ValueRangeError

__all__ = ["EnergyRows", "default_basis", "energy_rows", "outgoing_directions"]

#: N_l of the paper (Sec. 5)
NUM_OUTGOING = 192


def outgoing_directions(n: int = 8) -> torch.Tensor:
    """The :math:`3n^2` discretised outgoing directions (local, float64): (192, 3) for n = 8."""
    return hemicube_centers(n)


class EnergyRows:
    """The two Fresnel parts of :math:`g_j^l` for one basis and one set of outgoing directions.

    Attributes:
        directions: (N_l, 3) local outgoing directions :math:`\\omega_o^l`, float64.
        plain: (N_l, J) :math:`g^{(0)}` (:math:`F \\equiv 1`), float64.
        schlick: (N_l, J) :math:`g^{(5)}` (:math:`F = (1 - \\omega_i\\cdot h)^5`), float64.
    """

    def __init__(self, directions: torch.Tensor, plain: torch.Tensor, schlick: torch.Tensor):
        self.directions, self.plain, self.schlick = directions, plain, schlick

    def rows(self, f0) -> torch.Tensor:
        """:math:`g` for RGB (or scalar) :math:`F_0`: (C, N_l, J) float64 with C = len(f0)."""
        f = torch.as_tensor(f0, dtype=torch.float64).reshape(-1)
        if not bool(torch.isfinite(f).all()) or bool(((f < 0) | (f > 1)).any()):
            raise ValueRangeError(f"f0 must lie in [0, 1]; got {f.tolist()}")
        return f[:, None, None] * self.plain + (1 - f)[:, None, None] * self.schlick


_CACHE: dict[tuple, EnergyRows] = {}
_DEFAULT_BASIS: list[SRBFBasis] = []


def default_basis() -> SRBFBasis:
    """The paper's basis (147 hemicube lobes, sigma = pi/40), built once per process (its
    normalisation integrals take ~0.5 s)."""
    if not _DEFAULT_BASIS:
        _DEFAULT_BASIS.append(SRBFBasis())
    return _DEFAULT_BASIS[0]


def _key(basis: SRBFBasis, directions: torch.Tensor, n_theta: int, n_phi: int) -> tuple:
    c = basis.centers.double().contiguous().numpy().tobytes()
    d = directions.double().contiguous().numpy().tobytes()
    return (hash(c), hash(d), basis.bandwidth, n_theta, n_phi)


def energy_rows(
    basis: SRBFBasis | None = None,
    directions: torch.Tensor | None = None,
    n_theta: int = 192,
    n_phi: int = 384,
) -> EnergyRows:
    r"""Precompute :math:`g_j^l` (Eq. 15) for ``basis`` at ``directions`` (cached).

    Args:
        basis: the SRBFs (default :class:`SRBFBasis`: 147 lobes).
        directions: (N_l, 3) local unit outgoing directions with :math:`z > 0` (default the 192
            of :func:`outgoing_directions`).
        n_theta: Gauss-Legendre nodes in :math:`\theta_h` and :math:`\phi_h`.
        n_phi: as ``n_theta``.
    Returns:
        :class:`EnergyRows` with (N_l, J) float64 tables.
    """
    basis = basis if basis is not None else default_basis()
    wo = outgoing_directions() if directions is None else torch.as_tensor(directions, dtype=torch.float64)
    if wo.ndim != 2 or wo.shape[-1] != 3 or wo.shape[0] < 1:
        raise ShapeError(f"Expected directions to have shape (N_l, 3); got {tuple(wo.shape)}")
    if not bool(torch.isfinite(wo).all()) or bool((wo[:, 2] <= 0).any()):
        raise ValueRangeError("outgoing directions must be finite and above the horizon (z > 0)")
    wo = wo / wo.norm(dim=-1, keepdim=True)
    key = _key(basis, wo, n_theta, n_phi)
    if key in _CACHE:
        return _CACHE[key]
    x, w = np.polynomial.legendre.leggauss(n_theta)
    th = torch.from_numpy((x + 1) * (math.pi / 4))
    wth = torch.from_numpy(w * (math.pi / 4))
    xp, wp = np.polynomial.legendre.leggauss(n_phi)
    ph = torch.from_numpy((xp + 1) * math.pi)
    wph = torch.from_numpy(wp * math.pi)
    T, P = torch.meshgrid(th, ph, indexing="ij")
    h = torch.stack((torch.sin(T) * torch.cos(P), torch.sin(T) * torch.sin(P), torch.cos(T)), -1).reshape(-1, 3)
    dw = (torch.sin(T) * wth[:, None] * wph[None, :]).reshape(-1)  # solid angle weights of h
    G = basis.eval(h)  # (M, J)
    plain, schlick = [], []
    for chunk in wo.split(32):
        oh = chunk @ h.T  # (L, M)  wo . h
        wi_z = 2 * oh * h[:, 2] - chunk[:, 2:3]  # (omega_i . n) with omega_i = 2 (wo.h) h - wo
        ci, co = wi_z.clamp_min(0), chunk[:, 2:3]
        den = ci + co - ci * co
        ok = (wi_z > 0) & (oh > 0)
        jac = torch.where(ok, 4 * oh * ci / den.clamp_min(1e-300), torch.zeros((), dtype=torch.float64)) * dw
        plain.append(jac @ G)
        schlick.append((jac * (1 - oh).clamp(0, 1) ** 5) @ G)
    rows = EnergyRows(wo, torch.cat(plain), torch.cat(schlick))
    _CACHE[key] = rows
    return rows
