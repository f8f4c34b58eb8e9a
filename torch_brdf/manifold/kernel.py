r"""The shifted squared-exponential kernel (the Cholesky with jitter lives in :mod:`torch_brdf.linalg`).

Soler, Subr and Nowrouzezahrai, "A Practical Non-Linear Parameterization of the BRDF
Manifold", INRIA RR-9069, 2017 (the seed), Eq. 5:

.. math:: c(x, x') = \mu\,\delta(x, x') + \exp(-\lVert x - x' \rVert^2 / 2\ell^2).

:math:`\delta(x, x')` is the Kronecker delta on the *identity* of two points: it is 1 on the
diagonal of the training Gram matrix ``K`` and, for a query point, only where the query is
bit-identical to a training latent (so ``k(x_i)`` is row ``i`` of ``K`` and the interpolant
reproduces ``z_i`` exactly, the seed's property 2).
"""

from __future__ import annotations

import torch

from ..errors import ShapeError, ValueRangeError
from ..linalg import JITTER_CAP, JITTER_FLOOR, JitterWarning, cholesky_jitter

__all__ = [
    "JITTER_CAP",
    "JITTER_FLOOR",
    "JitterWarning",
    "cholesky_jitter",
    "cross_kernel",
    "kernel_matrix",
    "se_kernel",
    "sq_dist",
]


def sq_dist(x1: torch.Tensor, x2: torch.Tensor) -> torch.Tensor:
    """Squared Euclidean distances, clamped at 0.

    Args:
        x1: (M, Q). x2: (N, Q).
    Returns:
        (M, N).
    """
    d = (x1 * x1).sum(-1)[:, None] + (x2 * x2).sum(-1)[None, :] - 2 * x1 @ x2.T
    return d.clamp_min(0)


def se_kernel(x1: torch.Tensor, x2: torch.Tensor, lengthscale: float = 1.0) -> torch.Tensor:
    r"""The squared-exponential part :math:`\exp(-\lVert x - x'\rVert^2 / 2\ell^2)` (Eq. 5 without :math:`\mu`).

    Args:
        x1: (M, Q). x2: (N, Q). lengthscale: :math:`\ell > 0`.
    Returns:
        (M, N) in the dtype of ``x1``.
    """
    if x1.ndim != 2 or x2.ndim != 2 or x1.shape[1] != x2.shape[1]:
        raise ShapeError(f"Expected x1 (M, Q) and x2 (N, Q) with the same Q; got {tuple(x1.shape)}, {tuple(x2.shape)}")
    if not lengthscale > 0:
        raise ValueRangeError(f"lengthscale must be > 0; got {lengthscale}")
    # differences instead of the expanded form: exact 0 on coincident points, smooth gradients;
    # accumulated per latent axis (a reduction over a last axis of size 2..5 is slow in torch)
    sq = None
    for k in range(x1.shape[1]):
        diff = x1[:, k, None] - x2[None, :, k]
        sq = diff * diff if sq is None else sq + diff * diff
    return torch.exp(sq * (-0.5 / lengthscale**2))


def kernel_matrix(x: torch.Tensor, lengthscale: float = 1.0, mu: float = 1e-6) -> torch.Tensor:
    r"""Training Gram matrix :math:`K_{ij} = c(x_i, x_j)` of Eq. 5: SE part plus :math:`\mu I`.

    Args:
        x: (N, Q) latents.
    Returns:
        (N, N).
    """
    k = se_kernel(x, x, lengthscale)
    return k + mu * torch.eye(x.shape[0], dtype=k.dtype)


def cross_kernel(xs: torch.Tensor, x: torch.Tensor, lengthscale: float = 1.0, mu: float = 1e-6) -> torch.Tensor:
    r"""Query-vs-training covariances :math:`k(x_*)_i = c(x_i, x_*)` (seed Eq. 3), batched.

    The :math:`\mu\,\delta` term is added where a query equals a training latent exactly.

    Args:
        xs: (M, Q) query latents. x: (N, Q) training latents.
    Returns:
        (M, N).
    """
    k = se_kernel(xs, x, lengthscale)
    if mu != 0:
        same = (xs[:, None, :] == x[None, :, :]).all(-1)
        k = k + mu * same.to(k.dtype)
    return k
