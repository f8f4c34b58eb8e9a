"""Held-out reconstruction: the best manifold point of each held-out BRDF against PCA of the same dimension."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..errors import ValueRangeError
from ..metrics import cosine_weighted_rmse, log_relative_rmse
from .data import Observations, fit_pca
from .gplvm import GPLVM, GPLVMFit, fit_gplvm, gram, projection_terms, small_matrix_mode
from .kernel import se_kernel
from .paths import directional_albedo, interpolation_share


@dataclass(frozen=True)
class HeldOut:
    """Per-material errors of the manifold and of PCA on the held-out set.

    Attributes:
        names: held-out materials. q: latent / subspace dimension.
        gplvm_logrmse, pca_logrmse: (M,) log-relative RMSE (Nielsen et al. 2015 mapping).
        gplvm_cosrmse, pca_cosrmse: (M,) cosine-weighted RMSE.
        latents: (M, q) best manifold points. variance: (M,) predictive variance there.
        fit: the GPLVM fitted on the training materials.
        nearest_logrmse: (M,) log-relative RMSE of the nearest training material (smallest
            weighted squared error, the metric the projection minimises).
        gplvm_negative, pca_negative: (M,) fraction of negative values in the reconstructions.
        gplvm_projected_cosrmse, pca_projected_cosrmse: (M,) cosine-weighted RMSE of the
            reconstructions projected onto the non-negative cone (``max(z, 0)``, no negative
            values left); their log-relative RMSE is ``gplvm_logrmse`` / ``pca_logrmse`` (that
            metric clamps at 0 already).
        interpolation: (M,) distance of each placed latent to its nearest training latent over the
            local spacing (:func:`~.paths.interpolation_share`: < 0.1 means "on" a training material).
        top_weight: (M,) the largest blend weight of each reconstruction (1: one material alone).
    """

    names: tuple[str, ...]
    q: int
    gplvm_logrmse: torch.Tensor
    pca_logrmse: torch.Tensor
    gplvm_cosrmse: torch.Tensor
    pca_cosrmse: torch.Tensor
    latents: torch.Tensor
    variance: torch.Tensor
    fit: GPLVMFit
    nearest_logrmse: torch.Tensor | None = None
    gplvm_negative: torch.Tensor | None = None
    pca_negative: torch.Tensor | None = None
    gplvm_projected_cosrmse: torch.Tensor | None = None
    pca_projected_cosrmse: torch.Tensor | None = None
    interpolation: torch.Tensor | None = None
    top_weight: torch.Tensor | None = None

    def summary(self) -> dict[str, float]:
        return {
            "q": self.q,
            "heldout_logrmse": float(self.gplvm_logrmse.mean()),
            "pca_heldout_logrmse": float(self.pca_logrmse.mean()),
            "heldout_cosrmse": float(self.gplvm_cosrmse.mean()),
            "pca_heldout_cosrmse": float(self.pca_cosrmse.mean()),
        }


def _cos_columns(cos: torch.Tensor, d: int) -> torch.Tensor:
    """The clipped cosine map per column: (B,) -> (3 B,) for RGB rows, (d,) kept."""
    cos = cos.to(torch.float64)
    return cos.repeat(3) if cos.numel() * 3 == d else cos


def _logmap(z: torch.Tensor, cos: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """The log mapping of :func:`log_relative_rmse`: (..., d) -> (..., d)."""
    return torch.log(z.clamp_min(0) * _cos_columns(cos, z.shape[-1]) + eps)


def _signed_logmap(v: torch.Tensor, c: torch.Tensor, eps: float = 1e-3, negative_weight: float = 1.0) -> torch.Tensor:
    r""":math:`\operatorname{sign}(v)\log(1 + |v| c / \epsilon)`: (..., d), ``c`` the per-column cosine (d,).

    For :math:`v \ge 0` it differs from :func:`_logmap` by the constant :math:`\log\epsilon`, so
    differences of non-negative values are those of the log-relative RMSE; a negative value
    lands ``negative_weight`` times as far below zero as its magnitude would land above it
    (continuous, with finite slopes at 0).
    """
    m = torch.sign(v) * torch.log1p(v.abs() * c / eps)
    return m if negative_weight == 1.0 else torch.where(v < 0, negative_weight * m, m)


#: placement error options of :func:`project_perceptual`
NEGATIVES = ("penalise", "free")
#: default factor on mapped negative values in the placement (a factor of 1 left held-out
#: reconstructions with more negative values than PCA's on the family hold-outs; chosen after
#: seeing the quick-grid hold-outs, see the manifold guide)
NEGATIVE_WEIGHT = 100.0


#: default number of nearest training materials between which :func:`project_perceptual` also starts
NEIGHBOURS = 6
#: fractions along each segment between two neighbours that are scored as candidate starts
_SEGMENT = (0.15, 0.3, 0.5, 0.7, 0.85)


def project_perceptual(
    model: GPLVM,
    z_train: torch.Tensor,
    z_new: torch.Tensor,
    cosine: torch.Tensor,
    starts: int = 4,
    max_iter: int = 30,
    *,
    negatives: str = "penalise",
    negative_weight: float = NEGATIVE_WEIGHT,
    max_columns: int | None = 8192,
    train_map: torch.Tensor | None = None,
    neighbours: int = NEIGHBOURS,
) -> torch.Tensor:
    r"""Latent of a new BRDF that minimises the log-mapped error of :math:`b(x)^\top Z` against it.

    Error: the mean over columns of :math:`(m(b^\top Z) - m(z))^2` with the mapping of
    :func:`log_relative_rmse` (Nielsen et al. 2015), :math:`m(v) = \log(\max(v, 0)\cos + \epsilon)`.

    * ``negatives="penalise"`` (default): negative predicted values are charged ``negative_weight``
      times as far below zero as their magnitude lands above it,
      :math:`m(v) = \operatorname{sign}(v)\log(1 + |v|\cos/\epsilon)` (times the weight where :math:`v < 0`)
      (the same error for non-negative values; :func:`_signed_logmap`), so among points that fit
      equally well the search prefers one without negative values (without it, held-out
      reconstructions were more often negative than PCA's). It is never smaller than the clamped
      error the results are scored with.
    * ``negatives="free"``: the clamped mapping (a negative value costs what 0 costs), searched on
      a softplus surrogate of the clamp.

    L-BFGS (strong Wolfe) from the ``starts`` training latents whose rows have the smallest
    error and, with ``neighbours > 1``, from the ``starts`` best of a scored set of points between
    the ``neighbours`` nearest training latents (:func:`_between_starts`: the valid weights are
    exactly :math:`e_i` around each training latent, so a search started there stays on the
    material and only ever finds the nearest neighbour); the candidates (the training latents
    themselves included) are scored with the exact error on every column and the best is kept.
    The search itself sees at most ``max_columns`` columns (every k-th, evenly spread over the
    grid and the colour channels): its cost is
    :math:`O(N \cdot \text{columns})` per evaluation, 8x fewer columns on the full MERL grid
    (d = 63,339): a placement there took half the CPU time (the exact scoring of the candidates
    stays O(N d)) with the same log-RMSE to 4 digits (``benchmarks/manifold.py``).

    Args:
        model: a fitted :class:`GPLVM`. z_train: (N, d) its raw rows. z_new: (d,) the new BRDF.
        cosine: (B,) or (d,) clipped cosine map. starts: starting points. max_iter: per start.
        negatives: ``"penalise"`` or ``"free"`` (above).
        negative_weight: with ``"penalise"``, the factor (>= 1) on the mapped negative values: a
            larger weight trades a little log-RMSE for fewer negative values (default 100;
            ``benchmarks/manifold.py``). Near a training latent the smooth mean's weights are
            :math:`e_j - \mu K^{-1} e_j`, with entries of both signs: the source of the negatives.
        max_columns: columns the L-BFGS search evaluates (None = all).
        train_map: optional (N, d) :func:`_logmap` of ``z_train`` (computed when None; pass it
            when placing many materials against the same training rows).
        neighbours: nearest training materials between which starts are scored (1: none).
    Returns:
        (Q,) float64 latent.
    """
    if negatives not in NEGATIVES:
        raise ValueRangeError(f"negatives must be one of {NEGATIVES}; got {negatives!r}")
    if not (math.isfinite(negative_weight) and negative_weight >= 1):
        raise ValueRangeError(f"negative_weight must be finite and >= 1; got {negative_weight}")
    if max_columns is not None and max_columns < 1:
        raise ValueRangeError(f"max_columns must be >= 1 or None; got {max_columns}")
    z_train = torch.as_tensor(z_train, dtype=torch.float64)
    z_new = torch.as_tensor(z_new, dtype=torch.float64)
    d = z_train.shape[1]
    c = _cos_columns(cosine, d)
    penalise = negatives == "penalise"
    target = _signed_logmap(z_new, c, negative_weight=negative_weight) if penalise else _logmap(z_new, cosine)
    step = 1 if max_columns is None else max(1, math.ceil(d / max_columns))
    cols = slice(None, None, step)
    zc_sub, c_sub, t_sub = z_train[:, cols].contiguous(), c[cols].contiguous(), target[cols].contiguous()

    def error(x: torch.Tensor) -> float:
        p = model.predict(x)
        m = _signed_logmap(p, c, negative_weight=negative_weight) if penalise else _logmap(p, cosine)
        return float(((m - target) ** 2).mean())

    if train_map is None:
        train_map = _logmap(z_train, cosine)
    n_starts = max(1, min(starts, z_train.shape[0]))
    near = ((train_map - _logmap(z_new, cosine)) ** 2).mean(-1).argsort()
    order = near[:n_starts]
    inits = [model.latents[i] + 1e-3 for i in order.tolist()]
    if neighbours > 1:
        inits += _between_starts(
            model, near[: min(neighbours, z_train.shape[0])], zc_sub, c_sub, t_sub, n_starts, penalise, negative_weight
        )
    best_x, best_e = None, math.inf
    with small_matrix_mode(z_train.shape[0]):
        for i, x0 in enumerate(inits):
            x = x0.clone().requires_grad_(True)
            opt = torch.optim.LBFGS([x], lr=1.0, max_iter=max_iter, line_search_fn="strong_wolfe")

            def closure(x=x, opt=opt):
                opt.zero_grad()
                p = _weights_differentiable(model, x) @ zc_sub
                if penalise:
                    m = _signed_logmap(p, c_sub, negative_weight=negative_weight)
                else:
                    m = torch.log(torch.nn.functional.softplus(p * c_sub, beta=1e4) + 1e-3)
                e = ((m - t_sub) ** 2).mean()
                e.backward()
                return e

            opt.step(closure)
            own = (model.latents[order[i]],) if i < len(order) else ()
            with torch.no_grad():  # a non-finite end (line search on a plateau of valid weights) is dropped
                for cand in (x.detach(), *own) if bool(torch.isfinite(x).all()) else own:
                    e = error(cand)
                    if e < best_e:
                        best_x, best_e = cand.clone(), e
    return best_x


def _between_starts(
    model: GPLVM, near: torch.Tensor, zc_sub, c_sub, t_sub, count: int, penalise: bool, negative_weight: float
) -> list[torch.Tensor]:
    r"""Up to ``count`` starts between the nearest training latents, the best of a scored candidate set.

    Near a training latent the valid (simplex) weights are exactly :math:`e_i` on a small
    neighbourhood: a search started there sees a zero gradient and stays on the material, so the
    held-out material is only ever matched to its nearest neighbour. Candidates: points at
    :data:`_SEGMENT` fractions of every segment between two of the ``near`` latents and the centroid
    of every three; each is scored by the search's error on the subsampled columns (one batched
    blend), and the best ``count`` start searches of their own.
    """
    lat = model.latents[near]
    k = lat.shape[0]
    pts = [lat[i] + t * (lat[j] - lat[i]) for i in range(k) for j in range(i + 1, k) for t in _SEGMENT]
    pts += [(lat[i] + lat[j] + lat[m]) / 3 for i in range(k) for j in range(i + 1, k) for m in range(j + 1, k)]
    if not pts:
        return []
    xs = torch.stack(pts)
    with torch.no_grad():
        p = model.weights(xs) @ zc_sub
        if penalise:
            m = _signed_logmap(p, c_sub, negative_weight=negative_weight)
        else:
            m = torch.log(p.clamp_min(0) * c_sub + 1e-3)
        err = ((m - t_sub) ** 2).mean(-1)
    return list(xs[err.argsort()[:count]])


def _weights_differentiable(model: GPLVM, x: torch.Tensor) -> torch.Tensor:
    """b(x) = K^-1 k(x), made valid as the model's ``valid`` says, with gradients in x (the smooth mean's k)."""
    k = se_kernel(x[None], model.latents, model.fit.lengthscale)
    return model.constrain(torch.cholesky_solve(k.T, model.chol).T)[0]


def heldout_reconstruction(
    obs: Observations,
    train: Sequence[str],
    test: Sequence[str],
    q: int,
    *,
    fit_weights: torch.Tensor | None = None,
    starts: int = 4,
    generator: torch.Generator | None = None,
    continuous: bool = False,
    metric: str = "log",
    negatives: str = "penalise",
    negative_weight: float = NEGATIVE_WEIGHT,
    max_columns: int | None = 8192,
    valid: str | None = None,
    albedo: torch.Tensor | None = None,
    neighbours: int = NEIGHBOURS,
    **fit_kwargs,
) -> HeldOut:
    r"""Fit the GPLVM on ``train``, then place every ``test`` material at its best manifold point.

    ``metric="log"`` (default): the best point minimises the perceptual error the results are
    scored with, the mean squared difference of :math:`\log(\max(z, 0)\cos + \epsilon)`
    (:func:`log_relative_rmse`'s mapping; :func:`project_perceptual`), and the nearest-material
    baseline is the training row of smallest error in that same mapping. The prediction stays
    :math:`b(x_*)^\top Z`, linear in the measurements; only the choice of :math:`x_*` uses the
    mapping. ``metric="weighted"``: the best point minimises the same weighted (linear) error the
    latents were fitted with (:meth:`GPLVM.project`, default weights: the clipped cosine map),
    and so does the nearest material. PCA of the same dimension
    is fitted to the same training rows with the same weights and gives its best (orthogonal
    projection) reconstruction. Both are scored by :func:`log_relative_rmse` and
    :func:`cosine_weighted_rmse` against the raw held-out rows.

    Args:
        obs: observations holding every name. train, test: disjoint name lists. q: dimension.
        fit_weights: (d,) per-column weights (default ``obs.cosine_weights()``).
        starts: starting points of the projection. fit_kwargs: passed to :func:`fit_gplvm`.
        continuous: predict with the smooth GP mean (:class:`GPLVM` ``continuous=True``).
        metric: ``"log"`` or ``"weighted"`` (see above).
        negatives: how :func:`project_perceptual` treats negative
            predicted values and how many columns its search evaluates (``metric="log"`` only).
        negative_weight: as ``negatives``.
        max_columns: as ``negatives``.
        valid: the blend weights of the reconstructions and of their placement (:class:`GPLVM`'s
            ``valid``: ``"simplex"``, ``"energy"``, ``"none"`` = the seed's; None = the model's
            default with albedos, ``"energy"``).
        albedo: (N_train, K, C) training albedos, for ``valid="energy"`` (computed when None).
        neighbours: :func:`project_perceptual` also starts between this many nearest training
            materials (1: from the training latents only).
    """
    if metric not in ("log", "weighted"):
        raise ValueRangeError(f"metric must be 'log' or 'weighted'; got {metric!r}")
    w = obs.cosine_weights() if fit_weights is None else torch.as_tensor(fit_weights, dtype=torch.float64)
    cos = obs.grid.cosine_map()
    z_tr = obs.rows(train).to(torch.float64)
    z_te = obs.rows(test).to(torch.float64)
    s, d = gram(z_tr, w)
    fit = fit_gplvm(s, d, q, names=train, generator=generator, **fit_kwargs)
    if valid in (None, "energy") and albedo is None:
        albedo = directional_albedo(z_tr, obs.grid)
    model = GPLVM(fit, z_tr, continuous=continuous, valid=valid, albedo=albedo)
    lat, var, preds, nearest = [], [], [], []
    train_map = _logmap(z_tr, cos) if metric == "log" else None
    for z in z_te:
        if metric == "log":
            x = project_perceptual(
                model, z_tr, z, cos, starts=starts, negatives=negatives, negative_weight=negative_weight,
                max_columns=max_columns, train_map=train_map, neighbours=neighbours,
            )  # fmt: skip
            nearest.append(z_tr[int(((train_map - _logmap(z, cos)) ** 2).mean(-1).argmin())])
        else:
            g_mat, g_vec, c = projection_terms(z_tr, z, weights=w)
            nearest.append(z_tr[int(torch.argmin(torch.diagonal(g_mat) - 2 * g_vec))])
            x, _ = model.project(g_mat, g_vec, c, starts=starts)
        lat.append(x)
        var.append(model.variance(x))
        preds.append(model.predict(x))
    pred = torch.stack(preds)
    lat_t = torch.stack(lat)
    pca = fit_pca(z_tr, q, w)
    pred_pca = pca.reconstruct(z_te)
    return HeldOut(
        names=tuple(test),
        q=q,
        gplvm_logrmse=log_relative_rmse(pred, z_te, cos),
        pca_logrmse=log_relative_rmse(pred_pca, z_te, cos),
        gplvm_cosrmse=cosine_weighted_rmse(pred, z_te, cos),
        pca_cosrmse=cosine_weighted_rmse(pred_pca, z_te, cos),
        latents=lat_t,
        variance=torch.stack(var),
        fit=fit,
        nearest_logrmse=log_relative_rmse(torch.stack(nearest), z_te, cos),
        gplvm_negative=(pred < 0).double().mean(1),
        pca_negative=(pred_pca < 0).double().mean(1),
        gplvm_projected_cosrmse=cosine_weighted_rmse(pred.clamp_min(0), z_te, cos),
        pca_projected_cosrmse=cosine_weighted_rmse(pred_pca.clamp_min(0), z_te, cos),
        interpolation=interpolation_share(model.latents, lat_t).ratio,
        top_weight=model.weights(lat_t).max(1).values,
    )
