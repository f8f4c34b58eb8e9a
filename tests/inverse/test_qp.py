"""The interior point QP: KKT conditions, reference solvers, extremes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_brdf.errors import InfeasibleError, ShapeError, ValueRangeError
from torch_brdf.inverse import energy_rows, solve_qp


def _problem(gen, n=400, j=147, singular=False):
    T = torch.rand(n, j, generator=gen, dtype=torch.float64) ** 6
    if singular:  # unseen lobes (zero columns) and duplicated ones: H is singular
        T[:, 10:20] = 0
        T[:, 30] = T[:, 31]
    b = 3 * torch.rand(n, generator=gen, dtype=torch.float64)
    G = energy_rows().rows([0.875])[0]
    h = torch.full((G.shape[0],), 0.6, dtype=torch.float64)
    return T.T @ T, T.T @ b, G, h


def _kkt(H, f, G, h, r, tol=1e-7):
    x, zb, zr = r.x, r.bound_dual, r.row_dual
    scale = float(H.abs().max()) * (1 + float(x.abs().max()))
    assert bool((zb >= 0).all()) and bool((zr >= 0).all())
    stat = H @ x - f - zb + G.T @ zr
    assert float(stat.abs().max()) <= tol * scale
    assert float((zb * x).abs().max()) <= tol * scale  # complementarity
    assert float((zr * (h - G @ x)).abs().max()) <= tol * scale
    assert r.violation <= 1e-8


@pytest.mark.parametrize("singular", [False, True])
def test_kkt_conditions(gen, singular):
    H, f, G, h = _problem(gen, singular=singular)
    r = solve_qp(H, f, G, h)
    assert r.converged
    _kkt(H, f, G, h, r)
    assert bool((G @ r.x <= h + 1e-10).any())  # energy rows active: the constraints matter here
    assert float((G @ r.x - h).max()) > -1e-6


def test_unconstrained_rows_match_lstsq(gen):
    H, f, _, _ = _problem(gen, j=20)
    r = solve_qp(H, f, torch.zeros(0, 20, dtype=torch.float64), torch.zeros(0, dtype=torch.float64))
    x_nnls = r.x
    # with only x >= 0, compare with scipy's NNLS on the Cholesky factor
    from scipy.optimize import nnls

    L = torch.linalg.cholesky(H)
    y = torch.linalg.solve_triangular(L, f[:, None], upper=False)[:, 0]
    x_ref, _ = nnls(L.T.numpy(), y.numpy())
    obj = lambda x: 0.5 * float(x @ H @ x) - float(f @ x)  # noqa: E731
    assert obj(x_nnls) == pytest.approx(obj(torch.from_numpy(x_ref)), rel=1e-9)


def test_trivial_and_infeasible(gen):
    H, f, G, h = _problem(gen)
    r = solve_qp(H, -f, G, h)  # gradient points away from the feasible set: x = 0
    assert float(r.x.abs().max()) <= 1e-9
    with pytest.raises(InfeasibleError):
        solve_qp(H, f, G, -h)
    G2 = torch.tensor([[1.0, 0.0], [-1.0, 0.0]], dtype=torch.float64)  # x0 <= 1 and x0 >= 2
    with pytest.raises(InfeasibleError):
        solve_qp(torch.eye(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64), G2, torch.tensor([1.0, -2.0]))
    with pytest.raises(ValueRangeError):
        solve_qp(H, f * float("nan"), G, h)
    with pytest.raises(ShapeError):
        solve_qp(H, f[:5], G, h)


@pytest.mark.reference
@pytest.mark.parametrize("solver", ["proxqp", "clarabel"])
@pytest.mark.parametrize("singular", [False, True])
def test_agrees_with_reference_solvers(gen, solver, singular):
    qpsolvers = pytest.importorskip("qpsolvers")
    from scipy.sparse import csc_matrix as csc

    H, f, G, h = _problem(gen, singular=singular)
    r = solve_qp(H, f, G, h)
    kw = {"eps_abs": 1e-12, "eps_rel": 0.0} if solver == "proxqp" else {}
    args = (csc(H.numpy()), -f.numpy(), csc(G.numpy()), h.numpy())
    x = qpsolvers.solve_qp(*args, lb=np.zeros(H.shape[0]), solver=solver, **kw)
    x = torch.from_numpy(x)
    ref = 0.5 * float(x @ H @ x) - float(f @ x)
    assert r.objective == pytest.approx(ref, rel=1e-6)
    assert r.objective <= ref + 1e-9 * abs(ref)  # never worse than the reference
