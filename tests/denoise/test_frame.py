"""The frame denoiser keeps each object's mean and beats 16x the samples under any edits."""

from __future__ import annotations

import pytest
import torch

from torch_brdf.denoise import FrameDenoiser, glossy_objects, keep_region_means, oidn_available, region_mean_error
from torch_brdf.errors import NumericalError, ShapeError, ValueRangeError
from torch_brdf.render import PolynomialRenderer
from torch_brdf.report.benchmarks.denoise_edits import EDIT_CASES, edit_scene, mean_shift, run_edits
from torch_brdf.transport import PolynomialSettings, precompute_polynomial


def test_keep_region_means_is_exact_per_region():
    g = torch.Generator().manual_seed(0)
    noisy = torch.rand(8, 8, 3, generator=g, dtype=torch.float64)
    den = torch.rand(8, 8, 3, generator=g, dtype=torch.float64)
    regions = torch.randint(-1, 3, (8, 8), generator=g)
    out = keep_region_means(den, noisy, regions)
    for o in range(3):
        m = regions == o
        torch.testing.assert_close(out[m].sum(0), noisy[m].sum(0))
        ratio = out[m] / den[m]  # one scale per region and channel: the detail is the denoiser's
        torch.testing.assert_close(ratio, ratio[:1].expand_as(ratio))
    torch.testing.assert_close(out[regions < 0], noisy[regions < 0])
    with pytest.raises(ShapeError):
        keep_region_means(den, noisy, regions[:4])


def test_region_mean_error_is_the_residual_noise():
    noisy = torch.ones(4, 4, 3)
    noisy[0, 0] = 3.0  # residual 2 in each channel of one pixel of a 16-pixel region
    est = region_mean_error(torch.ones(4, 4, 3), noisy, torch.zeros(4, 4, dtype=torch.long))
    assert est[0] == pytest.approx(2.0 / 18.0)


@pytest.fixture(scope="module")
def small_record():
    scene = edit_scene(16, seed=3)
    T = precompute_polynomial(scene, PolynomialSettings("4,1", spp=2), seed=0, progress=False)
    return scene, T


def test_renderer_denoises_every_frame(small_record):
    scene, T = small_record
    mats = {o.name: scene.materials[o.material] for o in scene.objects}
    R = PolynomialRenderer(T, mats)
    R.set_material("glossy", EDIT_CASES["one"]["glossy"])
    noisy = R()
    R.denoise_frames("regression")
    out = R()
    assert not torch.equal(out, noisy)
    torch.testing.assert_close(out, FrameDenoiser(T.guides, "regression", glossy_objects(T))(noisy))
    regions = T.guides.object_id
    for o in range(3):  # the mean of every object region is the noisy frame's
        m = regions == o
        torch.testing.assert_close(out[m].sum(0), noisy[m].sum(0), rtol=1e-4, atol=1e-6)
    R.denoise_frames(None)
    torch.testing.assert_close(R(), noisy)


def test_bad_input_is_refused(small_record):
    _, T = small_record
    with pytest.raises(ValueRangeError, match="method"):
        FrameDenoiser(T.guides, "bilateral")
    with pytest.raises(ShapeError, match="frame of shape"):
        FrameDenoiser(T.guides, "linear")(torch.zeros(8, 8, 3))
    noisy = torch.rand(16, 16, 3, generator=torch.Generator().manual_seed(1))
    with pytest.raises(NumericalError, match="standard error"):  # 2 spp cannot pin a mean to 0.01 %
        FrameDenoiser(T.guides, "linear", mean_tolerance=1e-4)(noisy)


@pytest.fixture(scope="module")
def sweep():
    """Generated scene (glossy floor, diffuse and glossy spheres, sky with a soft sun), 32², 16 spp
    against 256 spp (16x) and a 1024-spp reference, under every edit case."""
    return run_edits(size=32, spp=16, series="8,1,1", ref=64, seed=0, basis=False)


@pytest.mark.parametrize("case", list(EDIT_CASES))
def test_denoiser_moves_no_object_mean(sweep, case):
    """Default material, one, two and all objects edited: every object region's mean is the noisy
    frame's (the unbiased estimate), while the plain denoiser moves some by more than 1 %."""
    r = sweep[case]
    assert r["mean_shift_added"]["frame"] <= 1e-5, r["mean_shift_added"]
    assert r["mean_shift"]["frame"] == pytest.approx(r["mean_shift"]["none"], abs=1e-5)


def test_plain_denoiser_moves_a_mean(sweep):
    """The statistic above can fail: without the correction the same denoiser moves a mean."""
    assert max(sweep[c]["mean_shift_added"]["frame_plain"] for c in EDIT_CASES) > 0.01


LIMIT = (
    "16 samples per pixel do not pin the glossy sphere's mean: the undenoised frame's own region mean is "
    "8-18 % off the reference (heavy-tailed samples; 256 spp: 0.5-1.4 %), and a denoiser that keeps the "
    "mean keeps that error"
)


@pytest.mark.parametrize("case", list(EDIT_CASES))
@pytest.mark.xfail(strict=True, reason=LIMIT)
def test_mean_within_one_percent_of_the_reference(sweep, case):
    r = sweep[case]
    assert r["mean_shift"]["frame"] <= 0.01, (r["mean_shift"], r["mean_error_estimate"])


@pytest.mark.skipif(not oidn_available(), reason="the figures are OIDN's (optional extra 'denoise')")
@pytest.mark.parametrize("case", list(EDIT_CASES))
def test_error_at_most_sixteen_times_the_samples(sweep, case):
    r = sweep[case]
    assert r["error_ratio"]["frame"] <= 1.0, r["error_ratio"]


def test_mean_shift_measures_a_shift():
    """The statistic the acceptance reads can fail: a 2 % brighter object is caught."""
    regions = torch.zeros(4, 4, dtype=torch.long)
    ref = torch.ones(4, 4, 3, dtype=torch.float64)
    assert mean_shift(ref * 1.02, ref, regions) == pytest.approx(0.02)
