r"""The error-budget planner of the BRDF manifold (issue #17): the latent dimension q and the
number of training materials n for a held-out error target.

The error is a statistic -- the median by default, or the mean (the seed's) -- over held-out
materials of the log-relative RMSE (:func:`~torch_brdf.metrics.log_relative_rmse`) of each
material's best manifold point. The planner measures it on materials drawn from the training
pool (never the held-out ones):

* the pool is put in a seeded order; its first ``validation`` materials are the validation set
  V and the rest R are the training ladder; candidate sizes are :math:`n = |R|/4, |R|/2, |R|`
  (at least q + 2), the training set of size n being the first n of R;
* each (q, n) with :math:`n \le |R|/2` is fitted (the pilots: the fits of the small half of the
  ladder) and scored on V plus the second half of the ladder, which no pilot trains on (|R|/2 +
  |V| materials, e.g. 23 of a pool of 40, for the price of projections, not fits), which gives
  each q's slope; with ``crossfit`` (default) the level at :math:`n = |R|/2` is the statistic
  over *every* pool material's held-out score (2-fold: one more fit per q, on the ladder's second
  half, scores the first half); the full :math:`n = |R|` is predicted by continuing the power law
  :math:`e = a n^{-p}` through the two measured sizes (:func:`~torch_brdf.planner.table.power_law`,
  with :math:`p \ge 0`: more materials never predict more error);
* an extrapolated size is never the plan's last word: when the cheapest option within the
  budget is :math:`n = |R|` (beyond every pilot), it is *measured* before it is chosen, by k-fold
  cross-fitting on the pool itself (:func:`_crossfit_whole_pool`): the plan's own model (trained
  on R) scores V, and :math:`\lceil |R|/|V| \rceil` more fits of the same size each hold out a
  chunk of |V| ladder materials and train on the other |R| pool materials (V included), so every
  pool material has a held-out score from a model of size |R| (7 fits, 40 scores for a pool of
  40; the fits cost little next to the placements). The prediction is their statistic, printed
  with its 90% bootstrap interval over the materials; the choice is then made again (a measured
  option that misses the budget gives way to the next). The power law had predicted 0.0071
  where 0.0037 was reached (0.52x) on one order of the test pool: a learning curve can fall
  faster than its first two points say. ``validate_folds=k`` makes only k of the fits (18 scores
  for k = 3, the former default) and corrects their statistic by the same materials' scores at
  |R|/2 (a regression estimator, :func:`_regression_estimate`); that gave 1.86x on one order
  after a rounding-level change of the GPLVM fit (issue #20), where the 40 scores give 1.29x
  (1.39x with single-threaded fits: the thread count alone moves a fit's path).
  On 16 cases (8 pool orders x q 2, 3; 40 pool and 80 held-out analytic materials, fits
  single-threaded) the achieved median at |R| was 0.75-1.57x the k-fold estimate (standard
  deviation of the log ratio 0.22; the 3-fold regression estimate: 0.66-1.86x, 0.27). That
  scatter is the materials': a median of 40 heavy-tailed scores moves by ~1.25x (bootstrap
  standard deviation of its log 0.11-0.33) with the materials drawn and the achieved median of
  80 by ~1.15x, so 1.5x is ~1.6-2 of their joint standard deviations: a pool of 40 makes the
  1.5x likely for an order, not certain (the level at |R|/2 from 40 scores scatters alike:
  0.57-1.63x on the same 16 cases);
* cost: the fit + projection seconds, predicted as :math:`\kappa\,u(q, n)` with the operation
  count :math:`u = (n^2 + q n) D + n^3` (D columns: the kernel products and the Cholesky of one
  likelihood evaluation) and one rate :math:`\kappa` fitted to the pilots' measured seconds. The
  ranking of the options therefore never depends on timer noise (the same data give the same
  plan); only the printed seconds do.

The chosen fit trains on the first n materials of R, so what the pilots measured for a size
below |R|/2 is the plan's own model; on the held-out set the same model is scored on other
materials.

**Why the median.** Per-material errors are heavy-tailed (on the analytic family, 200 fresh
materials: median 0.0053, 90th percentile 0.035, max 0.83): the mean of a few tens of them is
set by the one or two worst, and the mean over 10 held-out materials missed a prediction from
6 validation materials by 1.66x. The median of the same errors moves far less between
material sets, so the plan predicts (and the budget bounds) the median by default; the mean is
available with ``statistic="mean"`` and then needs many more held-out materials to check.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence

import torch

from ..errors import ValueRangeError
from ..manifold.data import Observations
from ..manifold.evaluate import heldout_reconstruction
from .table import Option, Plan, choose, power_law

__all__ = ["plan_manifold"]


def _crossfit_whole_pool(
    obs, val: list[str], ladder: list[str], q: int, folds: int | None, eligible: set[str], fit_kwargs
) -> tuple[list[str], torch.Tensor, int]:
    """Held-out scores of fits of size |R| = ``len(ladder)`` (k-fold cross-fitting on the pool).

    Fold 0 is the plan's own model (trained on ``ladder``), which scores ``val``; fold i >= 1
    holds out the i-th chunk of |V| ladder materials (from the end of the ladder) and trains on
    the other pool materials, |R| of them (the validation set and the rest of the ladder, cut to
    |R| where a short last chunk leaves more). With ``folds=None`` the chunks cover the whole
    ladder, so every pool material is scored by a model of the plan's size that never saw it;
    otherwise only ``folds`` fits are made, their chunks taken from ``eligible`` materials.

    Returns:
        (the scored names, (S,) their scores, the number of fits).
    """
    v, pool = len(val), val + ladder
    rest = ladder[::-1] if folds is None else [m for m in reversed(ladder) if m in eligible]
    chunks = [val] + [rest[i : i + v] for i in range(0, len(rest), v)]
    chunks = chunks if folds is None else chunks[:folds]
    names, scores = [], []
    for held in chunks:
        train = ladder if held is val else [m for m in pool if m not in held][: len(ladder)]
        h = heldout_reconstruction(obs, train, held, q, generator=torch.Generator().manual_seed(q), **fit_kwargs)
        names += held
        scores.append(h.gplvm_logrmse)
    return names, torch.cat(scores), len(chunks)


def _bootstrap_interval(
    scores: torch.Tensor, stat, coverage: float = 0.9, resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap interval of ``stat`` over the materials (resampled with replacement).

    Args:
        scores: (S,) per-material errors.
    Returns:
        (low, high) with ``coverage`` of the resampled statistics between them.
    """
    g = torch.Generator().manual_seed(seed)
    idx = torch.randint(scores.numel(), (resamples, scores.numel()), generator=g)
    s = scores[idx]
    b = s.median(1).values if stat is torch.median else s.mean(1)
    lo, hi = torch.quantile(b.double(), torch.tensor([(1 - coverage) / 2, (1 + coverage) / 2], dtype=torch.float64))
    return float(lo), float(hi)


def _regression_estimate(big: torch.Tensor, small: torch.Tensor, level: float, stat) -> tuple[float, float]:
    r"""The statistic at the large size from few materials, corrected by the small size's
    (a regression estimator, the control variate being the same materials' scores at the small
    size, whose statistic over every pool material, ``level``, is known):
    :math:`\log \hat e = \log s(b) + eta (\log \ell - \log s(a))`, with :math:`eta` the
    least-squares slope of :math:`\log b_i` on :math:`\log a_i` over the materials (in [0, 1]).

    Args:
        big, small: (S,) the same materials' scores at the large and the small size.
        level: the statistic of the small size over all pool materials.
    Returns:
        (estimate, beta).
    """
    lb, ls = big.clamp_min(1e-300).log(), small.clamp_min(1e-300).log()
    var = float(((ls - ls.mean()) ** 2).sum())
    beta = min(1.0, max(0.0, float(((lb - lb.mean()) * (ls - ls.mean())).sum()) / var)) if var > 0 else 0.0
    gap = math.log(max(level, 1e-300)) - math.log(max(float(stat(small)), 1e-300))
    return float(stat(big)) * math.exp(beta * gap), beta


def plan_manifold(
    obs: Observations,
    train: Sequence[str],
    error: float | None = 0.05,
    seconds: float | None = None,
    qs: Sequence[int] = (1, 2, 3),
    validation: int = 6,
    generator: torch.Generator | None = None,
    statistic: str = "median",
    crossfit: bool = True,
    validate_folds: int | None = None,
    **fit_kwargs,
) -> Plan:
    """Plan q and the training materials for a held-out log-RMSE ``error`` (its median; see the module).

    Args:
        obs: observations holding every name of ``train``.
        train: the materials the manifold may be trained on.
        error: budget on the held-out log-RMSE (its ``statistic``); seconds: budget on fit + projection.
        qs: candidate latent dimensions.
        validation: materials of ``train`` set aside (never trained on by any plan).
        generator: seeds the order of the pool (and the fits).
        statistic: ``"median"`` (default) or ``"mean"`` of the per-material errors: what the
            plan predicts (and the budget bounds). Per-material errors are heavy-tailed, so a
            mean over tens of materials scatters by more than 1.5x between material sets; the
            median does not (see the module).
        crossfit: also fit the second half of the ladder at n = |R|/2 and score the first half
            with it (2-fold), so that the level at |R|/2 comes from every pool material.
        validate_folds: how an extrapolated choice (n = |R|) is measured before it is taken (see
            the module): None (default) k-fold fits of that size until every pool material is
            scored; k > 0: only k of them, corrected by regression on n = |R|/2; 0: keep the
            extrapolation.
        fit_kwargs: passed to :func:`~torch_brdf.manifold.heldout_reconstruction` (e.g. ``max_iter``).
    Returns:
        :class:`~torch_brdf.planner.table.Plan` with settings ``q``, ``n`` and ``train`` (the
        names to train on, a tuple).
    """
    if statistic not in ("median", "mean"):
        raise ValueRangeError(f"statistic must be 'median' or 'mean'; got {statistic!r}")
    if validate_folds is not None and validate_folds < 0:
        raise ValueRangeError(f"validate_folds must be None or >= 0; got {validate_folds}")
    g = generator if generator is not None else torch.Generator().manual_seed(0)
    names = list(train)
    if len(names) < validation + 8:
        raise ValueRangeError(f"need at least {validation + 8} training materials; got {len(names)}")
    order = [names[i] for i in torch.randperm(len(names), generator=g).tolist()]
    val, ladder = order[:validation], order[validation:]
    sizes = sorted({max(max(qs) + 2, round(len(ladder) / k)) for k in (4, 2)} | {len(ladder)})
    t_start = time.perf_counter()
    d = obs.z.shape[1]

    def units(q: int, n: int) -> float:
        return float((n * n + q * n) * d + n**3)

    # every pilot is scored on the same materials: the validation set and the part of the ladder
    # that no pilot trains on (the pilots stop at |R|/2); these give each q's slope
    half = sizes[-2]
    scored = val + ladder[half:]
    stat = torch.median if statistic == "median" else torch.mean
    measured, scores = {}, {}
    for q in qs:
        for n in sizes[:-1]:
            t0 = time.perf_counter()
            h = heldout_reconstruction(
                obs, ladder[:n], scored, q, generator=torch.Generator().manual_seed(q), **fit_kwargs
            )
            measured[q, n] = (float(stat(h.gplvm_logrmse)), time.perf_counter() - t0)
            scores[q, n] = h.gplvm_logrmse
    level, small = {}, {q: dict(zip(scored, scores[q, half].tolist(), strict=True)) for q in qs}
    if crossfit and len(ladder) - half >= max(qs) + 2:
        # 2-fold at n = |R|/2: a fit on the other half scores the first half, so every pool material
        # has a score from a model of that size that never saw it (|V| + |R| scores, not |V| + |R|/2)
        other = ladder[half : 2 * half]
        for q in qs:
            h = heldout_reconstruction(
                obs, other, ladder[:half], q, generator=torch.Generator().manual_seed(q), **fit_kwargs
            )
            level[q] = float(stat(torch.cat((scores[q, half], h.gplvm_logrmse))))
            small[q].update(zip(ladder[:half], h.gplvm_logrmse.tolist(), strict=True))
    # one rate for the whole table (least squares through the origin): seconds per operation
    kappa = sum(t * units(q, n) for (q, n), (_, t) in measured.items()) / sum(units(q, n) ** 2 for q, n in measured)
    options = []
    for q in qs:
        xs = [n for n in sizes[:-1]]
        errs = [measured[q, n][0] for n in xs]
        _, p = power_law(xs, errs) if len(xs) > 1 else (errs[0], 0.0)
        base = level.get(q, measured[q, half][0])  # the error at |R|/2, continued by the slope
        for n in sizes:
            e = measured[q, n][0] if n < half else base * (n / half) ** -max(p, 0.0)
            options.append(Option((("q", q), ("n", n), ("train", tuple(ladder[:n]))), e, kappa * units(q, n)))
    metric = f"{statistic} held-out log-RMSE, from {len(scored) + (half if level else 0)} pool materials' scores"
    chosen = choose(options, error, seconds)
    validated: set[int] = set()
    while validate_folds != 0 and dict(chosen.settings)["n"] == len(ladder) and id(chosen) not in validated:
        q = dict(chosen.settings)["q"]
        held, big, fits = _crossfit_whole_pool(obs, val, ladder, q, validate_folds, set(small[q]), fit_kwargs)
        if len(held) == len(order):
            # every pool material scored at n = |R|: the statistic itself, no correction needed
            e = float(stat(big))
            lo, hi = _bootstrap_interval(big, stat)
            how = f"all {len(held)} pool materials by {fits} fits of that size, k-fold; 90% interval {lo:.3g}-{hi:.3g}"
        else:
            e, beta = _regression_estimate(
                big, torch.tensor([small[q][m] for m in held]), level.get(q, measured[q, half][0]), stat
            )
            how = f"{len(held)} of them by {fits} fits of that size, regression on n = {half}: beta {beta:.2f}"
        i = options.index(chosen)
        options[i] = dataclasses.replace(chosen, predicted_error=e)
        validated.add(id(options[i]))
        metric = (
            f"{statistic} held-out log-RMSE, from {len(scored) + (half if level else 0)} pool materials'"
            f" scores; n = {len(ladder)} measured on {how}"
        )
        chosen = choose(options, error, seconds)
    return Plan(
        capability="manifold",
        metric=metric,
        error=error,
        seconds=seconds,
        chosen=chosen,
        options=tuple(options),
        pilot_seconds=time.perf_counter() - t_start,
    )
