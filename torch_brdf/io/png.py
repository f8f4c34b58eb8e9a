"""8-bit sRGB PNG output for linear radiance, and a reader for the files written here.

:func:`to_srgb8` turns (H, W, 3) linear RGB radiance into display values: exposure, tone
map, sRGB encoding (IEC 61966-2-1, through colour-science), rounding to 8 bits.
:func:`write_png` stores them as an 8-bit RGB PNG with an ``sRGB`` chunk. No imaging
library is a dependency, so the PNG is encoded here with zlib and struct (PNG spec,
ISO/IEC 15948); :func:`read_png` decodes what :func:`write_png` writes.
"""

from __future__ import annotations

import math
import os
import struct
import warnings
import zlib
from collections.abc import Iterator

import numpy as np
import torch

from .._checks import check_finite
from ..errors import FileFormatError, ShapeError, ValueRangeError
from .atomic import replacing

__all__ = ["TONEMAPS", "auto_exposure", "read_png", "to_srgb8", "write_png"]

TONEMAPS = ("clip", "reinhard", "aces")
"""Tone maps accepted by :func:`to_srgb8` and :func:`write_png`."""

_LUMA = (0.2126, 0.7152, 0.0722)  # luminance Y of linear sRGB / Rec. 709 primaries
_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def auto_exposure(image, percentile: float = 99.0, limit: float = 20.0) -> float:
    """Exposure in stops for a preview: the ``percentile`` of the luminance of the pixels
    with light (luminance > 0) goes to 1 (white), clamped to ``[-limit, limit]``; 0 for an
    all-black image. Only for display (PNG): the EXR stays linear.

    Args:
        image: (H, W, 3) linear RGB radiance.
    """
    x = torch.as_tensor(np.asarray(image) if not torch.is_tensor(image) else image).detach().double()
    lum = (x[..., 0] * 0.2126 + x[..., 1] * 0.7152 + x[..., 2] * 0.0722).reshape(-1)
    lum = lum[torch.isfinite(lum) & (lum > 0)]
    if lum.numel() == 0:
        return 0.0
    p = float(torch.quantile(lum, percentile / 100.0)) if lum.numel() < 1 << 24 else float(lum.max())
    return float(min(limit, max(-limit, -math.log2(p))))


def to_srgb8(image, exposure: float = 0.0, tonemap: str = "clip") -> torch.Tensor:
    r"""Turn linear RGB radiance into 8-bit sRGB display values.

    Steps, in float64: negative values clip to 0; multiply by :math:`2^{exposure}`; tone
    map into [0, 1]; sRGB encoding (the IEC 61966-2-1 piecewise curve,
    ``colour.cctf_encoding(x, function="sRGB")``); round to the nearest of 0..255.
    With ``"clip"``, linear 0 -> 0, 0.5 -> 188 and anything >= 1 -> 255.

    Tone maps, with :math:`x` a channel value and :math:`L = 0.2126 R + 0.7152 G +
    0.0722 B` the luminance:

    - ``"clip"``: :math:`\min(x, 1)`.
    - ``"reinhard"``: the simple global operator of Reinhard et al. 2002, "Photographic
      Tone Reproduction for Digital Images", eq. 3, :math:`L_d = L / (1 + L)`, applied to
      luminance: every channel is divided by :math:`1 + L`, which keeps hue and
      saturation. A bright saturated colour can still have a channel above 1; it clips.
    - ``"aces"``: Narkowicz 2015, "ACES Filmic Tone Mapping Curve", per channel
      :math:`x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14)`, clipped to [0, 1]. The
      curve as published: it lifts mid-grey (0.18 -> 0.27).

    Args:
        image: (H, W, 3) linear RGB radiance, floating-point tensor or array;
            gradients are dropped.
        exposure: in stops; the image is multiplied by ``2 ** exposure``.
        tonemap: one of :data:`TONEMAPS`.

    Returns:
        (H, W, 3) uint8 sRGB-encoded values, on the CPU.

    Raises:
        ShapeError: ``image`` is not (H, W, 3) or not floating point (8-bit images are
            already encoded; this function is for radiance).
        ValueRangeError: ``image`` holds NaN/Inf (the message counts them), ``exposure``
            is not finite, or ``tonemap`` is unknown.
    """
    img = image if isinstance(image, torch.Tensor) else torch.as_tensor(image)
    if img.ndim != 3 or img.shape[-1] != 3 or not img.is_floating_point():
        raise ShapeError(
            "Expected image to be floating-point linear RGB of shape (H, W, 3); "
            f"got shape {tuple(img.shape)}, dtype {img.dtype}"
        )
    if tonemap not in TONEMAPS:
        raise ValueRangeError(f"tonemap must be one of {TONEMAPS}; got {tonemap!r}")
    if not math.isfinite(exposure):
        raise ValueRangeError(f"exposure must be a finite number of stops; got {exposure}")
    check_finite(img, "image")

    x = img.detach().to("cpu", torch.float64).clamp(min=0.0)
    # Bounding the exposure and the scaled values keeps everything finite (no inf/inf);
    # every tone map has saturated long before 1e30.
    x = (x * 2.0 ** min(max(exposure, -1000.0), 1000.0)).clamp(max=1e30)
    if tonemap == "reinhard":
        x = x / (1.0 + x @ x.new_tensor(_LUMA))[..., None]
    elif tonemap == "aces":
        x = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14)
    v = _srgb_encode(x.clamp(0.0, 1.0).numpy())
    return torch.from_numpy(np.rint(v * 255.0).astype(np.uint8))


def write_png(path: str | os.PathLike, image, exposure: float = 0.0, tonemap: str = "clip") -> None:
    """Write linear RGB radiance as an 8-bit sRGB PNG.

    The pixels are :func:`to_srgb8` of ``image``. The file is 8-bit RGB (colour type 2),
    non-interlaced, with an ``sRGB`` chunk (rendering intent 0, perceptual) so viewers
    know the encoding, plus the matching ``gAMA`` and ``cHRM`` chunks that the PNG spec
    recommends for decoders that ignore ``sRGB``. It is written to a temporary name in
    the same directory and moved over ``path`` with :func:`os.replace`, so nothing is
    written when the image is rejected.

    Args:
        path: the ``.png`` file to create or replace; its directory must exist.
        image: (H, W, 3) linear RGB radiance, floating point, H, W >= 1.
        exposure: in stops; the image is multiplied by ``2 ** exposure``.
        tonemap: one of :data:`TONEMAPS`; see :func:`to_srgb8`.

    Raises:
        ShapeError: ``image`` is not floating point of shape (H, W, 3) with H, W >= 1.
        ValueRangeError: as :func:`to_srgb8` (NaN/Inf never become a silent image).
        FileNotFoundError: the directory of ``path`` does not exist.
    """
    rgb8 = to_srgb8(image, exposure, tonemap)
    if rgb8.shape[0] == 0 or rgb8.shape[1] == 0:
        raise ShapeError(f"Expected image with H, W >= 1 for a PNG; got {tuple(rgb8.shape)}")
    with replacing(path) as tmp, open(tmp, "wb") as f:
        f.write(_encode_png(rgb8.numpy()))


def read_png(path: str | os.PathLike) -> torch.Tensor:
    """Read an 8-bit RGB PNG of the kind :func:`write_png` writes.

    This is a small decoder, not a general one: it reads 8-bit RGB (colour type 2),
    non-interlaced files whose rows use filter type 0 (None), and says so when a file
    is otherwise. Chunk CRCs are checked. The values are returned as stored (sRGB
    encoded); no colour conversion is applied.

    Args:
        path: the ``.png`` file.

    Returns:
        (H, W, 3) uint8 tensor.

    Raises:
        FileFormatError: the file is missing, not a PNG, truncated or corrupt, or in a
            layout this decoder does not read.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileFormatError(f"PNG file not found: {path}")
    with open(path, "rb") as f:
        data = f.read()
    ihdr, idat = None, []
    for ctype, body in _chunks(data, path):
        if ctype == b"IHDR" and len(body) == 13:
            ihdr = struct.unpack(">IIBBBBB", body)
        elif ctype == b"IDAT":
            idat.append(body)
    if ihdr is None:
        raise FileFormatError(f"PNG file {path} has no valid IHDR chunk")
    w, h, depth, colour_type, _, _, interlace = ihdr
    if (depth, colour_type, interlace) != (8, 2, 0):
        raise FileFormatError(
            f"PNG file {path} has bit depth {depth}, colour type {colour_type}, interlace "
            f"{interlace}; read_png reads 8-bit RGB only (8, 2, 0)"
        )
    try:
        raw = zlib.decompress(b"".join(idat))
    except zlib.error as exc:
        raise FileFormatError(f"PNG file {path}: image data is corrupt ({exc})") from exc
    if len(raw) != h * (1 + 3 * w):
        raise FileFormatError(
            f"PNG file {path}: image data has {len(raw)} bytes; expected {h * (1 + 3 * w)} for {w} x {h} RGB"
        )
    rows = np.frombuffer(raw, np.uint8).reshape(h, 1 + 3 * w)
    if rows[:, 0].any():
        filters = sorted({int(t) for t in rows[:, 0]})
        raise FileFormatError(
            f"PNG file {path} uses row filter types {filters}; read_png reads only "
            "type 0 (None), which is what write_png writes"
        )
    return torch.from_numpy(rows[:, 1:].reshape(h, w, 3).copy())


def _srgb_encode(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding of linear values in [0, 1], by colour-science."""
    with warnings.catch_warnings():
        # Imported here: it takes a second, and it warns that matplotlib is missing,
        # which matters only for its plotting.
        warnings.filterwarnings("ignore", message='"Matplotlib" related API features')
        import colour
    with colour.domain_range_scale("1"):  # colour's scale is global state; pin it
        return colour.cctf_encoding(x, function="sRGB")


def _encode_png(rgb8: np.ndarray) -> bytes:
    """(H, W, 3) uint8 -> bytes of an 8-bit RGB PNG, every row with filter type 0."""
    h, w, _ = rgb8.shape
    raw = np.zeros((h, 1 + 3 * w), np.uint8)  # the leading 0 of each row: filter None
    raw[:, 1:] = rgb8.reshape(h, 3 * w)
    chunks = [
        # width, height, bit depth 8, colour type 2 (RGB), deflate, filter method 0, no interlace
        (b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)),
        (b"sRGB", b"\x00"),  # rendering intent 0: perceptual
        # The gAMA and cHRM values the PNG spec's sRGB section asks to go with it.
        (b"gAMA", struct.pack(">I", 45455)),
        (b"cHRM", struct.pack(">8I", 31270, 32900, 64000, 33000, 30000, 60000, 15000, 6000)),
        (b"IDAT", zlib.compress(raw.tobytes())),
        (b"IEND", b""),
    ]
    return _SIGNATURE + b"".join(
        struct.pack(">I", len(body)) + ctype + body + struct.pack(">I", zlib.crc32(ctype + body))
        for ctype, body in chunks
    )


def _chunks(data: bytes, path: str) -> Iterator[tuple[bytes, bytes]]:
    """Yield (type, body) of each PNG chunk up to IEND, checking lengths and CRCs."""
    if not data.startswith(_SIGNATURE):
        raise FileFormatError(f"{path} is not a PNG file (no PNG signature)")
    pos = len(_SIGNATURE)
    while True:
        if pos + 12 > len(data):
            raise FileFormatError(f"PNG file {path} is truncated (no IEND chunk)")
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        ctype, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        crc = data[pos + 8 + n : pos + 12 + n]
        if len(crc) < 4:
            raise FileFormatError(f"PNG file {path} is truncated (in chunk {ctype!r})")
        if struct.unpack(">I", crc)[0] != zlib.crc32(ctype + body):
            raise FileFormatError(f"PNG file {path}: chunk {ctype!r} fails its CRC (corrupt)")
        yield ctype, body
        if ctype == b"IEND":
            return
        pos += 12 + n
