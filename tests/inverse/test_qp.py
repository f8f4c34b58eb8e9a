"""The QP solvers (interior point and ADMM): KKT conditions, reference solvers, agreement, extremes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_brdf.errors import InfeasibleError, NumericalError, ShapeError, ValueRangeError
from torch_brdf.inverse import StrokeTarget, energy_rows, fit, solve_qp

METHODS = ["interior_point", "admm"]


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


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("singular", [False, True])
def test_kkt_conditions(gen, singular, method):
    H, f, G, h = _problem(gen, singular=singular)
    r = solve_qp(H, f, G, h, method=method)
    assert r.converged and r.method == method
    assert bool((r.x >= 0).all())  # exactly, not to a tolerance
    if method == "admm":  # polishing gives the exact active-set solution: KKT to rounding
        assert r.polished
        _kkt(H, f, G, h, r, tol=1e-10)
    _kkt(H, f, G, h, r)
    assert bool((G @ r.x <= h + 1e-10).any())  # energy rows active: the constraints matter here
    assert float((G @ r.x - h).max()) > -1e-6


@pytest.mark.parametrize("method", METHODS)
def test_unconstrained_rows_match_lstsq(gen, method):
    H, f, _, _ = _problem(gen, j=20)
    r = solve_qp(H, f, torch.zeros(0, 20, dtype=torch.float64), torch.zeros(0, dtype=torch.float64), method=method)
    x_nnls = r.x
    # with only x >= 0, compare with scipy's NNLS on the Cholesky factor
    from scipy.optimize import nnls

    L = torch.linalg.cholesky(H)
    y = torch.linalg.solve_triangular(L, f[:, None], upper=False)[:, 0]
    x_ref, _ = nnls(L.T.numpy(), y.numpy())
    obj = lambda x: 0.5 * float(x @ H @ x) - float(f @ x)  # noqa: E731
    assert obj(x_nnls) == pytest.approx(obj(torch.from_numpy(x_ref)), rel=1e-9)


@pytest.mark.parametrize("method", METHODS)
def test_trivial_and_infeasible(gen, method):
    H, f, G, h = _problem(gen)
    r = solve_qp(H, -f, G, h, method=method)  # gradient points away from the feasible set: x = 0
    assert bool((r.x == 0).all()) and r.iterations == 0
    f1 = -f.clone()
    f1[5] = 0.01 * float(f.max())  # one lobe pulls: x = 0 except (near) x_5, many bounds active
    r1, ref = solve_qp(H, f1, G, h, method=method), solve_qp(H, f1, G, h, method="interior_point")
    assert r1.objective == pytest.approx(ref.objective, rel=1e-6) and bool((r1.x >= 0).all())
    exact = -0.5 * float(f1[5]) ** 2 / float(H[5, 5])  # x = e_5 f_5 / H_55 (the KKT point here)
    assert r1.objective == pytest.approx(exact, rel=1e-7)
    r0 = solve_qp(H, torch.zeros_like(f), G, h, method=method)  # all-zero target
    assert bool((r0.x == 0).all()) and r0.objective == 0.0
    with pytest.raises(InfeasibleError):
        solve_qp(H, f, G, -h, method=method)  # rho_d >= 1 leaves h < 0
    G2 = torch.tensor([[1.0, 0.0], [-1.0, 0.0]], dtype=torch.float64)  # x0 <= 1 and x0 >= 2
    with pytest.raises(InfeasibleError):
        solve_qp(
            torch.eye(2, dtype=torch.float64),
            torch.ones(2, dtype=torch.float64),
            G2,
            torch.tensor([1.0, -2.0]),
            method=method,
        )
    with pytest.raises(ValueRangeError):
        solve_qp(H, f * float("nan"), G, h, method=method)
    with pytest.raises(ShapeError):
        solve_qp(H, f[:5], G, h, method=method)
    with pytest.raises(ValueRangeError):
        solve_qp(H, f, G, h, method="newton")


@pytest.mark.reference
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("solver", ["proxqp", "clarabel"])
@pytest.mark.parametrize("singular", [False, True])
def test_agrees_with_reference_solvers(gen, solver, singular, method):
    qpsolvers = pytest.importorskip("qpsolvers")
    from scipy.sparse import csc_matrix as csc

    H, f, G, h = _problem(gen, singular=singular)
    r = solve_qp(H, f, G, h, method=method)
    kw = {"eps_abs": 1e-12, "eps_rel": 0.0} if solver == "proxqp" else {}
    args = (csc(H.numpy()), -f.numpy(), csc(G.numpy()), h.numpy())
    x = qpsolvers.solve_qp(*args, lb=np.zeros(H.shape[0]), solver=solver, **kw)
    x = torch.from_numpy(x)
    ref = 0.5 * float(x @ H @ x) - float(f @ x)
    assert r.objective == pytest.approx(ref, rel=1e-6)
    assert r.objective <= ref + 1e-9 * abs(ref)  # never worse than the reference


@pytest.mark.parametrize("seed", range(4))
def test_methods_agree_on_random_problems(seed):
    """ADMM (Stellato et al. 2020) and the interior point method on random problems, half with
    singular H, with tighter energy budgets so that several rows are active."""
    gen = torch.Generator().manual_seed(100 + seed)
    H, f, G, h = _problem(gen, n=200 + 50 * seed, singular=seed % 2 == 1)
    h = h * (0.3 + 0.2 * seed)
    ip = solve_qp(H, f, G, h, method="interior_point")
    assert solve_qp(H, f, G, h).method == "interior_point"  # the default
    ad = solve_qp(H, f, G, h, method="admm")
    assert ad.method == "admm" and not ad.fallback
    assert int(((G @ ip.x - h) > -1e-9).sum()) >= 1  # active energy rows
    assert ad.polished and ad.violation <= 1e-10 and bool((ad.x >= 0).all())
    assert ad.objective == pytest.approx(ip.objective, rel=1e-9)
    _kkt(H, f, G, h, ad, tol=1e-10)


def test_admm_without_polishing_and_warm_start(gen):
    """The plain ADMM iterate meets OSQP's residual criteria; a warm start from the solution
    stops at the first check."""
    H, f, G, h = _problem(gen, singular=True)
    ip = solve_qp(H, f, G, h, method="interior_point")
    raw = solve_qp(H, f, G, h, method="admm", polish=False)
    assert raw.converged and not raw.polished and 10 < raw.iterations <= 4000
    assert bool((raw.x >= 0).all()) and raw.violation <= 1e-8
    assert raw.objective == pytest.approx(ip.objective, rel=1e-6)
    warm = solve_qp(H, f, G, h, method="admm", warm_start=ip)
    cold = solve_qp(H, f, G, h, method="admm")
    assert warm.iterations < cold.iterations
    assert warm.objective == pytest.approx(ip.objective, rel=1e-9)


def test_fit_with_admm_matches_interior_point(view, target_render):
    """``fit(method="admm")`` against the default ``method="interior_point"`` on the recovery problem of
    test_solve (whole object painted with a known p(h)) and on a few-pixel, near-singular one:
    same objective, exact bounds."""
    rec = view[-1]
    n = target_render.shape[0]
    whole = StrokeTarget(target_render, torch.ones(n, dtype=torch.float64), torch.ones(n, dtype=torch.bool))
    w = torch.zeros(n, dtype=torch.float64)
    w[:12] = 1  # 12 pixels, 147 unknowns: H of rank <= 12 per channel
    few = StrokeTarget(target_render, w, w > 0)
    for target in (whole, few):
        ip = fit(rec, target, kd=(0.25, 0.375, 0.125), method="interior_point")
        ad = fit(rec, target, kd=(0.25, 0.375, 0.125), method="admm")
        assert ad.meta["method"] == "admm"  # (the few-pixel fit falls back to the interior point)
        # (the few-pixel fit is exact: both objectives ~1e-10 of the target's 1e2 sum of squares)
        assert ad.objective == pytest.approx(ip.objective, rel=1e-6, abs=1e-8)
        assert ad.violation <= 1e-8 and bool((ad.coefficients >= 0).all())
    with pytest.raises(ValueRangeError):
        fit(rec, whole, method="osqp")


@pytest.mark.parametrize("singular", [False, True])
def test_admm_at_the_albedo_extreme(singular):
    """rho_d -> 1 leaves h = 1e-9 (a near-LP): ADMM stays feasible relative to h and is at least
    as good as the interior point method run to a tight tolerance (and polished)."""
    gen = torch.Generator().manual_seed(1 if singular else 0)
    H, f, G, h = _problem(gen, n=150, singular=singular)
    h = torch.full_like(h, 1e-9)
    ad = solve_qp(H, f, G, h, method="admm")
    ip = solve_qp(H, f, G, h, method="interior_point", tol=1e-14)
    assert ad.polished and not ad.fallback and bool((ad.x >= 0).all())
    assert ad.violation <= 1e-10 * 1e-9
    assert ad.objective == pytest.approx(ip.objective, rel=1e-6)
    assert ad.objective <= ip.objective + 1e-9 * abs(ip.objective)


def test_admm_falls_back_to_the_interior_point(gen):
    """ADMM stopped long before convergence (10 iterations, no polishing): the default returns
    the interior point solution and says so; ``fallback=False`` raises instead."""
    H, f, G, h = _problem(gen, singular=True)
    ip = solve_qp(H, f, G, h)
    r = solve_qp(H, f, G, h, method="admm", max_iter=10, polish=False)
    assert r.fallback and r.method == "interior_point"
    assert torch.equal(r.x, ip.x)
    with pytest.raises(NumericalError, match="ADMM did not converge"):
        solve_qp(H, f, G, h, method="admm", max_iter=10, polish=False, fallback=False)
    ok = solve_qp(H, f, G, h, method="admm")
    assert not ok.fallback and ok.method == "admm"


def test_interior_point_polishing_is_exact(gen):
    """The polished interior point solution satisfies the KKT conditions to rounding; without
    polishing it is the (slightly interior) iterate, not better."""
    H, f, G, h = _problem(gen, singular=True)
    pol = solve_qp(H, f, G, h)
    raw = solve_qp(H, f, G, h, polish=False)
    assert pol.polished and not raw.polished
    _kkt(H, f, G, h, pol, tol=1e-10)
    assert pol.objective <= raw.objective + 1e-12 * abs(raw.objective)


@pytest.mark.parametrize("singular", [False, True])
def test_active_set_first_try_meets_the_interior_point_optimum(gen, singular):
    """A zero-residual target of a sparse coefficient vector: the default's active-set first
    try answers without Newton steps, at the interior point method's optimum and KKT point."""
    from torch_brdf.inverse.qp import _interior_point, _prepare

    H, _, G, h = _problem(gen, singular=singular)
    c = torch.zeros(H.shape[0], dtype=torch.float64)
    c[[3, 40, 41, 90, 120]] = torch.tensor([0.02, 0.05, 0.01, 0.03, 0.04], dtype=torch.float64)
    f = H @ c  # the target the coefficients c render: zero residual at the optimum
    r = solve_qp(H, f, G, h)
    ip = _interior_point(*_prepare(H, f, G, h), 1e-11, 100)
    assert r.iterations == 0 and r.polished  # the first try's answer
    assert r.objective <= ip.objective + 1e-12 * abs(ip.objective)
    _kkt(H, f, G, h, r)
