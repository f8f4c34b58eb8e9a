"""Visibility records kept in their file layout (:class:`PackedBlockVisibility`): what a load and
the precompute hold is the varint stream itself; it unpacks to the very record that was
saved, a damaged or oversized file is refused, and a load allocates about the file's size."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
import torch

from torch_brdf.errors import FileFormatError
from torch_brdf.io import arrays as arrays_io
from torch_brdf.io import load_arrays, save_arrays
from torch_brdf.records import BlockVisibility, PackedBlockVisibility, visibility_codec
from torch_brdf.records.visibility import SceneVertices, VertexVisibility
from torch_brdf.sphere.cubemap import CubemapBlocks
from torch_brdf.transport import visibility as transport

from .test_visibility_load_memory import horizon_and_caps


def _vertices(p: int, gen: torch.Generator) -> SceneVertices:
    pos = torch.randn(p, 3, generator=gen, dtype=torch.float64)
    half = p // 2
    ids = torch.cat([torch.zeros(half, dtype=torch.int64), torch.ones(p - half, dtype=torch.int64)])
    return SceneVertices(pos, pos / pos.norm(dim=1, keepdim=True), ids, torch.tensor([0, half, p]))


def _maps(p: int, nb: int, bits: int, gen: torch.Generator):
    v = torch.rand(p, nb, 256, generator=gen) < 0.5
    v[: p // 3] = True  # unoccluded blocks
    v[p // 3 : p // 2] = False  # occluded ones
    return BlockVisibility.encode(v.float() * torch.rand(p, nb, 1, generator=gen) if bits else v, bits)


def _same_csr(a: BlockVisibility, b: BlockVisibility) -> None:
    assert (a.block_count, a.bits, a.num_vertices, a.num_entries) == (
        b.block_count,
        b.bits,
        b.num_vertices,
        b.num_entries,
    )
    for k in ("counts", "offsets", "index", "states"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k
    assert (a.delta is None and b.delta is None) or torch.equal(a.delta, b.delta)


@pytest.mark.parametrize("bits", [0, 6])
def test_load_keeps_the_stream_and_unpacks_to_the_saved_record(bits, tmp_path):
    gen = torch.Generator().manual_seed(bits)
    geom = CubemapBlocks(16, 16)
    rec = _maps(40, geom.block_count, bits, gen)
    path = VertexVisibility(geom, _vertices(40, gen), rec, supersample=2 if bits else 1, bits=bits).save(
        tmp_path / "v.npz"
    )
    loaded = VertexVisibility.load(path)
    packed = loaded.blocks
    assert isinstance(packed, PackedBlockVisibility)
    stream, offsets = rec.to_bytes()
    assert np.array_equal(packed.stream.numpy(), stream) and np.array_equal(packed.vertex_offsets.numpy(), offsets)
    assert packed.nbytes == stream.size + 8 * offsets.size
    assert packed.num_vertices == 40 and packed.num_entries == rec.num_entries
    assert packed.nbytes_per_vertex == pytest.approx(rec.nbytes_per_vertex)
    ids = torch.tensor([39, 0, 7, 7, 20])
    _same_csr(packed.select(ids), rec.select(ids))
    assert torch.equal(packed.decode(ids), rec.decode(ids))
    _same_csr(packed.unpack(), rec)
    assert packed.unpack() is packed.unpack()  # unpacked once, kept
    assert torch.equal(packed.values(torch.float64), rec.values(torch.float64))
    # a loaded record saves the stream it holds: the same file content again
    again, _ = load_arrays(loaded.save(tmp_path / "again.npz"))
    first, _ = load_arrays(path)
    assert all(np.array_equal(first[k], again[k]) for k in first)


def test_pack_of_an_in_memory_record_is_its_stream():
    gen = torch.Generator().manual_seed(1)
    rec = _maps(9, 6, 0, gen)
    packed = PackedBlockVisibility.pack(rec)
    _same_csr(packed.unpack(), rec)
    empty = PackedBlockVisibility.pack(rec.select([]))
    assert empty.num_vertices == 0 and empty.unpack().counts.shape == (0, 6)


def _rewritten(path, tmp_path, change):
    """The file at ``path`` with ``change(arrays, meta)`` applied and a valid checksum (a faulty
    writer, not a damaged disk)."""
    arrays, meta = load_arrays(path)
    arrays = {k: v.copy() for k, v in arrays.items()}
    change(arrays, meta)
    return save_arrays(tmp_path / "bad.npz", arrays, VertexVisibility.kind, meta, kind_version=VertexVisibility.version)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda a, m: m.update(vertices=10**12), "maps for 30 vertices"),
        (lambda a, m: m.update(entries=m["entries"] + 1), "entries decoded, header says"),
        (lambda a, m: a.update(vertex_offsets=a["vertex_offsets"][::-1].copy()), "vertex offsets must rise"),
        (lambda a, m: a["stream"].__setitem__(0, 0x90), "block visibility"),  # a count's varint split
        (
            lambda a, m: a.update(
                stream=a["stream"][:-3], vertex_offsets=np.minimum(a["vertex_offsets"], a["stream"].size - 3)
            ),
            "block visibility",
        ),  # truncated
        (lambda a, m: m.update(resolution=512), "block visibility"),  # 6 x 32 x 32 blocks claimed per vertex
    ],
)
def test_damaged_or_oversized_files_are_refused(change, words, tmp_path):
    gen = torch.Generator().manual_seed(2)
    geom = CubemapBlocks(16, 16)
    path = VertexVisibility(geom, _vertices(30, gen), _maps(30, geom.block_count, 0, gen)).save(tmp_path / "v.npz")
    with pytest.raises(FileFormatError, match=words):
        VertexVisibility.load(_rewritten(path, tmp_path, change))


def test_load_allocates_about_the_file(tmp_path, monkeypatch):
    """Every array a load allocates is numpy's (traced by tracemalloc: deterministic, unlike
    resident memory): the file's arrays, plus the parse of one run of vertices and one read
    buffer, both of bounded size (made small here, so that a small file shows the proportion).
    The CSR layout held 11 bytes per vertex-block pair beside the entries, ~2x this file
    (more for scenes with fewer partial blocks), and its parse ~70x."""
    monkeypatch.setattr(visibility_codec, "_DECODE_MIN_BYTES", 1 << 10)
    monkeypatch.setattr(arrays_io, "_READ_CHUNK", 1 << 16)
    gen = torch.Generator().manual_seed(0)
    geom = CubemapBlocks(32, 16)
    p = 4000
    blocks = BlockVisibility.encode_packed(horizon_and_caps(p, geom, gen, caps=1))
    path = VertexVisibility(geom, _vertices(p, gen), blocks).save(tmp_path / "v.npz")
    size = path.stat().st_size
    VertexVisibility.load(path)  # code paths and caches first
    tracemalloc.start()
    try:
        rec = VertexVisibility.load(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert rec.blocks.num_vertices == p
    assert peak <= 1.5 * size, f"load allocated {peak:,} B at its peak for a file of {size:,} B"
    assert p * geom.block_count * 11 + blocks.num_entries > 1.5 * size  # what the CSR layout kept


def test_assembly_allocates_the_record_once():
    """The precompute's assembly copies the chunks' streams into one stream: it allocates the
    record's bytes and vertex offsets, nothing per vertex-block pair beyond them."""
    gen = torch.Generator().manual_seed(4)
    whole = BlockVisibility.encode_packed(horizon_and_caps(3000, CubemapBlocks(32, 16), gen))
    tiles = []
    for s in range(0, 3000, 256):
        r = whole.select(range(s, min(s + 256, 3000)))
        arrays, n = transport._chunk_stream({"counts": r.counts.numpy(), "index": r.index.numpy()}, 24, 0)
        tiles.append((arrays, {"chunk": s // 256, "entries": n}))
    stream_bytes = sum(a["stream"].size for a, _ in tiles)
    tracemalloc.start()
    try:
        joined = transport._join_tiles(tiles, 24, 0)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert joined.nbytes == stream_bytes + 8 * 3001
    assert peak <= joined.nbytes + (64 << 10), f"assembly allocated {peak:,} B for a record of {joined.nbytes:,} B"
    _same_csr(joined.unpack(), whole)
