"""The manifold planner (issue #17): q and the training materials from validation pilots; its
predicted median held-out error against the achieved one on the analytic family (no data
needed), for eight orders of the pool."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from torch_brdf.errors import ValueRangeError
from torch_brdf.manifold import analytic_observations, heldout_reconstruction
from torch_brdf.manifold.data import MERLGrid
from torch_brdf.planner import manifold as planner_manifold
from torch_brdf.planner.manifold import _bootstrap_interval, _crossfit_whole_pool, _regression_estimate, plan_manifold

FIT = {"metric": "weighted", "max_iter": 100}


@pytest.fixture(scope="module")
def family():
    """120 analytic materials: 80 held out (the achieved median's own scatter between sets of
    materials must stay well inside 1.5x), 40 the training pool."""
    obs, _ = analytic_observations(120, MERLGrid.strided(9, 9, 18), generator=torch.Generator().manual_seed(7))
    names = list(obs.names)
    return obs, names[:80], names[80:]


@pytest.fixture(scope="module")
def planned(family):
    obs, test, pool = family
    plan = plan_manifold(obs, pool, error=0.01, generator=torch.Generator().manual_seed(0), **FIT)
    return obs, test, pool, plan


def test_plan_trains_on_pool_materials_and_meets_the_budget(planned):
    _, test, pool, plan = planned
    s = plan.settings
    assert set(s["train"]) <= set(pool) and not set(s["train"]) & set(test) and len(s["train"]) == s["n"]
    assert plan.predicted_error <= 0.01
    assert all(o.predicted_error > 0.01 for o in plan.options if o.predicted_seconds < plan.predicted_seconds)
    assert f"q {s['q']}, n {s['n']}" in str(plan) and "predicted cost" in str(plan)


def _achieved_ratio(obs, test, plan) -> float:
    s = plan.settings
    h = heldout_reconstruction(
        obs, list(s["train"]), test, s["q"], generator=torch.Generator().manual_seed(s["q"]), **FIT
    )
    return float(h.gplvm_logrmse.median()) / plan.predicted_error


def test_achieved_heldout_median_within_1_5x_of_predicted(planned):
    """The plan predicts the median held-out log-RMSE (per-material errors are heavy-tailed:
    the mean of 40 held-out materials was 2.3-11x their median in trials, set by a few); achieved: the
    median over the 80 held-out materials, scored by the same statistic."""
    obs, test, _, plan = planned
    assert plan.metric.startswith("median")
    ratio = _achieved_ratio(obs, test, plan)
    assert 1 / 1.5 <= ratio <= 1.5, f"achieved / predicted = {ratio:.3f}"


@pytest.mark.parametrize("seed", range(1, 8))
def test_prediction_holds_for_other_pool_orders(family, seed):
    """The same check for other seeded orders of the pool (other validation sets and ladders):
    some plan a size the pilots measured (n = 17, its level cross-fitted over all 40 pool
    materials), others the whole pool (n = 34, beyond the pilots), whose prediction must be a
    measurement at that size -- every pool material scored by a k-fold fit of size 34 -- not the
    power law's extrapolation (which said 0.0071 where 0.0037 was reached) nor a few folds' (18
    scores gave 1.86x on order 3)."""
    obs, test, pool = family
    plan = plan_manifold(obs, pool, error=0.01, generator=torch.Generator().manual_seed(seed), **FIT)
    if plan.settings["n"] == len(pool) - 6:
        assert "n = 34 measured on all 40 pool materials by 7 fits" in plan.metric
    ratio = _achieved_ratio(obs, test, plan)
    assert 1 / 1.5 <= ratio <= 1.5, (
        f"seed {seed}: achieved / predicted = {ratio:.3f} ({plan.settings['q']}, {plan.settings['n']})"
    )


def test_regression_estimate_corrects_by_the_materials_drawn():
    """Scores at the large size proportional to the small size's (slope 1): the estimate is
    the pool's level times the ratio; scores falling where the small size's rise (slope < 0,
    clipped to 0): their plain median; a slope above 1 is clipped to 1."""
    small = torch.tensor([0.01, 0.02, 0.04, 0.08, 0.16])
    e, beta = _regression_estimate(small / 4, small, 0.08, torch.median)
    assert beta == pytest.approx(1.0) and e == pytest.approx(0.02)
    falling = torch.tensor([0.005, 0.004, 0.003, 0.002, 0.001])
    e, beta = _regression_estimate(falling, small, 0.08, torch.median)
    assert beta == 0.0 and e == pytest.approx(0.003)
    e, beta = _regression_estimate(small**2, small, 0.08, torch.median)
    assert beta == 1.0 and e == pytest.approx(0.04**2 * 2)


def test_crossfit_whole_pool_scores_every_material_once_with_models_of_the_plans_size(monkeypatch):
    """k-fold at n = |R|: fold 0 is the plan's own model (trained on R, scoring V); every other
    fold trains on |R| pool materials that exclude what it scores; with folds=None every pool
    material is scored exactly once (a short last chunk included); with folds=k, k fits score
    only eligible materials."""
    calls = []

    def fake(obs, train, held, q, **kw):
        calls.append((list(train), list(held)))
        return SimpleNamespace(gplvm_logrmse=torch.ones(len(held)))

    monkeypatch.setattr(planner_manifold, "heldout_reconstruction", fake)
    val, ladder = [f"v{i}" for i in range(6)], [f"r{i}" for i in range(34)]
    names, scores, fits = _crossfit_whole_pool(None, val, ladder, 2, None, set(), {})
    assert sorted(names) == sorted(val + ladder) and scores.shape == (40,) and fits == len(calls) == 7
    assert calls[0] == (ladder, val)
    for train, held in calls:
        assert len(train) == 34 and not set(train) & set(held) and set(train) | set(held) <= set(val + ladder)
    calls.clear()
    eligible = set(ladder[17:])
    names, _, fits = _crossfit_whole_pool(None, val, ladder, 2, 3, eligible, {})
    assert fits == 3 and names[:6] == val and set(names[6:]) <= eligible and len(names) == 18


def test_bootstrap_interval_brackets_the_statistic():
    scores = torch.logspace(-3, -1, 41, dtype=torch.float64)
    lo, hi = _bootstrap_interval(scores, torch.median)
    assert lo < float(scores.median()) < hi and (lo, hi) == _bootstrap_interval(scores, torch.median)
    lo, hi = _bootstrap_interval(scores, torch.mean)
    assert lo < float(scores.mean()) < hi


def test_manifold_plan_needs_enough_materials(planned):
    obs, _, pool, _ = planned
    with pytest.raises(ValueRangeError):
        plan_manifold(obs, pool[:10], error=0.02)
    with pytest.raises(ValueRangeError):
        plan_manifold(obs, pool, error=0.02, statistic="max")
    with pytest.raises(ValueRangeError):
        plan_manifold(obs, pool, error=0.02, validate_folds=-1)
