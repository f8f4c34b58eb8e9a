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

import time
from collections.abc import Sequence

import torch

from ..errors import ValueRangeError
from ..manifold.data import Observations
from ..manifold.evaluate import heldout_reconstruction
from .table import Option, Plan, choose, power_law

__all__ = ["plan_manifold"]


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
    **fit_kwargs,
) -> Plan:
    """Plan q and the training materials for a mean held-out log-RMSE ``error`` (see the module).

    Args:
        obs: observations holding every name of ``train``.
        train: the materials the manifold may be trained on.
        error: budget on the mean held-out log-RMSE; seconds: budget on fit + projection.
        qs: candidate latent dimensions.
        validation: materials of ``train`` set aside (never trained on by any plan).
        generator: seeds the order of the pool (and the fits).
        statistic: ``"median"`` (default) or ``"mean"`` of the per-material errors: what the
            plan predicts (and the budget bounds). Per-material errors are heavy-tailed, so a
            mean over tens of materials scatters by more than 1.5x between material sets; the
            median does not (see the module).
        crossfit: also fit the second half of the ladder at n = |R|/2 and score the first half
            with it (2-fold), so that the level at |R|/2 comes from every pool material.
        fit_kwargs: passed to :func:`~torch_brdf.manifold.heldout_reconstruction` (e.g. ``max_iter``).
    Returns:
        :class:`~torch_brdf.planner.table.Plan` with settings ``q``, ``n`` and ``train`` (the
        names to train on, a tuple).
    """
    if statistic not in ("median", "mean"):
        raise ValueRangeError(f"statistic must be 'median' or 'mean'; got {statistic!r}")
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
    level = {}
    if crossfit and len(ladder) - half >= max(qs) + 2:
        # 2-fold at n = |R|/2: a fit on the other half scores the first half, so every pool material
        # has a score from a model of that size that never saw it (|V| + |R| scores, not |V| + |R|/2)
        other = ladder[half : 2 * half]
        for q in qs:
            h = heldout_reconstruction(
                obs, other, ladder[:half], q, generator=torch.Generator().manual_seed(q), **fit_kwargs
            )
            level[q] = float(stat(torch.cat((scores[q, half], h.gplvm_logrmse))))
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
    chosen = choose(options, error, seconds)
    return Plan(
        capability="manifold",
        metric=f"{statistic} held-out log-RMSE, from {len(scored) + (half if level else 0)} pool materials' scores",
        error=error,
        seconds=seconds,
        chosen=chosen,
        options=tuple(options),
        pilot_seconds=time.perf_counter() - t_start,
    )
