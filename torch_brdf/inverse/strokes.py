r"""Strokes: painted target radiances and fit weights (Iwasaki et al., Sec. 4.3, Eq. 23).

A brush has a colour :math:`C` (RGB, negative values remove highlights), a diameter :math:`D`,
a Gaussian falloff :math:`\kappa` and optionally a scale :math:`S`. A stroke is a point
sequence (a polyline in display-frame pixel coordinates ``(x, y)`` = (column, row)); for a
pixel at distance :math:`d_i` from the polyline (pixel centres at +0.5)

.. math:: w_i = \begin{cases} e^{-\kappa d_i} & d_i \le D/2\\ 0 & \text{else}\end{cases},\qquad
          B_i = w_i C + (1 - w_i) B'_i \quad\text{or, with } S,\quad B_i = w_i S B'_i + (1 - w_i) B'_i,

with :math:`B'_i` the pixel's colour before the stroke (Eq. 23). Choice where the paper is
silent: Eq. 23 prints :math:`d_i \le D` for a brush it calls a *diameter*; we paint a band
:math:`D` wide, i.e. :math:`d_i \le D/2`. Strokes apply in order, each to the result of the
previous ones.

The fit weights (the :math:`w_i` of the solve's objective, not Eq. 23's): painted pixels
(:math:`w_i > 0` for some stroke) weigh 1; the object's other pixels keep their current colour
:math:`B'` with weight ``keep_weight`` (1 by default, the paper's fit over all object pixels; 0
fits the painted pixels only).

Strokes are given in the display frame (e.g. 640 x 480) and evaluated on the pixels of a
transfer record computed on a smaller solving frame (e.g. 160 x 120): a solving pixel's centre
is mapped to display coordinates, so :math:`D` and :math:`\kappa` are in display pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .._checks import check_finite
from ..errors import ShapeError, ValueRangeError
from ..records.basis_image import BasisImage
from ._util import f64

__all__ = ["Brush", "Stroke", "StrokeTarget", "paint", "paint_at", "pixel_xy", "stroke_distance", "target_from_image"]


@dataclass(frozen=True)
class Brush:
    """Brush parameters of Eq. 23.

    Attributes:
        color: RGB :math:`C` (3 floats, may be negative; ignored when ``scale`` is set).
        diameter: :math:`D` > 0 in display pixels.
        kappa: Gaussian falloff :math:`\\kappa` >= 0 per display pixel (0: a flat brush).
        scale: :math:`S` >= 0, or None to paint ``color``.
    """

    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    diameter: float = 20.0
    kappa: float = 0.05
    scale: float | None = None

    def __post_init__(self):
        c = f64(self.color, "brush color").reshape(-1)
        if c.numel() == 1:
            c = c.expand(3)
        if c.numel() != 3:
            raise ShapeError(f"brush color must be a scalar or 3 values; got {c.numel()} values")
        check_finite(c, "brush color")
        object.__setattr__(self, "color", tuple(float(v) for v in c))
        if not (float(self.diameter) > 0 and torch.isfinite(torch.tensor(float(self.diameter)))):
            raise ValueRangeError(f"brush diameter must be finite and > 0; got {self.diameter}")
        if not (float(self.kappa) >= 0 and torch.isfinite(torch.tensor(float(self.kappa)))):
            raise ValueRangeError(f"brush kappa must be finite and >= 0; got {self.kappa}")
        if self.scale is not None and not (float(self.scale) >= 0 and torch.isfinite(torch.tensor(float(self.scale)))):
            raise ValueRangeError(f"brush scale must be finite and >= 0; got {self.scale}")


@dataclass(frozen=True)
class Stroke:
    """A point sequence painted with one brush.

    Attributes:
        points: (K, 2) float64 display-frame pixel coordinates ``(x, y)``, K >= 1.
        brush: the :class:`Brush`.
    """

    points: torch.Tensor
    brush: Brush = Brush()

    def __post_init__(self):
        p = f64(self.points, "stroke points")
        if p.ndim != 2 or p.shape[-1] != 2 or p.shape[0] < 1:
            raise ShapeError(f"Expected stroke points of shape (K, 2) with K >= 1; got {tuple(p.shape)}")
        check_finite(p, "stroke points")
        object.__setattr__(self, "points", p)


@dataclass(frozen=True)
class StrokeTarget:
    """Target radiances and fit weights over the pixels of a transfer record.

    Attributes:
        target: (P, 3) float64 target radiance :math:`B_i`.
        weight: (P,) float64 fit weights >= 0.
        painted: (P,) bool, touched by a stroke (or inside the mask).
    """

    target: torch.Tensor
    weight: torch.Tensor
    painted: torch.Tensor


def stroke_distance(points: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Distance from positions ``xy`` (N, 2) to the polyline ``points`` (K, 2): (N,) float64."""
    if points.shape[0] == 1:
        return (xy - points[0]).norm(dim=-1)
    a, b = points[:-1], points[1:]  # (K-1, 2)
    ab = b - a
    len2 = (ab * ab).sum(-1).clamp_min(1e-300)
    t = (((xy[:, None, :] - a[None]) * ab[None]).sum(-1) / len2).clamp(0, 1)  # (N, K-1)
    closest = a[None] + t[..., None] * ab[None]
    return (xy[:, None, :] - closest).norm(dim=-1).amin(-1)


def pixel_xy(pixels: torch.Tensor, width: int, height: int, display_size: tuple[int, int] | None = None):
    """Display-frame centres ``(x, y)`` (P, 2) float64 of flat pixel indices (P,) of a
    ``width`` x ``height`` frame shown at ``display_size`` (default the frame itself)."""
    w_d, h_d = display_size if display_size is not None else (width, height)
    if int(w_d) < 1 or int(h_d) < 1:
        raise ValueRangeError(f"display size must be positive; got {display_size}")
    r = torch.div(pixels, width, rounding_mode="floor").double()
    c = (pixels % width).double()
    return torch.stack(((c + 0.5) * (w_d / width), (r + 0.5) * (h_d / height)), -1)


def _display_xy(record: BasisImage, display_size: tuple[int, int] | None) -> torch.Tensor:
    return pixel_xy(record.pixels, record.width, record.height, display_size)


def _check_before(before, P: int) -> torch.Tensor:
    b = f64(before, "before")
    if b.shape != (P, 3):
        raise ShapeError(f"Expected the current radiance 'before' of shape ({P}, 3); got {tuple(b.shape)}")
    check_finite(b, "before")
    return b


def paint(
    record: BasisImage,
    before,
    strokes: list[Stroke],
    display_size: tuple[int, int] | None = None,
    keep_weight: float = 1.0,
) -> StrokeTarget:
    """Apply strokes (Eq. 23) to the current colours of a record's pixels.

    Args:
        record: the transfer record (its pixels and frame size).
        before: (P, 3) the current radiance :math:`B'` of those pixels.
        strokes: non-empty list of :class:`Stroke`.
        display_size: ``(width, height)`` of the frame the stroke points refer to (default the
            record's frame).
        keep_weight: fit weight of unpainted object pixels (>= 0).
    Returns:
        :class:`StrokeTarget`.
    Raises:
        ValueRangeError: no strokes, or no stroke touches a pixel of the object.
    """
    B = _check_before(before, record.num_pixels)
    return paint_at(_display_xy(record, display_size), B, strokes, keep_weight)


def paint_at(xy: torch.Tensor, before: torch.Tensor, strokes: list[Stroke], keep_weight: float = 1.0) -> StrokeTarget:
    """:func:`paint` on pixels given by their display-frame centres ``xy`` (P, 2) and current
    radiance ``before`` (P, 3) (e.g. :func:`pixel_xy` of an image's pixels)."""
    if not strokes:
        raise ValueRangeError("no strokes given: paint at least one stroke (a list of points)")
    if not (keep_weight >= 0 and torch.isfinite(torch.tensor(float(keep_weight)))):
        raise ValueRangeError(f"keep_weight must be finite and >= 0; got {keep_weight}")
    B = _check_before(before, xy.shape[0]).clone()
    painted = torch.zeros(xy.shape[0], dtype=torch.bool)
    for k, st in enumerate(strokes):
        if not isinstance(st, Stroke):
            raise ShapeError(f"strokes[{k}] must be a Stroke; got {type(st).__name__}")
        d = stroke_distance(st.points, xy)
        inside = d <= 0.5 * st.brush.diameter
        w = torch.where(inside, torch.exp(-st.brush.kappa * d), torch.zeros((), dtype=torch.float64))[:, None]
        new = st.brush.scale * B if st.brush.scale is not None else torch.tensor(st.brush.color, dtype=torch.float64)
        B = w * new + (1 - w) * B
        painted |= inside
    if not bool(painted.any()):
        raise ValueRangeError(
            "no stroke touches the object: every stroke point is farther than D/2 from the object's pixels"
        )
    weight = torch.where(painted, 1.0, float(keep_weight)).double()
    return StrokeTarget(B, weight, painted)


def target_from_image(record: BasisImage, before, image, mask, keep_weight: float = 1.0) -> StrokeTarget:
    """Strokes given as a painted target image and a mask.

    Args:
        record: the transfer record.
        before: (P, 3) current radiance of the record's pixels.
        image: (H, W, 3) painted image; (H, W) an integer multiple of the record's frame (it is
            averaged down over the mask).
        mask: (H, W) painted region (bool, or weights in [0, 1]).
        keep_weight: fit weight of unpainted object pixels.
    Returns:
        :class:`StrokeTarget` whose painted pixels' weight is the mask coverage (in (0, 1]).
    """
    img = f64(image, "image")
    m = f64(mask, "mask")
    if img.ndim != 3 or img.shape[-1] != 3 or m.shape != img.shape[:2]:
        raise ShapeError(f"Expected image (H, W, 3) and mask (H, W); got {tuple(img.shape)} and {tuple(m.shape)}")
    check_finite(img, "target image")
    check_finite(m, "mask")
    if bool(((m < 0) | (m > 1)).any()):
        raise ValueRangeError("mask values must lie in [0, 1]")
    H, W = m.shape
    if H % record.height or W % record.width or H // record.height != W // record.width:
        raise ShapeError(
            f"image size {W}x{H} must be the same integer multiple of the record frame {record.width}x{record.height}"
        )
    k = H // record.height
    cov = F.avg_pool2d(m[None, None], k)[0, 0].reshape(-1)[record.pixels]  # (P,)
    num = F.avg_pool2d((img * m[..., None]).permute(2, 0, 1)[None], k)[0].reshape(3, -1)[:, record.pixels].T
    B = _check_before(before, record.num_pixels).clone()
    painted = cov > 0
    if not bool(painted.any()):
        raise ValueRangeError("the mask covers no pixel of the object")
    B[painted] = num[painted] / cov[painted, None]
    weight = torch.where(painted, cov, torch.full_like(cov, float(keep_weight)))
    return StrokeTarget(B, weight, painted)
