"""Sizes a record declares in its metadata are held to the caps of the same inputs.

A file is small, but the sizes in its header decide what a later call allocates (a basis
image of 65536 x 65536 pixels asks ``.image()`` for ~51 GB): each is refused on load with
``FileFormatError``, and the same size given directly is refused with ``ValueRangeError``.
"""

from __future__ import annotations

import pytest
import torch

from tests.records import test_records as contracts
from torch_brdf._checks import MAX_BANDS, MAX_BOUNCES, MAX_SUPERSAMPLE
from torch_brdf.errors import FileFormatError, ValueRangeError
from torch_brdf.io.arrays import load_arrays, save_arrays
from torch_brdf.records import BasisImage, ObjectBasis, Series


def _declare(case, tmp_path, **changes):
    """A valid record file of ``case`` whose metadata is changed (and sealed again)."""
    rec = case().make(torch.Generator().manual_seed(7))
    path = rec.save(tmp_path / "r.npz")
    arrays, meta = load_arrays(path)
    save_arrays(path, arrays, kind=rec.kind, meta={**meta, **changes}, kind_version=rec.version)
    return type(rec), path


@pytest.mark.parametrize(
    "case, changes",
    [
        (contracts.TestBasisImage, {"height": 65536, "width": 65536}),
        (contracts.TestBasisImage, {"height": 2**40}),
        (contracts.TestPolynomialTensors, {"series": [MAX_BANDS + 1, 2, 1]}),
        (contracts.TestPolynomialTensors, {"series": [4, 2] + [1] * MAX_BOUNCES}),
        (contracts.TestVertexVisibility, {"supersample": MAX_SUPERSAMPLE + 1}),
        (contracts.TestVertexVisibility, {"resolution": 65536}),
        (contracts.TestBlockVisibility, {"vertices": 2**40}),
    ],
)
def test_declared_size_beyond_the_cap_is_refused_on_load(tmp_path, case, changes):
    cls, path = _declare(case, tmp_path, **changes)
    with pytest.raises(FileFormatError):
        cls.load(path)


def test_declared_basis_size_is_refused(tmp_path):
    cls, path = _declare(contracts.TestPolynomialTensors, tmp_path)
    arrays, meta = load_arrays(path)
    bases = [dict(b) if b else b for b in meta["bases"]]
    bases[0]["J"] = 2**40
    save_arrays(path, arrays, kind=cls.kind, meta={**meta, "bases": bases}, kind_version=cls.version)
    with pytest.raises(FileFormatError):
        cls.load(path)


def test_the_same_sizes_given_directly_are_refused():
    rec = contracts.TestBasisImage().make(torch.Generator().manual_seed(7))
    with pytest.raises(ValueRangeError, match="basis image width"):
        BasisImage(rec.values, rec.pixels, 65536, 65536)
    with pytest.raises(ValueRangeError, match="at most"):
        Series((MAX_BANDS + 1, 1))
    with pytest.raises(ValueRangeError, match="at most"):
        Series.parse([1] * (MAX_BOUNCES + 1))
    with pytest.raises(ValueRangeError):
        ObjectBasis(MAX_BANDS + 1)
    assert Series.parse([MAX_BANDS, 1]).eye == MAX_BANDS  # the cap itself is allowed
