"""Held-out reconstruction: the best manifold point of each held-out BRDF against PCA of the same dimension."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..metrics import cosine_weighted_rmse, log_relative_rmse
from .data import Observations, fit_pca
from .gplvm import GPLVM, GPLVMFit, fit_gplvm, gram, projection_terms


@dataclass(frozen=True)
class HeldOut:
    """Per-material errors of the manifold and of PCA on the held-out set.

    Attributes:
        names: held-out materials. q: latent / subspace dimension.
        gplvm_logrmse, pca_logrmse: (M,) log-relative RMSE (Nielsen et al. 2015 mapping).
        gplvm_cosrmse, pca_cosrmse: (M,) cosine-weighted RMSE.
        latents: (M, q) best manifold points. variance: (M,) predictive variance there.
        fit: the GPLVM fitted on the training materials.
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

    def summary(self) -> dict[str, float]:
        return {
            "q": self.q,
            "heldout_logrmse": float(self.gplvm_logrmse.mean()),
            "pca_heldout_logrmse": float(self.pca_logrmse.mean()),
            "heldout_cosrmse": float(self.gplvm_cosrmse.mean()),
            "pca_heldout_cosrmse": float(self.pca_cosrmse.mean()),
        }


def heldout_reconstruction(
    obs: Observations,
    train: Sequence[str],
    test: Sequence[str],
    q: int,
    *,
    fit_weights: torch.Tensor | None = None,
    starts: int = 4,
    generator: torch.Generator | None = None,
    **fit_kwargs,
) -> HeldOut:
    """Fit the GPLVM on ``train``, then place every ``test`` material at its best manifold point.

    The best point minimises the same weighted error the latents were fitted with
    (:meth:`GPLVM.project`, default weights: the clipped cosine map); PCA of the same dimension
    is fitted to the same training rows with the same weights and gives its best (orthogonal
    projection) reconstruction. Both are scored by :func:`log_relative_rmse` and
    :func:`cosine_weighted_rmse` against the raw held-out rows.

    Args:
        obs: observations holding every name. train, test: disjoint name lists. q: dimension.
        fit_weights: (d,) per-column weights (default ``obs.cosine_weights()``).
        starts: starting points of the projection. fit_kwargs: passed to :func:`fit_gplvm`.
    """
    w = obs.cosine_weights() if fit_weights is None else torch.as_tensor(fit_weights, dtype=torch.float64)
    cos = obs.grid.cosine_map()
    z_tr = obs.rows(train).to(torch.float64)
    z_te = obs.rows(test).to(torch.float64)
    s, d = gram(z_tr, w)
    fit = fit_gplvm(s, d, q, names=train, generator=generator, **fit_kwargs)
    model = GPLVM(fit, z_tr)
    lat, var, preds = [], [], []
    for z in z_te:
        g_mat, g_vec, c = projection_terms(z_tr, z, weights=w)
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
    )
