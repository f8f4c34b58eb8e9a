r"""Haar wavelets on cubemap faces and the triple-product integral of Ng, Ramamoorthi & Hanrahan.

Direct lighting at a vertex is the discrete triple product over cubemap texels

.. math::
    B_c = \sum_t L_c(t)\, V(t)\, \rho_c(t),

with :math:`L` the lighting (solid angle folded in), :math:`V` the visibility and
:math:`\rho` the cosine-folded BRDF of the vertex. Ng, Ramamoorthi & Hanrahan, "Triple
product wavelet integrals for all-frequency relighting" (SIGGRAPH 2004), expand each
factor per cubemap face in the orthonormal 2-D Haar basis, keep only the largest lighting
and BRDF coefficients (non-linear approximation, Sec. 5), keep visibility exact, and
evaluate :math:`\sum_{ijk} C_{ijk} L_i V_j \rho_k` with the tripling coefficients
:math:`C_{ijk} = \sum_t \Psi_i(t)\Psi_j(t)\Psi_k(t)`, which vanish except in the cases of
their "Haar tripling coefficient theorem" (Sec. 4):

1. all three are the scaling function :math:`\phi`: :math:`C = \phi = 1/R`;
2. two are the same wavelet :math:`\psi` and the third is :math:`\phi` or a wavelet at a
   coarser level whose support contains :math:`\psi`'s: :math:`C` = the third function's
   (constant) value on :math:`\psi`'s support, :math:`\pm 2^{l'}/R` (or :math:`1/R`);
3. the three wavelet types (H, V, D) of one node: :math:`C = 2^l/R` (the product of the
   three sign patterns is +1 everywhere).

Inner products are discrete sums over texels (no area factor): a face has ``R * R`` texels,
``R = 2**n``, and the basis is orthonormal for :math:`\langle f, g\rangle = \sum_t f(t) g(t)`.

Coefficient layout (Mallat's, per face, the layout of :func:`haar2d`): entry ``(0, 0)``
holds the scaling coefficient (:math:`\phi = 1/R` on the whole face). At level
``l = 0 .. n-1`` with ``h = 2**l`` nodes per side, node ``(u, v)`` covers texel rows
``[u S, (u+1) S)`` and columns ``[v S, (v+1) S)``, ``S = R / h``, and its three wavelets,
each :math:`\pm 1/S` on the node, sit at

- ``(u, h + v)``: H, :math:`+1/S` on the left half of the node, :math:`-1/S` on the right;
- ``(h + u, v)``: V, :math:`+1/S` on the top half, :math:`-1/S` on the bottom;
- ``(h + u, h + v)``: D, :math:`+1/S` on the top-left and bottom-right quarters, else :math:`-1/S`.

Cubemap coefficients ``(6, R, R)`` are addressed by the flat position
``face * R * R + row * R + col`` (the order of ``.reshape(6 * R * R)``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from torch import nn

from .._checks import as_float_tensor, check_finite
from ..errors import ShapeError, TorchBRDFError, ValueRangeError

__all__ = [
    "HaarTripleProduct",
    "SparseHaar",
    "haar2d",
    "haar_tripling_coefficients",
    "ihaar2d",
    "keep_largest",
]

#: faces of a cubemap
FACES = 6


def _log2(size: int, what: str) -> int:
    """``n`` with ``size == 2**n``; ShapeError otherwise."""
    if size < 1 or size & (size - 1):
        raise ShapeError(f"{what}: expected a power-of-two size R (1, 2, 4, ...); got {size}")
    return size.bit_length() - 1


def _square_images(x, name: str) -> tuple[torch.Tensor, int]:
    """``x`` as a float tensor of (..., R, R) images with R a power of two, and R."""
    x = as_float_tensor(x, name)
    if x.ndim < 2 or x.shape[-1] != x.shape[-2]:
        raise ShapeError(f"Expected {name} to have shape (..., R, R); got {tuple(x.shape)}")
    _log2(x.shape[-1], name)
    return x, x.shape[-1]


def haar2d(x: torch.Tensor) -> torch.Tensor:
    r"""Orthonormal non-standard (pyramid) 2-D Haar transform of square images.

    Each step replaces the 2x2 blocks ``[[a, b], [c, d]]`` of the current approximation by
    :math:`(a+b+c+d)/2` (approximation, top-left quarter) and the details
    :math:`(a-b+c-d)/2` (H, top-right), :math:`(a+b-c-d)/2` (V, bottom-left) and
    :math:`(a-b-c+d)/2` (D, bottom-right), then recurses on the approximation; the layout
    is described in the module docstring. The transform is orthonormal:
    ``(haar2d(x) ** 2).sum() == (x ** 2).sum()``.

    Args:
        x: (..., R, R) images, R a power of two; any floating dtype (integers become the
            default float dtype).
    Returns:
        (..., R, R) coefficients in ``x``'s dtype.
    Raises:
        ShapeError: the last two dims are not equal or R is not a power of two.
    """
    x, size = _square_images(x, "haar2d input")
    lead = x.shape[:-2]
    out = torch.empty_like(x, memory_format=torch.contiguous_format)
    approx = x
    s = size
    while s > 1:
        h = s // 2
        q = approx.reshape(*lead, h, 2, h, 2)
        a, b = q[..., :, 0, :, 0], q[..., :, 0, :, 1]
        c, d = q[..., :, 1, :, 0], q[..., :, 1, :, 1]
        left, right = a + c, b + d
        a_c, b_d = a - c, b - d  # top minus bottom in the left / right column
        out[..., :h, h:s] = (left - right) * 0.5  # H: left minus right
        out[..., h:s, :h] = (a_c + b_d) * 0.5  # V: top minus bottom
        out[..., h:s, h:s] = (a_c - b_d) * 0.5  # D
        approx = (left + right) * 0.5
        s = h
    out[..., :1, :1] = approx
    return out


def ihaar2d(c: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`haar2d` (its transpose, the transform being orthonormal).

    Args:
        c: (..., R, R) coefficients in the layout of :func:`haar2d`, R a power of two.
    Returns:
        (..., R, R) images in ``c``'s dtype.
    Raises:
        ShapeError: the last two dims are not equal or R is not a power of two.
    """
    c, size = _square_images(c, "ihaar2d input")
    lead = c.shape[:-2]
    approx = c[..., :1, :1]
    h = 1
    while h < size:
        s = 2 * h
        hh, vv, dd = c[..., :h, h:s], c[..., h:s, :h], c[..., h:s, h:s]
        p, m = approx + vv, approx - vv  # top / bottom halves before the H and D split
        a, b = (p + hh + dd) * 0.5, (p - hh - dd) * 0.5
        cc, d = (m + hh - dd) * 0.5, (m - hh + dd) * 0.5
        top = torch.stack((a, b), dim=-1)  # (..., h, h, 2)
        bottom = torch.stack((cc, d), dim=-1)
        approx = torch.stack((top, bottom), dim=-3).reshape(*lead, s, s)  # (..., h, 2, h, 2)
        h = s
    return approx.clone() if size == 1 else approx


# --------------------------------------------------------------------------------------
# tables of the tripling-coefficient rules (per face, float64, cached per R)


@dataclass(frozen=True)
class _FaceTables:
    """Per-face tables of the Haar tripling rules, indexed by in-face flat position ``p``.

    Attributes:
        anc_idx: (R*R, A) long, the strictly coarser basis functions whose support contains
            ``p``'s: column 0 is :math:`\\phi`, column ``1 + 3 l' + t`` the type-``t`` wavelet
            (0 = H, 1 = V, 2 = D) of the level-``l'`` ancestor node; ``A = max(1, 3n - 2)``.
            Unused columns (levels >= ``p``'s, and every column of :math:`\\phi`) hold 0.
        anc_w: (R*R, A) float64, the value of that ancestor on ``p``'s support (Ng et al.
            case 2), 0 in unused columns.
        sib: (R*R, 2) long, the other two wavelet types of ``p``'s node (``p`` itself for
            :math:`\\phi`).
        c3: (R*R,) float64, the case-3 coefficient ``1/S`` of ``p``'s node (0 for :math:`\\phi`).
        phi: (R*R,) float64, ``1/R`` at the scaling position, 0 elsewhere (case 1).
    """

    anc_idx: torch.Tensor
    anc_w: torch.Tensor
    sib: torch.Tensor
    c3: torch.Tensor
    phi: torch.Tensor


@functools.lru_cache(maxsize=8)
def _face_tables(size: int) -> _FaceTables:
    n = _log2(size, "cubemap")
    n_pos = size * size
    width = max(1, 3 * n - 2)
    r, c = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    r, c = r.reshape(-1), c.reshape(-1)
    detail = torch.arange(n_pos) > 0
    m = torch.maximum(r, c)
    level = torch.full((n_pos,), -1, dtype=torch.long)
    for lv in range(n):
        level[m >= (1 << lv)] = lv
    h = torch.where(detail, torch.ones_like(level) << level.clamp_min(0), torch.zeros_like(level))
    typ = torch.where(r < h, 0, torch.where(c < h, 1, 2))  # 0 = H (top-right), 1 = V, 2 = D
    u = r - h * (typ >= 1)
    v = c - h * (typ != 1)

    def position(lv, uu, vv, t):
        hh = 1 << lv if isinstance(lv, int) else torch.ones_like(lv) << lv
        return (uu + hh * (t >= 1)) * size + (vv + hh * (t != 1))

    anc_idx = torch.zeros(n_pos, width, dtype=torch.long)
    anc_w = torch.zeros(n_pos, width, dtype=torch.float64)
    anc_w[detail, 0] = 1.0 / size
    for lv in range(n - 1):  # ancestors at level lv of the positions at finer levels
        sel = level > lv
        shift = level[sel] - lv
        uu, vv = u[sel], v[sel]
        au, av = uu >> shift, vv >> shift
        qr, qc = (uu >> (shift - 1)) & 1, (vv >> (shift - 1)) & 1  # quadrant of p within the ancestor
        value = (1 << lv) / size  # 1 / S of level lv
        signs = (1 - 2 * qc, 1 - 2 * qr, 1 - 2 * (qr ^ qc))
        for t in range(3):
            col = 1 + 3 * lv + t
            anc_idx[sel, col] = position(lv, au, av, torch.full_like(au, t))
            anc_w[sel, col] = signs[t].to(torch.float64) * value
    others = torch.tensor([[1, 2], [0, 2], [0, 1]])[typ]  # (R*R, 2) the two other types
    lv2 = level.clamp_min(0)[:, None].expand(-1, 2)
    sib = position(lv2, u[:, None].expand(-1, 2), v[:, None].expand(-1, 2), others)
    sib[~detail] = 0
    c3 = torch.where(detail, h.to(torch.float64) / size, torch.zeros(n_pos, dtype=torch.float64))
    phi = torch.zeros(n_pos, dtype=torch.float64)
    phi[0] = 1.0 / size
    return _FaceTables(anc_idx=anc_idx, anc_w=anc_w, sib=sib, c3=c3, phi=phi)


def haar_tripling_coefficients(resolution: int, i, j, k) -> torch.Tensor:
    r"""Tripling coefficients :math:`C_{ijk}` of one face from the rules of Ng et al. 2004, Sec. 4.

    The same tables drive :meth:`HaarTripleProduct.product`; this function exposes them for
    checking against a brute-force sum over texels.

    Args:
        resolution: face size R (a power of two).
        i: (...) broadcastable integer tensors of in-face flat positions
            ``row * R + col`` in the layout of :func:`haar2d`, each in ``[0, R*R)``.
        j: as ``i``.
        k: as ``i``.
    Returns:
        (...) float64 :math:`C_{ijk} = \sum_t \Psi_i(t)\Psi_j(t)\Psi_k(t)`.
    Raises:
        ShapeError: R is not a power of two, or the indices do not broadcast.
        ValueRangeError: an index is outside ``[0, R*R)``.
    """
    size = int(resolution)
    tab = _face_tables(size)
    try:
        i, j, k = torch.broadcast_tensors(*(torch.as_tensor(a, dtype=torch.long) for a in (i, j, k)))
    except RuntimeError as exc:
        raise ShapeError(f"tripling indices must broadcast; got {exc}") from exc
    for name, a in (("i", i), ("j", j), ("k", k)):
        if a.numel() and (int(a.min()) < 0 or int(a.max()) >= size * size):
            raise ValueRangeError(f"tripling index {name} must lie in [0, {size * size}); got {a.min()}..{a.max()}")
    out = ((i == 0) & (j == 0) & (k == 0)).to(torch.float64) / size  # case 1
    for a, b, third in ((i, j, k), (j, k, i), (i, k, j)):  # case 2: a == b, third coarser
        w = ((tab.anc_idx[a] == third[..., None]) * tab.anc_w[a]).sum(-1)
        out = out + torch.where(a == b, w, torch.zeros_like(w))
    sib = tab.sib[i]  # case 3: j and k are i's two siblings (in either order)
    same_node = ((j == sib[..., 0]) & (k == sib[..., 1])) | ((j == sib[..., 1]) & (k == sib[..., 0]))
    return out + torch.where(same_node, tab.c3[i], torch.zeros_like(out))


# --------------------------------------------------------------------------------------
# non-linear approximation


@dataclass(frozen=True)
class SparseHaar:
    """The kept Haar coefficients of a batch of cubemaps (non-linear approximation).

    Attributes:
        indices: (..., k) long, flat positions ``face * R * R + row * R + col`` (layout of
            :func:`haar2d` per face), ascending along the last dim.
        values: (..., k, C) the coefficients at those positions (all channels), or (..., k)
            for single-channel input (``channels=False`` in :func:`keep_largest`).
        resolution: face size R.
    """

    indices: torch.Tensor
    values: torch.Tensor
    resolution: int

    @property
    def k(self) -> int:
        """Number of kept coefficients per batch item."""
        return self.indices.shape[-1]

    @property
    def has_channels(self) -> bool:
        """True when ``values`` carries a trailing channel dim."""
        return self.values.ndim == self.indices.ndim + 1

    def to_dense(self) -> torch.Tensor:
        """Dense coefficients with zeros at the dropped positions.

        Returns:
            (..., 6, R, R, C) (or (..., 6, R, R) without channels) in ``values``' dtype.
        """
        size = self.resolution
        vals = self.values if self.has_channels else self.values[..., None]
        lead, ch = self.indices.shape[:-1], vals.shape[-1]
        dense = vals.new_zeros(*lead, FACES * size * size, ch)
        dense.scatter_(-2, self.indices[..., None].expand(*self.indices.shape, ch), vals)
        dense = dense.reshape(*lead, FACES, size, size, ch)
        return dense if self.has_channels else dense[..., 0]


def _kept_count(fraction: float, n: int) -> int:
    f = float(fraction)
    if not (math.isfinite(f) and 0.0 < f <= 1.0):
        raise ValueRangeError(f"fraction of kept coefficients must lie in (0, 1]; got {fraction}")
    # round away products like 0.01 * 24576 = 245.76000000000002 only at the 1e-9 level
    return min(n, max(1, math.ceil(f * n - 1e-9)))


def _largest_positions(score: torch.Tensor, k: int) -> torch.Tensor:
    """Positions of the k largest scores per row, ascending; ties go to the lower position.

    Args:
        score: (B, N) finite scores.
        k: 1 <= k <= N.
    Returns:
        (B, k) long.
    """
    rows, n = score.shape
    if k == n:
        return torch.arange(n, device=score.device).expand(rows, n).clone()
    kth = score.topk(k, dim=-1).values[:, -1:]  # (B, 1) the k-th largest score
    keep = score > kth
    tied = score == kth
    need = k - keep.sum(-1)  # (B,) >= 1 tied positions still to take
    excess = (tied.sum(-1) > need).nonzero()[:, 0]  # rows with more ties than places (rare with real data)
    keep |= tied
    if excess.numel():
        first = tied[excess].cumsum(-1) <= need[excess, None]  # the lowest tied positions
        keep[excess] = keep[excess] & (~tied[excess] | first)
    return keep.nonzero()[:, 1].reshape(rows, k)


def keep_largest(coeffs: torch.Tensor, fraction: float, *, channels: bool = True) -> SparseHaar:
    r"""Keep the largest Haar coefficients of each cubemap (non-linear approximation, Ng et al. Sec. 5).

    Per batch item keeps the ``k = max(1, ceil(fraction * 6 R^2))`` positions of largest
    magnitude and drops the rest. With channels a position is ranked by the sum over channels
    of :math:`|c|` (its L1 norm, so one RGB position competes as a whole) and all its channels
    are kept. Ties are broken towards the lower flat position, so the choice is deterministic.

    Args:
        coeffs: (..., 6, R, R, C) Haar coefficients (:func:`haar2d` per face), or
            (..., 6, R, R) with ``channels=False``.
        fraction: share of the ``6 R^2`` positions to keep, in (0, 1].
        channels: whether ``coeffs`` has a trailing channel dim.
    Returns:
        :class:`SparseHaar` with indices (..., k) and values (..., k, C) (or (..., k)).
    Raises:
        ShapeError: the shape is not (..., 6, R, R[, C]) with R a power of two.
        ValueRangeError: ``fraction`` outside (0, 1] or non-finite coefficients.
    """
    x = as_float_tensor(coeffs, "Haar coefficients")
    nd = 4 if channels else 3
    want = "(..., 6, R, R, C)" if channels else "(..., 6, R, R)"
    if x.ndim < nd or x.shape[-nd] != FACES or x.shape[-nd + 1] != x.shape[-nd + 2]:
        raise ShapeError(f"Expected Haar coefficients of shape {want}; got {tuple(x.shape)}")
    size = x.shape[-nd + 1]
    _log2(size, "Haar coefficients")
    check_finite(x, "Haar coefficients")
    n = FACES * size * size
    k = _kept_count(fraction, n)
    lead = x.shape[:-nd]
    flat = x.reshape(-1, n, x.shape[-1] if channels else 1)
    idx = _largest_positions(sum(ch.abs() for ch in flat.unbind(-1)), k)  # L1 over channels
    vals = flat.gather(1, idx[..., None].expand(-1, -1, flat.shape[-1]))
    vals = vals.reshape(*lead, k, flat.shape[-1]) if channels else vals.reshape(*lead, k)
    return SparseHaar(indices=idx.reshape(*lead, k), values=vals, resolution=size)


# --------------------------------------------------------------------------------------
# the triple product


def _cube_haar(x: torch.Tensor) -> torch.Tensor:
    """(..., 6, R, R, C) texels -> (..., 6, R, R, C) Haar coefficients per face and channel."""
    return haar2d(x.movedim(-1, -3)).movedim(-3, -1)


def _check_cube(x, name: str, channels: bool, batched: bool) -> torch.Tensor:
    x = as_float_tensor(x, name)
    want = ("(P, " if batched else "(") + "6, R, R" + (", C)" if channels else ")")
    nd = (4 if channels else 3) + batched
    if x.ndim != nd or x.shape[batched] != FACES or x.shape[batched + 1] != x.shape[batched + 2]:
        raise ShapeError(f"Expected {name} to have shape {want}; got {tuple(x.shape)}")
    _log2(x.shape[batched + 1], name)
    return check_finite(x, name)


class HaarTripleProduct(nn.Module):
    r"""Direct lighting by Haar triple products (Ng, Ramamoorthi & Hanrahan 2004).

    ``B_c = sum_t L_c(t) V(t) rho_c(t)`` per vertex with the lighting and the BRDF truncated
    to their largest Haar coefficients and visibility exact, evaluated from the coefficients
    by the tripling rules (never by reconstructing texels). With ``fraction = 1`` for both
    the result equals the dense texel sum up to rounding.

    Usage::

        tp = HaarTripleProduct()
        tp.set_lighting(L, fraction=0.01)                  # L: (6, R, R, C)
        rho_c = tp.brdf_coefficients(rho, fraction=0.01)   # rho: (P, 6, R, R, C)
        v_c = tp.visibility_coefficients(V)                # V: (P, 6, R, R)
        B = tp.product(v_c, rho_c)                         # (P, C)

    Cost of :meth:`product`: ``O(P (nnz(W) + k_rho) C)`` where ``W`` is the fixed
    ``(k_L, |U|)`` matrix of ancestor values of the kept lighting positions (``U`` = their
    distinct strict ancestors), ``nnz(W) <= k_L A`` and ``|U| <= k_L A`` with
    ``A = 3 log2(R) - 2`` ancestors per finest wavelet; nothing in it scales with the texel
    count ``6 R^2``.

    Args:
        chunk_elements: vertices are processed in chunks whose temporaries of
            ``(chunk, k_rho + |U| + k_L, C)`` elements hold at most about this many (at least
            one vertex per chunk).
    """

    def __init__(self, chunk_elements: int = 1 << 22):
        super().__init__()
        if int(chunk_elements) < 1:
            raise ValueRangeError(f"chunk_elements must be >= 1; got {chunk_elements}")
        self.chunk_elements = int(chunk_elements)
        self.resolution: int | None = None
        for name in (
            "light_indices",  # (k_L,) kept lighting positions
            "light_values",  # (k_L, C) their coefficients
            "union",  # (|U|,) U: the distinct strict ancestors of the kept lighting positions
            "w_rows",  # (nnz,) W[q, u]: value of ancestor union[u] on kept position q's support
            "w_cols",  # (nnz,)
            "w_vals",  # (nnz,)
            "slots",  # (6R^2, 4) long: slot in U (|U| if none), slot in light_indices (k_L if
            #           dropped), and the other two wavelet types of the position's node
            "light_table",  # (6R^2, 2C + 1): parent sum of the lighting (+ case 1 at phi),
            #                 truncated lighting coefficient (0 if dropped), case-3 coefficient
        ):
            self.register_buffer(name, None)

    # ---- the three factors -------------------------------------------------------------

    def set_lighting(self, lighting: torch.Tensor, fraction: float = 1.0) -> SparseHaar:
        r"""Transform and truncate the lighting and precompute its side of the product.

        Precomputes the lighting's parent sums :math:`\bar L(p) = \sum_{a \succ p} L_a\,
        \Psi_a|_{\mathrm{supp}\,p}` at every position ``p`` (the value of the truncated
        lighting's reconstruction from levels coarser than ``p`` on ``p``'s support), the
        sparse ancestor matrix ``W`` of the kept lighting positions, and per-position slots.

        Args:
            lighting: (6, R, R, C) texel lighting, solid angle folded in; R a power of two.
            fraction: share of the ``6 R^2`` lighting coefficients to keep, in (0, 1].
        Returns:
            :class:`SparseHaar` with indices (k_L,) and values (k_L, C): the kept lighting.
        Raises:
            ShapeError: wrong shape. ValueRangeError: non-finite values or bad fraction.
        """
        L = _check_cube(lighting, "lighting", channels=True, batched=False)
        size = L.shape[1]
        sparse = keep_largest(_cube_haar(L), fraction)
        tab, dev, dt = _face_tables(size), L.device, L.dtype
        n_face = size * size
        n = FACES * n_face
        offset = (torch.arange(FACES) * n_face)[:, None]  # (6, 1)
        anc_pos = (offset[..., None] + tab.anc_idx).reshape(n, -1).to(dev)  # (6R^2, A)
        anc_w = tab.anc_w.to(dev, dt).repeat(FACES, 1)  # (6R^2, A)
        dense = sparse.to_dense().reshape(n, -1)  # (6R^2, C)
        # case 2 with L the coarser factor (+ case 1 at the scaling positions, phi = 1/R)
        parent = (dense[anc_pos] * anc_w[..., None]).sum(1)
        parent = parent + tab.phi.to(dev, dt).repeat(FACES)[:, None] * dense
        c3 = tab.c3.to(dev, dt).repeat(FACES)[:, None]
        idx = sparse.indices
        k_l = idx.shape[0]
        light_slot = torch.full((n,), k_l, dtype=torch.long, device=dev)
        light_slot[idx] = torch.arange(k_l, device=dev)
        used = anc_w[idx] != 0  # (k_L, A)
        rows = torch.arange(k_l, device=dev)[:, None].expand_as(used)[used]
        union, cols = torch.unique(anc_pos[idx][used], return_inverse=True)
        union_slot = torch.full((n,), union.numel(), dtype=torch.long, device=dev)
        union_slot[union] = torch.arange(union.numel(), device=dev)
        sib = (offset[..., None] + tab.sib).reshape(n, 2).to(dev)

        self.resolution = size
        self.light_indices, self.light_values, self.union = idx, sparse.values, union
        self.w_rows, self.w_cols, self.w_vals = rows, cols, anc_w[idx][used]
        self.slots = torch.cat((union_slot[:, None], light_slot[:, None], sib), dim=1)
        self.light_table = torch.cat((parent, dense, c3), dim=1)
        return sparse

    def brdf_coefficients(self, brdf: torch.Tensor, fraction: float = 1.0) -> SparseHaar:
        """Haar-transform and truncate the per-vertex BRDF (cosine folded in), in chunks of vertices.

        Args:
            brdf: (P, 6, R, R, C) BRDF times cosine at the texel centres, per vertex.
            fraction: share of the ``6 R^2`` coefficients kept per vertex, in (0, 1].
        Returns:
            :class:`SparseHaar` with indices (P, k_rho) and values (P, k_rho, C).
        Raises:
            ShapeError: wrong shape. ValueRangeError: non-finite values or bad fraction.
        """
        rho = _check_cube(brdf, "brdf", channels=True, batched=True)
        size = rho.shape[2]
        _kept_count(fraction, FACES * size * size)  # check before any work
        if rho.shape[0] == 0:
            return keep_largest(_cube_haar(rho), fraction)
        step = max(1, self.chunk_elements // rho[0].numel())
        parts = [keep_largest(_cube_haar(chunk), fraction) for chunk in rho.split(step)]
        return SparseHaar(
            indices=torch.cat([p.indices for p in parts]),
            values=torch.cat([p.values for p in parts]),
            resolution=size,
        )

    def visibility_coefficients(self, visibility: torch.Tensor) -> torch.Tensor:
        """Full (untruncated) Haar coefficients of the per-vertex visibility.

        Args:
            visibility: (P, 6, R, R) visibility per texel, binary or in [0, 1].
        Returns:
            (P, 6, R, R) coefficients, layout of :func:`haar2d` per face.
        Raises:
            ShapeError: wrong shape. ValueRangeError: non-finite values.
        """
        return haar2d(_check_cube(visibility, "visibility", channels=False, batched=True))

    # ---- the product -------------------------------------------------------------------

    def product(self, visibility_coeffs: torch.Tensor, brdf: SparseHaar) -> torch.Tensor:
        r"""Triple product :math:`B_c = \sum_{ijk} C_{ijk} L_{c,i} V_j \rho_{c,k}` over the six faces.

        Write :math:`q` for the kept lighting positions, :math:`p` for a vertex's kept BRDF
        positions, :math:`a \succ x` for the strict ancestors of :math:`x` (coarser wavelets
        whose support contains :math:`x`'s, and :math:`\phi`), :math:`w(a, x)` for the value
        of :math:`\Psi_a` on :math:`x`'s support, and :math:`\bar F(x) = \sum_{a \succ x}
        F_a w(a, x)` for the parent sum. The non-zero tripling coefficients give

        - case 1 (:math:`\phi\phi\phi`): :math:`\sum_f L_{\phi_f} V_{\phi_f}
          \rho_{\phi_f} / R`, taken at the BRDF's scaling positions;
        - case 2, lighting and visibility the equal pair, BRDF coarser:
          :math:`\sum_q L_q V_q \bar\rho(q) = \sum_p \rho_p Y(p)` with
          :math:`Y(p) = \sum_{q \prec p} w(p, q) L_q V_q` (``W^T (L V)``, non-zero on ``U`` only);
        - case 2, visibility and BRDF the equal pair, lighting coarser:
          :math:`\sum_p \rho_p V_p \bar L(p)`, :math:`\bar L` precomputed everywhere;
        - case 2, lighting and BRDF the equal pair, visibility coarser:
          :math:`\sum_p \rho_p L_p \bar V(p)`, non-zero only where both are kept;
          :math:`\bar V` at the kept lighting positions is ``W V_U``;
        - case 3: :math:`\sum_p \rho_p c_3(p) (L_{s_1} V_{s_2} + L_{s_2} V_{s_1})` with
          :math:`s_1, s_2` the other two wavelet types of :math:`p`'s node and
          :math:`c_3 = 2^l / R` (all six assignments of H, V, D to the three factors),
          non-zero only where the lighting has a kept coefficient at the BRDF's node.

        So per vertex: two products with the sparse ``W`` (``nnz(W) <= k_L A``) and a few
        gathers at the ``k_rho`` BRDF positions.

        Args:
            visibility_coeffs: (P, 6, R, R) from :meth:`visibility_coefficients`.
            brdf: :class:`SparseHaar` with indices (P, k_rho) and values (P, k_rho, C) or
                (P, k_rho, 1), from :meth:`brdf_coefficients` (C may be 1 on either side).
        Returns:
            (P, C) outgoing radiance per vertex and channel, in the promoted dtype of the inputs.
        Raises:
            TorchBRDFError: no lighting was set. ShapeError: mismatched shapes or resolution.
        """
        if self.resolution is None:
            raise TorchBRDFError("HaarTripleProduct: call set_lighting(...) before product(...)")
        size = self.resolution
        vis = as_float_tensor(visibility_coeffs, "visibility coefficients")
        if vis.ndim != 4 or tuple(vis.shape[1:]) != (FACES, size, size):
            raise ShapeError(
                f"Expected visibility coefficients of shape (P, 6, {size}, {size}) (the lighting's R); "
                f"got {tuple(vis.shape)}"
            )
        n_vert = vis.shape[0]
        if not isinstance(brdf, SparseHaar) or not brdf.has_channels or brdf.indices.ndim != 2:
            raise ShapeError("Expected brdf as SparseHaar with indices (P, k) and values (P, k, C)")
        if brdf.resolution != size or brdf.indices.shape[0] != n_vert:
            raise ShapeError(
                f"brdf coefficients: expected P={n_vert} vertices at R={size}; "
                f"got P={brdf.indices.shape[0]} at R={brdf.resolution}"
            )
        c_l, c_r = self.light_values.shape[-1], brdf.values.shape[-1]
        if c_l != c_r and 1 not in (c_l, c_r):
            raise ShapeError(f"channels of lighting ({c_l}) and brdf ({c_r}) must match or be 1")
        dt = torch.promote_types(torch.promote_types(vis.dtype, brdf.values.dtype), self.light_values.dtype)
        vis = vis.reshape(n_vert, -1).to(dt)
        l_val = self.light_values.to(dt)
        table = self.light_table.to(dt)
        l_dense = table[:, c_l : 2 * c_l]
        k_l, n_u, k_r = l_val.shape[0], self.union.numel(), brdf.k
        # W (k_L, |U|) and its transpose, coalesced once per call (nnz <= k_L A); one more, empty,
        # row each, so that the products hold a zero at slot |U| (outside U) and k_L (L dropped)
        w_idx = torch.stack((self.w_rows, self.w_cols))
        w_val = self.w_vals.to(dt)
        w = torch.sparse_coo_tensor(w_idx, w_val, (k_l + 1, n_u), check_invariants=False).coalesce()
        w_t = torch.sparse_coo_tensor(w_idx.flip(0), w_val, (n_u + 1, k_l), check_invariants=False).coalesce()

        ch = max(c_l, c_r)
        step = max(1, self.chunk_elements // max(1, (k_r + n_u + k_l) * ch))
        out = vis.new_empty(n_vert, ch)
        for a in range(0, n_vert, step):
            b = min(n_vert, a + step)
            m = b - a
            v = vis[a:b]  # (m, 6R^2)
            ri = brdf.indices[a:b]  # (m, k)
            rv = brdf.values[a:b].to(dt)  # (m, k, C)
            col = torch.arange(m, device=v.device)[:, None]
            flat = ri.reshape(-1)
            slots = self.slots.index_select(0, flat).view(m, k_r, 4)
            lt = table.index_select(0, flat).view(m, k_r, -1)
            l_parent, l_p, c3 = lt[..., :c_l], lt[..., c_l : 2 * c_l], lt[..., 2 * c_l :]

            # case 2, pair (L, V), rho coarser: Y = W^T (L V) on U, then Y at the BRDF positions
            lv = v.index_select(1, self.light_indices).t()[..., None] * l_val[:, None, :]  # (k_L, m, C_L)
            y = torch.sparse.mm(w_t, lv.reshape(k_l, -1)).view(-1, c_l)  # (|U| + 1, m C_L)
            y_p = y.index_select(0, (slots[..., 0] * m + col).reshape(-1)).view(m, k_r, c_l)

            # case 2, pair (L, rho), V coarser: V_bar = W V_U at the kept lighting positions
            v_bar = torch.sparse.mm(w, v.index_select(1, self.union).t()).view(-1)  # (k_L + 1, m)
            v_bar_p = v_bar.index_select(0, (slots[..., 1] * m + col).reshape(-1)).view(m, k_r, 1)

            # case 2, pair (V, rho), L coarser, with case 1 folded into l_parent at phi
            v_p = v.gather(1, ri)[..., None]  # (m, k, 1)

            # case 3: the other two wavelet types s1, s2 of the BRDF position's node
            sib = slots[..., 2:]
            v_s = v.gather(1, sib.reshape(m, -1)).view(m, k_r, 2, 1)
            l_s = l_dense.index_select(0, sib.reshape(-1)).view(m, k_r, 2, c_l)
            mixed = (l_s[:, :, 0] * v_s[:, :, 1]).addcmul_(l_s[:, :, 1], v_s[:, :, 0])

            # the factor multiplying rho_p: (m, k, C_L)
            factor = torch.addcmul(y_p, v_p, l_parent).addcmul_(v_bar_p, l_p).addcmul_(c3, mixed)
            out[a:b] = (rv * factor).sum(1)
        return out

    def forward(self, visibility_coeffs: torch.Tensor, brdf: SparseHaar) -> torch.Tensor:
        """Alias of :meth:`product`."""
        return self.product(visibility_coeffs, brdf)
