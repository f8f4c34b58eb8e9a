"""The inverse-design planner: light samples, SRBF count and cut tolerance from
pilots; its predicted error against the achieved one on a small teapot view."""

from __future__ import annotations

import math

import pytest
import torch

from torch_brdf.errors import ValueRangeError
from torch_brdf.inverse import CutOptions, LightSamples, cosine_visibility, object_pixels, transfer_functions
from torch_brdf.inverse.strokes import StrokeTarget
from torch_brdf.planner.inverse import _basis, design_image, plan_inverse
from torch_brdf.planner.table import Plan
from torch_brdf.scene import teatray

KD = 0.3


def highlight_target(scene, px) -> StrokeTarget:
    """The diffuse-only image brightened along a horizontal band of the teapot (one stroke)."""
    ls = LightSamples.from_environment(scene.environment, 64, torch.Generator().manual_seed(1))
    rec = transfer_functions(px, ls, cosine_visibility(scene, px, ls), f0=0.9)
    c = torch.zeros(rec.values.shape[1], 3, dtype=torch.float64)
    c[-1] = KD
    before = rec.pixel_values(c)
    y = px.position[:, 1]
    w = torch.exp(-(((y - y.median()) / 0.1) ** 2))
    return StrokeTarget(before + 0.5 * w[:, None] * before.max(), torch.ones(px.count, dtype=torch.float64), w > 0.1)


def _design(scene, px, target, S, n, tol, seed):
    ls = LightSamples.from_environment(scene.environment, S, torch.Generator().manual_seed(seed))
    vis = cosine_visibility(scene, px, ls)
    cuts = None if tol == 0 else CutOptions(tolerance=tol)
    return design_image(transfer_functions(px, ls, vis, basis=_basis(n), f0=0.9, cuts=cuts), target, n, KD)


@pytest.fixture(scope="module")
def planned():
    scene = teatray((40, 30))
    px = object_pixels(scene, "teapot")
    target = highlight_target(scene, px)
    plan = plan_inverse(
        scene,
        px,
        scene.environment,
        target,
        error=0.06,
        kd=KD,
        f0=0.9,
        light_samples=(32, 64, 128, 256, 512),
        hemicube=(5, 7),
        tolerances=(0.0, 0.2),
        pilot_samples=64,
        generator=torch.Generator().manual_seed(0),
    )
    return scene, px, target, plan


def test_plan_prints_its_choice_and_meets_the_budget(planned):
    _, _, _, plan = planned
    assert isinstance(plan, Plan)
    s = plan.settings
    assert set(s) == {"light_samples", "J", "hemicube", "cut_tolerance"} and s["J"] == 3 * s["hemicube"] ** 2
    assert plan.predicted_error <= 0.06
    # the cheapest: no cheaper candidate is predicted to reach the budget
    assert all(o.predicted_error > 0.06 for o in plan.options if o.predicted_seconds < plan.predicted_seconds)
    text = str(plan)
    assert f"light_samples {s['light_samples']}" in text and "predicted cost" in text and "noise" in text


def test_achieved_error_within_1_5x_of_predicted(planned):
    """The prediction is the expected error over light-sample seeds (one run scatters around
    it: the design's noise lives in a few hundred coefficients), so the achieved error is the
    RMS over three seeds, against the design of a dense 2048-sample precomputation with 147 lobes."""
    scene, px, target, plan = planned
    s = plan.settings
    ref = _design(scene, px, target, 2048, 7, 0.0, 99)
    errs = [
        float((_design(scene, px, target, s["light_samples"], s["hemicube"], s["cut_tolerance"], seed) - ref).norm())
        / float(ref.norm())
        for seed in (11, 12, 13)
    ]
    achieved = math.sqrt(sum(e * e for e in errs) / len(errs))
    ratio = achieved / plan.predicted_error
    assert 1 / 1.5 <= ratio <= 1.5, f"achieved {achieved:.4f} ({errs}), predicted {plan.predicted_error:.4f}"


def test_inverse_plan_checks_its_inputs(planned):
    scene, px, target, _ = planned
    with pytest.raises(ValueRangeError):
        plan_inverse(scene, px, scene.environment, target, error=0.1, light_samples=(100,))
    with pytest.raises(ValueRangeError):
        plan_inverse(scene, px, scene.environment, target, error=0.1, pilot_sets=1)
