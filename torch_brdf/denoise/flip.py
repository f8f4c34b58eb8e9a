"""HDR-FLIP (NVIDIA's ``flip-evaluator``, Andersson et al. 2021), a perceptual error beside the
relative RMSE. (Kept here until the project's one metrics module exists; it moves there.)"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import ShapeError, TorchBRDFError


def hdr_flip(image: torch.Tensor, reference: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """Mean HDR-FLIP error of ``image`` against ``reference`` (0 = identical; higher worse).

    Args:
        image, reference: (H, W, 3) linear radiance (negative values clamped to 0).
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
