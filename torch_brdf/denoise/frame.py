r"""Denoise the final edited frame and keep each object's mean: the path for any set of edits.

Denoising the basis images once (:mod:`.tensors`) keeps edits cheap, but a denoiser that is not
linear (OIDN) or that spreads entries (every filter) then has to be right for materials it never
saw, and the whole-record path makes the record several times denser. :class:`FrameDenoiser`
denoises the frame the user looks at instead, after every edit of any number of objects, with
the view's material-independent guides (OIDN: the mean of a colour-only pass and one with the
albedo proxy; the linear filters: object, normal and plane guides), and then puts back each object region's mean:

.. math:: D'(B)_p = D(B)_p \, \frac{\sum_{q \in O} B_q}{\sum_{q \in O} D(B)_q}, \qquad p \in O,

per channel, for every object region :math:`O` (the pixels whose centre sees object ``O``,
``guides.object_id``); pixels that see no object (the environment, exact in the record) keep
their value. The noisy frame's region sum is an unbiased estimate of the reference's, so the
denoised frame's region mean is exactly that unbiased estimate: the denoiser moves radiance
inside an object, never between objects or in or out of the view.

What it costs: no stored entries (the record is read as before; the guides are ``H·W`` pixels
the record already carries) and a fixed number of denoiser calls per frame, :math:`O(HW)` work
(two OIDN passes, or ``(2r+1)^2`` taps per pixel for the regression filter) on top of the frame.

What it cannot do: make the region mean better than the samples' own. Its standard error is
estimated per region from the frame itself, :math:`\sqrt{\sum_{p \in O} (B_p - D(B)_p)^2} / \sum_{p\in O}
B_p` (the residual taken as independent per-pixel noise; residual detail the denoiser removed
makes the estimate larger, never smaller), in :attr:`FrameDenoiser.last_mean_error`; with
``mean_tolerance`` set, a frame whose estimate exceeds it raises :class:`~torch_brdf.errors.NumericalError`
naming the region: more samples are needed for that accuracy, no denoiser can supply it.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from ..errors import NumericalError, ShapeError, ValueRangeError
from ..records.guides import GuideBuffers

FrameFilter = Callable[[torch.Tensor], torch.Tensor]

METHODS = ("oidn", "regression", "linear")


def keep_region_means(denoised: torch.Tensor, noisy: torch.Tensor, regions: torch.Tensor) -> torch.Tensor:
    """Rescale ``denoised`` per region and channel so that each region's sum equals ``noisy``'s.

    Args:
        denoised: (H, W, C) the denoiser's output.
        noisy: (H, W, C) its input.
        regions: (H, W) int64 region id per pixel; negative ids keep ``noisy``'s value.
    Returns:
        (H, W, C): per region the denoised detail with the noisy sum. A region whose denoised
        sum is zero (in a channel) takes the noisy values there.
    """
    if denoised.shape != noisy.shape or denoised.ndim != 3 or tuple(regions.shape) != tuple(noisy.shape[:2]):
        raise ShapeError(
            f"expected denoised and noisy (H, W, C) and regions (H, W); got {tuple(denoised.shape)}, "
            f"{tuple(noisy.shape)}, {tuple(regions.shape)}"
        )
    ids = regions.reshape(-1)
    x, y = noisy.reshape(-1, noisy.shape[-1]), denoised.reshape(-1, noisy.shape[-1]).to(noisy.dtype)
    inside = ids >= 0
    n = int(ids.max()) + 1 if bool(inside.any()) else 0
    seg = torch.where(inside, ids, n)  # one extra bin for the pixels left as they are
    sx = torch.zeros(n + 1, x.shape[1], dtype=x.dtype).index_add(0, seg, x)
    sy = torch.zeros(n + 1, x.shape[1], dtype=x.dtype).index_add(0, seg, y)
    ok = sy != 0
    scale = torch.where(ok, sx / torch.where(ok, sy, torch.ones_like(sy)), torch.ones_like(sy))
    out = torch.where(ok[seg], y * scale[seg], x)
    out = torch.where(inside[:, None], out, x)
    return out.reshape(noisy.shape)


def region_mean_error(denoised: torch.Tensor, noisy: torch.Tensor, regions: torch.Tensor) -> dict[int, float]:
    r"""Per region, the estimated relative standard error of the noisy frame's region mean,
    :math:`\sqrt{\sum_p \lVert B_p - D(B)_p\rVert^2 / C} / |\sum_p \bar B_p|` (the residual taken as
    independent per-pixel noise, averaged over the C channels).

    Args:
        denoised: (H, W, C).
        noisy: (H, W, C).
        regions: (H, W) int64; negative ids are skipped.
    Returns:
        {region id: relative standard error} (inf where the region's sum is zero).
    """
    out = {}
    c = noisy.shape[-1]
    for o in regions.unique().tolist():
        if o < 0:
            continue
        m = regions == o
        total = float(noisy[m].sum()) / c
        resid = float(((noisy[m] - denoised[m].to(noisy.dtype)) ** 2).sum()) / c
        out[int(o)] = resid**0.5 / abs(total) if total != 0 else float("inf")
    return out


class FrameDenoiser:
    """Denoise a final frame (H, W, 3) with the view's guides and keep each object region's mean.

    Args:
        guides: the view's :class:`~torch_brdf.records.guides.GuideBuffers` (``tensors.guides``).
        method: ``"oidn"`` (Open Image Denoise, the mean of a colour-only pass and one with the
            albedo proxy; the ``denoise`` extra), ``"regression"``
            (:class:`~.regression.RegressionFilter`) or ``"linear"`` (:class:`~.atrous.EdgeAwareFilter`),
            or any callable (H, W, 3) -> (H, W, 3).
        glossy: object ids with more than one band (the linear filters' half-vector guide).
        keep_mean: rescale each object region to the noisy frame's sum (default True; False is
            the plain denoiser, for comparison).
        mean_tolerance: if set, raise when a region's mean has an estimated relative standard
            error above it (see the module docstring).
        quality: OIDN quality.

    Calling it on a frame returns the denoised frame; :attr:`last_mean_error` holds the last
    frame's per-region estimate ``{object id: relative standard error}``.
    """

    def __init__(
        self,
        guides: GuideBuffers,
        method: str | FrameFilter = "oidn",
        glossy=(),
        keep_mean: bool = True,
        mean_tolerance: float | None = None,
        quality: str = "high",
    ):
        if not isinstance(guides, GuideBuffers):
            raise ValueRangeError(f"FrameDenoiser needs the view's GuideBuffers; got {type(guides).__name__}")
        if mean_tolerance is not None and not mean_tolerance > 0:
            raise ValueRangeError(f"mean_tolerance must be > 0 or None; got {mean_tolerance}")
        self.guides = guides
        self.keep_mean = bool(keep_mean)
        self.mean_tolerance = mean_tolerance
        self.last_mean_error: dict[int, float] = {}
        if callable(method):
            self.method, self._filter = getattr(method, "description", type(method).__name__), method
        elif method == "oidn":
            from .oidn import oidn_image

            # two passes, colour alone and colour with the albedo proxy, averaged: the guides are
            # material-independent proxies (the albedo is one value per object, not the edited
            # material's), and their errors are partly independent; measured on generated scenes
            # (32² and 40², three seeds) the mean beat OIDN with albedo and normals in every edit case
            self.method = "oidn"
            self._filter = lambda x: 0.5 * (oidn_image(x, None, quality) + oidn_image(x, guides, quality, normal=False))
        elif method in ("regression", "linear"):
            from .atrous import EdgeAwareFilter
            from .regression import RegressionFilter

            lin = (RegressionFilter if method == "regression" else EdgeAwareFilter)(guides, glossy=glossy)
            self.method = method
            self._filter = lambda x: lin(x.permute(2, 0, 1)).permute(1, 2, 0)
        else:
            raise ValueRangeError(f"method must be one of {METHODS} or a callable; got {method!r}")

    @property
    def description(self) -> str:
        keep = "keeping each object's mean" if self.keep_mean else "plain"
        return f"frame denoiser ({self.method}, {keep})"

    def __call__(self, frame: torch.Tensor) -> torch.Tensor:
        """Denoise one frame.

        Args:
            frame: (H, W, 3) the noisy frame (e.g. ``PolynomialRenderer.evaluate()``).
        Returns:
            (H, W, 3) in the frame's dtype.
        Raises:
            ShapeError: a frame of another view.
            NumericalError: with ``mean_tolerance``, a region whose mean the samples do not pin down.
        """
        h, w = self.guides.height, self.guides.width
        if frame.ndim != 3 or tuple(frame.shape) != (h, w, 3):
            raise ShapeError(f"expected a frame of shape ({h}, {w}, 3); got {tuple(frame.shape)}")
        noisy = frame.detach()
        den = self._filter(noisy).to(noisy.dtype)
        regions = self.guides.object_id
        self.last_mean_error = region_mean_error(den, noisy, regions)
        if self.mean_tolerance is not None:
            bad = {o: e for o, e in self.last_mean_error.items() if e > self.mean_tolerance}
            if bad:
                o, e = max(bad.items(), key=lambda kv: kv[1])
                raise NumericalError(
                    f"object {o}'s mean has an estimated standard error of {100 * e:.2g}% "
                    f"(> mean_tolerance {100 * self.mean_tolerance:.2g}%): precompute with more samples"
                )
        out = keep_region_means(den, noisy, regions) if self.keep_mean else den
        return torch.where((regions >= 0)[..., None], out, noisy)
