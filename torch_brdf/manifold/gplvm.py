r"""GPLVM over an observation matrix, fitted through its Gram matrix.

Seed: Soler, Subr, Nowrouzezahrai 2017 (INRIA RR-9069), Sec. 3.1. The latents
:math:`X \in \mathbb{R}^{N \times Q}` maximise (Eq. 6)

.. math:: L(X) = -\frac{d}{2}\log|K| - \frac{1}{2}\operatorname{tr}(K^{-1} Z Z^\top),

with :math:`K_{ij} = c(x_i, x_j)` the shifted SE kernel (Eq. 5). ``L`` depends on ``Z`` only
through the Gram matrix :math:`S = Z Z^\top` (N x N) and the width ``d``, so every optimiser
here takes ``(S, d)``: a step costs :math:`O(N^3)` whatever ``d`` (never :math:`O(N^2 d)`, never
a d x d matrix). :func:`gram` accumulates ``S`` over column chunks, so the full MERL grid
never has to be in memory at once.

Two optimisers, both monotone (the log-likelihood never decreases over the recorded
iterations):

* ``"lbfgs"`` (default): L-BFGS (memory 20, compact inverse-Hessian product) on the exact gradient — closed
  form :func:`log_likelihood_and_grad`, or autograd through the float64 Cholesky with
  ``autograd=True`` (equal, tested) — with our strong-Wolfe line search (:mod:`.linesearch`, c1 = 1e-4,
  c2 = 0.9) and, where it ends on a point that does not raise ``L``, a backtracking Armijo
  search; when no step length passes, the curvature memory is dropped, then the fit stops.
* ``"adam"``: autograd + Adam, a step that lowers ``L`` is undone and the learning rate halved.
* ``"hooke-jeeves"``: the seed's derivative-free direct search (Hooke and Jeeves 1961),
  one latent coordinate at a time, keeping :math:`K^{-1}`, :math:`\log|K|` and
  :math:`\operatorname{tr}(K^{-1}S)` up to date with two Sherman–Morrison updates and the
  matrix determinant lemma per trial (:math:`O(N^2)`), refactorised once per sweep.

Data scale: the kernel has unit amplitude, so ``L`` depends on the scale of ``Z``. By
default (``normalise=True``) ``S`` is divided by its mean diagonal entry per column,
:math:`s = \operatorname{tr}(S)/(N d)` (``Z`` rescaled to unit mean square); the
reported log-likelihoods are those of the normalised data. Interpolants do not depend on
it (they are linear in the raw ``Z``).
"""

from __future__ import annotations

import contextlib
import math
import time
import warnings
from collections.abc import Callable, Iterable

import numpy as np
import torch
from scipy.linalg import lapack
from tqdm.auto import tqdm

from ..data import progress_default
from ..errors import NumericalError, ShapeError, ValueRangeError
from ..parallel.threads import single_thread
from ..records.fits import GPLVMFit
from .kernel import JITTER_CAP, JITTER_FLOOR, JitterWarning, cholesky_jitter, cross_kernel, kernel_matrix, se_kernel
from .linesearch import strong_wolfe

FIT_KIND = GPLVMFit.kind
_METHODS = ("lbfgs", "adam", "hooke-jeeves")
#: blend-weight constraints of :class:`GPLVM` (its ``valid`` argument)
VALIDITY = ("none", "simplex", "energy")
#: the default warm-up mu of :func:`fit_gplvm`: fits at a mu 100x smaller or less start there (chosen
#: among 1e-6 ... 1e-4 on a MERL budget map of ``benchmarks/manifold.py``: a selection, not a law)
WARMUP_MU = 3e-6
#: the warm-up runs only when the fit's mu is at most this fraction of ``warmup_mu``
WARMUP_RATIO = 1e-2


# -- Gram matrix ----------------------------------------------------------------------------------
def _check_matrix(z: torch.Tensor, name: str) -> torch.Tensor:
    if not isinstance(z, torch.Tensor):
        z = torch.as_tensor(np.asarray(z))
    if z.ndim != 2 or z.shape[0] < 2 or z.shape[1] < 1:
        raise ShapeError(f"Expected {name} to have shape (N, d) with N >= 2; got {tuple(z.shape)}")
    if not z.is_floating_point():
        z = z.to(torch.float64)
    return z


def gram(
    z: torch.Tensor | Iterable[torch.Tensor],
    weights: torch.Tensor | None = None,
    chunk: int = 1 << 16,
) -> tuple[torch.Tensor, int]:
    r"""Gram matrix :math:`S = (Z W)(Z W)^\top` in float64, accumulated over column chunks.

    Args:
        z: (N, d) observation matrix, or an iterable of (N, d_k) column blocks (e.g. read
            from disk one block at a time); rows are materials.
        weights: (d,) non-negative per-column weights :math:`w` (:math:`W = \mathrm{diag}(w)`),
            e.g. a cosine map; only for a single matrix ``z``. None = 1.
        chunk: columns per block when ``z`` is one matrix (memory only).
    Returns:
        (S, d): S (N, N) float64 symmetric, d the total number of columns.
    Raises:
        ShapeError: wrong shapes. ValueRangeError: NaN/Inf in ``z`` or bad weights.
    """
    blocks = [z] if isinstance(z, torch.Tensor | np.ndarray) else z
    s = None
    d = 0
    for blk in blocks:
        blk = _check_matrix(blk, "z").detach()
        if weights is not None:
            if not isinstance(z, torch.Tensor | np.ndarray):
                raise ShapeError("weights are only supported with a single (N, d) matrix")
            w = torch.as_tensor(weights, dtype=torch.float64)
            if w.shape != (blk.shape[1],) or not bool(torch.isfinite(w).all()) or bool((w < 0).any()):
                raise ValueRangeError(f"weights must be finite, >= 0, of shape ({blk.shape[1]},); got {tuple(w.shape)}")
        for a in range(0, blk.shape[1], chunk):
            part = blk[:, a : a + chunk].to(torch.float64)
            if not bool(torch.isfinite(part).all()):
                raise ValueRangeError(
                    f"z holds non-finite values (NaN/Inf) in columns {d + a}..{d + a + part.shape[1] - 1}"
                )
            if weights is not None:
                part = part * w[a : a + chunk]
            s = part @ part.T if s is None else s + part @ part.T
        d += blk.shape[1]
    if s is None:
        raise ShapeError("z has no columns")
    return s, d


def _check_gram(s: torch.Tensor, d: int) -> torch.Tensor:
    if not isinstance(s, torch.Tensor) or s.ndim != 2 or s.shape[0] != s.shape[1] or s.shape[0] < 2:
        raise ShapeError(f"Expected a square Gram matrix S (N, N), N >= 2; got {getattr(s, 'shape', type(s))}")
    if not bool(torch.isfinite(s).all()):
        raise ValueRangeError("Gram matrix S holds NaN/Inf")
    if int(d) < 1:
        raise ValueRangeError(f"d (number of columns of Z) must be >= 1; got {d}")
    return s.detach().to(torch.float64)


# -- objective ------------------------------------------------------------------------------------
def log_likelihood(
    x: torch.Tensor, s: torch.Tensor, d: int, lengthscale: float = 1.0, mu: float = 1e-6
) -> torch.Tensor:
    r"""GPLVM log-likelihood (seed Eq. 6, without the constant :math:`-\frac{Nd}{2}\log 2\pi`).

    :math:`L = -\frac{d}{2}\log|K| - \frac{1}{2}\operatorname{tr}(K^{-1}S)` via a float64 Cholesky
    of :math:`K = K_{SE}(X) + \mu I`. Differentiable in ``x``.

    Args:
        x: (N, Q) latents. s: (N, N) Gram matrix :math:`ZZ^\top`. d: columns of Z.
        lengthscale: kernel hyperparameters (Eq. 5).
        mu: as ``lengthscale``.
    Returns:
        () float64; ``-inf`` when K is not positive definite at this ``mu`` (no jitter here).
    """
    k = kernel_matrix(x.to(torch.float64), lengthscale, mu)
    chol, info = torch.linalg.cholesky_ex(k)
    if int(info) != 0:
        return torch.tensor(-math.inf, dtype=torch.float64)
    logdet = 2 * torch.log(torch.diagonal(chol)).sum()
    a = torch.cholesky_solve(s, chol)
    return -0.5 * d * logdet - 0.5 * torch.diagonal(a).sum()


def pca_latents(s: torch.Tensor, q: int) -> torch.Tensor:
    """Truncated linear PCA of the rows of Z from the Gram matrix alone (the seed's start).

    The centred Gram matrix :math:`HSH` (H the centring matrix) has eigenvectors ``U`` and
    eigenvalues ``λ``; the PCA scores are :math:`U_q \\sqrt{λ_q}`. They are rescaled by one common
    factor so the first coordinate has unit standard deviation (relative scales kept), i.e. a
    latent spread of the order of the kernel's unit lengthscale. Deterministic: each
    eigenvector's sign is fixed so its largest-magnitude entry is positive.

    Args:
        s: (N, N) Gram matrix. q: latent dimension (<= N - 1).
    Returns:
        (N, q) float64.
    """
    n = s.shape[0]
    h = torch.eye(n, dtype=torch.float64) - 1.0 / n
    sc = h @ s.to(torch.float64) @ h
    sc = 0.5 * (sc + sc.T)
    evals, evecs = torch.linalg.eigh(sc)
    evals, evecs = evals.flip(0)[:q].clamp_min(0), evecs.flip(1)[:, :q]
    big = evecs.abs().argmax(0)
    evecs = evecs * torch.sign(evecs[big, torch.arange(q)])[None, :]
    x = evecs * evals.sqrt()[None, :]
    sd = x[:, 0].std()
    return (x / sd if float(sd) > 0 else x).contiguous()


# -- optimisers ----------------------------------------------------------------------------------
def _check_hyper(q: int, n: int, lengthscale: float, mu: float) -> None:
    if not isinstance(q, int) or not 1 <= q <= min(n - 1, 32):
        raise ValueRangeError(f"latent dimension q must be an int in 1..{min(n - 1, 32)} for N = {n}; got {q!r}")
    if not (math.isfinite(lengthscale) and lengthscale > 0):
        raise ValueRangeError(f"lengthscale must be finite and > 0; got {lengthscale}")
    if not (math.isfinite(mu) and mu >= 0):
        raise ValueRangeError(f"mu must be finite and >= 0; got {mu}")


def _initial_jitter(x: torch.Tensor, lengthscale: float, mu: float, floor: float, cap: float) -> float:
    with small_matrix_mode(x.shape[0]):
        _, jitter = cholesky_jitter(kernel_matrix(x, lengthscale, mu), floor, cap, what="GPLVM K", warn=False)
    return jitter


def _start_latents(s: torch.Tensor, q: int, init, generator: torch.Generator | None) -> torch.Tensor:
    """(N, q) starting latents: ``init`` (checked), else PCA's, nudged by a tiny seeded noise."""
    n = s.shape[0]
    if init is None:
        with small_matrix_mode(n):
            x0 = pca_latents(s, q)
        # duplicated rows give coincident PCA latents, a saddle of L with a symmetric gradient;
        # a tiny seeded nudge lets the optimiser separate them (it does not change a good start)
        noise = torch.randn(x0.shape, generator=generator, dtype=torch.float64)
        return x0 + 1e-6 * noise * float(x0.std().clamp_min(1e-12))
    x0 = torch.as_tensor(init, dtype=torch.float64).clone().contiguous()
    if x0.shape != (n, q) or not bool(torch.isfinite(x0).all()):
        raise ValueRangeError(f"init must be finite of shape ({n}, {q}); got {tuple(x0.shape)}")
    return x0


def _check_warmup_and_window(warmup_fraction: float, tol_window, method: str) -> None:
    if not 0 <= warmup_fraction < 1:
        raise ValueRangeError(f"warmup_fraction must be in [0, 1); got {warmup_fraction}")
    if not isinstance(tol_window, int) or tol_window < 1 or (tol_window > 1 and method != "lbfgs"):
        raise ValueRangeError(f"tol_window must be an int >= 1 (> 1 only with method='lbfgs'); got {tol_window!r}")


def fit_gplvm(
    s: torch.Tensor,
    d: int,
    q: int = 2,
    *,
    lengthscale: float = 1.0,
    mu: float = 1e-6,
    method: str = "lbfgs",
    max_iter: int = 500,
    tol: float = 1e-10,
    init: torch.Tensor | None = None,
    normalise: bool = True,
    jitter_floor: float = JITTER_FLOOR,
    jitter_cap: float = JITTER_CAP,
    lr: float = 0.05,
    autograd: bool = False,
    names: Iterable[str] = (),
    generator: torch.Generator | None = None,
    progress: bool | None = None,
    callback: Callable[[int, float], None] | None = None,
    warmup_mu: float | None = WARMUP_MU,
    warmup_fraction: float = 0.2,
    tol_window: int = 1,
) -> GPLVMFit:
    r"""Maximise the GPLVM log-likelihood (seed Eq. 6) over the latents, from a PCA start.

    Args:
        s: (N, N) Gram matrix :math:`ZZ^\top` (from :func:`gram`, possibly cosine-weighted).
        d: number of columns of Z (the :math:`d/2\,\log|K|` factor).
        q: latent dimension (the seed uses 2..5).
        lengthscale: kernel hyperparameters (Eq. 5; seed: 1 and 1e-6).
        mu: as ``lengthscale``.
        method: ``"lbfgs"`` (exact gradient, strong-Wolfe line search, monotone), ``"adam"``
            (autograd, step halving on a decrease) or ``"hooke-jeeves"`` (the seed's direct search).
        max_iter: iterations (L-BFGS/Adam steps; Hooke–Jeeves sweeps over all coordinates).
        tol: stop when the last ``tol_window`` iterations together improved L by less
            than ``tol * |L|`` (``tol_window > 1``: L-BFGS only; on this multimodal objective single
            iterations can gain little just before a larger gain, so a window is the safer test).
        tol_window: as ``tol``.
        init: (N, q) starting latents (default :func:`pca_latents`).
        normalise: divide S by :math:`\operatorname{tr}(S)/(Nd)` (unit mean square entries).
        jitter_floor: Cholesky jitter escalation (x10 steps) when :math:`K` is not
            positive definite at ``mu``; the jitter used is in the result and warned about.
        jitter_cap: as ``jitter_floor``.
        lr: Adam learning rate / initial Hooke–Jeeves step (in latent units).
        autograd: L-BFGS gradients by autograd through the Cholesky (:func:`log_likelihood`)
            instead of the closed form of :func:`log_likelihood_and_grad` (equal, tested; the
            closed form is ~5x cheaper). Adam always uses autograd.
        names: row labels kept in the result.
        generator: breaks exact ties of a degenerate PCA start (duplicated rows) with a tiny
            seeded perturbation (1e-6 of the latent spread); None = ``torch.default_generator``.
        progress: tqdm bar over iterations.
        callback: called as ``callback(iteration, loglik)`` after every accepted iteration.
        warmup_mu: continuation in :math:`\mu` (L-BFGS only): when ``mu`` is
            at most ``warmup_mu / 100``, the first ``warmup_fraction`` of ``max_iter`` iterations maximise
            L at ``warmup_mu`` (a better conditioned K), the rest at ``mu`` from there. The
            recorded ``loglik`` is that of the final ``mu`` only (non-decreasing);
            ``meta["warmup"]`` gives the warm-up's ``mu``, iterations and seconds (counted in
            ``seconds``). None (or ``mu > warmup_mu / 100``) = no warm-up. At ``mu = 1e-10`` the PCA
            start has a hugely negative L (near-coincident latents make K nearly singular) and
            the warm-up reached a higher final L than strong-Wolfe L-BFGS from the PCA start on the
            MERL data at budgets of 150 to 1000 iterations, not at 60 or 100 (both need ~60
            iterations to leave the start's region; ``benchmarks/manifold.py``).
        warmup_fraction: as ``warmup_mu``.
    Returns:
        :class:`GPLVMFit`.
    Raises:
        ValueRangeError: bad q / hyperparameters / non-finite S. NumericalError: K not positive
            definite even at ``jitter_cap``.
    """
    s = _check_gram(s, d)
    n = s.shape[0]
    _check_hyper(q, n, lengthscale, mu)
    if method not in _METHODS:
        raise ValueRangeError(f"method must be one of {_METHODS}; got {method!r}")
    scale = float(torch.diagonal(s).sum()) / (n * d) if normalise else 1.0
    if not scale > 0:
        raise ValueRangeError("Z is all zeros (tr(S) = 0): nothing to fit")
    s = s / scale
    t0 = time.perf_counter()  # the start (PCA, jitter) counts in ``seconds``
    x0 = _start_latents(s, q, init, generator)
    _check_warmup_and_window(warmup_fraction, tol_window, method)
    window = {"window": tol_window} if method == "lbfgs" else {}
    meta, n_warm = {}, round(warmup_fraction * max_iter)
    if method == "lbfgs" and warmup_mu is not None and mu <= WARMUP_RATIO * warmup_mu and n_warm > 0:
        jw = _initial_jitter(x0, lengthscale, warmup_mu, jitter_floor, jitter_cap)
        with small_matrix_mode(n):
            x0, hist_w, _, _ = _fit_lbfgs(x0, s, d, lengthscale, warmup_mu, jw, n_warm, tol, lr, progress, None,
                                          jitter_floor, jitter_cap, autograd, **window)  # fmt: skip
        meta["warmup"] = {"mu": float(warmup_mu), "iterations": len(hist_w) - 1, "seconds": time.perf_counter() - t0}
        max_iter -= n_warm
    jitter = _initial_jitter(x0, lengthscale, mu, jitter_floor, jitter_cap)
    with small_matrix_mode(n):
        run = {"lbfgs": _fit_lbfgs, "adam": _fit_adam, "hooke-jeeves": _fit_hooke_jeeves}[method]
        x, hist, rejected, jitter = run(
            x0, s, d, lengthscale, mu, jitter, max_iter, tol, lr, progress, callback, jitter_floor, jitter_cap,
            autograd, **window,
        )  # fmt: skip
    seconds = time.perf_counter() - t0
    if not bool(torch.isfinite(x).all()):  # pragma: no cover - guarded by the accept test
        raise NumericalError("GPLVM latents became non-finite")
    if jitter > 0:
        warnings.warn(
            f"GPLVM fit: K needed diagonal jitter {jitter:.1e} on top of mu = {mu:g}", JitterWarning, stacklevel=2
        )
    return GPLVMFit(
        latents=x.detach().clone(),
        lengthscale=float(lengthscale),
        mu=float(mu),
        jitter=float(jitter),
        loglik=torch.tensor(hist, dtype=torch.float64),
        d=int(d),
        data_scale=scale,
        method=method,
        iterations=len(hist) - 1,
        rejected=rejected,
        seconds=seconds,
        names=tuple(names),
        meta=meta,
    )


@contextlib.contextmanager
def small_matrix_mode(n: int):
    """Settings for many small (N x N) float64 factorisations, restored after the block.

    * Subnormal floats are flushed to zero: far-apart latents give kernel entries and
      Cholesky intermediates in the float64 subnormal range, where x86 arithmetic is ~30x
      slower; zero is exact enough there (torch's default, off, is restored).
    * One intra-op thread when N < 512: a 100 x 100 Cholesky is ~10x slower with 2 threads on
      a loaded 2-core machine (measured 1.2 ms vs 11 ms per objective evaluation).
    """
    torch.set_flush_denormal(True)
    try:
        with single_thread(n < 512):
            yield
    finally:
        torch.set_flush_denormal(False)


def _converged(old: float, new: float, tol: float) -> bool:
    return abs(new - old) <= tol * max(1.0, abs(old))


def log_likelihood_and_grad(
    x: torch.Tensor, s: torch.Tensor, d: int, lengthscale: float = 1.0, mu: float = 1e-6
) -> tuple[float, torch.Tensor | None]:
    r"""L (seed Eq. 6) and its analytic gradient :math:`\partial L/\partial X` in :math:`O(N^3)`.

    :math:`G = \partial L/\partial K = \tfrac12(K^{-1} S K^{-1} - d K^{-1})`; with
    :math:`A = G \odot K_{SE}`, :math:`\partial L/\partial x_i = -\frac{2}{\ell^2}\sum_j A_{ij}(x_i - x_j)`.
    Equal to autograd through :func:`log_likelihood` (tested) at a fraction of the cost; computed
    by :func:`_objective` in numpy (LAPACK ``potrf``/``potri`` and two N x N products, no torch
    dispatch per operation: the fit's unit of work).

    Args:
        x: (N, Q). s: (N, N). d: columns of Z.
    Returns:
        (L, grad (N, Q) float64), or (-inf, None) where K is not positive definite.
    """
    xn = np.ascontiguousarray(x.detach().to(torch.float64).numpy())
    sn = np.ascontiguousarray(s.detach().to(torch.float64).numpy())
    ll, g = _objective(xn, sn, d, lengthscale, mu)
    return ll, None if g is None else torch.from_numpy(g)


def _objective(x: np.ndarray, s: np.ndarray, d: int, ell: float, mu: float) -> tuple[float, np.ndarray | None]:
    """:func:`log_likelihood_and_grad` on float64 numpy arrays: x (N, Q), s (N, N) -> (L, grad (N, Q))."""
    n = x.shape[0]
    sq = np.zeros((n, n))
    for k in range(x.shape[1]):  # differences per latent axis: exact 0 on coincident points (as se_kernel)
        diff = x[:, k, None] - x[None, :, k]
        sq += diff * diff
    kse = np.exp(sq * (-0.5 / ell**2))
    k = kse.copy()
    k.flat[:: n + 1] += mu
    chol, info = lapack.dpotrf(k, lower=1, clean=1, overwrite_a=1)
    if info != 0:
        return -math.inf, None
    kinv, info = lapack.dpotri(chol, lower=1)
    if info != 0:  # pragma: no cover - a successful potrf has a non-singular factor
        return -math.inf, None
    kinv = kinv + kinv.T  # potri fills the lower triangle; the upper one is 0 (clean potrf factor)
    kinv.flat[:: n + 1] *= 0.5
    a = kinv @ s
    ll = -d * float(np.log(np.diagonal(chol)).sum()) - 0.5 * float(np.trace(a))
    g = a @ kinv
    g -= d * kinv
    g = 0.25 * (g + g.T)
    w = g * kse
    return ll, (-2.0 / ell**2) * (w.sum(1)[:, None] * x - w @ x)


def _value_and_grad(
    x: np.ndarray, s: np.ndarray, d, ell, mu, autograd: bool = False
) -> tuple[float, np.ndarray | None]:
    """L and its gradient (N, Q) at latents ``x`` (N, Q) (numpy): the closed form, or autograd."""
    if not autograd:
        return _objective(x, s, d, ell, mu)
    xr = torch.from_numpy(x).clone().requires_grad_(True)
    ll = log_likelihood(xr, torch.from_numpy(s), d, ell, mu)
    if not bool(torch.isfinite(ll)):
        return -math.inf, None
    (g,) = torch.autograd.grad(ll, xr)
    return float(ll.detach()), g.numpy()


def _wolfe_step(x, p, f, slope, s, d, ell, mu, autograd) -> tuple[float, np.ndarray | None, float]:
    """One strong-Wolfe line search (c1 = 1e-4, c2 = 0.9; :func:`.linesearch.strong_wolfe`) along
    the ascent direction ``p`` ((N, Q) numpy) from ``x``: returns (L, grad, step) at the accepted point."""
    scale = float(x.shape[0] * d)

    def phi(t):
        fv, gv = _value_and_grad(x + t * p, s, d, ell, mu, autograd)
        if gv is None:  # K not positive definite: an infinitely bad value (the search shrinks the step)
            return math.inf, math.nan, None
        return -fv / scale, -float(np.vdot(gv, p)) / scale, gv

    res = strong_wolfe(phi, -f / scale, -slope / scale, 1.0)
    if res.payload is None or not res.step > 0:
        return -math.inf, None, 0.0
    return -res.value * scale, res.payload, res.step


def _two_loop(g: np.ndarray, pairs: list[tuple[np.ndarray, np.ndarray, float]]) -> np.ndarray:
    """L-BFGS product H g for the stored pairs (flat vectors), oldest first; H0 = (s^T y / y^T y) I.

    The compact representation of Byrd, Nocedal and Schnabel (1994, Eq. 3.1; Nocedal and Wright,
    Eq. 7.24): a few matrix products instead of the two-loop recursion (Alg. 7.4) it equals
    (tested against the dense BFGS update): with N Q of a few hundred, the recursion's 4m
    Python-level dot products cost as much as the objective. No pairs: a gradient step of at most
    0.1 latent units per coordinate.
    """
    if not pairs:
        return g * (0.1 / max(float(np.abs(g).max()), 1e-300))
    sm = np.stack([p[0] for p in pairs])  # (m, n)
    ym = np.stack([p[1] for p in pairs])
    sy = sm @ ym.T  # sy[i, j] = s_i . y_j
    yy = ym @ ym.T
    gamma = float(sy[-1, -1]) / float(yy[-1, -1])
    r = np.triu(sy)
    a, b = sm @ g, gamma * (ym @ g)
    w, _ = lapack.dtrtrs(r, a, lower=0)
    u, _ = lapack.dtrtrs(r, np.diagonal(sy) * w + gamma * (yy @ w) - b, lower=0, trans=1)
    return gamma * g + sm.T @ u - gamma * (ym.T @ w)


def _fit_lbfgs(
    x0, s, d, ell, mu, jitter, max_iter, tol, lr, progress, callback, floor, cap, autograd=False, memory=20, window=1
):
    """L-BFGS ascent (compact inverse-Hessian product), strong-Wolfe line search with Armijo backtracking
    as fallback, on numpy arrays (one torch round trip per fit, not per evaluation).

    Monotone by construction: a step is taken only if it raises L by at least
    ``1e-4 * t * g.p``; when no step length passes, the curvature memory is dropped and a
    gradient step is tried; when that fails too, the fit stops (a local optimum to
    numerical precision). Stops when L rose by less than ``tol * |L|`` over ``window`` iterations.
    """
    x = np.array(x0.detach().to(torch.float64).numpy(), copy=True)
    s = np.ascontiguousarray(s.detach().to(torch.float64).numpy())
    f, g = _value_and_grad(x, s, d, ell, mu + jitter, autograd)
    if g is None:  # pragma: no cover - the initial jitter makes K positive definite
        raise NumericalError("GPLVM K is not positive definite at the start")
    hist = [f]
    pairs: list[tuple[np.ndarray, np.ndarray, float]] = []
    rejected = 0
    show = progress_default(progress)
    bar = tqdm(range(max_iter), desc="GPLVM L-BFGS", disable=not show)
    for it in bar:
        gf = g.reshape(-1)
        p = _two_loop(gf, pairs)  # ascent direction of L (descent of -L)
        slope = float(np.dot(gf, p))
        if not slope > 0:  # not an ascent direction: fall back to the gradient
            pairs.clear()
            p = _two_loop(gf, pairs)
            slope = float(np.dot(gf, p))
            if not slope > 0:  # the gradient vanishes: a stationary point, nothing to search along
                break
        p = p.reshape(x.shape)
        t = 1.0
        accepted = False
        # strong-Wolfe line search (ours, on -L / (N d)); the Armijo backtracking below is the
        # fallback when it ends on a non-finite or non-increasing point
        fn, gn, t_sw = _wolfe_step(x, p, f, slope, s, d, ell, mu + jitter, autograd)
        if gn is not None and math.isfinite(fn) and fn >= f + 1e-4 * t_sw * slope and t_sw > 0:
            xn, accepted = x + t_sw * p, True
        for _ in range(0 if accepted else 60):
            xn = x + t * p
            fn, gn = _value_and_grad(xn, s, d, ell, mu + jitter, autograd)
            if gn is not None and fn >= f + 1e-4 * t * slope:
                accepted = True
                break
            rejected += 1
            t *= 0.5
        if not accepted:
            if pairs:  # retry from a pure gradient step with an empty memory
                pairs.clear()
                continue
            break
        sk, yk = (xn - x).reshape(-1), gf - gn.reshape(-1)  # curvature of -L
        sy = float(np.dot(sk, yk))
        if sy > 1e-12 * float(np.linalg.norm(yk)) * float(np.linalg.norm(sk)):
            pairs.append((sk, yk, 1.0 / sy))
            if len(pairs) > memory:
                pairs.pop(0)
        x, f, g = xn, fn, gn
        hist.append(f)
        done = len(hist) > window and _converged(hist[-1 - window], f, tol)
        if callback is not None:
            callback(it, f)
        if show:
            bar.set_postfix(loglik=f"{f:.6g}", refresh=False)
        if done:
            break
    return torch.from_numpy(x), hist, rejected, jitter


def _fit_adam(x0, s, d, ell, mu, jitter, max_iter, tol, lr, progress, callback, floor, cap, autograd=True):
    x = x0.clone().requires_grad_(True)
    opt = torch.optim.Adam([x], lr=lr)
    with torch.no_grad():
        hist = [float(log_likelihood(x, s, d, ell, mu + jitter))]
    rejected = 0
    for it in tqdm(range(max_iter), desc="GPLVM Adam", disable=not progress_default(progress)):
        saved = x.detach().clone()
        opt.zero_grad()
        ll_t = log_likelihood(x, s, d, ell, mu + jitter)
        (-ll_t / (d * x0.shape[0])).backward()
        opt.step()
        with torch.no_grad():
            ll = float(log_likelihood(x, s, d, ell, mu + jitter))
        if not (math.isfinite(ll) and ll >= hist[-1]):
            with torch.no_grad():
                x.copy_(saved)
            for g in opt.param_groups:
                g["lr"] *= 0.5
            rejected += 1
            if opt.param_groups[0]["lr"] < 1e-8:
                break
            continue
        done = _converged(hist[-1], ll, tol)
        hist.append(ll)
        if callback is not None:
            callback(it, ll)
        if done:
            break
    return x.detach(), hist, rejected, jitter


class _RankOneState:
    """K^{-1}, log|K| and tr(K^{-1}S) of the current latents, updated when one latent moves."""

    def __init__(self, x: np.ndarray, s: np.ndarray, d: int, ell: float, diag: float):
        self.x, self.s, self.d, self.ell, self.diag = x, s, d, ell, diag
        self.refactor()

    def column(self, xi: np.ndarray, i: int) -> np.ndarray:
        c = np.exp(-((self.x - xi) ** 2).sum(1) / (2 * self.ell**2))
        c[i] = 1.0 + self.diag
        return c

    def refactor(self) -> None:
        x = self.x
        k = np.exp(-((x[:, None, :] - x[None, :, :]) ** 2).sum(-1) / (2 * self.ell**2))
        k[np.diag_indices_from(k)] = 1.0 + self.diag
        chol = np.linalg.cholesky(k)
        self.kinv = np.linalg.inv(k)
        self.kinv = 0.5 * (self.kinv + self.kinv.T)
        self.k = k
        self.logdet = 2 * float(np.log(np.diag(chol)).sum())
        self.trace = float((self.kinv * self.s).sum())

    @property
    def loglik(self) -> float:
        return -0.5 * self.d * self.logdet - 0.5 * self.trace

    def trial(self, i: int, xi: np.ndarray):
        """L after moving latent i to xi, with what is needed to commit; None if not PD."""
        u = self.column(xi, i) - self.k[:, i]
        u[i] = 0.0
        e = np.zeros_like(u)
        e[i] = 1.0
        v1, v2 = (e + u) / math.sqrt(2), (e - u) / math.sqrt(2)
        w1 = self.kinv @ v1
        den1 = 1.0 + v1 @ w1
        w2 = self.kinv @ v2 - w1 * ((w1 @ v2) / den1)
        den2 = 1.0 - v2 @ w2
        if not (den1 > 0 and den2 > 0):
            return None
        logdet = self.logdet + math.log(den1) + math.log(den2)
        trace = self.trace - (w1 @ self.s @ w1) / den1 + (w2 @ self.s @ w2) / den2
        return -0.5 * self.d * logdet - 0.5 * trace, (i, xi, u, w1, den1, w2, den2, logdet, trace)

    def commit(self, info) -> None:
        i, xi, u, w1, den1, w2, den2, logdet, trace = info
        self.kinv = self.kinv - np.outer(w1, w1) / den1 + np.outer(w2, w2) / den2
        self.k[:, i] += u
        self.k[i, :] += u
        self.x[i] = xi
        self.logdet, self.trace = logdet, trace


def _fit_hooke_jeeves(x0, s, d, ell, mu, jitter, max_iter, tol, step, progress, callback, floor, cap, autograd=False):
    st = _RankOneState(x0.numpy().copy(), s.numpy(), d, ell, mu + jitter)
    hist = [st.loglik]
    n, q = st.x.shape
    rejected = 0
    min_step = 1e-6
    bar = tqdm(range(max_iter), desc="GPLVM Hooke-Jeeves", disable=not progress_default(progress))
    for it in bar:
        base = st.x.copy()
        start = st.loglik
        for i in range(n):
            for j in range(q):
                cur = st.loglik
                for sgn in (1.0, -1.0):
                    xi = st.x[i].copy()
                    xi[j] += sgn * step
                    res = st.trial(i, xi)
                    if res is not None and res[0] > cur:
                        st.commit(res[1])
                        break
                    rejected += 1
        try:
            st.refactor()  # limit the drift of the rank-1 updates
        except np.linalg.LinAlgError:  # pragma: no cover - the updates kept K PD
            raise NumericalError("Hooke-Jeeves: K lost positive definiteness") from None
        if st.loglik > start:
            # pattern move: X + (X - base), kept only if it improves L
            keep = st.x.copy()
            keep_ll = st.loglik
            st.x = 2 * keep - base
            try:
                st.refactor()
                ok = st.loglik > keep_ll
            except np.linalg.LinAlgError:
                ok = False
            if not ok:
                st.x = keep
                st.refactor()
        else:
            step *= 0.5
        if st.loglik < hist[-1]:  # refactorisation rounding only; never record a decrease
            st.x = base
            st.refactor()
            step *= 0.5
        done = _converged(hist[-1], st.loglik, tol) and step < min_step
        hist.append(max(st.loglik, hist[-1]))
        if callback is not None:
            callback(it, hist[-1])
        bar.set_postfix(loglik=f"{hist[-1]:.6g}", step=f"{step:.2g}", refresh=False)
        if done or step < min_step:
            break
    return torch.from_numpy(st.x.copy()), hist, rejected, jitter


# -- interpolation ---------------------------------------------------------------------------------
class GPLVM(torch.nn.Module):
    r"""A fitted GPLVM: interpolation weights, predictions and variance at any latent point.

    Seed Eq. 1-4: :math:`b(x_*) = K^{-1} k(x_*)`, :math:`z_* = b^\top Z`,
    :math:`\sigma^2(x_*) = c(x_*, x_*) - k(x_*)^\top K^{-1} k(x_*)`, with
    :math:`c(x_*, x_*) = 1 + \mu`. ``Z`` is kept raw: the interpolant is linear in the
    measurements, so any linear functional of the BRDF (images, ZH coefficients, band
    coefficients) interpolates with the same weights :math:`b`. ``K`` uses
    :math:`\mu + \text{jitter}` from the fit.

    Args:
        fit: a :class:`GPLVMFit`.
        z: optional (N, d) raw observations (kept as a buffer for :meth:`predict`); any other
            (N, ...) per-material quantity can be blended with :meth:`blend`.
        continuous: use the smooth GP mean :math:`k_{SE}(x_*)` without the :math:`\mu\delta`
            term (continuous in :math:`x_*`; at a training latent it returns
            :math:`z_i - \mu (K^{-1}Z)_i` instead of :math:`z_i`). Default False: the seed's
            interpolant, exact at the training latents and discontinuous next to them.
        valid: which blend weights :meth:`weights` (and so :meth:`blend`, :meth:`predict`)
            return; every option keeps the BRDF a weighted blend of the training rows, so blended
            images stay blends of the per-material images.

            * None (default): ``"energy"`` when ``albedo`` is given, else ``"simplex"``
              (:func:`default_validity`): every latent point non-negative, and with the
              albedos also energy conserving (albedo <= 1), whatever the training rows' own albedo.
            * ``"simplex"``: :math:`b(x_*)` projected onto the probability simplex
              (:func:`simplex_projection`: non-negative weights summing to one, the closest such
              vector in the Euclidean norm). A convex blend of non-negative BRDFs is non-negative
              and its directional albedo is at most the largest training albedo at every angle,
              so every latent point is a valid BRDF when every training BRDF is. At a training
              latent the seed's weights are :math:`e_i`, which the projection keeps: training
              rows are still reproduced exactly (``continuous=False``).
            * ``"energy"``: ``"simplex"``, then scaled by :math:`\min(1, 1/\max a)`, with
              :math:`a` the blended directional albedo over the angles and channels of
              ``albedo`` (the missing weight goes to a black material): albedo <= 1 even where
              a training row's own albedo exceeds 1 (e.g. fits loose at grazing angles).
              Needs ``albedo``.
            * ``"none"``: the seed's unconstrained weights :math:`K^{-1}k(x_*)` (of both signs
              and any sum: negative values and albedos above 1 between the materials).
        albedo: (N, K, C) per-material directional albedos (:func:`~.paths.directional_albedo`);
            required by ``valid="energy"``, kept as a buffer.
    """

    def __init__(
        self,
        fit: GPLVMFit,
        z: torch.Tensor | None = None,
        continuous: bool = False,
        valid: str | None = None,
        albedo: torch.Tensor | None = None,
    ):
        super().__init__()
        self.fit = fit
        self.continuous = bool(continuous)
        self.valid = _check_valid(default_validity(albedo) if valid is None else valid, albedo)
        x = fit.latents.to(torch.float64)
        if not bool(torch.isfinite(x).all()):
            raise ValueRangeError("GPLVM latents hold NaN/Inf")
        self.register_buffer("latents", x)
        k = kernel_matrix(x, fit.lengthscale, fit.mu_effective)
        chol, extra = cholesky_jitter(k, what="GPLVM K (interpolation)")
        if extra:
            # keep delta-consistency: the interpolation K must be the Gram of the same kernel
            self._mu = fit.mu_effective + extra
        else:
            self._mu = fit.mu_effective
        self.register_buffer("chol", chol)
        if z is not None:
            z = _check_matrix(z, "z")
            if z.shape[0] != x.shape[0]:
                raise ShapeError(f"z has {z.shape[0]} rows but the fit has {x.shape[0]} latents")
        self.register_buffer("z", z)
        if albedo is not None:
            albedo = torch.as_tensor(albedo, dtype=torch.float64)
            if albedo.ndim < 2 or albedo.shape[0] != x.shape[0]:
                raise ShapeError(f"Expected albedo of shape ({x.shape[0]}, K, C); got {tuple(albedo.shape)}")
            if not bool(torch.isfinite(albedo).all()) or bool((albedo < 0).any()):
                raise ValueRangeError("albedo must be finite and >= 0")
            albedo = albedo.reshape(x.shape[0], -1)
        self.register_buffer("albedo", albedo)

    @property
    def mu(self) -> float:
        """Diagonal shift :math:`\\mu` (+ jitter) of the K that is inverted."""
        return self._mu

    @property
    def q(self) -> int:
        return self.latents.shape[1]

    def _queries(self, xs) -> tuple[torch.Tensor, bool]:
        xs = torch.as_tensor(xs, dtype=torch.float64)
        single = xs.ndim == 1
        if single:
            xs = xs[None]
        if xs.ndim != 2 or xs.shape[1] != self.q:
            raise ShapeError(f"Expected latent points of shape (M, {self.q}) or ({self.q},); got {tuple(xs.shape)}")
        if not bool(torch.isfinite(xs).all()):
            raise ValueRangeError("latent points hold NaN/Inf")
        return xs, single

    def kvec(self, xs) -> torch.Tensor:
        """(M, N) covariances :math:`k(x_*)` (seed Eq. 3) of query points (M, Q)."""
        xs, _ = self._queries(xs)
        return self._cross(xs)

    def _cross(self, xs: torch.Tensor) -> torch.Tensor:
        return cross_kernel(xs, self.latents, self.fit.lengthscale, 0.0 if self.continuous else self._mu)

    def weights(self, xs, valid: str | None = None) -> torch.Tensor:
        r"""Blending weights :math:`b(x_*) = K^{-1} k(x_*)` (seed Eq. 4), made valid, batched.

        Args:
            xs: (M, Q) or (Q,) latent points.
            valid: ``"simplex"``, ``"energy"`` or ``"none"`` (see :class:`GPLVM`); None = the model's.
        Returns:
            (M, N) or (N,) float64.
        """
        xs, single = self._queries(xs)
        k = self._cross(xs)
        b = self.constrain(torch.cholesky_solve(k.T, self.chol).T, valid)
        return b[0] if single else b

    def constrain(self, b: torch.Tensor, valid: str | None = None) -> torch.Tensor:
        """Make raw weights valid: (M, N) -> (M, N), differentiable (see :class:`GPLVM`'s ``valid``)."""
        valid = self.valid if valid is None else _check_valid(valid, self.albedo)
        if valid == "none":
            return b
        b = simplex_projection(b)
        if valid == "energy":
            top = (b @ self.albedo.to(b.dtype)).max(-1, keepdim=True).values
            b = b / top.clamp_min(1.0)
        return b

    def variance(self, xs) -> torch.Tensor:
        r"""Predictive variance :math:`\sigma^2(x_*) = 1 + \mu - k^\top K^{-1} k` (seed Eq. 2), >= 0.

        Args:
            xs: (M, Q) or (Q,). Returns: (M,) or () float64.
        """
        xs, single = self._queries(xs)
        k = self._cross(xs)
        b = torch.cholesky_solve(k.T, self.chol).T
        v = (1.0 + self._mu - (k * b).sum(-1)).clamp_min(0)
        return v[0] if single else v

    def blend(self, xs, values: torch.Tensor, chunk: int = 4096, valid: str | None = None) -> torch.Tensor:
        """Blend any per-material quantity with :math:`b(x_*)`: ``(M, *F)`` from ``values`` ``(N, *F)``.

        Computed in float64, returned in the dtype of ``values``; ``valid`` as in :meth:`weights`.
        """
        xs, single = self._queries(xs)
        values = torch.as_tensor(values)
        if values.shape[0] != self.latents.shape[0]:
            raise ShapeError(
                f"Expected values with {self.latents.shape[0]} rows (one per material); got {tuple(values.shape)}"
            )
        flat = values.reshape(values.shape[0], -1)
        out = []
        for a in range(0, xs.shape[0], chunk):
            b = self.weights(xs[a : a + chunk], valid)
            out.append((b @ flat.to(torch.float64)).to(values.dtype))
        res = torch.cat(out).reshape(xs.shape[0], *values.shape[1:])
        return res[0] if single else res

    def predict(self, xs, chunk: int = 4096, valid: str | None = None) -> torch.Tensor:
        """Interpolated observations :math:`z_* = b(x_*)^\\top Z`: (M, d) (or (d,)) from the stored ``z``.

        ``valid`` as in :meth:`weights` (None = the model's).
        """
        if self.z is None:
            raise ValueRangeError("this GPLVM holds no observation matrix z; use blend(xs, values)")
        return self.blend(xs, self.z, chunk, valid)

    def project(
        self, target_gram: torch.Tensor, target_cross: torch.Tensor, target_sq: float = 0.0, starts: int = 4,
        max_iter: int = 100,
    ) -> tuple[torch.Tensor, float]:  # fmt: skip
        r"""Out-of-sample latent of a new BRDF: :math:`x_* = \arg\min_x \lVert W(b(x)^\top Z - z)\rVert^2`.

        The error is :math:`b^\top G b - 2 b^\top g + c` with :math:`G = Z_o W^2 Z_o^\top`,
        :math:`g = Z_o W^2 z_o` and :math:`c = z_o^\top W^2 z_o` over the observed columns ``o``
        (:func:`projection_terms`), so a partially observed BRDF costs nothing more. L-BFGS from
        the ``starts`` training latents with the smallest error :math:`G_{ii} - 2 g_i`, best kept.

        Args:
            target_gram: (N, N) :math:`G`. target_cross: (N,) :math:`g`. target_sq: :math:`c`.
            starts: number of starting points. max_iter: L-BFGS iterations per start.
        Returns:
            (x_*, error): (Q,) float64 latent and its squared weighted error.
        """
        g_mat = torch.as_tensor(target_gram, dtype=torch.float64)
        g_vec = torch.as_tensor(target_cross, dtype=torch.float64)
        n = self.latents.shape[0]
        if g_mat.shape != (n, n) or g_vec.shape != (n,):
            raise ShapeError(f"Expected G ({n}, {n}) and g ({n},); got {tuple(g_mat.shape)}, {tuple(g_vec.shape)}")
        with small_matrix_mode(n):
            return self._project(g_mat, g_vec, float(target_sq), starts, max_iter)

    def _project(self, g_mat, g_vec, target_sq: float, starts: int, max_iter: int) -> tuple[torch.Tensor, float]:
        n = self.latents.shape[0]
        at_data = torch.diagonal(g_mat) - 2 * g_vec
        order = torch.argsort(at_data)[: max(1, min(starts, n))]
        best_x, best_e = None, math.inf
        for i in order.tolist():
            x = (self.latents[i] + 1e-3).clone().requires_grad_(True)
            opt = torch.optim.LBFGS([x], lr=1.0, max_iter=max_iter, line_search_fn="strong_wolfe")

            def closure(x=x, opt=opt):
                opt.zero_grad()
                k = se_kernel(x[None], self.latents, self.fit.lengthscale)[0]
                b = self.constrain(torch.cholesky_solve(k[:, None], self.chol).T)[0]
                e = b @ g_mat @ b - 2 * b @ g_vec
                e.backward()
                return e

            opt.step(closure)
            cands = [(self.latents[i], float(at_data[i]))]
            # the valid weights are constant on plateaus (a vertex of the simplex), where the line
            # search can divide by a zero curvature: a non-finite end point is not a candidate
            if bool(torch.isfinite(x).all()):
                with torch.no_grad():
                    cands.append((x.detach(), float(self._error(x.detach(), g_mat, g_vec))))
            for cand, ce in cands:
                if ce < best_e:
                    best_x, best_e = cand.clone(), ce
        return best_x, best_e + float(target_sq)

    def _error(self, x, g_mat, g_vec) -> torch.Tensor:
        b = self.weights(x)
        return b @ g_mat @ b - 2 * b @ g_vec


def default_validity(albedo: torch.Tensor | None) -> str:
    """The blend weights of :class:`GPLVM` when ``valid`` is not given: ``"energy"`` with albedos, else ``"simplex"``.

    ``"energy"`` bounds the blended albedo by 1 where the simplex alone bounds it by the largest
    training albedo, which exceeds 1 for a few NBRDF fits of MERL (chrome, steel, tungsten
    carbide: loose at grazing angles); it scales only the blends that exceed 1, so materials with
    albedo <= 1 and their blends are unchanged.
    """
    return "simplex" if albedo is None else "energy"


def _check_valid(valid: str, albedo: torch.Tensor | None) -> str:
    if valid not in VALIDITY:
        raise ValueRangeError(f"valid must be one of {VALIDITY}; got {valid!r}")
    if valid == "energy" and albedo is None:
        raise ValueRangeError("valid='energy' needs per-material albedos: GPLVM(..., albedo=directional_albedo(...))")
    return valid


def simplex_projection(b: torch.Tensor) -> torch.Tensor:
    r"""Euclidean projection of each row onto the probability simplex :math:`\{w \ge 0, \sum w = 1\}`.

    :math:`w = \max(b - \tau, 0)` with the threshold :math:`\tau` found by sorting (Held, Wolfe
    and Crowder 1974; Duchi et al. 2008): :math:`O(N \log N)` per row, exact, differentiable almost
    everywhere (autograd through the sort). A row already on the simplex is returned unchanged.

    Args:
        b: (..., N) weights.
    Returns:
        (..., N), same dtype.
    """
    u = torch.sort(b, dim=-1, descending=True).values
    css = u.cumsum(-1) - 1
    k = torch.arange(1, b.shape[-1] + 1, dtype=b.dtype, device=b.device)
    rho = ((u - css / k) > 0).sum(-1, keepdim=True).clamp_min(1)  # the last index kept (>= 1)
    tau = css.gather(-1, rho - 1) / rho.to(b.dtype)
    return (b - tau).clamp_min(0)


def projection_terms(
    z_train: torch.Tensor, z_new: torch.Tensor, mask: torch.Tensor | None = None, weights: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, float]:
    r"""The quadratic-form terms of :meth:`GPLVM.project` for a new BRDF ``z_new`` (d,).

    Args:
        z_train: (N, d) raw training observations. z_new: (d,).
        mask: (d,) bool, observed entries (default all). weights: (d,) per-entry weights w.
    Returns:
        (G (N, N), g (N,), c) with :math:`G = Z_o W^2 Z_o^\top`, :math:`g = Z_o W^2 z_o`,
        :math:`c = \lVert W z_o \rVert^2`.
    """
    z_train = _check_matrix(z_train, "z_train").to(torch.float64)
    z_new = torch.as_tensor(z_new, dtype=torch.float64)
    if z_new.shape != (z_train.shape[1],):
        raise ShapeError(f"Expected z_new of shape ({z_train.shape[1]},); got {tuple(z_new.shape)}")
    if not bool(torch.isfinite(z_new).all()):
        raise ValueRangeError("z_new holds NaN/Inf (mark unobserved entries with mask instead)")
    w = torch.ones_like(z_new) if weights is None else torch.as_tensor(weights, dtype=torch.float64)
    if mask is not None:
        w = w * torch.as_tensor(mask, dtype=torch.float64)
    a = z_train * w
    return a @ a.T, a @ (z_new * w), float(((z_new * w) ** 2).sum())
