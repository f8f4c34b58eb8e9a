r"""Local shading frames and the angles BRDFs are written in.

Conventions (the whole package): a shading frame has :math:`z` along the normal; local
directions are unit ``(*B, 3)`` vectors pointing *away* from the surface (both ``wi``
and ``wo``); :math:`\theta` is measured from :math:`+z`, :math:`\phi` from :math:`+x`
towards :math:`+y` (the tangent ``s`` and bitangent ``t`` of the frame).

Half/difference angles follow Rusinkiewicz 1998: :math:`h = (w_i + w_o)/|w_i + w_o|`
with spherical angles :math:`(\theta_h, \phi_h)`; the difference vector
:math:`d = R_y(-\theta_h) R_z(-\phi_h) w_i` has angles :math:`(\theta_d, \phi_d)`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ._checks import check_vectors


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


@dataclass(frozen=True)
class Frame:
    """A batch of orthonormal shading frames.

    Attributes:
        s: (*B, 3) tangent (local +x; the anisotropy direction of anisotropic BRDFs).
        t: (*B, 3) bitangent (local +y).
        n: (*B, 3) normal (local +z).
    """

    s: torch.Tensor
    t: torch.Tensor
    n: torch.Tensor

    @classmethod
    def from_normal(cls, normal: torch.Tensor, tangent: torch.Tensor | None = None) -> Frame:
        """Frame from unit normals (*B, 3); with ``tangent`` (*B, 3), its component
        orthogonal to the normal becomes ``s`` (Gram-Schmidt), else Duff et al.'s basis."""
        n = check_vectors(normal, "normal", ndim=None)
        if tangent is None:
            s, t = orthonormal_basis(n)
        else:
            tg = check_vectors(tangent, "tangent", ndim=None).to(n.dtype)
            s = tg - (tg * n).sum(-1, keepdim=True) * n
            s = s / s.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(n.dtype).tiny)
            t = torch.linalg.cross(n, s, dim=-1)
        return cls(s, t, n)

    def to_local(self, v: torch.Tensor) -> torch.Tensor:
        """World vectors (*B, 3) -> local (*B, 3)."""
        return torch.stack(((v * self.s).sum(-1), (v * self.t).sum(-1), (v * self.n).sum(-1)), -1)

    def to_world(self, v: torch.Tensor) -> torch.Tensor:
        """Local vectors (*B, 3) -> world (*B, 3)."""
        return v[..., :1] * self.s + v[..., 1:2] * self.t + v[..., 2:3] * self.n


def cos_theta(w: torch.Tensor) -> torch.Tensor:
    """Cosine of the polar angle of local directions (*B, 3) -> (*B,)."""
    return w[..., 2]


def spherical_angles(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    r"""Polar and azimuthal angles of local unit vectors: :math:`\theta \in [0, \pi]`,
    :math:`\phi \in (-\pi, \pi]`. Args: w (*B, 3). Returns: theta, phi (*B,) each."""
    theta = torch.atan2(torch.linalg.vector_norm(w[..., :2], dim=-1), w[..., 2])
    phi = torch.atan2(w[..., 1], w[..., 0])
    return theta, phi


def half_vector(wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    r"""Unit half vector :math:`(w_i + w_o)/|w_i + w_o|` of local directions (*B, 3).

    Where :math:`w_i = -w_o` (undefined), the normal :math:`+z` is returned, so the result
    is always finite.
    """
    h = wi + wo
    norm = torch.linalg.vector_norm(h, dim=-1, keepdim=True)
    tiny = torch.finfo(h.dtype).eps
    z = torch.zeros_like(h)
    z[..., 2] = 1.0
    return torch.where(norm > tiny, h / norm.clamp_min(tiny), z)


def _rotate_z(v: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    return torch.stack((c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]), -1)


def _rotate_y(v: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    return torch.stack((c * v[..., 0] + s * v[..., 2], v[..., 1], -s * v[..., 0] + c * v[..., 2]), -1)


def half_diff_angles(
    wi: torch.Tensor, wo: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    r"""Rusinkiewicz half/difference angles of local directions.

    Args:
        wi, wo: (*B, 3) unit local directions.
    Returns:
        theta_h, phi_h, theta_d, phi_d: (*B,) each; :math:`\theta_h, \theta_d \in [0, \pi]`,
        :math:`\phi_h, \phi_d \in (-\pi, \pi]`.
    """
    h = half_vector(wi, wo)
    theta_h, phi_h = spherical_angles(h)
    d = _rotate_y(_rotate_z(wi, -phi_h), -theta_h)
    theta_d, phi_d = spherical_angles(d)
    return theta_h, phi_h, theta_d, phi_d


def half_diff_to_directions(
    theta_h: torch.Tensor, phi_h: torch.Tensor, theta_d: torch.Tensor, phi_d: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of :func:`half_diff_angles`: (wi, wo), each (*B, 3) local unit vectors."""
    st, ct = torch.sin(theta_d), torch.cos(theta_d)
    d = torch.stack((st * torch.cos(phi_d), st * torch.sin(phi_d), ct), -1)
    wi = _rotate_z(_rotate_y(d, theta_h), phi_h)
    hs = torch.sin(theta_h)
    h = torch.stack((hs * torch.cos(phi_h), hs * torch.sin(phi_h), torch.cos(theta_h)), -1)
    wo = 2 * (wi * h).sum(-1, keepdim=True) * h - wi
    return wi, wo
