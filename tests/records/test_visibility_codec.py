"""Differential block visibility (Inger et al. 2013, Sec. 4.2): lossless binary round trips,
graded quantisation bounds, block states, vertex subsets, the varint stream and its errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_brdf.errors import FileFormatError, ShapeError, ValueRangeError
from torch_brdf.io.arrays import save_arrays
from torch_brdf.records import BlockVisibility
from torch_brdf.records.visibility_codec import (
    OCCLUDED,
    PARTIAL,
    UNOCCLUDED,
    decode_varints,
    encode_varints,
    packed_entries,
    zigzag_decode,
    zigzag_encode,
)


# -- map generators ---------------------------------------------------------------------------
def random_spans(p: int, nb: int, gen: torch.Generator, max_spans: int = 3, flip: float = 0.3) -> torch.Tensor:
    """``(p, nb, 256)`` bool: per block 0..max_spans random spans, inverted with probability ``flip``
    (so blocks start visible too); coinciding span ends cancel, as they would in a raster."""
    n = p * nb
    ends = torch.randint(0, 257, (n, 2 * max_spans), generator=gen)
    spans = torch.randint(0, max_spans + 1, (n, 1), generator=gen)
    ends = torch.where(torch.arange(2 * max_spans) < 2 * spans, ends, 256)  # 256: past the block
    hits = torch.zeros(n, 257, dtype=torch.uint8).scatter_add_(1, ends, torch.ones_like(ends, dtype=torch.uint8))
    inside = (hits[:, :256].cumsum(1, dtype=torch.uint8) & 1).bool()  # parity survives uint8 wrap-around
    invert = torch.rand(n, 1, generator=gen) < flip
    return (inside ^ invert).reshape(p, nb, 256)


def cube_directions(res: int) -> torch.Tensor:
    """``(6, res, res, 3)`` unit directions of cubemap texel centres (float64)."""
    t = (torch.arange(res, dtype=torch.float64) + 0.5) / res * 2 - 1
    v, u = torch.meshgrid(t, t, indexing="ij")
    one = torch.ones_like(u)
    faces = [(one, -v, -u), (-one, -v, u), (u, one, v), (u, -one, -v), (u, -v, one), (-u, -v, -one)]
    d = torch.stack([torch.stack(f, -1) for f in faces])
    return d / d.norm(dim=-1, keepdim=True)


def to_blocks(faces: torch.Tensor) -> torch.Tensor:
    """``(P, 6, R, R)`` cubemaps -> ``(P, 6 * (R/16)**2, 256)``: 16 x 16 blocks, rows concatenated."""
    p, _, r, _ = faces.shape
    k = r // 16
    return faces.reshape(p, 6, k, 16, k, 16).permute(0, 1, 2, 4, 3, 5).reshape(p, 6 * k * k, 256)


def scene_visibility(p: int, res: int, gen: torch.Generator, caps: int = 3) -> torch.Tensor:
    """``(p, 6, res, res)`` bool "real-like" visibility: a tilted horizon plane and a few spherical
    caps (occluders) per vertex."""
    d = cube_directions(res)
    out = []
    for _ in range(p):  # a handful of test vertices
        n = torch.randn(3, generator=gen, dtype=torch.float64)
        visible = d @ (n / n.norm()) > 0.3 * (torch.rand(1, generator=gen, dtype=torch.float64) - 0.5)
        for _ in range(caps):
            c = torch.randn(3, generator=gen, dtype=torch.float64)
            radius = 0.2 + 0.6 * float(torch.rand(1, generator=gen))
            visible &= d @ (c / c.norm()) < math.cos(radius)
        out.append(visible)
    return torch.stack(out)


def assert_same(a: BlockVisibility, b: BlockVisibility) -> None:
    assert (a.block_count, a.bits) == (b.block_count, b.bits)
    for name in ("counts", "offsets", "index", "states"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert (a.delta is None and b.delta is None) or torch.equal(a.delta, b.delta)


def round_trips(v: torch.Tensor, bits: int, tmp_path) -> BlockVisibility:
    """Encode, and check that bytes and files give back the same record."""
    rec = BlockVisibility.encode(v, bits)
    stream, offsets = rec.to_bytes()
    assert stream.dtype == np.uint8 and offsets.dtype == np.int64 and offsets.shape == (rec.num_vertices + 1,)
    assert_same(BlockVisibility.from_bytes(stream, offsets, rec.block_count, bits), rec)
    assert rec.nbytes_per_vertex == pytest.approx(stream.size / max(rec.num_vertices, 1))
    path = rec.save(tmp_path / "vis.npz", meta={"scene": "test"})
    back = BlockVisibility.load(path)
    assert_same(back, rec)
    assert back.meta == {"scene": "test"}
    return rec


# -- binary maps ------------------------------------------------------------------------------
def test_binary_random_spans_round_trip(gen, tmp_path):
    v = random_spans(7, 24, gen)
    rec = round_trips(v, 0, tmp_path)
    assert torch.equal(rec.decode(), v.float())
    assert rec.decode().dtype == torch.float32
    assert torch.equal(BlockVisibility.load(tmp_path / "vis.npz").decode(), v.float())
    assert rec.counts.dtype == torch.int16 and rec.index.dtype == torch.uint8 and rec.delta is None


def test_entries_are_the_derivative_of_eq5(gen):
    """index/values() scattered densely equal D V with the explicit matrix of Eq. 5."""
    v = random_spans(3, 5, gen).double()
    d_matrix = torch.eye(256, dtype=torch.float64) - torch.diag(torch.ones(255, dtype=torch.float64), -1)
    vd = v @ d_matrix.T
    rec = BlockVisibility.encode(v)
    dense = torch.zeros(15 * 256, dtype=torch.float64)
    dense[rec.pair_of_entry() * 256 + rec.index.long()] = rec.values(torch.float64)
    assert torch.equal(dense.reshape(3, 5, 256), vd)
    assert torch.equal(rec.counts, (vd != 0).sum(-1).to(torch.int16))


def test_light_product_via_partial_sums_eq6(gen):
    """The dot product L_int^T V_d (Eq. 6) per pair with pair_of_entry/values is sum(L * V)."""
    for bits in (0, 6):
        v = random_spans(4, 6, gen) if bits == 0 else torch.rand(4, 6, 256, generator=gen, dtype=torch.float64)
        rec = BlockVisibility.encode(v, bits)
        light = torch.rand(6, 256, generator=gen, dtype=torch.float64)
        l_int = light.flip(-1).cumsum(-1).flip(-1)  # D^{-T} L: suffix sums
        pair = rec.pair_of_entry()
        block = pair % rec.block_count
        terms = rec.values(torch.float64) * l_int[block, rec.index.long()]
        got = torch.zeros(rec.counts.numel(), dtype=torch.float64).index_add_(0, pair, terms)
        want = (rec.decode(dtype=torch.float64) * light).sum(-1)
        assert float((got.reshape(4, 6) - want).abs().max()) < 1e-11


def test_special_maps(tmp_path):
    alternating = torch.arange(256) % 2 == 0  # 1010...: 256 changes, the largest count
    maps = torch.stack(
        [
            torch.zeros(256, dtype=torch.bool),
            torch.ones(256, dtype=torch.bool),
            alternating,
            ~alternating,
            torch.arange(256) == 0,
            torch.arange(256) == 255,
            torch.arange(256) == 77,
            torch.arange(256) >= 255,
            torch.arange(256) < 255,
        ]
    )
    v = maps[None]
    rec = round_trips(v, 0, tmp_path)
    assert torch.equal(rec.decode(), v.float())
    assert rec.counts.tolist() == [[0, 1, 256, 255, 2, 1, 2, 1, 2]]
    assert rec.states.tolist() == [[OCCLUDED, UNOCCLUDED] + [PARTIAL] * 7]
    stream, _ = rec.to_bytes()
    assert stream[:3].tolist() == [0, 1, 0]  # occluded: count 0; unoccluded: count 1, gap 0
    assert stream[3:5].tolist() == [0x80, 0x02]  # count 256 needs two bytes
    assert torch.equal(rec.select([0]).decode(), v.float())


def test_stream_layout_by_hand():
    v = torch.zeros(1, 2, 256)
    v[0, 0, 3:5] = 2 / 3
    v[0, 1] = 1
    binary = BlockVisibility.encode(v.ceil())
    # block 0: count 2, gaps 3 and 2; block 1: count 1, gap 0
    assert binary.to_bytes()[0].tolist() == [2, 3, 2, 1, 0]
    graded = BlockVisibility.encode(v, bits=2)
    # graded: zigzag deltas follow the gaps: +2 -> 4, -2 -> 3, +3 -> 6
    assert graded.to_bytes()[0].tolist() == [2, 3, 4, 2, 3, 1, 0, 6]
    assert graded.delta.tolist() == [2, -2, 3]
    assert graded.values().tolist() == pytest.approx([2 / 3, -2 / 3, 1.0])
    assert binary.values().tolist() == [1.0, -1.0, 1.0]


def test_scene_like_maps(gen, tmp_path):
    faces = scene_visibility(6, 64, gen)
    v = to_blocks(faces)  # (6, 96, 256)
    rec = round_trips(v, 0, tmp_path)
    assert torch.equal(rec.decode(), v.float())
    states = rec.states.flatten().tolist()
    assert {OCCLUDED, UNOCCLUDED, PARTIAL} <= set(states)
    dense_bytes = 96 * 256 / 8
    print(
        f"scene-like binary maps (NB=96): {rec.nbytes_per_vertex:.1f} bytes/vertex "
        f"({rec.num_entries / rec.num_vertices:.1f} entries) vs {dense_bytes:.0f} as a dense bitmap; "
        f"states occluded/unoccluded/partial = {[states.count(s) for s in (0, 1, 2)]}"
    )


def test_concat_equals_encoding_the_whole(gen):
    v = random_spans(9, 8, gen)
    for bits in (0, 6):
        whole = BlockVisibility.encode(v.float() * (0.5 if bits else 1.0), bits)
        parts = [
            BlockVisibility.encode(v[a:b].float() * (0.5 if bits else 1.0), bits) for a, b in ((0, 4), (4, 4), (4, 9))
        ]
        assert_same(BlockVisibility.concat(parts), whole)
    with pytest.raises(ShapeError, match="bits"):
        BlockVisibility.concat([BlockVisibility.encode(v), BlockVisibility.encode(v, 2)])
    with pytest.raises(ShapeError):
        BlockVisibility.concat([])


def test_no_vertices():
    rec = BlockVisibility.encode(torch.zeros(0, 4, 256, dtype=torch.bool))
    stream, offsets = rec.to_bytes()
    assert stream.size == 0 and offsets.tolist() == [0]
    assert BlockVisibility.from_bytes(stream, offsets, 4).decode().shape == (0, 4, 256)
    assert rec.nbytes_per_vertex == 0.0


# -- graded maps ------------------------------------------------------------------------------
@pytest.mark.parametrize("bits", [2, 6, 8])
def test_graded_quantisation_bound(bits, gen, tmp_path):
    levels = 2**bits - 1
    # anti-aliased visibility: 4x4 supersampled binary maps, averaged (values j/16)
    fine = scene_visibility(4, 128, gen).double()
    graded = torch.nn.functional.avg_pool2d(fine.reshape(24, 1, 128, 128), 4).reshape(4, 6, 32, 32)
    v = torch.cat([to_blocks(graded), torch.rand(4, 3, 256, generator=gen, dtype=torch.float64)], 1)
    rec = round_trips(v, bits, tmp_path)
    dec = rec.decode(dtype=torch.float64)
    err = float((dec - v).abs().max())
    bound = 0.5 / levels
    print(f"bits={bits}: max |V - decoded| = {err:.6g}, bound 0.5/{levels} = {bound:.6g}")
    assert err <= bound * (1 + 1e-9), (err, bound)
    assert err >= 0.9 * bound, (err, bound)  # the bound is reached (ties at j/16 = 1/2)
    assert torch.equal(dec * levels, (dec * levels).round())  # levels k / (2^bits - 1), no drift
    assert torch.equal(BlockVisibility.load(tmp_path / "vis.npz").decode(), rec.decode())
    assert rec.delta.abs().max() <= levels and bool((rec.delta != 0).all())


def test_graded_states():
    v = torch.zeros(1, 5, 256, dtype=torch.float64)
    v[0, 0] = 0.1  # rounds to 0 at 2 bits
    v[0, 1] = 0.9  # rounds to 1
    v[0, 2] = 0.5  # constant but not full: one entry at 0 of less than full value
    v[0, 3, 100:] = 1.0
    rec = BlockVisibility.encode(v, bits=2)
    assert rec.states.tolist() == [[OCCLUDED, UNOCCLUDED, PARTIAL, PARTIAL, OCCLUDED]]
    assert rec.counts.tolist() == [[0, 1, 1, 1, 0]]


def test_select_matches_decode_then_index(gen, tmp_path):
    v = random_spans(10, 6, gen)
    for bits in (0, 6):
        rec = BlockVisibility.encode(v.float() * (0.7 if bits else 1.0), bits)
        ids = torch.tensor([7, 0, 7, 3, 9])
        full = rec.decode()
        sub = rec.select(ids)
        assert torch.equal(sub.decode(), full[ids])
        assert torch.equal(rec.decode(ids), full[ids])
        assert torch.equal(sub.states, rec.states[ids]) and torch.equal(sub.counts, rec.counts[ids])
        assert rec.select(torch.zeros(0, dtype=torch.int64)).decode().shape == (0, 6, 256)
        stream, offsets = rec.to_bytes()
        assert_same(BlockVisibility.from_bytes(stream, offsets, 6, bits, vertices=ids), sub)
    path = rec.save(tmp_path / "v.npz")
    assert torch.equal(BlockVisibility.load(path, vertices=[2, 5]).decode(), full[[2, 5]])
    with pytest.raises(ValueRangeError, match=r"\[0, 10\)"):
        rec.select([10])
    with pytest.raises(ValueRangeError):
        rec.select([-1])
    with pytest.raises(ShapeError):
        rec.select(torch.tensor([0.0, 1.0]))


# -- bad input --------------------------------------------------------------------------------
def test_encode_rejects_bad_input():
    ok = torch.zeros(2, 3, 256)
    with pytest.raises(ShapeError, match=r"\(P, NB, 256\)"):
        BlockVisibility.encode(torch.zeros(2, 3, 255))
    with pytest.raises(ShapeError):
        BlockVisibility.encode(torch.zeros(3, 256))
    for bad in (0.5, float("nan"), 2.0, -1.0):
        v = ok.clone()
        v[1, 2, 3] = bad
        with pytest.raises(ValueRangeError, match="binary"):
            BlockVisibility.encode(v)
    for bad in (float("nan"), 1.5, -0.1, float("inf")):
        v = ok.clone()
        v[0, 0, 0] = bad
        with pytest.raises(ValueRangeError, match=r"\[0, 1\]"):
            BlockVisibility.encode(v, bits=6)
    for bits in (9, -1, True, 2.0):
        with pytest.raises(ValueRangeError, match="bits"):
            BlockVisibility.encode(ok, bits=bits)
    assert BlockVisibility.encode(ok.to(torch.uint8)).num_entries == 0


# -- varints ----------------------------------------------------------------------------------
def test_varint_edge_values():
    values = [0, 1, 127, 128, 300, 16383, 16384, 2**21 - 1, 2**21, 2**31, 2**64 - 1]
    lengths = [1, 1, 1, 2, 2, 2, 3, 3, 4, 5, 10]
    for x, n in zip(values, lengths, strict=True):
        b = encode_varints(np.array([x], dtype=np.uint64))
        assert b.size == n, x
        assert decode_varints(b).tolist() == [x]
    assert encode_varints([128]).tolist() == [0x80, 0x01]
    assert encode_varints([300]).tolist() == [0xAC, 0x02]  # the protocol-buffers documentation's example
    assert encode_varints([16384]).tolist() == [0x80, 0x80, 0x01]
    assert encode_varints([2**31]).tolist() == [0x80, 0x80, 0x80, 0x80, 0x08]
    stream = encode_varints(np.array(values, dtype=np.uint64))
    assert decode_varints(stream).tolist() == values
    assert decode_varints(np.zeros(0, dtype=np.uint8)).size == 0
    signed = np.array([0, -1, 1, -2, 2, 2**31 - 1, -(2**31), -255, 255])
    assert zigzag_encode(signed).tolist() == [0, 1, 2, 3, 4, 2**32 - 2, 2**32 - 1, 509, 510]
    assert zigzag_decode(zigzag_encode(signed)).tolist() == signed.tolist()
    with pytest.raises(ValueRangeError):
        encode_varints([-1])


def test_varint_errors():
    with pytest.raises(FileFormatError, match="runs off the end"):
        decode_varints(np.array([5, 0x80], dtype=np.uint8))
    with pytest.raises(FileFormatError, match="at most 10"):
        decode_varints(np.array([0x80] * 10 + [1], dtype=np.uint8))
    with pytest.raises(FileFormatError, match="overflows"):
        decode_varints(np.array([0xFF] * 9 + [2], dtype=np.uint8))


# -- corrupt streams --------------------------------------------------------------------------
def parse(stream, offsets=None, nb=1, bits=0):
    stream = np.array(stream, dtype=np.uint8)
    offsets = np.array([0, stream.size] if offsets is None else offsets, dtype=np.int64)
    return BlockVisibility.from_bytes(stream, offsets, nb, bits)


def test_hand_streams_parse():
    assert parse([2, 3, 2]).decode()[0, 0].nonzero().flatten().tolist() == [3, 4]
    assert parse([1, 0x85, 0x01]).index.tolist() == [133]  # a two-byte gap
    assert parse([1, 0, 2, 0], nb=2, bits=2).states.tolist() == [[PARTIAL, OCCLUDED]]


@pytest.mark.parametrize(
    ("stream", "offsets", "nb", "bits", "message"),
    [
        ([2, 3, 0x80], None, 1, 0, "runs off the end"),
        ([1, 0x85, 0x01, 0], [0, 2, 4], 1, 0, "runs off the end of vertex 0"),
        ([2, 3], None, 1, 0, "ends before|counts inconsistent"),
        ([2, 3, 2, 7], None, 1, 0, "tokens left|counts inconsistent"),
        ([0], None, 2, 0, "ends before its block 1"),
        ([0x7F, 3], None, 1, 0, "counts inconsistent"),
        ([0x81, 0x02] + [1] * 257, None, 1, 0, "at most 256"),
        ([2, 100, 0xC8, 0x01], None, 1, 0, "index 300 > 255"),
        ([1, 0x80, 0x02], None, 1, 0, "index 256 > 255"),
        ([2, 5, 0], None, 1, 0, "not strictly increasing"),
        ([1, 0, 0], None, 1, 2, "derivative 0"),
        ([1, 0, 8], None, 1, 2, "beyond"),
        ([2, 0, 6, 1, 2], None, 1, 2, r"leaves \[0, 1\]"),
        ([1, 0, 1], None, 1, 2, r"leaves \[0, 1\]"),
        ([0], [0, 1, 1], 1, 0, "vertex 1 ends before its block 0"),
        ([0, 0], [0, 1], 1, 0, "vertex offsets"),
        ([0, 0], [0, 2, 1], 1, 0, "vertex offsets"),
    ],
)
def test_corrupt_streams(stream, offsets, nb, bits, message):
    with pytest.raises(FileFormatError, match=message):
        parse(stream, offsets, nb, bits)


def test_corrupted_real_streams(gen, tmp_path):
    rec = BlockVisibility.encode(random_spans(5, 8, gen))
    stream, offsets = rec.to_bytes()
    cut = offsets.copy()
    cut[-1] -= 1
    with pytest.raises(FileFormatError, match="counts inconsistent"):
        BlockVisibility.from_bytes(stream[:-1], cut, 8)
    with pytest.raises(FileFormatError, match="vertex offsets"):
        BlockVisibility.from_bytes(stream[:-1], offsets, 8)
    with pytest.raises(FileFormatError):
        BlockVisibility.from_bytes(stream, offsets, 9)  # wrong block count
    # a file of another kind, and a file whose header disagrees with its arrays
    save_arrays(tmp_path / "other.npz", {"x": np.zeros(3)}, kind="something-else")
    with pytest.raises(FileFormatError, match="expected 'block-visibility'"):
        BlockVisibility.load(tmp_path / "other.npz")
    meta = {"block_count": 8, "bits": 0, "vertices": 4}
    save_arrays(tmp_path / "bad.npz", {"stream": stream, "vertex_offsets": offsets}, kind="block-visibility", meta=meta)
    with pytest.raises(FileFormatError, match="4 vertices"):
        BlockVisibility.load(tmp_path / "bad.npz")


def test_chunked_encoding_matches_one_chunk(gen, monkeypatch):
    """Chunk boundaries (here every 7 pairs, inside vertices) change nothing, and a bad texel in a
    later chunk is reported at its own vertex and block."""
    from torch_brdf.records import visibility_codec

    v = random_spans(5, 6, gen).float()
    maps = {0: v, 6: v * torch.rand(5, 6, 256, generator=gen)}
    whole = {bits: BlockVisibility.encode(m, bits) for bits, m in maps.items()}
    monkeypatch.setattr(visibility_codec, "_CHUNK_PAIRS", 7)
    for bits, m in maps.items():
        assert_same(BlockVisibility.encode(m, bits), whole[bits])
    v[3, 4, 10] = float("nan")
    with pytest.raises(ValueRangeError, match="vertex 3 block 4 texel 10"):
        BlockVisibility.encode(v, bits=6)


def test_random_corruption_raises_only_file_format_errors(gen):
    """Flipping random bytes either still parses into a valid record or raises FileFormatError."""
    for bits in (0, 6):
        v = random_spans(4, 6, gen).float() * (0.6 if bits else 1.0)
        stream, offsets = BlockVisibility.encode(v, bits).to_bytes()
        rejected = 0
        for _ in range(100):
            bad = stream.copy()
            at = int(torch.randint(0, stream.size, (1,), generator=gen))
            bad[at] = int(torch.randint(0, 256, (1,), generator=gen))
            try:
                rec = BlockVisibility.from_bytes(bad, offsets, 6, bits)
            except FileFormatError:
                rejected += 1
                continue
            dec = rec.decode()
            assert bool(((dec >= 0) & (dec <= 1)).all())
        assert rejected > 50


# -- packed binary encoding -------------------------------------------------------------------
def _entries(rec: BlockVisibility) -> tuple:
    return tuple(getattr(rec, n) for n in ("counts", "offsets", "index", "states"))


def test_packed_encoding_equals_the_texel_by_texel_one(gen):
    # bool maps take the packed path; 0/1 floats the texel-by-texel one (the previous code)
    spans = random_spans(40, 12, gen)
    noise = torch.rand(6, 12, 256, generator=gen) < 0.5  # many flips, some in every byte
    edges = torch.zeros(6, 12, 256, dtype=torch.bool)
    edges[0, 0] = True  # unoccluded block: one entry at 0
    edges[1, :, 0] = True  # the first texel only (a flip at 0 and at 1)
    edges[2, :, 255] = True  # the last texel only (no closing flip)
    edges[3, :, 0::2] = True  # 256 flips: at every texel
    edges[4, :, 7:9] = True  # a span across a byte boundary
    edges[5, :, 8:16] = True  # a whole byte
    for V in (spans, noise, edges):
        packed = BlockVisibility.encode(V)
        for a, b in zip(_entries(packed), _entries(BlockVisibility.encode(V.float())), strict=True):
            assert torch.equal(a, b)
        assert torch.equal(packed.decode().bool(), V)
    assert int(BlockVisibility.encode(edges).counts[3].max()) == 256


def test_packed_entries_and_from_entries(gen):
    V = random_spans(9, 6, gen)
    counts, index = packed_entries(np.packbits(V.numpy(), axis=-1))
    ref = BlockVisibility.encode(V.float())
    assert counts.dtype == np.int16 and index.dtype == np.uint8
    assert np.array_equal(counts, ref.counts.numpy()) and np.array_equal(index, ref.index.numpy())
    # records of consecutive vertices: entries concatenated = concat of the records
    a, b = (np.packbits(x.numpy(), axis=-1) for x in (V[:4], V[4:]))
    (ca, ia), (cb, ib) = packed_entries(a), packed_entries(b)
    joined = BlockVisibility.from_entries(6, 0, np.concatenate([ca, cb]), np.concatenate([ia, ib]))
    for x, y in zip(_entries(joined), _entries(ref), strict=True):
        assert torch.equal(x, y)
    with pytest.raises(ShapeError, match="add up"):
        BlockVisibility.from_entries(6, 0, counts, index[:-1])
    with pytest.raises(ShapeError, match="packed visibility"):
        packed_entries(np.zeros((2, 3, 31), np.uint8))
    with pytest.raises(ShapeError, match="packed visibility"):
        packed_entries(np.zeros((2, 3, 32), np.int8))


def test_run_by_run_decoding_matches_one_parse(gen, monkeypatch):
    """Decoding a few bytes of the stream at a time (runs of one or a few vertices) gives the
    same arrays as one run over the whole stream, and errors name vertices of the whole stream."""
    from torch_brdf.records import visibility_codec

    v = random_spans(9, 6, gen)
    streams = {bits: BlockVisibility.encode(v.float() * (0.6 if bits else 1.0), bits).to_bytes() for bits in (0, 6)}
    whole = {bits: BlockVisibility.from_bytes(s, o, 6, bits) for bits, (s, o) in streams.items()}
    for small in (1, 7, 40):
        monkeypatch.setattr(visibility_codec, "_DECODE_MIN_BYTES", small)
        monkeypatch.setattr(visibility_codec, "_DECODE_MAX_BYTES", small)
        for bits, (stream, offsets) in streams.items():
            assert_same(BlockVisibility.from_bytes(stream, offsets, 6, bits), whole[bits])
            ids = [8, 2, 2, 5]
            assert_same(BlockVisibility.from_bytes(stream, offsets, 6, bits, vertices=ids), whole[bits].select(ids))
        stream, offsets = streams[0]
        bad = stream.copy()
        bad[offsets[7]] = 0x7F  # vertex 7's first count: more entries than the vertex holds
        with pytest.raises(FileFormatError, match="vertex 7 "):
            BlockVisibility.from_bytes(bad, offsets, 6)
        bad = stream.copy()
        bad[offsets[5] - 1] |= 0x80  # vertex 4 ends inside a varint
        with pytest.raises(FileFormatError, match="runs off the end of vertex 4"):
            BlockVisibility.from_bytes(bad, offsets, 6)
