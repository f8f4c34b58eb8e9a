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


def test_save_streams_without_an_image_of_the_file_in_memory(tmp_path):
    """Saving a 128 MiB array allocates a bounded amount (chunks), not copies of the file."""
    import tracemalloc

    a = np.arange(16 << 20, dtype=np.float64)  # 128 MiB
    tracemalloc.start()
    try:
        save_arrays(tmp_path / "big.npz", {"a": a}, "test")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 0.4 * a.nbytes, f"peak {peak / 2**20:.0f} MiB while saving {a.nbytes / 2**20:.0f} MiB"
    got, _ = load_arrays(tmp_path / "big.npz", "test")
    assert np.array_equal(got["a"], a)


def test_files_of_the_in_memory_encoder_still_load(tmp_path):
    """Files written by numpy's savez into memory, with the digest appended (how files were
    written before saves streamed), load; and a streamed save reads back with numpy too."""
    import hashlib
    import io
    import json

    from torch_brdf.io import arrays as codec

    arrays = {"x": np.arange(12.0).reshape(3, 4), "f": np.asfortranarray(np.ones((2, 3), np.float32))}
    header = {"format": codec.FORMAT, "kind": "k", "version": 1, "meta": {"a": 1}, "checksum": codec._checksum(arrays)}
    header["file_digest"] = True
    blob = np.frombuffer(json.dumps(header, sort_keys=True).encode(), dtype=np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays, __header__=blob)
    raw = buf.getvalue()
    comment = codec._DIGEST + hashlib.sha256(raw[:-2]).hexdigest().encode()
    (tmp_path / "old.npz").write_bytes(raw[:-2] + len(comment).to_bytes(2, "little") + comment)
    got, meta = load_arrays(tmp_path / "old.npz", "k")
    assert meta == {"a": 1} and all(np.array_equal(got[k], v) for k, v in arrays.items())
    save_arrays(tmp_path / "new.npz", arrays, "k", {"a": 1})
    with np.load(tmp_path / "new.npz") as z:
        assert np.array_equal(z["f"], arrays["f"]) and z["f"].flags.f_contiguous
