r"""A linear denoiser by local weighted polynomial regression, in the spirit of NFOR's
first-order regression (Bitterli et al., "Nonlinearly weighted first-order regression for
denoising Monte Carlo renderings", EGSR 2016, Eq. 4-6), with weights from the guides only.

For every interior pixel :math:`p` (see :mod:`.atrous`) the image inside a
:math:`(2r + 1)^2` window is fitted by a polynomial of degree ``order`` in the screen offset
:math:`(u, v) = (q - p) / r`, weighted by the guide weight of :class:`~.atrous.GuideWeights`
times a Gaussian :math:`\exp(-|q - p|^2 / 2\sigma_s^2)`; the output is the fit's value at
:math:`p`:

.. math:: \hat y_p = e_1^\top (X_p^\top W_p X_p + \lambda\,\bar w_p D)^{-1} X_p^\top W_p\, y
          = \sum_q h_{pq}\, y_q,

(:math:`X_p` the features :math:`1, u, v, u^2, v^2, uv` of the window, :math:`W_p` the weights,
:math:`\lambda` a ridge on the non-constant features scaled by the weight sum
:math:`\bar w_p`, :math:`D = \mathrm{diag}(0, 1, \dots, 1)`). The hat weights
:math:`h_{pq}` depend on the guides alone, so the filter is one fixed linear operator, applied
alike to every basis image: every edit stays exact, as with the à-trous filter.

Why it helps (measured in ``benchmarks/denoise.py``): the à-trous filter averages, so on a
wall lit by a nearby area light (a gradient) and at contact shadows it returns the window's
mean instead of the pixel's value (a bias that grows with the footprint). A local linear or
quadratic fit reproduces gradients and curvature exactly (:math:`h` reproduces any polynomial
of degree ``order`` where the window is one object's interior) and removes noise only.
The price is a larger weight on far taps (``h`` may be negative), so it removes less noise
than the mean of the same window; pixels with too few taps for the fit (fewer than
``min_taps`` effective taps per feature) fall back to the weighted mean (degree 0).
Where it still blurs: structure finer than the window's polynomial (a sharp glossy highlight
inside one mirror region, the last pixels of a contact shadow); there the negative hat weights
can also ring (measured: the Cornell box's contact region under an edited n = 1000 back wall,
whose reflections of the boxes are sharper than the 11-pixel window).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..errors import ValueRangeError
from ..parallel.threads import tuned
from ..records.guides import GuideBuffers
from .atrous import GuideFilter, GuideSigmas, GuideWeights


@dataclass(frozen=True)
class RegressionSettings(GuideSigmas):
    """What decides the regression filter (hashable; benchmarks report it): the guide
    tolerances of :class:`~.atrous.GuideSigmas` and the fit's own settings. The defaults were
    chosen on 16-spp frames of both benchmark scenes (``benchmarks/denoise_tune.py``).

    Attributes:
        radius: window half-width r in pixels (the window is 2r + 1 wide).
        order: polynomial degree in the screen offset: 0 (weighted mean), 1 or 2.
        sigma_space: standard deviation of the spatial Gaussian, pixels (large: a box).
        ridge: ridge on the non-constant coefficients, relative to the weight sum.
        min_taps: effective taps (:math:`(\\sum w)^2 / \\sum w^2`) needed per fitted feature;
            below it the pixel uses the weighted mean (0: never).
    """

    sigma_half: float = 0.02
    radius: int = 5
    order: int = 2
    sigma_space: float = 100.0
    ridge: float = 1e-3
    min_taps: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        if self.radius < 1 or self.order not in (0, 1, 2) or self.sigma_space <= 0:
            raise ValueRangeError(f"need radius >= 1, order 0, 1 or 2 and sigma_space > 0; got {self}")
        if self.ridge < 0 or self.min_taps < 0:
            raise ValueRangeError(f"need ridge >= 0 and min_taps >= 0; got {self}")


def _features(u: float, v: float, order: int) -> list[float]:
    """The polynomial features of a screen offset (u, v): 1, then u, v, then u², v², uv."""
    return [1.0, u, v, u * u, v * v, u * v][: (1, 3, 6)[order]]


class RegressionFilter(GuideFilter):
    """Local weighted polynomial regression for one view; hat weights precomputed from ``guides``.

    Args:
        guides: the view's :class:`GuideBuffers`.
        settings: :class:`RegressionSettings` (default: radius 5, degree 2).
        glossy: object ids where the half-vector guide applies (as :class:`~.atrous.EdgeAwareFilter`).
        guide_weights: the :class:`~.atrous.GuideWeights` of these guides and glossy objects to
            take the tap weights from (filters of several radii share one that keeps its taps);
            None builds one.

    Calling it on images (..., H, W) returns the filtered images in their dtype; it is linear:
    ``A(a x + b y) == a A(x) + b A(y)`` up to rounding.

    Attributes:
        interior: (H, W) bool pixels that are filtered (the others are left as they are).
        fallback: (H, W) bool interior pixels that use the weighted mean (too few taps).
        weights: ((2r + 1)², H, W) float32 hat weights, one plane per window offset (at the
            default r = 5, 121 planes: 32 MB at 256², 127 MB at 512²).
    """

    def __init__(
        self,
        guides: GuideBuffers,
        settings: RegressionSettings | None = None,
        glossy=(),
        guide_weights: GuideWeights | None = None,
    ):
        self._setup(guides, settings, RegressionSettings, glossy)
        r = self.settings.radius
        if guide_weights is not None and (guide_weights.guides is not guides or guide_weights.glossy != self.glossy):
            raise ValueRangeError("guide_weights belong to other guides or glossy objects")
        with tuned("denoise.regression_weights", guides.height * guides.width * (2 * r + 1) ** 2):
            self._build(guide_weights or GuideWeights(self.guides, self.glossy))

    def _build(self, gw: GuideWeights) -> None:
        s = self.settings
        interior = self.interior = gw.interior
        r = s.radius
        self.offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
        w = torch.stack(
            [
                gw.weight(dy, dx, s) * torch.exp(torch.tensor(-(dy * dy + dx * dx) / (2 * s.sigma_space**2))).double()
                for dy, dx in self.offsets
            ]
        )  # (T, H, W)
        w = torch.where(interior, w, 0.0)
        x = torch.tensor([_features(dy / r, dx / r, s.order) for dy, dx in self.offsets], dtype=torch.float64)
        nf = x.shape[1]
        # (H, W, F, F) weighted normal equations as one matmul (an einsum over three operands
        # took 4 s per filter at 256² under load): sum_t w[t, p] x[t, f] x[t, g]
        m = w.reshape(len(self.offsets), -1).T @ (x[:, :, None] * x[:, None, :]).reshape(len(self.offsets), -1)
        m = m.reshape(*self.shape, nf, nf)
        total = m[..., 0, 0].clamp_min(1e-300)
        ridge = torch.ones(nf, dtype=torch.float64)
        ridge[0] = 0.0
        m = m + torch.diag(ridge) * (s.ridge * total)[..., None, None]
        m[~interior] = torch.eye(nf, dtype=torch.float64)  # unused rows; keeps the solve regular
        e1 = torch.zeros(nf, dtype=torch.float64)
        e1[0] = 1.0
        v = torch.linalg.solve(m, e1.expand(*self.shape, nf))  # (H, W, F)
        hat = w * (x @ v.reshape(-1, nf).T).reshape(w.shape)
        taps = total**2 / (w * w).sum(0).clamp_min(1e-300)  # effective taps
        self.fallback = interior & (taps < s.min_taps * nf) if nf > 1 else torch.zeros_like(interior)
        hat = torch.where(self.fallback, w / total, hat)
        centre = self.offsets.index((0, 0))  # silhouette pixels keep their value
        hat = torch.where(interior, hat, 0.0)
        hat[centre] = torch.where(interior, hat[centre], 1.0)
        self.weights = hat.float()

    @property
    def description(self) -> str:
        return f"linear regression {self.settings}, glossy objects {list(self.glossy)}"

    @property
    def radius(self) -> int:
        """The window half-width (the largest tap offset)."""
        return self.settings.radius

    def __call__(self, images: torch.Tensor, groups: torch.Tensor | None = None) -> torch.Tensor:
        """Filter images (..., H, W) (e.g. (B, 3, H, W) basis images) -> the same shape.
        ``groups`` is ignored (a linear filter treats every image alike)."""
        return apply_hat(self, images)


def apply_hat(filt: GuideFilter, images: torch.Tensor) -> torch.Tensor:
    """``out[p] = sum_k weights[k, p] images[p + offsets[k]]`` for a filter with hat
    ``weights`` (T, H, W), ``offsets`` (T (dy, dx) pairs) and ``radius`` (the largest offset).

    Args:
        filt: the filter (:class:`RegressionFilter` or one that shares its hat-weight form).
        images: (..., H, W).
    Returns:
        (..., H, W) in the images' dtype.
    """
    lead = images.shape[:-2]
    x = filt._planes(images)
    h, w = filt.shape
    pad = filt.radius
    with tuned("denoise.regression", x.numel() * len(filt.offsets)):
        xp = F.pad(x, (pad, pad, pad, pad))
        out = torch.zeros_like(x)
        hat = filt.weights.to(x.dtype)
        for k, (dy, dx) in enumerate(filt.offsets):
            out += hat[k] * xp[:, pad + dy : pad + dy + h, pad + dx : pad + dx + w]
    return out.reshape(*lead, h, w)
