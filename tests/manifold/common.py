"""Small synthetic data shared by the manifold tests (no shared data needed)."""

from __future__ import annotations

import torch

from torch_brdf.manifold.data import MERLGrid, analytic_observations
from torch_brdf.manifold.gplvm import GPLVM, fit_gplvm, gram

SMALL_GRID = MERLGrid.strided(9, 9, 18)


def small_family(n: int = 24, seed: int = 7):
    g = torch.Generator().manual_seed(seed)
    return analytic_observations(n, SMALL_GRID, generator=g)


def small_model(n: int = 24, q: int = 2, seed: int = 7, **kw):
    obs, params = small_family(n, seed)
    s, d = gram(obs.z)
    fit = fit_gplvm(
        s, d, q, max_iter=kw.pop("max_iter", 150), names=obs.names, generator=torch.Generator().manual_seed(seed), **kw
    )
    return GPLVM(fit, obs.z.double()), obs, params
