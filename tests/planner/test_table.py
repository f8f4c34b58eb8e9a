"""The shared choice of the capability planners: cheapest option within the error, most
accurate within the time, the cost/error front, the power-law fit."""

from __future__ import annotations

import math

import pytest

from torch_brdf.errors import ValueRangeError
from torch_brdf.planner.table import Option, Plan, choose, pareto, power_law


def _opt(k: int, e: float, s: float) -> Option:
    return Option((("k", k),), e, s, (("noise", e),))


OPTIONS = [_opt(1, 0.3, 1.0), _opt(2, 0.1, 2.0), _opt(3, 0.05, 4.0), _opt(4, 0.2, 5.0)]


def test_choose_cheapest_within_error_and_most_accurate_within_time():
    assert choose(OPTIONS, 0.15, None).as_dict() == {"k": 2}
    assert choose(OPTIONS, 0.01, None).as_dict() == {"k": 3}  # none reaches: the most accurate
    assert choose(OPTIONS, None, 3.0).as_dict() == {"k": 2}
    assert choose(OPTIONS, 0.06, 3.0).as_dict() == {"k": 2}  # the time wins over the error
    assert choose(OPTIONS, None, 0.5).as_dict() == {"k": 1}  # nothing in time: the cheapest
    with pytest.raises(ValueRangeError):
        choose(OPTIONS, None, None)
    with pytest.raises(ValueRangeError):
        choose(OPTIONS, -1.0, None)


def test_pareto_front_drops_dominated_options():
    assert [o.as_dict()["k"] for o in pareto(OPTIONS)] == [1, 2, 3]


def test_power_law_recovers_its_parameters():
    x = [4.0, 8.0, 16.0, 32.0]
    a, p = power_law(x, [3.0 * v**-0.5 for v in x])
    assert a == pytest.approx(3.0) and p == pytest.approx(0.5)
    with pytest.raises(ValueRangeError):
        power_law([2.0, 2.0], [1.0, 1.0])


def test_plan_prints_choice_cost_error_and_psnr():
    plan = Plan("relighting", "RMSE / peak", 0.01, None, OPTIONS[2], tuple(OPTIONS), 0.5, psnr=True)
    text = str(plan)
    assert "k 3" in text and "predicted cost 4 s" in text and f"{-20 * math.log10(0.05):.2f} dB" in text
    assert "* k 3" in text and "k 4" not in text  # the dominated option is left out
    assert plan.settings == {"k": 3} and plan.predicted_error == 0.05


def test_plan_prints_the_interval_of_a_measured_option():
    chosen = Option((("q", 2),), 0.008, 3.0, interval=(0.006, 0.011))
    text = str(Plan("manifold", "median held-out log-RMSE", 0.01, None, chosen, (chosen,), 1.0))
    assert "predicted error 0.008 (median held-out log-RMSE); interval 0.006 to 0.011" in text
    assert "interval" not in str(Plan("relighting", "RMSE", 0.1, None, OPTIONS[1], tuple(OPTIONS), 0.5))
