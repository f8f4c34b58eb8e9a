"""Reduction of path contributions to tensor entries (Ben-Artzi et al. 2008, Sec. 5.1, bookkeeping).

Per pass group the entries are summed per path (so the per-entry Monte Carlo variance is the
variance over paths, not over light samples); a tile's sums become one sparse
:class:`~torch_brdf.records.polynomial.TensorBlock` per (eye object, bounce), and the terms
that occur are numbered into one :class:`~torch_brdf.records.polynomial.TermTable` per bounce.
"""

from __future__ import annotations

import math

import torch

from ...errors import ValueRangeError
from ...records.polynomial import TensorBlock, TermTable
from .._native import Accumulator, TileSums, key_bits


def _radix_key(cols: list[tuple[torch.Tensor, int]]) -> torch.Tensor:
    key = torch.zeros_like(cols[0][0])
    total = 1
    for x, size in cols:
        total *= max(size, 1)
        if total >= 2**62:
            raise ValueRangeError("too many distinct tensor entries per tile for 64-bit keys; use smaller tiles")
        key = key * max(size, 1) + x
    return key


def _code_fits(m: int, max_count: int) -> bool:
    """Whether :func:`_multiset_ids` numbers multisets of ``m`` objects by one int64 code
    (base ``max_count + 1``, the last object most significant) rather than row by row."""
    return m * math.log2(max(max_count + 1, 2)) < 62


def _first_rows(inv: torch.Tensor, u: int) -> torch.Tensor:
    """(u,) the first row of each of ``u`` distinct values, given each row's index ``inv`` among
    them (``torch.unique(..., return_inverse=True)``)."""
    return torch.full((u,), inv.numel(), dtype=torch.long).scatter_reduce(
        0, inv, torch.arange(inv.numel()), reduce="amin"
    )


def _multiset_ids(counts: torch.Tensor) -> tuple[torch.Tensor, int]:
    """Dense ids of the distinct rows of ``counts`` (n, M) int8: one exact int64 code per row
    (base = max count + 1) when it fits in 62 bits, else ``unique(dim=0)``."""
    m = counts.shape[1]
    base = int(counts.max()) + 1 if counts.numel() else 1
    if _code_fits(m, base - 1):
        powers = base ** torch.arange(m, dtype=torch.long)
        code = (counts.long() * powers).sum(-1)
        uniq, zid = torch.unique(code, return_inverse=True)
        return zid, uniq.numel()
    uniq, zid = torch.unique(counts, dim=0, return_inverse=True)
    return zid, uniq.shape[0]


def _reduce(d: dict[str, torch.Tensor], sizes: dict[str, int], by_path: bool) -> dict[str, torch.Tensor]:
    """Sum rows with equal (record, object, bounce, j, w, counts[, path]) keys.

    Returns unique rows with ``sum`` (U, 3) float64 (and ``sq``: the sum of per-path squares
    when ``by_path``; otherwise ``sq`` is summed from the input's ``sq``)."""
    if not d:
        return {}
    zid, nz = _multiset_ids(d["counts"])
    cols = [
        (d["rec"], sizes["rec"]),
        (d["obj"], sizes["obj"]),
        (d["bounce"], sizes["bounce"]),
        (d["j"], sizes["j"]),
        (d["w"] + 1, sizes["w"] + 1),
        (zid, nz),
    ]
    if by_path:
        cols.append((d["path"], sizes["path"]))
    key = _radix_key(cols)
    uniq, inv = torch.unique(key, return_inverse=True)
    u = uniq.numel()
    first = _first_rows(inv, u)
    w = d["weight"].double()
    s = torch.zeros(u, 3, dtype=torch.float64).index_add_(0, inv, w)
    out = {k: d[k][first] for k in ("rec", "obj", "bounce", "j", "w", "counts")}
    if by_path:
        out["sum"], out["sq"] = s, s * s
    else:
        out["sum"] = s
        out["sq"] = torch.zeros(u, 3, dtype=torch.float64).index_add_(0, inv, d["sq"])
    return out


class NativeEntries:
    """The entries of one pass group, made and summed per (key, path) in the compiled kernel
    (:class:`~torch_brdf.transport._native.Accumulator`): the twin of the tracer's ``_Entries`` followed by
    ``_reduce(..., sizes, by_path=True)``, without a torch op per layer combination or copy.

    Args:
        lib: the kernel (:func:`~torch_brdf.transport._native.library`).
        num_objects: M.
        pixels: p, the tile's records: an entry's ray id ``r`` is record ``r % p``, path ``r // p``.
        bits: :func:`native_bits` of the tile (not None).
    """

    native = True  # the tracer calls :meth:`emit` instead of building entries in torch

    def __init__(self, lib, num_objects: int, pixels: int, bits: list[int]):
        self.acc, self.p = Accumulator(lib, num_objects, 3, bits), pixels

    def emit(self, v, kk, st, lw, rec, ob, ed, f, scale, x, x_rows, y, y_rows):
        """The entries of light samples ``kk`` at vertex ``v`` of the path state ``st``
        (:meth:`~._native.Accumulator.emit`)."""
        raw = st.raw if v > 1 else None  # the eye vertex's weights are the layer factors times the light's
        self.acc.emit(v, self.p, kk, raw, st.idx, rec, st.m1, st.counts, ob, ed, lw, f, scale, x, x_rows, y, y_rows)

    def reduce(self) -> dict[str, torch.Tensor]:
        """``_reduce(entries, sizes, by_path=True)`` of the entries made."""
        return _exported(self.acc)

    def reduce_into(self, tile) -> None:
        """Add :meth:`reduce`'s sums (and squares) to a :func:`tile_accumulator` without leaving
        the kernel: the tile's :func:`_exported` then equals ``_reduce_groups`` of the groups'
        :meth:`reduce` outputs bit for bit (same sums, same order)."""
        self.acc.reduce_into(not _code_fits(self.acc.M, self.acc.max_count()), tile)


def tile_accumulator(lib, num_objects: int, bits: list[int]) -> TileSums | Accumulator:
    """The accumulator of a tile's per-path sums and squares (keys without the path field),
    for :meth:`NativeEntries.reduce_into`; ``bits``: the pass groups' :func:`native_bits`.
    A :class:`~torch_brdf.transport._native.TileSums` (per-record tables, no sort) where the
    groups' record and path fields fit its buckets, else an accumulator of the groups' sorted
    runs (merged at the end); both give the same sums bit for bit."""
    if TileSums.fits(bits):
        return TileSums(lib, num_objects, bits[:-1] + [0])
    return Accumulator(lib, num_objects, 6, bits[:-1] + [0])


def native_bits(sizes: dict[str, int], num_objects: int, bounces: int) -> list[int] | None:
    """The packed key widths of a tile's per-path keys (None: too wide for the kernel)."""
    return key_bits(sizes, num_objects, bounces, by_path=True)


def _exported(acc: Accumulator) -> dict[str, torch.Tensor]:
    """An accumulator's sums as :func:`_reduce` returns them (same keys, order and dtypes)."""
    if len(acc) == 0:
        return {}
    keys, vals = acc.reduce(forward=not _code_fits(acc.M, acc.max_count()))
    out = {k: keys[:, c].contiguous() for c, k in enumerate(("rec", "obj", "bounce", "j", "w"))}
    out["counts"] = keys[:, 5:].to(torch.int8)
    if acc.V == 3:
        out["sum"], out["sq"] = vals, vals * vals
    else:
        out["sum"], out["sq"] = vals[:, :3].contiguous(), vals[:, 3:].contiguous()
    return out


def _reduce_groups(lib, groups: list[dict[str, torch.Tensor]], num_objects: int, bits: list[int]):
    """``_reduce(cat(groups), sizes, by_path=False)`` in the compiled kernel: the per-path sums
    of a tile's pass groups summed per key in the same order (group by group). ``bits``: the
    groups' :func:`native_bits` (its path field is dropped)."""
    acc = Accumulator(lib, num_objects, 6, bits[:-1] + [0])
    for g in groups:
        vals = torch.cat([g["sum"], g["sq"]], 1)
        acc.add_sums(g["rec"], g["obj"], g["bounce"], g["j"], g["w"], g["counts"], vals)
    return _exported(acc)


def _local_blocks(red: dict[str, torch.Tensor], bases, spp: int | torch.Tensor) -> list[dict[str, torch.Tensor]]:
    """The part of the block assembly that needs only the tile (it runs where the tile ran):
    per (eye object, bounce) the pixels and terms that occur, numbered locally, and the
    entries sorted by their local flat index.

    Returns one dict per block: ``head`` (3,) [object, bounce, J]; ``upix`` (P,) tile-local
    pixel records; ``tw`` (Z,) and ``tc`` (Z, M) the terms (second-bounce slot, multiset) in
    local order; ``key`` (E,) ascending ``(j * Z + z) * P + p`` with local z and p; ``vals``
    and ``var`` (C, E) float32 mean and Monte Carlo variance. ``spp``: the paths per pixel,
    or (U, 1) those of each entry's pixel (a tile of mixed spp).
    """
    if not red:
        return []
    out = []
    mean = red["sum"] / spp
    dof = max(spp - 1, 1) if isinstance(spp, int) else (spp - 1).clamp_min(1)
    var = ((red["sq"] / spp - mean * mean) / dof).clamp_min(0)
    group = red["obj"] * 1000 + red["bounce"]
    # each block's rows in their order, by one stable sort (not a full-size mask per block)
    order = torch.argsort(group, stable=True)
    gkeys, sizes = torch.unique_consecutive(group[order], return_counts=True)
    for gkey, m in zip(gkeys.tolist(), torch.split(order, sizes.tolist()), strict=True):
        obj, bounce = divmod(int(gkey), 1000)
        upix, prow = torch.unique(red["rec"][m], return_inverse=True)
        tw, tc = red["w"][m], red["counts"][m]
        zid, nz = _multiset_ids(tc)
        upid, pinv = torch.unique((tw + 1) * nz + zid, return_inverse=True)
        first = _first_rows(pinv, upid.numel())
        J = 1 if bases[obj] is None else bases[obj].size
        key, perm = torch.sort((red["j"][m] * upid.numel() + pinv) * upix.numel() + prow)
        out.append(
            {
                "head": torch.tensor([obj, bounce, J]),
                "upix": upix,
                "tw": tw[first],
                "tc": tc[first],
                "key": key,
                "vals": mean[m][perm].T.float().contiguous(),
                "var": var[m][perm].T.float().contiguous(),
            }
        )
    return out


def native_local_blocks(acc: TileSums | Accumulator, bases, spp: int | torch.Tensor) -> list[dict[str, torch.Tensor]]:
    """:func:`_local_blocks` of a tile's sums (:func:`tile_accumulator`) in the compiled kernel
    (``tb_blocks``): the same blocks, bit for bit. ``spp``: the paths per pixel, or (P,) those of
    each of the tile's records."""
    if len(acc) == 0:
        return []
    sp = spp.to(torch.int64).contiguous() if isinstance(spp, torch.Tensor) else None
    if isinstance(acc, TileSums):
        out = _tile_blocks(acc, bases, spp, sp)
        if out is not None:
            return out
    keys, vals = acc.reduce(not _code_fits(acc.M, acc.max_count()))
    u, m = keys.shape[0], acc.M
    bits = torch.tensor(acc.bits[:6], dtype=torch.int32)
    room = (1 << (acc.bits[1] + acc.bits[2])) if acc.bits[1] + acc.bits[2] <= 20 else 0
    key, upix, rows = (torch.empty(u, dtype=torch.int64) for _ in range(3))
    mean, var = torch.empty(3 * u, dtype=torch.float32), torch.empty(3 * u, dtype=torch.float32)
    meta = torch.empty(max(room, 1), 5, dtype=torch.int64)
    nb = acc.lib.tb_blocks(
        u, m, bits.data_ptr(), keys.data_ptr(), vals.data_ptr(), None if sp is None else sp.data_ptr(),
        0 if sp is not None else int(spp), room, *(t.data_ptr() for t in (key, mean, var, upix, rows, meta)),
    )  # fmt: skip
    if nb == -1:
        raise MemoryError("the block kernel ran out of memory")
    if nb < 0:  # fields too wide for the kernel's tables: torch
        red = {k: keys[:, c].contiguous() for c, k in enumerate(("rec", "obj", "bounce", "j", "w"))}
        red["counts"] = keys[:, 5:].to(torch.int8)
        red["sum"], red["sq"] = vals[:, :3].contiguous(), vals[:, 3:].contiguous()
        return _local_blocks(red, bases, spp if sp is None else sp[red["rec"]][:, None])
    out, at, up = [], 0, 0
    for obj, bounce, e, p, z in meta[:nb].tolist():
        t = rows[up : up + z]
        out.append(
            _block(bases, obj, bounce, upix[up : up + p], keys[t, 4], keys[t, 5:].to(torch.int8), key, mean, var, at, e)
        )
        at, up = at + e, up + max(p, z)
    return out


def _block(bases, obj: int, bounce: int, upix, tw, tc, key, mean, var, at: int, e: int) -> dict[str, torch.Tensor]:
    """One block of :func:`native_local_blocks` (object ``obj``, ``bounce``): its pixels, term
    tables and the ``e`` entries from ``at`` of the kernel's ``key``, ``mean`` and ``var``."""
    return {
        "head": torch.tensor([obj, bounce, 1 if bases[obj] is None else bases[obj].size]),
        "upix": upix.clone(),
        "tw": tw,
        "tc": tc,
        "key": key[at : at + e].clone(),
        "vals": mean[3 * at : 3 * (at + e)].view(3, e).clone(),
        "var": var[3 * at : 3 * (at + e)].view(3, e).clone(),
    }


def _tile_blocks(acc: TileSums, bases, spp, sp: torch.Tensor | None) -> list[dict[str, torch.Tensor]] | None:
    """:func:`native_local_blocks` of a :class:`~torch_brdf.transport._native.TileSums` read in
    place (``tb_tile_blocks``: no export of its keys, no sort of them), or None when its fields
    are too wide for the kernel's tables."""
    u, m = len(acc), acc.M
    if acc.bits[1] + acc.bits[2] > 20:
        return None
    nblk = 1 << (acc.bits[1] + acc.bits[2])
    key, upix, tw = (torch.empty(u, dtype=torch.int64) for _ in range(3))
    tc = torch.empty(u, m, dtype=torch.int8)
    mean, var = torch.empty(3 * u, dtype=torch.float32), torch.empty(3 * u, dtype=torch.float32)
    meta = torch.empty(nblk, 5, dtype=torch.int64)
    nb = acc.lib.tb_tile_blocks(
        acc._h, None if sp is None else sp.data_ptr(), 0 if sp is not None else int(spp), nblk,
        *(t.data_ptr() for t in (key, mean, var, upix, tw, tc, meta)),
    )  # fmt: skip
    if nb == -2:
        return None
    if nb < 0:
        raise MemoryError("the block kernel ran out of memory")
    out, at, ap, az = [], 0, 0, 0
    for obj, bounce, e, p, z in meta[:nb].tolist():
        tw_z, tc_z = tw[az : az + z].clone(), tc[az : az + z].clone()
        out.append(_block(bases, obj, bounce, upix[ap : ap + p], tw_z, tc_z, key, mean, var, at, e))
        at, ap, az = at + e, ap + p, az + z
    return out


class TermNumbering:
    """The driver's part of the block assembly: the tiles' blocks, then the global term ids.

    :meth:`add` takes a tile's blocks (:func:`_local_blocks`, in tile order) as they are: no
    numbering per tile, no entry moved. :meth:`finish`, once every tile is in, numbers each
    bounce's terms in one canonical order, ascending ``(w, c_{M-1}, ..., c_0)`` (last object most
    significant), which is the order in which :func:`_local_blocks` (and the compiled
    ``tb_blocks``) already hold a block's terms whenever their multiset codes fit in 62 bits. Each
    block's ids are then increasing as they are; a block in another order (codes too wide: the
    rows' own order) has its entries re-sorted. Numbering the terms in order of first appearance while the tiles
    come in would leave blocks to re-sort on the driver: serial work per tile that bounds the
    speedup on a cluster.

    Args:
        num_objects: M, the width of a term's counts.
        bounces: the series' bounces (every bounce gets a table, empty if no entry reached it).
    """

    def __init__(self, num_objects: int, bounces: int):
        self.M, self.bounces = num_objects, bounces
        self.pending: list[tuple[dict[str, torch.Tensor], torch.Tensor]] = []

    def add(self, local: list[dict[str, torch.Tensor]], pixels: torch.Tensor) -> None:
        """A tile's blocks (:func:`_local_blocks`); ``pixels`` (P_tile,) the flat pixel indices of
        its records."""
        self.pending.extend((b, pixels) for b in local)

    def finish(self) -> tuple[dict[int, TermTable], list[TensorBlock]]:
        """(per bounce its :class:`TermTable`, the blocks in the order they were added)."""
        by_bounce: dict[int, list[int]] = {}
        for i, (b, _) in enumerate(self.pending):
            by_bounce.setdefault(int(b["head"][1]), []).append(i)
        terms, gids = {}, {}
        for n in range(1, self.bounces + 1):
            members = by_bounce.get(n, [])
            if not members:
                terms[n] = TermTable(torch.zeros(0, dtype=torch.long), torch.zeros(0, self.M, dtype=torch.long))
                continue
            w = torch.cat([self.pending[i][0]["tw"] for i in members]).long()
            c = torch.cat([self.pending[i][0]["tc"] for i in members]).long()
            uniq, inv = _canonical_rows(w, c)
            terms[n] = TermTable(uniq[:, 0].contiguous(), uniq[:, 1:].contiguous())
            at = 0
            for i in members:
                z = self.pending[i][0]["tw"].numel()
                gids[i], at = inv[at : at + z], at + z
        blocks = [_global_block(b, pixels, gids[i]) for i, (b, pixels) in enumerate(self.pending)]
        self.pending = []
        return terms, blocks


def _canonical_rows(w: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct terms (w, *counts) of ``w`` (n,) and ``c`` (n, M), ascending (w, c_{M-1}, ...,
    c_0), as (T, 1 + M) rows, and each input row's index among them: by one exact int64 code per
    row when it fits in 62 bits (base = largest count + 1), else by ``unique(dim=0)``. The
    counts are >= 0 and w >= -1 (a tile's own terms)."""
    m = c.shape[1]
    base = int(c.max()) + 1 if c.numel() else 1
    span = int(w.max()) + 2 if w.numel() else 1
    if span * base**m < 2**62:
        code = (w + 1) * base**m + (c * base ** torch.arange(m, dtype=torch.long)).sum(-1)
        ucode, inv = torch.unique(code, return_inverse=True)
        first = _first_rows(inv, ucode.numel())
        return torch.cat([w[first, None], c[first]], 1), inv
    uniq, inv = torch.unique(torch.cat([w[:, None], c.flip(1)], 1), dim=0, return_inverse=True)
    return torch.cat([uniq[:, :1], uniq[:, 1:].flip(1)], 1), inv


def _global_block(b: dict[str, torch.Tensor], pixels: torch.Tensor, gids: torch.Tensor) -> TensorBlock:
    """Block ``b`` of :func:`_local_blocks` with its terms' global ids ``gids`` (Z,), its entries
    re-sorted only where the ids are not increasing."""
    obj, bounce, J = (int(v) for v in b["head"])
    key, vals, vv = b["key"], b["vals"], b["var"]
    if gids.numel() > 1 and not bool((gids[1:] > gids[:-1]).all()):
        order = torch.argsort(gids)
        rank = torch.empty_like(order)
        rank[order] = torch.arange(order.numel())
        z, p = order.numel(), b["upix"].numel()
        jz, prow = torch.div(key, p, rounding_mode="floor"), key % p
        key, perm = torch.sort((torch.div(jz, z, rounding_mode="floor") * z + rank[jz % z]) * p + prow)
        vals, vv = vals[:, perm].contiguous(), vv[:, perm].contiguous()
        gids = gids[order]
    return TensorBlock(obj, bounce, pixels[b["upix"]], gids, J, key, vals, vv)
