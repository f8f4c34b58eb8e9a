"""Geometry shared by the band bases and the quotients.

The half vector and the difference angle come from :func:`torch_brdf.frame.half_terms`
(the package's one half vector, with its epsilon policy); polar angles from
:func:`torch_brdf.frame.polar_angle`. Everything here is symmetric in ``wi`` and ``wo``
bit for bit, so bases and quotients built on it are exactly reciprocal.
"""

from __future__ import annotations

import math

import torch

from ...frame import half_terms

HALF_PI = math.pi / 2


def eps(x: torch.Tensor) -> float:
    """Machine epsilon of ``x``'s dtype: the floor of cosines the quotients divide by."""
    return float(torch.finfo(x.dtype).eps)


def half_and_diff(wi: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    r"""Half vector and difference angle of :func:`~torch_brdf.frame.half_terms`, as the
    triple the bands use.

    :math:`|\omega_i + \omega_o| = 2\cos\theta_d` and :math:`|\omega_i - \omega_o| =
    2\sin\theta_d`, so :math:`\theta_d = \operatorname{atan2}(\sin\theta_d, \cos\theta_d)`
    is accurate everywhere and bitwise reciprocal.

    Args:
        wi: (*B, 3) local unit directions.
        wo: (*B, 3) local unit directions.
    Returns:
        h: (*B, 3) unit half vector (+z where undefined), cos_d: (*B,), theta_d: (*B,).
    """
    ht = half_terms(wi, wo)
    return ht.h, ht.cos_d, ht.theta_d


def log_cos_over_sin2(h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    r""":math:`\ln\cos\theta_h / \sin^2\theta_h` (-> -1/2 at the pole) and :math:`\sin^2\theta_h`
    of unit half vectors (*B, 3); (*B,) each."""
    r2 = (h[..., 0] ** 2 + h[..., 1] ** 2).clamp(0.0, 1.0 - eps(h))
    small = r2 < 1e-4
    safe = torch.where(small, torch.full_like(r2, 0.5), r2)
    ratio = torch.where(small, -0.5 - 0.25 * r2, 0.5 * torch.log1p(-safe) / safe)
    return ratio, r2


def anisotropy_ratio(h: torch.Tensor, n_u: float) -> torch.Tensor:
    r""":math:`\gamma_r = (\cos\theta_h)^{n_u\sin^2\phi_h}` (Eq. 35) for half vectors (*B, 3) -> (*B,).

    Uses :math:`\sin^2\phi_h\ln\cos\theta_h = h_y^2\,(\ln\cos\theta_h/\sin^2\theta_h)`, finite
    at the pole (:math:`\gamma_r = 1`)."""
    ratio, _ = log_cos_over_sin2(h)
    return torch.exp(n_u * h[..., 1] ** 2 * ratio)
