r"""The direction sampler of the multibounce precomputation (Ben-Artzi et al. 2008, Sec. 5.1)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ...errors import ValueRangeError
from ...frame import half_vector
from ...sphere.warps import (
    cosine_hemisphere_pdf,
    cosine_power_hemisphere_pdf,
    square_to_cosine_hemisphere,
    square_to_cosine_power_hemisphere,
)

__all__ = ["Mixture"]


@dataclass(frozen=True)
class Mixture:
    r"""Direction sampling independent of the final BRDF (Sec. 5.1): with probability
    ``diffuse`` a cosine lobe, otherwise a Blinn lobe :math:`\cos^n\theta_h` about the
    mirror direction (the seed: 70% diffuse, 30% Blinn exponent 200)."""

    diffuse: float = 0.7
    exponent: float = 200.0

    def __post_init__(self):
        if not 0.0 <= self.diffuse <= 1.0 or not self.exponent >= 0.0:
            raise ValueRangeError(f"mixture needs diffuse in [0, 1] and exponent >= 0; got {self}")

    def sample(self, wo: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Local ``wo`` (n, 3), uniforms ``u`` (n, 3) -> ``wi`` (n, 3), solid-angle pdf (n,)."""
        cosine = square_to_cosine_hemisphere(u[:, 1:])
        h = square_to_cosine_power_hemisphere(u[:, 1:], self.exponent)
        glossy = 2 * (wo * h).sum(-1, keepdim=True) * h - wo
        wi = torch.where((u[:, :1] < self.diffuse), cosine, glossy)
        return wi, self.pdf(wi, wo)

    def pdf(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """Solid-angle density of :meth:`sample` (0 below the horizon)."""
        n = self.exponent
        h = half_vector(wi, wo)
        cos_oh = (wo * h).sum(-1).abs().clamp_min(1e-12)
        p_h = cosine_power_hemisphere_pdf(h[:, 2], n)
        p = self.diffuse * cosine_hemisphere_pdf(wi[:, 2]) + (1 - self.diffuse) * p_h / (4 * cos_oh)
        return torch.where(wi[:, 2] > 0, p, torch.zeros_like(p))
