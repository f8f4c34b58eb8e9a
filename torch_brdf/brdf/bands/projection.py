r"""Projection onto the bands: cosine-weighted least squares over all pairs
:math:`(\omega_i, \omega_o)` by a dense deterministic quadrature in Rusinkiewicz coordinates
(:class:`PairQuadrature`), in float64 (see :mod:`torch_brdf.brdf.bands`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from ...errors import ValueRangeError
from ._geometry import HALF_PI
from .basis import BandBasis
from .quotients import Quotient, make_quotient

__all__ = ["PairQuadrature", "Projector", "project", "projection_error"]


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


def _assemble(quadrature: PairQuadrature, basis: BandBasis, q: Quotient, brdf=None, keep: bool = False):
    r"""One pass over ``quadrature``: the normal matrix :math:`M` (3, J, J), the right-hand side
    :math:`r` (J, 3) of ``brdf`` (None without one), and with ``keep`` the nodes
    ``(wi, wo, a, b, wq)`` with positive weight (``wq`` (N, 3): :math:`\frac12 w \rho_q`, the
    weight of :math:`\rho` in :math:`r`; a pair adds it to both its bands ``a`` and ``b``)."""
    J = basis.J
    M = torch.zeros(J * J, 3, dtype=torch.float64)
    r = None if brdf is None else torch.zeros(J, 3, dtype=torch.float64)
    kept = []
    with torch.no_grad():
        for wi, wo, w in quadrature.chunks():
            pos = w > 0
            wi, wo, w = wi[pos], wo[pos], w[pos]
            qv = q(wi, wo).to(torch.float64)
            qv = qv.unsqueeze(-1).expand(-1, 3) if qv.ndim == 1 else qv
            a, b = basis.membership(wi, wo)
            wq2 = (0.25 * w).unsqueeze(-1) * qv * qv
            for x, y in ((a, a), (a, b), (b, a), (b, b)):
                M.index_add_(0, x * J + y, wq2)
            wq = (0.5 * w).unsqueeze(-1) * qv
            if r is not None:
                wqr = wq * _eval_rgb(brdf, wi, wo)
                r.index_add_(0, a, wqr)
                r.index_add_(0, b, wqr)
            if keep:
                kept.append((wi, wo, a, b, wq))
    return M.reshape(J, J, 3).permute(2, 0, 1), r, kept


class _NormalSolver:
    """The LU factorisation of the ridged normal matrix (3, J, J) and the bands it reaches."""

    def __init__(self, M: torch.Tensor):
        diag = torch.diagonal(M, dim1=-2, dim2=-1)
        scale = diag.amax(-1, keepdim=True).clamp_min(1e-300)
        self.lu, self.pivots = torch.linalg.lu_factor(M + torch.diag_embed((1e-13 * scale).expand_as(diag)))
        self.reached = (diag > 1e-14 * scale).T  # (J, 3)

    def __call__(self, r: torch.Tensor, nonnegative: bool) -> torch.Tensor:
        c = torch.linalg.lu_solve(self.lu, self.pivots, r.T.unsqueeze(-1)).squeeze(-1).T
        c = torch.where(self.reached, c, torch.zeros_like(c))
        return c.clamp_min(0) if nonnegative else c


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
    quadrature never reaches with :math:`\rho_q \ne 0` get :math:`c_j = 0`. One pass, nothing
    kept; to project many BRDFs on the same bands use :class:`Projector`.

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
    M, r, _ = _assemble(quadrature, basis, q, brdf)
    return _NormalSolver(M)(r, nonnegative)


class Projector:
    r""":func:`project` for many BRDFs on the same bands: the quadrature's nodes, their band
        memberships and the LU factorisation of the normal matrix are made once, so a projection
        costs one evaluation of the BRDF on the kept nodes, two scatter-adds and a J x J
        triangular solve per channel. Same result as :func:`project` on the same rule (tested).

        The nodes are kept in memory (about 90 bytes a pair: the default isotropic rule's ~410k
        pairs take ~37 MB); interactive use passes a coarser rule through ``quad_kwargs`` (the
        editor's ``n_theta_d=2, n_phi_d=4, order=2``: ~10k pairs; the :math:`	heta_h` cells
        still keep the band edges).

        Args:
            basis: the bands.
            quotient: :math:`
    ho_q`.
            anisotropic: integrate over :math:`\phi_h` too (for anisotropic BRDFs; implied by an
                anisotropic basis or quotient).
            quadrature: a prebuilt rule; default :meth:`PairQuadrature.build` with ``quad_kwargs``.
    """

    def __init__(
        self,
        basis: BandBasis,
        quotient: str | Quotient = "one",
        anisotropic: bool = False,
        quadrature: PairQuadrature | None = None,
        **quad_kwargs,
    ):
        q = make_quotient(quotient)
        if quadrature is None:
            aniso = bool(anisotropic or q.anisotropic or basis.anisotropic)
            quadrature = PairQuadrature.build(basis, aniso, **quad_kwargs)
        self.J = basis.J
        M, _, kept = _assemble(quadrature, basis, q, keep=True)
        wi, wo, a, b, wq = (torch.cat(t) for t in zip(*kept, strict=True))
        self.wi, self.wo, self.a, self.b, self.wq = wi, wo, a, b, wq
        self.solver = _NormalSolver(M)

    @property
    def pairs(self) -> int:
        """Quadrature pairs evaluated per projection."""
        return self.wi.shape[0]

    @property
    def reached(self) -> torch.Tensor:
        """(J, 3) bool: the bands the rule reaches (the others get 0)."""
        return self.solver.reached

    def __call__(self, brdf, nonnegative: bool = True) -> torch.Tensor:
        """Coefficients (J, 3) float64 of ``brdf`` (``eval_local`` or a callable), as :func:`project`."""
        with torch.no_grad():
            wr = self.wq * _eval_rgb(brdf, self.wi, self.wo)
            r = torch.zeros(self.J, 3, dtype=torch.float64).index_add_(0, self.a, wr).index_add_(0, self.b, wr)
        return self.solver(r, nonnegative)


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
