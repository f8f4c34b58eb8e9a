from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from tests.conftest import RTOL, corrupted_copy
from tests.manifold.common import SMALL_GRID, small_family, small_model
from torch_brdf.errors import FileFormatError, ShapeError, ValueRangeError
from torch_brdf.manifold.data import analytic_rows
from torch_brdf.manifold.gplvm import (
    GPLVM,
    GPLVMFit,
    _RankOneState,
    fit_gplvm,
    gram,
    log_likelihood,
    log_likelihood_and_grad,
    pca_latents,
    projection_terms,
)
from torch_brdf.manifold.kernel import JitterWarning, kernel_matrix


def test_gram_chunks_weights_and_blocks(gen):
    z = torch.randn(5, 37, generator=gen, dtype=torch.float64)
    w = torch.rand(37, generator=gen, dtype=torch.float64)
    s, d = gram(z, chunk=4)
    assert d == 37
    torch.testing.assert_close(s, z @ z.T, rtol=1e-12, atol=1e-12)
    sw, _ = gram(z, w, chunk=5)
    torch.testing.assert_close(sw, (z * w) @ (z * w).T, rtol=1e-12, atol=1e-12)
    sb, db = gram([z[:, :10], z[:, 10:]])
    assert db == 37
    torch.testing.assert_close(sb, s, rtol=1e-12, atol=1e-12)
    z[2, 30] = float("nan")
    with pytest.raises(ValueRangeError, match="non-finite"):
        gram(z)


def test_loglik_equals_dense_gaussian_density(gen):
    """Eq. 6 via the Gram matrix == sum over the d columns of log N(z_col; 0, K) + Nd/2 log 2 pi."""
    n, d = 7, 11
    x = torch.randn(n, 2, generator=gen, dtype=torch.float64)
    z = torch.randn(n, d, generator=gen, dtype=torch.float64)
    s, _ = gram(z)
    k = kernel_matrix(x, 1.3, 1e-2)
    mvn = torch.distributions.MultivariateNormal(torch.zeros(n, dtype=torch.float64), covariance_matrix=k)
    dense = float(mvn.log_prob(z.T).sum()) + n * d / 2 * math.log(2 * math.pi)
    got = float(log_likelihood(x, s, d, 1.3, 1e-2))
    assert abs(got - dense) <= 1e-10 * abs(dense)


def test_analytic_gradient_matches_autograd_and_finite_differences(gen):
    n, d = 9, 13
    x = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    z = torch.randn(n, d, generator=gen, dtype=torch.float64)
    s, _ = gram(z)
    ll, g = log_likelihood_and_grad(x, s, d, 0.9, 1e-3)
    xr = x.clone().requires_grad_(True)
    log_likelihood(xr, s, d, 0.9, 1e-3).backward()
    torch.testing.assert_close(g, xr.grad, rtol=1e-8, atol=1e-8)
    h = 1e-6
    for i, j in [(0, 0), (3, 1), (8, 2)]:
        xp, xm = x.clone(), x.clone()
        xp[i, j] += h
        xm[i, j] -= h
        fd = (float(log_likelihood(xp, s, d, 0.9, 1e-3)) - float(log_likelihood(xm, s, d, 0.9, 1e-3))) / (2 * h)
        assert abs(fd - float(g[i, j])) <= 1e-5 * max(1.0, abs(fd))
    assert abs(ll - float(log_likelihood(x, s, d, 0.9, 1e-3))) < 1e-9 * abs(ll)


@pytest.mark.parametrize("method", ["lbfgs", "adam", "hooke-jeeves"])
def test_fit_is_monotone_and_improves(method):
    obs, _ = small_family(16)
    s, d = gram(obs.z)
    fit = fit_gplvm(s, d, 2, method=method, max_iter=40)
    ll = fit.loglik
    assert bool((ll[1:] >= ll[:-1]).all()), "log-likelihood decreased"
    assert float(ll[-1]) > float(ll[0])
    assert bool(torch.isfinite(fit.latents).all())
    # the recorded final value is the objective at the returned latents
    again = float(log_likelihood(fit.latents, s / fit.data_scale, d, 1.0, fit.mu_effective))
    assert abs(again - fit.final_loglik) <= 1e-8 * abs(again)


def test_lbfgs_with_autograd_gradients_follows_the_same_path():
    obs, _ = small_family(12)
    s, d = gram(obs.z)
    a = fit_gplvm(s, d, 2, max_iter=15, generator=torch.Generator().manual_seed(1))
    b = fit_gplvm(s, d, 2, max_iter=15, autograd=True, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(a.loglik, b.loglik, rtol=1e-6, atol=0)


def test_rank_one_updates_match_refactorisation(gen):
    x = torch.randn(10, 2, generator=gen, dtype=torch.float64).numpy()
    z = torch.randn(10, 6, generator=gen, dtype=torch.float64)
    s = (z @ z.T).numpy()
    st = _RankOneState(x.copy(), s, 6, 1.0, 1e-3)
    new = st.x[4] + np.array([0.3, -0.2])
    ll, info = st.trial(4, new)
    st.commit(info)
    x2 = x.copy()
    x2[4] = new
    direct = float(log_likelihood(torch.from_numpy(x2), torch.from_numpy(s), 6, 1.0, 1e-3))
    assert abs(ll - direct) <= 1e-9 * abs(direct)
    np.testing.assert_allclose(st.kinv, np.linalg.inv(kernel_matrix(torch.from_numpy(x2), 1.0, 1e-3).numpy()), 1e-8)


def test_training_latents_reproduce_rows_and_zero_variance():
    model, obs, _ = small_model(q=2)
    pred = model.predict(model.latents)
    z = obs.z.double()
    rel = ((pred - z).abs().max(1).values / z.abs().max(1).values).max()
    assert float(rel) < 1e-6
    assert float(model.variance(model.latents).max()) < 1e-8
    far = model.latents.max(0).values + 100.0
    assert abs(float(model.variance(far)) - (1 + model.mu)) < 1e-12


def test_weights_batched_equal_loop(gen):
    model, _, _ = small_model(q=3)
    xs = model.latents[:5] + 0.1 * torch.randn(5, 3, generator=gen, dtype=torch.float64)
    b = model.weights(xs)
    # solves with K differ by rounding amplified by cond(K): tolerance cond * eps
    tol = float(torch.linalg.cond(model.chol @ model.chol.T)) * 2.2e-16 * 10
    for i in range(5):
        torch.testing.assert_close(b[i], model.weights(xs[i]), rtol=0, atol=tol)
    torch.testing.assert_close(model.blend(xs, model.z), b @ model.z, rtol=RTOL[torch.float64], atol=1e-12)


def test_bad_input_raises():
    obs, _ = small_family(8)
    s, d = gram(obs.z)
    with pytest.raises(ValueRangeError, match="q must be"):
        fit_gplvm(s, d, 0)
    with pytest.raises(ValueRangeError, match="q must be"):
        fit_gplvm(s, d, 8)
    with pytest.raises(ValueRangeError, match="method"):
        fit_gplvm(s, d, 2, method="newton")
    with pytest.raises(ValueRangeError, match="mu"):
        fit_gplvm(s, d, 2, mu=-1.0)
    bad = s.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(ValueRangeError, match="NaN"):
        fit_gplvm(bad, d, 2)
    with pytest.raises(ShapeError):
        fit_gplvm(s[:3], d, 2)
    model = GPLVM(fit_gplvm(s, d, 2, max_iter=5))
    with pytest.raises(ShapeError):
        model.weights(torch.zeros(3))
    with pytest.raises(ValueRangeError):
        model.weights(torch.tensor([float("nan"), 0.0]))
    with pytest.raises(ValueRangeError, match="no observation"):
        model.predict(torch.zeros(2))


@pytest.mark.parametrize(
    "case",
    ["duplicates", "huge_lengthscale", "mu_zero", "duplicates_mu_zero"],
)
def test_numerical_extremes_do_not_crash(case):
    obs, _ = small_family(12)
    z = obs.z.double()
    kw = {}
    if case.startswith("duplicates"):
        z = torch.cat([z, z[:4]])
    if case == "huge_lengthscale":
        kw["lengthscale"] = 1e4
    if case.endswith("mu_zero"):
        kw["mu"] = 0.0
    if case == "duplicates_mu_zero":  # the jitter path: the mu warm-up would separate the duplicates first
        kw["warmup_mu"] = None
    s, d = gram(z)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit = fit_gplvm(s, d, 2, max_iter=30, generator=torch.Generator().manual_seed(0), **kw)
    assert bool(torch.isfinite(fit.latents).all())
    assert bool(torch.isfinite(fit.loglik).all())
    assert bool((fit.loglik[1:] >= fit.loglik[:-1]).all())
    if fit.jitter > 0:  # the jitter used is reported, in the record and as a warning
        assert any(issubclass(w.category, JitterWarning) and "jitter" in str(w.message) for w in caught)
    if case == "huge_lengthscale":  # K is all ones up to mu: condition number ~ N / mu
        k = kernel_matrix(fit.latents, 1e4, fit.mu_effective)
        assert float(torch.linalg.cond(k)) > 1e5
    if case == "duplicates_mu_zero":  # coincident latents and mu = 0: K is singular without jitter
        assert fit.jitter > 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", JitterWarning)
        model = GPLVM(fit, z)
    b = model.weights(model.latents[:2] + 0.01)
    assert bool(torch.isfinite(b).all())


def test_float32_and_float64_data_agree():
    obs, _ = small_family(16)
    s32, d = gram(obs.z.float())
    s64, _ = gram(obs.z.double())
    # S is accumulated in float64 from either, so the fits are identical for the same seed
    f32 = fit_gplvm(s32, d, 2, max_iter=20, generator=torch.Generator().manual_seed(3))
    f64 = fit_gplvm(s64, d, 2, max_iter=20, generator=torch.Generator().manual_seed(3))
    assert torch.equal(s32, s64)
    torch.testing.assert_close(f32.latents, f64.latents, rtol=RTOL[torch.float64], atol=0)
    m32, m64 = GPLVM(f64, obs.z.float()), GPLVM(f64, obs.z.double())
    x = f64.latents[:3] + 0.05
    torch.testing.assert_close(m32.predict(x).double(), m64.predict(x), rtol=RTOL[torch.float32], atol=1e-5)


def test_fit_save_load_roundtrip_and_corruption(tmp_path):
    model, _, _ = small_model(n=10, q=2, max_iter=10)
    p = model.fit.save(tmp_path / "fit.npz")
    back = GPLVMFit.load(p)
    assert torch.equal(back.latents, model.fit.latents)
    assert back.names == model.fit.names and back.jitter == model.fit.jitter
    with pytest.raises(FileFormatError):
        GPLVMFit.load(corrupted_copy(p, tmp_path / "bad.npz"))


def test_pca_start_is_deterministic_and_centred(gen):
    z = torch.randn(12, 30, generator=gen, dtype=torch.float64)
    s, _ = gram(z)
    x1, x2 = pca_latents(s, 3), pca_latents(s.clone(), 3)
    assert torch.equal(x1, x2)
    torch.testing.assert_close(x1.mean(0), torch.zeros(3, dtype=torch.float64), atol=1e-10, rtol=0)
    # scores reproduce the centred Gram matrix along the top components
    zc = z - z.mean(0)
    u, sv, _ = torch.linalg.svd(zc, full_matrices=False)
    scores = u[:, :3] * sv[:3]
    c = 1.0 / scores[:, 0].std()
    torch.testing.assert_close(x1.abs(), (scores * c).abs(), rtol=1e-8, atol=1e-8)


def test_project_recovers_training_latent_and_partial_observations(gen):
    valid, obs, _params = small_model(n=24, q=2, max_iter=200)
    z = obs.z.double()
    # the seed's interpolant matches a training row only at its latent; the simplex-projected
    # weights are e_i on a whole neighbourhood of it (checked below without the variance)
    model = GPLVM(valid.fit, z, valid="none")
    g, c, sq = projection_terms(z, z[5])
    x, err = valid.project(g, c, sq)
    assert err <= 1e-8 * sq
    x, err = model.project(g, c, sq)
    assert err <= 1e-8 * sq
    assert float(model.variance(x)) < 1e-6  # at (or next to) the training latent
    # half the entries observed: still (near) exact for a training row
    mask = torch.rand(z.shape[1], generator=gen) < 0.5
    g, c, sq = projection_terms(z, z[5], mask=mask)
    x, err = model.project(g, c, sq)
    assert err <= 1e-6 * sq
    assert float(model.variance(x)) < 1e-4
    # a new member of the family: better than the best single training row
    new = analytic_rows(torch.tensor([[0.43, 0.61]]), SMALL_GRID)[0]
    g, c, sq = projection_terms(z, new)
    nearest = float((torch.diagonal(g) - 2 * c).min()) + sq
    for m in (model, valid):
        _x, err = m.project(g, c, sq)
        assert err < nearest


def test_interpolants_are_reciprocal(gen):
    """Columns for (wi, wo) and (wo, wi) are equal in every row, so in every interpolant too."""
    from torch_brdf.brdf import create

    wi = torch.nn.functional.normalize(torch.randn(40, 3, generator=gen, dtype=torch.float64), dim=-1)
    wo = torch.nn.functional.normalize(torch.randn(40, 3, generator=gen, dtype=torch.float64), dim=-1)
    wi[:, 2], wo[:, 2] = wi[:, 2].abs() + 0.05, wo[:, 2].abs() + 0.05
    wi, wo = torch.nn.functional.normalize(wi, dim=-1), torch.nn.functional.normalize(wo, dim=-1)
    rows = []
    for e in (5.0, 20.0, 50.0, 120.0, 300.0, 800.0, 10.0, 60.0):
        f = create({"type": "blinn_phong", "kd": (0.3, 0.2, 0.1), "ks": (0.5, 0.5, 0.5), "exponent": e})
        rows.append(torch.cat([f.eval(wi, wo).reshape(-1), f.eval(wo, wi).reshape(-1)]).detach().double())
    z = torch.stack(rows)
    half = z.shape[1] // 2
    torch.testing.assert_close(z[:, :half], z[:, half:], rtol=1e-12, atol=1e-12)
    s, d = gram(z)
    model = GPLVM(fit_gplvm(s, d, 2, max_iter=50), z)
    xs = model.latents.mean(0) + torch.randn(10, 2, generator=gen, dtype=torch.float64)
    zi = model.predict(xs)
    assert float(zi.abs().max()) > 0
    torch.testing.assert_close(zi[:, :half], zi[:, half:], rtol=1e-10, atol=1e-10)


def _row_jump(model, eps: float) -> torch.Tensor:
    """(N,) relative max difference of the interpolated rows at x_i + eps and at x_i."""
    at = model.predict(model.latents)
    near = model.predict(model.latents + eps)
    return (near - at).abs().max(1).values / at.abs().max(1).values


def test_continuous_predictor_is_continuous_at_training_latents():
    """The smooth GP mean (``continuous=True``) moves by < 1% between x_i and x_i + 1e-6 for
    every material and reproduces the rows up to mu (K^-1 Z)_i; the seed's interpolant jumps
    there by far more than its own move (the delta term of Eq. 5)."""
    model, obs, _ = small_model(q=2)
    model = GPLVM(model.fit, obs.z.double(), valid="none")  # the seed's weights: the formulas below are theirs
    smooth = GPLVM(model.fit, obs.z.double(), continuous=True, valid="none")
    assert float(_row_jump(smooth, 1e-6).max()) < 0.01
    z = obs.z.double()
    kinv_z = torch.cholesky_solve(z, smooth.chol)
    want = z - smooth.mu * kinv_z
    torch.testing.assert_close(smooth.predict(smooth.latents), want, rtol=1e-6, atol=1e-9 * float(z.abs().max()))
    assert float(_row_jump(model, 1e-6).max()) > float(_row_jump(smooth, 1e-6).max())
    # away from the training latents both predictors are the same
    x = model.latents.mean(0, keepdim=True) + 0.123
    torch.testing.assert_close(smooth.weights(x), model.weights(x))


def test_heldout_in_the_log_metric_is_never_worse_than_the_nearest_material():
    """Held-out placement in the perceptual (log) mapping: the training latents are candidates and
    the seed interpolant reproduces their rows, so the GPLVM is never worse than the nearest
    training material in that mapping; the prediction is b(x*)^T Z (linear in the data)."""
    from torch_brdf.manifold.evaluate import heldout_reconstruction

    obs, _ = small_family(20)
    names = list(obs.names)
    h = heldout_reconstruction(obs, names[:16], names[16:], 2, max_iter=60, generator=torch.Generator().manual_seed(0))
    assert bool((h.gplvm_logrmse <= h.nearest_logrmse + 1e-12).all())
    model = GPLVM(h.fit, obs.rows(names[:16]).double())
    pred = model.predict(h.latents)
    assert h.gplvm_negative is not None and torch.equal(h.gplvm_negative, (pred < 0).double().mean(1))
    with pytest.raises(ValueRangeError, match="metric"):
        heldout_reconstruction(obs, names[:16], names[16:], 2, metric="l1")


def test_lbfgs_stops_at_a_stationary_point():
    """Latents so far apart that K is the identity: the gradient is exactly zero and the fit
    returns them unchanged (not a zero slope handed to the line search, which raises)."""
    z = analytic_rows(torch.rand(6, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64), SMALL_GRID)
    s, d = gram(z)
    init = 1e4 * torch.arange(6, dtype=torch.float64)[:, None]
    fit = fit_gplvm(s, d, 1, init=init, normalise=False, max_iter=20)
    assert torch.equal(fit.latents, init)


def test_two_loop_recursion_equals_the_dense_bfgs_update(gen):
    """The numpy two-loop recursion gives H g of the dense inverse-BFGS recursion
    H <- (I - rho s y^T) H (I - rho y s^T) + rho s s^T from H0 = (s^T y / y^T y) I of the last pair."""
    from torch_brdf.manifold.gplvm import _two_loop

    n = 12
    a = torch.randn(n, n, generator=gen, dtype=torch.float64)
    hess = (a @ a.T + n * torch.eye(n, dtype=torch.float64)).numpy()  # SPD: every pair has s^T y > 0
    pairs = []
    for _ in range(5):
        sk = torch.randn(n, generator=gen, dtype=torch.float64).numpy()
        yk = hess @ sk
        pairs.append((sk, yk, 1.0 / float(sk @ yk)))
    g = torch.randn(n, generator=gen, dtype=torch.float64).numpy()
    sl, yl, _ = pairs[-1]
    h = np.eye(n) * float(sl @ yl) / float(yl @ yl)
    for sk, yk, rho in pairs:
        v = np.eye(n) - rho * np.outer(yk, sk)
        h = v.T @ h @ v + rho * np.outer(sk, sk)
    np.testing.assert_allclose(_two_loop(g, pairs), h @ g, rtol=1e-10, atol=1e-12)
    # no pairs: a gradient step scaled to at most 0.1 per coordinate
    np.testing.assert_allclose(np.abs(_two_loop(g, [])).max(), 0.1, rtol=1e-12)


def test_windowed_tolerance_stops_the_fit_and_is_checked():
    """tol over tol_window iterations: the fit stops at the first iteration where the last
    window together gained less than tol |L|, and not before."""
    obs, _ = small_family(16)
    s, d = gram(obs.z)
    tol, window = 1e-3, 5
    fit = fit_gplvm(s, d, 2, max_iter=400, tol=tol, tol_window=window, generator=torch.Generator().manual_seed(0))
    ll = fit.loglik.tolist()
    assert fit.iterations < 400

    def stop(k):
        return abs(ll[k] - ll[k - window]) <= tol * max(1.0, abs(ll[k - window]))

    assert stop(len(ll) - 1)
    assert not any(stop(k) for k in range(window, len(ll) - 1))
    with pytest.raises(ValueRangeError, match="tol_window"):
        fit_gplvm(s, d, 2, tol_window=0)
    with pytest.raises(ValueRangeError, match="tol_window"):
        fit_gplvm(s, d, 2, method="hooke-jeeves", tol_window=3)


def test_signed_log_mapping_charges_negative_values():
    """The placement's signed log mapping: the log-RMSE mapping (up to a constant) on values >= 0,
    odd, and a negative value is never closer to a non-negative target than 0 is."""
    from torch_brdf.manifold.evaluate import _logmap, _signed_logmap

    c = torch.tensor([0.01, 0.5, 1.0], dtype=torch.float64)
    v = torch.tensor([0.0, 0.3, 200.0], dtype=torch.float64)
    torch.testing.assert_close(_signed_logmap(v, c), _logmap(v, c) - math.log(1e-3), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(_signed_logmap(-v, c), -_signed_logmap(v, c), rtol=0, atol=0)
    t = _signed_logmap(torch.tensor([0.0, 0.1, 5.0], dtype=torch.float64), c)
    neg = _signed_logmap(torch.tensor([-1e-4, -0.2, -3.0], dtype=torch.float64), c)
    assert bool(((neg - t).abs() > t.abs()).all())
    torch.testing.assert_close(_signed_logmap(-v, c, negative_weight=10.0), -10.0 * _signed_logmap(v, c))
    torch.testing.assert_close(_signed_logmap(v, c, negative_weight=10.0), _signed_logmap(v, c), rtol=0, atol=0)


def test_perceptual_placement_options():
    """Column subsampling with every column kept is the full search; the penalised placement is
    scored with an error >= the clamped one, so it stays no worse than the nearest material in the
    clamped (log-RMSE) mapping; bad options raise."""
    from torch_brdf.manifold.evaluate import _logmap, project_perceptual

    obs, _ = small_family(16)
    names = list(obs.names)
    z_tr = obs.rows(names[:12]).double()
    s, d = gram(z_tr)
    m = GPLVM(fit_gplvm(s, d, 2, max_iter=60, generator=torch.Generator().manual_seed(0)), z_tr)
    cos = obs.grid.cosine_map()
    z = obs.rows(names[12:13]).double()[0]
    full = project_perceptual(m, z_tr, z, cos, max_columns=None)
    torch.testing.assert_close(project_perceptual(m, z_tr, z, cos, max_columns=z_tr.shape[1]), full, rtol=0, atol=0)
    for negatives, weight in (("penalise", 1.0), ("penalise", 10.0), ("penalise", 100.0), ("free", 1.0)):
        for cols in (None, 97):
            x = project_perceptual(m, z_tr, z, cos, negatives=negatives, negative_weight=weight, max_columns=cols)
            err = float(((_logmap(m.predict(x), cos) - _logmap(z, cos)) ** 2).mean())
            nearest = float(((_logmap(z_tr, cos) - _logmap(z, cos)) ** 2).mean(-1).min())
            assert err <= nearest + 1e-12
    with pytest.raises(ValueRangeError, match="negatives"):
        project_perceptual(m, z_tr, z, cos, negatives="clamp")
    with pytest.raises(ValueRangeError, match="negative_weight"):
        project_perceptual(m, z_tr, z, cos, negative_weight=0.5)
    with pytest.raises(ValueRangeError, match="max_columns"):
        project_perceptual(m, z_tr, z, cos, max_columns=0)
