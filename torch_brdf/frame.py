r"""Local shading frames (z = normal) for batches of normals.

The BRDF layer builds on this; for now it offers the orthonormal basis used to map
local-frame samples (e.g. cosine-weighted hemisphere) to world space.
"""

from __future__ import annotations

import torch


def orthonormal_basis(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    r"""Tangent and bitangent for unit normals, branch-free and continuous except at one
    pole (Duff et al. 2017, "Building an Orthonormal Basis, Revisited").

    Args:
        n: (..., 3) unit normals.
    Returns:
        s, t: (..., 3) each, with (s, t, n) right-handed orthonormal.
    """
    x, y, z = n.unbind(-1)
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    s = torch.stack((1.0 + sign * x * x * a, sign * b, -sign * x), -1)
    t = torch.stack((b, sign + y * y * a, -y), -1)
    return s, t


def to_world(local: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Map local-frame vectors (..., 3) (z along ``n``) to world space."""
    s, t = orthonormal_basis(n)
    return local[..., :1] * s + local[..., 1:2] * t + local[..., 2:3] * n


def to_local(v: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Map world vectors (..., 3) into the frame with z along ``n``."""
    s, t = orthonormal_basis(n)
    return torch.stack(((v * s).sum(-1), (v * t).sum(-1), (v * n).sum(-1)), -1)
