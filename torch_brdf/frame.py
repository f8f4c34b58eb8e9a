r"""Local shading frames and the angles BRDFs are written in.

Conventions (the whole package): a shading frame has :math:`z` along the normal; local
directions are unit ``(*B, 3)`` vectors pointing *away* from the surface (both ``wi``
and ``wo``); :math:`\theta` is measured from :math:`+z`, :math:`\phi` from :math:`+x`
towards :math:`+y` (the tangent ``s`` and bitangent ``t`` of the frame).

Half/difference angles follow Rusinkiewicz 1998: :math:`h = (w_i + w_o)/|w_i + w_o|`
with spherical angles :math:`(\theta_h, \phi_h)`; the difference vector
:math:`d = R_y(-\theta_h) R_z(-\phi_h) w_i` has angles :math:`(\theta_d, \phi_d)`.

This module is the one home of the half vector (:func:`half_vector`, :func:`half_terms`) and
of shading frames (:class:`Frame`, :func:`orthonormal_basis`). Epsilon policy of the half
vector, for every caller: with :math:`s = w_i + w_o`, :math:`h = s/|s|` where
:math:`|s| > \varepsilon` (the machine epsilon of the dtype), else :math:`h = +z` (the pair
is opposite to rounding, :math:`h` is undefined; the fallback keeps values and gradients
finite). Squared quantities that are divided by (:math:`s_z^2` in :math:`\tan^2\theta_h`)
are floored at :math:`\sqrt{\text{tiny}}` of the dtype, so their reciprocals stay finite.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

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
        """Frame from unit normals (*B, 3); with ``tangent`` (*B, 3) (e.g. a view direction),
        its component orthogonal to the normal becomes ``s`` (Gram-Schmidt); where there is
        none (``tangent`` along the normal: the component is at most sqrt(eps) of its
        length, so its direction would be rounding noise) and without ``tangent``, Duff et
        al.'s basis."""
        n = check_vectors(normal, "normal", ndim=None)
        if tangent is None:
            return cls(*orthonormal_basis(n), n)
        tg = check_vectors(tangent, "tangent", ndim=None).to(n.dtype)
        s = tg - (tg * n).sum(-1, keepdim=True) * n
        length = s.norm(dim=-1, keepdim=True)
        ok = length > math.sqrt(torch.finfo(n.dtype).eps) * tg.norm(dim=-1, keepdim=True)
        s = torch.where(ok, s / length.clamp_min(torch.finfo(n.dtype).tiny), orthonormal_basis(n)[0])
        return cls(s, torch.linalg.cross(n, s, dim=-1), n)

    def matrix(self) -> torch.Tensor:
        """Rows s, t, n as (*B, 3, 3): ``local = matrix @ world`` (its transpose maps back)."""
        return torch.stack((self.s, self.t, self.n), -2)

    def to_local(self, v: torch.Tensor) -> torch.Tensor:
        """World vectors (*B, 3) -> local (*B, 3)."""
        return torch.stack(((v * self.s).sum(-1), (v * self.t).sum(-1), (v * self.n).sum(-1)), -1)

    def to_world(self, v: torch.Tensor) -> torch.Tensor:
        """Local vectors (*B, 3) -> world (*B, 3)."""
        return v[..., :1] * self.s + v[..., 1:2] * self.t + v[..., 2:3] * self.n


def cos_theta(w: torch.Tensor) -> torch.Tensor:
    """Cosine of the polar angle of local directions (*B, 3) -> (*B,)."""
    return w[..., 2]


def polar_angle(w: torch.Tensor) -> torch.Tensor:
    r"""Polar angle :math:`\theta \in [0, \pi]` of local vectors (*B, 3) -> (*B,), as
    :math:`\operatorname{atan2}(|w_{xy}|, w_z)` (accurate near the poles, unlike an arccos)."""
    return torch.atan2(_sqrt0(w[..., 0] ** 2 + w[..., 1] ** 2), w[..., 2])


def spherical_angles(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    r"""Polar and azimuthal angles of local unit vectors: :math:`\theta \in [0, \pi]`,
    :math:`\phi \in (-\pi, \pi]` (0 at the poles, with a zero gradient there rather than
    atan2(0, 0)'s NaN). Args: w (*B, 3). Returns: theta, phi (*B,) each."""
    x, y = w[..., 0], w[..., 1]
    pole = (x == 0) & (y == 0)
    phi = torch.where(pole, torch.zeros_like(x), torch.atan2(y, torch.where(pole, torch.ones_like(x), x)))
    return polar_angle(w), phi


def _sqrt0(x: torch.Tensor) -> torch.Tensor:
    """``sqrt(x)`` of ``x >= 0`` with a finite gradient at 0 (the value there is exactly 0;
    a plain sqrt's infinite derivative turned the gradients of wi = -wo pairs into NaN)."""
    pos = x > 0
    return torch.where(pos, torch.where(pos, x, torch.ones_like(x)).sqrt(), torch.zeros_like(x))


def _unit_sum(s: torch.Tensor, length: torch.Tensor) -> torch.Tensor:
    """``s / length`` (*B, 3) where ``length`` (*B,) exceeds eps, else +z (the policy above)."""
    eps = torch.finfo(s.dtype).eps
    z = torch.zeros((3,), dtype=s.dtype, device=s.device)
    z[2] = 1.0
    return torch.where((length > eps).unsqueeze(-1), s / length.clamp_min(eps).unsqueeze(-1), z)


def half_vector(wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    r"""Unit half vector :math:`(w_i + w_o)/|w_i + w_o|` of local directions (*B, 3).

    Where :math:`w_i = -w_o` (undefined; see the module's epsilon policy), the normal
    :math:`+z` is returned, so the result is always finite. :func:`half_terms` returns it
    with the angles computed without cancellation.
    """
    s = wi + wo
    return _unit_sum(s, _sqrt0((s * s).sum(-1)))


class HalfTerms(NamedTuple):
    r"""Half-vector quantities of a direction pair, computed without cancellation and
    symmetrically in :math:`(\omega_i, \omega_o)` (bit for bit).

    Attributes:
        s: (*B, 3) the unnormalised sum :math:`\omega_i + \omega_o`.
        h: (*B, 3) the unit half vector (:math:`+z` where undefined, :math:`\omega_i = -\omega_o`).
        tan2: (*B,) :math:`\tan^2\theta_h` (finite; large near the horizon).
        cos_h: (*B,) :math:`\cos\theta_h = h_z`.
        cos_d: (*B,) :math:`\cos\theta_d = \omega_i\cdot h = \omega_o\cdot h = |s|/2`.
        one_minus_cos_d: (*B,) :math:`1 - \cos\theta_d`, accurate near 0.
        sin_d: (*B,) :math:`\sin\theta_d = |\omega_i - \omega_o|/2`.
        up: (*B,) bool, both directions strictly above the horizon.
    """

    s: torch.Tensor
    h: torch.Tensor
    tan2: torch.Tensor
    cos_h: torch.Tensor
    cos_d: torch.Tensor
    one_minus_cos_d: torch.Tensor
    sin_d: torch.Tensor
    up: torch.Tensor

    @property
    def theta_d(self) -> torch.Tensor:
        r""":math:`\theta_d = \operatorname{atan2}(\sin\theta_d, \cos\theta_d)` (*B,),
        accurate everywhere (no arccos of a rounded cosine)."""
        return torch.atan2(self.sin_d, self.cos_d)


def half_terms(wi: torch.Tensor, wo: torch.Tensor) -> HalfTerms:
    r"""Half-vector terms of local unit directions ``wi, wo`` (*B, 3); see :class:`HalfTerms`.

    Angles of :math:`h` are read from the unnormalised sum: :math:`\tan^2\theta_h =
    (s_x^2 + s_y^2)/s_z^2` is accurate near the mirror direction, where
    :math:`1 - \cos\theta_h` would cancel; :math:`1 - \cos\theta_d = q/(1 + \sqrt{1-q})`
    with :math:`q = \sin^2\theta_d = |\omega_i - \omega_o|^2/4`. Inputs are assumed unit length.
    """
    s = wi + wo
    sxy2 = s[..., 0] ** 2 + s[..., 1] ** 2
    sz = s[..., 2]
    length = _sqrt0(sxy2 + sz * sz)
    tan2 = sxy2 / (sz * sz).clamp_min(math.sqrt(torch.finfo(s.dtype).tiny))
    h = _unit_sum(s, length)
    d = wi - wo
    q = ((d * d).sum(-1) * 0.25).clamp(0.0, 1.0)
    one_minus_cos_d = q / (1.0 + _sqrt0(1.0 - q))
    up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    return HalfTerms(s, h, tan2, h[..., 2], 0.5 * length, one_minus_cos_d, _sqrt0(q), up)


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
        wi: (*B, 3) unit local directions.
        wo: as ``wi``.
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
