r"""Real spherical harmonics, rotated zonal harmonics, and ZH shading of interpolated BRDFs.

Our own tested convention (not scipy's: 1.17 removed ``sph_harm``, and ``sph_harm_y`` orders its
angles differently).
For a unit vector :math:`\omega = (x, y, z)` with polar angle :math:`\theta` from :math:`+z`
and azimuth :math:`\phi = \operatorname{atan2}(y, x)`:

.. math::
    Y_{l0} = K_l^0 P_l^0(\cos\theta),\quad
    Y_{lm} = \sqrt2 K_l^m P_l^m(\cos\theta)\cos(m\phi),\quad
    Y_{l,-m} = \sqrt2 K_l^m P_l^m(\cos\theta)\sin(m\phi)\ (m > 0),

:math:`K_l^m = \sqrt{\frac{2l+1}{4\pi}\frac{(l-m)!}{(l+m)!}}`, :math:`P_l^m` the associated
Legendre functions **with** the Condon–Shortley phase :math:`(-1)^m`. Index
:math:`i = l^2 + l + m`. Orthonormal on the sphere; addition theorem
:math:`\sum_m Y_{lm}(a) Y_{lm}(b) = \frac{2l+1}{4\pi} P_l(a\cdot b)` (both tested). These are
*local* functions of a vector: apply them to world vectors directly (the polar axis is the
vector's third component; nothing assumes world ``+y`` is up).

**Rotated ZH** (Soler, Bagher, Nowrouzezahrai 2015, "Efficient and accurate spherical kernel
integrals using isotropic decomposition"; the seed's Sec. 3.3, Eq. 9-10). A zonal harmonic
about axis :math:`a` is :math:`Y_l^0(\omega\cdot a) = \sqrt{\frac{2l+1}{4\pi}} P_l(\omega\cdot a)`.
For each band :math:`l` we fix :math:`2l+1` axes :math:`a_{lk}` (:func:`zh_axes`); band ``l``
of any function :math:`g_l = \sum_m \lambda_{lm} Y_{lm}` is then
:math:`\sum_k \mu_{lk} Y_l^0(\omega\cdot a_{lk})` with :math:`\mu_l = M_l^{-1}\lambda_l / c_l`,
:math:`M_l[m, k] = Y_{lm}(a_{lk})`, :math:`c_l = \sqrt{4\pi/(2l+1)}`. The Funk–Hecke theorem
turns the integral against lighting into a lookup of the ZH-convolved environment
:math:`C_l(a) = \int E(\omega) Y_l^0(\omega\cdot a)\,d\omega = c_l\sum_m E_{lm} Y_{lm}(a)`:

.. math:: I(n, \omega_o) = \sum_l \sum_k \mu_{lk}(\theta_o)\, C_l(R\, a_{lk}),

with :math:`R` the local-to-world rotation of the shading frame (normal :math:`n`, tangent
chosen so :math:`\omega_o` has azimuth 0: isotropic BRDFs need only :math:`\theta_o`).
:math:`\Lambda_i = [\mu_{lk}(\theta_o)]` is linear in the BRDF, so the interpolated
material's vector is :math:`\Lambda_* = b^\top \Lambda` (seed Eq. 10). Dynamic view and
lighting: only :math:`C_l` (from the env map) and the per-pixel frames change.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

from ..errors import ShapeError, ValueRangeError
from ..frame import Frame
from .data import MERLGrid, to_table


def num_coeffs(order: int) -> int:
    """(L + 1)^2 coefficients up to band ``order`` = L."""
    return (order + 1) ** 2


def sh_basis(dirs: torch.Tensor, order: int) -> torch.Tensor:
    """Real SH up to band ``order`` at unit vectors (module convention).

    Args:
        dirs: (..., 3) unit vectors. order: L >= 0.
    Returns:
        (..., (L+1)^2) in float64, index l^2 + l + m.
    """
    if order < 0:
        raise ValueRangeError(f"order must be >= 0; got {order}")
    if dirs.shape[-1] != 3:
        raise ShapeError(f"Expected dirs of shape (..., 3); got {tuple(dirs.shape)}")
    d = dirs.to(torch.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2].clamp(-1, 1)
    s = torch.sqrt((x * x + y * y).clamp_min(0))
    phi = torch.atan2(y, x)
    out = torch.zeros(*d.shape[:-1], num_coeffs(order), dtype=torch.float64)
    # P_m^m with Condon-Shortley phase: P_m^m = (-1)^m (2m-1)!! s^m
    pmm = torch.ones_like(z)
    for m in range(order + 1):
        if m > 0:
            pmm = -pmm * (2 * m - 1) * s
        plm_prev, plm = None, pmm
        for l in range(m, order + 1):
            if l == m + 1:
                plm_prev, plm = plm, z * (2 * m + 1) * pmm
            elif l > m + 1:
                plm_prev, plm = plm, ((2 * l - 1) * z * plm - (l + m - 1) * plm_prev) / (l - m)
            k = math.sqrt((2 * l + 1) / (4 * math.pi) * math.exp(math.lgamma(l - m + 1) - math.lgamma(l + m + 1)))
            if m == 0:
                out[..., l * l + l] = k * plm
            else:
                out[..., l * l + l + m] = math.sqrt(2) * k * plm * torch.cos(m * phi)
                out[..., l * l + l - m] = math.sqrt(2) * k * plm * torch.sin(m * phi)
    return out


def legendre(x: torch.Tensor, order: int) -> torch.Tensor:
    """Legendre polynomials P_0..P_L at ``x``: (..., L+1) float64."""
    x = x.to(torch.float64)
    p = [torch.ones_like(x), x]
    for l in range(2, order + 1):
        p.append(((2 * l - 1) * x * p[-1] - (l - 1) * p[-2]) / l)
    return torch.stack(p[: order + 1], -1)


def zh_axes(order: int) -> list[torch.Tensor]:
    """Fixed ZH axes per band (see :func:`_zh_axes`); cached."""
    return [a.clone() for a in _zh_axes(order)]


@functools.lru_cache(maxsize=8)
def _zh_axes(order: int) -> tuple[torch.Tensor, ...]:
    """Fixed ZH axes per band: ``2l+1`` unit vectors for band l (deterministic).

    For each band, the best-conditioned :math:`M_l` of 16 seeded random axis sets (seed = band),
    as Soler et al. 2015 recommend well-spread axes; a fixed set, so results are reproducible.
    """
    axes = []
    for l in range(order + 1):
        g = torch.Generator().manual_seed(1000 + l)
        best, best_cond = None, math.inf
        for _ in range(16):
            a = torch.nn.functional.normalize(torch.randn(2 * l + 1, 3, generator=g, dtype=torch.float64), dim=-1)
            cond = float(torch.linalg.cond(sh_basis(a, l)[:, l * l :]))
            if cond < best_cond:
                best, best_cond = a, cond
        axes.append(best)
    return tuple(axes)


def zh_matrices(order: int) -> list[torch.Tensor]:
    r"""Per band, the map :math:`\lambda_l \mapsto \mu_l = M_l^{-1}\lambda_l / c_l`: ((2l+1) x (2l+1)) each."""
    out = []
    for l, a in enumerate(zh_axes(order)):
        m = sh_basis(a, l)[:, l * l :].T  # (m, k)
        cond = float(torch.linalg.cond(m))
        if cond > 1e8:  # pragma: no cover - the spiral is fine up to high orders
            raise ValueRangeError(f"ZH axes of band {l} are degenerate (condition {cond:.1e})")
        out.append(torch.linalg.inv(m) / math.sqrt(4 * math.pi / (2 * l + 1)))
    return out


def env_sh(envmap, order: int) -> torch.Tensor:
    """SH coefficients of an :class:`~torch_brdf.scene.envmap.EnvironmentMap` (quadrature on its entries).

    :math:`E_{lm} = \\sum_t L_t Y_{lm}(\\omega_t)\\,\\Omega_t` over the map's entries (texel
    centres or bilinear nodes, :meth:`~torch_brdf.scene.envmap.EnvironmentMap.entry_directions`),
    the same discretisation as ``EnvironmentMap.irradiance``.

    Returns:
        ((L+1)^2, 3) float64, in world coordinates.
    """
    dirs = envmap.entry_directions().reshape(-1, 3)
    lo = (envmap.radiance.double() * envmap.solid_angle[..., None]).reshape(-1, 3)
    out = torch.zeros(num_coeffs(order), 3, dtype=torch.float64)
    for a in range(0, dirs.shape[0], 8192):
        out += sh_basis(dirs[a : a + 8192], order).T @ lo[a : a + 8192]
    return out


def zh_convolution(e_lm: torch.Tensor, axes: torch.Tensor, l: int) -> torch.Tensor:
    r""":math:`C_l(a) = \sqrt{4\pi/(2l+1)}\sum_m E_{lm} Y_{lm}(a)` (Funk–Hecke) at world axes (..., 3) -> (..., C)."""
    y = sh_basis(axes, l)[..., l * l : (l + 1) ** 2]
    return math.sqrt(4 * math.pi / (2 * l + 1)) * y @ e_lm[l * l : (l + 1) ** 2]


# -- per-material coefficients -------------------------------------------------------------------------
@dataclass(frozen=True)
class ZHCoefficients:
    """Rotated-ZH coefficient vectors of BRDFs, tabulated over the view elevation.

    Attributes:
        mu: (M, T, (L+1)^2, 3) float64: material, view bin, ZH coefficient (band-major, k within
            band), RGB. Linear in the BRDF: blend with ``torch.einsum("n,ntkc->tkc", b, mu)``.
        theta_o: (T,) view elevations (radians) of the bins.
        order: L.
    """

    mu: torch.Tensor
    theta_o: torch.Tensor
    order: int

    def blend(self, weights: torch.Tensor) -> torch.Tensor:
        r""":math:`\Lambda_* = b^\top\Lambda` (seed Eq. 10): (T, (L+1)^2, 3) from weights (N,)."""
        return torch.einsum("n,ntkc->tkc", torch.as_tensor(weights, dtype=torch.float64), self.mu)


def _quadrature(n_theta: int, n_phi: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Upper-hemisphere rule: Gauss-Legendre in cos(theta) on (0, 1) x midpoint in phi. (Q, 3), (Q,)."""
    import numpy as np

    xg, wg = np.polynomial.legendre.leggauss(n_theta)
    ct = torch.from_numpy(0.5 * (xg + 1))
    wt = torch.from_numpy(0.5 * wg)
    ph = (torch.arange(n_phi, dtype=torch.float64) + 0.5) * (2 * math.pi / n_phi)
    c, p = torch.meshgrid(ct, ph, indexing="ij")
    s = (1 - c * c).clamp_min(0).sqrt()
    dirs = torch.stack((s * p.cos(), s * p.sin(), c), -1).reshape(-1, 3)
    w = (wt[:, None] * (2 * math.pi / n_phi)).expand(n_theta, n_phi).reshape(-1)
    return dirs, w


def zh_coefficients(
    brdf, order: int, n_view: int = 16, n_theta: int = 64, n_phi: int = 128, max_view_deg: float = 89.0
) -> ZHCoefficients:
    r"""Rotated-ZH vectors :math:`\Lambda` of one or more isotropic BRDFs.

    For each view elevation :math:`\theta_o` (``n_view`` values uniform in :math:`[0, \text{max}]`)
    the transfer :math:`g(\omega) = \rho(\omega, \omega_o)\cos^+\theta` is projected on the SH by
    quadrature over the upper hemisphere (Gauss–Legendre in :math:`\cos\theta`), then turned into
    ZH coefficients (:func:`zh_matrices`).

    Args:
        brdf: callable ``f(wi, wo) -> (M, Q, 3)`` for local directions wi (Q, 3), wo (3,) (e.g.
            :func:`rows_brdf`), returning M materials at once.
        order: L. n_view: T. n_theta, n_phi: quadrature resolution.
    Returns:
        :class:`ZHCoefficients` with mu (M, T, (L+1)^2, 3).
    """
    if n_view < 2:
        raise ValueRangeError(f"n_view must be >= 2; got {n_view}")
    dirs, w = _quadrature(n_theta, n_phi)
    yw = sh_basis(dirs, order) * w[:, None]  # (Q, K)
    mats = zh_matrices(order)
    theta_o = torch.linspace(0, math.radians(max_view_deg), n_view, dtype=torch.float64)
    mus = []
    for t in theta_o:
        wo = torch.stack((t.sin(), torch.zeros(()), t.cos())).to(torch.float64)
        f = torch.as_tensor(brdf(dirs, wo), dtype=torch.float64)  # (M, Q, 3)
        lam = torch.einsum("mqc,qk->mkc", f * dirs[None, :, 2:3], yw)  # SH coefficients
        mu = torch.cat(
            [torch.einsum("mk,nkc->nmc", mats[l], lam[:, l * l : (l + 1) ** 2]) for l in range(order + 1)], 1
        )
        mus.append(mu)
    return ZHCoefficients(torch.stack(mus, 1), theta_o, order)


def rows_brdf(z: torch.Tensor, grid: MERLGrid):
    """A batched BRDF callable for :func:`zh_coefficients` from rows of ``Z`` (MERL nearest lookup on ``grid``).

    Linear in the rows (negative values of interpolants included).
    """
    from ..frame import half_diff_angles
    from ..io.merl import merl_indices

    tables = torch.stack([to_table(r, grid, missing=0.0) for r in torch.as_tensor(z, dtype=torch.float64)])
    kept = [torch.as_tensor(k) for k in grid.indices]

    def f(wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        th, _, td, pd = half_diff_angles(wi, wo.expand_as(wi))
        pos = [
            (torch.searchsorted(k, i.contiguous(), right=True) - 1).clamp_min(0)
            for i, k in zip(merl_indices(th, td, pd), kept, strict=True)
        ]
        return tables[:, :, pos[0], pos[1], pos[2]].permute(0, 2, 1)  # (M, Q, 3)

    return f


# -- shading ---------------------------------------------------------------------------------------------
def _frames(normals: torch.Tensor, views: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation R (P, 3, 3) local->world (columns t, b, n; view at azimuth 0) and cos(theta_o) (P,).

    The tangent is the view's component in the tangent plane (:meth:`Frame.from_normal`). A view
    along the normal has none; then the x axis (the y axis for normals near it) is used, the
    tangent the ZH tables were validated with: the truncated ZH expansion is not exactly zonal,
    so this choice, arbitrary in principle, changes the shading at the percent level."""
    n = torch.nn.functional.normalize(normals.double(), dim=-1)
    v = torch.nn.functional.normalize(views.double(), dim=-1)
    cos_o = (n * v).sum(-1)
    along = (v - cos_o[:, None] * n).norm(dim=-1, keepdim=True) <= math.sqrt(torch.finfo(n.dtype).eps)
    axis = torch.where(n[:, :1].abs() < 0.9, torch.tensor([1.0, 0, 0], dtype=n.dtype), torch.tensor([0, 1.0, 0]))
    return Frame.from_normal(n, torch.where(along, axis, v)).matrix().transpose(-1, -2), cos_o


def zh_shade(
    normals: torch.Tensor, views: torch.Tensor, lam: torch.Tensor, theta_o: torch.Tensor, e_lm: torch.Tensor, order: int
) -> torch.Tensor:
    r"""Shade points with a rotated-ZH BRDF vector under SH lighting (seed Eq. 9).

    Exact evaluation of :math:`C_l` at the rotated axes (no texture lookup); linear
    interpolation of :math:`\mu` in :math:`\theta_o`; 0 where the view is below the horizon.

    Args:
        normals: (P, 3) world normals and directions towards the eye.
        views: as ``normals``.
        lam: (T, (L'+1)^2, 3) a material's (or a blend's) ZH vector, L' >= order.
        theta_o: (T,) its view bins. e_lm: ((L''+1)^2, 3) lighting SH, L'' >= order.
        order: L, the shading order (<= both).
    Returns:
        (P, 3) float64 outgoing radiance.
    """
    if lam.shape[1] < num_coeffs(order) or e_lm.shape[0] < num_coeffs(order):
        raise ValueRangeError(f"order {order} exceeds the coefficients given ({lam.shape[1]}, {e_lm.shape[0]})")
    rot, cos_o = _frames(normals, views)
    th = torch.arccos(cos_o.clamp(-1, 1))
    tq = theta_o.double()
    u = ((th - tq[0]) / (tq[-1] - tq[0]) * (tq.numel() - 1)).clamp(0, tq.numel() - 1)
    i0 = u.floor().long().clamp_max(tq.numel() - 2)
    a1 = (u - i0)[:, None, None]
    mu = (1 - a1) * lam[i0, : num_coeffs(order)] + a1 * lam[i0 + 1, : num_coeffs(order)]  # (P, K, 3)
    out = torch.zeros(normals.shape[0], 3, dtype=torch.float64)
    for l, ax in enumerate(zh_axes(order)):
        world = torch.einsum("pij,kj->pki", rot, ax)  # (P, 2l+1, 3)
        c = zh_convolution(e_lm, world, l)  # (P, 2l+1, 3)
        out += (mu[:, l * l : (l + 1) ** 2] * c).sum(1)
    return torch.where((cos_o > 0)[:, None], out, torch.zeros_like(out))
