r"""A small dense convex QP solver in torch (float64) for the normal equations of the fit.

Problem (the inverse-design solve, Iwasaki Eq. 17-19, after forming the normal equations):

.. math:: \min_c\ \tfrac12 c^\top H c - f^\top c \quad\text{s.t.}\quad c \ge 0,\ \ G c \le h,

with :math:`H = T^\top W T` (J x J, positive *semi*-definite: SRBF lobes that no pixel sees
give zero rows and columns), :math:`G` the N_l x J energy rows and :math:`h = 1 - \rho_d`.

Method: Mehrotra's predictor-corrector primal-dual interior point method (Nocedal & Wright,
*Numerical Optimization*, 2nd ed., Alg. 16.4), written on the J x J normal equations.
Why this and not projected gradient or ADMM: (i) the answer must satisfy every constraint
to 1e-8 and match ProxQP/Clarabel's objective to 1e-6, which first-order methods reach only
after thousands of iterations on these ill-conditioned problems (the Gram matrix of
overlapping SRBF lobes has a condition number of 1e8 and more, and is singular when lobes are
unseen); (ii) an interior point method converges in 15-30 iterations almost independently of
conditioning, and each iteration costs one Cholesky factorisation of the J x J matrix
:math:`H + D_1 + G^\top D_2 G` (the barrier terms make it positive definite even when H is
singular), reused for the predictor and the corrector; (iii) there is no active-set
combinatorics with 339 inequality rows. The small size (J = 147) makes a dense Cholesky
cheap (~0.2 ms). The problem is scaled so that :math:`\|H\|_\infty = 1` and the constraint
rows have unit norm before iterating (the solution is unchanged).

At the end the iterate is clipped to :math:`c \ge 0` (it is interior up to rounding), and the
report gives the iterations, the objective and the largest constraint violation.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass

import torch

from ..errors import InfeasibleError, NumericalError, ShapeError, ValueRangeError

__all__ = ["QPResult", "solve_qp"]


@dataclass(frozen=True)
class QPResult:
    """Solution of :func:`solve_qp`.

    Attributes:
        x: (J,) float64 minimiser.
        bound_dual: (J,) multipliers of :math:`x \\ge 0` (>= 0).
        row_dual: (M,) multipliers of :math:`Gx \\le h` (>= 0).
        iterations: interior point iterations.
        objective: :math:`\\frac12 x^\\top H x - f^\\top x` at ``x``.
        violation: :math:`\\max(0, \\max_l (Gx - h)_l, \\max_j -x_j)`.
        converged: the stopping tolerances were met.
    """

    x: torch.Tensor
    bound_dual: torch.Tensor
    row_dual: torch.Tensor
    iterations: int
    objective: float
    violation: float
    converged: bool


def _chol(K: torch.Tensor) -> torch.Tensor:
    L, info = torch.linalg.cholesky_ex(K)
    if int(info) == 0:
        return L
    scale = float(K.diagonal().abs().max()) or 1.0
    eye = torch.eye(K.shape[0], dtype=K.dtype)
    for jitter in (1e-14, 1e-12, 1e-10, 1e-8):
        L, info = torch.linalg.cholesky_ex(K + jitter * scale * eye)
        if int(info) == 0:
            return L
    raise NumericalError("interior point: the J x J Newton matrix is not positive definite even with jitter 1e-8")


@contextmanager
def _single_thread():
    """Run small dense kernels on one intra-op thread: on a shared 2-core machine a 147 x 192
    matrix-vector product takes ~0.1 ms on one thread and up to ~4 ms on two (thread hand-off
    under load; cf. OPENBLAS_NUM_THREADS=1 in ../shared/FACTS.md)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def solve_qp(H, f, G, h, tol: float = 1e-11, max_iter: int = 100) -> QPResult:
    r"""Solve :math:`\min \frac12 x^\top H x - f^\top x` s.t. :math:`x \ge 0,\ Gx \le h` (see the module).

    Args:
        H: (J, J) symmetric positive semi-definite.
        f: (J,).
        G: (M, J) constraint rows (M may be 0).
        h: (M,) right-hand sides.
        tol: relative tolerance on the residuals and the duality measure.
        max_iter: iteration limit.
    Returns:
        :class:`QPResult` (float64).
    Raises:
        InfeasibleError: the constraints admit no point (detected up front for ``h < 0`` with
            non-negative rows, else from diverging iterates).
        NumericalError: no convergence within ``max_iter`` iterations.
    """
    with _single_thread():
        return _solve_qp(H, f, G, h, tol, max_iter)


def _solve_qp(H, f, G, h, tol: float, max_iter: int) -> QPResult:
    H = torch.as_tensor(H, dtype=torch.float64)
    f = torch.as_tensor(f, dtype=torch.float64)
    G = torch.as_tensor(G, dtype=torch.float64)
    h = torch.as_tensor(h, dtype=torch.float64)
    J = H.shape[0]
    if H.shape != (J, J) or f.shape != (J,) or G.ndim != 2 or G.shape[1] != J or h.shape != (G.shape[0],):
        raise ShapeError(
            f"Expected H (J, J), f (J,), G (M, J), h (M,); got {tuple(H.shape)}, {tuple(f.shape)}, "
            f"{tuple(G.shape)}, {tuple(h.shape)}"
        )
    for name, t in (("H", H), ("f", f), ("G", G), ("h", h)):
        if not bool(torch.isfinite(t).all()):
            raise ValueRangeError(f"QP data {name} holds NaN or Inf")
    if bool((G >= 0).all()) and bool((h < 0).any()):
        raise InfeasibleError(f"no x >= 0 satisfies G x <= h: G is non-negative and min(h) = {float(h.min()):.3g} < 0")
    # scaling: objective to unit size, constraint rows to unit norm
    s_obj = max(float(H.abs().max()), float(f.abs().max()), 1e-300)
    Hs, fs = H / s_obj, f / s_obj
    rn = G.norm(dim=1).clamp_min(1e-300)
    Gs, hs = G / rn[:, None], h / rn
    M = G.shape[0]
    m = J + M
    x = torch.zeros(J, dtype=torch.float64)
    s = torch.ones(m, dtype=torch.float64)
    z = torch.ones(m, dtype=torch.float64)
    b = torch.cat((torch.zeros(J, dtype=torch.float64), hs))

    def A(v):  # rows: -x >= ... i.e. A = [-I; G]
        return torch.cat((-v, Gs @ v))

    GsT = Gs.T.contiguous()

    def At(y):
        return torch.addmv(-y[:J], GsT, y[J:])

    norm_b = 1 + float(b.abs().max())
    norm_f = 1 + float(fs.abs().max())
    converged, it = False, 0
    best, best_score, stall = None, math.inf, 0
    for it in range(1, max_iter + 1):
        rd = Hs @ x - fs + At(z)
        rp = A(x) + s - b
        mu = float(s @ z) / m
        obj = 0.5 * float(x @ (Hs @ x)) - float(fs @ x)
        e_d = float(rd.abs().max()) / norm_f
        e_p = float(rp.abs().max()) / norm_b
        e_g = mu * m / (1 + abs(obj))
        # the dual residual stalls near 1e-11 on singular H (rounding in the J x J solve): it is
        # held to 100 tol, primal feasibility and the duality gap to tol
        score = max(e_d / 100, e_p, e_g)
        if score < best_score:
            best, best_score, stall = (x, s, z, it - 1), score, 0
        else:
            stall += 1
        if score <= tol:
            converged = True
            break
        if stall >= 5 and best_score <= 100 * tol:  # rounding floor reached: keep the best iterate
            converged = True
            break
        if float(x.abs().max()) > 1e12 / max(tol, 1e-300):
            raise InfeasibleError("interior point iterates diverge: the constraints admit no point")
        d = z / s
        K = Hs + torch.diag(d[:J]) + GsT @ (d[J:, None] * Gs)
        L = _chol(K)

        def newton(rc, rd=rd, rp=rp, d=d, L=L, s=s, z=z):
            rhs = -rd - At(d * rp - rc / s)
            dx = torch.cholesky_solve(rhs[:, None], L)[:, 0]
            ds = -rp - A(dx)
            dz = -(rc + z * ds) / s
            return dx, ds, dz

        def step(v, dv):  # largest step in (0, 1] keeping v + step * dv >= 0
            ratio = torch.where(dv < 0, v / -dv.clamp_max(-1e-300), 1.0)
            return min(1.0, float(ratio.min()))

        dx, ds, dz = newton(s * z)
        a_aff = min(step(s, ds), step(z, dz))
        mu_aff = float((s + a_aff * ds) @ (z + a_aff * dz)) / m
        sigma = (mu_aff / max(mu, 1e-300)) ** 3
        dx, ds, dz = newton(s * z + ds * dz - sigma * mu)
        alpha = min(1.0, 0.995 * min(step(s, ds), step(z, dz)))
        x, s, z = x + alpha * dx, s + alpha * ds, z + alpha * dz
    if not converged:
        rp = A(x) + s - b
        if float(rp.abs().max()) > 1e-6 * norm_b:
            raise InfeasibleError(
                f"interior point: constraints still violated by {float(rp.abs().max()):.3g} after {max_iter} "
                "iterations; the constraints appear infeasible"
            )
        raise NumericalError(f"interior point did not converge in {max_iter} iterations (mu = {mu:.3g})")
    x, s, z, it = best
    x = x.clamp_min(0)  # interior up to rounding
    viol = max(0.0, float((G @ x - h).max()) if M else 0.0)
    objective = 0.5 * float(x @ (H @ x)) - float(f @ x)
    return QPResult(x, z[:J] * s_obj, z[J:] * s_obj / rn, it, objective, viol, converged)
