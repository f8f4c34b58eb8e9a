r"""A small dense convex QP solver in torch (float64) for the normal equations of the fit.

Problem (the inverse-design solve, Iwasaki Eq. 17-19, after forming the normal equations):

.. math:: \min_c\ \tfrac12 c^\top H c - f^\top c \quad\text{s.t.}\quad c \ge 0,\ \ G c \le h,

with :math:`H = T^\top W T` (J x J, positive *semi*-definite: SRBF lobes that no pixel sees
give zero rows and columns), :math:`G` the N_l x J energy rows and :math:`h = 1 - \rho_d`.

Two methods, both selectable (``solve_qp(..., method=...)``, ``fit(..., method=...)``):

``"interior_point"`` (the default): Mehrotra's predictor-corrector primal-dual interior point
method (Nocedal & Wright, *Numerical Optimization*, 2nd ed., Alg. 16.4) on the J x J normal
equations: 15-30 iterations almost independently of conditioning (the Gram matrix of
overlapping SRBF lobes has a condition number of 1e8 and more, and is singular when lobes are
unseen), one Cholesky of :math:`H + D_1 + G^\top D_2 G` per iteration
(:func:`torch_brdf.linalg.cholesky_jitter`; the barrier terms make it positive definite even
when H is singular), reused for predictor and corrector. The problem is scaled so that
:math:`\|H\|_\infty = 1` and the constraint rows have unit norm. The interior iterate is
optimal to ~1e-11 relative to the objective, which on a zero-residual target (optimum ~0)
leaves ~1e-11 of the target energy; so it is then *polished*: the active set it identifies
(:math:`x_j < z_j`, slack < multiplier) is solved exactly as for ADMM below, and the polished
point is kept when its KKT conditions verify, it is feasible to 1e-12 and not worse.

``"admm"``: the fit "as a torch optimisation with projected constraints on the small normal
equations" ("the constrained inverse fits are autograd optimisations with projected
constraints"), written as OSQP's ADMM (Stellato et al., "OSQP: an
operator splitting solver for quadratic programs", Math. Prog. Comp. 12, 2020). The
constraints are stacked as :math:`l \le Ax \le u` with :math:`A = [G; I]`,
:math:`l = [-\infty; 0]`, :math:`u = [h; +\infty]`. Each iteration solves
:math:`(H + \sigma I + \rho A^\top A)\tilde x = \sigma x - q + A^\top(\rho z - y)` with a cached
Cholesky factor (refactored only when :math:`\rho` changes), relaxes with
:math:`\alpha = 1.6`, and the z-update is the *exact projection* onto the box :math:`[l, u]`
(a clamp): that is the projected constraint. :math:`\rho` adapts to the ratio of the relative
primal and dual residuals every 100 iterations (OSQP Sec. 5.2); the data are Ruiz-equilibrated
(Sec. 5.1) after normalising rows to unit norm, x to units of :math:`\max h` and
:math:`\|H\|_{max}` to 1. It stops on OSQP's residual criteria (:math:`\epsilon_{abs} =
\epsilon_{rel} = 10^{-9}`) or earlier once *polishing* (Sec. 4) succeeds: the active set is
guessed from z and y, the equality-constrained QP on it is solved through its reduced KKT
system (regularised by 1e-10, 5 steps of iterative refinement; bounds are eliminated so active
:math:`c_j` are exactly 0), the guess is repaired when a multiplier has the wrong sign or a
constraint is violated, and the result is accepted only if it satisfies all KKT conditions, is
feasible to 1e-10 (absolute and relative to :math:`\max h`) and is not worse in objective than
the ADMM iterate (within its tolerance). Polishing is tried whenever the relative residual
falls by another decade below 1e-3, and every 200 iterations. Primal infeasibility is detected
from OSQP's certificate on :math:`\delta y` (Sec. 3.4). ADMM alone does not converge in 4000
iterations on some singular problems (painted pixels only, rank 76 of 147); there it falls back
to the interior point method (``fallback=True`` in the result; ``fallback=False`` raises
:class:`~torch_brdf.errors.NumericalError` instead).

Why the interior point method is the default: on the tests' set of fit QPs
(``tests/inverse/qp_set.py``: partial masks, zero-residual targets, rank-deficient H, an
out-of-family target, rho_d -> 1) it solves every problem to the reference optimum, in a
fixed ~15-25 iterations; ADMM needs 50-3600 iterations and fails on two of them without the
fallback. Timings and success counts: ``benchmarks/inverse.py`` (and the inverse-design guide).

Before the interior point method, the default first tries an *active-set* solve
(:func:`_active_set_first`): the polishing step below started from every bound active (x = 0),
freeing the most negative multiplier per pass as Lawson and Hanson's NNLS does (and adding the
violated bounds and rows when a pass leaves them), for at most 60 passes. Its point is accepted
only when it verifies every KKT condition of the normalised problem (feasible to 1e-10,
stationary to 1e-9, multipliers >= 0, complementary), so a convex QP's answer is the optimum
either way; when the passes run out, the interior point method runs as before. A solution with
a few dozen non-zero coefficients is then a few dozen small linear solves (of the free
coefficients only) instead of 15-30 Newton steps on all of them; ``benchmarks/inverse.py``
times both against ProxQP on an easy set (targets the SRBF family reaches) and a hard set.

When :math:`f \le 0` and :math:`h \ge 0`, :math:`x = 0` is an exact KKT point and is returned
without iterating (both methods). The report gives the iterations, the objective and the
largest constraint violation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from ..errors import InfeasibleError, NumericalError, ShapeError, ValueRangeError
from ..linalg import cholesky_jitter
from ..parallel.threads import single_thread

__all__ = ["QPResult", "solve_qp"]


@dataclass(frozen=True)
class QPResult:
    """Solution of :func:`solve_qp`.

    Attributes:
        x: (J,) float64 minimiser.
        bound_dual: (J,) multipliers of :math:`x \\ge 0` (>= 0).
        row_dual: (M,) multipliers of :math:`Gx \\le h` (>= 0).
        iterations: interior point or ADMM iterations.
        objective: :math:`\\frac12 x^\\top H x - f^\\top x` at ``x``.
        violation: :math:`\\max(0, \\max_l (Gx - h)_l, \\max_j -x_j)`.
        converged: the stopping tolerances were met (ADMM: the residual criteria, or a
            polished point that satisfies the KKT conditions).
        method: ``"interior_point"`` or ``"admm"``.
        polished: the returned point is the polished one (exact active-set solve, KKT
            conditions verified).
        fallback: ADMM was asked for but failed; ``x`` is the interior point solution.
    """

    x: torch.Tensor
    bound_dual: torch.Tensor
    row_dual: torch.Tensor
    iterations: int
    objective: float
    violation: float
    converged: bool
    method: str = "interior_point"
    polished: bool = False
    fallback: bool = False


def _chol(K: torch.Tensor) -> torch.Tensor:
    """Cholesky of a J x J Newton/ADMM matrix, jitter 1e-14 .. 1e-8 of its largest diagonal entry."""
    return cholesky_jitter(K, 1e-14, 1e-8, what="QP: the J x J Newton matrix", warn=False, relative=True)[0]


def solve_qp(
    H,
    f,
    G,
    h,
    tol: float | None = None,
    max_iter: int | None = None,
    method: str = "interior_point",
    warm_start: QPResult | None = None,
    polish: bool = True,
    early_polish: bool = True,
    fallback: bool = True,
) -> QPResult:
    r"""Solve :math:`\min \frac12 x^\top H x - f^\top x` s.t. :math:`x \ge 0,\ Gx \le h` (see the module).

    Args:
        H: (J, J) symmetric positive semi-definite.
        f: (J,).
        G: (M, J) constraint rows (M may be 0).
        h: (M,) right-hand sides.
        tol: relative tolerance: residuals and duality measure for the interior point method
            (default 1e-11), OSQP's eps_abs = eps_rel for ADMM (default 1e-9).
        max_iter: iteration limit (default 100 for the interior point method, 4000 for ADMM).
        method: ``"interior_point"`` (Mehrotra, then active-set polishing; the default) or
            ``"admm"`` (OSQP-style ADMM with projected constraints and polishing, the design
            card's method). See the module for the comparison.
        warm_start: ADMM only: a previous :class:`QPResult` whose x and multipliers start the
            iteration.
        polish: polish the final point on its active set (default True; both methods).
        early_polish: ADMM only: try polishing before the residual criteria are met and stop
            when it succeeds (default True; False runs ADMM to ``tol`` first).
        fallback: ADMM only: when ADMM neither converges nor polishes, return the interior point
            solution (``method == "interior_point"``, ``fallback == True`` in the result) instead
            of raising :class:`NumericalError` (default True).
    Returns:
        :class:`QPResult` (float64); ``method``, ``polished`` and ``fallback`` say how it was obtained.
    Raises:
        ValueRangeError: unknown ``method``, or NaN/Inf in the data.
        ShapeError: inconsistent shapes.
        InfeasibleError: the constraints admit no point (detected up front for ``h < 0`` with
            non-negative rows, else from diverging iterates or ADMM's infeasibility certificate).
        NumericalError: no convergence within ``max_iter`` iterations (ADMM with
            ``fallback=False``: and polishing failed).
    """
    if method not in ("interior_point", "admm"):
        raise ValueRangeError(f"method must be 'interior_point' or 'admm'; got {method!r}")
    with single_thread():
        H, f, G, h = _prepare(H, f, G, h)
        if bool((f <= 0).all()) and (G.shape[0] == 0 or bool((h >= 0).all())):
            # x = 0 is feasible and the gradient -f >= 0 there: an exact KKT point (bound
            # multipliers -f, row multipliers 0), returned without iterating
            zero = torch.zeros_like(f)
            return QPResult(zero, -f, torch.zeros_like(h), 0, 0.0, 0.0, True, method, False)
        if method == "admm":
            eps, n = 1e-9 if tol is None else tol, max_iter or 4000
            try:
                return _solve_admm(H, f, G, h, eps, n, warm_start, polish, early_polish)
            except NumericalError:
                if not fallback:
                    raise
            r = _interior_point(H, f, G, h, 1e-11, 100)  # the default method's answer
            return replace(r, fallback=True)
        if polish:
            first = _active_set_first(H, f, G, h)
            if first is not None:
                return first
        return _interior_point(H, f, G, h, 1e-11 if tol is None else tol, max_iter or 100, polish)


def _scaled(H, f, G, h):
    """The normalised problem of both methods' polishing: objective to unit size, rows to unit
    norm, x in units of max h. Returns (Hp, fp, Gs, hp, s_obj, rn, s_x)."""
    s_obj = max(float(H.abs().max()), float(f.abs().max()), 1e-300)
    rn = G.norm(dim=1).clamp_min(1e-300)
    Gs, hs = G / rn[:, None], h / rn
    s_x = float(hs.max()) if G.shape[0] and float(hs.max()) > 0 else 1.0
    return H / s_obj * (s_x * s_x), f / s_obj * s_x, Gs, hs / s_x, s_obj, rn, s_x


#: how negative a bound multiplier of the active-set first try may be (normalised units): the
#: passes accept -1e-11, which on a zero-residual target leaves 1e-10 of the optimum on the table
DUAL_TOL = 1e-13


def _refined(Hp, fp, Gs, hp, x, mu, y):
    """The point of :func:`_polish` solved once more on its active set without the 1e-10
    regularisation (minimum-norm least squares of the KKT system: H is singular where lobes are
    unseen), so that a zero-residual optimum is met to rounding rather than to 1e-10; the
    polished point when the refined one is not better or not feasible."""
    fi, ri = (x > 0).nonzero()[:, 0], (y > 0).nonzero()[:, 0]
    nf, nr = fi.numel(), ri.numel()
    if nf == 0:
        return x, mu, y
    K = torch.zeros(nf + nr, nf + nr, dtype=torch.float64)
    K[:nf, :nf] = Hp[fi][:, fi]
    K[:nf, nf:] = Gs[ri][:, fi].T
    K[nf:, :nf] = Gs[ri][:, fi]
    v = torch.linalg.lstsq(K, torch.cat((fp[fi], hp[ri]))[:, None], driver="gelsd").solution[:, 0]
    x2, y2 = torch.zeros_like(x), torch.zeros_like(y)
    x2[fi], y2[ri] = v[:nf], v[nf:]
    if bool((x2 < 0).any()) or bool((y2 < 0).any()):
        return x, mu, y
    mu2 = (Hp @ x2 - fp + Gs.T @ y2).clamp_min(0) * (x2 == 0)
    obj = lambda z: 0.5 * float(z @ (Hp @ z)) - float(fp @ z)  # noqa: E731
    if obj(x2) > obj(x) or (Gs.shape[0] and float((Gs @ x2 - hp).max()) > 1e-12):
        return x, mu, y
    return x2, mu2, y2


def _active_set_first(H, f, G, h, passes: int = 60) -> QPResult | None:
    """The active-set first try of the default method (see the module): :func:`_polish` from
    every bound active (x = 0), freeing one coefficient per pass as Lawson and Hanson's NNLS
    does, so that a pass solves a system of the free coefficients only; the verified KKT point,
    or None after ``passes`` (then the interior point method runs)."""
    Hp, fp, Gs, hp, s_obj, rn, s_x = _scaled(H, f, G, h)
    J, M = H.shape[0], G.shape[0]
    pol = _polish(Hp, fp, Gs, hp, torch.ones(J, dtype=torch.bool), torch.zeros(M, dtype=torch.bool), passes)
    if pol is None:
        return None
    xs, mu, y = _refined(Hp, fp, Gs, hp, *pol)
    # every KKT condition again, on every row (the passes check the rows outside their active
    # set; an inconsistent active set, e.g. of infeasible rows, would pass unseen otherwise)
    slack = Gs @ xs - hp
    raw = Hp @ xs - fp + Gs.T @ y  # the bound multipliers where x = 0: none may be negative
    grad = raw - mu
    tol = 1e-10
    if (
        float(torch.where(xs == 0, raw, torch.zeros_like(raw)).min()) < -DUAL_TOL
        or (M and float(y.min()) < 0)
        or (M and float(slack.max()) > tol)
        or (M and float((y * slack.clamp_max(0)).abs().max()) > tol)
        or float((mu * xs).abs().max()) > tol
        or float(grad.abs().max()) > 1e-9
    ):
        return None
    x, zb, zr = xs * s_x, mu / s_x, y / s_x
    viol = max(0.0, float((G @ x - h).max()) if M else 0.0)
    objective = 0.5 * float(x @ (H @ x)) - float(f @ x)
    return QPResult(x, zb * s_obj, zr * s_obj / rn, 0, objective, viol, True, "interior_point", True)


def _interior_point(H, f, G, h, tol: float, max_iter: int, polish: bool = True) -> QPResult:
    """The interior point method, polished; when polishing fails, once more to ``tol / 100``.

    The active set read off a ``tol``-accurate iterate can be wrong in a few near-degenerate
    entries (seen on a zero-residual, half-masked target: the unpolished point was 2.5e-6 of
    the reference gap above the optimum); the tighter iterate identifies it. If that run does
    not converge or polish either, the first result is kept.
    """
    r = _solve_qp(H, f, G, h, tol, max_iter, polish)
    if not polish or r.polished:
        return r
    try:
        r2 = _solve_qp(H, f, G, h, tol / 100, max_iter, polish)
    except NumericalError:
        return r
    return replace(r2, iterations=r.iterations + r2.iterations) if r2.polished or r2.objective < r.objective else r


def _prepare(H, f, G, h):
    """Validate and convert the QP data; raise InfeasibleError for the obvious infeasible case."""
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
    return H, f, G, h


def _solve_qp(H, f, G, h, tol: float, max_iter: int, polish: bool = True) -> QPResult:
    H, f, G, h = _prepare(H, f, G, h)
    J = H.shape[0]
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
    zb, zr, polished = z[:J], z[J:], False
    if polish:
        # the interior iterate is optimal to ~tol relative to |objective|; on zero-residual targets
        # that leaves ~1e-11 of the target energy: the active set it identifies (x_j < z_j, slack <
        # multiplier) is solved exactly (in units of max h, as for ADMM, so that h ~ 1e-9 is not
        # below the polishing tolerances) and kept when its KKT conditions verify and it is not worse
        s_x = float(hs.max()) if M and float(hs.max()) > 0 else 1.0
        Hp, fp, hp = Hs * (s_x * s_x), fs * s_x, hs / s_x
        pol = _polish(Hp, fp, Gs, hp, x < z[:J], s[J:] < z[J:])
        if pol is not None:
            xi = x / s_x
            obj_i = 0.5 * float(xi @ (Hp @ xi)) - float(fp @ xi)
            obj_p = 0.5 * float(pol[0] @ (Hp @ pol[0])) - float(fp @ pol[0])
            viol_p = max(0.0, float((Gs @ pol[0] - hp).max()) if M else 0.0)
            if viol_p <= 1e-12 and obj_p <= obj_i + 1e-12 * (1 + abs(obj_i)):
                x, zb, zr, polished = pol[0] * s_x, pol[1] / s_x, pol[2] / s_x, True
    viol = max(0.0, float((G @ x - h).max()) if M else 0.0)
    objective = 0.5 * float(x @ (H @ x)) - float(f @ x)
    return QPResult(x, zb * s_obj, zr * s_obj / rn, it, objective, viol, converged, "interior_point", polished)


# ---------------------------------------------------------------------------------------------
# ADMM (OSQP, Stellato et al. 2020) with exact projection and polishing
# ---------------------------------------------------------------------------------------------


def _ruiz(P, q, A, iters: int = 10):
    """Modified Ruiz equilibration of OSQP (Stellato et al. 2020, Sec. 5.1): returns D (J,), E (m,)
    and the cost scale c with :math:`\\bar P = c D P D`, :math:`\\bar q = c D q`, :math:`\\bar A = E A D`."""
    J, m = P.shape[0], A.shape[0]
    D = torch.ones(J, dtype=torch.float64)
    E = torch.ones(m, dtype=torch.float64)
    c = 1.0
    Pb, qb, Ab = P.clone(), q.clone(), A.clone()

    def limit(v):
        return torch.where(v < 1e-4, torch.ones_like(v), v).clamp_max(1e4)

    for _ in range(iters):
        col = torch.maximum(Pb.abs().amax(0), Ab.abs().amax(0)) if m else Pb.abs().amax(0)
        dx = 1 / limit(col).sqrt()
        dz = 1 / limit(Ab.abs().amax(1)).sqrt() if m else E
        Pb = dx[:, None] * Pb * dx[None]
        Ab = dz[:, None] * Ab * dx[None]
        qb = dx * qb
        D, E = D * dx, E * dz
        gamma = 1 / max(float(limit(Pb.abs().amax(0)).mean()), float(limit(qb.abs().max()[None])[0]))
        gamma = min(max(gamma, 1e-4), 1e4)
        Pb, qb, c = Pb * gamma, qb * gamma, c * gamma
    return D, E, c, Pb, qb, Ab


def _polish(Hs, fs, Gs, hs, bound_active, row_active, passes: int = 25):
    r"""OSQP's solution polishing (Stellato et al. 2020, Sec. 4): solve the equality-constrained QP on
    the guessed active set (bounds ``x_B = 0``, rows ``G_R x = h_R``) exactly through the reduced KKT
    system (regularised by 1e-10 with iterative refinement), then -- beyond OSQP -- repair the guess
    (add the violated constraints; when none, release the one with the most negative multiplier;
    changing everything at once cycles) until the point satisfies all KKT conditions of the
    normalised problem.

    Returns:
        ``(x, mu, y)`` (bound and row multipliers, >= 0) or None when no pass verifies.
    """
    J = Hs.shape[0]
    tol_p, tol_d = 1e-12, 1e-11
    B, R = bound_active.clone(), row_active.clone()
    for _ in range(passes):
        F = ~B
        fi, ri = F.nonzero()[:, 0], R.nonzero()[:, 0]
        nf, nr = fi.numel(), ri.numel()
        GRF = Gs[ri][:, fi]
        K0 = torch.zeros(nf + nr, nf + nr, dtype=torch.float64)
        K0[:nf, :nf] = Hs[fi][:, fi]
        K0[:nf, nf:] = GRF.T
        K0[nf:, :nf] = GRF
        rhs = torch.cat((fs[fi], hs[ri]))
        reg = torch.cat((torch.full((nf,), 1e-10), torch.full((nr,), -1e-10))).double()
        K0d = K0.clone()
        K0d.diagonal().add_(reg)
        LU, piv = torch.linalg.lu_factor(K0d)
        v = torch.linalg.lu_solve(LU, piv, rhs[:, None])[:, 0]
        for _ in range(5):
            v = v + torch.linalg.lu_solve(LU, piv, (rhs - K0 @ v)[:, None])[:, 0]
        x = torch.zeros(J, dtype=torch.float64)
        x[fi] = v[:nf]
        y = torch.zeros(Gs.shape[0], dtype=torch.float64)
        y[ri] = v[nf:]
        grad = Hs @ x - fs + Gs.T @ y  # = mu on B, ~0 on F
        mu = torch.where(B, grad, torch.zeros_like(grad))
        slack = Gs @ x - hs
        bad_x = F & (x < -tol_p)
        bad_row = ~R & (slack > tol_p)
        bad_y = R & (y < -tol_d)
        bad_mu = B & (mu < -tol_d)
        stat = float(grad[F].abs().max()) if nf else 0.0
        if not (bad_x.any() or bad_row.any() or bad_y.any() or bad_mu.any()) and stat <= 1e-9:
            return x.clamp_min(0), mu.clamp_min(0), y.clamp_min(0)
        if bool(bad_x.any()) or bool(bad_row.any()):  # primal repair first: add the violated constraints
            B, R = B | bad_x, R | bad_row
        elif bool(bad_mu.any()) or bool(bad_y.any()):  # then release the most negative multiplier only
            m_mu = float(torch.where(bad_mu, mu, torch.zeros_like(mu)).min()) if J else 0.0
            m_y = float(torch.where(bad_y, y, torch.zeros_like(y)).min()) if y.numel() else 0.0
            if m_mu <= m_y:
                B = B & (mu != m_mu)
            else:
                R = R & (y != m_y)
        else:
            return None  # stationarity not met on a consistent active set: give up
    return None


def _normalised(H, f, G, h):
    """Unit-norm rows, x in units of the largest right-hand side (so that h ~ 1 also for rho_d ->
    1, where h = 1e-9 would otherwise sit below the absolute tolerances), ||H||_max = 1:
    (row norms, x scale, objective scale, H, f, G, h normalised)."""
    M = G.shape[0]
    rn = G.norm(dim=1).clamp_min(1e-300)
    Gs, hr = G / rn[:, None], h / rn
    s_x = float(hr.max()) if M and float(hr.max()) > 0 else 1.0
    s_obj = max(float(H.abs().max()) * s_x * s_x, float(f.abs().max()) * s_x, 1e-300)
    return rn, s_x, s_obj, H * (s_x * s_x / s_obj), f * (s_x / s_obj), Gs, hr / s_x


def _certified_infeasible(dy, lb, ub, E, Dinv, AbT) -> bool:
    """OSQP's primal infeasibility certificate (Sec. 3.4) on the dual step ``dy`` projected onto
    the recession cone of the box [lb, ub]."""
    dy = torch.where(torch.isinf(ub), dy.clamp_max(0), dy)
    dy = torch.where(torch.isinf(lb), dy.clamp_min(0), dy)
    ndy = float((E * dy).abs().max())
    if ndy <= 1e-12:
        return False
    supp = float(torch.where(dy > 0, torch.nan_to_num(ub, posinf=0.0) * dy, torch.zeros_like(dy)).sum())
    supp += float(torch.where(dy < 0, torch.nan_to_num(lb, neginf=0.0) * dy, torch.zeros_like(dy)).sum())
    return float((Dinv * (AbT @ dy)).abs().max()) <= 1e-9 * ndy and supp < -1e-9 * ndy


def _residuals(x, y, z, Ab, AbT, P, q, Einv, Dinv, c, qn) -> tuple[float, float, float, float]:
    """ADMM's unscaled primal and dual residuals and their norms (OSQP Sec. 3.4)."""
    Ax, Px, Aty = Ab @ x, P @ x, AbT @ y
    r_prim = float((Einv * (Ax - z)).abs().max())
    r_dual = float((Dinv * (Px + q + Aty)).abs().max()) / c
    n_prim = max(float((Einv * Ax).abs().max()), float((Einv * z).abs().max()))
    n_dual = max(float((Dinv * Px).abs().max()) / c, float((Dinv * Aty).abs().max()) / c, qn)
    return r_prim, r_dual, n_prim, n_dual


def _solve_admm(
    H,
    f,
    G,
    h,
    eps: float,
    max_iter: int,
    warm_start,
    polish: bool,
    early_polish: bool,
    sigma=1e-6,
    alpha=1.6,
    rho0=0.1,
    check_every=10,
    rho_every=100,
) -> QPResult:
    H, f, G, h = _prepare(H, f, G, h)
    J, M = H.shape[0], G.shape[0]
    rn, s_x, s_obj, Hs, fs, Gs, hs = _normalised(H, f, G, h)
    # constraints l <= A x <= u with A = [G; I], l = [-inf; 0], u = [h; +inf]
    lo = torch.cat((torch.full((M,), -math.inf, dtype=torch.float64), torch.zeros(J, dtype=torch.float64)))
    up = torch.cat((hs, torch.full((J,), math.inf, dtype=torch.float64)))
    D, E, c, P, q, Ab = _ruiz(Hs, -fs, torch.cat((Gs, torch.eye(J, dtype=torch.float64))))
    lb, ub = E * lo, E * up
    AbT = Ab.T.contiguous()
    AtA = AbT @ Ab
    eye = torch.eye(J, dtype=torch.float64)
    Einv, Dinv = 1 / E, 1 / D

    x = torch.zeros(J, dtype=torch.float64)
    y = torch.zeros(M + J, dtype=torch.float64)
    if warm_start is not None:
        x = torch.as_tensor(warm_start.x, dtype=torch.float64) / (s_x * D)
        yu = torch.cat((warm_start.row_dual * rn, -warm_start.bound_dual)) * (s_x / s_obj)
        y = yu * c / E
    z = torch.maximum(torch.minimum(Ab @ x, ub), lb)

    def unscale(x, y):  # clamped x and multipliers (>= 0) of the normalised problem
        yu = E * y / c
        return (D * x).clamp_min(0), (-yu[M:]).clamp_min(0), yu[:M].clamp_min(0)

    def try_polish(x, z, y, tol_obj):
        """Polish from the active set guessed by OSQP's rule; accept if feasible to 1e-10 and not worse."""
        zu, yu = Einv * z, E * y / c
        row_act = (hs - zu[:M]) < yu[:M]  # upper bound active: u - z < y
        bnd_act = zu[M:] < -yu[M:]  # lower bound active: z - l < -y
        pol = _polish(Hs, fs, Gs, hs, bnd_act, row_act)
        if pol is None:
            return None
        xa = unscale(x, y)[0]
        obj_a = 0.5 * float(xa @ (Hs @ xa)) - float(fs @ xa)
        obj_p = 0.5 * float(pol[0] @ (Hs @ pol[0])) - float(fs @ pol[0])
        viol_s = max(0.0, float((Gs @ pol[0] - hs).max()) if M else 0.0)  # relative to max(h) = 1
        viol_p = max(0.0, float((G @ (s_x * pol[0]) - h).max()) if M else 0.0)
        # "not worse": within the current ADMM tolerance of the (slightly infeasible) ADMM point
        if max(viol_s, viol_p) <= 1e-10 and obj_p <= obj_a + 10 * tol_obj * (1 + abs(obj_a)):
            return pol
        return None

    rho = rho0
    L = _chol(P + sigma * eye + rho * AtA)
    early, next_polish = None, 1e-3
    y_prev = y.clone()
    converged, it = False, 0
    qn = float((Dinv * q).abs().max()) / c
    for it in range(1, max_iter + 1):
        rhs = sigma * x - q + AbT @ (rho * z - y)
        xt = torch.cholesky_solve(rhs[:, None], L)[:, 0]
        zt = Ab @ xt
        x = alpha * xt + (1 - alpha) * x
        zr = alpha * zt + (1 - alpha) * z
        zn = torch.maximum(torch.minimum(zr + y / rho, ub), lb)  # exact projection onto the box
        y = y + rho * (zr - zn)
        z = zn
        if it % check_every and it != max_iter:
            continue
        r_prim, r_dual, n_prim, n_dual = _residuals(x, y, z, Ab, AbT, P, q, Einv, Dinv, c, qn)
        if r_prim <= eps + eps * n_prim and r_dual <= eps + eps * n_dual:
            converged = True
            break
        # early polishing (OSQP's recipe: moderate ADMM accuracy, then the exact active-set solve):
        # tried each time the relative residual falls by another decade below 1e-3 and every 200
        # iterations (slow tails, e.g. many bounds active at a small x); a polished point
        # that passes the KKT check of _polish is optimal, which is stronger than the eps criteria
        rel = max(r_prim / (1 + n_prim), r_dual / (1 + n_dual))
        if polish and early_polish and (rel <= next_polish or it % 200 == 0):
            next_polish = min(next_polish, rel / 10)
            early = try_polish(x, z, y, rel)
            if early is not None:
                break
        # primal infeasibility certificate (OSQP Sec. 3.4) on dy projected onto the recession cone
        if r_prim > eps + eps * n_prim and _certified_infeasible(y - y_prev, lb, ub, E, Dinv, AbT):
            raise InfeasibleError(f"ADMM: primal infeasibility certificate after {it} iterations")
        y_prev = y.clone()
        # adaptive rho (OSQP Sec. 5.2): balance the relative residuals, every rho_every iterations
        # (every 10 made rho oscillate and ADMM stall on the near-LP problems of rho_d -> 1)
        if it % rho_every:
            continue
        ratio = (r_prim / max(n_prim, 1e-300)) / max(r_dual / max(n_dual, 1e-300), 1e-300)
        rho_new = min(max(rho * math.sqrt(ratio), 1e-6), 1e6)
        if rho_new > 5 * rho or rho_new < rho / 5:
            rho = rho_new
            L = _chol(P + sigma * eye + rho * AtA)
    if early is not None:
        (xs, mu, yr), polished = early, True
    else:
        xs, mu, yr = unscale(x, y)
        pol = try_polish(x, z, y, eps) if polish else None
        polished = pol is not None
        if polished:
            xs, mu, yr = pol
    if not (converged or polished):
        raise NumericalError(
            f"ADMM did not converge in {max_iter} iterations (primal residual {r_prim:.3g}, dual {r_dual:.3g}; "
            "no infeasibility certificate) and polishing failed; try method='interior_point'"
        )
    xs = xs * s_x
    viol = max(0.0, float((G @ xs - h).max()) if M else 0.0)
    objective = 0.5 * float(xs @ (H @ xs)) - float(f @ xs)
    return QPResult(xs, mu * (s_obj / s_x), yr * (s_obj / s_x) / rn, it, objective, viol, True, "admm", polished)
