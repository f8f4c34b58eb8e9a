"""The fit: recovery of a known BRDF, agreement with ProxQP/Clarabel, odd input, extremes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.inverse.conftest import KD, true_coefficients
from torch_brdf.errors import FileFormatError, InfeasibleError, ShapeError, ValueRangeError
from torch_brdf.inverse import (
    LightSamples,
    StrokeTarget,
    cosine_visibility,
    energy_rows,
    fit,
    load_fit,
    normal_equations,
    save_fit,
    solve_qp,
    transfer_functions,
)
from torch_brdf.metrics import relative_rmse
from torch_brdf.report.benchmarks.qp_set import objective_gap, problem_targets, qp_set, reference_solution, violation
from torch_brdf.report.benchmarks.qp_set import strokes as _strokes
from torch_brdf.report.benchmarks.qp_set import whole as _whole


def test_recovers_a_known_brdf(view, target_render):
    """Acceptance: target rendered with a known p(h) in the SRBF span (the BRDF module, same light
    samples), whole object as the stroke region -> <= 1% relative RMSE, constraints to 1e-8."""
    rec, target = view[-1], target_render
    res = fit(rec, _whole(target), kd=KD)
    img = rec.pixel_values(res.record_coefficients())
    assert relative_rmse(img, target) <= 0.01
    assert res.violation <= 1e-8
    assert bool((res.coefficients >= 0).all())
    g = energy_rows().rows(res.f0.tolist())
    energy = torch.tensor(KD, dtype=torch.float64)[:, None] + torch.einsum("clj,jc->cl", g, res.coefficients)
    assert float(energy.max()) <= 1 + 1e-8 and res.max_energy == pytest.approx(float(energy.max()))


def test_strokes_make_the_constraints_active(view):
    rec = view[-1]
    res = fit(rec, _strokes(rec), kd=KD)
    assert res.violation <= 1e-8
    assert res.max_energy == pytest.approx(1.0, abs=1e-6)  # the bright stroke asks for more than allowed
    free = fit(rec, _strokes(rec), kd=KD, constrained=False)
    assert free.objective <= res.objective * (1 + 1e-9)
    assert free.max_energy > 1.0 or bool((free.coefficients < 0).any())  # physically impossible


@pytest.mark.reference
@pytest.mark.parametrize("solver", ["proxqp", "clarabel"])
@pytest.mark.parametrize("problem", ["strokes", "recovery", "shared"])
def test_objective_agrees_with_reference_solver(view, target_render, solver, problem):
    qpsolvers = pytest.importorskip("qpsolvers")
    from scipy.sparse import csc_matrix as csc

    rec = view[-1]
    if problem == "recovery":
        target = _whole(target_render)
    else:
        target = _strokes(rec)
    shared = problem == "shared"
    res = fit(rec, target, kd=KD, shared=shared)
    ref, total = 0.0, 0.0
    tight = {"proxqp": {"eps_abs": 1e-12, "eps_rel": 0.0}, "clarabel": {"tol_gap_abs": 1e-12, "tol_gap_rel": 1e-12}}
    for pr in normal_equations(rec, target, kd=KD, shared=shared):
        args = (csc(pr.H.numpy()), -pr.f.numpy(), csc(pr.G.numpy()), pr.h.numpy())
        x = qpsolvers.solve_qp(*args, lb=np.zeros(147), solver=solver, **tight[solver])
        ref += pr.sum_of_squares(torch.from_numpy(x))
        total += pr.k
    # relative to the optimum; for the recovery problem (optimum ~ 0): 1e-10 of the target energy
    assert abs(res.objective - ref) <= 1e-6 * max(ref, 1e-4 * total)
    assert res.objective <= ref + 1e-9 * total  # and never worse


def test_all_zero_target_gives_zero(view):
    rec = view[-1]
    zero = _whole(torch.zeros(rec.num_pixels, 3, dtype=torch.float64))
    for kd in (0.0, KD):
        res = fit(rec, zero, kd=kd)
        assert torch.equal(res.coefficients, torch.zeros_like(res.coefficients))
        assert res.iterations == 0 and np.isfinite(res.objective)


def test_diffuse_albedo_extremes(view):
    rec = view[-1]
    target = _strokes(rec, kd=0.0)
    with pytest.raises(InfeasibleError, match="kd"):
        fit(rec, target, kd=1.0)
    with pytest.raises(InfeasibleError):
        fit(rec, target, kd=(0.2, 1.2, 0.2))
    with pytest.raises(ValueRangeError):
        fit(rec, target, kd=-0.1)
    near = fit(rec, target, kd=1 - 1e-9)
    assert near.violation <= 1e-8 and bool(torch.isfinite(near.coefficients).all())
    assert near.max_energy <= 1 + 1e-8
    zero = fit(rec, target, kd=0.0)
    assert zero.violation <= 1e-8 and float(zero.coefficients.max()) > 0
    fit(rec, target, kd=1.5, constrained=False)  # allowed when the user wants impossible BRDFs


def test_float32_record_gives_the_float64_answer(view):
    rec = view[-1]
    target = _strokes(rec)
    a = fit(rec, target, kd=KD)
    b = fit(rec.to(torch.float32), target, kd=KD)
    assert b.coefficients.dtype == torch.float64
    assert b.objective == pytest.approx(a.objective, rel=1e-4)


def test_near_singular_normal_equations(view):
    """Few painted pixels and no kept pixels: most lobes unseen, H singular; still a KKT point.

    The default method solves it on the procedural stand-in teapot too (no data folder), where
    a plain ADMM default fails; so does ADMM through its fallback."""
    rec = view[-1]
    t = _strokes(rec)
    few = StrokeTarget(t.target, t.painted.double(), t.painted)
    res = fit(rec, few, kd=KD)
    assert res.violation <= 1e-8 and np.isfinite(res.objective)
    assert res.meta["method"] == "interior_point"
    pr = normal_equations(rec, few, kd=KD)[0]
    assert int(torch.linalg.matrix_rank(pr.H)) < 147
    ad = fit(rec, few, kd=KD, method="admm")
    assert ad.violation <= 1e-8
    assert ad.objective == pytest.approx(res.objective, rel=1e-9)


def test_odd_targets(view):
    rec = view[-1]
    t = _strokes(rec)
    bad = t.target.clone()
    bad[0, 1] = float("nan")
    with pytest.raises(ValueRangeError, match="non-finite"):
        fit(rec, StrokeTarget(bad, t.weight, t.painted), kd=KD)
    with pytest.raises(ValueRangeError, match="no pixel carries weight"):
        fit(rec, StrokeTarget(t.target, torch.zeros_like(t.weight), t.painted), kd=KD)
    with pytest.raises(ValueRangeError):
        fit(rec, StrokeTarget(t.target, -t.weight, t.painted), kd=KD)
    with pytest.raises(ShapeError):
        fit(rec, StrokeTarget(t.target[:4], t.weight[:4], t.painted[:4]), kd=KD)


def test_save_and_load(view, tmp_path):
    rec = view[-1]
    res = fit(rec, _strokes(rec), kd=KD)
    save_fit(tmp_path / "fit.npz", res)
    back = load_fit(tmp_path / "fit.npz")
    assert torch.equal(back.coefficients, res.coefficients) and back.objective == res.objective
    raw = bytearray((tmp_path / "fit.npz").read_bytes())
    raw[-200] ^= 0xFF
    (tmp_path / "bad.npz").write_bytes(bytes(raw))
    with pytest.raises(FileFormatError):
        load_fit(tmp_path / "bad.npz")


@pytest.fixture(scope="module")
def problems(view):
    """The QP set of tests/inverse/qp_set.py on this view, with reference solutions."""
    pytest.importorskip("qpsolvers")
    _, px, ls, vis, rec = view
    out = {}
    for name, pr in qp_set(px, ls, vis, rec):
        out.setdefault(name.split("/")[0], []).append((pr, reference_solution(pr)[0]))
    return out


KINDS = ["exact-whole", "exact-half", "ward-whole", "ward-half", "few-pixels", "strokes", "strokes-painted"]
KINDS += ["shared", "kd-extreme"]


#: On a target the basis reproduces exactly (zero residual) the optimal sum of squares is 0 and
#: every solver stops at its own tolerance: 1e-10 of the target's weighted energy k is where two
#: such answers count as the same optimum (the relative gap's floor, 1e-6 k, is then 1e-12 k).
ZERO_RESIDUAL = 1e-10


def _same_optimum(pr, x, ref) -> bool:
    """Within 1e-6 relative of the reference's objective, or both at a zero-residual optimum."""
    close = abs(objective_gap(pr, x, ref)) <= 1e-6
    return close or abs(pr.sum_of_squares(x) - pr.sum_of_squares(ref)) <= ZERO_RESIDUAL * pr.k


@pytest.mark.reference
@pytest.mark.parametrize("method", ["interior_point", "admm"])
@pytest.mark.parametrize("kind", KINDS)
def test_qp_set_against_reference(problems, kind, method):
    """Every QP of the set solved within 1e-6 relative of ProxQP at
    eps 1e-12 (Clarabel where ProxQP returns nothing: kd-extreme), violation <= 1e-8. ADMM may
    reach it through its interior point fallback (tested on its own in test_qp)."""
    for pr, ref in problems[kind]:
        r = solve_qp(pr.H, pr.f, pr.G, pr.h, method=method)
        assert _same_optimum(pr, r.x, ref), (kind, pr.channels, objective_gap(pr, r.x, ref))
        assert violation(pr, r.x) <= 1e-8
        assert bool((r.x >= 0).all())


@pytest.mark.reference
@pytest.mark.parametrize("kind", ["exact-half", "ward-half", "few-pixels", "strokes-painted"])
def test_fit_with_and_without_ridge_against_reference(view, problems, kind):
    """``fit(ridge=0)`` is the reference optimum; the default minimum-norm term costs at most
    1e-9 of the target's weighted energy k."""
    _, px, ls, vis, rec = view
    target, kd, shared = problem_targets(px, ls, vis, rec)[kind]
    ref = sum(pr.sum_of_squares(x) for pr, x in problems[kind])
    k = sum(pr.k for pr, _ in problems[kind])
    plain = fit(rec, target, kd=kd, shared=shared, ridge=0.0)
    assert abs(plain.objective - ref) <= max(1e-6 * max(ref, 1e-6 * k), ZERO_RESIDUAL * k)
    default = fit(rec, target, kd=kd, shared=shared)
    assert default.meta["ridge"] == 1e-8
    assert ref - 1e-12 * k <= default.objective <= ref + 1e-9 * k
    assert default.violation <= 1e-8


def _patch(rec, target, share=0.15):
    """Weights on the ``share`` of the pixels nearest the object's centre (a painted patch)."""
    r = torch.div(rec.pixels, rec.width, rounding_mode="floor").double()
    c = (rec.pixels % rec.width).double()
    d = ((r - r.mean()) ** 2 + (c - c.mean()) ** 2).sqrt()
    w = (d < d.quantile(share)).double()
    return StrokeTarget(target, w, w > 0)


def test_unconstrained_lobes_get_minimum_norm(view, target_render):
    """A patch of 15% of the pixels with a target inside the SRBF family: many exact solutions.
    The default (minimum-norm) fit keeps the lobes the patch does not see near 0, so the
    coefficients, the energy and a re-render under a new light stay close to the truth;
    the unregularised optimum is an arbitrary exact solution, not closer to the truth."""
    scene, px, _, _, rec = view
    target = _patch(rec, target_render)
    plain = fit(rec, target, kd=KD, ridge=0.0)
    ridge = fit(rec, target, kd=KD)
    truth = true_coefficients()[:, None].expand(147, 3)
    fits = (("plain", plain), ("ridge", ridge))
    err = {n: float((r.coefficients - truth).norm() / truth.norm()) for n, r in fits}
    assert err["ridge"] < 0.5 and err["ridge"] < err["plain"]
    g = energy_rows().rows(ridge.f0.tolist())
    true_energy = float((torch.tensor(KD, dtype=torch.float64)[:, None] + torch.einsum("clj,jc->cl", g, truth)).max())
    assert ridge.max_energy <= true_energy + 0.05
    # re-render under the sky turned by 2.5 rad (new light samples and visibility)
    ls2 = LightSamples.from_environment(scene.environment.rotated(2.5), 128, torch.Generator().manual_seed(8))
    rec2 = transfer_functions(px, ls2, cosine_visibility(scene, px, ls2), f0=ridge.f0.tolist())
    want = rec2.pixel_values(torch.cat((truth, torch.tensor(KD, dtype=torch.float64)[None])))
    rel = {n: relative_rmse(rec2.pixel_values(r.record_coefficients()), want) for n, r in fits}
    assert rel["ridge"] < 0.1 and rel["ridge"] <= rel["plain"]
    with pytest.raises(ValueRangeError, match="ridge"):
        fit(rec, target, kd=KD, ridge=-1.0)
