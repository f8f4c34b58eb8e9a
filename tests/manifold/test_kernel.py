from __future__ import annotations

import math
import warnings

import pytest
import torch

from torch_brdf.errors import NumericalError, ShapeError, ValueRangeError
from torch_brdf.manifold.kernel import JitterWarning, cholesky_jitter, cross_kernel, kernel_matrix, se_kernel


def test_se_kernel_matches_loop(gen):
    x1 = torch.randn(5, 3, generator=gen, dtype=torch.float64)
    x2 = torch.randn(4, 3, generator=gen, dtype=torch.float64)
    k = se_kernel(x1, x2, 0.7)
    for i in range(5):
        for j in range(4):
            want = math.exp(-float(((x1[i] - x2[j]) ** 2).sum()) / (2 * 0.7**2))
            assert abs(float(k[i, j]) - want) < 1e-15


def test_cross_kernel_at_training_points_is_a_row_of_K(gen):
    x = torch.randn(6, 2, generator=gen, dtype=torch.float64)
    k = kernel_matrix(x, 1.0, 1e-3)
    assert torch.equal(cross_kernel(x, x, 1.0, 1e-3), k)
    # a point that is not a training latent gets no mu term
    off = cross_kernel(x[:1] + 1e-3, x, 1.0, 1e-3)
    assert abs(float(off[0, 0]) - math.exp(-(2e-6) / 2)) < 1e-15


def test_cholesky_no_jitter_when_pd(gen):
    x = torch.randn(8, 2, generator=gen, dtype=torch.float64) * 3
    k = kernel_matrix(x, 1.0, 1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        chol, jitter = cholesky_jitter(k)
    assert jitter == 0.0
    torch.testing.assert_close(chol @ chol.T, k, rtol=1e-12, atol=1e-12)


def test_cholesky_escalates_and_warns_on_duplicates():
    x = torch.zeros(4, 2, dtype=torch.float64)  # four identical latents, mu = 0: rank 1
    k = kernel_matrix(x, 1.0, 0.0)
    with pytest.warns(JitterWarning, match="jitter"):
        chol, jitter = cholesky_jitter(k, floor=1e-12, cap=1e-2)
    assert 1e-12 <= jitter <= 1e-2
    torch.testing.assert_close(chol @ chol.T, k + jitter * torch.eye(4, dtype=torch.float64), rtol=1e-10, atol=1e-12)


def test_cholesky_cap_and_nan():
    with pytest.raises(NumericalError, match="cap"):
        cholesky_jitter(-torch.eye(3, dtype=torch.float64), floor=1e-8, cap=1e-4)
    bad = torch.eye(3, dtype=torch.float64)
    bad[0, 1] = float("nan")
    with pytest.raises(ValueRangeError, match="non-finite"):
        cholesky_jitter(bad)
    with pytest.raises(ShapeError):
        cholesky_jitter(torch.ones(2, 3))
    with pytest.raises(ValueRangeError):
        se_kernel(torch.ones(2, 1), torch.ones(2, 1), lengthscale=0.0)
