"""The array-file codec: a flipped byte anywhere in the file is refused with FileFormatError."""

from __future__ import annotations

import numpy as np
import pytest

from torch_brdf.errors import FileFormatError
from torch_brdf.io.arrays import load_arrays, save_arrays


@pytest.mark.parametrize("compress", [False, True])
def test_every_single_byte_flip_is_refused(tmp_path, compress):
    arrays = {"a": np.arange(12, dtype=np.float32).reshape(3, 4), "b": np.array([1, 2, 3], dtype=np.int64)}
    path = save_arrays(tmp_path / "x.npz", arrays, kind="test", meta={"passes_done": 3}, compress=compress)
    back, meta = load_arrays(path, kind="test")
    assert meta == {"passes_done": 3}
    assert all(np.array_equal(back[k], v) for k, v in arrays.items())
    raw = path.read_bytes()
    bad = tmp_path / "bad.npz"
    for i in range(len(raw)):  # exhaustive: zip headers, timestamps, metadata, payload, digest
        flipped = bytearray(raw)
        flipped[i] ^= 0x10
        bad.write_bytes(bytes(flipped))
        with pytest.raises(FileFormatError):
            load_arrays(bad, kind="test")


def test_truncations_are_refused(tmp_path):
    path = save_arrays(tmp_path / "x.npz", {"a": np.ones(100)}, kind="test")
    raw = path.read_bytes()
    bad = tmp_path / "bad.npz"
    for n in range(0, len(raw), 7):
        bad.write_bytes(raw[:n])
        with pytest.raises(FileFormatError):
            load_arrays(bad, kind="test")
