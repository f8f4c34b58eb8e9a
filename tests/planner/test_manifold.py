"""The manifold planner (issue #17): q and the training materials from validation pilots; its
predicted held-out error against the achieved one on the analytic family (no data needed)."""

from __future__ import annotations

import pytest
import torch

from torch_brdf.errors import ValueRangeError
from torch_brdf.manifold import analytic_observations, heldout_reconstruction
from torch_brdf.manifold.data import MERLGrid
from torch_brdf.planner.manifold import plan_manifold

FIT = {"metric": "weighted", "max_iter": 100}


@pytest.fixture(scope="module")
def planned():
    obs, _ = analytic_observations(50, MERLGrid.strided(9, 9, 18), generator=torch.Generator().manual_seed(7))
    names = list(obs.names)
    test, pool = names[:10], names[10:]
    plan = plan_manifold(obs, pool, error=0.02, **FIT)
    return obs, test, pool, plan


def test_plan_trains_on_pool_materials_and_meets_the_budget(planned):
    _, test, pool, plan = planned
    s = plan.settings
    assert set(s["train"]) <= set(pool) and not set(s["train"]) & set(test) and len(s["train"]) == s["n"]
    assert plan.predicted_error <= 0.02
    assert all(o.predicted_error > 0.02 for o in plan.options if o.predicted_seconds < plan.predicted_seconds)
    assert f"q {s['q']}, n {s['n']}" in str(plan) and "predicted cost" in str(plan)


@pytest.mark.xfail(
    reason="known gap (#17, open): the planner predicts the held-out error from 6 validation "
    "materials and misses it beyond 1.5x (here predicted 0.0101, achieved 0.0168); a 4-fold "
    "cross-validated variant passed 1 of 4 pool orders (ratios 0.11-0.96), because per-material "
    "errors are heavy-tailed and 10 test materials are too few to estimate their mean",
    strict=False,
)
def test_achieved_heldout_error_within_1_5x_of_predicted(planned):
    obs, test, _, plan = planned
    s = plan.settings
    h = heldout_reconstruction(
        obs, list(s["train"]), test, s["q"], generator=torch.Generator().manual_seed(s["q"]), **FIT
    )
    achieved = float(h.gplvm_logrmse.mean())
    ratio = achieved / plan.predicted_error
    assert 1 / 1.5 <= ratio <= 1.5, f"achieved {achieved:.4f}, predicted {plan.predicted_error:.4f}"


def test_manifold_plan_needs_enough_materials(planned):
    obs, _, pool, _ = planned
    with pytest.raises(ValueRangeError):
        plan_manifold(obs, pool[:10], error=0.02)
