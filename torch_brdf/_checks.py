"""Input checks for public entry points: shapes, dtypes, finite values, counts and sizes.

Errors follow pytorch3d's habit: say what was expected and what came. The caps on sizes
that come from users (scene files, command-line options) live here too, so one table
documents them (``docs/guides/files-and-errors.md``):

* :data:`MAX_IMAGE_SIDE` pixels per image side, :data:`MAX_IMAGE_PIXELS` pixels per image;
* :data:`MAX_BANDS` bands per entry of a BRDF series, :data:`MAX_BOUNCES` entries (bounces);
* :data:`MAX_CUBEMAP_RESOLUTION` texels per cubemap face side, :data:`MAX_ENVMAP_HEIGHT` rows
  of a procedural environment map.

They bound what a typo can ask the allocator for (``width = 100000`` would be a 120 GB
float32 RGB image with its per-pixel buffers) while staying far above every size the
methods are used at (images of 4k x 4k, series of 256 bands, cubemaps of 128 texels).
"""

from __future__ import annotations

import math
import numbers
import sys
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from .errors import ShapeError, TorchBRDFError, ValueRangeError

if TYPE_CHECKING:  # torch is imported where it is used: the CLI reads the caps below without it
    import torch


def _is_tensor(value) -> bool:
    """``isinstance(value, torch.Tensor)`` without importing torch (no torch: no tensor)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(value, torch.Tensor)


def as_float_tensor(x, name: str, dtype: torch.dtype | None = None) -> torch.Tensor:
    """Convert ``x`` (tensor, array or sequence) to a floating tensor.

    Integer inputs become the default float dtype; floating tensors keep their dtype
    unless ``dtype`` is given.
    """
    import torch

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
    import torch

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
    """Accept a scalar or 3 numbers >= 0 (finite in float32) and return an RGB triple of floats."""
    import torch

    t = as_float_tensor(value, name, torch.float64).reshape(-1)
    if t.numel() == 1:
        t = t.expand(3)
    if t.numel() != 3:
        raise ShapeError(f"Expected {name} to be a scalar or 3 values (RGB); got {t.numel()} values")
    check_nonnegative(t, name)
    big = float(t.max())
    if big > torch.finfo(torch.float32).max:
        # lights and materials keep RGB in float32 buffers: 1e300 would become Inf there
        raise ValueRangeError(
            f"{name} exceeds the float32 range (max {torch.finfo(torch.float32).max:.4g}); got {big:.4g}"
        )
    return (float(t[0]), float(t[1]), float(t[2]))


#: largest image width or height (pixels)
MAX_IMAGE_SIDE = 16384
#: largest image (pixels): 8192 x 8192; the renderers keep several float32 RGB buffers per pixel
MAX_IMAGE_PIXELS = 8192 * 8192
#: largest number of bands in one entry of a BRDF series (the papers use up to 256)
MAX_BANDS = 4096
#: most bounces (surface vertices per path) of a BRDF series; the papers use up to 4
MAX_BOUNCES = 64
#: most rays per cubemap texel side when visibility is supersampled (k x k rays per texel)
MAX_SUPERSAMPLE = 16
#: largest cubemap face side (texels); 1024 is 6 Mi texels per vertex
MAX_CUBEMAP_RESOLUTION = 1024
#: largest procedural environment map height (rows; the map is H x 2H, built in float64: 200 MB)
MAX_ENVMAP_HEIGHT = 2048
#: seeds are non-negative 63-bit integers (what torch.Generator.manual_seed and numpy accept)
MAX_SEED = 2**63 - 1


def check_int(value, name: str, minimum: int | None = None, maximum: int | None = None) -> int:
    """Return ``value`` as an int after checking it is an integer in ``[minimum, maximum]``.

    Python, numpy and 0-d torch integers are accepted; bools, floats (even ``16.0``), strings
    and anything else raise :class:`ValueRangeError` naming ``name``.
    """
    if _is_tensor(value) and value.numel() == 1 and not value.is_floating_point():
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueRangeError(f"{name} must be an integer; got {value!r} ({type(value).__name__})")
    value = int(value)
    if minimum is not None and value < minimum:
        raise ValueRangeError(f"{name} must be >= {minimum}; got {value}")
    if maximum is not None and value > maximum:
        raise ValueRangeError(f"{name} must be <= {maximum}; got {value}")
    return value


def check_count(value, name: str, maximum: int | None = None) -> int:
    """A positive integer (>= 1, <= ``maximum``): counts, sizes, chunk lengths."""
    return check_int(value, name, 1, maximum)


def check_seed(value, name: str = "seed") -> int:
    """A random seed: an integer in ``[0, 2**63 - 1]``."""
    return check_int(value, name, 0, MAX_SEED)


def check_real(
    value, name: str, minimum: float | None = None, maximum: float | None = None, finite: bool = True
) -> float:
    """Return ``value`` as a float after checking it is a real number (not a bool or a
    string), finite unless ``finite=False`` (NaN is always refused), in ``[minimum, maximum]``."""
    if _is_tensor(value) and value.numel() == 1:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueRangeError(f"{name} must be a number; got {value!r} ({type(value).__name__})")
    value = float(value)
    if math.isnan(value) or (finite and math.isinf(value)):
        raise ValueRangeError(f"{name} must be a finite number; got {value}")
    if minimum is not None and value < minimum:
        raise ValueRangeError(f"{name} must be >= {minimum:g}; got {value:g}")
    if maximum is not None and value > maximum:
        raise ValueRangeError(f"{name} must be <= {maximum:g}; got {value:g}")
    return value


def check_image_size(width, height, name: str = "image") -> tuple[int, int]:
    """Width and height in ``[1, MAX_IMAGE_SIDE]`` with at most :data:`MAX_IMAGE_PIXELS` pixels."""
    w = check_count(width, f"{name} width", MAX_IMAGE_SIDE)
    h = check_count(height, f"{name} height", MAX_IMAGE_SIDE)
    if w * h > MAX_IMAGE_PIXELS:
        raise ValueRangeError(
            f"{name} size {w}x{h} = {w * h} pixels exceeds the cap of {MAX_IMAGE_PIXELS} (8192 x 8192)"
        )
    return w, h


def check_bool(value, name: str) -> bool:
    """``value`` if it is True or False (not 0, 1 or a string)."""
    if not isinstance(value, bool):
        raise ValueRangeError(f"{name} must be True or False; got {value!r}")
    return value


def check_fields(obj: Any, checks: Mapping[str, Callable[[Any], Any]]) -> None:
    """Check and normalise the fields of a frozen settings dataclass (from its ``__post_init__``):
    ``checks[name](value)`` returns the value kept; the exception of a refused value gets a
    ``setting`` attribute naming the field (so the command line can name it as its option)."""
    for name, check in checks.items():
        try:
            value = check(getattr(obj, name))
        except TorchBRDFError as exc:
            exc.setting = name
            raise
        object.__setattr__(obj, name, value)
