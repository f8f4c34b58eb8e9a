"""Transfer functions against a brute-force render of the same BRDF with the same light samples."""

from __future__ import annotations

import pytest
import torch

from tests.conftest import RTOL
from tests.inverse.conftest import F0, KD, direct_render, true_coefficients
from torch_brdf.errors import SceneError, ShapeError, ValueRangeError
from torch_brdf.inverse import CutOptions, LightSamples, object_pixels, split_record, transfer_functions
from torch_brdf.metrics import relative_rmse
from torch_brdf.render.record import BasisImage


def _coeffs(c, kd=KD):
    return torch.cat((c[:, None].expand(-1, 3), torch.tensor(kd, dtype=torch.float64)[None]))


def test_record_layout(view):
    _, px, ls, _, rec = view
    assert isinstance(rec, BasisImage)
    assert rec.values.shape == (3, 148, px.count) and rec.values.dtype == torch.float64
    assert rec.basis == "srbf:147+diffuse"
    T, E = split_record(rec)
    assert bool((T >= 0).all()) and bool((E >= 0).all())
    assert rec.meta["light_samples"] == ls.count and rec.meta["f0"] == list(F0)


def test_equals_direct_render_of_the_brdf(view, target_render):
    """Same light samples, visibility and BRDF: the record reproduces the module's render to rounding."""
    rec, c, want = view[-1], true_coefficients(), target_render
    got = rec.pixel_values(_coeffs(c))
    torch.testing.assert_close(got, want, rtol=RTOL[torch.float64] * 1e-2, atol=1e-15)
    assert float(want.max()) > 0.05  # the highlights are really there


def test_diffuse_part_is_lambert(view):
    _, px, ls, vis, rec = view
    c = torch.zeros(147, dtype=torch.float64)
    torch.testing.assert_close(rec.pixel_values(_coeffs(c)), direct_render(px, ls, vis, c), rtol=1e-12, atol=1e-15)


def test_exact_cuts_equal_dense(view):
    _, px, ls, vis, rec = view
    cut = transfer_functions(px, ls, vis, f0=F0, cuts=CutOptions(0.0, 0.0))
    torch.testing.assert_close(cut.values, rec.values, rtol=1e-10, atol=1e-14)
    assert cut.meta["mean_cut_size"] <= ls.count


def test_cuts_error_shrinks_with_tolerance(view):
    _, px, ls, vis, rec = view
    errs, sizes = [], []
    for tol, ang in [(0.5, 20.0), (0.1, 4.0), (0.0, 0.0)]:
        cut = transfer_functions(px, ls, vis, f0=F0, cuts=CutOptions(tol, ang))
        errs.append(relative_rmse(cut.values, rec.values))
        sizes.append(cut.meta["mean_cut_size"])
    assert errs[0] >= errs[1] >= errs[2] and errs[2] < 1e-12 and errs[1] < 0.05
    assert sizes[0] <= sizes[1] <= sizes[2]


def test_seeded_samples_reproduce(view):
    scene = view[0]
    a = LightSamples.from_environment(scene.environment, 64, torch.Generator().manual_seed(3))
    b = LightSamples.from_environment(scene.environment, 64, torch.Generator().manual_seed(3))
    assert torch.equal(a.directions, b.directions) and torch.equal(a.weight, b.weight)


def test_bad_input(view):
    scene, px, ls, vis, _ = view
    with pytest.raises(ShapeError):
        transfer_functions(px, ls, vis[:, :5])
    with pytest.raises(ValueRangeError):
        transfer_functions(px, ls, vis * float("nan"))
    with pytest.raises(ValueRangeError):
        transfer_functions(px, ls, vis, f0=1.5)
    odd = LightSamples(ls.directions[:100], ls.weight[:100])
    with pytest.raises(ValueRangeError, match="power-of-two"):
        transfer_functions(px, odd, vis[:, :100], cuts=CutOptions())
    with pytest.raises(SceneError):
        object_pixels(scene, "no_such_object")
    with pytest.raises(ValueRangeError):
        LightSamples.from_environment(scene.environment, 0)
