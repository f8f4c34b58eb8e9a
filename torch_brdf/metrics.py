r"""Error metrics of images and BRDF tables: the one home of every score the package reports.

Every metric computes in float64, whatever the inputs' dtype; the image metrics return
Python floats of detached inputs, the BRDF-row metrics float64 tensors (one value per row).

Images, ``(H, W, C)`` (or any two equal shapes), with an optional ``(H, W)`` bool ``mask``
of the pixels that count (all channels of a counted pixel count):

- :func:`relative_rmse`: :math:`\sqrt{\sum (I - R)^2 / \sum R^2}`, the relative L2 error
  (equal to :math:`\mathrm{rms}(I - R)/\mathrm{rms}(R)`);
- :func:`relative_l1`: :math:`\sum |I - R| / \sum |R|`;
- :func:`psnr`: :math:`10\log_{10}(\mathrm{peak}^2/\mathrm{MSE})` in dB;
- :func:`hdr_flip`: NVIDIA's perceptual HDR-FLIP (``flip-evaluator``, Andersson et al. 2021,
  the optional extra ``denoise``), the mean of its per-pixel map (0 = identical).

BRDF rows on a MERL grid, ``(M, 3 B)`` or ``(3 B,)`` (RGB blocks of B bins), scored after
Nielsen, Jensen and Ramamoorthi 2015 ("On Optimal, Minimal BRDF Sampling for Reflectance
Acquisition") with the clipped cosine map :math:`c = \cos\theta_i\cos\theta_o` of the bins,
``(B,)`` or ``(3 B,)``:

- :func:`log_relative_rmse`: RMSE of :math:`m(\hat\rho) - m(\rho)` with the log mapping
  :math:`m(\rho) = \log((\rho c + \varepsilon)/(\rho_{\mathrm{ref}} c + \varepsilon))`
  (:math:`\varepsilon = 10^{-3}` by default; :math:`\rho_{\mathrm{ref}}` cancels in the
  difference; values are clamped at 0 inside the log, negative values have no log);
- :func:`cosine_weighted_rmse`: RMSE of :math:`c(\hat\rho - \rho)`.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .errors import ShapeError, TorchBRDFError, ValueRangeError

__all__ = ["cosine_weighted_rmse", "hdr_flip", "log_relative_rmse", "psnr", "relative_l1", "relative_rmse"]

F64 = torch.float64


def _compared(image, reference, mask) -> tuple[torch.Tensor, torch.Tensor]:
    """The float64 values of ``image`` and ``reference`` that a masked image metric compares."""
    a = torch.as_tensor(image).detach().to(F64)
    b = torch.as_tensor(reference).detach().to(F64)
    if a.shape != b.shape:
        raise ShapeError(f"image {tuple(a.shape)} and reference {tuple(b.shape)} differ in shape")
    if mask is None:
        return a, b
    mask = torch.as_tensor(mask)
    if mask.dtype != torch.bool or mask.shape != a.shape[: mask.ndim]:
        raise ShapeError(
            f"Expected mask to be a bool tensor of a leading part of the images' shape {tuple(a.shape)}; "
            f"got {mask.dtype} {tuple(mask.shape)}"
        )
    return a[mask], b[mask]


def _ratio(error: float, size: float, name: str) -> float:
    """``error / size`` of a relative metric, refused when the reference's ``size`` is zero."""
    if not size > 0:
        raise ValueRangeError(f"the reference is zero where compared; {name} is undefined")
    return error / size


def relative_rmse(image: torch.Tensor, reference: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    r"""Relative RMSE :math:`\sqrt{\sum (I - R)^2 / \sum R^2}` over the counted pixels and channels.

    Args:
        image: (H, W, C) (or any equal shapes).
        reference: as ``image``.
        mask: optional (H, W) bool; only those pixels count (default all).
    Returns:
        float.
    Raises:
        ValueRangeError: the reference is zero wherever compared.
    """
    a, b = _compared(image, reference, mask)
    return math.sqrt(_ratio(float(((a - b) ** 2).sum()), float((b * b).sum()), "relative RMSE"))


def relative_l1(image: torch.Tensor, reference: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    r"""Relative L1 error :math:`\sum |I - R| / \sum |R|` over the counted pixels and channels:
    a float, from images (H, W, C) and an optional (H, W) bool mask as :func:`relative_rmse`
    takes them (and refused, as there, when the reference is zero wherever compared)."""
    a, b = _compared(image, reference, mask)
    return _ratio(float((a - b).abs().sum()), float(b.abs().sum()), "relative L1 error")


def psnr(
    image: torch.Tensor, reference: torch.Tensor, mask: torch.Tensor | None = None, peak: float | None = None
) -> float:
    r"""Peak signal-to-noise ratio in dB, :math:`10\log_{10}(\mathrm{peak}^2/\mathrm{MSE})`.

    Args:
        image: (H, W, C) (or any equal shapes) linear images.
        reference: as ``image``.
        mask: optional (H, W) bool; only those pixels count.
        peak: default the reference's maximum over the counted pixels.
    Returns:
        float (``inf`` for identical images).
    """
    a, b = _compared(image, reference, mask)
    mse = float(((a - b) ** 2).mean())
    p = float(b.max()) if peak is None else float(peak)
    if mse == 0:
        return math.inf
    return 10 * math.log10(p * p / mse)


def hdr_flip(image: torch.Tensor, reference: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """Mean HDR-FLIP error of ``image`` against ``reference`` (0 = identical; higher worse).

    Args:
        image: (H, W, 3) linear radiance (negative values clamped to 0).
        reference: as ``image``.
        mask: (H, W) bool pixels to average over (default all); FLIP itself sees the whole
            images (its filters are spatial).
    Returns:
        The mean of the per-pixel FLIP map (default viewing: 67 pixels per degree; exposure
        range and tone mapper (ACES) chosen by FLIP from the reference).
    """
    if image.shape != reference.shape or image.ndim != 3 or image.shape[-1] != 3:
        raise ShapeError(f"expected two (H, W, 3) images; got {tuple(image.shape)} and {tuple(reference.shape)}")
    try:
        import flip_evaluator
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise TorchBRDFError("HDR-FLIP needs the optional extra: pip install 'torch_brdf[denoise]'") from exc
    ref = np.ascontiguousarray(reference.detach().float().clamp_min(0).numpy())
    test = np.ascontiguousarray(image.detach().float().clamp_min(0).numpy())
    err_map, mean, _ = flip_evaluator.evaluate(ref, test, "HDR", applyMagma=False)
    if mask is None:
        return float(mean)
    err = np.asarray(err_map).reshape(image.shape[0], image.shape[1], -1)[..., 0]
    return float(err[mask.numpy()].mean())


def _cosine_map(cosine, like: torch.Tensor) -> torch.Tensor:
    """The cosine map (B,) or (3 B,) as float64 (3 B,) for rows of width 3 B like ``like``."""
    c = torch.as_tensor(cosine, dtype=F64)
    if c.numel() * 3 == like.shape[-1]:
        c = c.repeat(3)
    if c.shape != (like.shape[-1],):
        raise ShapeError(f"cosine map of shape {tuple(c.shape)} does not match rows of width {like.shape[-1]}")
    return c


def log_relative_rmse(
    pred: torch.Tensor, true: torch.Tensor, cosine: torch.Tensor, eps: float = 1e-3, reference=None
) -> torch.Tensor:
    r"""Log-relative RMSE per row (Nielsen et al. 2015 mapping, see the module docstring).

    Args:
        pred: (M, 3 * B) or (3 * B,) BRDF values. cosine: (B,) or (3 * B,) clipped cosine map.
        true: as ``pred``.
        eps: :math:`\varepsilon`. reference: optional per-bin :math:`\rho_{ref}` (cancels; accepted for clarity).
    Returns:
        (M,) or () float64.
    """
    pred, true = torch.as_tensor(pred, dtype=F64), torch.as_tensor(true, dtype=F64)
    c = _cosine_map(cosine, true)
    ref = torch.zeros_like(c) if reference is None else torch.as_tensor(reference, dtype=F64) * c
    mp = torch.log(pred.clamp_min(0) * c + eps) - torch.log(ref + eps)
    mt = torch.log(true.clamp_min(0) * c + eps) - torch.log(ref + eps)
    return ((mp - mt) ** 2).mean(-1).sqrt()


def cosine_weighted_rmse(pred: torch.Tensor, true: torch.Tensor, cosine: torch.Tensor) -> torch.Tensor:
    """RMSE of ``cosine * (pred - true)`` per row.

    Args:
        pred: (M, 3 * B) or (3 * B,) BRDF values. cosine: (B,) or (3 * B,) clipped cosine map.
        true: as ``pred``.
    Returns:
        (M,) or () float64.
    """
    pred, true = torch.as_tensor(pred, dtype=F64), torch.as_tensor(true, dtype=F64)
    c = _cosine_map(cosine, true)
    return (((pred - true) * c) ** 2).mean(-1).sqrt()
