r"""Denoise precomputed records along their pixel axis, keeping every BRDF edit exact.

The image is linear in each bounce's coefficients, :math:`B = E + \sum_k g_k(c, \hat c, d)\,T_k`
(Ben-Artzi et al. 2008, Eq. 26/29), with basis images :math:`T_k` fixed by the
precomputation. A denoiser :math:`D` applied to every :math:`T_k` once gives new fixed basis
images :math:`D(T_k)`; every edit is then still the same two matrix products, and the edited
frame is exactly :math:`E + \sum_k g_k D(T_k)`:

* for a linear :math:`D = A` (:class:`~.atrous.EdgeAwareFilter`) that equals :math:`E + A(B - E)`,
  the filter applied to the noisy edited frame, for every :math:`(c, \hat c, d)`;
* for Open Image Denoise (:class:`~.oidn.OIDNBasis`, not linear) the edit is exact *given the
  denoised bases* (linear in the coefficients, as before); it is not OIDN of the edited frame.

The emission term :math:`E` (emitters and the environment seen directly) is left as it is.
Denoising commutes with freezing (Eq. 27): :func:`denoise_frozen` on a frozen tensor equals
freezing the output of :func:`denoise_tensors`, for a linear :math:`D`.

A denoiser here is any callable ``(images (B, 3, H, W), groups (B,) int64) -> (B, 3, H, W)``;
``groups`` numbers images that a non-linear denoiser may merge (consecutive bands of one
term), a linear one ignores them.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import torch

from ..errors import ShapeError, ValueRangeError
from ..records.polynomial import PolynomialTensors, TensorBlock, TermTable
from .atrous import glossy_objects

Denoiser = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

#: images filtered together (memory: ``chunk * 3 * H * W`` floats, a few times over)
DEFAULT_CHUNK = 64


def _chunks(groups: torch.Tensor, chunk: int) -> list[tuple[int, int]]:
    """[start, stop) ranges of about ``chunk`` images that never split a group."""
    out, start, b = [], 0, groups.numel()
    while start < b:
        stop = min(start + chunk, b)
        while stop < b and groups[stop] == groups[stop - 1]:
            stop += 1
        out.append((start, stop))
        start = stop
    return out


def denoise_planes(
    den: Denoiser, values: torch.Tensor, pixels: torch.Tensor, hw: tuple[int, int], groups=None, chunk=DEFAULT_CHUNK
) -> tuple[torch.Tensor, torch.Tensor]:
    """Denoise basis images stored on a pixel subset.

    Args:
        den: the denoiser.
        values: (3, B, P) the B basis images on ``pixels``.
        pixels: (P,) int64 flat row-major pixel indices (ascending).
        hw: (H, W).
        groups: (B,) int64 group ids (default: each image its own group).
    Returns:
        (values (3, B, P'), pixels (P',)): the denoised images on ``pixels`` and every
        pixel where some output is non-zero, ascending.
    """
    c, b, p = values.shape
    if c != 3 or pixels.shape != (p,):
        raise ShapeError(f"expected values (3, B, P) and pixels (P,); got {tuple(values.shape)}, {tuple(pixels.shape)}")
    h, w = hw
    groups = torch.arange(b) if groups is None else groups
    nonzero = torch.zeros(h * w, dtype=torch.bool)
    rows, outs = _chunks(groups, chunk), []
    for a, stop in rows:
        dense = torch.zeros(stop - a, 3, h * w, dtype=values.dtype)
        dense[:, :, pixels] = values[:, a:stop].permute(1, 0, 2)
        res = den(dense.reshape(stop - a, 3, h, w), groups[a:stop]).reshape(stop - a, 3, h * w)
        nonzero |= (res != 0).any(0).any(0)
        outs.append(res)
    new_pix = torch.nonzero(nonzero | _mask(pixels, h * w)).squeeze(1)
    out = torch.zeros(3, b, new_pix.numel(), dtype=values.dtype)
    for (a, stop), res in zip(rows, outs, strict=True):
        out[:, a:stop] = res[:, :, new_pix].permute(1, 0, 2)
    return out, new_pix


def _mask(pixels: torch.Tensor, n: int) -> torch.Tensor:
    m = torch.zeros(n, dtype=torch.bool)
    m[pixels] = True
    return m


def denoise_frozen(frozen: dict[str, Any], den: Denoiser, hw: tuple[int, int], chunk: int = DEFAULT_CHUNK) -> dict:
    """Denoise a frozen tensor (the dict :meth:`PolynomialRenderer.freeze` builds: ``F``
    (C, J, K'·P_i) on pixels ``pix_i``, ``V`` (C, K', P_r) on ``pix_r``; Eq. 27-28).

    Every basis image ``F[:, j, k']`` and ``V[:, k']`` is denoised once; the images of one k'
    form a group (consecutive bands a non-linear denoiser may merge). Returns a new dict of
    the same form, so the renderer's frame is unchanged code; the public way to use it is
    :meth:`PolynomialRenderer.freeze(obj, denoiser=...) <torch_brdf.render.polynomial.PolynomialRenderer.freeze>`.

    Args:
        frozen: the frozen tensor.
        den: the denoiser.
        hw: (H, W) of the view.
    """
    need = {"F", "V", "pix_i", "pix_r", "K"}
    if not need <= set(frozen):
        raise ValueRangeError(f"not a frozen tensor: missing {sorted(need - set(frozen))}")
    F, V, K = frozen["F"], frozen["V"], int(frozen["K"])
    c, j = F.shape[:2]
    p_i = frozen["pix_i"].numel()
    f_img = F.reshape(c, j, K, p_i).permute(0, 2, 1, 3).reshape(c, K * j, p_i)  # images ordered (k', j)
    groups = torch.arange(K).repeat_interleave(j)
    f_out, pix_i = denoise_planes(den, f_img, frozen["pix_i"], hw, groups, chunk)
    f_out = f_out.reshape(c, K, j, -1).permute(0, 2, 1, 3).reshape(c, j, -1).contiguous()
    v_out, pix_r = denoise_planes(den, V, frozen["pix_r"], hw, None, chunk)
    return {**frozen, "F": f_out, "V": v_out.contiguous(), "pix_i": pix_i, "pix_r": pix_r}


def denoise_tensors(
    tensors: PolynomialTensors, den: Denoiser, chunk: int = DEFAULT_CHUNK, max_entries: int | None = 2**28
) -> PolynomialTensors:
    """Denoise every basis image of the multibounce tensors: one image per (eye object,
    bounce, eye coefficient j, term t), gathered over the tiles.

    The output has one sparse :class:`TensorBlock` per (eye object, bounce) over the whole
    view (entries that are non-zero after denoising), no variances, and the same emission,
    terms, bases and series; ``meta["denoised"]`` says what was done. A filter spreads each
    band's entries to the object's neighbouring pixels, so the record grows towards dense
    ``J x Z`` per pixel: ``max_entries`` (stored values, channels included) guards memory.

    Args:
        tensors: the precomputed tensors.
        den: the denoiser; images of one term over consecutive j form a group.
        chunk: images denoised together.
        max_entries: raise :class:`ValueRangeError` before building a larger record.
    """
    h, w = tensors.height, tensors.width
    by_key: dict[tuple[int, int], list[TensorBlock]] = {}
    for b in tensors.blocks:
        by_key.setdefault((b.object_id, b.bounce), []).append(b)
    blocks, total = [], 0
    for (m, n), bl in sorted(by_key.items()):
        jj, tt, pp, vv = [], [], [], []
        for b in bl:
            j, z, p = b.coordinates()
            jj.append(j)
            tt.append(b.terms[z])
            pp.append(b.pixels[p])
            vv.append(b.values)
        j, t, p, v = torch.cat(jj), torch.cat(tt), torch.cat(pp), torch.cat(vv, 1)
        terms = torch.unique(t)
        J = bl[0].J
        pair = torch.searchsorted(terms, t) * J + j  # image id ordered (term, j)
        ids, inv = torch.unique(pair, return_inverse=True)
        pix, pinv = torch.unique(p, return_inverse=True)
        est = ids.numel() * 3 * pix.numel()
        if max_entries is not None and total + est > max_entries:
            raise ValueRangeError(
                f"denoising would store up to {total + est} entries (> max_entries={max_entries}) at "
                f"(object {m}, bounce {n}); denoise a frozen tensor instead (denoise_frozen)"
            )
        vals = torch.zeros(3, ids.numel(), pix.numel(), dtype=v.dtype)
        vals.index_put_((torch.arange(3)[:, None], inv[None], pinv[None]), v, accumulate=True)
        out, new_pix = denoise_planes(den, vals, pix, (h, w), torch.div(ids, J, rounding_mode="floor"), chunk)
        keep = (out != 0).any(0)  # (B, P') entries some channel holds
        bi, pi = torch.nonzero(keep, as_tuple=True)
        z, jb = torch.div(ids[bi], J, rounding_mode="floor"), ids[bi] % J
        index = (jb * terms.numel() + z) * new_pix.numel() + pi
        order = torch.argsort(index)
        total += 3 * index.numel()
        blocks.append(TensorBlock(m, n, new_pix, terms, J, index[order], out[:, bi, pi][:, order].contiguous()))
    meta = {**tensors.meta, "denoised": getattr(den, "description", type(den).__name__)}
    return dataclasses.replace(tensors, blocks=blocks, meta=meta)


def mean_tensors(records: list[PolynomialTensors]) -> PolynomialTensors:
    """The record of all the samples of independent precomputations of one view and series
    (e.g. the two half-spp runs whose frames pick a :class:`~.selection.SelectedRegressionFilter`):
    every block of each record with its values divided by their number (variances by its
    square) and its term rows renumbered into the union of the records' term tables, so
    every frame (full, frozen) is the mean of the records' frames. Blocks of different
    records may share pixels: the renderer adds them. The guides are the first record's.

    Args:
        records: precomputed tensors of the same view, series and bases.
    Returns:
        the mean record; ``meta["spp"]`` is the sum of the records' spp when they all say it.
    Raises:
        ValueRangeError: no records, or records of different views, series or bases.
    """
    if not records:
        raise ValueRangeError("need at least one record")
    first, n = records[0], len(records)
    for r in records[1:]:
        if (r.height, r.width, r.series, r.object_names, r.bases) != (
            first.height,
            first.width,
            first.series,
            first.object_names,
            first.bases,
        ) or r.terms.keys() != first.terms.keys():
            raise ValueRangeError("the records differ in view, series or bases; they cannot be averaged")
    terms, remap = {}, [{} for _ in records]  # remap[record][bounce]: old row -> new row
    for k in first.terms:
        rows = [torch.cat([r.terms[k].w[:, None], r.terms[k].counts.to(r.terms[k].w.dtype)], 1) for r in records]
        union, inverse = torch.unique(torch.cat(rows), dim=0, return_inverse=True)
        terms[k] = TermTable(union[:, 0].contiguous(), union[:, 1:].to(first.terms[k].counts.dtype).contiguous())
        for i, part in enumerate(torch.split(inverse, [x.shape[0] for x in rows])):
            remap[i][k] = part
    blocks = [
        dataclasses.replace(
            b,
            terms=remap[i][b.bounce][b.terms],
            values=b.values / n,
            variance=None if b.variance is None else b.variance / n**2,
        )
        for i, r in enumerate(records)
        for b in r.blocks
    ]
    emission = sum(r.emission for r in records) / n
    meta = {**first.meta, "mean_of": n}
    spps = [r.meta.get("spp") for r in records]
    if all(isinstance(x, int) for x in spps):
        meta["spp"] = sum(spps)
    return dataclasses.replace(first, terms=terms, blocks=blocks, emission=emission, meta=meta)


def memory_bytes(tensors: PolynomialTensors) -> int:
    """Bytes of the record's stored entries (values, indices, variances)."""
    return sum(b.nbytes for b in tensors.blocks)


def dense_fraction(tensors: PolynomialTensors) -> float:
    """Stored entries over the dense (C, J, Z, P) size of the blocks (1 = dense)."""
    d = tensors.num_dense_entries
    return tensors.num_entries / d if d else math.nan


def make_denoiser(guides, method: str = "linear", glossy=(), settings=None, quality: str = "high") -> Denoiser:
    """The denoiser ``method`` of a view: ``"linear"`` (:class:`~.atrous.EdgeAwareFilter`,
    ``settings`` an :class:`~.atrous.AtrousSettings`), ``"regression"``
    (:class:`~.regression.RegressionFilter`, ``settings`` a
    :class:`~.regression.RegressionSettings`), ``"oidn"`` (:class:`~.oidn.OIDNBasis` over
    the à-trous filter; needs the ``denoise`` extra) or ``"cumulative"``
    (:class:`~.oidn.CumulativeOIDN`, OIDN per cumulative band sum, over the regression filter
    (``settings`` its :class:`~.regression.RegressionSettings`); needs the ``denoise`` extra;
    with two half-spp records, pass ``CumulativeOIDN(guides, SelectedRegressionFilter(...))``).

    Args:
        guides: the view's :class:`~torch_brdf.records.guides.GuideBuffers`.
        method: ``"linear"``, ``"regression"``, ``"oidn"`` or ``"cumulative"``.
        glossy: object ids with more than one band (the half-vector guide applies there).
        settings: the linear filter's settings (default: its settings class's defaults).
        quality: OIDN quality.
    Raises:
        ValueRangeError: an unknown method.
    """
    from .atrous import EdgeAwareFilter
    from .oidn import CumulativeOIDN, OIDNBasis
    from .regression import RegressionFilter

    if method not in ("linear", "regression", "oidn", "cumulative"):
        raise ValueRangeError(f"method must be 'linear', 'regression', 'oidn' or 'cumulative'; got {method!r}")
    if method == "regression":
        return RegressionFilter(guides, settings, glossy=glossy)
    if method == "cumulative":
        return CumulativeOIDN(guides, RegressionFilter(guides, settings, glossy=glossy), quality=quality)
    linear = EdgeAwareFilter(guides, settings, glossy=glossy)
    return linear if method == "linear" else OIDNBasis(guides, linear, quality=quality)


def denoise(
    tensors: PolynomialTensors, method: str | Denoiser = "linear", settings=None, **options
) -> PolynomialTensors:
    """Denoise the precomputed tensors with the guides they carry (attached by
    :func:`~torch_brdf.transport.polynomial.precompute_polynomial` by default).

    Args:
        tensors: the precomputed tensors (with ``tensors.guides``).
        method: ``"linear"``, ``"regression"``, ``"oidn"``, ``"cumulative"`` (see :func:`make_denoiser`)
            or a denoiser.
        settings: the linear filter's settings (see :func:`make_denoiser`).
        **options: passed to :func:`denoise_tensors` (``chunk``, ``max_entries``).
    Returns:
        the denoised :class:`PolynomialTensors` (render them as before).
    Raises:
        ValueRangeError: the tensors carry no guides (precomputed with ``guides=False``).
    """
    if isinstance(method, str):
        if tensors.guides is None:
            raise ValueRangeError(
                "the tensors carry no guides: precompute with guides=True or attach guide_buffers(scene)"
            )
        method = make_denoiser(tensors.guides, method, glossy_objects(tensors), settings)
    return denoise_tensors(tensors, method, **options)
