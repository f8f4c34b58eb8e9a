"""BRDF manifold benchmark: GPLVM fits, interpolation, held-out reconstruction vs PCA, blending.

    OPENBLAS_NUM_THREADS=1 python benchmarks/manifold.py [--quick] [--cache PATH] [--no-peer]
        [--fits-only | --heldout-only] [--no-seed-config] [--max-iter N] [--tol T --tol-window W]
        [--negatives penalise|free] [--negative-weight L] [--max-columns C] [--peer-seconds S]
        [--splits N] [--budget-map B1,B2,...] [--valid none|simplex|energy]
        [--validity-only] [--validity-splits N]

Data: the 100 NBRDF fits of the MERL materials (an APPROXIMATION of MERL, shared data)
tabulated on the default grid (theta_h / theta_d every 3rd index, phi_d every 6th; valid bins
only; 63,339 columns) and cached (``$TORCH_BRDF_CACHE`` or ``~/.cache/torch_brdf``). With
``--quick`` the grid is coarser (every 9th / 9th / 18th index) and fits are shorter; without
the shared data, the analytic family of :func:`torch_brdf.manifold.data.analytic_rows`
(100 members) stands in and ``"data"`` says so.

Prints progress lines, then one JSON object as the LAST line:

* ``fit_s_q2``, ``fit_s_q5``, ``loglik_q2``, ``loglik_q5``: fits on all materials (cosine
  weights, normalised data, L-BFGS from PCA; log-likelihood of Eq. 6 without its constant);
  ``loglik_curve_q2/_q5``: every 10th value of the history; ``monotone_q2/_q5``;
  ``repro_rel_err_q2/_q5``: max relative error reproducing the rows at the training latents.
* ``hj_fit_s_q2``, ``hj_loglik_q2``: the seed's Hooke–Jeeves search on the same data.
* ``interp_per_s``: blending weights b(x*) per second (batches of 10k random latents);
  ``predict_rows_per_s``: full interpolated rows z* = bᵀZ per second.
* ``heldout_logrmse``, ``pca_heldout_logrmse`` (q = 5), ``..._q2`` and cosine-weighted RMSEs:
  mean over the 20 held-out materials of ``datasets/merl_split.txt``.
* ``blend_fps_512``: blended 512x512 RGB frames per second from a 100-material record (random
  values: the speed of ``BasisImage.image`` does not depend on them).
* the seed's limitation: ``path_*`` along the best path chrome -> silver-paint (q = 2, variance
  weight 10) and ``slice_*`` over a 2-D slice: fraction of negative BRDF values (max / mean over
  interpolants, share of slice points with any) and the maximum directional albedo of
  interpolants (``training_max_albedo`` for the measured rows themselves).
* ``gi_blend_rel_l1/_rmse``: seed Eq. 12, blended GI renders (3 bounces) of a few materials vs a
  GI render of the interpolated BRDF at the midpoint of their best path (sphere on a plane
  under the sky); ``direct_blend_*`` the same with direct light only (exact up to the clamp of
  negative values, ``gi_midpoint_negative_fraction``); ``gi_weights`` the blending weights used and
  ``gi_convex_blend_rel_l1`` the GI error of the uniform convex blend of the same renders.
* Configuration: unless stated otherwise, fits use ``mu = MU = 1e-10`` (the seed:
  1e-6) and the model predicts with the smooth GP mean (``GPLVM(continuous=True)``); the
  seed's configuration (mu 1e-6, interpolant exact at the latents) is reported beside it.
* held-out study: ``heldout_logrmse_mean`` / ``_std``, ``pca_heldout_logrmse_mean`` / ``_std``,
  ``nearest_heldout_logrmse_mean`` / ``_std`` (dicts by q = 2, 3, 5): mean over the held-out
  materials, then mean and std over 5 random 80/20 splits (seeds 0..4; ``--splits``, printed as
  ``splits``); the GPLVM is fitted on
  the training rows and each held-out material placed at its best manifold point in the log
  mapping of the score (``heldout_reconstruction(metric="log")``; the prediction stays
  b(x*)ᵀZ), PCA of the same dimension (cosine weights, orthogonal projection), and the nearest
  training material in the same log mapping; ``heldout_seed_logrmse_mean``: the seed's
  configuration; ``heldout_negative_mean`` / ``pca_heldout_negative_mean``: fraction of
  negative values in the reconstructions; ``family_heldout``: each family held out whole
  (names containing ``metallic-paint``, ``phenolic``, ``fabric``; q = 2, 3, 5; NBRDF data only),
  with ``on_training_latent`` (share placed where the predictive variance is < 1e-6) and the
  blending weights' mean negative sum / minimum (``weights_negative_sum``, ``weights_min``): why
  negative values appear. ``--splits 0``: the family hold-outs only.
* ``continuity_max``: max over the training materials of the relative max difference between
  the rows at x_i + 1e-6 and at x_i (q = 2 fit on all materials, the default configuration);
  ``continuity_max_seed`` the same for the seed's interpolant; ``repro_rel_err_smooth_q2``: the
  smooth mean's max relative error reproducing the rows at the training latents.
* ``lbfgs_wolfe_loglik_q2``, ``lbfgs_wolfe_s_q2``: ``torch.optim.LBFGS`` with the strong-Wolfe
  line search on :func:`log_likelihood` (autograd), same data, mu, PCA start and iteration budget
  (``max_iter`` iterations, torch's default of 1.25 evaluations per iteration), one thread like
  ours. Our fit includes its mu warm-up (the first 20 % of the budget at mu = 3e-6, see
  :func:`fit_gplvm`); ``loglik_q2_no_warmup`` / ``fit_s_q2_no_warmup``: ours without it.
  ``--budget-map 60,100,...``: ``lbfgs_wolfe_budget_map_q2`` ({budget: {"ours", "torch"}}, our
  default fit and that peer at each budget) and ``budgets_ours_at_least_wolfe_q2``.
* ``gpytorch_*``: GPyTorch ExactGP with the latents as parameters (their MAP GPLVM), q = 2, same
  normalised data, noise = mu, PCA start, ``torch.optim.LBFGS`` (strong Wolfe) in chunks of 10
  iterations until it reaches our final L (``gpytorch_s_to_our_loglik_q2``; None = not reached),
  converges or hits ``--peer-seconds``; L is Eq. 6 evaluated by our code at their latents (same
  objective, directly comparable); ``time_ratio_gpytorch_over_ours``,
  ``loglik_ours_minus_gpytorch``.
* ``gpy`` (:func:`gpy_peer`): GPy's GPLVM (L-BFGS-B) on the same objective at mu = GPY_MU (1e-6),
  same start; ours runs ``max_iter`` iterations first, GPy until it reaches our L
  (``gpy_s_to_our_loglik``) or ``--peer-seconds``; ``time_ratio_gpy_over_ours``;
  ``gpy_objective_gap`` = relative difference of the two objectives at the start. "not installed"
  without GPy.
* ``objective_ms_q2/_q5``: one objective + gradient evaluation at the fitted latents (median of
  30, same run); ``fit_q2_in_objective_evaluations``: the fit's wall time in those units;
  ``fit_cpu_s_q2/_q5``: the fit's CPU time (``time.process_time``, one thread): on a shared,
  overloaded machine the wall time mostly waits for a core, the CPU time is the work.
  ``settings``: budget, stop rule, placement.
* ``heldout_cosrmse_mean`` / ``heldout_projected_cosrmse_mean`` (and ``pca_...``): cosine-weighted
  RMSE of the held-out reconstructions as they are and projected onto the non-negative cone
  (max(z, 0), no negative values left; the log-RMSE is the same both ways, it clamps at 0).
* every latent point a valid BRDF (:func:`validity_study`, q = 2, the seed's configuration):
  ``negative_fraction_{unconstrained,valid,energy}`` and ``max_albedo_*`` at 10,000 latents
  uniform inside the hull of the training latents; ``heldout_logrmse_*``, ``heldout_negative_*``,
  ``heldout_s_*`` over ``validity_splits`` random splits (5, quick 2); ``weights_us_per_point_*``.
  ``unconstrained`` is the seed's weights (``GPLVM(valid="none")``), ``valid`` the default
  simplex projection, ``energy`` the simplex scaled to albedo <= 1. Every other section measures
  the seed's weights (``SEED``; ``--valid`` sets the held-out study's). ``--validity-only``: this
  section only.
* ``load_start`` / ``load_end``: 1-minute load average (the machine is shared; timings vary).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torch_brdf.data import cache_path, data_path
from torch_brdf.manifold.data import (
    MERLGrid,
    Observations,
    analytic_rows,
    default_grid,
    nbrdf_observations,
    read_split,
    split_names,
)
from torch_brdf.manifold.evaluate import NEGATIVE_WEIGHT, NEGATIVES, heldout_reconstruction
from torch_brdf.manifold.gplvm import (
    GPLVM,
    VALIDITY,
    fit_gplvm,
    gram,
    log_likelihood,
    log_likelihood_and_grad,
    pca_latents,
    small_matrix_mode,
)
from torch_brdf.manifold.materials import material_record, random_record, sphere_scene
from torch_brdf.manifold.paths import (
    best_path,
    directional_albedo,
    interpolant_diagnostics,
    latent_slice,
    straight_paths,
)
from torch_brdf.render.manifold import blend, gi_blend_error, render_rows

#: the repository checkout (its datasets/merl_split.txt), when the package runs from one
ROOT = Path(__file__).resolve().parents[3]
#: the kernel's mu for every fit here (the seed's 1e-6 is reported beside it in the held-out study)
MU = 1e-10
#: the blend weights of every section but the validity study: the seed's unconstrained interpolant
#: (the keys measure the seed; ``--valid`` changes the held-out study's)
SEED = "none"
#: mu of the GPy comparison (the seed's): GPy adds 1e-8 to its noise, so MU = 1e-10 cannot be matched
GPY_MU = 1e-6


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def load_data(quick: bool, cache: Path | None) -> tuple[Observations, str]:
    grid = MERLGrid.strided(9, 9, 18) if quick else default_grid()
    weights = data_path("merl", "nbrdf_merl100_weights.npz", required=False)
    if weights is None:
        g = torch.Generator().manual_seed(0)
        params = torch.rand(100, 2, generator=g, dtype=torch.float64)
        z = analytic_rows(params, grid).float()
        names = tuple(f"analytic-{i:03d}" for i in range(100))
        return Observations(z, names, grid, "analytic"), "analytic family (no shared NBRDF data)"
    cache = cache or cache_path(f"merl_nbrdf_{'quick' if quick else 'default'}_{grid.digest()[:8]}.npz")
    obs = nbrdf_observations(weights, grid, cache=cache, progress=True)
    return obs, f"NBRDF approximation of MERL, grid {grid.describe()}, {obs.z.shape[1]} columns"


def fit_all(obs: Observations, q: int, max_iter: int, method: str = "lbfgs", **kwargs) -> dict:
    s, d = gram(obs.z, obs.cosine_weights())
    cpu0 = time.process_time()
    fit = fit_gplvm(
        s, d, q, max_iter=max_iter, method=method, mu=MU, names=obs.names, generator=torch.Generator().manual_seed(0),
        **kwargs,
    )  # fmt: skip
    cpu = time.process_time() - cpu0
    model = GPLVM(fit, obs.z.double(), valid=SEED)
    z = obs.z.double()
    pred = model.predict(model.latents)
    repro = float(((pred - z).abs().max(1).values / z.abs().max(1).values.clamp_min(1e-300)).max())
    ll = fit.loglik
    evals = []
    with small_matrix_mode(s.shape[0]):
        for _ in range(30):  # one objective + gradient evaluation at the fitted latents, the fit's unit of work
            t0 = time.perf_counter()
            log_likelihood_and_grad(fit.latents, s, d, 1.0, MU)
            evals.append(time.perf_counter() - t0)
    return {
        "objective_s": sorted(evals)[len(evals) // 2],
        "cpu_seconds": cpu,
        "fit": fit,
        "model": model,
        "seconds": fit.seconds,
        "loglik": fit.final_loglik,
        "curve": [round(float(v), 3) for v in ll[::10].tolist()] + [round(float(ll[-1]), 3)],
        "monotone": bool((ll[1:] >= ll[:-1]).all()),
        "repro": repro,
        "iterations": fit.iterations,
    }


def gpytorch_peer(obs: Observations, q: int, target: float, seconds_cap: float, chunk: int = 10) -> dict | None:
    """GPyTorch ExactGP with the latents as parameters (their MAP GPLVM), L-BFGS (strong Wolfe) to convergence.

    Same normalised, cosine-weighted data, unit lengthscale, noise = MU, PCA start. Runs in chunks
    of ``chunk`` L-BFGS iterations, scoring their latents with OUR Eq. 6 after each chunk, until
    they reach ``target`` (our final L), converge (L changes < 1e-9 relative) or ``seconds_cap``.
    """
    try:
        import gpytorch
    except ImportError:
        return None
    s, d = gram(obs.z, obs.cosine_weights())
    scale = float(torch.diagonal(s).sum()) / (s.shape[0] * d)
    y = (obs.z.double() * obs.cosine_weights()).T.contiguous() / math.sqrt(scale)  # (d, N), same data as ours

    class LatentExactGP(gpytorch.models.ExactGP):
        def __init__(self, x, y, lik):
            super().__init__(x, y, lik)
            self.mean = gpytorch.means.ZeroMean()
            self.cov = gpytorch.kernels.RBFKernel()
            self.cov.lengthscale = 1.0
            self.cov.raw_lengthscale.requires_grad_(False)

        def forward(self, x):
            return gpytorch.distributions.MultivariateNormal(self.mean(x), self.cov(x))

    lik = gpytorch.likelihoods.GaussianLikelihood(noise_constraint=gpytorch.constraints.GreaterThan(0.0))
    lik.noise = MU
    lik.raw_noise.requires_grad_(False)
    x = torch.nn.Parameter(pca_latents(s / scale, q).clone())
    model = LatentExactGP(x, y, lik).double()
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(lik, model)
    model.train()
    lik.train()
    opt = torch.optim.LBFGS([x], lr=1.0, max_iter=chunk, line_search_fn="strong_wolfe", history_size=20)

    def closure():
        opt.zero_grad()
        model.set_train_data(inputs=x, strict=False)
        loss = -mll(model(x), model.train_targets).sum()
        loss.backward()
        return loss

    seconds, iters, ll, reached = 0.0, 0, -math.inf, None
    with gpytorch.settings.max_cholesky_size(10**6), small_matrix_mode(x.shape[0]):
        while seconds < seconds_cap:
            t0 = time.perf_counter()
            opt.step(closure)
            seconds += time.perf_counter() - t0
            iters += chunk
            new = float(log_likelihood(x.detach(), s / scale, d, 1.0, MU))
            if new >= target and reached is None:
                reached = seconds
                break
            if abs(new - ll) <= 1e-9 * abs(new):
                ll = new
                break
            ll = new
            _log(f"GPyTorch L-BFGS: {iters} iterations, L = {new:.6g} (ours {target:.6g}), {seconds:.1f} s")
    ll = float(log_likelihood(x.detach(), s / scale, d, 1.0, MU))
    return {"seconds": seconds, "iterations": iters, "loglik": ll, "seconds_to_our_loglik": reached}


def gpy_peer(obs: Observations, q: int, mu: float, max_iter: int, seconds_cap: float) -> dict | None:
    """GPy's GPLVM (L-BFGS-B from scipy) against ours on the same objective, to our final L.

    Same normalised, cosine-weighted data, RBF with unit variance and lengthscale (fixed), noise
    ``mu - 1e-8`` (fixed; GPy's exact inference adds 1e-8 to the noise), the same nudged PCA start.
    So ``mu`` must exceed 1e-8 (the seed's 1e-6 here; the default MU = 1e-10 cannot be matched);
    ``gpy_objective_gap`` is the relative difference of GPy's L (without its constant) and Eq. 6
    at the start. Ours runs first (``max_iter``
    iterations, no warm-up); GPy runs until it reaches our L (every evaluation is scored), its own
    convergence or ``seconds_cap``.
    """
    try:
        import GPy
    except ImportError:
        return None
    s, d = gram(obs.z, obs.cosine_weights())
    n = s.shape[0]
    scale = float(torch.diagonal(s).sum()) / (n * d)
    s = s / scale
    y = ((obs.z.double() * obs.cosine_weights()) / math.sqrt(scale)).numpy()
    x0 = pca_latents(s, q)
    x0 = x0 + 1e-6 * torch.randn(x0.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * float(
        x0.std()
    )
    ours = fit_gplvm(s, d, q, mu=mu, max_iter=max_iter, init=x0, normalise=False, warmup_mu=None)
    kern = GPy.kern.RBF(q, variance=1.0, lengthscale=1.0)
    kern.variance.fix()
    kern.lengthscale.fix()
    m = GPy.models.GPLVM(y, q, X=x0.numpy().copy(), kernel=kern)
    m.likelihood.variance = mu - 1e-8
    m.likelihood.variance.fix()
    const = 0.5 * n * d * math.log(2 * math.pi)  # GPy's L includes it; Eq. 6 here does not
    ll0 = float(log_likelihood(x0, s, d, 1.0, mu))
    gap = abs(float(m.log_likelihood()) + const - ll0) / abs(ll0)
    target = ours.final_loglik
    state = {"reached": None, "evals": 0, "best": -math.inf}

    class _Stop(Exception):
        pass

    objective = m._objective_grads
    t0 = time.perf_counter()

    def scored(p):
        f, g = objective(p)
        state["evals"] += 1
        state["best"] = max(state["best"], -float(f) + const)
        if state["best"] >= target and state["reached"] is None:
            state["reached"] = time.perf_counter() - t0
            raise _Stop
        if time.perf_counter() - t0 > seconds_cap:
            raise _Stop
        return f, g

    m._objective_grads = scored
    with contextlib.suppress(_Stop), small_matrix_mode(n):
        m.optimize("lbfgsb", max_iters=100 * max_iter, messages=False)
    seconds = time.perf_counter() - t0
    return {
        "mu": mu,
        "ours_loglik": target,
        "ours_s": ours.seconds,
        "ours_iterations": ours.iterations,
        "gpy_loglik": float(log_likelihood(torch.as_tensor(np.asarray(m.X)), s, d, 1.0, mu)),
        "gpy_s": seconds,
        "gpy_evaluations": state["evals"],
        "gpy_s_to_our_loglik": state["reached"],
        "gpy_objective_gap": gap,
    }


def row_jump(model: GPLVM, eps: float = 1e-6) -> torch.Tensor:
    """(N,) relative max difference of the interpolated rows at x_i + eps and at x_i."""
    at = model.predict(model.latents)
    near = model.predict(model.latents + eps)
    return (near - at).abs().max(1).values / at.abs().max(1).values.clamp_min(1e-300)


def wolfe_peer(obs: Observations, q: int, iters: int) -> dict:
    """torch.optim.LBFGS (strong Wolfe) on the package's log_likelihood, same data, start and budget."""
    s, d = gram(obs.z, obs.cosine_weights())
    n = s.shape[0]
    s = s / (float(torch.diagonal(s).sum()) / (n * d))
    x0 = pca_latents(s, q)
    x0 = x0 + 1e-6 * torch.randn(x0.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * float(
        x0.std()
    )
    x = x0.clone().requires_grad_(True)
    opt = torch.optim.LBFGS([x], lr=1.0, max_iter=iters, line_search_fn="strong_wolfe", history_size=20)

    def closure():
        opt.zero_grad()
        loss = -log_likelihood(x, s, d, 1.0, MU) / (n * d)
        loss.backward()
        return loss

    t0 = time.perf_counter()
    with small_matrix_mode(n):  # the same thread / denormal settings as our fits
        opt.step(closure)
    seconds = time.perf_counter() - t0
    return {"loglik": float(log_likelihood(x.detach(), s, d, 1.0, MU)), "seconds": seconds}


def budget_map(obs: Observations, q: int, budgets: tuple[int, ...]) -> dict:
    """Our default fit and torch's strong-Wolfe L-BFGS at each iteration budget (same data, mu, start)."""
    s, d = gram(obs.z, obs.cosine_weights())
    out = {}
    for b in budgets:
        ours = fit_gplvm(s, d, q, max_iter=b, mu=MU, generator=torch.Generator().manual_seed(0)).final_loglik
        out[b] = {"ours": ours, "torch": wolfe_peer(obs, q, b)["loglik"]}
        _log(f"budget {b}, q={q}: ours {ours:.6g}, strong-Wolfe L-BFGS {out[b]['torch']:.6g}")
    return out


def heldout_study(
    obs: Observations, max_iter: int, splits: int = 5, with_seed: bool = True, qs: tuple = (2, 3, 5), **kwargs
) -> dict:
    """Held-out log-RMSE mean/std over random splits and family hold-outs (see the module docstring)."""
    names = list(obs.names)
    res: dict = {}
    keys = ("gplvm", "pca", "nearest", "neg", "pca_neg", "cont", "cos", "pca_cos", "proj_cos", "pca_proj_cos")
    per: dict = {k: {q: [] for q in qs} for k in keys}
    for seed in range(splits):  # splits = 0: the family hold-outs only
        perm = torch.randperm(len(names), generator=torch.Generator().manual_seed(seed)).tolist()
        n_test = len(names) // 5
        test = sorted(names[i] for i in perm[:n_test])
        train = sorted(names[i] for i in perm[n_test:])
        for q in qs:
            for seed_config in (True, False)[0 if with_seed else 1 :]:
                h = heldout_reconstruction(
                    obs, train, test, q, max_iter=max_iter, continuous=not seed_config,
                    mu=1e-6 if seed_config else MU, generator=torch.Generator().manual_seed(0), **kwargs,
                )  # fmt: skip
                if seed_config:
                    per["cont"][q].append(float(h.gplvm_logrmse.mean()))
                    continue
                per["gplvm"][q].append(float(h.gplvm_logrmse.mean()))
                per["pca"][q].append(float(h.pca_logrmse.mean()))
                per["nearest"][q].append(float(h.nearest_logrmse.mean()))
                per["neg"][q].append(float(h.gplvm_negative.mean()))
                per["pca_neg"][q].append(float(h.pca_negative.mean()))
                per["cos"][q].append(float(h.gplvm_cosrmse.mean()))
                per["pca_cos"][q].append(float(h.pca_cosrmse.mean()))
                per["proj_cos"][q].append(float(h.gplvm_projected_cosrmse.mean()))
                per["pca_proj_cos"][q].append(float(h.pca_projected_cosrmse.mean()))
            seed_s = f"{per['cont'][q][-1]:.3f}" if with_seed else "-"
            _log(
                f"split {seed} q={q}: GPLVM {per['gplvm'][q][-1]:.3f} (seed's {seed_s}), PCA {per['pca'][q][-1]:.3f}, "
                f"nearest {per['nearest'][q][-1]:.3f}, negatives {per['neg'][q][-1]:.4f} / {per['pca_neg'][q][-1]:.4f}"
            )

    def stats(key):
        t = {q: torch.tensor(v, dtype=torch.float64) for q, v in per[key].items()}
        return {q: round(float(v.mean()), 4) for q, v in t.items()}, {q: round(float(v.std()), 4) for q, v in t.items()}

    if splits:
        for key, name in (
            ("gplvm", "heldout_logrmse"),
            ("pca", "pca_heldout_logrmse"),
            ("nearest", "nearest_heldout_logrmse"),
        ):
            res[f"{name}_mean"], res[f"{name}_std"] = stats(key)
        if with_seed:
            res["heldout_seed_logrmse_mean"] = stats("cont")[0]
        res["heldout_negative_mean"], _ = stats("neg")
        res["pca_heldout_negative_mean"], _ = stats("pca_neg")
        res["heldout_cosrmse_mean"], _ = stats("cos")
        res["pca_heldout_cosrmse_mean"], _ = stats("pca_cos")
        res["heldout_projected_cosrmse_mean"], _ = stats("proj_cos")
        res["pca_heldout_projected_cosrmse_mean"], _ = stats("pca_proj_cos")
    if obs.source == "nbrdf":
        fam = {}
        for family in ("metallic-paint", "phenolic", "fabric"):
            test = [n for n in names if family in n]
            train = [n for n in names if family not in n]
            for q in qs:
                h = heldout_reconstruction(
                    obs, train, test, q, max_iter=max_iter, mu=MU, continuous=True,
                    generator=torch.Generator().manual_seed(0), **kwargs,
                )  # fmt: skip
                # why negatives: a placement on a training latent (variance ~0), where the smooth
                # mean's weights are e_j - mu K^-1 e_j, with large entries of both signs
                model = GPLVM(h.fit, obs.rows(train).double(), continuous=True, valid=SEED)
                w = model.weights(h.latents)
                fam[f"{family}_q{q}"] = {
                    "on_training_latent": round(float((h.variance < 1e-6).double().mean()), 4),
                    "weights_negative_sum": round(float(w.clamp_max(0).sum(1).mean()), 4),
                    "weights_min": round(float(w.min()), 4),
                    "n": len(test),
                    "gplvm": round(float(h.gplvm_logrmse.mean()), 4),
                    "pca": round(float(h.pca_logrmse.mean()), 4),
                    "nearest": round(float(h.nearest_logrmse.mean()), 4),
                    "negative": round(float(h.gplvm_negative.mean()), 4),
                    "pca_negative": round(float(h.pca_negative.mean()), 4),
                    "cosrmse": round(float(h.gplvm_cosrmse.mean()), 4),
                    "projected_cosrmse": round(float(h.gplvm_projected_cosrmse.mean()), 4),
                    "pca_cosrmse": round(float(h.pca_cosrmse.mean()), 4),
                    "pca_projected_cosrmse": round(float(h.pca_projected_cosrmse.mean()), 4),
                }
                _log(f"family {family} q={q}: {fam[f'{family}_q{q}']}")
        res["family_heldout"] = fam
    return res


def interp_rate(model: GPLVM, z: torch.Tensor, quick: bool) -> tuple[float, float]:
    g = torch.Generator().manual_seed(1)
    lo, hi = model.latents.min(0).values, model.latents.max(0).values
    xs = lo + (hi - lo) * torch.rand(10_000, model.q, generator=g, dtype=torch.float64)
    best = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        model.weights(xs)
        best = min(best, time.perf_counter() - t0)
    m = 20 if quick else 100
    t0 = time.perf_counter()
    model.blend(xs[:m], z)
    rows = m / (time.perf_counter() - t0)
    return xs.shape[0] / best, rows


def blend_fps(n: int, size: int, repeats: int) -> float:
    rec = random_record(n, size, size, generator=torch.Generator().manual_seed(2))
    w = torch.rand(n, generator=torch.Generator().manual_seed(3))
    rec.image(w)
    t0 = time.perf_counter()
    for _ in range(repeats):
        rec.image(w)
    return repeats / (time.perf_counter() - t0)


def limitation(model: GPLVM, obs: Observations, ends: tuple, quick: bool) -> dict:
    """Negative values and max directional albedo of interpolants along a best path and across a slice."""
    alb = directional_albedo(obs.z, obs.grid)
    path = best_path(model, *ends, variance_weight=10.0)
    dp = interpolant_diagnostics(path.weights, obs.z, alb)
    sl = latent_slice(model, resolution=12 if quick else 24)
    ds = interpolant_diagnostics(model.weights(sl.points.reshape(-1, model.q)), obs.z, alb)
    train_max = float(alb.flatten(1).max(-1).values.max())
    return {
        "path_ends": list(ends) if isinstance(ends[0], str) else [int(e) for e in ends],
        "path_waypoints": len(path.waypoints),
        "path_max_variance": path.max_variance,
        "path_negative_fraction_max": float(dp.negative_fraction.max()),
        "path_negative_fraction_mean": float(dp.negative_fraction.mean()),
        "path_max_albedo": float(dp.max_albedo.max()),
        "slice_points_with_negatives": float((ds.negative_fraction > 0).double().mean()),
        "slice_negative_fraction_mean": float(ds.negative_fraction.mean()),
        "slice_max_albedo": float(ds.max_albedo.max()),
        "training_max_albedo": train_max,
    }


def _hull_points(latents: torch.Tensor, m: int, generator: torch.Generator) -> torch.Tensor:
    """(m, Q) latents uniform inside the convex hull of ``latents`` (rejection from the bounding box)."""
    from scipy.spatial import Delaunay

    tri = Delaunay(latents.numpy())
    lo, hi = latents.min(0).values, latents.max(0).values
    got: list[torch.Tensor] = []
    n = 0
    while n < m:
        x = lo + (hi - lo) * torch.rand(4 * m, latents.shape[1], generator=generator, dtype=torch.float64)
        x = x[torch.from_numpy(tri.find_simplex(x.numpy()) >= 0)]
        got.append(x)
        n += x.shape[0]
    return torch.cat(got)[:m]


def _with_raw_tests(data: Observations, raw: Observations, test) -> Observations:
    """``data`` with the rows of ``test`` put back to those of ``raw`` (held-out rows are never rescaled)."""
    z = data.z.clone()
    for n in test:
        z[raw.names.index(n)] = raw.z[raw.names.index(n)]
    return Observations(z, data.names, data.grid, data.source)


def validity_study(obs: Observations, max_iter: int, splits: int, points: int = 10_000, **stop) -> dict:
    """Every latent point a valid BRDF: the blend-weight options of :class:`GPLVM` (``valid``) compared.

    q = 2, the seed's configuration (mu 1e-6, interpolant exact at the latents). On a fit to all
    materials, ``points`` latents uniform inside the convex hull of the training latents (seeded):
    ``negative_fraction_*`` (share of predicted BRDF values < 0), ``max_albedo_*`` (largest
    directional albedo over points, angles and RGB, blended from the per-material albedos: exact, it
    is linear in the BRDF), ``weights_us_per_point_*`` (best of 3, 10,000 points). Held-out:
    ``heldout_logrmse_*`` / ``heldout_negative_*`` / ``heldout_s_*`` (fit + placements, CPU wall)
    over ``splits`` random 80/20 splits (seeds 0..), each option placing with its own weights
    (:func:`heldout_reconstruction` ``valid=``); ``nearest_`` / ``pca_heldout_logrmse_valid_study``
    on the same splits. Suffixes: ``unconstrained`` = ``"none"``, ``valid`` = ``"simplex"``,
    ``energy`` (the default with albedos, ``default_validity``), ``normalised`` = ``"simplex"`` on
    training rows scaled to albedo <= 1 (``training_above_albedo_1`` the rows it scales; scored
    against the raw held-out rows).
    """
    options = {"unconstrained": "none", "valid": "simplex", "energy": "energy", "normalised": "simplex"}
    alb = directional_albedo(obs.z, obs.grid)
    z = obs.z.double()
    # "normalised": the other answer to training rows of albedo > 1: scale those rows to albedo 1,
    # then simplex weights (the rows every option predicts with and is scored against are raw)
    row_scale = 1 / alb.flatten(1).max(1).values.clamp_min(1.0)
    s, d = gram(obs.z, obs.cosine_weights())
    fit = fit_gplvm(s, d, 2, max_iter=max_iter, mu=1e-6, generator=torch.Generator().manual_seed(0), **stop)
    model = GPLVM(fit, z, valid=SEED, albedo=alb)
    xs = _hull_points(model.latents, points, torch.Generator().manual_seed(4))
    out: dict = {"validity_points": points, "training_max_albedo_valid_study": float(alb.max())}
    out["training_above_albedo_1"] = [n for n, a in zip(obs.names, alb.flatten(1).max(1).values, strict=True) if a > 1]
    out["default_validity"] = GPLVM(fit, z, albedo=alb).valid
    for key, valid in options.items():
        scale = row_scale if key == "normalised" else torch.ones_like(row_scale)
        w = model.weights(xs, valid=valid) * scale
        neg = sum(int(((w[a : a + 1000] @ z) < 0).sum()) for a in range(0, points, 1000))
        out[f"negative_fraction_{key}"] = neg / (points * z.shape[1])
        out[f"max_albedo_{key}"] = float((w @ alb.flatten(1)).max())
        best = math.inf
        for _ in range(3):
            t0 = time.perf_counter()
            model.weights(xs, valid=valid)
            best = min(best, time.perf_counter() - t0)
        out[f"weights_us_per_point_{key}"] = 1e6 * best / points
        _log(
            f"validity {key}: negative {out[f'negative_fraction_{key}']:.4f}, max albedo {out[f'max_albedo_{key}']:.3g}"
        )
    names = list(obs.names)
    per: dict = {k: [] for k in ("nearest", "pca", *(f"{m}_{o}" for m in ("rmse", "neg", "s") for o in options))}
    for seed in range(splits):
        perm = torch.randperm(len(names), generator=torch.Generator().manual_seed(seed)).tolist()
        test = sorted(names[i] for i in perm[: len(names) // 5])
        train = sorted(names[i] for i in perm[len(names) // 5 :])
        train_alb = alb[[names.index(n) for n in train]]
        for key, valid in options.items():
            t0 = time.perf_counter()
            data = obs
            if key == "normalised":
                data = Observations((obs.z.double() * row_scale[:, None]).float(), obs.names, obs.grid, obs.source)
                data = _with_raw_tests(data, obs, test)
            h = heldout_reconstruction(
                data, train, test, 2, max_iter=max_iter, mu=1e-6, generator=torch.Generator().manual_seed(0),
                valid=valid, albedo=train_alb, **stop,
            )  # fmt: skip
            per[f"s_{key}"].append(time.perf_counter() - t0)
            per[f"rmse_{key}"].append(float(h.gplvm_logrmse.mean()))
            per[f"neg_{key}"].append(float(h.gplvm_negative.mean()))
            _log(f"validity split {seed} {key}: held-out log-RMSE {per[f'rmse_{key}'][-1]:.4f}")
        per["nearest"].append(float(h.nearest_logrmse.mean()))
        per["pca"].append(float(h.pca_logrmse.mean()))
    if splits:
        for key in options:
            out[f"heldout_logrmse_{key}"] = float(np.mean(per[f"rmse_{key}"]))
            out[f"heldout_negative_{key}"] = float(np.mean(per[f"neg_{key}"]))
            out[f"heldout_s_{key}"] = float(np.mean(per[f"s_{key}"]))
        out["nearest_heldout_logrmse_valid_study"] = float(np.mean(per["nearest"]))
        out["pca_heldout_logrmse_valid_study"] = float(np.mean(per["pca"]))
        out["validity_splits"] = splits
    return out


#: families of materials held out whole in the default configuration's study, by name: the pool
#: the benchmark draws from leaves out the three families the placement was tuned on
#: (``metallic-paint``, ``phenolic``, ``fabric``, in :func:`heldout_study`)
FAMILIES = {
    "metals": (
        "alum-bronze", "aluminium", "black-oxidized-steel", "brass", "chrome", "chrome-steel",
        "grease-covered-steel", "nickel", "ss440", "steel", "tungsten-carbide",
    ),
    "plastics": ("plastic",),
    "acrylics": ("acrylic",),
    "rubbers": ("rubber", "latex"),
    "woods": ("cherry-235", "colonial-maple-223", "fruitwood-241", "ipswich-pine-221", "natural-209",
              "pickled-oak-260", "special-walnut-224"),
    "paints": ("dark-blue-paint", "dark-red-paint", "gold-paint", "light-red-paint", "orange-paint",
               "pearl-paint", "purple-paint", "silver-paint", "white-paint", "yellow-paint"),
}  # fmt: skip
#: default seed of the draw of family hold-outs (printed with the result)
FAMILY_SEED = 2017
#: the margin over the nearest training material the default configuration is held to
MARGIN = 0.10


def family_members(names, family: str) -> list[str]:
    """Materials of ``family`` (:data:`FAMILIES`): exact names, or substrings for one-word patterns."""
    pats = FAMILIES[family]
    return [n for n in names if n in pats or any("-" not in p and p in n for p in pats)]


def pick_families(seed: int, count: int = 2) -> list[str]:
    """``count`` families of :data:`FAMILIES` drawn with ``seed`` (the benchmark prints both)."""
    order = torch.randperm(len(FAMILIES), generator=torch.Generator().manual_seed(seed)).tolist()
    return [list(FAMILIES)[i] for i in order[:count]]


def default_study(
    obs: Observations, max_iter: int, splits: int, family_seed: int = FAMILY_SEED, qs=(2, 3, 5), **stop
) -> dict:
    """Held-out accuracy and placement of the DEFAULT model: valid weights (``GPLVM``'s default with
    albedos), the seed's mu 1e-6 and exact interpolant, placement between neighbours.

    Cases: ``splits`` random 80/20 splits (seeds 0..) and, on the NBRDF data, two families of
    :data:`FAMILIES` held out whole, drawn with ``family_seed``. Per case and q (``default_heldout``):
    mean log-RMSE of the GPLVM, the nearest training material and PCA; ``margin`` = 1 - GPLVM /
    nearest; ``interpolation_share`` = share of held-out latents at >= 0.1 of the local spacing from
    every training latent (:func:`interpolation_share`); ``top_weight`` the mean largest blend
    weight. Summary: ``default_margin_min`` (by q, over cases), ``default_below_pca_all``,
    ``default_margin_ok`` (every case and q at least :data:`MARGIN`), ``default_interpolation_share``
    (by q, mean over cases), ``default_heldout_s``.
    """
    names = list(obs.names)
    alb = directional_albedo(obs.z, obs.grid)
    cases = []
    for seed in range(splits):
        perm = torch.randperm(len(names), generator=torch.Generator().manual_seed(seed)).tolist()
        test = sorted(names[i] for i in perm[: len(names) // 5])
        cases.append((f"split{seed}", test))
    fams = pick_families(family_seed) if obs.source == "nbrdf" else []
    _log(f"default study: family seed {family_seed} -> {fams}")
    for f in fams:
        cases.append((f, family_members(names, f)))
    per: dict = {}
    t0 = time.perf_counter()
    for tag, test in cases:
        train = [n for n in names if n not in test]
        train_alb = alb[[names.index(n) for n in train]]
        for q in qs:
            h = heldout_reconstruction(
                obs, train, test, q, max_iter=max_iter, mu=1e-6, generator=torch.Generator().manual_seed(0),
                albedo=train_alb, **stop,
            )  # fmt: skip
            g, n, p = (float(v.mean()) for v in (h.gplvm_logrmse, h.nearest_logrmse, h.pca_logrmse))
            per.setdefault(tag, {})[q] = {
                "n": len(test),
                "gplvm": round(g, 4),
                "nearest": round(n, 4),
                "pca": round(p, 4),
                "margin": round(1 - g / n, 4),
                "interpolation_share": round(float((h.interpolation >= 0.1).double().mean()), 4),
                "interpolation_ratio_median": round(float(h.interpolation.median()), 4),
                "top_weight": round(float(h.top_weight.mean()), 4),
                "negative": float(h.gplvm_negative.mean()),
            }
            _log(f"default {tag} q={q}: {per[tag][q]}")
    out = {"default_heldout": per, "default_family_seed": family_seed, "default_families": fams}
    out["default_families_members"] = {f: family_members(names, f) for f in fams}
    out["default_margin_min"] = {q: min(per[t][q]["margin"] for t in per) for q in qs}
    out["default_below_pca_all"] = all(v["gplvm"] < v["pca"] for t in per for v in per[t].values())
    out["default_margin_ok"] = all(v["margin"] >= MARGIN for t in per for v in per[t].values())
    out["default_interpolation_share"] = {
        q: round(float(np.mean([per[t][q]["interpolation_share"] for t in per])), 4) for q in qs
    }
    out["default_heldout_s"] = round(time.perf_counter() - t0, 1)
    return out


def path_study(obs: Observations, max_iter: int, pairs: int = 20, **stop) -> dict:
    """Straight latent paths between neighbouring training materials (the default model, q = 2).

    ``pairs`` materials drawn with seed 5, each paired with its nearest latent neighbour; along each
    straight path (33 points, :func:`straight_paths`): ``path_monotone_share`` (share of paths whose
    albedo or highlight width changes monotonically), ``path_jump_max`` / ``path_jump_median`` (the
    largest step's share of the change between the ends; uniform steps: 1/32) and
    ``path_jump_share`` (share of paths with a step above 0.25); ``*_unconstrained``: the same for
    the seed's weights.
    """
    z = obs.z.double()
    alb = directional_albedo(obs.z, obs.grid)
    s, d = gram(obs.z, obs.cosine_weights())
    fit = fit_gplvm(s, d, 2, max_iter=max_iter, mu=1e-6, generator=torch.Generator().manual_seed(0), **stop)
    model = GPLVM(fit, z, albedo=alb)
    lat = model.latents
    dist = torch.cdist(lat, lat)
    dist.fill_diagonal_(math.inf)
    firsts = torch.randperm(lat.shape[0], generator=torch.Generator().manual_seed(5))[:pairs].tolist()
    pp = [(i, int(dist[i].argmin())) for i in firsts]
    out: dict = {"path_pairs": [[obs.names[i], obs.names[j]] for i, j in pp]}
    for key, valid in (("", None), ("_unconstrained", "none")):
        prof = straight_paths(model, pp, z, alb, obs.grid, valid=valid)
        out[f"path_monotone_share{key}"] = float(prof.monotone.double().mean())
        out[f"path_jump_max{key}"] = float(prof.jump.max())
        out[f"path_jump_median{key}"] = float(prof.jump.median())
        out[f"path_jump_share{key}"] = float((prof.jump > 0.25).double().mean())
        if not key:
            out["path_profiles"] = {
                "albedo": [[round(float(v), 4) for v in row] for row in prof.albedo[:4]],
                "width": [[round(float(v), 4) for v in row] for row in prof.width[:4]],
            }
    _log(f"paths: monotone {out['path_monotone_share']:.2f}, jump max {out['path_jump_max']:.3f}")
    return out


def gi_experiment(obs: Observations, ends: tuple, quick: bool) -> dict:
    """Seed Eq. 12: blend GI renders of k materials; compare with a GI render of the interpolated BRDF.

    k materials (the two ends and their nearest neighbours by Gram distance), a GPLVM on them, the
    midpoint of their best path; renders share their random numbers (same seed), so the difference
    is the L2+ paths (and the clamp of negative values), not independent noise.
    """
    k = 4 if quick else 6
    z = obs.z.double()
    i0 = obs.names.index(ends[0]) if isinstance(ends[0], str) else int(ends[0])
    i1 = obs.names.index(ends[1]) if isinstance(ends[1], str) else int(ends[1])
    dist = torch.cdist(z, z[[i0, i1]]).min(1).values
    sub = sorted(set([i0, i1] + dist.argsort()[: k + 2].tolist()))[:k]
    if i1 not in sub:
        sub[-1] = i1
    zk = z[sub]
    s, d = gram(zk, obs.cosine_weights())
    model = GPLVM(fit_gplvm(s, d, 2, max_iter=300, generator=torch.Generator().manual_seed(0)), zk, valid=SEED)
    path = best_path(model, sub.index(i0), sub.index(i1), variance_weight=10.0, resolution=24)
    w = path.weights[len(path.weights) // 2]
    scene = sphere_scene(24 if quick else 48)
    out = {"gi_materials": [obs.names[i] for i in sub]}
    for bounces in (1, 3):
        spp = 2 if quick else 8
        rows = torch.cat([zk, torch.zeros_like(zk[:1])])  # the last render: a black material
        imgs = render_rows(scene, "sample", rows, obs.grid, spp=spp, max_bounces=bounces, progress=False)
        rec = material_record(imgs[:-1], constant=imgs[-1])
        ref = render_rows(scene, "sample", (w @ zk)[None], obs.grid, spp=spp, max_bounces=bounces, progress=False)[0]
        err = gi_blend_error(blend(rec, w), ref)
        tag = "direct" if bounces == 1 else "gi"
        out[f"{tag}_blend_rel_l1"], out[f"{tag}_blend_rel_rmse"] = err["rel_l1"], err["rel_rmse"]
    out["gi_midpoint_negative_fraction"] = float(((w @ zk) < 0).double().mean())
    out["gi_weights"] = [round(float(v), 4) for v in w]  # L2+ is quadratic in rho: large cancelling weights hurt
    # control: a convex blend (weights 1/k) of the same renders, where Eq. 12 should hold up to L2+
    wc = torch.full((len(sub),), 1.0 / len(sub), dtype=torch.float64)
    ref = render_rows(scene, "sample", (wc @ zk)[None], obs.grid, spp=spp, max_bounces=3, progress=False)[0]
    out["gi_convex_blend_rel_l1"] = gi_blend_error(blend(rec, wc), ref)["rel_l1"]
    return out


def _fit_section(obs: Observations, max_iter: int, stop: dict, out: dict) -> dict:
    """Fits on all materials, continuity, the optimiser comparison; fills ``out``, returns our q = 2 fit."""
    for q in (2, 5):
        r = fit_all(obs, q, max_iter, **stop)
        _log(f"q={q}: loglik {r['loglik']:.6g} in {r['seconds']:.3f} s ({r['iterations']} it), repro {r['repro']:.2e}")
        out[f"fit_s_q{q}"] = round(r["seconds"], 4)
        out[f"loglik_q{q}"] = r["loglik"]
        out[f"iterations_q{q}"] = r["iterations"]
        out[f"objective_ms_q{q}"] = round(1e3 * r["objective_s"], 4)
        out[f"fit_q{q}_in_objective_evaluations"] = round(r["seconds"] / r["objective_s"], 1)
        out[f"fit_cpu_s_q{q}"] = round(r["cpu_seconds"], 4)
        out[f"monotone_q{q}"] = r["monotone"]
        out[f"repro_rel_err_q{q}"] = r["repro"]
        out[f"loglik_curve_q{q}"] = r["curve"]
        if q == 2:
            model2 = r["model"]
            ours_q2 = r
    z = obs.z.double()
    smooth = GPLVM(model2.fit, z, continuous=True, valid=SEED)
    s_all, d_all = gram(obs.z, obs.cosine_weights())
    seed_fit = fit_gplvm(s_all, d_all, 2, max_iter=max_iter, generator=torch.Generator().manual_seed(0))
    jumps = row_jump(GPLVM(seed_fit, z, valid=SEED))
    out["continuity_max"] = float(row_jump(smooth).max())
    out["continuity_max_seed"] = float(jumps.max())
    out["continuity_seed_share_above_1pct"] = float((jumps > 0.01).double().mean())
    out["repro_rel_err_smooth_q2"] = float(
        ((smooth.predict(smooth.latents) - z).abs().max(1).values / z.abs().max(1).values).max()
    )
    _log(f"continuity: smooth mean {out['continuity_max']:.3g}, seed interpolant {out['continuity_max_seed']:.3g}")
    peer = wolfe_peer(obs, 2, max_iter)
    out["lbfgs_wolfe_loglik_q2"], out["lbfgs_wolfe_s_q2"] = peer["loglik"], round(peer["seconds"], 3)
    cold = fit_all(obs, 2, max_iter, warmup_mu=None, **stop)
    out["loglik_q2_no_warmup"], out["fit_s_q2_no_warmup"] = cold["loglik"], round(cold["seconds"], 4)
    _log(f"ours q=2 without the mu warm-up: {cold['loglik']:.6g} in {cold['seconds']:.2f} s")
    _log(f"strong-Wolfe L-BFGS q=2: {peer['loglik']:.6g} in {peer['seconds']:.2f} s")
    return ours_q2


def _parser() -> argparse.ArgumentParser:
    """The benchmark's command-line options."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small grid and short fits")
    ap.add_argument("--cache", type=Path, default=None, help="observation-matrix cache file")
    ap.add_argument("--max-iter", type=int, default=None, help="GPLVM iterations (default 1000, quick 200)")
    ap.add_argument("--no-peer", action="store_true", help="skip the GPyTorch comparison")
    ap.add_argument("--peer-seconds", type=float, default=900.0, help="time cap of the GPyTorch / GPy runs")
    ap.add_argument("--tol", type=float, default=1e-10, help="fit stop: L rose by < tol |L| over --tol-window its")
    ap.add_argument("--tol-window", type=int, default=1, help="iterations of the --tol test")
    ap.add_argument(
        "--negatives", choices=NEGATIVES, default="penalise", help="held-out placement (project_perceptual)"
    )
    ap.add_argument("--fits-only", action="store_true", help="fits, continuity and the optimiser comparison only")
    ap.add_argument("--heldout-only", action="store_true", help="fits, continuity, optimisers, held-out study only")
    ap.add_argument("--splits", type=int, default=5, help="random 80/20 splits (0 = the family hold-outs only)")
    ap.add_argument("--budget-map", default="", help="budgets (e.g. 60,100,200) of the ours-vs-torch L-BFGS map, q = 2")
    ap.add_argument("--qs", default="2,3,5", help="latent dimensions of the held-out study (e.g. one per process)")
    ap.add_argument("--skip-fits", action="store_true", help="no fits / continuity / optimisers (with --heldout-only)")
    ap.add_argument("--no-seed-config", action="store_true", help="held-out study without the seed's configuration")
    ap.add_argument(
        "--negative-weight", type=float, default=NEGATIVE_WEIGHT, help="placement: factor on negative values"
    )
    ap.add_argument("--max-columns", type=int, default=8192, help="columns the placement search sees (0 = all)")
    ap.add_argument("--valid", choices=VALIDITY, default=SEED, help="blend weights of the held-out study")
    ap.add_argument("--validity-only", action="store_true", help="the validity study only (no fits / peers)")
    ap.add_argument("--validity-splits", type=int, default=None, help="validity study splits (default 5, quick 2)")
    ap.add_argument("--family-seed", type=int, default=FAMILY_SEED, help="draw of the default study's families")
    ap.add_argument("--no-default-study", action="store_true", help="skip the default model's held-out study")
    return ap


def main(argv=None) -> dict:
    args = _parser().parse_args(argv)
    stop = {"tol": args.tol, "tol_window": args.tol_window}
    place = {"negatives": args.negatives, "negative_weight": args.negative_weight}
    place["max_columns"] = args.max_columns or None
    place["valid"] = args.valid
    quick = args.quick
    max_iter = args.max_iter or (200 if quick else 1000)
    out: dict = {"quick": quick, "threads": torch.get_num_threads(), "load_start": os.getloadavg()[0]}
    out["settings"] = {"max_iter": max_iter, **stop, **place}
    out["splits"] = args.splits  # random 80/20 splits of the held-out study
    obs, desc = load_data(quick, args.cache)
    out["data"] = desc
    out["n_materials"], out["d"] = obs.z.shape
    vsplits = args.validity_splits if args.validity_splits is not None else (2 if quick else 5)
    out.update(validity_study(obs, max_iter, vsplits, **stop))
    out.update(path_study(obs, max_iter, **stop))
    if not args.no_default_study:
        out.update(default_study(obs, max_iter, vsplits, args.family_seed, **stop))
    if args.validity_only:
        out["load_end"] = os.getloadavg()[0]
        print(json.dumps(out))
        return out
    if not args.skip_fits:
        ours_q2 = _fit_section(obs, max_iter, stop, out)
    if args.budget_map:
        bm = budget_map(obs, 2, tuple(int(v) for v in args.budget_map.split(",")))
        out["lbfgs_wolfe_budget_map_q2"] = bm
        out["budgets_ours_at_least_wolfe_q2"] = [b for b, v in bm.items() if v["ours"] >= v["torch"]]
    if args.fits_only:
        out["load_end"] = os.getloadavg()[0]
        print(json.dumps(out))
        return out
    qs = tuple(int(v) for v in args.qs.split(","))
    study = heldout_study(obs, max_iter, args.splits, with_seed=not args.no_seed_config, qs=qs, **stop, **place)
    out.update(study)
    if args.heldout_only or args.skip_fits:
        out["load_end"] = os.getloadavg()[0]
        print(json.dumps(out))
        return out
    hj = fit_all(obs, 2, 30 if quick else 100, method="hooke-jeeves")
    out["hj_fit_s_q2"], out["hj_loglik_q2"], out["hj_sweeps_q2"] = (
        round(hj["seconds"], 3),
        hj["loglik"],
        hj["iterations"],
    )
    _log(f"Hooke-Jeeves q=2: {hj['loglik']:.6g} in {hj['seconds']:.2f} s")
    model2 = ours_q2["model"]
    rate, rows = interp_rate(model2, obs.z, quick)
    out["interp_per_s"], out["predict_rows_per_s"] = round(rate), round(rows, 1)
    ends = ("chrome", "silver-paint") if obs.source == "nbrdf" else (0, 5)
    out.update(limitation(model2, obs, ends, quick))
    _log(
        f"limitation: path max negative fraction {out['path_negative_fraction_max']:.3f}, "
        f"max albedo {out['path_max_albedo']:.3g}"
    )
    out.update(gi_experiment(obs, ends, quick))
    _log(f"GI blend vs render: rel L1 {out['gi_blend_rel_l1']:.3g} (direct light: {out['direct_blend_rel_l1']:.2g})")
    split_file = ROOT / "datasets" / "merl_split.txt"
    by_file = obs.source == "nbrdf" and split_file.is_file()  # an installed package has no datasets/
    train, test = read_split(split_file) if by_file else split_names(obs.names)
    out["split"] = str(split_file.relative_to(ROOT)) if by_file else "split_names (every 5th)"
    for q in (2, 5):
        h = heldout_reconstruction(
            obs, train, test, q, max_iter=max_iter, generator=torch.Generator().manual_seed(0), **stop, **place
        )
        sm = h.summary()
        _log(f"held-out q={q}: {sm}")
        suffix = "" if q == 5 else "_q2"
        for k in ("heldout_logrmse", "pca_heldout_logrmse", "heldout_cosrmse", "pca_heldout_cosrmse"):
            out[k + suffix] = sm[k]
        out[f"heldout_wins_vs_pca{suffix}"] = int((h.gplvm_logrmse < h.pca_logrmse).sum())
    out["blend_fps_512"] = round(blend_fps(obs.z.shape[0], 512, 5 if quick else 20), 2)
    _log(f"blend 512x512 x {obs.z.shape[0]} materials: {out['blend_fps_512']} fps")
    if not args.no_peer:
        peer = gpytorch_peer(obs, 2, ours_q2["loglik"], seconds_cap=args.peer_seconds)
        if peer is not None:
            out["gpytorch_s_q2"] = round(peer["seconds"], 3)
            out["gpytorch_iterations_q2"] = peer["iterations"]
            out["gpytorch_loglik_q2"] = peer["loglik"]
            reached = peer["seconds_to_our_loglik"]
            out["gpytorch_s_to_our_loglik_q2"] = None if reached is None else round(reached, 3)
            out["time_ratio_gpytorch_over_ours"] = round(peer["seconds"] / max(ours_q2["seconds"], 1e-9), 2)
            out["loglik_ours_minus_gpytorch"] = ours_q2["loglik"] - peer["loglik"]
            _log(f"GPyTorch q=2 (L-BFGS): {peer['loglik']:.6g} in {peer['seconds']:.2f} s (reached ours: {reached})")
        gp = gpy_peer(obs, 2, GPY_MU, max_iter, seconds_cap=args.peer_seconds)
        if gp is None:
            out["gpy"] = "not installed"
        else:
            out["gpy"] = gp
            reached = gp["gpy_s_to_our_loglik"]
            out["time_ratio_gpy_over_ours"] = None if reached is None else round(reached / gp["ours_s"], 1)
            _log(f"GPy q=2 (mu {GPY_MU:g}): {gp}")
    out["load_end"] = os.getloadavg()[0]
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
