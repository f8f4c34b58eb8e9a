"""The metrics module: known values, masks, dtypes and bad input (the two tests moved here from
tests/render/test_triple.py and tests/manifold/test_data.py keep their assertions)."""

from __future__ import annotations

import math

import pytest
import torch

from torch_brdf.errors import ShapeError, ValueRangeError
from torch_brdf.metrics import cosine_weighted_rmse, hdr_flip, log_relative_rmse, psnr, relative_l1, relative_rmse

F64 = torch.float64


def _pair(gen, shape=(5, 6, 3)):
    ref = torch.rand(shape, generator=gen, dtype=F64) + 0.1
    return ref + 0.05 * torch.randn(shape, generator=gen, dtype=F64), ref


def test_psnr_values():
    a = torch.zeros(4, 4, 3)
    b = torch.ones(4, 4, 3)
    assert psnr(b, b) == math.inf
    assert psnr(a + 0.1, b * 1.0, peak=1.0) == pytest.approx(10 * math.log10(1 / 0.81))
    with pytest.raises(ShapeError):
        psnr(a, b[:2])


def test_log_relative_rmse_known_values():
    c = torch.tensor([0.5, 1.0, 0.25], dtype=torch.float64)
    true = torch.tensor([1.0, 2.0, 3.0, 0.5, 0.2, 0.1, 4.0, 4.0, 4.0], dtype=torch.float64)
    assert float(log_relative_rmse(true, true, c)) == 0.0
    # eps -> 0: doubling every value gives exactly log 2
    assert abs(float(log_relative_rmse(2 * true, true, c, eps=1e-300)) - math.log(2)) < 1e-12
    # the per-bin reference cancels in the difference
    ref = torch.rand(9, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    a = log_relative_rmse(1.3 * true, true, c, reference=ref)
    assert abs(float(a) - float(log_relative_rmse(1.3 * true, true, c))) < 1e-12
    # negative interpolant values are clamped at 0 inside the log
    neg = true.clone()
    neg[0] = -5.0
    assert math.isfinite(float(log_relative_rmse(neg, true, c)))
    cw = cosine_weighted_rmse(true + 1.0, true, c)
    assert abs(float(cw) - float(c.repeat(3).pow(2).mean().sqrt())) < 1e-12
    with pytest.raises(ShapeError):
        log_relative_rmse(true, true, torch.ones(4))


def test_relative_errors_known_values():
    ref = torch.tensor([[[1.0, 2.0], [2.0, 4.0]]], dtype=F64)  # (1, 2, 2): sum R^2 = 25, sum |R| = 9
    err = torch.tensor([[[3.0, 0.0], [0.0, -4.0]]], dtype=F64)  # sum e^2 = 25, sum |e| = 7
    assert relative_rmse(ref + err, ref) == 1.0
    assert relative_l1(ref + err, ref) == pytest.approx(7 / 9, rel=1e-15)
    assert relative_rmse(1.5 * ref, ref) == pytest.approx(0.5, rel=1e-15)
    assert relative_rmse(ref, ref) == 0.0 and relative_l1(ref, ref) == 0.0


def test_relative_rmse_is_the_ratio_of_norms_and_of_rms(gen):
    """The three spellings it replaced: sqrt(sum/sum), |a-b|/|b| and rms(a-b)/rms(b)."""
    img, ref = _pair(gen)
    want = float((img - ref).norm() / ref.norm())
    assert relative_rmse(img, ref) == pytest.approx(want, rel=1e-12)
    rms = float((img - ref).pow(2).mean().sqrt() / ref.pow(2).mean().sqrt())
    assert relative_rmse(img, ref) == pytest.approx(rms, rel=1e-12)


@pytest.mark.parametrize("metric", [relative_rmse, relative_l1, psnr])
def test_mask_counts_only_its_pixels(metric, gen):
    img, ref = _pair(gen)
    mask = torch.rand(img.shape[:2], generator=gen) < 0.5
    mask[0, 0] = True
    wild = img.clone()
    wild[~mask] = 1e6  # outside the mask: must not matter
    want = metric(img[mask], ref[mask])  # (K, C) rows of the counted pixels
    assert metric(wild, ref, mask) == pytest.approx(want, rel=1e-12)
    assert metric(wild, ref, mask) != pytest.approx(metric(wild, ref), rel=1e-3)


def test_psnr_peak_defaults_to_the_counted_reference_maximum(gen):
    img, ref = _pair(gen)
    mask = torch.zeros(img.shape[:2], dtype=torch.bool)
    mask[1:3] = True
    ref_out = ref.clone()
    ref_out[~mask] = 50.0  # a bright pixel outside the mask does not set the peak
    assert psnr(img, ref_out, mask) == pytest.approx(psnr(img, ref_out, mask, peak=float(ref[mask].max())))
    mse = float(((img - ref) ** 2).mean())
    assert psnr(img, ref, peak=2.0) == pytest.approx(10 * math.log10(4.0 / mse), rel=1e-12)


@pytest.mark.parametrize("metric", [relative_rmse, relative_l1, psnr])
@pytest.mark.parametrize("dtype", [torch.float16, torch.float32])
def test_image_metrics_compute_in_float64_whatever_the_dtype(metric, dtype, gen):
    """Inputs exactly representable in ``dtype`` give the float64 result; grads are detached."""
    img, ref = (x.to(dtype) for x in _pair(gen))
    want = metric(img.double(), ref.double())
    got = metric(img.requires_grad_(), ref)
    assert isinstance(got, float) and got == want


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_brdf_row_metrics_are_per_row_float64(dtype, gen):
    c = torch.rand(4, generator=gen, dtype=F64).clamp_min(0.01)
    true = torch.rand(3, 12, generator=gen, dtype=F64).to(dtype)
    pred = (true.double() * 1.2 + 0.01).to(dtype)
    for metric in (log_relative_rmse, cosine_weighted_rmse):
        rows = metric(pred, true, c)
        assert rows.shape == (3,) and rows.dtype == F64
        loop = torch.stack([metric(pred[i], true[i], c) for i in range(3)])
        torch.testing.assert_close(rows, loop, rtol=1e-12, atol=0)
        # the cosine map given per bin (B,) or per column (3 B,) is the same
        torch.testing.assert_close(rows, metric(pred, true, c.repeat(3)), rtol=0, atol=0)


def test_bad_input_is_refused():
    a = torch.ones(2, 3, 3)
    with pytest.raises(ValueRangeError):
        relative_rmse(a, torch.zeros_like(a))
    with pytest.raises(ValueRangeError):
        relative_l1(a, torch.zeros_like(a))
    mask = torch.zeros(2, 3, dtype=torch.bool)
    mask[0] = True
    with pytest.raises(ValueRangeError):  # zero where compared, not elsewhere
        relative_rmse(a, torch.cat((torch.zeros(1, 3, 3), a[1:])), mask)
    for metric in (relative_rmse, relative_l1, psnr):
        with pytest.raises(ShapeError):
            metric(a, a[:1])
        with pytest.raises(ShapeError):  # a mask of another shape
            metric(a, a, torch.ones(3, 2, dtype=torch.bool))
        with pytest.raises(ShapeError):  # a mask that is not boolean
            metric(a, a, torch.ones(2, 3))
    with pytest.raises(ShapeError):
        cosine_weighted_rmse(torch.ones(6), torch.ones(6), torch.ones(4))


def test_hdr_flip_orders_errors(gen):
    pytest.importorskip("flip_evaluator")
    ref = torch.rand(32, 32, 3, generator=gen) * 4
    assert hdr_flip(ref, ref) == pytest.approx(0.0, abs=1e-6)
    small = ref * (1 + 0.05 * torch.randn(32, 32, 3, generator=gen)).clamp_min(0)
    big = ref * (1 + 0.5 * torch.randn(32, 32, 3, generator=gen)).clamp_min(0)
    assert 0 < hdr_flip(small, ref) < hdr_flip(big, ref) <= 1
    m = torch.zeros(32, 32, dtype=torch.bool)
    m[:16] = True
    assert math.isfinite(hdr_flip(big, ref, m))
    with pytest.raises(ShapeError):
        hdr_flip(ref[:2], ref)
