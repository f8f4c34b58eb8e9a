"""Input checks for public entry points: shapes, dtypes and finite values.

Errors follow pytorch3d's habit: say what was expected and what came.
"""

from __future__ import annotations

import torch

from .errors import ShapeError, ValueRangeError


def as_float_tensor(x, name: str, dtype: torch.dtype | None = None) -> torch.Tensor:
    """Convert ``x`` (tensor, array or sequence) to a floating tensor.

    Integer inputs become the default float dtype; floating tensors keep their dtype
    unless ``dtype`` is given.
    """
    if not isinstance(x, torch.Tensor):
        try:
            # convert straight to the requested dtype: Python floats are doubles, and a detour
            # through the default float32 would round them (1 - 1e-9 would become 1.0)
            x = torch.as_tensor(x, dtype=dtype)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ShapeError(f"{name}: expected a tensor or array of numbers; got {type(x)!r}") from exc
    if dtype is not None:
        return x.to(dtype)
    if not x.is_floating_point():
        x = x.to(torch.get_default_dtype())
    return x


def check_vectors(x, name: str, dtype: torch.dtype | None = None, ndim: int | None = 2) -> torch.Tensor:
    """Check ``x`` has shape ``(*B, 3)`` (``(N, 3)`` when ``ndim == 2``) and finite values."""
    x = as_float_tensor(x, name, dtype)
    if x.ndim < 1 or x.shape[-1] != 3 or (ndim is not None and x.ndim != ndim):
        want = "(N, 3)" if ndim == 2 else "(..., 3)"
        raise ShapeError(f"Expected {name} to have shape {want}; got {tuple(x.shape)}")
    check_finite(x, name)
    return x


def check_finite(x: torch.Tensor, name: str) -> torch.Tensor:
    """Raise :class:`ValueRangeError` if ``x`` holds NaN or Inf."""
    if x.is_floating_point() and not bool(torch.isfinite(x).all()):
        n_nan = int(torch.isnan(x).sum())
        n_inf = int(torch.isinf(x).sum())
        raise ValueRangeError(f"{name} holds non-finite values ({n_nan} NaN, {n_inf} Inf)")
    return x


def check_nonnegative(x: torch.Tensor, name: str) -> torch.Tensor:
    """Raise :class:`ValueRangeError` if ``x`` is non-finite or has negative entries."""
    check_finite(x, name)
    if bool((x < 0).any()):
        raise ValueRangeError(
            f"{name} has {int((x < 0).sum())} negative values (min {float(x.min()):.4g}); "
            "radiance and reflectance must be >= 0"
        )
    return x


def check_rgb(value, name: str) -> tuple[float, float, float]:
    """Accept a scalar or 3 numbers >= 0 and return an RGB triple of floats."""
    t = as_float_tensor(value, name, torch.float64).reshape(-1)
    if t.numel() == 1:
        t = t.expand(3)
    if t.numel() != 3:
        raise ShapeError(f"Expected {name} to be a scalar or 3 values (RGB); got {t.numel()} values")
    check_nonnegative(t, name)
    return (float(t[0]), float(t[1]), float(t[2]))
