"""Every record type keeps the :class:`~tests.records.contract.RecordContract`."""

from __future__ import annotations

import re

import pytest
import torch

from tests.records.contract import RecordContract
from torch_brdf.errors import FileFormatError
from torch_brdf.records import (
    BasisImage,
    BlockVisibility,
    FitResult,
    GPLVMFit,
    ObjectBasis,
    PolynomialTensors,
    SceneVertices,
    Series,
    TensorBlock,
    TermTable,
    VertexVisibility,
)
from torch_brdf.sphere.cubemap import CubemapBlocks


def _equal(a, b):
    assert (a is None) == (b is None)
    if a is not None:
        assert a.dtype == b.dtype and torch.equal(a, b)


def _refused_on_load(record, path, array: str, entry: int, value: int, words: str) -> None:
    """``record`` saved with ``array[entry] = value``, rewritten with a valid checksum (so only a
    faulty writer makes it), is refused at load with a FileFormatError containing ``words``."""
    from torch_brdf.io import load_arrays, save_arrays

    cls = type(record)
    arrays, meta = load_arrays(record.save(path))
    arrays[array] = arrays[array].copy()
    arrays[array][entry] = value
    save_arrays(path, arrays, cls.kind, meta, kind_version=cls.version)
    with pytest.raises(FileFormatError, match=re.escape(words)):
        cls.load(path)


class TestBasisImage(RecordContract):
    def make(self, gen):
        images = torch.rand(3, 4, 5, 3, generator=gen)
        mask = torch.rand(4, 5, generator=gen) > 0.3
        rec = BasisImage.from_dense(images, torch.rand(4, 5, 3, generator=gen), mask, "test:3", {"spp": 2})
        return BasisImage(rec.values, rec.pixels, 4, 5, rec.constant, rec.values.square(), rec.basis, rec.meta)

    def assert_same(self, a, b):
        for k in ("values", "pixels", "constant", "variance"):
            _equal(getattr(a, k), getattr(b, k))
        assert (a.height, a.width, a.basis, a.meta) == (b.height, b.width, b.basis, b.meta)


class TestPolynomialTensors(RecordContract):
    def make(self, gen):
        series = Series.parse("4,2,1")
        bases = [ObjectBasis(4, second=2), None]
        terms = {
            1: TermTable(torch.tensor([-1]), torch.zeros(1, 2, dtype=torch.long)),
            2: TermTable(torch.tensor([0, 1]), torch.zeros(2, 2, dtype=torch.long)),
            3: TermTable(torch.tensor([1]), torch.tensor([[1, 0]])),
        }
        blocks = []
        for n, z in ((1, 1), (2, 2), (3, 1)):
            p = 3
            index = torch.sort(torch.randperm(4 * z * p, generator=gen)[:5]).values
            vals = torch.rand(3, 5, generator=gen)
            blocks.append(TensorBlock(0, n, torch.tensor([1, 4, 7]), torch.arange(z), 4, index, vals, vals / 10))
        return PolynomialTensors(
            3, 3, series, ["a", "b"], bases, torch.rand(3, 9, generator=gen), terms, blocks, {"s": 1}
        )

    @pytest.mark.parametrize(
        ("array", "entry", "value", "words"),
        [
            ("b0_pixels", 0, -1, "block 0: pixels outside [0, 9)"),  # wrapped around to the last pixel
            ("b0_pixels", 0, 10**9, "block 0: pixels outside"),  # an IndexError when rendered
            ("b1_index", 0, 10**6, "block 1: index outside [0, 24)"),
            ("b2_terms", 0, 7, "block 2: terms outside [0, 1)"),
        ],
    )
    def test_indices_out_of_range_are_refused(self, gen, tmp_path, array, entry, value, words):
        _refused_on_load(self.make(gen), tmp_path / "t.npz", array, entry, value, words)

    def assert_same(self, a, b):
        assert (a.height, a.width, a.series, a.object_names, a.bases, a.meta) == (
            b.height,
            b.width,
            b.series,
            b.object_names,
            b.bases,
            b.meta,
        )
        _equal(a.emission, b.emission)
        assert a.terms.keys() == b.terms.keys()
        for n in a.terms:
            _equal(a.terms[n].w, b.terms[n].w)
            _equal(a.terms[n].counts, b.terms[n].counts)
        assert len(a.blocks) == len(b.blocks)
        for x, y in zip(a.blocks, b.blocks, strict=True):
            assert (x.object_id, x.bounce, x.J) == (y.object_id, y.bounce, y.J)
            for k in ("pixels", "terms", "index", "values", "variance"):
                _equal(getattr(x, k), getattr(y, k))


def _blocks(gen, p=4):
    return BlockVisibility.encode(torch.rand(p, 6, 256, generator=gen) > 0.5, meta={"scene": "test"})


def _same_blocks(a, b, meta=True):
    assert (a.block_count, a.bits) == (b.block_count, b.bits)
    assert a.meta == b.meta or not meta
    for k in ("counts", "offsets", "index", "delta", "states"):
        _equal(getattr(a, k), getattr(b, k))


class TestBlockVisibility(RecordContract):
    def make(self, gen):
        return _blocks(gen)

    def assert_same(self, a, b):
        _same_blocks(a, b)


class TestVertexVisibility(RecordContract):
    def make(self, gen):
        n = torch.nn.functional.normalize(torch.randn(4, 3, generator=gen, dtype=torch.float64), dim=-1)
        verts = SceneVertices(
            torch.randn(4, 3, generator=gen, dtype=torch.float64),
            n,
            torch.tensor([0, 0, 1, 1]),
            torch.tensor([0, 2, 4]),
        )
        return VertexVisibility(CubemapBlocks(16, 16), verts, _blocks(gen))

    @pytest.mark.parametrize(
        ("array", "entry", "value", "words"),
        [
            ("object_ids", 3, 7, "object_ids: vertex 3 has object 7, its offsets say 1 (objects 0..1)"),
            ("object_ids", 0, -1, "object_ids: vertex 0 has object -1"),
            ("object_offsets", 1, 9, "object_offsets [0, 9, 4]: expected (O + 1,) rising from 0 to the 4 vertices"),
            ("object_offsets", 2, 3, "rising from 0 to the 4 vertices"),  # the last vertex in no object
        ],
    )
    def test_indices_out_of_range_are_refused(self, gen, tmp_path, array, entry, value, words):
        _refused_on_load(self.make(gen), tmp_path / "v.npz", array, entry, value, words)

    def assert_same(self, a, b):
        assert a.settings() == b.settings()
        for k in ("positions", "normals", "object_ids", "offsets"):
            _equal(getattr(a.vertices, k), getattr(b.vertices, k))
        _same_blocks(a.blocks, b.blocks, meta=False)  # the vertex record keeps its own settings, not the blocks' meta


class TestGPLVMFit(RecordContract):
    def make(self, gen):
        x = torch.randn(6, 2, generator=gen, dtype=torch.float64)
        ll = torch.linspace(-10.0, -3.0, 5, dtype=torch.float64)
        return GPLVMFit(x, 0.8, 1e-6, 1e-8, ll, 12, 2.0, "lbfgs", 4, 1, 0.5, tuple("abcdef"), {"note": "test"})

    def assert_same(self, a, b):
        _equal(a.latents, b.latents)
        _equal(a.loglik, b.loglik)
        for k in (
            "lengthscale",
            "mu",
            "jitter",
            "d",
            "data_scale",
            "method",
            "iterations",
            "rejected",
            "names",
            "meta",
        ):
            assert getattr(a, k) == getattr(b, k)


class TestFitResult(RecordContract):
    def make(self, gen):
        c = torch.rand(5, 3, generator=gen, dtype=torch.float64)
        kd, f0 = torch.full((3,), 0.3, dtype=torch.float64), torch.full((3,), 0.04, dtype=torch.float64)
        return FitResult(c, kd, f0, 1.5, 0.0, 12, 0.25, True, 0.9, {"pixels": 10})

    def assert_same(self, a, b):
        for k in ("coefficients", "kd", "f0"):
            _equal(getattr(a, k), getattr(b, k))
        keys = ("objective", "violation", "iterations", "seconds", "constrained", "max_energy", "meta")
        assert [getattr(a, k) for k in keys] == [getattr(b, k) for k in keys]
