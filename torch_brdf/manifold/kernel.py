r"""The shifted squared-exponential kernel and a Cholesky factorisation with jitter escalation.

Soler, Subr and Nowrouzezahrai, "A Practical Non-Linear Parameterization of the BRDF
Manifold", INRIA RR-9069, 2017 (the seed), Eq. 5:

.. math:: c(x, x') = \mu\,\delta(x, x') + \exp(-\lVert x - x' \rVert^2 / 2\ell^2).

:math:`\delta(x, x')` is the Kronecker delta on the *identity* of two points: it is 1 on the
diagonal of the training Gram matrix ``K`` and, for a query point, only where the query is
bit-identical to a training latent (so ``k(x_i)`` is row ``i`` of ``K`` and the interpolant
reproduces ``z_i`` exactly, the seed's property 2).
"""

from __future__ import annotations

import warnings

import torch

from ..errors import NumericalError, ShapeError, ValueRangeError

#: default jitter floor and cap (absolute, added to the diagonal of a unit-amplitude kernel)
JITTER_FLOOR = 1e-10
JITTER_CAP = 1e-2


class JitterWarning(UserWarning):
    """A Cholesky factorisation needed extra diagonal jitter; the message gives its value."""


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


def cholesky_jitter(
    k: torch.Tensor,
    floor: float = JITTER_FLOOR,
    cap: float = JITTER_CAP,
    what: str = "K",
    warn: bool = True,
) -> tuple[torch.Tensor, float]:
    """Cholesky factor of a symmetric matrix, adding diagonal jitter x10 from ``floor`` to ``cap``.

    NaN/Inf entries are checked first (they are bad input, not an ill-conditioned matrix).
    Jitter 0 is tried first; then ``floor``, ``10 * floor``, ... up to ``cap``. When jitter was
    needed a :class:`JitterWarning` names the final value.

    Args:
        k: (N, N) symmetric matrix (factorised in float64 whatever its dtype).
        floor, cap: smallest and largest jitter (absolute).
        what: name for messages.
        warn: emit :class:`JitterWarning` when jitter > 0 was needed.
    Returns:
        (L, jitter): L (N, N) float64 lower triangular with L Lᵀ = k + jitter I; the jitter used.
    Raises:
        ValueRangeError: non-finite entries. NumericalError: still not positive definite at ``cap``.
    """
    if k.ndim != 2 or k.shape[0] != k.shape[1]:
        raise ShapeError(f"Expected {what} to be square (N, N); got {tuple(k.shape)}")
    if not bool(torch.isfinite(k).all()):
        raise ValueRangeError(f"{what} holds {int((~torch.isfinite(k)).sum())} non-finite entries (NaN/Inf)")
    if not (0 < floor <= cap):
        raise ValueRangeError(f"need 0 < floor <= cap; got floor={floor}, cap={cap}")
    k64 = k.to(torch.float64)
    eye = torch.eye(k.shape[0], dtype=torch.float64)
    jitter = 0.0
    while True:
        chol, info = torch.linalg.cholesky_ex(k64 + jitter * eye if jitter else k64)
        if int(info) == 0 and bool(torch.isfinite(chol).all()):
            if jitter and warn:
                warnings.warn(f"{what}: Cholesky needed diagonal jitter {jitter:.1e}", JitterWarning, stacklevel=2)
            return chol, jitter
        nxt = floor if jitter == 0 else jitter * 10
        if nxt > cap * (1 + 1e-12):
            raise NumericalError(
                f"{what} ({k.shape[0]}x{k.shape[0]}) is not positive definite even with diagonal jitter {jitter:.1e} "
                f"(the cap); the latents may coincide with mu = 0, or the lengthscale is far too large"
            )
        jitter = nxt
