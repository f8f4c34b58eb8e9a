r"""Differential block visibility (Inger, Farbman & Lischinski 2013, Sec. 4.2 and 4.4).

Each vertex's visibility cubemap is split into ``NB`` blocks of 16 x 16 texels; the texels of
a block, rows concatenated, form a visibility vector :math:`V \in [0, 1]^{256}`. Occluders
make contiguous spans, so the derivative (Eq. 5)

.. math:: V_d = D\,V,\qquad V_d[0] = V[0],\quad V_d[i] = V[i] - V[i-1],

is sparse, and :math:`V` is recovered by a cumulative sum. We store only the non-zero
entries of :math:`V_d`:

* **binary** maps (``bits == 0``): only the positions where the visibility flips. The values
  are implied: +1, -1, +1, ... in order (the first change can only be 0 -> 1). The
  representation is lossless.
* **graded** maps (``bits`` in 1..8, e.g. anti-aliased visibility from supersampled binary
  maps; the paper uses 2, 6 and 8 bits): :math:`V` itself is rounded to the nearest level
  :math:`k / (2^{bits} - 1)` and the integer derivative (in units of one level) is stored
  beside each position. Because :math:`V`, not :math:`V_d`, is quantised, the cumulative sum
  does not drift: :math:`|V - \mathrm{decoded}| \le 0.5 / (2^{bits} - 1)` everywhere.

In memory, :class:`BlockVisibility` keeps every vertex-block pair's entries in flat arrays
with CSR offsets, so rendering can work on all entries at once: ``pair_of_entry()`` and
``values()`` feed ``index_add_``/``scatter_add`` (e.g. the light-visibility dot product
:math:`L_{int}^T V_d` of Sec. 4.2, Eq. 6, with :math:`L_{int}` the suffix sums of the lighting
in the block), and ``decode`` expands to the standard (pixel) basis of Sec. 4.4.

On disk (and for :meth:`BlockVisibility.to_bytes`) the entries are written as base-128
varints, protocol-buffer style (the paper's "base 128 varints" [Goo12]). Per vertex, per
block, in order::

    varint(count)
    count times: varint(gap)            gap = index - previous index (the first: index - 0)
                 [zigzag varint(delta)]  graded maps only

Every varint here is at most 2 bytes (counts <= 256, gaps <= 255, zigzag deltas <= 510), an
unoccluded or occluded block costs 2 or 1 bytes. Per-vertex byte offsets let any subset of
vertices be decoded without reading the rest.

Nothing here loops in Python over vertices, blocks or entries: encoding works on chunks of
``_CHUNK_PAIRS`` vertex-block pairs at a time (to bound the temporaries; each chunk is one
set of numpy array operations, several times faster than the torch equivalents for the
byte-sized masks and ``nonzero``), and parsing a stream finds the block starts by pointer
doubling (``ceil(log2 NB)`` vectorised steps), a run of whole vertices (1/1024 of the
stream, 16 KB to 1 MB) at a time: a parse's temporaries (~70 bytes per stream byte of the
run) stay below a tenth of the stream's size, where one parse of the whole stream held ~70
times the stream.

A record of a whole scene keeps the stream itself (:class:`PackedBlockVisibility`, what a
load and the precompute give): about the file's size, where the CSR arrays of
:class:`BlockVisibility` take 11 bytes per vertex-block pair beside the entries; the
vertices a renderer shades are unpacked from it (:meth:`PackedBlockVisibility.select`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch

from ..errors import FileFormatError, ShapeError, ValueRangeError
from .codec import Member, Record

VISIBILITY_KIND = "block-visibility"
#: texels per block (16 x 16); indices into a block's visibility vector fit in a uint8
BLOCK_TEXELS = 256
#: block states
OCCLUDED, UNOCCLUDED, PARTIAL = 0, 1, 2
#: vertex-block pairs per encoding chunk (16M texels): bounds the temporaries of ``encode``
_CHUNK_PAIRS = 1 << 16
#: stream bytes parsed at once when decoding: a 1/_DECODE_CHUNK_DIVISOR part of the stream,
#: within [_DECODE_MIN_BYTES, _DECODE_MAX_BYTES] (see ``_decode_stream``)
_DECODE_CHUNK_DIVISOR, _DECODE_MIN_BYTES, _DECODE_MAX_BYTES = 1024, 1 << 14, 1 << 20
_MAX_BITS = 8
_MAX_VARINT_BYTES = 10  # 64-bit values


# --------------------------------------------------------------------------------------------
# base-128 varints (protocol buffers), vectorised with numpy
# --------------------------------------------------------------------------------------------
def zigzag_encode(x) -> np.ndarray:
    """Map signed to unsigned integers so small magnitudes stay small (protocol buffers).

    0, -1, 1, -2, 2, ... -> 0, 1, 2, 3, 4, ...

    Args:
        x: ``(N,)`` integers in the int64 range.

    Returns:
        ``(N,)`` uint64.
    """
    x = np.asarray(x, dtype=np.int64)
    return ((x << 1) ^ (x >> 63)).astype(np.uint64)


def zigzag_decode(u) -> np.ndarray:
    """Inverse of :func:`zigzag_encode`.

    Args:
        u: ``(N,)`` unsigned integers.

    Returns:
        ``(N,)`` int64.
    """
    u = np.asarray(u, dtype=np.uint64)
    return ((u >> np.uint64(1)).astype(np.int64)) ^ -((u & np.uint64(1)).astype(np.int64))


def _varint_lengths(v: np.ndarray) -> np.ndarray:
    """Bytes of each value's varint: ``(N,)`` uint64 -> ``(N,)`` int64 in 1..10."""
    lengths = np.ones(v.shape, dtype=np.int64)
    if v.size == 0:
        return lengths
    top = int(v.max())
    k = 1
    while k < _MAX_VARINT_BYTES and top >> (7 * k):  # one pass per byte of the largest value
        lengths += (v >> np.uint64(7 * k)) != 0
        k += 1
    return lengths


def _encode_varints(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Varints of ``(N,)`` uint64 values: the ``(S,)`` uint8 stream and ``(N+1,)`` byte starts."""
    lengths = _varint_lengths(v)
    starts = np.zeros(v.size + 1, dtype=np.int64)
    np.cumsum(lengths, out=starts[1:])
    out = np.empty(int(starts[-1]), dtype=np.uint8)
    for k in range(int(lengths.max()) if v.size else 0):  # byte position within a varint, <= 10
        sel = np.flatnonzero(lengths > k)
        byte = (v[sel] >> np.uint64(7 * k)) & np.uint64(0x7F)
        byte |= np.where(lengths[sel] > k + 1, np.uint64(0x80), np.uint64(0))
        out[starts[sel] + k] = byte.astype(np.uint8)
    return out, starts


def encode_varints(values) -> np.ndarray:
    """Concatenated base-128 varints (little-endian groups of 7 bits, high bit = "more").

    Args:
        values: ``(N,)`` non-negative integers below 2**64.

    Returns:
        ``(S,)`` uint8 stream; 0..127 take one byte, 128..16383 two, and so on.

    Raises:
        ValueRangeError: a value is negative.
    """
    a = np.asarray(values)
    if a.dtype.kind not in "ui" and a.size:
        raise ValueRangeError(f"varints encode integers; got dtype {a.dtype}")
    if a.dtype.kind == "i" and a.size and int(a.min()) < 0:
        raise ValueRangeError(f"varints encode non-negative integers; got minimum {int(a.min())} (zigzag first)")
    return _encode_varints(a.astype(np.uint64).reshape(-1))[0]


def _parse_varints(stream: np.ndarray, what: str, first_byte: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Values ``(N,)`` uint64 and terminator mask ``(S,)`` bool of a varint stream (a part of a
    longer one from byte ``first_byte`` on: messages name bytes of the whole stream)."""
    term = stream < 0x80
    if stream.size and not term[-1]:
        end = first_byte + stream.size
        raise FileFormatError(
            f"{what}: truncated stream, the last varint runs off the end "
            f"(byte {end - 1} of {end} has its continuation bit set)"
        )
    ends = np.flatnonzero(term)
    starts = np.empty_like(ends)
    starts[:1] = 0
    starts[1:] = ends[:-1] + 1
    lengths = ends - starts + 1
    if lengths.size and int(lengths.max()) > _MAX_VARINT_BYTES:
        i = int(np.argmax(lengths))
        raise FileFormatError(
            f"{what}: varint at byte {first_byte + int(starts[i])} is {int(lengths[i])} bytes long "
            "(at most 10 for 64 bits)"
        )
    long = np.flatnonzero((lengths == _MAX_VARINT_BYTES) & (stream[ends] > 1))
    if long.size:
        raise FileFormatError(f"{what}: varint at byte {first_byte + int(starts[long[0]])} overflows 64 bits")
    if not ends.size:
        return np.zeros(0, dtype=np.uint64), term
    shift = (np.arange(stream.size, dtype=np.int64) - np.repeat(starts, lengths)) * 7
    groups = (stream & 0x7F).astype(np.uint64) << shift.astype(np.uint64)
    return np.add.reduceat(groups, starts), term  # disjoint bit groups: the sum is the bitwise or


def decode_varints(stream) -> np.ndarray:
    """Inverse of :func:`encode_varints`.

    Args:
        stream: ``(S,)`` uint8.

    Returns:
        ``(N,)`` uint64 values.

    Raises:
        FileFormatError: the last varint runs off the end, or a varint is longer than 64 bits.
    """
    return _parse_varints(_as_stream(stream), "varint stream")[0]


def _as_stream(stream) -> np.ndarray:
    if isinstance(stream, (bytes, bytearray, memoryview)):
        return np.frombuffer(stream, dtype=np.uint8)
    s = np.asarray(stream)
    if s.ndim != 1 or s.dtype != np.uint8:
        raise ShapeError(f"Expected a byte stream of shape (S,) and dtype uint8; got {s.dtype} {s.shape}")
    return s


# --------------------------------------------------------------------------------------------
# helpers on CSR layouts
# --------------------------------------------------------------------------------------------
def _levels(bits: int) -> int:
    """Largest quantisation level ``2**bits - 1`` (1 for binary maps)."""
    return (1 << bits) - 1 if bits else 1


def _check_bits(bits) -> int:
    if isinstance(bits, bool) or not isinstance(bits, (int, np.integer)) or not 0 <= int(bits) <= _MAX_BITS:
        raise ValueRangeError(f"bits must be an integer in 0..{_MAX_BITS} (0 = binary); got {bits!r}")
    return int(bits)


def _check_ids(vertices, n_vertices: int) -> np.ndarray:
    """Vertex ids ``(K,)`` (tensor, array or sequence) checked against ``[0, n_vertices)``: int64 array."""
    ids = vertices.numpy() if isinstance(vertices, torch.Tensor) else np.asarray(vertices)
    if ids.ndim != 1 or (ids.size and ids.dtype.kind not in "iu"):
        raise ShapeError(f"Expected vertex ids of shape (K,) and an integer dtype; got {ids.dtype} {ids.shape}")
    ids = ids.astype(np.int64)
    bad = (ids < 0) | (ids >= n_vertices)
    if bad.any():
        raise ValueRangeError(
            f"vertex ids must lie in [0, {n_vertices}); got {int(bad.sum())} outside (e.g. {int(ids[bad][0])})"
        )
    return ids


def _offsets_from_counts(counts: torch.Tensor) -> torch.Tensor:
    """``(P, NB)`` counts -> ``(P*NB+1,)`` int64 CSR starts."""
    flat = counts.reshape(-1).to(torch.int64)
    offsets = torch.zeros(flat.numel() + 1, dtype=torch.int64)
    torch.cumsum(flat, 0, out=offsets[1:])
    return offsets


def _segment_ranks(offsets: np.ndarray, pair: np.ndarray) -> np.ndarray:
    """Position of each entry within its pair's range: ``(F,)`` int64."""
    return np.arange(pair.size, dtype=np.int64) - offsets[pair]


def _gather_ranges(starts: torch.Tensor, lengths: torch.Tensor, total: int) -> torch.Tensor:
    """Concatenated ``arange(s, s + n)`` for each (start, length): ``(total,)`` int64."""
    new_starts = torch.cumsum(lengths, 0) - lengths
    shift = torch.repeat_interleave(starts - new_starts, lengths, output_size=total)
    return shift + torch.arange(total, dtype=torch.int64)


def _raise_bad_visibility(x: np.ndarray, bad: np.ndarray, first_pair: int, nb: int, bits: int):
    """Raise ValueRangeError naming the first bad texel of a chunk ``x`` (pairs x 256)."""
    pair, texel = np.argwhere(bad)[0]
    vertex, block = divmod(first_pair + int(pair), nb)
    where = f"vertex {vertex} block {block} texel {int(texel)} holds {float(x[pair, texel])}"
    if bits == 0:
        raise ValueRangeError(
            f"binary visibility (bits=0) must hold only 0 and 1; {where} ({int(bad.sum())} such values "
            "in this chunk); encode graded maps with bits=2, 6 or 8"
        )
    raise ValueRangeError(f"visibility must lie in [0, 1]; {where} ({int(bad.sum())} such values in this chunk)")


def packed_entries(packed) -> tuple[np.ndarray, np.ndarray]:
    r"""The flips of binary block visibility packed 8 texels a byte (Eq. 5 for binary maps).

    A flip at texel ``t`` of a block is bit ``t`` of ``x ^ (x >> 1)`` along the block's 256
    bits (texel ``-1`` reads 0); whole bytes are shifted and compared, and only the few non-zero
    bytes are unpacked, so the cost is about that of the 32-byte rows themselves.

    Args:
        packed: ``(P, NB, 32)`` uint8, ``np.packbits`` of ``(P, NB, 256)`` bool along the last
            axis (big-endian bits: texel ``8 j`` is the top bit of byte ``j``).

    Returns:
        ``counts``: ``(P, NB)`` int16 flips per pair; ``index``: ``(F,)`` uint8 their texel
        positions, pair by pair, increasing: the entries of :meth:`BlockVisibility.encode`.

    Raises:
        ShapeError: not ``(P, NB, 32)`` uint8.
    """
    x = np.asarray(packed)
    width = BLOCK_TEXELS // 8
    if x.ndim != 3 or x.shape[-1] != width or x.shape[1] < 1 or x.dtype != np.uint8:
        raise ShapeError(f"Expected packed visibility of shape (P, NB, {width}) uint8; got {x.dtype} {x.shape}")
    p, nb, _ = x.shape
    x = np.ascontiguousarray(x).reshape(p * nb, width)
    prev = x >> 1  # each texel's predecessor, moved onto its bit
    prev[:, 1:] |= x[:, :-1] << 7  # the last texel of the byte before
    change = x ^ prev  # one bit per flip
    counts = np.bitwise_count(change.view(np.uint64)).sum(1, dtype=np.int16)
    at = np.flatnonzero(change)  # row-major: pair by pair, bytes increasing
    row, col = np.nonzero(np.unpackbits(change.reshape(-1)[at][:, None], axis=1))  # (n, 8), big-endian
    index = ((at[row] & (width - 1)) * 8 + col).astype(np.uint8)
    return counts.reshape(p, nb), index


# --------------------------------------------------------------------------------------------
# the record
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)  # identity equality: elementwise == of tensors has no truth value
class BlockVisibility(Record):
    r"""Sparse differential visibility of ``P`` vertices x ``NB`` blocks of 256 texels.

    Build with :meth:`encode` (from dense maps), :meth:`from_bytes`, :meth:`load` or
    :meth:`concat`; the constructor trusts its arguments (it checks shapes and dtypes only).

    The entries of vertex ``p``, block ``b`` (pair ``q = p * NB + b``) are
    ``index[offsets[q]:offsets[q + 1]]``, strictly increasing texel positions where
    :math:`V_d \ne 0`.

    Attributes:
        block_count: ``NB``, blocks per vertex.
        bits: 0 for binary maps, else the quantisation bits of graded maps (levels
            ``k / (2**bits - 1)``).
        counts: ``(P, NB)`` int16, number of non-zero derivative entries per pair (0..256).
        offsets: ``(P*NB+1,)`` int64 CSR starts into the flat entry arrays.
        index: ``(F,)`` uint8 texel positions 0..255.
        delta: ``(F,)`` int16 derivative values in units of one level, or None for binary
            maps (implied +1, -1, +1, ...; see :meth:`values`).
        states: ``(P, NB)`` uint8: 0 occluded (V == 0, no entries), 1 unoccluded (V == 1: one
            entry at index 0 of full value), 2 partial. For graded maps this describes the
            quantised map.
        meta: JSON-serialisable provenance (scene, resolution, ...), kept by save/load.
    """

    block_count: int
    bits: int
    counts: torch.Tensor
    offsets: torch.Tensor
    index: torch.Tensor
    delta: torch.Tensor | None
    states: torch.Tensor
    meta: dict[str, Any] = field(default_factory=dict)

    kind = VISIBILITY_KIND
    version = 1
    schema: ClassVar[dict[str, Member]] = {"stream": Member("u", 1), "vertex_offsets": Member("iu", 1)}

    def __post_init__(self):
        nb = self.block_count
        if not isinstance(nb, int) or nb < 1:
            raise ShapeError(f"block_count must be a positive int; got {nb!r}")
        _check_bits(self.bits)
        c = self.counts
        if c.ndim != 2 or c.shape[1] != nb or c.dtype != torch.int16:
            raise ShapeError(f"Expected counts of shape (P, {nb}) and dtype int16; got {c.dtype} {tuple(c.shape)}")
        n_pairs = c.numel()
        o = self.offsets
        if o.shape != (n_pairs + 1,) or o.dtype != torch.int64:
            raise ShapeError(
                f"Expected offsets of shape ({n_pairs + 1},) and dtype int64; got {o.dtype} {tuple(o.shape)}"
            )
        f = int(o[-1])
        if self.index.shape != (f,) or self.index.dtype != torch.uint8:
            raise ShapeError(
                f"Expected index of shape ({f},) and dtype uint8; got {self.index.dtype} {tuple(self.index.shape)}"
            )
        if self.bits == 0 and self.delta is not None:
            raise ShapeError("binary maps (bits=0) store no delta; got a delta tensor")
        if self.bits and (self.delta is None or self.delta.shape != (f,) or self.delta.dtype != torch.int16):
            got = None if self.delta is None else f"{self.delta.dtype} {tuple(self.delta.shape)}"
            raise ShapeError(f"Expected delta of shape ({f},) and dtype int16 for bits={self.bits}; got {got}")
        if self.states.shape != c.shape or self.states.dtype != torch.uint8:
            raise ShapeError(
                f"Expected states of shape {tuple(c.shape)} and dtype uint8; "
                f"got {self.states.dtype} {tuple(self.states.shape)}"
            )

    # -- construction -------------------------------------------------------------------
    @classmethod
    def _from_entries(cls, block_count, bits, counts, index, delta, meta=None) -> BlockVisibility:
        """Build offsets and states from ``(P, NB)`` int16 counts and the flat entries (in runs of
        ``_CHUNK_PAIRS`` pairs: no temporary of the size of all pairs beside the results)."""
        flat = counts.reshape(-1).numpy()
        offsets = np.empty(flat.size + 1, dtype=np.int64)
        offsets[0] = 0
        np.cumsum(flat, dtype=np.int64, out=offsets[1:])
        states = np.empty(flat.size, dtype=np.uint8)
        idx = index.numpy()
        dlt = delta.numpy() if bits else None
        for q0 in range(0, flat.size, _CHUNK_PAIRS):
            q1 = min(q0 + _CHUNK_PAIRS, flat.size)
            f0, f1 = int(offsets[q0]), int(offsets[q1])
            states[q0:q1] = _states(
                flat[q0:q1], offsets[q0 : q1 + 1] - f0, idx[f0:f1], dlt[f0:f1] if bits else None, bits
            )
        return cls(
            block_count,
            bits,
            counts,
            torch.from_numpy(offsets),
            index,
            delta,
            torch.from_numpy(states).reshape(counts.shape),
            dict(meta or {}),
        )

    @classmethod
    def encode(cls, visibility, bits: int = 0, meta: dict[str, Any] | None = None) -> BlockVisibility:
        r"""Differential encoding of dense block visibility (Sec. 4.2, Eq. 5).

        Args:
            visibility: ``(P, NB, 256)`` bool or numbers in [0, 1]: per vertex and block the
                block's texels, rows concatenated. Binary maps (``bits == 0``) must hold
                exactly 0 and 1.
            bits: 0 for binary maps (lossless), else 1..8: ``V`` is rounded to the nearest
                level ``k / (2**bits - 1)`` and the integer derivative is stored.
            meta: provenance kept with the record.

        Returns:
            The record; ``decode()`` returns ``V`` (binary) or the quantised ``V`` (graded,
            within ``0.5 / (2**bits - 1)``).

        Raises:
            ShapeError: not of shape ``(P, NB, 256)``.
            ValueRangeError: NaN, values outside [0, 1], or non-binary values with ``bits == 0``.
        """
        bits = _check_bits(bits)
        v = visibility if isinstance(visibility, torch.Tensor) else torch.as_tensor(np.asarray(visibility))
        if v.ndim != 3 or v.shape[-1] != BLOCK_TEXELS or v.shape[1] < 1:
            raise ShapeError(f"Expected visibility of shape (P, NB, {BLOCK_TEXELS}); got {tuple(v.shape)}")
        if v.is_complex():
            raise ValueRangeError(f"visibility must be real; got {v.dtype}")
        p, nb, _ = v.shape
        flat = v.detach().reshape(p * nb, BLOCK_TEXELS)
        if flat.dtype == torch.bool and bits == 0:  # packed: 8 texels a byte, same entries
            return cls.encode_packed(np.packbits(flat.cpu().numpy(), axis=1).reshape(p, nb, BLOCK_TEXELS // 8), meta)
        levels = _levels(bits)
        counts, index, delta = [], [], []
        for start in range(0, p * nb, _CHUNK_PAIRS):  # chunks of pairs bound the temporaries
            chunk = flat[start : start + _CHUNK_PAIRS]
            if chunk.dtype == torch.bool:
                x = chunk.cpu().numpy()
            else:
                if not chunk.is_floating_point() or chunk.element_size() < 4:  # ints, float16, bfloat16
                    chunk = chunk.to(torch.float32)
                x = chunk.cpu().numpy()
                bad = ~((x == 0) | (x == 1)) if bits == 0 else ~((x >= 0) & (x <= 1))  # NaN is bad
                if bad.any():
                    _raise_bad_visibility(x, bad, start, nb, bits)
            # mask of non-zero derivative entries (Eq. 5), per pair: first texel, then changes
            if bits == 0:
                change = np.empty(x.shape, dtype=bool)
                np.not_equal(x[:, 0], 0, out=change[:, 0])
                np.not_equal(x[:, 1:], x[:, :-1], out=change[:, 1:])
            else:
                level = np.rint(x * levels).astype(np.int16)  # V quantised, not V_d: no drift
                d = np.empty_like(level)
                d[:, 0] = level[:, 0]
                np.subtract(level[:, 1:], level[:, :-1], out=d[:, 1:])
                change = d != 0
            counts.append(change.sum(1, dtype=np.int16))
            at = np.flatnonzero(change)  # row-major: pair by pair, positions increasing
            index.append((at & (BLOCK_TEXELS - 1)).astype(np.uint8))
            if bits:
                delta.append(d.reshape(-1)[at])
        counts_t = torch.from_numpy(np.concatenate(counts) if counts else np.zeros(0, np.int16)).reshape(p, nb)
        index_t = torch.from_numpy(np.concatenate(index) if index else np.zeros(0, np.uint8))
        delta_t = torch.from_numpy(np.concatenate(delta) if delta else np.zeros(0, np.int16)) if bits else None
        meta = dict(meta or {})
        return cls._from_entries(nb, bits, counts_t, index_t, delta_t, meta)

    @classmethod
    def encode_packed(cls, packed, meta: dict[str, Any] | None = None) -> BlockVisibility:
        r"""Differential encoding of binary block visibility packed 8 texels a byte.

        The same record as :meth:`encode` of the unpacked maps with ``bits=0``, from
        :func:`packed_entries`.

        Args:
            packed: ``(P, NB, 32)`` uint8, ``np.packbits`` of ``(P, NB, 256)`` bool along the
                last axis (big-endian bits: texel ``8 j`` is the top bit of byte ``j``).
            meta: provenance kept with the record.

        Returns:
            The binary record (``bits == 0``).

        Raises:
            ShapeError: not ``(P, NB, 32)`` uint8.
        """
        counts, index = packed_entries(packed)
        return cls._from_entries(counts.shape[1], 0, torch.from_numpy(counts), torch.from_numpy(index), None, meta)

    @classmethod
    def from_entries(
        cls, block_count: int, bits: int, counts, index, delta=None, meta: dict[str, Any] | None = None
    ) -> BlockVisibility:
        """The record of given entries (e.g. those of :func:`packed_entries`, or of several
        records' ``counts`` / ``index`` / ``delta`` concatenated); trusted as :meth:`encode`'s.

        Args:
            block_count: ``NB``. bits: 0 (binary) or the quantisation bits.
            counts: ``(P, NB)`` int16 entries per pair. index: ``(F,)`` uint8 texel positions,
                increasing within each pair. delta: ``(F,)`` int16 (graded maps) or None.
            meta: provenance kept with the record.

        Raises:
            ShapeError: shapes or dtypes, or counts that do not add up to ``F``.
        """
        counts, index = torch.as_tensor(counts), torch.as_tensor(index)
        delta = None if delta is None else torch.as_tensor(delta)
        total = int(counts.numpy().sum(dtype=np.int64)) if counts.dtype == torch.int16 else None
        if total is not None and total != index.numel():
            raise ShapeError(f"counts add up to {total} entries; got {index.numel()}")
        return cls._from_entries(block_count, _check_bits(bits), counts, index, delta, meta)

    @classmethod
    def concat(cls, records: Sequence[BlockVisibility]) -> BlockVisibility:
        """Join records of consecutive vertex chunks (same ``NB`` and ``bits``).

        Args:
            records: non-empty sequence; vertex ids follow the order given. The first
                record's ``meta`` is kept.

        Returns:
            One record with ``sum(P_i)`` vertices.
        """
        records = list(records)
        if not records:
            raise ShapeError("concat needs at least one BlockVisibility")
        nb, bits = records[0].block_count, records[0].bits
        for i, r in enumerate(records):
            if (r.block_count, r.bits) != (nb, bits):
                raise ShapeError(
                    f"concat: record {i} has block_count={r.block_count}, bits={r.bits}; "
                    f"record 0 has block_count={nb}, bits={bits}"
                )
        ends = torch.tensor([int(r.offsets[-1]) for r in records], dtype=torch.int64)
        shifts = torch.cumsum(ends, 0) - ends
        tails = [r.offsets[1:] + s for r, s in zip(records, shifts, strict=True)]
        offsets = torch.cat([torch.zeros(1, dtype=torch.int64), *tails])
        return cls(
            nb,
            bits,
            torch.cat([r.counts for r in records]),
            offsets,
            torch.cat([r.index for r in records]),
            torch.cat([r.delta for r in records]) if bits else None,
            torch.cat([r.states for r in records]),
            dict(records[0].meta),
        )

    # -- sizes --------------------------------------------------------------------------
    @property
    def num_vertices(self) -> int:
        """``P``."""
        return self.counts.shape[0]

    @property
    def num_entries(self) -> int:
        """``F``, stored non-zero derivative entries."""
        return self.index.numel()

    @property
    def levels(self) -> int:
        """Largest quantisation level ``2**bits - 1`` (1 for binary maps)."""
        return _levels(self.bits)

    @property
    def nbytes_per_vertex(self) -> float:
        """Mean size of one vertex in the varint serialisation (:meth:`to_bytes`), in bytes."""
        if self.num_vertices == 0:
            return 0.0
        tokens = self._tokens()[0]
        return float(_varint_lengths(tokens).sum()) / self.num_vertices

    # -- entries ------------------------------------------------------------------------
    def pair_of_entry(self) -> torch.Tensor:
        """Pair id ``vertex * NB + block`` of each flat entry, for scatter-adds.

        Returns:
            ``(F,)`` int64, non-decreasing.
        """
        pairs = torch.arange(self.counts.numel(), dtype=torch.int64)
        return torch.repeat_interleave(pairs, self.counts.reshape(-1).to(torch.int64), output_size=self.num_entries)

    def values(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """Derivative values of the flat entries in visibility units.

        Binary maps: +1, -1, +1, ... within each pair. Graded maps: ``delta / (2**bits - 1)``.

        Args:
            dtype: floating dtype of the result.

        Returns:
            ``(F,)`` of ``dtype``.
        """
        if self.bits:
            return self.delta.to(dtype) / self.levels
        return self._signs(self.pair_of_entry()).to(dtype)

    def _signs(self, pair: torch.Tensor) -> torch.Tensor:
        """Implied binary derivatives +1, -1, +1, ... from ``(F,)`` pair ids: ``(F,)`` int8."""
        rank = torch.arange(self.num_entries, dtype=torch.int64) - self.offsets[pair]
        return 1 - 2 * (rank & 1).to(torch.int8)

    def decode(self, vertices=None, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """Dense visibility: the cumulative sum of :math:`V_d` (Sec. 4.4).

        Args:
            vertices: ``(P',)`` vertex ids to decode (default all), as for :meth:`select`.
            dtype: floating dtype of the result.

        Returns:
            ``(P', NB, 256)``: exactly 0/1 for binary maps, levels ``k / (2**bits - 1)`` for
            graded maps.
        """
        rec = self if vertices is None else self.select(vertices)
        out = torch.zeros(rec.counts.numel(), BLOCK_TEXELS, dtype=dtype)
        pair = rec.pair_of_entry()
        units = rec.delta if rec.bits else rec._signs(pair)  # integers: the sums below are exact
        out.view(-1)[pair * BLOCK_TEXELS + rec.index.to(torch.int64)] = units.to(dtype)
        out.cumsum_(1)
        if rec.bits:
            out.div_(rec.levels)
        return out.reshape(rec.num_vertices, rec.block_count, BLOCK_TEXELS)

    def select(self, vertices) -> BlockVisibility:
        """The record restricted to some vertices, in the order given (repeats allowed).

        Args:
            vertices: ``(K,)`` integer vertex ids in ``[0, P)``.

        Returns:
            A record with ``K`` vertices.

        Raises:
            ShapeError: not a 1-D integer sequence.
            ValueRangeError: an id outside ``[0, P)``.
        """
        p, nb = self.counts.shape
        ids = torch.from_numpy(_check_ids(vertices, p))
        pairs = (ids[:, None] * nb + torch.arange(nb, dtype=torch.int64)).reshape(-1)
        counts = self.counts[ids]
        lengths = counts.reshape(-1).to(torch.int64)
        total = int(lengths.sum())
        src = _gather_ranges(self.offsets[pairs], lengths, total)
        return BlockVisibility(
            nb,
            self.bits,
            counts,
            _offsets_from_counts(counts),
            self.index[src],
            self.delta[src] if self.bits else None,
            self.states[ids],
            dict(self.meta),
        )

    def unpack(self) -> BlockVisibility:
        """The record itself (as :meth:`PackedBlockVisibility.unpack` of a packed one)."""
        return self

    # -- varint serialisation -----------------------------------------------------------
    def _tokens(self) -> tuple[np.ndarray, np.ndarray]:
        """Unsigned tokens of the stream ``(T,)`` uint64 and the token of each pair's count ``(P*NB,)``."""
        width = 2 if self.bits else 1
        counts = self.counts.reshape(-1).numpy().astype(np.int64)
        offsets = self.offsets.numpy()
        pair = np.repeat(np.arange(counts.size, dtype=np.int64), counts)
        count_at = offsets[:-1] * width + np.arange(counts.size, dtype=np.int64)
        tokens = np.empty(counts.size + width * pair.size, dtype=np.uint64)
        tokens[count_at] = counts
        rank = _segment_ranks(offsets, pair)
        index = self.index.numpy().astype(np.int64)
        gap = index.copy()
        gap[1:] -= index[:-1]
        first = rank == 0
        gap[first] = index[first]
        at = count_at[pair] + 1 + width * rank
        tokens[at] = gap
        if self.bits:
            tokens[at + 1] = zigzag_encode(self.delta.numpy())
        return tokens, count_at

    def to_bytes(self) -> tuple[np.ndarray, np.ndarray]:
        """Compact varint serialisation (see the module docstring for the layout).

        Returns:
            ``(stream, vertex_offsets)``: ``(S,)`` uint8 and ``(P+1,)`` int64; vertex ``p`` is
            ``stream[vertex_offsets[p]:vertex_offsets[p + 1]]`` and decodes on its own.
        """
        tokens, count_at = self._tokens()
        stream, starts = _encode_varints(tokens)
        vertex_offsets = np.append(starts[count_at[:: self.block_count]], stream.size).astype(np.int64)
        return stream, vertex_offsets

    @classmethod
    def from_bytes(
        cls,
        stream,
        vertex_offsets,
        block_count: int,
        bits: int = 0,
        vertices=None,
        meta: dict[str, Any] | None = None,
    ) -> BlockVisibility:
        """Parse a stream written by :meth:`to_bytes` and rebuild the in-memory record.

        Args:
            stream: ``(S,)`` uint8 (or ``bytes``).
            vertex_offsets: ``(P+1,)`` int64 byte offsets of the vertices, from 0 to ``S``.
            block_count: ``NB``.
            bits: 0 (binary) or the quantisation bits, as written.
            vertices: ``(K,)`` ids of the vertices to decode (default all); the others are
                not read.
            meta: provenance for the record.

        Returns:
            The record (of ``K`` vertices if ``vertices`` is given).

        Raises:
            FileFormatError: inconsistent offsets, a varint running off the end of a vertex,
                indices not increasing or above 255, counts that disagree with the stream,
                zero or out-of-range graded deltas.
        """
        nb, bits, stream, vo = _check_stream(stream, vertex_offsets, block_count, bits)
        if vertices is not None:
            stream, vo = _select_stream(stream, vo, vertices)
        _check_pairs(stream, vo, nb)
        arrays = (torch.from_numpy(a) if a is not None else None for a in _decode_stream(stream, vo, nb, bits))
        counts, offsets, index, delta, states = arrays
        return cls(nb, bits, counts, offsets, index, delta, states, dict(meta or {}))

    # -- files --------------------------------------------------------------------------
    def to_arrays(self, meta: dict[str, Any] | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """The varint form for :meth:`save` (``save(path, meta=...)``: atomic, versioned,
        checksummed, no pickle); ``meta`` (JSON-serialisable) is merged over the record's ``meta``."""
        stream, vertex_offsets = self.to_bytes()
        header = {
            "block_count": self.block_count,
            "bits": self.bits,
            "vertices": self.num_vertices,
            "entries": self.num_entries,
            "meta": {**self.meta, **(meta or {})},
        }
        return {"stream": stream, "vertex_offsets": vertex_offsets}, header

    @classmethod
    def from_arrays(cls, arrays, meta, vertices=None) -> BlockVisibility:
        """Rebuild the in-memory CSR (``load(path, vertices=...)``).

        Args:
            vertices: ``(K,)`` ids of the vertices to keep (default all).

        Raises:
            FileFormatError: incomplete, corrupt, or inconsistent with its header.
        """
        try:
            stream, vertex_offsets = arrays["stream"], arrays["vertex_offsets"]
            nb, bits, n_vertices = int(meta["block_count"]), int(meta["bits"]), int(meta["vertices"])
        except (KeyError, TypeError, ValueError) as exc:
            raise FileFormatError(f"incomplete block-visibility file ({exc!r})") from exc
        if vertex_offsets.shape != (n_vertices + 1,):
            raise FileFormatError(
                f"header says {n_vertices} vertices but there are {vertex_offsets.size} vertex offsets"
            )
        rec = cls.from_bytes(stream, vertex_offsets, nb, bits, vertices, meta.get("meta", {}))
        if vertices is None and "entries" in meta and rec.num_entries != int(meta["entries"]):
            raise FileFormatError(f"{rec.num_entries} entries decoded, header says {meta['entries']}")
        return rec


@dataclass(frozen=True, eq=False)  # identity equality, as BlockVisibility's
class PackedBlockVisibility:
    r"""Block visibility kept in its file layout: the varint stream and per-vertex byte offsets.

    What :meth:`~torch_brdf.records.visibility.VertexVisibility.load` and
    :func:`~torch_brdf.transport.visibility.precompute_visibility` hold for a whole scene: one
    byte per occluded block, two per unoccluded one, about one per flip of a partial one (the
    module docstring's layout), where the CSR arrays of :class:`BlockVisibility` take 11 bytes
    per vertex-block pair plus the entries. A renderer unpacks only the vertices it shades
    (:meth:`select`, a :class:`BlockVisibility`); the stream was parsed once in full when the
    record was made (:meth:`from_bytes` checks everything :meth:`BlockVisibility.from_bytes`
    checks), so a selection of it parses without error.

    The CSR attributes (``counts``, ``offsets``, ``index``, ``delta``, ``states``,
    :meth:`values`, :meth:`pair_of_entry`) are those of the whole record, unpacked on first
    use and kept (the 11 bytes per pair again): for small records, tests and tools; code
    that works on large ones goes through :meth:`select`.

    Attributes:
        block_count: ``NB``, blocks per vertex.
        bits: 0 for binary maps, else the quantisation bits of graded maps.
        stream: ``(S,)`` uint8 varints; vertex ``p`` is ``stream[vertex_offsets[p]:vertex_offsets[p + 1]]``.
        vertex_offsets: ``(P+1,)`` int64 byte offsets of the vertices, from 0 to ``S``.
        entries: ``F``, the non-zero derivative entries the stream holds.
        meta: JSON-serialisable provenance.
    """

    block_count: int
    bits: int
    stream: torch.Tensor
    vertex_offsets: torch.Tensor
    entries: int
    meta: dict[str, Any] = field(default_factory=dict)
    _unpacked: list = field(default_factory=list, repr=False)  # the whole CSR, once asked for

    def __post_init__(self):
        if self.stream.ndim != 1 or self.stream.dtype != torch.uint8:
            raise ShapeError(
                f"Expected a stream of shape (S,) and dtype uint8; got {self.stream.dtype} {tuple(self.stream.shape)}"
            )
        vo = self.vertex_offsets
        if vo.ndim != 1 or vo.numel() < 1 or vo.dtype != torch.int64:
            raise ShapeError(
                f"Expected vertex offsets of shape (P+1,) and dtype int64; got {vo.dtype} {tuple(vo.shape)}"
            )

    @classmethod
    def from_bytes(
        cls, stream, vertex_offsets, block_count: int, bits: int = 0, meta: dict[str, Any] | None = None
    ) -> PackedBlockVisibility:
        """Check a stream written by :meth:`BlockVisibility.to_bytes` and keep it as it is.

        The whole stream is parsed a run of vertices at a time, each run's results dropped
        once checked: the temporaries stay a small fraction of the stream, and what is kept
        is the stream itself (not copied when it is a C-contiguous uint8 array).

        Args:
            stream: ``(S,)`` uint8 (or ``bytes``).
            vertex_offsets: ``(P+1,)`` integer byte offsets of the vertices, from 0 to ``S``.
            block_count: ``NB``.
            bits: 0 (binary) or the quantisation bits, as written.
            meta: provenance for the record.

        Returns:
            The record, holding the stream (not copied when it is a C-contiguous uint8 array).

        Raises:
            FileFormatError: everything :meth:`BlockVisibility.from_bytes` refuses.
        """
        nb, bits, stream, vo = _check_stream(stream, vertex_offsets, block_count, bits)
        _check_pairs(stream, vo, nb)
        entries = sum(i.size for _, _, _, i, _ in _runs(stream, vo, nb, bits))
        return cls(
            nb,
            bits,
            torch.from_numpy(np.ascontiguousarray(stream)),
            torch.from_numpy(np.ascontiguousarray(vo)),
            int(entries),
            dict(meta or {}),
        )

    @classmethod
    def pack(cls, record: BlockVisibility) -> PackedBlockVisibility:
        """The packed form of an in-memory record (its :meth:`BlockVisibility.to_bytes`).

        Args:
            record: the in-memory record.
        """
        stream, vo = record.to_bytes()
        return cls(
            record.block_count,
            record.bits,
            torch.from_numpy(stream),
            torch.from_numpy(vo),
            record.num_entries,
            dict(record.meta),
        )

    # -- sizes ----------------------------------------------------------------------------
    @property
    def num_vertices(self) -> int:
        """``P``."""
        return self.vertex_offsets.numel() - 1

    @property
    def num_entries(self) -> int:
        """``F``, stored non-zero derivative entries."""
        return self.entries

    @property
    def levels(self) -> int:
        """Largest quantisation level ``2**bits - 1`` (1 for binary maps)."""
        return _levels(self.bits)

    @property
    def nbytes(self) -> int:
        """Bytes held: the stream and the vertex offsets."""
        return self.stream.numel() + 8 * self.vertex_offsets.numel()

    @property
    def nbytes_per_vertex(self) -> float:
        """Mean size of one vertex in the varint stream, in bytes."""
        return self.stream.numel() / self.num_vertices if self.num_vertices else 0.0

    # -- unpacking ------------------------------------------------------------------------
    def select(self, vertices) -> BlockVisibility:
        """The in-memory record (:class:`BlockVisibility`) of some vertices, in the order given
        (repeats allowed); only their bytes are read.

        Args:
            vertices: ``(K,)`` integer vertex ids in ``[0, P)``.

        Raises:
            ShapeError: not a 1-D integer sequence. ValueRangeError: an id outside ``[0, P)``.
        """
        return BlockVisibility.from_bytes(
            self.stream.numpy(), self.vertex_offsets.numpy(), self.block_count, self.bits, vertices, self.meta
        )

    def unpack(self) -> BlockVisibility:
        """The whole record as a :class:`BlockVisibility` (made once and kept)."""
        if not self._unpacked:
            self._unpacked.append(
                BlockVisibility.from_bytes(
                    self.stream.numpy(), self.vertex_offsets.numpy(), self.block_count, self.bits, None, self.meta
                )
            )
        return self._unpacked[0]

    def decode(self, vertices=None, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """Dense visibility of some vertices, as :meth:`BlockVisibility.decode`.

        Args:
            vertices: ``(P',)`` vertex ids (default all).
            dtype: floating dtype of the result.

        Returns:
            ``(P', NB, 256)``.
        """
        rec = self.unpack() if vertices is None else self.select(vertices)
        return rec.decode(dtype=dtype)

    @property
    def counts(self) -> torch.Tensor:
        """``(P, NB)`` int16 of the whole record (unpacks it, see the class docstring)."""
        return self.unpack().counts

    @property
    def offsets(self) -> torch.Tensor:
        """``(P*NB+1,)`` int64 CSR starts of the whole record (unpacks it)."""
        return self.unpack().offsets

    @property
    def index(self) -> torch.Tensor:
        """``(F,)`` uint8 texel positions of the whole record (unpacks it)."""
        return self.unpack().index

    @property
    def delta(self) -> torch.Tensor | None:
        """``(F,)`` int16 graded derivatives of the whole record, or None (unpacks it)."""
        return self.unpack().delta

    @property
    def states(self) -> torch.Tensor:
        """``(P, NB)`` uint8 block states of the whole record (unpacks it)."""
        return self.unpack().states

    def values(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """``(F,)`` derivative values of the whole record, as :meth:`BlockVisibility.values`.

        Args:
            dtype: floating dtype of the result.
        """
        return self.unpack().values(dtype)

    def pair_of_entry(self) -> torch.Tensor:
        """``(F,)`` pair ids of the whole record's entries, as :meth:`BlockVisibility.pair_of_entry`."""
        return self.unpack().pair_of_entry()

    # -- serialisation --------------------------------------------------------------------
    def to_bytes(self) -> tuple[np.ndarray, np.ndarray]:
        """``(stream, vertex_offsets)`` as :meth:`BlockVisibility.to_bytes` gives them (no copy)."""
        return self.stream.numpy(), self.vertex_offsets.numpy()


def _check_stream(stream, vertex_offsets, block_count, bits) -> tuple[int, int, np.ndarray, np.ndarray]:
    """``(NB, bits, stream, vertex_offsets)`` checked: a positive ``NB``, known bits, a byte
    stream and int64 vertex offsets rising from 0 to its length (FileFormatError otherwise)."""
    bits = _check_bits(bits)
    if isinstance(block_count, bool) or not isinstance(block_count, (int, np.integer)) or block_count < 1:
        raise ShapeError(f"block_count must be a positive int; got {block_count!r}")
    stream = _as_stream(stream)
    vo = np.asarray(vertex_offsets)
    if vo.ndim != 1 or vo.size < 1 or vo.dtype.kind not in "iu":
        raise FileFormatError(f"vertex offsets must be a 1-D integer array (P+1,); got {vo.dtype} {vo.shape}")
    vo = vo.astype(np.int64, copy=False)
    if vo[0] != 0 or vo[-1] != stream.size or bool((np.diff(vo) < 0).any()):
        raise FileFormatError(
            f"vertex offsets must rise from 0 to the stream length {stream.size}; "
            f"got first {int(vo[0])}, last {int(vo[-1])}, {int((np.diff(vo) < 0).sum())} decreasing steps"
        )
    return int(block_count), bits, stream, vo


def _check_pairs(stream: np.ndarray, vo: np.ndarray, nb: int) -> None:
    """Every block starts with a count byte, so P x NB cannot exceed the stream's length: the
    (P, NB) tables are bounded before they are allocated (small excesses go on to the
    parser's precise message)."""
    if (vo.size - 1) * nb > stream.size + (1 << 16):
        raise FileFormatError(
            f"block visibility: {vo.size - 1} vertices x {nb} blocks need at least {(vo.size - 1) * nb:,} "
            f"count bytes; the stream has {stream.size:,}"
        )


def _select_stream(stream: np.ndarray, vo: np.ndarray, vertices) -> tuple[np.ndarray, np.ndarray]:
    """The bytes and vertex offsets of some vertices of a stream, in the order given."""
    ids = _check_ids(vertices, vo.size - 1)
    lengths = vo[ids + 1] - vo[ids]
    src = _gather_ranges(torch.from_numpy(vo[ids]), torch.from_numpy(lengths), int(lengths.sum())).numpy()
    out = np.zeros(ids.size + 1, dtype=np.int64)
    np.cumsum(lengths, out=out[1:])
    return stream[src], out


def _decode_chunk_bytes(size: int) -> int:
    """Stream bytes parsed at once for a stream of ``size`` bytes (see :func:`_decode_stream`)."""
    return int(min(max(size // _DECODE_CHUNK_DIVISOR, _DECODE_MIN_BYTES), _DECODE_MAX_BYTES))


def _runs(stream: np.ndarray, vertex_offsets: np.ndarray, nb: int, bits: int):
    """Parse a stream a run of whole vertices at a time: yields ``(v0, v1, counts, index, delta)``
    of vertices ``v0:v1`` (numpy, as :func:`_parse_stream`).

    Parsing one run costs ~70 bytes of temporaries per stream byte (int64 tokens, shifts,
    pointer-doubling tables), so runs are kept to a small fraction of the stream (and at
    most a few MB): the transient stays below the stream's own size.
    """
    n_vertices = vertex_offsets.size - 1
    step = _decode_chunk_bytes(stream.size)
    v0 = 0
    while v0 < n_vertices:
        # the run: whole vertices up to ``step`` bytes past its first byte (at least one vertex)
        v1 = max(int(np.searchsorted(vertex_offsets, vertex_offsets[v0] + step, side="right")) - 1, v0 + 1)
        v1 = min(v1, n_vertices)
        b0, b1 = int(vertex_offsets[v0]), int(vertex_offsets[v1])
        if b1 < stream.size:  # the run must end at a varint boundary (its inside is checked by the parse)
            ends = vertex_offsets[v0 + 1 : v1 + 1]
            split = np.flatnonzero((ends > 0) & (stream[np.maximum(ends - 1, 0)] >= 0x80))
            if split.size:
                raise FileFormatError(
                    f"block visibility: a varint runs off the end of vertex {v0 + int(split[0])} "
                    "(its bytes end inside a varint)"
                )
        c, i, d = _parse_stream(stream[b0:b1], vertex_offsets[v0 : v1 + 1] - b0, nb, bits, v0, b0)
        yield v0, v1, c, i, d
        v0 = v1


def _decode_stream(stream: np.ndarray, vertex_offsets: np.ndarray, nb: int, bits: int):
    """Counts, offsets, index, delta and states of a whole stream, parsed a run of vertices at a
    time (:func:`_runs`) into arrays allocated once: ``index`` and ``delta`` at their upper
    bound (every entry costs at least one stream byte, a graded one two), of which only the
    pages written become resident, then shrunk in place to the entries found.

    Returns:
        numpy ``counts`` ``(P, NB)`` int16, ``offsets`` ``(P*NB+1,)`` int64, ``index`` ``(F,)``
        uint8, ``delta`` ``(F,)`` int16 or None, ``states`` ``(P, NB)`` uint8: the arrays of
        :class:`BlockVisibility`, the same as one parse of the whole stream.
    """
    n_vertices = vertex_offsets.size - 1
    counts = np.empty((n_vertices, nb), dtype=np.int16)
    states = np.empty((n_vertices, nb), dtype=np.uint8)
    offsets = np.empty(n_vertices * nb + 1, dtype=np.int64)
    offsets[0] = 0
    index = np.empty(stream.size, dtype=np.uint8)
    delta = np.empty(stream.size // 2, dtype=np.int16) if bits else None
    n_entries = 0
    for v0, v1, c, i, d in _runs(stream, vertex_offsets, nb, bits):
        q0, q1, f = v0 * nb, v1 * nb, i.size
        counts[v0:v1] = c
        flat = c.reshape(-1)
        np.cumsum(flat, out=offsets[q0 + 1 : q1 + 1])
        offsets[q0 + 1 : q1 + 1] += n_entries
        index[n_entries : n_entries + f] = i
        if bits:
            delta[n_entries : n_entries + f] = d
        states[v0:v1] = _states(flat, offsets[q0 : q1 + 1] - n_entries, i, d, bits).reshape(c.shape)
        n_entries += f
    index.resize(n_entries, refcheck=False)  # in place: no copy, the untouched tail never was resident
    if bits:
        delta.resize(n_entries, refcheck=False)
    return counts, offsets, index, delta, states


def _states(counts: np.ndarray, offsets: np.ndarray, index: np.ndarray, delta, bits: int) -> np.ndarray:
    """Block states ``(Q,)`` uint8 of ``Q`` pairs from their counts, CSR offsets and entries."""
    states = np.full(counts.shape, PARTIAL, dtype=np.uint8)
    states[counts == 0] = OCCLUDED
    if index.size:
        first = np.minimum(offsets[:-1], index.size - 1)
        full = (counts == 1) & (index[first] == 0)
        if bits:
            full &= delta[first] == _levels(bits)
        states[full] = UNOCCLUDED
    return states


def _parse_stream(
    stream: np.ndarray, vertex_offsets: np.ndarray, nb: int, bits: int, first_vertex: int = 0, first_byte: int = 0
):
    """Counts ``(P, NB)`` int16, index ``(F,)`` uint8, delta ``(F,)`` int16 or None of a stream
    (numpy), which starts at vertex ``first_vertex`` and byte ``first_byte`` of the whole one:
    messages name vertices and bytes of the whole stream."""
    n_vertices = vertex_offsets.size - 1
    width = 2 if bits else 1
    tokens, term = _parse_varints(stream, "block visibility", first_byte)
    # every vertex must end at a varint boundary
    inner = vertex_offsets[1:-1]
    split = np.flatnonzero((inner > 0) & ~term[np.maximum(inner - 1, 0)]) if inner.size else inner[:0]
    if split.size:
        raise FileFormatError(
            f"block visibility: a varint runs off the end of vertex {first_vertex + int(split[0])} "
            "(its bytes end inside a varint)"
        )
    n_tokens = tokens.size
    tok = np.minimum(tokens, np.uint64(1 << 40)).astype(np.int64)  # caps garbage before arithmetic
    # token number of each vertex start: terminators before its first byte
    term_before = np.zeros(stream.size + 1, dtype=np.int64)
    np.cumsum(term, out=term_before[1:])
    vtok = term_before[vertex_offsets]
    starts, ends = vtok[:-1], vtok[1:]
    # Block starts by pointer doubling. Read as a count, token t starts a block whose
    # successor begins at t + 1 + width * tok[t]; jump[t] is that successor 2**k blocks on
    # (n_tokens is an absorbing "off the end" sentinel).
    jump = np.minimum(np.arange(n_tokens, dtype=np.int64) + 1 + width * tok, n_tokens)
    jump = np.append(jump, n_tokens)
    block_at = np.empty((n_vertices, nb), dtype=np.int64)
    block_at[:, 0] = np.minimum(starts, n_tokens)
    done = 1
    while done < nb:  # ceil(log2 NB) steps
        step = min(done, nb - done)
        block_at[:, done : done + step] = jump[block_at[:, :step]]
        done += step
        if done < nb:
            jump = jump[jump]
    short = block_at >= ends[:, None]
    if short.any():
        v, b = np.argwhere(short)[0]
        raise FileFormatError(
            f"block visibility: vertex {first_vertex + int(v)} ends before its block {int(b)} of {nb} "
            "(counts inconsistent with the stream, or the stream is truncated)"
        )
    counts = tok[block_at]
    if counts.size and int(counts.max()) > BLOCK_TEXELS:
        v, b = np.argwhere(counts > BLOCK_TEXELS)[0]
        raise FileFormatError(
            f"block visibility: vertex {first_vertex + int(v)} block {int(b)} claims {int(counts[v, b])} entries "
            "(at most 256)"
        )
    last_end = block_at[:, -1] + 1 + width * counts[:, -1]
    extra = last_end != ends
    if extra.any():
        v = int(np.flatnonzero(extra)[0])
        raise FileFormatError(
            f"block visibility: vertex {first_vertex + v} has {int(ends[v] - last_end[v])} tokens left "
            f"after its {nb} blocks "
            "(counts inconsistent with the stream)"
        )
    flat_counts = counts.reshape(-1)
    offsets = np.zeros(flat_counts.size + 1, dtype=np.int64)
    np.cumsum(flat_counts, out=offsets[1:])
    pair = np.repeat(np.arange(flat_counts.size, dtype=np.int64), flat_counts)
    rank = _segment_ranks(offsets, pair)
    at = block_at.reshape(-1)[pair] + 1 + width * rank
    gap = tok[at]

    def where(mask) -> tuple[int, str]:
        e = int(np.flatnonzero(mask)[0])
        vertex, block = first_vertex + int(pair[e] // nb), int(pair[e] % nb)
        return e, f"block visibility: vertex {vertex} block {block} entry {int(rank[e])}"

    if gap.size and int(gap.max()) > BLOCK_TEXELS - 1:
        e, at_entry = where(gap > BLOCK_TEXELS - 1)
        raise FileFormatError(f"{at_entry}: index {int(gap[e])} > 255")
    repeat = (gap == 0) & (rank > 0)
    if repeat.any():
        raise FileFormatError(f"{where(repeat)[1]}: indices not strictly increasing")
    index = _segment_cumsum(gap, offsets, pair)
    if index.size and int(index.max()) > BLOCK_TEXELS - 1:
        e, at_entry = where(index > BLOCK_TEXELS - 1)
        raise FileFormatError(f"{at_entry}: index {int(index[e])} > 255")
    delta = None
    if bits:
        levels = _levels(bits)
        d = zigzag_decode(tokens[at + 1])
        bad = (d == 0) | (np.abs(d) > levels)
        if bad.any():
            e, at_entry = where(bad)
            raise FileFormatError(f"{at_entry}: derivative {int(d[e])} is zero or beyond +-{levels} ({bits} bits)")
        level = _segment_cumsum(d, offsets, pair)
        out = (level < 0) | (level > levels)
        if out.any():
            e, at_entry = where(out)
            raise FileFormatError(f"{at_entry}: decoded visibility leaves [0, 1] (level {int(level[e])} of {levels})")
        delta = d.astype(np.int16)
    return counts.astype(np.int16), index.astype(np.uint8), delta


def _segment_cumsum(x: np.ndarray, offsets: np.ndarray, pair: np.ndarray) -> np.ndarray:
    """Inclusive cumulative sum of ``x`` restarting at each pair: ``(F,)`` int64."""
    cs = np.zeros(x.size + 1, dtype=np.int64)
    np.cumsum(x, dtype=np.int64, out=cs[1:])
    return cs[1:] - cs[offsets[:-1]][pair]  # minus the sum before each pair's first entry
