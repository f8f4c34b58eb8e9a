"""The GI-editing planner: bands from projection errors, the pilot's per-bounce
images from the record alone, and the plan's predicted error against the achieved one."""

from __future__ import annotations

import pytest
import torch
from typer.testing import CliRunner

from torch_brdf.cli import app
from torch_brdf.errors import SceneError, ValueRangeError
from torch_brdf.metrics import relative_rmse
from torch_brdf.planner import (
    GIPlan,
    choose_bands,
    pilot_images,
    plan_from_pilots,
    plan_polynomial,
    planned_bases,
    precompute_planned,
)
from torch_brdf.planner.gi import MIN_SPP, _error_at, allocate_spp, spp_levels, with_fixed
from torch_brdf.records.polynomial import ObjectBasis, PolynomialTensors, Series
from torch_brdf.render.polynomial import PolynomialRenderer, emitter_mask
from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial, spp_map_of

GLOSSY = {"type": "blinn_phong", "kd": 0.25, "ks": 0.6, "exponent": 100.0}


def _materials(scene):
    return {o.name: scene.materials[o.material] for o in scene.objects if o.editable}


def test_lambert_takes_one_band_and_glossy_the_fewest_that_reach_the_target():
    assert choose_bands({"type": "lambert", "albedo": 0.5}, 1e-9) == (1, 0.0)
    J, e = choose_bands(GLOSSY, 0.06)
    assert e <= 0.06 and J > 1
    assert _error_at(GLOSSY, J // 2) > 0.06  # one power of two fewer would not do
    assert choose_bands(GLOSSY, 10.0)[0] == 1


def test_planned_bases_fix_the_objects_not_edited():
    sc = cornell_box_glossy(8)
    bases, errors, fixed = planned_bases(sc, 0.2, edit=["back", "left"])
    names = [o.name for o in sc.objects]
    assert set(errors) == {"back", "left"} and errors["left"] == 0.0
    assert bases[names.index("left")].J == 1 and bases[names.index("back")].J > 1
    assert set(fixed) == {o.name for o in sc.objects if o.editable} - {"back", "left"}
    assert all(bases[names.index(n)] is None for n in fixed)
    with pytest.raises(SceneError):
        planned_bases(sc, 0.2, edit=["nope"])


def test_pilot_images_equal_the_renderer_per_bounce():
    """The planner's evaluation from the record (below the render layer) is the renderer's sum."""
    sc = cornell_box_glossy(10)
    bases = [
        None if o.name == "light" else ObjectBasis(J=8 if o.name == "back" else 1, spacing="lobe:100")
        for o in sc.objects
    ]
    T = precompute_polynomial(sc, PolynomialSettings(Series((8, 1, 1)), spp=4, bases=bases), seed=3, progress=False)
    mats = _materials(sc)
    ours = pilot_images(T, mats)
    R = PolynomialRenderer(T, mats, dtype=torch.float64)
    theirs = torch.stack(R.evaluate(per_bounce=True))
    assert ours.shape == theirs.shape == (4, 10, 10, 3)
    # the renderer projects with project's default quadrature, the planner with a coarser one
    assert torch.allclose(ours, theirs, rtol=2e-3, atol=1e-6 * float(theirs.abs().max()))


def test_plan_needs_a_budget_and_two_pilots():
    sc = cornell_box_glossy(8)
    with pytest.raises(ValueRangeError):
        plan_from_pilots(sc, [], {}, (), [], error=None, seconds=None)
    with pytest.raises(ValueRangeError):
        plan_from_pilots(sc, [], {}, (), [], error=0.1)
    with pytest.raises(ValueRangeError):
        plan_polynomial(sc, error=0.1, pilot_runs=1)
    with pytest.raises(ValueRangeError):
        precompute_planned(sc, plan="manual", error=0.1, progress=False)


def test_plan_shows_progress_by_default(monkeypatch, capsys):
    # the pilots are the planner's long step: a bar per pilot like any precompute (was silent)
    monkeypatch.setenv("TORCH_BRDF_PROGRESS", "1")
    plan_polynomial(cornell_box_glossy(8), error=0.3, pilot_spp=1, pilot_bounces=2, max_light_samples=1)
    assert capsys.readouterr().err.count("precompute cornell_box_glossy") >= 4


@pytest.fixture(scope="module")
def planned():
    """Plan the 24-px glossy Cornell box for 0.2, carry it out, and converge the same model:
    6 bounces, 64 bands on the back wall, 128 spp (its own noise is ~0.05, which adds ~3% to
    an error of 0.2 in quadrature)."""
    sc = cornell_box_glossy(24)
    plan = plan_polynomial(sc, error=0.2, seed=0)
    T = precompute_planned(sc, plan=plan, seed=1, progress=False)
    ref_bases = [None if b is None else ObjectBasis(J=64, spacing=b.spacing) if b.J > 1 else b for b in plan.bases]
    R = precompute_polynomial(
        sc, PolynomialSettings(Series((64,) + (1,) * 5), spp=128, bases=ref_bases), seed=99, progress=False
    )
    mats = _materials(sc)
    img = PolynomialRenderer(T, mats, dtype=torch.float64)()
    ref = PolynomialRenderer(R, mats, dtype=torch.float64)()
    return sc, plan, T, relative_rmse(img, ref, emitter_mask(T))


def test_achieved_error_within_1_5x_of_predicted(planned):
    _, plan, _, achieved = planned
    assert isinstance(plan, GIPlan)
    ratio = achieved / plan.predicted_error
    assert 1 / 1.5 <= ratio <= 1.5, f"achieved {achieved:.4f}, predicted {plan.predicted_error:.4f}"


def test_plan_models_only_what_the_scene_requires(planned):
    sc, plan, T, _ = planned
    names = list(plan.object_names)
    for o in sc.objects:
        b = plan.bases[names.index(o.name)]
        if sc.materials[o.material]["type"] == "lambert" and o.editable:
            assert b.J == 1
    assert plan.bases[names.index("back")].J > 1
    assert not plan.series.two_level  # a flat glossy wall cannot light itself
    assert plan.glossy_to_glossy == 0.0
    assert 1 < plan.series.bounces < 8 and plan.spp >= 1
    assert plan.series.bounces <= plan.needed_bounces  # never more bounces than the light needs
    assert plan.predicted_error <= 0.2 * 1.001
    assert T.series == plan.series and "predicted error" in T.meta["plan"]
    # adaptive sampling: the record carries the plan's map; pixels that the budget does not
    # count (they see the light) get the least spp, the glossy wall more than the average
    assert torch.equal(spp_map_of(T), plan.spp_map) and T.meta["spp"] == pytest.approx(plan.spp)
    lit = ~emitter_mask(T)
    assert int(plan.spp_map[lit].max()) == MIN_SPP < int(plan.spp_map.max())
    back = torch.zeros(24 * 24, dtype=torch.bool)
    for b in T.blocks:
        if b.bounce == 1 and T.object_names[b.object_id] == "back":
            back[b.pixels] = True
    assert float(plan.spp_map.reshape(-1)[back].double().mean()) > plan.spp
    text = str(plan)
    assert "back: " in text and "predicted cost" in text and f"adaptive spp {plan.spp:.1f}" in text


def test_time_budget_lowers_spp_and_raises_the_predicted_error(planned):
    sc, plan, _, _ = planned
    # the pilots of this call are the fixture's (same seed), so only the budget differs
    fast = plan_polynomial(sc, error=0.2, seconds=plan.predicted_seconds / 4, seed=0)
    assert fast.spp < plan.spp and fast.predicted_error > plan.predicted_error


def test_cli_precompute_error(tmp_path):
    out = tmp_path / "t.npz"
    res = CliRunner().invoke(
        app, ["precompute", "cornell_box_glossy", "--resolution", "8", "--error", "0.3", "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    T = PolynomialTensors.load(out)
    assert T.bases[[*T.object_names].index("back")].J > 1 and T.bases[[*T.object_names].index("left")].J == 1


def test_allocation_follows_sigma_over_sqrt_cost_and_meets_the_noise():
    """n_i ~ sigma_i / sqrt(c_i) (Lagrange) on the level grid, the least such map for the noise."""
    var = torch.tensor([[16.0, 16.0, 1.0, 0.0]], dtype=torch.float64)
    cost = torch.tensor([[1.0, 4.0, 1.0, 1.0]], dtype=torch.float64)
    n = allocate_spp(var, var.sqrt(), cost, noise=0.5)
    assert float((var / n).sum()) <= 0.5
    assert n[0, 0] > n[0, 1] > n[0, 2] >= n[0, 3] == MIN_SPP  # sigma 4 at cost 1 > at cost 4 > sigma 1
    # one level less anywhere it matters breaks the noise (the least map on the grid)
    smaller = spp_levels(n.double() / 1.5)
    assert float((var / smaller).sum()) > 0.5
    # a cost budget: the largest map whose mean cost fits
    m = allocate_spp(var, var.sqrt(), cost, mean_cost=20.0)
    assert float((cost * m).sum() / cost.sum()) <= 20.0 < float((cost * spp_levels(m * 1.5)).sum() / cost.sum())
    assert torch.equal(spp_levels(torch.tensor([0.0, 4.0, 4.1, 5.6, 6.0])), torch.tensor([4, 4, 6, 6, 8]))


def test_uniform_plan_on_request(planned):
    sc, plan, _, _ = planned
    flat = plan_polynomial(sc, error=0.2, seed=0, adaptive=False)
    assert flat.spp_map is None and isinstance(flat.spp, int) and flat.settings().spp == flat.spp
    assert flat.series == plan.series  # the same pilots, bands and bounces; only the spp differ


def test_a_sun_lit_scene_splits_its_light_samples():
    """teatray's noise is almost all the eye vertex's next-event estimate (a sky with a sun):
    the plan takes several light samples there, and the record carries them out."""
    from torch_brdf.scene.builtin import teatray

    sc = teatray(12)
    plan = plan_polynomial(sc, error=0.1, seed=0)  # (at 0.3 the least spp, 4, already does)
    assert plan.eye_light_share > 0.5 and plan.light_samples > 1
    assert f"{plan.light_samples} light samples per eye vertex" in str(plan)
    one = plan_polynomial(sc, error=0.1, seed=0, max_light_samples=1)
    assert one.light_samples == 1 and one.eye_light_share == 0.0
    T = precompute_planned(sc, PolynomialSettings(guides=False), plan=plan, seed=1, progress=False)
    assert T.meta["light_samples"] == plan.light_samples


def test_env_lit_achieved_error_within_1_5x_of_predicted():
    """teatray (sky with a sun; adaptive spp and split light samples) at 24 px for 0.2, against
    the converged model: 6 bounces, 64 bands on the tray, 128 spp with 16 light samples per eye
    vertex (its own noise ~0.04 adds ~2% to an error of 0.2 in quadrature)."""
    from torch_brdf.scene.builtin import teatray

    sc = teatray(24)
    plan = plan_polynomial(sc, error=0.2, seed=0)
    T = precompute_planned(sc, PolynomialSettings(guides=False), plan=plan, seed=1, progress=False)
    ref_bases = [None if b is None else ObjectBasis(J=64, spacing=b.spacing) if b.J > 1 else b for b in plan.bases]
    R = precompute_polynomial(
        with_fixed(sc, plan.fixed),
        PolynomialSettings(Series((64,) + (1,) * 5), spp=128, bases=ref_bases, light_samples=16, guides=False),
        seed=99,
        progress=False,
    )
    mats = _materials(sc)
    img = PolynomialRenderer(T, mats, dtype=torch.float64)()
    ref = PolynomialRenderer(R, mats, dtype=torch.float64)()
    achieved = relative_rmse(img, ref, emitter_mask(T))
    ratio = achieved / plan.predicted_error
    assert 1 / 1.5 <= ratio <= 1.5, f"achieved {achieved:.4f}, predicted {plan.predicted_error:.4f}"
