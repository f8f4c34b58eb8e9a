"""A held-out-like set of inverse-design QPs made from one teapot view (the inverse benchmark and the tests).

Problem kinds (a plain ADMM fails on the first four):

* ``*-half``: partial masks (half the object weighted, the other half free): lobes no pixel
  constrains, singular H;
* ``exact-*``: targets rendered from coefficients inside the SRBF family (zero residual);
* ``ward-*``: an out-of-family target (an isotropic Ward BRDF rendered by the BRDF module);
* ``few-pixels``: 12 weighted pixels for 147 unknowns (rank <= 12);
* ``strokes``, ``strokes-painted``: painted strokes on the diffuse image, with and without the
  kept pixels; ``shared``: one grey p(h); ``kd-extreme``: rho_d = 1 - 1e-6 (h ~ 1e-6).

Each problem is a :class:`~torch_brdf.inverse.solve.NormalEquations` per channel (or one shared).
"""

from __future__ import annotations

import torch

from torch_brdf.brdf.analytic import DistributionBased, Ward
from torch_brdf.brdf.srbf import SRBFDistribution
from torch_brdf.frame import Frame
from torch_brdf.inverse import Brush, Stroke, StrokeTarget, normal_equations, paint
from torch_brdf.inverse.energy import default_basis

KD = (0.25, 0.375, 0.125)
F0 = (0.875, 0.75, 0.625)


def true_coefficients() -> torch.Tensor:
    """A sparse p(h) in the SRBF span (dyadic values), well inside the energy constraints: (147,)."""
    c = torch.zeros(147, dtype=torch.float64)
    c[[0, 1, 7, 24, 60, 100]] = torch.tensor([0.5, 0.25, 0.5, 0.75, 0.25, 0.125], dtype=torch.float64)
    return c


def render_brdf(px, ls, vis, brdf) -> torch.Tensor:
    """Brute-force direct render of a BRDF module: (P, 3) sum over light samples of f_r L V cos / pdf."""
    fr = Frame.from_normal(px.normal)
    frame = Frame(fr.s[:, None], fr.t[:, None], fr.n[:, None])  # (P, 1, 3): broadcast over samples
    wi = ls.directions[None].expand(px.count, -1, 3)
    wo = px.wo[:, None].expand_as(wi)
    with torch.no_grad():
        f = brdf.double().eval(wi, wo, frame)  # (P, S, 3)
    return (f * vis[..., None] * ls.weight[None]).sum(1)


def srbf_brdf(c: torch.Tensor, kd=KD, f0=F0) -> DistributionBased:
    """The SRBF distribution-based BRDF module of coefficients ``c`` (147,)."""
    return DistributionBased(SRBFDistribution(default_basis(), c), kd=kd, f0=f0)


def whole(target: torch.Tensor) -> StrokeTarget:
    """Every pixel weighted 1 and painted."""
    n = target.shape[0]
    return StrokeTarget(target, torch.ones(n, dtype=torch.float64), torch.ones(n, dtype=torch.bool))


def half(rec, target: torch.Tensor) -> StrokeTarget:
    """Only the left half of the object (by image column) is weighted."""
    col = (rec.pixels % rec.width).double()
    w = (col < col.median()).double()
    return StrokeTarget(target, w, w > 0)


def strokes(rec, kd=KD) -> StrokeTarget:
    """A white highlight and a dark stroke painted on the diffuse-only image (unreachable exactly)."""
    kd = torch.tensor(kd, dtype=torch.float64).expand(3)
    c0 = torch.cat((torch.zeros(147, 3, dtype=torch.float64), kd[None]))
    before = rec.pixel_values(c0)
    r = torch.div(rec.pixels, rec.width, rounding_mode="floor").double()
    c = (rec.pixels % rec.width).double()
    mid = torch.stack((c.mean(), r.mean()))
    s = [
        Stroke(torch.stack((mid - 4, mid + torch.tensor([2.0, -3.0]))), Brush((3.0, 3.0, 2.5), 6.0, 0.05)),
        Stroke((mid + torch.tensor([5.0, 4.0]))[None], Brush((-0.5, -0.5, -0.5), 5.0, 0.0)),
    ]
    return paint(rec, before, s)


def problem_targets(px, ls, vis, rec) -> dict[str, tuple[StrokeTarget, tuple, bool]]:
    """The named fit problems: ``name -> (target, kd, shared)``."""
    exact = render_brdf(px, ls, vis, srbf_brdf(true_coefficients()))
    ward = render_brdf(px, ls, vis, Ward(kd=KD, ks=(0.3, 0.25, 0.2), alpha=0.12))
    st = strokes(rec)
    n = exact.shape[0]
    w12 = torch.zeros(n, dtype=torch.float64)
    w12[:12] = 1
    return {
        "exact-whole": (whole(exact), KD, False),
        "exact-half": (half(rec, exact), KD, False),
        "ward-whole": (whole(ward), KD, False),
        "ward-half": (half(rec, ward), KD, False),
        "few-pixels": (StrokeTarget(exact, w12, w12 > 0), KD, False),
        "strokes": (st, KD, False),
        "strokes-painted": (StrokeTarget(st.target, st.painted.double(), st.painted), KD, False),
        "shared": (st, KD, True),
        "kd-extreme": (strokes(rec, 0.0), (1 - 1e-6,) * 3, False),
    }


def qp_set(px, ls, vis, rec) -> list[tuple[str, object]]:
    """Every channel QP of :func:`problem_targets`: a list of ``(name/channel, NormalEquations)``."""
    out = []
    for name, (target, kd, shared) in problem_targets(px, ls, vis, rec).items():
        for pr in normal_equations(rec, target, kd=kd, shared=shared):
            out.append((f"{name}/{''.join('rgb'[c] for c in pr.channels)}", pr))
    return out


def reference_solution(pr) -> tuple[torch.Tensor, str]:
    """ProxQP (qpsolvers, eps_abs 1e-12) on one problem; Clarabel (gap 1e-12) where ProxQP fails.

    Solved in units of ``max(h)`` (x = s y) so that rho_d -> 1 (h ~ 1e-6) stays well scaled.
    ProxQP returns no solution on ``kd-extreme`` at any tolerance tried (1e-12 .. 1e-9, with and
    without scaling); Clarabel solves it.

    Returns:
        ((J,) float64 solution, name of the solver that produced it).
    """
    import numpy as np
    import qpsolvers

    s = float(pr.h.max()) if pr.G.shape[0] and float(pr.h.max()) > 0 else 1.0
    args = ((pr.H * s * s).numpy(), -(pr.f * s).numpy(), pr.G.numpy(), (pr.h / s).numpy())
    lb = np.zeros(pr.H.shape[0])
    y = qpsolvers.solve_qp(*args, lb=lb, solver="proxqp", eps_abs=1e-12, eps_rel=0.0, max_iter=100_000)
    if y is not None:
        return torch.from_numpy(y) * s, "proxqp"
    from scipy.sparse import csc_matrix

    sparse = (csc_matrix(args[0]), args[1], csc_matrix(args[2]), args[3])
    y = qpsolvers.solve_qp(*sparse, lb=lb, solver="clarabel", tol_gap_abs=1e-12, tol_gap_rel=1e-12)
    if y is None:
        raise RuntimeError("neither ProxQP nor Clarabel returned a solution")
    return torch.from_numpy(y) * s, "clarabel"


def objective_gap(pr, x: torch.Tensor, ref: torch.Tensor) -> float:
    """Relative objective difference of ``x`` against ``ref``: (f(x) - f(ref)) / max(f(ref), 1e-6 k).

    The sum of squares is the objective; for zero-residual targets (optimum ~ 0) the floor is
    1e-6 of the target's weighted energy k, so "relative" stays meaningful.
    """
    a, b = pr.sum_of_squares(x), pr.sum_of_squares(ref)
    return (a - b) / max(abs(b), 1e-6 * pr.k)


def violation(pr, x: torch.Tensor) -> float:
    """Largest violation of x >= 0 and G x <= h (absolute)."""
    v = float((-x).max())
    if pr.G.shape[0]:
        v = max(v, float((pr.G @ x - pr.h).max()))
    return max(0.0, v)
