r"""A strong-Wolfe line search (Nocedal and Wright, *Numerical Optimization*, 2nd ed., Alg. 3.5-3.6).

Our own implementation for the GPLVM's L-BFGS (the strong-Wolfe function inside ``torch.optim.LBFGS`` is
private API and may change between versions). Along a descent direction, the search looks for a
step :math:`t > 0` of :math:`\phi(t) = f(x + t p)` with

* sufficient decrease: :math:`\phi(t) \le \phi(0) + c_1 t \phi'(0)`,
* strong curvature: :math:`|\phi'(t)| \le c_2 |\phi'(0)|`,

by expanding the step (cubic extrapolation, at most x10 per evaluation) until a bracket is found,
then shrinking the bracket (safeguarded cubic interpolation, bisection when the cubic has no
minimiser, lands next to an end or a value is not finite). A non-finite :math:`\phi(t)` (e.g. a
Cholesky that failed) counts as "too far" and shrinks the step.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..errors import ValueRangeError

__all__ = ["LineSearchResult", "strong_wolfe"]


@dataclass(frozen=True)
class LineSearchResult:
    """Outcome of :func:`strong_wolfe`.

    Attributes:
        step: accepted step length (0 when no step decreased :math:`\\phi` sufficiently).
        value, slope: :math:`\\phi(t)` and :math:`\\phi'(t)` at that step.
        payload: what ``phi`` returned with them (e.g. the full gradient), None at step 0.
        evaluations: calls of ``phi``. wolfe: both strong-Wolfe conditions hold at ``step``.
    """

    step: float
    value: float
    slope: float
    payload: Any
    evaluations: int
    wolfe: bool


def _cubic_min(t1: float, f1: float, d1: float, t2: float, f2: float, d2: float, lo: float, hi: float) -> float:
    """Minimiser of the cubic through (t1, f1, d1), (t2, f2, d2), clamped to [lo, hi]; midpoint if none."""
    if t1 == t2 or not all(math.isfinite(v) for v in (f1, d1, f2, d2)):
        return 0.5 * (lo + hi)
    e1 = d1 + d2 - 3.0 * (f1 - f2) / (t1 - t2)
    disc = e1 * e1 - d1 * d2
    if disc < 0:
        return 0.5 * (lo + hi)
    e2 = math.copysign(math.sqrt(disc), t2 - t1)
    den = d2 - d1 + 2.0 * e2
    if den == 0:
        return 0.5 * (lo + hi)
    t = t2 - (t2 - t1) * (d2 + e2 - e1) / den
    return min(max(t, lo), hi) if math.isfinite(t) else 0.5 * (lo + hi)


def strong_wolfe(
    phi: Callable[[float], tuple[float, float, Any]],
    value0: float,
    slope0: float,
    step: float = 1.0,
    *,
    c1: float = 1e-4,
    c2: float = 0.9,
    max_evaluations: int = 25,
    min_width: float = 1e-12,
) -> LineSearchResult:
    r"""Find a step satisfying the strong Wolfe conditions along a descent direction.

    Args:
        phi: ``phi(t) -> (value, slope, payload)``: :math:`\phi(t)`, :math:`\phi'(t)` and anything
            the caller wants back for the accepted step (e.g. the gradient vector).
        value0: :math:`\phi(0)`.
        slope0: :math:`\phi'(0) < 0`.
        step: first trial step (> 0).
        c1: the sufficient-decrease (Armijo) constant, 0 < c1 < c2.
        c2: the curvature constant, c1 < c2 < 1.
        max_evaluations: budget of ``phi`` calls.
        min_width: stop shrinking when the bracket is narrower than this (relative to its end).
    Returns:
        :class:`LineSearchResult`: the step satisfying both conditions, or else the step with the
        lowest value that satisfies sufficient decrease (``wolfe=False``), or step 0.
    Raises:
        ValueRangeError: ``slope0 >= 0`` (not a descent direction), bad constants or step.
    """
    if not (math.isfinite(value0) and math.isfinite(slope0) and slope0 < 0):
        raise ValueRangeError(f"strong_wolfe needs a finite value and a negative slope at 0; got {value0}, {slope0}")
    if not 0 < c1 < c2 < 1 or not (math.isfinite(step) and step > 0):
        raise ValueRangeError(f"need 0 < c1 < c2 < 1 and step > 0; got c1={c1}, c2={c2}, step={step}")
    evals = 0

    def armijo(t: float, f: float) -> bool:
        return math.isfinite(f) and f <= value0 + c1 * t * slope0

    def curvature(d: float) -> bool:
        return abs(d) <= -c2 * slope0

    prev = (0.0, value0, slope0, None)
    t = step
    lo = hi = None
    while evals < max_evaluations:
        f, d, pl = phi(t)
        evals += 1
        cur = (t, f, d, pl)
        if not armijo(t, f) or (evals > 1 and f >= prev[1]):
            lo, hi = prev, cur
            break
        if curvature(d):
            return LineSearchResult(t, f, d, pl, evals, True)
        if d >= 0:
            lo, hi = cur, prev
            break
        # still descending and sufficiently lower: extrapolate (at least 1.1x, at most 10x)
        t_next = _cubic_min(prev[0], prev[1], prev[2], t, f, d, 1.1 * t, 10.0 * t)
        prev, t = cur, t_next
    else:
        return LineSearchResult(prev[0], prev[1], prev[2], prev[3], evals, False)
    # zoom: lo satisfies sufficient decrease with the lowest value so far; the minimiser lies between
    while evals < max_evaluations:
        a, b = sorted((lo[0], hi[0]))
        width = b - a
        if width <= min_width * max(b, 1e-300):
            break
        t = _cubic_min(lo[0], lo[1], lo[2], hi[0], hi[1], hi[2], a, b)
        if min(t - a, b - t) < 0.1 * width:  # too close to an end: bisect
            t = 0.5 * (a + b)
        f, d, pl = phi(t)
        evals += 1
        cur = (t, f, d, pl)
        if not armijo(t, f) or f >= lo[1]:
            hi = cur
            continue
        if curvature(d):
            return LineSearchResult(t, f, d, pl, evals, True)
        if d * (hi[0] - lo[0]) >= 0:
            hi = lo
        lo = cur
    return LineSearchResult(lo[0], lo[1], lo[2], lo[3], evals, False)
