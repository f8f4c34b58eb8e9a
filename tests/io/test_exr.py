"""OpenEXR read/write: bit-exact round trips, accepted layouts, and clear errors."""

from __future__ import annotations

import os

import numpy as np
import OpenEXR
import pytest
import torch

from torch_brdf.errors import FileFormatError, ShapeError
from torch_brdf.io import read_exr, write_exr


def _write_raw(path, channels: dict) -> None:
    """Write channels with OpenEXR directly: layouts other tools produce."""
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


def _random_image(h=7, w=5, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(h, w, 3, generator=g) * 10.0


def test_float32_round_trip_is_bit_exact(tmp_path):
    # Random bit patterns cover every exponent: denormals, tiny, huge, and NaN payloads.
    g = torch.Generator().manual_seed(1)
    bits = torch.randint(-(2**31), 2**31, (33, 17, 3), generator=g).to(torch.int32)
    img = bits.view(torch.float32).clone()
    special = torch.tensor([0.0, -0.0, 1e-45, -1e-45, 1e-40, 1.1754944e-38, 3.4e38, -3.4e38])
    img.view(-1)[: special.numel()] = special
    path = tmp_path / "img.exr"
    write_exr(path, img)
    back = read_exr(path)
    assert back.dtype == torch.float32 and back.shape == (33, 17, 3)
    assert torch.equal(back.view(torch.int32), img.view(torch.int32))


def test_nonfinite_values_are_written(tmp_path):
    img = torch.ones(2, 3, 3)
    img[0, 0, 0], img[1, 2, 1], img[1, 1, 2] = float("nan"), float("inf"), -float("inf")
    write_exr(tmp_path / "a.exr", img)
    back = read_exr(tmp_path / "a.exr")
    assert torch.equal(torch.isnan(back), torch.isnan(img))
    assert torch.equal(back.nan_to_num(0.0), img.nan_to_num(0.0))


def test_half_round_trip_and_stored_type(tmp_path):
    img = _random_image().half().float()  # exactly representable in float16
    path = tmp_path / "h.exr"
    write_exr(path, img, half=True)
    assert torch.equal(read_exr(path), img)
    with OpenEXR.File(str(path), separate_channels=True) as f:
        types = {name: ch.type() for name, ch in f.channels().items()}
    assert types == dict.fromkeys("RGB", OpenEXR.HALF)


def test_header_is_zip_scanline_float(tmp_path):
    path = tmp_path / "f.exr"
    write_exr(path, _random_image())
    with OpenEXR.File(str(path), separate_channels=True) as f:
        header = dict(f.header())  # the live dict is emptied on close
        types = {name: ch.type() for name, ch in f.channels().items()}
    assert header["compression"] == OpenEXR.ZIP_COMPRESSION
    assert header["type"] == OpenEXR.scanlineimage
    assert types == dict.fromkeys("RGB", OpenEXR.FLOAT)


def test_accepts_ndarray_float64_noncontiguous_and_grad(tmp_path):
    base = _random_image(6, 8).double()
    write_exr(tmp_path / "a.exr", base.numpy()[:, ::2])  # strided view
    assert torch.equal(read_exr(tmp_path / "a.exr"), base[:, ::2].float())
    write_exr(str(tmp_path / "b.exr"), base.float().requires_grad_())
    assert torch.equal(read_exr(str(tmp_path / "b.exr")), base.float())


@pytest.mark.parametrize("dtype", ["e", "f"])
def test_reads_separate_channels_and_drops_alpha(tmp_path, dtype):
    rgb = _random_image().numpy().astype(dtype)
    chans = {"R": rgb[..., 0].copy(), "G": rgb[..., 1].copy(), "B": rgb[..., 2].copy()}
    _write_raw(tmp_path / "rgba.exr", {**chans, "A": np.ones(rgb.shape[:2], dtype)})
    assert torch.equal(read_exr(tmp_path / "rgba.exr"), torch.from_numpy(rgb.astype("f")))
    rgba = np.concatenate([rgb, np.ones((*rgb.shape[:2], 1), dtype)], axis=-1)
    _write_raw(tmp_path / "group.exr", {"RGBA": rgba})
    assert torch.equal(read_exr(tmp_path / "group.exr"), torch.from_numpy(rgb.astype("f")))


def test_reads_mixed_half_and_float_channels(tmp_path):
    rgb = _random_image().half().float().numpy()
    _write_raw(
        tmp_path / "m.exr",
        {"R": rgb[..., 0].astype("e"), "G": rgb[..., 1].copy(), "B": rgb[..., 2].copy()},
    )
    assert torch.equal(read_exr(tmp_path / "m.exr"), torch.from_numpy(rgb))


def test_gray_needs_allow_gray(tmp_path):
    y = _random_image()[..., 0].numpy()
    _write_raw(tmp_path / "y.exr", {"Y": y.copy()})
    with pytest.raises(FileFormatError, match=r"\['Y'\].*allow_gray=True"):
        read_exr(tmp_path / "y.exr")
    img = read_exr(tmp_path / "y.exr", allow_gray=True)
    assert img.shape == (*y.shape, 3)
    assert all(torch.equal(img[..., c], torch.from_numpy(y)) for c in range(3))


@pytest.mark.parametrize(
    "names",
    [("R", "G"), ("R", "G", "B", "Z"), ("diffuse.R", "diffuse.G", "diffuse.B"), ("Y", "R")],
)
def test_wrong_channels_are_named(tmp_path, names):
    _write_raw(tmp_path / "c.exr", {n: np.ones((2, 3), "f") for n in names})
    with pytest.raises(FileFormatError) as info:
        read_exr(tmp_path / "c.exr", allow_gray=True)
    msg = str(info.value)
    assert str(sorted(names)) in msg and "expected R, G, B" in msg and "c.exr" in msg


def test_uint_channels_are_rejected(tmp_path):
    _write_raw(tmp_path / "u.exr", {c: np.ones((2, 2), np.uint32) for c in "RGB"})
    with pytest.raises(FileFormatError, match="not HALF or FLOAT"):
        read_exr(tmp_path / "u.exr")


def test_missing_file(tmp_path):
    with pytest.raises(FileFormatError, match=r"EXR file not found: .*nope\.exr"):
        read_exr(tmp_path / "nope.exr")


@pytest.mark.parametrize("cut", [0, 4, 100, 350, -5])
def test_truncated_or_garbage_file_names_path(tmp_path, cut):
    path = tmp_path / "t.exr"
    write_exr(path, _random_image(64, 64))
    data = path.read_bytes()
    path.write_bytes(data[:cut] if cut else b"not an exr file at all")
    with pytest.raises(FileFormatError, match=r"t\.exr") as info:
        read_exr(path)
    assert isinstance(info.value.__cause__, (RuntimeError, ValueError))


@pytest.mark.parametrize("shape", [(4, 5), (4, 5, 4), (1, 4, 5, 3), (0, 5, 3), (4, 0, 3)])
def test_write_shape_errors(tmp_path, shape):
    with pytest.raises(ShapeError, match=r"\(H, W, 3\)"):
        write_exr(tmp_path / "s.exr", torch.zeros(shape))
    assert os.listdir(tmp_path) == []


def test_write_replaces_atomically_and_leaves_no_temp(tmp_path, monkeypatch):
    path = tmp_path / "a.exr"
    write_exr(path, _random_image(seed=1))
    write_exr(path, _random_image(seed=2))  # overwrite
    assert torch.equal(read_exr(path), _random_image(seed=2))
    assert os.listdir(tmp_path) == ["a.exr"]

    def fail(self, filename):
        with open(filename, "wb") as f:  # a half-written temp file, then a crash
            f.write(b"partial")
        raise RuntimeError("disk full")

    monkeypatch.setattr(OpenEXR.File, "write", fail)
    with pytest.raises(OSError, match="disk full"):  # OpenEXR's RuntimeError becomes an OSError (the CLI's I/O line)
        write_exr(path, _random_image(seed=3))
    monkeypatch.undo()
    assert torch.equal(read_exr(path), _random_image(seed=2))  # old file intact
    assert os.listdir(tmp_path) == ["a.exr"]


def test_write_into_missing_directory(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        write_exr(tmp_path / "no" / "a.exr", _random_image())
