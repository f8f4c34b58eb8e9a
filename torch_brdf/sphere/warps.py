r"""Sampling warps: maps from the unit square to the sphere, hemisphere, disk and triangle.

Every warp takes ``u``: (N, 2) uniforms in :math:`[0, 1)^2` and returns samples in
``u``'s dtype and device; every pdf is a density with respect to the measure of the target
domain (solid angle for directions, area for the disk). Hemispheres are in the local frame
with :math:`z` = normal (the package's shading-frame convention). The formulas follow Mitsuba 3's
``warp`` module and pbrt-v4 (section A.5).
"""

from __future__ import annotations

import math

import torch

from ..errors import ShapeError

__all__ = [
    "cosine_hemisphere_pdf",
    "cosine_power_hemisphere_pdf",
    "square_to_cosine_hemisphere",
    "square_to_cosine_power_hemisphere",
    "square_to_uniform_disk_concentric",
    "square_to_uniform_hemisphere",
    "square_to_uniform_sphere",
    "square_to_uniform_triangle",
    "uniform_hemisphere_pdf",
    "uniform_sphere_pdf",
]


def _check_u(u: torch.Tensor) -> torch.Tensor:
    if not isinstance(u, torch.Tensor) or u.ndim != 2 or u.shape[1] != 2 or not u.is_floating_point():
        got = f"{tuple(u.shape)} {u.dtype}" if isinstance(u, torch.Tensor) else repr(type(u))
        raise ShapeError(f"Expected u to be a floating tensor of shape (N, 2); got {got}")
    return u


def square_to_uniform_sphere(u: torch.Tensor) -> torch.Tensor:
    r"""Uniform directions on the unit sphere (Archimedes: :math:`z = 1 - 2u_0` is uniform).

    Args:
        u: (N, 2) uniforms in [0, 1).
    Returns:
        (N, 3) unit vectors with density :math:`1/(4\pi)`.
    """
    _check_u(u)
    z = 1 - 2 * u[:, 0]
    r = (1 - z * z).clamp_min(0).sqrt()
    phi = (2 * math.pi) * u[:, 1]
    return torch.stack([r * phi.cos(), r * phi.sin(), z], dim=-1)


def uniform_sphere_pdf(v: torch.Tensor) -> torch.Tensor:
    r"""Density :math:`1/(4\pi)` of :func:`square_to_uniform_sphere`: (N, 3) -> (N,)."""
    return v.new_full(v.shape[:-1], 1 / (4 * math.pi))


def square_to_uniform_hemisphere(u: torch.Tensor) -> torch.Tensor:
    r"""Uniform directions on the hemisphere :math:`z \ge 0` (:math:`z = 1 - u_0`).

    Args:
        u: (N, 2) uniforms in [0, 1).
    Returns:
        (N, 3) unit vectors with :math:`z > 0` and density :math:`1/(2\pi)`.
    """
    _check_u(u)
    z = 1 - u[:, 0]
    r = (1 - z * z).clamp_min(0).sqrt()
    phi = (2 * math.pi) * u[:, 1]
    return torch.stack([r * phi.cos(), r * phi.sin(), z], dim=-1)


def uniform_hemisphere_pdf(v: torch.Tensor) -> torch.Tensor:
    r"""Density of :func:`square_to_uniform_hemisphere`, :math:`1/(2\pi)` where z >= 0.

    Args:
        v: (N, 3) directions.
    Returns:
        (N,) pdf in ``v``'s dtype.
    """
    return torch.where(v[..., 2] >= 0, 1 / (2 * math.pi), 0.0).to(v.dtype)


def square_to_uniform_disk_concentric(u: torch.Tensor) -> torch.Tensor:
    r"""Shirley-Chiu concentric map of the square onto the unit disk (area-preserving).

    Shirley and Chiu, "A low distortion map between disk and square", JGT 1997; the
    branch-free form of pbrt-v4 ``SampleUniformDiskConcentric``.

    Args:
        u: (N, 2) uniforms in [0, 1).
    Returns:
        (N, 2) points in the unit disk with area density :math:`1/\pi`.
    """
    _check_u(u)
    a, b = 2 * u[:, 0] - 1, 2 * u[:, 1] - 1
    first = a.abs() > b.abs()
    r = torch.where(first, a, b)
    safe = torch.where(r == 0, torch.ones_like(r), r)
    phi = torch.where(first, (math.pi / 4) * (b / safe), (math.pi / 2) - (math.pi / 4) * (a / safe))
    return torch.stack([r * phi.cos(), r * phi.sin()], dim=-1)


def square_to_cosine_hemisphere(u: torch.Tensor) -> torch.Tensor:
    r"""Cosine-weighted directions on :math:`z \ge 0` by Malley's method.

    A concentric disk sample projected up to the hemisphere has solid-angle density
    :math:`\cos\theta/\pi` (pbrt-v4, section A.5.3).

    Args:
        u: (N, 2) uniforms in [0, 1).
    Returns:
        (N, 3) unit vectors with :math:`z \ge 0`; density :func:`cosine_hemisphere_pdf`.
    """
    p = square_to_uniform_disk_concentric(u)
    z = (1 - (p * p).sum(-1)).clamp_min(0).sqrt()
    return torch.cat([p, z[:, None]], dim=-1)


def cosine_hemisphere_pdf(cos_theta: torch.Tensor) -> torch.Tensor:
    r"""Density :math:`\max(0,\cos\theta)/\pi` of :func:`square_to_cosine_hemisphere`.

    Args:
        cos_theta: (N,) z components of the directions.
    Returns:
        (N,) solid-angle pdf.
    """
    return cos_theta.clamp_min(0) * (1 / math.pi)


def square_to_cosine_power_hemisphere(u: torch.Tensor, exponent: torch.Tensor | float) -> torch.Tensor:
    r"""Directions on :math:`z \ge 0` with the cosine-power (Blinn/Phong lobe) density
    :math:`\frac{n+1}{2\pi}\cos^n\theta` (pbrt-v3 13.6.3; Lafortune & Willems 1994):
    :math:`\cos\theta = (1-u_0)^{1/(n+1)}`, :math:`\phi = 2\pi u_1`, with
    :math:`\sin^2\theta = -\mathrm{expm1}(2\log(1-u_0)/(n+1))` for accuracy at large
    :math:`n`. The one Blinn lobe sampler of the package: half vectors with density
    :math:`D_n(h)\cos\theta_h` of the Blinn distribution are this warp with exponent
    :math:`n + 1`.

    Unlike the other warps it takes any batch shape (the BRDFs sample per query).

    Args:
        u: (*B, 2) uniforms in [0, 1).
        exponent: () or (*B,) :math:`n \ge 0`.
    Returns:
        (*B, 3) unit vectors; density :func:`cosine_power_hemisphere_pdf`.
    """
    if not isinstance(u, torch.Tensor) or u.ndim < 1 or u.shape[-1] != 2 or not u.is_floating_point():
        got = f"{tuple(u.shape)} {u.dtype}" if isinstance(u, torch.Tensor) else repr(type(u))
        raise ShapeError(f"Expected u to be a floating tensor of shape (..., 2); got {got}")
    log_u = torch.log((1.0 - u[..., 0]).clamp(torch.finfo(u.dtype).tiny, 1.0))
    sin2 = (-torch.expm1(2.0 * log_u / (exponent + 1.0))).clamp(0.0, 1.0)
    st = sin2.sqrt()
    phi = (2 * math.pi) * u[..., 1]
    return torch.stack((st * torch.cos(phi), st * torch.sin(phi), (1.0 - sin2).sqrt()), -1)


def cosine_power_hemisphere_pdf(cos_theta: torch.Tensor, exponent: torch.Tensor | float) -> torch.Tensor:
    r"""Density :math:`\frac{n+1}{2\pi}\max(0,\cos\theta)^n` of
    :func:`square_to_cosine_power_hemisphere`. Args: cos_theta (*B,); exponent () or (*B,).
    Returns: (*B,) solid-angle pdf (0 at and below the horizon)."""
    c = cos_theta.clamp_min(0)
    val = (exponent + 1.0) / (2 * math.pi) * c.clamp_min(torch.finfo(c.dtype).tiny) ** exponent
    return torch.where(c > 0, val, torch.zeros((), dtype=c.dtype))


def square_to_uniform_triangle(u: torch.Tensor) -> torch.Tensor:
    r"""Uniform barycentric coordinates on a triangle (pbrt-v3 ``UniformSampleTriangle``).

    :math:`b_0 = 1 - \sqrt{u_0}`, :math:`b_1 = u_1\sqrt{u_0}`, :math:`b_2 = 1 - b_0 - b_1`;
    the point :math:`b_0 v_0 + b_1 v_1 + b_2 v_2` is uniform in area (density 1/area).

    Args:
        u: (N, 2) uniforms in [0, 1).
    Returns:
        (N, 3) barycentrics, each >= 0, summing to 1.
    """
    _check_u(u)
    s = u[:, 0].sqrt()
    b0, b1 = 1 - s, u[:, 1] * s
    return torch.stack([b0, b1, (1 - b0 - b1).clamp_min(0)], dim=-1)
