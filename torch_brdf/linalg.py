r"""Dense linear algebra shared by the package: one Cholesky factorisation with jitter escalation.

Used by the GPLVM (:mod:`torch_brdf.manifold`: the kernel matrix :math:`K`, unit amplitude,
absolute jitter) and by the QP solvers of inverse design (:mod:`torch_brdf.inverse.qp`: the
J x J Newton and ADMM matrices, jitter relative to their largest diagonal entry).
"""

from __future__ import annotations

import warnings

import torch

from .errors import NumericalError, ShapeError, ValueRangeError

__all__ = ["JITTER_CAP", "JITTER_FLOOR", "JitterWarning", "cholesky_jitter"]

#: default jitter floor and cap (absolute, or relative to max |diag| with ``relative=True``)
JITTER_FLOOR = 1e-10
JITTER_CAP = 1e-2


class JitterWarning(UserWarning):
    """A Cholesky factorisation needed extra diagonal jitter; the message gives its value."""


def cholesky_jitter(
    k: torch.Tensor,
    floor: float = JITTER_FLOOR,
    cap: float = JITTER_CAP,
    what: str = "K",
    warn: bool = True,
    relative: bool = False,
) -> tuple[torch.Tensor, float]:
    """Cholesky factor of a symmetric matrix, adding diagonal jitter x10 from ``floor`` to ``cap``.

    NaN/Inf entries are checked first (they are bad input, not an ill-conditioned matrix).
    Jitter 0 is tried first; then ``floor``, ``10 * floor``, ... up to ``cap``. When jitter was
    needed and ``warn`` is set, a :class:`JitterWarning` names the final value.

    Args:
        k: (N, N) symmetric matrix (factorised in float64 whatever its dtype).
        floor: smallest and largest jitter.
        cap: as ``floor``.
        what: name for messages.
        warn: emit :class:`JitterWarning` when jitter > 0 was needed.
        relative: jitter in units of :math:`\\max_i |k_{ii}|` (1 when the diagonal is 0) instead of
            absolute units.
    Returns:
        (L, jitter): L (N, N) float64 lower triangular with L Lᵀ = k + jitter I; ``jitter`` the
        absolute value added (0 when none was needed).
    Raises:
        ShapeError: k not square. ValueRangeError: non-finite entries or bad floor/cap.
        NumericalError: still not positive definite at ``cap``.
    """
    if k.ndim != 2 or k.shape[0] != k.shape[1]:
        raise ShapeError(f"Expected {what} to be square (N, N); got {tuple(k.shape)}")
    if not bool(torch.isfinite(k).all()):
        raise ValueRangeError(f"{what} holds {int((~torch.isfinite(k)).sum())} non-finite entries (NaN/Inf)")
    if not (0 < floor <= cap):
        raise ValueRangeError(f"need 0 < floor <= cap; got floor={floor}, cap={cap}")
    k64 = k.to(torch.float64)
    unit = (float(k64.diagonal().abs().max()) or 1.0) if relative and k.shape[0] else 1.0
    eye = torch.eye(k.shape[0], dtype=torch.float64)
    step = 0.0
    while True:
        chol, info = torch.linalg.cholesky_ex(k64 + (step * unit) * eye if step else k64)
        if int(info) == 0 and bool(torch.isfinite(chol).all()):
            if step and warn:
                warnings.warn(f"{what}: Cholesky needed diagonal jitter {step * unit:.1e}", JitterWarning, stacklevel=2)
            return chol, step * unit
        nxt = floor if step == 0 else step * 10
        if nxt > cap * (1 + 1e-12):
            raise NumericalError(
                f"{what} ({k.shape[0]}x{k.shape[0]}) is not positive definite even with diagonal jitter "
                f"{step * unit:.1e} (the cap{' relative to max diag' if relative else ''})"
            )
        step = nxt
