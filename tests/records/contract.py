"""The contract every saved record keeps (inherit :class:`RecordContract`).

A subclass defines :meth:`RecordContract.make` (a small record) and
:meth:`RecordContract.assert_same` (what a faithful round trip keeps); it inherits the tests:
the round trip, refusal of a corrupt file, of a truncated file, of a file of another layout
version (older or newer) and of a file of another kind, all with FileFormatError.
"""

from __future__ import annotations

import zipfile
from typing import ClassVar

import numpy as np
import pytest

from torch_brdf.errors import FileFormatError
from torch_brdf.io.arrays import save_arrays
from torch_brdf.records import Record


def corrupt_payload(path, dest):
    """Copy ``path`` to ``dest`` with one byte flipped inside the largest stored array's data.

    (A byte anywhere in the file may land in a zip field that readers ignore; a byte of the
    payload must be caught by the zip CRC or the record checksum.)
    """
    raw = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as z:
        info = max(z.infolist(), key=lambda i: i.compress_size)
    start = info.header_offset
    name_len = int.from_bytes(raw[start + 26 : start + 28], "little")
    extra_len = int.from_bytes(raw[start + 28 : start + 30], "little")
    data = start + 30 + name_len + extra_len
    raw[data + info.compress_size - 1] ^= 0x5A  # the last payload byte: array data, not the npy header
    dest.write_bytes(bytes(raw))
    return dest


class RecordContract:
    """Shared tests of a :class:`~torch_brdf.records.Record` type."""

    #: options of ``save`` and ``load`` for the round trip
    save_options: ClassVar[dict] = {}
    load_options: ClassVar[dict] = {}

    def make(self, gen) -> Record:
        raise NotImplementedError

    def assert_same(self, a: Record, b: Record) -> None:
        raise NotImplementedError

    def test_is_a_record(self, gen):
        rec = self.make(gen)
        assert isinstance(rec, Record) and rec.kind and rec.version >= 1

    def test_round_trip(self, gen, tmp_path):
        rec = self.make(gen)
        path = rec.save(tmp_path / "r.npz", **self.save_options)
        back = type(rec).load(path, **self.load_options)
        assert type(back) is type(rec)
        self.assert_same(rec, back)
        # saving what was loaded gives the same arrays again
        again = type(rec).load(back.save(tmp_path / "r2.npz", **self.save_options), **self.load_options)
        self.assert_same(rec, again)

    def test_corrupt_file_refused(self, gen, tmp_path):
        path = self.make(gen).save(tmp_path / "r.npz", **self.save_options)
        with pytest.raises(FileFormatError):
            type(self.make(gen)).load(corrupt_payload(path, tmp_path / "bad.npz"), **self.load_options)
        (tmp_path / "cut.npz").write_bytes(path.read_bytes()[: path.stat().st_size // 2])
        with pytest.raises(FileFormatError):
            type(self.make(gen)).load(tmp_path / "cut.npz", **self.load_options)

    @pytest.mark.parametrize("step", [1, -1])
    def test_version_mismatch_refused(self, gen, tmp_path, monkeypatch, step):
        rec = self.make(gen)
        cls = type(rec)
        reader = cls.version
        monkeypatch.setattr(cls, "version", reader + step if reader + step >= 1 else reader + 2)
        path = rec.save(tmp_path / "r.npz", **self.save_options)
        monkeypatch.setattr(cls, "version", reader)
        with pytest.raises(FileFormatError, match="version"):
            cls.load(path, **self.load_options)

    def test_other_kind_refused(self, gen, tmp_path):
        cls = type(self.make(gen))
        save_arrays(tmp_path / "o.npz", {"x": np.zeros(3)}, kind=cls.kind + "-other")
        with pytest.raises(FileFormatError, match="expected"):
            cls.load(tmp_path / "o.npz", **self.load_options)
