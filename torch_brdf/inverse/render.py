r"""Re-rendering with the designed BRDF (Iwasaki et al., Eq. 22) and the fitted :math:`p(h)`.

The solved coefficients define an ordinary BRDF of the package, :func:`srbf_brdf`
(:class:`~torch_brdf.brdf.analytic.DistributionBased` with an
:class:`~torch_brdf.brdf.srbf.SRBFDistribution`), usable by every renderer. For interactive
re-rendering under a new light and view, :func:`rerender` evaluates Eq. 22,

.. math:: B(x, \omega_o) = \sum_k L(\omega_k)\tilde V(x, \omega_k)
          \Big(\frac{\rho_d}{\pi} + \sum_j c_j G_j(h_k)s(\omega_k, \omega_o)\Big),

by computing the transfer record of the new view and lighting (dense, or over visibility cuts)
and applying :math:`[c; \rho_d]` to it: the same code path as the fit, so a re-render in the
fitting view reproduces the fitted image exactly.
"""

from __future__ import annotations

import torch

from ..brdf.analytic import DistributionBased
from ..brdf.srbf import SRBFBasis, SRBFDistribution
from ..errors import SceneError, ShapeError, ValueRangeError
from ..scene.camera import Camera
from ..scene.envmap import EnvironmentMap
from ..scene.scene import Scene
from .energy import default_basis
from .solve import FitResult
from .transfer import CutOptions, LightSamples, cosine_visibility, object_pixels, transfer_functions

__all__ = ["distribution_image", "rerender", "srbf_brdf"]


def srbf_brdf(result: FitResult, basis: SRBFBasis | None = None) -> DistributionBased:
    """The designed BRDF as a module: :math:`\\rho_d/\\pi + p(h)F/(\\ldots)` (Eq. 11, 13)."""
    basis = basis if basis is not None else default_basis()
    if bool((result.coefficients < 0).any()):
        raise ValueRangeError(
            "the fit has negative SRBF coefficients (an unconstrained fit); SRBFDistribution needs c >= 0 -- "
            "re-render it with rerender(), which accepts any coefficients"
        )
    return DistributionBased(SRBFDistribution(basis, result.coefficients), kd=result.kd.clamp(0, 1), f0=result.f0)


def rerender(
    scene: Scene,
    obj: str | int,
    result: FitResult,
    camera: Camera | None = None,
    environment: EnvironmentMap | None = None,
    light_samples: int = 1024,
    cuts: CutOptions | None = None,
    basis: SRBFBasis | None = None,
    generator: torch.Generator | None = None,
    background: float = 0.0,
    progress: bool | None = None,
) -> torch.Tensor:
    """Render ``obj`` with the fitted BRDF under a new view and/or environment (Eq. 22).

    Args:
        scene: the scene (its environment map is the default light).
        obj: object name or id.
        result: the fit.
        camera: the view (default ``scene.camera``).
        environment: the light, e.g. ``scene.environment.rotated(0.5)`` (default the scene's).
        light_samples: S directions drawn from the environment (seeded by ``generator``).
        cuts: visibility-cut options (None: dense).
        basis: the SRBFs (default 147 lobes).
        generator: random source for the light samples.
        background: value of the pixels not covered by the object.
    Returns:
        (H, W, 3) float64 radiance; only the object's pixels are shaded (direct lighting).
    """
    env = environment if environment is not None else scene.environment
    if env is None:
        raise SceneError(f"scene {scene.name!r} has no environment map; pass environment=")
    px = object_pixels(scene, obj, camera)
    ls = LightSamples.from_environment(env, light_samples, generator)
    vis = cosine_visibility(scene, px, ls, progress=progress)
    rec = transfer_functions(px, ls, vis, basis, result.f0.tolist(), cuts, progress=progress)
    return rec.image(result.record_coefficients(), background)


def distribution_image(coefficients, basis: SRBFBasis | None = None, size: int = 128) -> torch.Tensor:
    r""":math:`p(h)` on the upper hemisphere seen from above (orthographic: pixel (r, c) is
    :math:`h = (x, y, \sqrt{1 - x^2 - y^2})` with :math:`x` along columns and :math:`y` up the
    rows), 0 outside the unit disk; for plotting the fitted distribution.

    Args:
        coefficients: (J,) or (J, C) SRBF coefficients.
        basis: the SRBFs (default 147 lobes).
        size: image side.
    Returns:
        (size, size) or (size, size, C) float64.
    """
    basis = basis if basis is not None else default_basis()
    c = torch.as_tensor(coefficients, dtype=torch.float64)
    if c.shape[0] != basis.K or c.ndim not in (1, 2):
        raise ShapeError(f"Expected coefficients of shape ({basis.K},) or ({basis.K}, C); got {tuple(c.shape)}")
    if int(size) < 2:
        raise ValueRangeError(f"size must be >= 2; got {size}")
    t = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2 - 1
    y, x = torch.meshgrid(-t, t, indexing="ij")
    r2 = x * x + y * y
    inside = r2 < 1
    h = torch.stack((x, y, (1 - r2).clamp_min(0).sqrt()), -1)
    p = basis.eval(h.reshape(-1, 3)) @ c
    p = p.reshape((size, size) + tuple(c.shape[1:]))
    mask = inside if p.ndim == 2 else inside[..., None]
    return torch.where(mask, p, torch.zeros((), dtype=torch.float64))
