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

    def summary(self) -> dict[str, float]:
        return {
            "q": self.q,
            "heldout_logrmse": float(self.gplvm_logrmse.mean()),
            "pca_heldout_logrmse": float(self.pca_logrmse.mean()),
            "heldout_cosrmse": float(self.gplvm_cosrmse.mean()),
            "pca_heldout_cosrmse": float(self.pca_cosrmse.mean()),
        }


def _logmap(z: torch.Tensor, cos: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """The log mapping of :func:`log_relative_rmse`: (..., d) -> (..., d)."""
    c = cos.repeat(3) if cos.numel() * 3 == z.shape[-1] else cos
    return torch.log(z.clamp_min(0) * c + eps)


def project_perceptual(
    model: GPLVM, z_train: torch.Tensor, z_new: torch.Tensor, cosine: torch.Tensor, starts: int = 4, max_iter: int = 30
) -> torch.Tensor:
    r"""Latent of a new BRDF that minimises the log-mapped error of :math:`b(x)^\top Z` against it.

    Error: the mean over columns of :math:`(\log(\max(b^\top Z, 0)\cos + \epsilon) -
    \log(\max(z, 0)\cos + \epsilon))^2` (the mapping of :func:`log_relative_rmse`, Nielsen
    et al. 2015). L-BFGS (strong Wolfe) from the ``starts`` training latents whose rows have the
    smallest error, on a smooth surrogate (softplus instead of the clamp); the candidates are
    scored with the exact error, the training latents themselves included, and the best is kept.

    Args:
        model: a fitted :class:`GPLVM`. z_train: (N, d) its raw rows. z_new: (d,) the new BRDF.
        cosine: (B,) or (d,) clipped cosine map. starts: starting points. max_iter: per start.
    Returns:
        (Q,) float64 latent.
    """
    z_train = torch.as_tensor(z_train, dtype=torch.float64)
    target = _logmap(torch.as_tensor(z_new, dtype=torch.float64), cosine)
    c = cosine.double().repeat(3) if cosine.numel() * 3 == z_train.shape[1] else cosine.double()

    def error(x: torch.Tensor) -> float:
        return float(((_logmap(model.predict(x), cosine) - target) ** 2).mean())

    order = ((_logmap(z_train, cosine) - target) ** 2).mean(-1).argsort()[: max(1, min(starts, z_train.shape[0]))]
    best_x, best_e = None, math.inf
    with small_matrix_mode(z_train.shape[0]):
        for i in order.tolist():
            x = (model.latents[i] + 1e-3).clone().requires_grad_(True)
            opt = torch.optim.LBFGS([x], lr=1.0, max_iter=max_iter, line_search_fn="strong_wolfe")

            def closure(x=x, opt=opt):
                opt.zero_grad()
                p = _weights_differentiable(model, x)
                e = ((torch.log(torch.nn.functional.softplus(p @ z_train * c, beta=1e4) + 1e-3) - target) ** 2).mean()
                e.backward()
                return e

            opt.step(closure)
            with torch.no_grad():
                for cand in (x.detach(), model.latents[i]):
                    e = error(cand)
                    if e < best_e:
                        best_x, best_e = cand.clone(), e
    return best_x


def _weights_differentiable(model: GPLVM, x: torch.Tensor) -> torch.Tensor:
    """b(x) = K^-1 k(x) with gradients in x (the smooth mean's k: no delta term off the data)."""
    k = se_kernel(x[None], model.latents, model.fit.lengthscale)[0]
    return torch.cholesky_solve(k[:, None], model.chol)[:, 0]


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
    """
    if metric not in ("log", "weighted"):
        raise ValueRangeError(f"metric must be 'log' or 'weighted'; got {metric!r}")
    w = obs.cosine_weights() if fit_weights is None else torch.as_tensor(fit_weights, dtype=torch.float64)
    cos = obs.grid.cosine_map()
    z_tr = obs.rows(train).to(torch.float64)
    z_te = obs.rows(test).to(torch.float64)
    s, d = gram(z_tr, w)
    fit = fit_gplvm(s, d, q, names=train, generator=generator, **fit_kwargs)
    model = GPLVM(fit, z_tr, continuous=continuous)
    lat, var, preds, nearest = [], [], [], []
    for z in z_te:
        if metric == "log":
            x = project_perceptual(model, z_tr, z, cos, starts=starts)
            nearest.append(z_tr[int(((_logmap(z_tr, cos) - _logmap(z, cos)) ** 2).mean(-1).argmin())])
        else:
            g_mat, g_vec, c = projection_terms(z_tr, z, weights=w)
            nearest.append(z_tr[int(torch.argmin(torch.diagonal(g_mat) - 2 * g_vec))])
            x, _ = model.project(g_mat, g_vec, c, starts=starts)
        lat.append(x)
        var.append(model.variance(x))
        preds.append(model.predict(x))
    pred = torch.stack(preds)
    pca = fit_pca(z_tr, q, w)
    pred_pca = pca.reconstruct(z_te)
    return HeldOut(
        names=tuple(test),
        q=q,
        gplvm_logrmse=log_relative_rmse(pred, z_te, cos),
        pca_logrmse=log_relative_rmse(pred_pca, z_te, cos),
        gplvm_cosrmse=cosine_weighted_rmse(pred, z_te, cos),
        pca_cosrmse=cosine_weighted_rmse(pred_pca, z_te, cos),
        latents=torch.stack(lat),
        variance=torch.stack(var),
        fit=fit,
        nearest_logrmse=log_relative_rmse(torch.stack(nearest), z_te, cos),
        gplvm_negative=(pred < 0).double().mean(1),
        pca_negative=(pred_pca < 0).double().mean(1),
    )
