"""8-bit sRGB output: the encoding curve, tone maps, the PNG file layout, and errors.

The oracles here are independent of the code under test: the sRGB curve is written out
from IEC 61966-2-1, and PNG files are parsed with struct + zlib directly.
"""

from __future__ import annotations

import os
import struct
import zlib

import numpy as np
import pytest
import torch

from torch_brdf.errors import FileFormatError, ShapeError, ValueRangeError
from torch_brdf.io import TONEMAPS, read_png, to_srgb8, write_png


def _srgb8_oracle(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding of values in [0, 1], rounded to 8 bits."""
    v = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
    return np.floor(v * 255.0 + 0.5).astype(np.uint8)


def _chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    out, pos = [], 8
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        ctype, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        assert struct.unpack(">I", data[pos + 8 + n : pos + 12 + n])[0] == zlib.crc32(ctype + body)
        out.append((ctype, body))
        pos += 12 + n
    return out


def _gray(*values) -> torch.Tensor:
    """A (1, N, 3) image of grey pixels."""
    return torch.tensor(values, dtype=torch.float32)[None, :, None].expand(1, len(values), 3)


def test_clip_anchor_values():
    out = to_srgb8(_gray(0.0, 0.5, 1.0, 7.0, 1e30, -0.25))
    assert out.dtype == torch.uint8 and out.shape == (1, 6, 3)
    assert out[0, :, 0].tolist() == [0, 188, 255, 255, 255, 0]
    assert round(255 * (1.055 * 0.5 ** (1 / 2.4) - 0.055)) == 188


def test_clip_matches_srgb_oracle_on_a_ramp():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(16, 32, 3, generator=g, dtype=torch.float64)
    x[0, :, 0] = torch.linspace(0, 0.01, 32, dtype=torch.float64)  # the linear toe
    assert np.array_equal(to_srgb8(x).numpy(), _srgb8_oracle(x.numpy()))


def test_exposure_is_in_stops():
    x = _gray(0.02, 0.1, 0.25, 0.4)
    assert torch.equal(to_srgb8(x, exposure=1.0), to_srgb8(2 * x))
    assert torch.equal(to_srgb8(x, exposure=-2.0), to_srgb8(x / 4))
    assert to_srgb8(x, exposure=5000.0).eq(255).all()
    assert to_srgb8(x, exposure=-5000.0).eq(0).all()


def test_reinhard_on_luminance_keeps_hue():
    x = torch.tensor([[[0.2, 0.1, 0.05], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [3.0, 0.5, 0.1]]])
    lum = (x.double() @ torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64))[..., None]
    expect = _srgb8_oracle(np.clip((x.double() / (1 + lum)).numpy(), 0, 1))
    out = to_srgb8(x, tonemap="reinhard")
    assert np.array_equal(out.numpy(), expect)
    assert out[0, 1].tolist() == [188] * 3  # grey L = 1 -> 0.5


def test_aces_curve():
    x = _gray(0.0, 0.18, 1.0, 1e6)
    v = x[0, :, 0].double().numpy()
    expect = _srgb8_oracle(np.clip(v * (2.51 * v + 0.03) / (v * (2.43 * v + 0.59) + 0.14), 0, 1))
    out = to_srgb8(x, tonemap="aces")[0, :, 0]
    assert out.tolist() == expect.tolist()
    assert out[0] == 0 and out[-1] == 255


@pytest.mark.parametrize("tonemap", TONEMAPS)
def test_tonemaps_are_monotone_and_bounded(tonemap):
    x = _gray(*np.geomspace(1e-4, 1e4, 200).tolist())
    out = to_srgb8(x, tonemap=tonemap)[0, :, 0].int()
    assert (out.diff() >= 0).all() and out[0] <= 1 and out[-1] == 255


def test_input_kinds():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(4, 5, 3, generator=g)
    ref = to_srgb8(x)
    assert torch.equal(to_srgb8(x.numpy()), ref)
    assert torch.equal(to_srgb8(x.double()), ref)
    assert torch.equal(to_srgb8(x.clone().requires_grad_()), ref)


def test_nonfinite_raise_with_counts(tmp_path):
    x = torch.ones(3, 3, 3)
    x[0, 0, 0], x[1, 1, 1], x[2, 2, 2] = float("nan"), float("inf"), -float("inf")
    with pytest.raises(ValueRangeError, match=r"1 NaN, 2 Inf"):
        to_srgb8(x)
    with pytest.raises(ValueRangeError, match=r"1 NaN, 2 Inf"):
        write_png(tmp_path / "x.png", x)
    assert os.listdir(tmp_path) == []


def test_bad_arguments():
    with pytest.raises(ValueRangeError, match="tonemap must be one of"):
        to_srgb8(torch.ones(2, 2, 3), tonemap="filmic")
    with pytest.raises(ValueRangeError, match="exposure"):
        to_srgb8(torch.ones(2, 2, 3), exposure=float("nan"))
    for bad in (torch.ones(2, 2), torch.ones(2, 2, 4), torch.ones(2, 2, 3, dtype=torch.uint8)):
        with pytest.raises(ShapeError, match=r"\(H, W, 3\)"):
            to_srgb8(bad)


def test_png_layout(tmp_path):
    path = tmp_path / "a.png"
    write_png(path, torch.full((5, 7, 3), 0.5))
    chunks = _chunks(path.read_bytes())
    types = [c for c, _ in chunks]
    assert types[0] == b"IHDR" and types[-1] == b"IEND"
    assert types.index(b"sRGB") < types.index(b"IDAT")
    w, h, depth, colour_type, comp, filt, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    assert (w, h, depth, colour_type, comp, filt, interlace) == (7, 5, 8, 2, 0, 0, 0)
    assert dict(chunks)[b"sRGB"] == b"\x00"  # rendering intent 0
    raw = zlib.decompress(b"".join(b for c, b in chunks if c == b"IDAT"))
    assert raw == (b"\x00" + bytes([188]) * 21) * 5


def test_write_read_round_trip(tmp_path):
    g = torch.Generator().manual_seed(3)
    x = torch.rand(13, 9, 3, generator=g) * 4
    for tonemap in TONEMAPS:
        path = tmp_path / f"{tonemap}.png"
        write_png(path, x, exposure=-0.5, tonemap=tonemap)
        assert torch.equal(read_png(path), to_srgb8(x, exposure=-0.5, tonemap=tonemap))


def test_write_replaces_atomically(tmp_path):
    path = tmp_path / "a.png"
    write_png(path, torch.zeros(2, 2, 3))
    write_png(str(path), torch.ones(2, 2, 3))
    assert read_png(path).eq(255).all()
    with pytest.raises(ValueRangeError):
        write_png(path, torch.full((2, 2, 3), float("nan")))
    with pytest.raises(ShapeError):
        write_png(path, torch.zeros(0, 2, 3))
    assert read_png(path).eq(255).all() and os.listdir(tmp_path) == ["a.png"]
    with pytest.raises(FileNotFoundError, match="does not exist"):
        write_png(tmp_path / "no" / "a.png", torch.zeros(2, 2, 3))


def test_read_png_errors(tmp_path):
    with pytest.raises(FileFormatError, match="PNG file not found"):
        read_png(tmp_path / "nope.png")
    path = tmp_path / "a.png"
    write_png(path, torch.rand(4, 4, 3, generator=torch.Generator().manual_seed(0)))
    good = path.read_bytes()
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"GIF89a" + good[6:])
    with pytest.raises(FileFormatError, match="not a PNG"):
        read_png(bad)
    bad.write_bytes(good[:-20])
    with pytest.raises(FileFormatError, match="truncated"):
        read_png(bad)
    flipped = bytearray(good)
    flipped[-20] ^= 0xFF  # inside the IDAT data
    bad.write_bytes(bytes(flipped))
    with pytest.raises(FileFormatError, match="CRC"):
        read_png(bad)


def test_read_png_rejects_layouts_it_does_not_decode(tmp_path):
    def png(ihdr: bytes, raw: bytes) -> bytes:
        def chunk(t, b):
            return struct.pack(">I", len(b)) + t + b + struct.pack(">I", zlib.crc32(t + b))

        idat = chunk(b"IDAT", zlib.compress(raw))
        return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + idat + chunk(b"IEND", b"")

    path = tmp_path / "x.png"
    path.write_bytes(png(struct.pack(">IIBBBBB", 1, 1, 8, 6, 0, 0, 0), b"\x00" + b"\x01" * 4))
    with pytest.raises(FileFormatError, match="colour type 6"):
        read_png(path)
    path.write_bytes(png(struct.pack(">IIBBBBB", 1, 2, 8, 2, 0, 0, 0), b"\x00abc\x02abc"))
    with pytest.raises(FileFormatError, match=r"filter types \[0, 2\]"):
        read_png(path)
