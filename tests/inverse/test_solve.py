"""The fit: recovery of a known BRDF, agreement with ProxQP/Clarabel, odd input, extremes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.inverse.conftest import KD
from torch_brdf.errors import FileFormatError, InfeasibleError, ShapeError, ValueRangeError
from torch_brdf.inverse import (
    Brush,
    Stroke,
    StrokeTarget,
    energy_rows,
    fit,
    load_fit,
    normal_equations,
    paint,
    save_fit,
)
from torch_brdf.metrics import relative_rmse


def _whole(target: torch.Tensor) -> StrokeTarget:
    n = target.shape[0]
    return StrokeTarget(target, torch.ones(n, dtype=torch.float64), torch.ones(n, dtype=torch.bool))


def _strokes(rec, kd=KD):
    """Paint a white highlight and a dark stroke on the diffuse-only image (unreachable exactly)."""
    kd = torch.tensor(kd, dtype=torch.float64).expand(3)
    c0 = torch.cat((torch.zeros(147, 3, dtype=torch.float64), kd[None]))
    before = rec.pixel_values(c0)
    r = torch.div(rec.pixels, rec.width, rounding_mode="floor").double()
    c = (rec.pixels % rec.width).double()
    mid = torch.stack((c.mean(), r.mean()))
    strokes = [
        Stroke(torch.stack((mid - 4, mid + torch.tensor([2.0, -3.0]))), Brush((3.0, 3.0, 2.5), 6.0, 0.05)),
        Stroke((mid + torch.tensor([5.0, 4.0]))[None], Brush((-0.5, -0.5, -0.5), 5.0, 0.0)),
    ]
    return paint(rec, before, strokes)


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
    """Few painted pixels and no kept pixels: most lobes unseen, H singular; still a KKT point."""
    rec = view[-1]
    t = _strokes(rec)
    few = StrokeTarget(t.target, t.painted.double(), t.painted)
    res = fit(rec, few, kd=KD)
    assert res.violation <= 1e-8 and np.isfinite(res.objective)
    pr = normal_equations(rec, few, kd=KD)[0]
    assert int(torch.linalg.matrix_rank(pr.H)) < 147


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
