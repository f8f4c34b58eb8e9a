"""The relighting planner: cubemap resolution, visibility bits and sampling rule from
pilots on a sample of the seen vertices; its predicted error against the error the planned
settings reach on every seen vertex (no data needed: the procedural bunny)."""

from __future__ import annotations

import math

import pytest
import torch

from torch_brdf.errors import ValueRangeError
from torch_brdf.planner.relight import RelightPilot, error_from_psnr, plan_from_relight_pilots
from torch_brdf.planner.relight_pilots import make_rule, plan_relighting, planned_renderer, shade_vertices
from torch_brdf.planner.table import Plan
from torch_brdf.render.triple import FixedRule, GenericRule, PhongRule
from torch_brdf.scene import bunny_relight
from torch_brdf.scene.gbuffer import trace_gbuffer

SMALL = {
    "resolutions": (16, 32),
    "visibility": ((1, 0), (2, 2), (4, 8)),
    "rules": ("fixed:1", "fixed:2", "appendix-a:1", "generic:1"),
    "pilot_vertices": 64,
    "brightest": 32,
}


@pytest.fixture(scope="module")
def planned():
    scene = bunny_relight((32, 24), plane_quads=4, use_data=False)
    plan = plan_relighting(scene, psnr=30, generator=torch.Generator().manual_seed(0), **SMALL)
    return scene, plan


@pytest.fixture(scope="module")
def reference(planned):
    """The converged radiance of every seen vertex: dense product, 32x32x6, 4x4 rays, 8 bits."""
    scene, _ = planned
    gb = trace_gbuffer(scene)
    ref, _ = shade_vertices(scene, gb.vertex_ids, gb.eye, 32, 4, 8, [None])
    return gb.vertex_ids, ref[None].to(torch.float64)


def _achieved(scene, plan: Plan, reference) -> float:
    """RMSE / peak of the planned settings carried out on the whole scene (the visibility record
    of every vertex, the renderer's own view and culling) against the reference."""
    ids, ref = reference
    r = planned_renderer(scene, plan, progress=False)
    view = r.view()
    assert torch.equal(view.vertex_ids, ids)
    rad, _ = r.shade(view, progress=False)
    return float(((rad.to(torch.float64) - ref) ** 2).mean().sqrt()) / float(ref.max())


def test_plan_prints_its_choice_and_meets_the_budget(planned):
    _, plan = planned
    s = plan.settings
    assert set(s) == {"cubemap", "supersample", "bits", "rule"}
    assert plan.predicted_error <= error_from_psnr(30)
    assert all(o.predicted_error > plan.error for o in plan.options if o.predicted_seconds < plan.predicted_seconds)
    text = str(plan)
    assert "dB" in text and f"cubemap {s['cubemap']}" in text and "precompute" in text and "frame" in text
    assert len(plan.options) == 2 * 3 * 4


@pytest.mark.parametrize("psnr", [30.0, 50.0])
def test_achieved_error_within_1_5x_of_predicted(planned, reference, psnr):
    """Both ways, for two targets that pick different settings from the same pilots."""
    scene, plan = planned
    plan = plan.for_budget(error=error_from_psnr(psnr))
    achieved = _achieved(scene, plan, reference)
    ratio = achieved / plan.predicted_error
    assert 1 / 1.5 <= ratio <= 1.5, f"{plan.settings}: achieved {achieved:.3g}, predicted {plan.predicted_error:.3g}"
    assert -20 * math.log10(achieved) >= psnr - 20 * math.log10(1.5)


def test_two_targets_choose_different_settings(planned):
    _, plan = planned
    a, b = (plan.for_budget(error=error_from_psnr(p)).settings for p in (30.0, 50.0))
    assert a != b


def test_make_rule_names():
    assert isinstance(make_rule("fixed:4"), FixedRule) and make_rule("fixed:4").level == 4
    rule = make_rule("appendix-a:2")
    assert isinstance(rule, PhongRule) and rule.angles == pytest.approx((math.pi / 4, math.pi / 2))
    assert make_rule("generic:10").linear == pytest.approx(0.1) and isinstance(make_rule("generic"), GenericRule)
    for bad in ("fixed:3", "phong:1", "generic:-1", "generic:x"):
        with pytest.raises(ValueRangeError):
            make_rule(bad)


def test_relight_plan_checks_its_inputs(planned):
    scene, _ = planned
    with pytest.raises(ValueRangeError):
        plan_relighting(scene, error=0.01, psnr=40)
    with pytest.raises(ValueRangeError):
        plan_relighting(scene, psnr=40, visibility=((2, 0),))
    with pytest.raises(ValueRangeError):
        plan_from_relight_pilots([RelightPilot(16, 1, 0, "fixed:1", 1e-4, 1.0, 0.1, 60.0)], peak=0.0, error=0.01)


def test_choice_from_pilots_is_the_cheapest_within_the_budget():
    pilots = [
        RelightPilot(16, 1, 0, "fixed:1", 0.04**2, 1.0, 0.01, 60.0),  # error 0.04, 2 s
        RelightPilot(16, 1, 0, "generic:1", 0.005**2, 1.0, 0.05, 60.0),  # 0.005, 6 s
        RelightPilot(32, 4, 8, "generic:1", 0.001**2, 20.0, 0.1, 200.0),  # 0.001, 30 s
    ]
    plan = plan_from_relight_pilots(pilots, peak=1.0, error=0.01)
    assert plan.settings["rule"] == "generic:1" and plan.settings["cubemap"] == 16
    assert plan.predicted_seconds == pytest.approx(1.0 + 100 * 0.05)
    assert plan.for_budget(error=0.0015).settings["cubemap"] == 32
    assert plan.for_budget(seconds=3.0).settings["rule"] == "fixed:1"
