r"""The error-budget planner of the BRDF manifold (issue #17): the latent dimension q and the
number of training materials n for a held-out error target.

The error is the mean held-out log-relative RMSE (:func:`~torch_brdf.metrics.log_relative_rmse`,
the seed's measure) of the best manifold point of each held-out material. The planner
measures it on a *validation* set drawn from the training materials (never the held-out ones):

* the pool is put in a seeded order; its first ``validation`` materials are the validation set
  V and the rest R are the training ladder; candidate sizes are :math:`n = |R|/4, |R|/2, |R|`
  (at least q + 2), the training set of size n being the first n of R;
* each (q, n) with :math:`n \le |R|/2` is fitted and scored on V (the pilots: the fits of the
  small half of the ladder); the full :math:`n = |R|` is predicted by continuing the power law
  :math:`e = a n^{-p}` through the two measured sizes (:func:`~torch_brdf.planner.table.power_law`,
  with :math:`p \ge 0`: more materials never predict more error);
* cost: the fit + projection seconds, predicted as :math:`\kappa\,u(q, n)` with the operation
  count :math:`u = (n^2 + q n) D + n^3` (D columns: the kernel products and the Cholesky of one
  likelihood evaluation) and one rate :math:`\kappa` fitted to the pilots' measured seconds. The
  ranking of the options therefore never depends on timer noise (the same data give the same
  plan); only the printed seconds do.

The chosen fit trains on the first n materials of R, so what the pilots measured for a
measured size is the plan's own model, scored on V; on the held-out set the same model is
scored on other materials.
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
    **fit_kwargs,
) -> Plan:
    """Plan q and the training materials for a mean held-out log-RMSE ``error`` (see the module).

    Args:
        obs: observations holding every name of ``train``.
        train: the materials the manifold may be trained on.
        error: budget on the mean held-out log-RMSE; seconds: budget on fit + projection.
        qs: candidate latent dimensions.
        validation: materials of ``train`` set aside to score the pilots.
        generator: seeds the order of the pool (and the fits).
        fit_kwargs: passed to :func:`~torch_brdf.manifold.heldout_reconstruction` (e.g. ``max_iter``).
    Returns:
        :class:`~torch_brdf.planner.table.Plan` with settings ``q``, ``n`` and ``train`` (the
        names to train on, a tuple).
    """
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

    measured = {}
    for q in qs:
        for n in sizes[:-1]:
            t0 = time.perf_counter()
            h = heldout_reconstruction(
                obs, ladder[:n], val, q, generator=torch.Generator().manual_seed(q), **fit_kwargs
            )
            measured[q, n] = (float(h.gplvm_logrmse.mean()), time.perf_counter() - t0)
    # one rate for the whole table (least squares through the origin): seconds per operation
    kappa = sum(t * units(q, n) for (q, n), (_, t) in measured.items()) / sum(units(q, n) ** 2 for q, n in measured)
    options = []
    for q in qs:
        xs = [n for n in sizes[:-1]]
        errs = [measured[q, n][0] for n in xs]
        a, p = power_law(xs, errs) if len(xs) > 1 else (errs[0], 0.0)
        for n in sizes:
            e = measured[q, n][0] if (q, n) in measured else a * n ** -max(p, 0.0)
            options.append(Option((("q", q), ("n", n), ("train", tuple(ladder[:n]))), e, kappa * units(q, n)))
    chosen = choose(options, error, seconds)
    return Plan(
        capability="manifold",
        metric="mean held-out log-RMSE, measured on a validation set",
        error=error,
        seconds=seconds,
        chosen=chosen,
        options=tuple(options),
        pilot_seconds=time.perf_counter() - t_start,
    )
