"""OpenEXR images as (H, W, 3) linear RGB tensors, through the OpenEXR 3.x Python API.

:func:`read_exr` takes the layouts renderers and image tools write: R, G, B channels
(stored separately or as one ``RGB``/``RGBA`` group), HALF or FLOAT, scanline or tiled;
alpha is dropped. :func:`write_exr` writes one part, scanline, ZIP compression, and
writes atomically: a reader never sees a half-written file, and a failed write leaves
the old file as it was.
"""

from __future__ import annotations

import errno
import os

import numpy as np
import OpenEXR
import torch

from .._checks import as_float_tensor
from ..errors import FileFormatError, ShapeError
from .atomic import replacing

__all__ = ["read_exr", "write_exr"]

_RGB = ("R", "G", "B")


def read_exr(path: str | os.PathLike, allow_gray: bool = False) -> torch.Tensor:
    """Read an OpenEXR file as linear RGB.

    Values come back as stored: NaN, Inf and negative values are not checked here
    (loaders that need radiance >= 0, such as environment maps, check for themselves).
    Only the first part of a multi-part file is read.

    Args:
        path: the ``.exr`` file.
        allow_gray: accept a luminance-only file (channel ``Y``, optionally ``A``) and
            repeat ``Y`` into R, G and B. When False such a file raises.

    Returns:
        image: (H, W, 3) float32 RGB; HALF channels are widened exactly.

    Raises:
        FileFormatError: the file is missing or unreadable (corrupt, truncated, not an
            EXR), or its channels are not R, G, B (+ A), or Y (+ A) with ``allow_gray``.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileFormatError(f"EXR file not found: {path}")
    try:
        with OpenEXR.File(path, separate_channels=True) as f:
            channels = {name: ch.pixels for name, ch in f.channels().items()}
    except (RuntimeError, ValueError) as exc:  # OpenEXR's own errors for unreadable files
        raise FileFormatError(f"Cannot read EXR file {path}: {exc}") from exc

    names = set(channels)
    if set(_RGB) <= names <= {*_RGB, "A"}:
        used = _RGB
    elif allow_gray and "Y" in names and names <= {"Y", "A"}:
        used = ("Y",)
    else:
        hint = "; pass allow_gray=True to read a luminance (Y) file" if "Y" in names else ""
        want = "R, G, B (optionally A)" + (" or Y (optionally A)" if allow_gray else "")
        raise FileFormatError(f"EXR file {path} has channels {sorted(names)}; expected {want}{hint}")
    bad = {c: str(channels[c].dtype) for c in used if channels[c].dtype.kind != "f"}
    if bad:
        raise FileFormatError(f"EXR file {path}: channels {bad} are not HALF or FLOAT")
    if len({channels[c].shape for c in used}) != 1:  # subsampled channels
        shapes = {c: channels[c].shape for c in used}
        raise FileFormatError(f"EXR file {path}: channels have different sizes {shapes}")
    rgb = np.stack([channels[c] for c in used], axis=-1).astype(np.float32)
    return torch.from_numpy(np.repeat(rgb, 3 // len(used), axis=-1))


def write_exr(path: str | os.PathLike, image, half: bool = False) -> None:
    """Write linear RGB to an OpenEXR file: one part, scanline, ZIP compression.

    NaN and Inf are written as they are (EXR stores them, and an image that shows
    where they are is often what one wants when debugging); call
    :func:`torch_brdf._checks.check_finite` first if they must not reach the file.
    float32 values round-trip bit-exactly through :func:`read_exr`.

    The file is written to a temporary name in the same directory and then moved over
    ``path`` with :func:`os.replace`.

    Args:
        path: the ``.exr`` file to create or replace; its directory must exist.
        image: (H, W, 3) tensor or array, any real dtype; gradients are dropped.
        half: store float16 (HALF) instead of float32 (FLOAT). Values are rounded to
            the nearest float16; magnitudes above 65504 become Inf.

    Raises:
        ShapeError: ``image`` is not (H, W, 3) with H, W >= 1.
        FileNotFoundError: the directory of ``path`` does not exist.
    """
    img = as_float_tensor(image, "image")
    if img.ndim != 3 or img.shape[-1] != 3 or img.shape[0] == 0 or img.shape[1] == 0:
        raise ShapeError(f"Expected image to have shape (H, W, 3) with H, W >= 1; got {tuple(img.shape)}")
    # OpenEXR needs C-contiguous pixels: a strided array is written scrambled, silently.
    pixels = img.detach().to("cpu", torch.float16 if half else torch.float32).contiguous()
    # A fresh header each time: OpenEXR.File fills in (mutates) the dict it is given.
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with replacing(path) as tmp, OpenEXR.File(header, {"RGB": pixels.numpy()}) as f:
        try:
            f.write(tmp)
        except RuntimeError as exc:  # OpenEXR's I/O failures (disk full, ...): an OSError
            raise OSError(errno.EIO, f"cannot write EXR ({exc})", os.fspath(path)) from exc
