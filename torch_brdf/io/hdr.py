"""Radiance RGBE (``.hdr``, ``.pic``) images as (H, W, 3) linear RGB tensors.

The format (Ward, *Real Pixels*, Graphics Gems II, 1991): a text header (``#?RADIANCE`` or
``#?RGBE``, ``FORMAT=32-bit_rle_rgbe``, an empty line), a resolution line ``-Y H +X W``,
then H scanlines of W pixels of 4 bytes (R, G, B mantissas and a shared exponent
:math:`e`: value :math:`= (m + 0.5)\\,2^{e-136}`, 0 where :math:`e = 0`), each scanline
either flat or run-length encoded per channel ("new RLE", the form every tool writes).
Only the standard orientation (``-Y H +X W``, row 0 at the top) and the RGBE format are
read; XYZE, other orientations and the old RLE are refused by name. Sizes are bounded
(:data:`~torch_brdf._checks.MAX_IMAGE_PIXELS`) before anything is allocated.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from .._checks import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE
from ..errors import FileFormatError
from .atomic import replacing

__all__ = ["read_hdr", "write_hdr"]

_MAX_HEADER = 64 * 1024


def _header(data: bytes, path: str) -> tuple[int, int, int]:
    """(height, width, offset of the pixel data)."""
    if not data.startswith((b"#?RADIANCE", b"#?RGBE")):
        raise FileFormatError(f"{path} is not a Radiance HDR file (no '#?RADIANCE' signature)")
    end = data.find(b"\n\n", 0, _MAX_HEADER)
    if end < 0:
        raise FileFormatError(f"{path}: Radiance header has no end (an empty line) within {_MAX_HEADER} bytes")
    for line in data[:end].split(b"\n"):
        if line.startswith(b"FORMAT=") and line.strip() != b"FORMAT=32-bit_rle_rgbe":
            raise FileFormatError(f"{path}: unsupported Radiance format {line.decode(errors='replace')!r}; only RGBE")
    nl = data.find(b"\n", end + 2, end + 2 + 256)
    if nl < 0:
        raise FileFormatError(f"{path}: Radiance resolution line missing")
    parts = data[end + 2 : nl].split()
    if len(parts) != 4 or parts[0] != b"-Y" or parts[2] != b"+X" or not (parts[1].isdigit() and parts[3].isdigit()):
        raise FileFormatError(
            f"{path}: unsupported Radiance resolution line {data[end + 2 : nl][:40]!r}; expected '-Y H +X W'"
        )
    h, w = int(parts[1]), int(parts[3])
    if not (1 <= h <= MAX_IMAGE_SIDE and 1 <= w <= MAX_IMAGE_SIDE) or h * w > MAX_IMAGE_PIXELS:
        raise FileFormatError(f"{path}: image size {w}x{h} outside the caps ({MAX_IMAGE_SIDE} a side)")
    return h, w, nl + 1


def _scanlines(buf: np.ndarray, h: int, w: int, path: str) -> np.ndarray:
    out = np.empty((h, w, 4), np.uint8)
    pos, n = 0, len(buf)
    for y in range(h):
        if pos + 4 > n:
            raise FileFormatError(f"{path}: truncated at scanline {y} of {h}")
        head = buf[pos : pos + 4]
        if 8 <= w < 32768 and head[0] == 2 and head[1] == 2 and head[2] < 128:
            if (int(head[2]) << 8) | int(head[3]) != w:
                raise FileFormatError(f"{path}: scanline {y} has length {(int(head[2]) << 8) | int(head[3])}, not {w}")
            pos += 4
            for c in range(4):
                x = 0
                while x < w:
                    if pos >= n:
                        raise FileFormatError(f"{path}: truncated in scanline {y}")
                    count = int(buf[pos])
                    pos += 1
                    if count > 128:  # a run
                        count -= 128
                        if x + count > w or pos >= n:
                            raise FileFormatError(f"{path}: bad run length in scanline {y}")
                        out[y, x : x + count, c] = buf[pos]
                        pos += 1
                    else:
                        if count == 0 or x + count > w or pos + count > n:
                            raise FileFormatError(f"{path}: bad literal length in scanline {y}")
                        out[y, x : x + count, c] = buf[pos : pos + count]
                        pos += count
                    x += count
        else:  # flat pixels (old RLE is not supported: rare, and refused by the run marker)
            if head[0] == 1 and head[1] == 1 and head[2] == 1:
                raise FileFormatError(f"{path}: old-style Radiance run-length encoding is not supported")
            if pos + 4 * w > n:
                raise FileFormatError(f"{path}: truncated at scanline {y} of {h}")
            out[y] = buf[pos : pos + 4 * w].reshape(w, 4)
            pos += 4 * w
    return out


def read_hdr(path: str | os.PathLike) -> torch.Tensor:
    """Read a Radiance RGBE file as linear RGB.

    Args:
        path: the ``.hdr`` file.
    Returns:
        image: (H, W, 3) float32, row 0 at the top.
    Raises:
        FileFormatError: missing, not Radiance RGBE, an unsupported variant, truncated or corrupt.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileFormatError(f"Radiance HDR file not found: {path}")
    size = os.path.getsize(path)
    if size > 5 * MAX_IMAGE_PIXELS + _MAX_HEADER:
        raise FileFormatError(f"{path}: {size} bytes is larger than any image within the caps")
    with open(path, "rb") as f:
        data = f.read()
    h, w, off = _header(data, path)
    rgbe = _scanlines(np.frombuffer(data, np.uint8, offset=off), h, w, path)
    e = rgbe[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    rgb = (rgbe[..., :3].astype(np.float64) + 0.5) * scale[..., None]
    return torch.from_numpy(rgb.astype(np.float32))


def _encode_rows(rgbe: np.ndarray) -> bytes:
    """Scanlines in the new run-length layout with literal runs only (readers recognise a
    scanline by its header; a flat scanline whose first pixel is (2, 2, <128, .) would be
    misread as run-length encoded, so widths 8..32767 are always written in this layout)."""
    h, w = rgbe.shape[:2]
    if not 8 <= w < 32768:
        return rgbe.tobytes()
    out = bytearray()
    for y in range(h):
        out += bytes([2, 2, w >> 8, w & 255])
        for c in range(4):
            ch = rgbe[y, :, c]
            for x in range(0, w, 128):
                chunk = ch[x : x + 128]
                out.append(len(chunk))
                out += chunk.tobytes()
    return bytes(out)


def write_hdr(path: str | os.PathLike, image) -> None:
    """Write (H, W, 3) linear RGB (values >= 0) as an RGBE file (RGBE keeps 8 bits of mantissa
    of each pixel's largest channel), atomically.

    Args:
        path: the ``.hdr`` file.
        image: (H, W, 3) tensor or array.
    """
    a = np.asarray(torch.as_tensor(image).detach().cpu().double().numpy())
    if a.ndim != 3 or a.shape[2] != 3:
        raise FileFormatError(f"write_hdr expects an (H, W, 3) image; got shape {a.shape}")
    a = np.clip(np.nan_to_num(a, nan=0.0, posinf=0.0), 0.0, None)
    m = a.max(-1)
    mant, exp = np.frexp(m)
    ok = m > 1e-32
    scale = np.where(ok, mant * 256.0 / np.where(ok, m, 1.0), 0.0)
    rgbe = np.zeros(a.shape[:2] + (4,), np.uint8)
    rgbe[..., :3] = np.clip(np.floor(a * scale[..., None]), 0, 255).astype(np.uint8)
    rgbe[..., 3] = np.where(ok, exp + 128, 0).astype(np.uint8)
    head = f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {a.shape[0]} +X {a.shape[1]}\n".encode()
    with replacing(os.fspath(path)) as tmp, open(tmp, "wb") as f:
        f.write(head + _encode_rows(rgbe))
