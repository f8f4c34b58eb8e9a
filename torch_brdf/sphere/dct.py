r"""The 2-D DCT over square texel blocks, and its subsampled low-frequency projections.

Inger et al. (Sec. 4.1, Eq. 4) approximate a smooth function over an ``S x S`` block by
its first ``l x l`` DCT coefficients, found from only ``l x l`` samples. We use the
orthonormal DCT-II basis

.. math:: b_u(x) = c_u \cos\frac{\pi (2x + 1) u}{2S}, \qquad c_0 = \sqrt{1/S},\ c_{u>0} = \sqrt{2/S},

(the printed Eq. 4 has lost the half-sample shift and the normalisation), and
:math:`B_{pq}(r, c) = b_p(r)\, b_q(c)` on texel ``t = r S + c``. Sampling at the centres of an
``l x l`` grid of sub-intervals, :math:`x_i = (2i + 1) S / (2l) - 1/2` (texel units), makes
:math:`b_u(x_i) = c_u \cos(\pi u (2i + 1) / (2l))`: the ``l``-point DCT-II, so the ``l^2``
equations of Eq. 4 have a well-conditioned inverse, precomputed once per ``l``. A function
that is constant over the block is recovered exactly by ``l = 1``, a bilinear one by ``l = 2``
up to its DCT truncation, and so on.

Coefficient ``k = p * L + q`` of the first ``L x L = 16`` (``L = 4``) low frequencies;
``l x l`` projections use the subset ``p, q < l``.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch

from ..errors import ValueRangeError

__all__ = ["LOW", "dct_basis", "low_indices", "sample_positions", "subsampled_inverse"]

#: side of the low-frequency square kept for the lighting (16 coefficients)
LOW = 4


def _b(u: torch.Tensor, x: torch.Tensor, size: int) -> torch.Tensor:
    c = torch.where(u == 0, math.sqrt(1.0 / size), math.sqrt(2.0 / size)).to(torch.float64)
    return c * torch.cos(math.pi * (2 * x + 1) * u / (2 * size))


@lru_cache(maxsize=8)
def _basis(size: int, side: int) -> torch.Tensor:
    u = torch.arange(side, dtype=torch.float64)
    x = torch.arange(size, dtype=torch.float64)
    b = _b(u[:, None], x[None, :], size)  # (side, size)
    return torch.einsum("pr,qc->pqrc", b, b).reshape(side * side, size * size)


def dct_basis(size: int = 16, side: int | None = None, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Orthonormal 2-D DCT-II basis functions of the lowest ``side x side`` frequencies.

    Args:
        size: S, block side in texels.
        side: frequencies per axis kept (default ``size``: the full, square basis).
    Returns:
        (side^2, S^2) rows ``B_k`` over texels ``t = r S + c``; with ``side == size`` it is
        orthogonal: ``B @ B.T == I``.
    """
    side = size if side is None else int(side)
    if not 1 <= side <= size:
        raise ValueRangeError(f"DCT side must be in [1, {size}]; got {side}")
    return _basis(int(size), side).to(dtype)


def sample_positions(l: int, size: int = 16) -> torch.Tensor:
    """In-block sample coordinates (texel units) of the ``l``-point grid: (l,) float64."""
    if l < 1 or l > size:
        raise ValueRangeError(f"samples per side must be in [1, {size}]; got {l}")
    return (2 * torch.arange(l, dtype=torch.float64) + 1) * size / (2 * l) - 0.5


def low_indices(l: int, side: int = LOW) -> torch.Tensor:
    """Indices (l^2,) of the ``p, q < l`` coefficients among the first ``side^2``."""
    p = torch.arange(l)
    return (p[:, None] * side + p[None, :]).reshape(-1)


@lru_cache(maxsize=8)
def _inverse(l: int, size: int) -> torch.Tensor:
    x = sample_positions(l, size)
    u = torch.arange(l, dtype=torch.float64)
    b = _b(u[None, :], x[:, None], size)  # (l samples, l freqs)
    m = torch.einsum("ip,jq->ijpq", b, b).reshape(l * l, l * l)  # sample (i,j) x coefficient (p,q)
    return torch.linalg.inv(m)


def subsampled_inverse(l: int, size: int = 16, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """The precomputed inverse of Eq. 4: (l^2 coefficients, l^2 samples).

    ``A = subsampled_inverse(l) @ f(samples)`` gives the coefficients ``A_pq`` (``p, q < l``,
    index ``p * l + q``) of the DCT interpolant through the ``l x l`` samples taken at
    :func:`sample_positions` (row-major, rows first).
    """
    return _inverse(int(l), int(size)).to(dtype)
