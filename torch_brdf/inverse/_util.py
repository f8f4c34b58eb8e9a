"""float64 input conversion for the inverse solver."""

from __future__ import annotations

import torch

from .._checks import as_float_tensor


def f64(x, name: str) -> torch.Tensor:
    """``x`` as a float64 tensor. Python numbers and arrays are converted straight to float64:
    ``torch_brdf._checks.as_float_tensor(x, name, torch.float64)`` first makes a tensor of the
    default dtype (float32) and casts afterwards, which turns ``1 - 1e-9`` into exactly 1."""
    if isinstance(x, torch.Tensor):
        return as_float_tensor(x, name, torch.float64)
    try:
        return torch.as_tensor(x, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        return as_float_tensor(x, name, torch.float64)  # raises the package's ShapeError
