r"""Spherical radial basis functions on the half vector (Iwasaki et al., Sec. 3.2 and 5).

Iwasaki et al. write the specular term as Ashikhmin's distribution-based BRDF (their
Eq. 11) with the half-vector distribution expanded in Gaussian SRBFs (Eq. 12):

.. math::
    p(h) = \sum_k c_k\, G(h; \xi_k, \lambda), \qquad G(h; \xi, \lambda) = e^{\lambda(h\cdot\xi - 1)},

non-negative for :math:`c_k \ge 0` (their Eq. 18), with one centre per pixel of a
:math:`3\times7\times7 = 147` hemicube and spread :math:`\sigma = \pi/40`.

Centres (:func:`hemicube_centers`). A hemicube (Cohen and Greenberg 1985) is the top face of
a cube around the shading point plus the upper halves of the four side faces: area
:math:`1 + 4\cdot\frac12 = 3` faces, hence :math:`3n^2` pixels for an :math:`n\times n`
face. For odd :math:`n` (the paper's 7) the horizon cuts the middle pixel row of every side
face in half; we keep the :math:`(n-1)/2` full rows of each side face and divide the
remaining half-row strip around the cube (perimeter 8, height :math:`1/n` for a cube of
half-size 1) into :math:`2n` cells of one pixel's area (two pixels wide), centred at
mid-height. That reproduces exactly :math:`3n^2` equal-area pixels (147 for n = 7); for
even :math:`n` no strip is left and the count is :math:`3n^2` as well. Centres are the
normalised pixel centres.

Bandwidth (:func:`lambda_from_sigma`). The paper's relation, printed as
":math:`\sigma^2 = 1 - (\cosh(2\lambda) - (2\lambda)^{-1})`" (Narcowich and Ward 1996), cannot
be right as printed (:math:`\cosh 2\lambda \ge 1` makes :math:`\sigma^2 < 0`); with
:math:`\coth` it is the spherical variance of the SRBF:

.. math:: \sigma^2 = 1 - \Big(\coth 2\lambda - \frac{1}{2\lambda}\Big).

Derivation: Narcowich and Ward measure the spread of a function :math:`G` on :math:`S^2`
through the probability density :math:`|G|^2/\|G\|^2`; for :math:`G = e^{\lambda(h\cdot\xi-1)}`
that is a von Mises-Fisher density with concentration :math:`\kappa = 2\lambda`, whose mean
resultant length is :math:`\|\mathbb E[h]\| = \int e^{\kappa t}t\,dt/\int e^{\kappa t}dt =
\coth\kappa - 1/\kappa` (:math:`t = h\cdot\xi \in [-1, 1]`), and the spherical variance is
one minus it. For large :math:`\lambda`, :math:`\sigma^2 \approx 1/(2\lambda)`, so
:math:`\sigma = \pi/40` gives :math:`\lambda \approx 81.06` (half maximum at
:math:`7.5^\circ` from the centre, against a centre spacing of about :math:`16^\circ` at
n = 7 -- neighbouring lobes overlap at about a quarter of their peak). The relation is
checked numerically in the tests.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from .._checks import as_float_tensor
from ..errors import ShapeError, ValueRangeError
from ..frame import orthonormal_basis
from .analytic import HalfVectorDistribution
from .base import Clamped

__all__ = [
    "SRBFBasis",
    "SRBFDistribution",
    "hemicube_centers",
    "lambda_from_sigma",
    "sigma_from_lambda",
]


# --------------------------------------------------------------------------------------------
# bandwidth
# --------------------------------------------------------------------------------------------
def _coth_minus_inv(x: float) -> float:
    r""":math:`\coth x - 1/x` (the vMF mean resultant length), stable for small and large x."""
    if x < 1e-3:
        return x / 3 - x**3 / 45
    if x > 20:
        return 1.0 + 2 * math.exp(-2 * x) - 1 / x
    return 1 / math.tanh(x) - 1 / x


def sigma_from_lambda(lam: float) -> float:
    r"""Spread :math:`\sigma = \sqrt{1 - (\coth 2\lambda - 1/(2\lambda))}` of the Gaussian SRBF
    :math:`e^{\lambda(h\cdot\xi-1)}` (see the module docstring)."""
    if not lam > 0:
        raise ValueRangeError(f"lambda must be > 0; got {lam}")
    return math.sqrt(max(0.0, 1 - _coth_minus_inv(2 * lam)))


def lambda_from_sigma(sigma: float) -> float:
    r"""Bandwidth :math:`\lambda` with :math:`1 - (\coth 2\lambda - 1/(2\lambda)) = \sigma^2`
    (bisection in :math:`\log\lambda`, float64; the left side decreases monotonically from
    1 to 0).

    Args:
        sigma: spread in (0, 1).
    Returns:
        lambda > 0 (81.06 for the paper's :math:`\sigma = \pi/40`).
    """
    if not 0 < sigma < 1:
        raise ValueRangeError(f"sigma must lie in (0, 1); got {sigma}")
    target = sigma * sigma
    lo, hi = math.log(1e-8), math.log(1e12)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if 1 - _coth_minus_inv(2 * math.exp(mid)) > target:
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))


# --------------------------------------------------------------------------------------------
# centres
# --------------------------------------------------------------------------------------------
def hemicube_centers(n: int = 7) -> torch.Tensor:
    r"""Unit directions of the :math:`3n^2` pixels of an :math:`n\times n` hemicube
    (layout in the module docstring): the top face first (row-major in :math:`(y, x)`), then
    the full rows of the side faces :math:`+x, +y, -x, -y`, then the horizon strip.

    Args:
        n: face resolution (>= 1).
    Returns:
        (3 n^2, 3) float64, all with :math:`z > 0`.
    """
    if n < 1:
        raise ValueRangeError(f"hemicube resolution must be >= 1; got {n}")
    c = -1 + (2 * torch.arange(n, dtype=torch.float64) + 1) / n  # pixel centres on a face
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    pts = [torch.stack((xx.reshape(-1), yy.reshape(-1), torch.ones(n * n, dtype=torch.float64)), -1)]
    rows = n // 2
    zc = 1 - (2 * torch.arange(rows, dtype=torch.float64) + 1) / n  # full rows, top down
    zz, ss = torch.meshgrid(zc, c, indexing="ij")
    zz, ss = zz.reshape(-1), ss.reshape(-1)
    one = torch.ones_like(zz)
    pts += [
        torch.stack((one, ss, zz), -1),  # +x face, tangent coordinate y
        torch.stack((-ss, one, zz), -1),  # +y face
        torch.stack((-one, -ss, zz), -1),  # -x face
        torch.stack((ss, -one, zz), -1),  # -y face
    ]
    if n % 2 == 1:  # horizon strip [0, 1/n] of height half a pixel: 2n cells two pixels long
        cells = 2 * n
        s = (torch.arange(cells, dtype=torch.float64) + 0.5) * (8.0 / cells)  # arc length along the perimeter
        # start at the middle of the +x face, counter-clockwise; corners at s = 1, 3, 5, 7
        side = torch.floor((s + 1) / 2).remainder(4)
        t = (s + 1) - 2 * torch.floor((s + 1) / 2) - 1  # in [-1, 1) along the side
        x = torch.where(side == 0, 1.0, torch.where(side == 1, -t, torch.where(side == 2, -1.0, t)))
        y = torch.where(side == 0, t, torch.where(side == 1, 1.0, torch.where(side == 2, -t, -1.0)))
        pts.append(torch.stack((x, y, torch.full_like(x, 0.5 / n)), -1))
    p = torch.cat(pts)
    return p / p.norm(dim=-1, keepdim=True)


# --------------------------------------------------------------------------------------------
# the basis
# --------------------------------------------------------------------------------------------
def _check_h(h: torch.Tensor) -> torch.Tensor:
    if not isinstance(h, torch.Tensor) or h.ndim < 1 or h.shape[-1] != 3 or not h.is_floating_point():
        got = f"{tuple(h.shape)} {h.dtype}" if isinstance(h, torch.Tensor) else repr(type(h))
        raise ShapeError(f"Expected half vectors to be a floating tensor of shape (..., 3); got {got}")
    return h


class SRBFBasis(nn.Module):
    r"""Gaussian SRBFs :math:`G_k(h) = e^{\lambda(h\cdot\xi_k - 1)}` (Iwasaki Eq. 12).

    Args:
        centers: (K, 3) centre directions (normalised here); default :func:`hemicube_centers`.
        n: hemicube resolution for the default centres (7 -> K = 147).
        sigma: spread; :math:`\lambda` = :func:`lambda_from_sigma` (default :math:`\pi/40`).
        bandwidth: :math:`\lambda` directly (overrides ``sigma``).
    """

    def __init__(self, centers=None, n: int = 7, sigma: float = math.pi / 40, bandwidth: float | None = None):
        super().__init__()
        xi = hemicube_centers(n) if centers is None else as_float_tensor(centers, "centers", torch.float64)
        if xi.ndim != 2 or xi.shape[-1] != 3 or xi.shape[0] < 1:
            raise ShapeError(f"Expected centers to have shape (K, 3); got {tuple(xi.shape)}")
        self.register_buffer("centers", xi / xi.norm(dim=-1, keepdim=True))
        self.bandwidth = float(bandwidth) if bandwidth is not None else lambda_from_sigma(sigma)
        if not self.bandwidth > 0:
            raise ValueRangeError(f"bandwidth must be > 0; got {self.bandwidth}")
        # the normalisation integrals depend only on the centres and lambda: computed once
        self.register_buffer("integral_cos", self._integrals(True, 256), persistent=False)
        self.register_buffer("integral", self._integrals(False, 256), persistent=False)

    @property
    def K(self) -> int:
        return self.centers.shape[0]

    def _apply(self, fn, recurse=True):
        # centres and integrals stay float64 under .to(dtype): lambda ~ 81 amplifies their rounding
        super()._apply(fn, recurse)
        for name in ("centers", "integral_cos", "integral"):
            t = getattr(self, name)
            if t.dtype != torch.float64:
                setattr(self, name, t.to(torch.float64))
        return self

    def extra_repr(self) -> str:
        return f"K={self.K}, bandwidth={self.bandwidth:.6g}, sigma={sigma_from_lambda(self.bandwidth):.6g}"

    def eval(self, h: torch.Tensor | None = None) -> torch.Tensor:
        """Basis values :math:`G_k(h)` for unit vectors h (*B, 3) -> (*B, K), in h's dtype.

        (Like :meth:`BRDF.eval`, this shadows ``nn.Module.eval``; called without arguments it
        still switches the module to evaluation mode and returns it.)"""
        if h is None:
            return super().eval()
        h = _check_h(h)
        # float64 inside: lambda ~ 81 amplifies the rounding of h . xi (and float32 matmuls
        # round differently for different batch sizes)
        xi = self.centers.to(device=h.device, dtype=torch.float64)
        dot = h.to(torch.float64) @ xi.T
        return torch.exp(self.bandwidth * (dot - 1)).to(h.dtype)

    def integrals(self, cosine: bool = True, cells: int = 256) -> torch.Tensor:
        """See :meth:`_integrals` (cached for the default ``cells``)."""
        if cells == 256:
            return (self.integral_cos if cosine else self.integral).double()
        return self._integrals(cosine, cells)

    def _integrals(self, cosine: bool = True, cells: int = 256) -> torch.Tensor:
        r"""Hemisphere integrals :math:`\int_{h_z > 0} G_k(h)\,(h\cdot n)\,d\omega_h` (or without
        the cosine): (K,) float64.

        With :math:`\alpha_k` the polar angle of :math:`\xi_k`, the azimuthal integral is a
        Bessel function, :math:`\int_0^{2\pi} e^{x\cos\phi}d\phi = 2\pi I_0(x)`, so

        .. math:: \int_{H^+} G_k\,(h\cdot n)\,d\omega = 2\pi\int_0^{\pi/2}
                  e^{\lambda(\cos(\theta-\alpha_k)-1)}\,\tilde I_0(\lambda\sin\alpha_k\sin\theta)
                  \cos\theta\sin\theta\,d\theta

        with the scaled :math:`\tilde I_0(x) = e^{-x}I_0(x)` (every exponent <= 0), evaluated by
        composite Gauss-Legendre (``cells`` x 8 nodes; exact to rounding for the lobes
        here). Closed forms: at the pole, :math:`2\pi((\lambda - 1) + e^{-\lambda})/\lambda^2`
        (with cosine) and :math:`2\pi(1 - e^{-\lambda})/\lambda`; over the whole sphere
        without cosine, :math:`2\pi(1 - e^{-2\lambda})/\lambda` for every centre.
        """
        x, w = np.polynomial.legendre.leggauss(8)
        e = torch.linspace(0, math.pi / 2, cells + 1, dtype=torch.float64)
        width = (e[1:] - e[:-1])[:, None]
        th = (e[:-1, None] + width * torch.from_numpy(0.5 * (x + 1))).reshape(-1)
        wt = (width * torch.from_numpy(0.5 * w)).reshape(-1)
        alpha = torch.acos(self.centers[:, 2].double().clamp(-1, 1))[:, None]
        lam = self.bandwidth
        arg = lam * torch.sin(alpha) * torch.sin(th)
        f = torch.exp(lam * (torch.cos(th - alpha) - 1)) * torch.special.i0e(arg) * torch.sin(th)
        if cosine:
            f = f * torch.cos(th)
        return 2 * math.pi * (f * wt).sum(-1)


# --------------------------------------------------------------------------------------------
# the distribution p(h)
# --------------------------------------------------------------------------------------------
class SRBFDistribution(HalfVectorDistribution):
    r"""A half-vector distribution :math:`p(h) = \sum_k c_k G_k(h)` on the upper hemisphere
    (zero for :math:`h_z \le 0`), pluggable as the :math:`p(h)` of a distribution-based BRDF
    (:class:`~torch_brdf.brdf.analytic.DistributionBased`: a module mapping (*B, 3) to (*B,) or
    (*B, C), with its sampler protocol ``sample_h``, ``pdf_h``, ``albedo_scale``).

    ``coefficients`` (K,) gives a scalar :math:`p`; (K, C) an RGB one. They are stored raw
    (``raw_coefficients``) behind ``Clamped(0, inf)`` and exposed as ``coefficients``, so
    :math:`p \ge 0` always (Iwasaki Eq. 18) while gradients flow to the raw values.

    Args:
        basis: an :class:`SRBFBasis` (default: 147 hemicube centres, :math:`\sigma = \pi/40`).
        coefficients: (K,) or (K, C); default a constant with :math:`\int p\,(h\cdot n)\,
            d\omega_h = 1/4` (:meth:`normalization`), i.e. :math:`p = D/4` for a unit-normalised
            microfacet :math:`D` -- the convention of ``DistributionBased`` (Iwasaki's Eq. 11
            folds the 4 into :math:`p`), so ``albedo_scale() == 1``.
    """

    #: p depends on the azimuth of h (the hemicube centres are not rotation invariant)
    anisotropic = True

    def __init__(self, basis: SRBFBasis | None = None, coefficients=None):
        super().__init__()
        self.basis = basis if basis is not None else SRBFBasis()
        if coefficients is None:
            c = torch.full((self.basis.K,), 0.25, dtype=torch.float64) / float(self.basis.integrals().sum())
        else:
            c = as_float_tensor(coefficients, "coefficients", torch.float64)
        if c.ndim not in (1, 2) or c.shape[0] != self.basis.K:
            want = f"({self.basis.K},) or ({self.basis.K}, C)"
            raise ShapeError(f"Expected coefficients of shape {want}; got {tuple(c.shape)}")
        if bool((c < 0).any()) or not bool(torch.isfinite(c).all()):
            raise ValueRangeError("SRBF coefficients must be finite and >= 0")
        self.register_constrained("coefficients", c, Clamped(0.0, math.inf), shape=tuple(c.shape))

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        """:math:`p(h)` for local unit half vectors (*B, 3) -> (*B,) or (*B, C) (summed in
        float64, returned in h's dtype)."""
        h = _check_h(h)
        g = self.basis.eval(h.to(torch.float64))
        p = g @ self.coefficients.to(torch.float64)
        up = h[..., 2] > 0
        p = torch.where(up if p.ndim == up.ndim else up.unsqueeze(-1), p, torch.zeros((), dtype=p.dtype))
        return p.to(h.dtype)

    def normalization(self) -> torch.Tensor:
        r""":math:`\int_{H^+} p(h)\,(h\cdot n)\,d\omega_h = \sum_k c_k I_k`: () or (C,), float64;
        1 for a normalised microfacet distribution."""
        c = self.coefficients.double()
        i = self.basis.integrals().to(c.device)
        return (c * (i if c.ndim == 1 else i[:, None])).sum(0)

    def normalized(self) -> SRBFDistribution:
        """A copy with :math:`c / \\int p\\,(h\\cdot n)` (per channel)."""
        c = self.coefficients.detach().double()
        return SRBFDistribution(self.basis, c / self.normalization().clamp_min(1e-300))

    # -- sampling -----------------------------------------------------------------------------
    def _mixture(self) -> torch.Tensor:
        """Lobe probabilities (K,) float64, differentiable in the coefficients."""
        c = self.coefficients.double()
        w = c if c.ndim == 1 else c.mean(-1)
        tot = w.sum()
        if not float(tot.detach()) > 0:
            raise ValueRangeError("cannot sample an SRBF distribution whose coefficients are all zero")
        return w / tot

    def _vmf(self, cos: torch.Tensor) -> torch.Tensor:
        lam = self.basis.bandwidth
        return lam / (2 * math.pi * -math.expm1(-2 * lam)) * torch.exp(lam * (cos - 1))

    def sample(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        r"""Draw half vectors from the folded vMF mixture.

        Lobe :math:`k` is chosen with probability :math:`\pi_k \propto \bar c_k` (every
        :math:`G_k` has the same full-sphere integral, so this is :math:`p` normalised over
        the sphere); :math:`h` is drawn from the von Mises-Fisher density with mean
        :math:`\xi_k` and :math:`\kappa = \lambda` (:math:`\propto G_k`; Jakob's stable
        inversion :math:`w = 1 + \ln(u + (1-u)e^{-2\kappa})/\kappa`), and a sample below the
        horizon is mirrored to :math:`(h_x, h_y, -h_z)`. The exact density on the upper
        hemisphere is (:meth:`pdf`)

        .. math:: q(h) = \sum_k \pi_k\,[v_k(h) + v_k(\tilde h)], \quad
                  v_k(h) = \frac{\lambda e^{\lambda(h\cdot\xi_k - 1)}}{2\pi(1 - e^{-2\lambda})},

        which integrates to 1 and equals :math:`p/\int p` away from the horizon.

        Args:
            u: (*B, 2) uniforms in [0, 1) (the first also selects the lobe, rescaled).
        Returns:
            h: (*B, 3) unit vectors with :math:`h_z \ge 0`; pdf: (*B,) solid-angle density.
        """
        if u.shape[-1] != 2:
            raise ShapeError(f"Expected u to have shape (..., 2); got {tuple(u.shape)}")
        pi = self._mixture().detach().to(u.dtype)
        cdf = torch.cumsum(pi, 0)
        cdf[-1] = 1.0
        u0, u1 = u[..., 0], u[..., 1]
        k = torch.searchsorted(cdf, u0.contiguous(), right=True).clamp_max(pi.numel() - 1)
        last = int(torch.nonzero(pi > 0)[-1])
        k = torch.where(pi[k] > 0, k, torch.full_like(k, last))
        lo = torch.where(k > 0, cdf[(k - 1).clamp_min(0)], torch.zeros_like(u0))
        v = ((u0 - lo) / pi[k]).clamp(0.0, 1.0)
        lam = self.basis.bandwidth
        w = 1 + torch.log(v + (1 - v) * math.exp(-2 * lam)) / lam
        w = w.clamp(-1.0, 1.0)
        r = (1 - w * w).clamp_min(0).sqrt()
        phi = 2 * math.pi * u1
        xi = self.basis.centers.to(u.dtype)[k]
        s, t = orthonormal_basis(xi)
        h = w.unsqueeze(-1) * xi + (r * torch.cos(phi)).unsqueeze(-1) * s + (r * torch.sin(phi)).unsqueeze(-1) * t
        h = h / h.norm(dim=-1, keepdim=True)
        h = torch.cat([h[..., :2], h[..., 2:].abs()], -1)
        return h, self.pdf(h)

    def pdf(self, h: torch.Tensor) -> torch.Tensor:
        """Density (*B,) of :meth:`sample` at unit half vectors h (*B, 3) (0 below the horizon)."""
        h = _check_h(h)
        pi = self._mixture()
        used = torch.nonzero(pi.detach() > 0)[:, 0]  # only the lobes in use
        pi, xi = pi[used], self.basis.centers.to(torch.float64)[used]
        h64 = h.to(torch.float64)
        mirror = h64 * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
        q = (self._vmf(h64 @ xi.T) + self._vmf(mirror @ xi.T)) @ pi
        return torch.where(h[..., 2] >= 0, q, torch.zeros_like(q)).to(h.dtype)

    # -- the sampler protocol of analytic.DistributionBased ------------------------------------
    def sample_h(self, u: torch.Tensor) -> torch.Tensor:
        """Half vectors (*B, 3) from :meth:`sample` (the ``DistributionBased`` protocol)."""
        return self.sample(u)[0]

    def pdf_h(self, h: torch.Tensor) -> torch.Tensor:
        """Their density (*B,) (:meth:`pdf`)."""
        return self.pdf(h)

    def albedo_scale(self) -> torch.Tensor:
        r""":math:`4\int p(h)(h\cdot n)\,d\omega_h` (channel mean): the specular albedo at normal
        incidence of a distribution-based BRDF without Fresnel, a () tensor."""
        return 4 * self.normalization().mean().to(self.raw_coefficients.dtype)

    # -- fitting ------------------------------------------------------------------------------
    @classmethod
    def fit(cls, target, basis: SRBFBasis | None = None, n_theta: int = 96, n_phi: int = 96) -> SRBFDistribution:
        r"""Non-negative least squares fit of a half-vector distribution (Iwasaki Eq. 18's
        :math:`c \ge 0`) on the upper hemisphere, weighting by :math:`\cos\theta_h\,d\omega_h`:

        .. math:: \min_{c \ge 0}\int_{H^+}\Big(\sum_k c_k G_k(h) - p^*(h)\Big)^2\cos\theta_h\,d\omega_h,

        by a midpoint quadrature (``n_theta`` rings uniform in :math:`\theta_h^{1/2}`, so dense
        near the pole, times ``n_phi`` azimuths) and ``scipy.optimize.nnls`` per channel.

        Args:
            target: callable h (N, 3) float64 -> (N,) or (N, C).
            basis: the SRBFs (default :class:`SRBFBasis`).
        Returns:
            An :class:`SRBFDistribution` with (K,) or (K, C) coefficients.
        """
        from scipy.optimize import nnls

        basis = basis if basis is not None else SRBFBasis()
        t = (torch.arange(n_theta, dtype=torch.float64) + 0.5) / n_theta
        th = (math.pi / 2) * t**2
        dth = (math.pi / 2) * 2 * t / n_theta
        ph = (torch.arange(n_phi, dtype=torch.float64) + 0.5) * (2 * math.pi / n_phi)
        T, P = torch.meshgrid(th, ph, indexing="ij")
        h = torch.stack((torch.sin(T) * torch.cos(P), torch.sin(T) * torch.sin(P), torch.cos(T)), -1).reshape(-1, 3)
        w = (torch.sin(T) * torch.cos(T) * dth[:, None] * (2 * math.pi / n_phi)).reshape(-1)
        with torch.no_grad():
            y = torch.as_tensor(target(h), dtype=torch.float64)
        y2 = y[:, None] if y.ndim == 1 else y
        A = basis.eval(h) * w.sqrt()[:, None]
        cols = [nnls(A.numpy(), (y2[:, j] * w.sqrt()).numpy(), maxiter=50 * basis.K)[0] for j in range(y2.shape[1])]
        c = torch.from_numpy(np.stack(cols, -1))
        return cls(basis, c[:, 0] if y.ndim == 1 else c)
