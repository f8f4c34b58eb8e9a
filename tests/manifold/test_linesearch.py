"""Our strong-Wolfe line search (replaces torch's private ``torch.optim.lbfgs._strong_wolfe``)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest
import torch

import torch_brdf
from torch_brdf.errors import ValueRangeError
from torch_brdf.manifold.gplvm import WARMUP_MU, fit_gplvm, gram, log_likelihood, pca_latents, small_matrix_mode
from torch_brdf.manifold.linesearch import strong_wolfe
from torch_brdf.records.fits import GPLVMFit

from .common import small_family


def _line(f, grad, x, p):
    """phi(t) = f(x + t p) with its slope, counting calls."""
    calls = []

    def phi(t):
        y = x + t * p
        calls.append(t)
        return float(f(y)), float(grad(y) @ p), y

    return phi, calls


def _rosenbrock(y):
    return (1 - y[0]) ** 2 + 100 * (y[1] - y[0] ** 2) ** 2


def _rosenbrock_grad(y):
    return torch.stack([-2 * (1 - y[0]) - 400 * y[0] * (y[1] - y[0] ** 2), 200 * (y[1] - y[0] ** 2)])


@pytest.mark.parametrize(
    ("x", "p", "step"),
    [
        ((-1.2, 1.0), None, 1.0),  # steepest descent: the unit step is far too long (zoom)
        ((-1.2, 1.0), None, 1e-5),  # far too short: expansion
        ((0.0, 0.0), (1.0, 0.0), 1.0),
        ((2.0, 2.0), None, 1e-3),
    ],
)
@pytest.mark.parametrize("c2", [0.9, 0.1])
def test_step_satisfies_the_strong_wolfe_conditions(x, p, step, c2):
    x = torch.tensor(x, dtype=torch.float64)
    p = -_rosenbrock_grad(x) if p is None else torch.tensor(p, dtype=torch.float64)
    phi, _ = _line(_rosenbrock, _rosenbrock_grad, x, p)
    f0, d0, _ = phi(0.0)
    res = strong_wolfe(phi, f0, d0, step, c2=c2)
    assert res.wolfe and res.step > 0
    assert res.value <= f0 + 1e-4 * res.step * d0
    assert abs(res.slope) <= c2 * abs(d0)
    assert res.value == pytest.approx(float(_rosenbrock(x + res.step * p)), rel=1e-12)
    torch.testing.assert_close(res.payload, x + res.step * p)


def test_quadratic_with_tight_curvature_lands_near_the_minimiser():
    # phi(t) = (t - 3)^2: the strong curvature condition with c2 = 0.01 pins t to 3 +- 0.03
    def phi(t):
        return (t - 3.0) ** 2, 2 * (t - 3.0), None

    res = strong_wolfe(phi, 9.0, -6.0, 1.0, c2=0.01)
    assert res.wolfe and abs(res.step - 3.0) <= 0.03 + 1e-12
    assert res.evaluations <= 6


def test_non_finite_values_shrink_the_step():
    # phi is only defined on t < 0.5 (e.g. a Cholesky that fails further out)
    def phi(t):
        if t >= 0.5:
            return math.inf, math.nan, None
        return (t - 0.4) ** 2, 2 * (t - 0.4), t

    res = strong_wolfe(phi, 0.16, -0.8, 1.0)
    assert 0 < res.step < 0.5 and math.isfinite(res.value) and res.payload == res.step
    assert res.value <= 0.16 + 1e-4 * res.step * -0.8


def test_no_decrease_returns_step_zero():
    # a slope that lies: phi rises immediately, every trial fails sufficient decrease
    def phi(t):
        return 1.0 + t, 1.0, t

    res = strong_wolfe(phi, 1.0, -1.0, 1.0, max_evaluations=10)
    assert res.step == 0.0 and not res.wolfe and res.payload is None and res.evaluations <= 10


def test_bad_arguments_raise():
    def phi(t):
        return t, 1.0, None

    with pytest.raises(ValueRangeError, match="negative slope"):
        strong_wolfe(phi, 0.0, 1.0)
    with pytest.raises(ValueRangeError, match="c1"):
        strong_wolfe(phi, 0.0, -1.0, c1=0.5, c2=0.4)
    with pytest.raises(ValueRangeError, match="step"):
        strong_wolfe(phi, 0.0, -1.0, step=0.0)


def test_package_uses_no_private_torch_optimiser_api():
    root = Path(torch_brdf.__file__).parent
    private = re.compile(r"torch\.optim\.lbfgs|_strong_wolfe")
    offenders = [p.name for p in root.rglob("*.py") if private.search(p.read_text(encoding="utf-8"))]
    assert offenders == []


def _torch_strong_wolfe(s, d, q, mu, budget, x0) -> float:
    """L after torch.optim.LBFGS(line_search_fn="strong_wolfe") on our log_likelihood (autograd)."""
    x = x0.clone().requires_grad_(True)
    opt = torch.optim.LBFGS([x], lr=1.0, max_iter=budget, line_search_fn="strong_wolfe", history_size=20)

    def closure():
        opt.zero_grad()
        loss = -log_likelihood(x, s, d, 1.0, mu) / (s.shape[0] * d)
        loss.backward()
        return loss

    with small_matrix_mode(s.shape[0]):  # one thread, as our fits (a 40 x 40 Cholesky on 2 threads is slow)
        opt.step(closure)
    return float(log_likelihood(x.detach(), s, d, 1.0, mu))


def test_mu_warmup_is_recorded_and_reaches_at_least_strong_wolfe_lbfgs(tmp_path):
    """At a tiny mu the PCA start is nearly singular; our fit (mu warm-up, then L-BFGS with our
    strong-Wolfe search) must end at least as high as torch.optim.LBFGS(strong_wolfe) on the same
    objective, start and iteration budget, and the warm-up is recorded in the fit's meta."""
    obs, _ = small_family(40, seed=3)
    s, d = gram(obs.z, obs.cosine_weights())
    mu, budget = 1e-10, 60
    fit = fit_gplvm(s, d, 2, mu=mu, max_iter=budget, generator=torch.Generator().manual_seed(0))
    assert fit.meta["warmup"]["mu"] == WARMUP_MU and fit.meta["warmup"]["iterations"] <= 12
    assert fit.iterations <= budget - 12
    fit.save(tmp_path / "fit.npz")  # the warm-up record survives the codec
    assert GPLVMFit.load(tmp_path / "fit.npz").meta["warmup"] == fit.meta["warmup"]
    ll = fit.loglik
    assert bool((ll[1:] >= ll[:-1]).all())
    sn = s / fit.data_scale
    assert fit.final_loglik >= _torch_strong_wolfe(sn, d, 2, mu, budget, pca_latents(sn, 2))
    # no warm-up when mu is not 100x below warmup_mu (the seed's 1e-6), or when switched off
    assert "warmup" not in fit_gplvm(s, d, 2, mu=1e-6, max_iter=5).meta
    assert "warmup" not in fit_gplvm(s, d, 2, mu=mu, max_iter=5, warmup_mu=None).meta
    with pytest.raises(ValueRangeError, match="warmup_fraction"):
        fit_gplvm(s, d, 2, warmup_fraction=1.0)


@pytest.mark.parametrize("q", [2, 3])
@pytest.mark.parametrize("budget", [20, 40, 100])
def test_default_fit_ends_at_least_as_high_as_strong_wolfe_lbfgs_at_small_budgets(q, budget):
    """The default fit (mu 1e-10 with its warm-up, our L-BFGS, closed-form gradient)
    ends at least as high as torch.optim.LBFGS(line_search_fn="strong_wolfe") on the same
    normalised objective, PCA start and iteration budget. Fails if ours ends lower. (A multimodal
    objective: on other data and budgets either can end higher.)"""
    obs, _ = small_family(40, seed=3)
    s, d = gram(obs.z, obs.cosine_weights())
    fit = fit_gplvm(s, d, q, mu=1e-10, max_iter=budget, generator=torch.Generator().manual_seed(0))
    sn = s / fit.data_scale
    assert fit.final_loglik >= _torch_strong_wolfe(sn, d, q, 1e-10, budget, pca_latents(sn, q))
