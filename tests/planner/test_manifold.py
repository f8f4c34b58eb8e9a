"""The manifold planner (issue #17): q and the training materials from validation pilots; its
predicted median held-out error against the achieved one on the analytic family (no data
needed), for three orders of the pool."""

from __future__ import annotations

import pytest
import torch

from torch_brdf.errors import ValueRangeError
from torch_brdf.manifold import analytic_observations, heldout_reconstruction
from torch_brdf.manifold.data import MERLGrid
from torch_brdf.planner.manifold import _regression_estimate, plan_manifold

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


@pytest.mark.parametrize(
    "seed",
    [
        1,
        2,
        pytest.param(
            3,
            marks=pytest.mark.xfail(
                reason="issue #17 open: order 3 plans n = |R|, predicted from 18 scores of 3 validation folds; "
                "1.39x before the GPLVM fit's numpy objective (#20), 1.86x after (a rounding-level change of a "
                "multimodal fit's path moves it): the estimate is not robust enough yet",
                strict=False,
            ),
        ),
    ],
)
def test_prediction_holds_for_other_pool_orders(family, seed):
    """The same check for other seeded orders of the pool (other validation sets and ladders).
    Orders 0-2 plan n = 17 (a measured size, its level cross-fitted); order 3 plans the whole
    pool (n = 34, beyond the pilots), so its prediction must be the validation folds'
    measurement, not the power law's extrapolation (which said 0.0071 where 0.0037 was reached)."""
    obs, test, pool = family
    plan = plan_manifold(obs, pool, error=0.01, generator=torch.Generator().manual_seed(seed), **FIT)
    if plan.settings["n"] == len(pool) - 6:
        assert "n = 34 measured on 18 of them" in plan.metric
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


def test_manifold_plan_needs_enough_materials(planned):
    obs, _, pool, _ = planned
    with pytest.raises(ValueRangeError):
        plan_manifold(obs, pool[:10], error=0.02)
    with pytest.raises(ValueRangeError):
        plan_manifold(obs, pool, error=0.02, statistic="max")
