"""Small shared problems for the inverse-design tests: one teapot view, few light samples."""

from __future__ import annotations

import pytest
import torch

from torch_brdf.brdf.analytic import DistributionBased
from torch_brdf.brdf.srbf import SRBFDistribution
from torch_brdf.frame import Frame
from torch_brdf.inverse import LightSamples, cosine_visibility, object_pixels, transfer_functions
from torch_brdf.inverse.energy import default_basis
from torch_brdf.scene import teatray

#: Fresnel F0 and diffuse albedo exactly representable in float32 (BRDF modules store float32
#: parameters), so a float64 render of the module equals the record to rounding
F0 = (0.875, 0.75, 0.625)
KD = (0.25, 0.375, 0.125)


@pytest.fixture(scope="module")
def view():
    g = torch.Generator().manual_seed(7)
    scene = teatray((48, 36))
    px = object_pixels(scene, "teapot")
    ls = LightSamples.from_environment(scene.environment, 128, g)
    vis = cosine_visibility(scene, px, ls)
    rec = transfer_functions(px, ls, vis, f0=F0)
    return scene, px, ls, vis, rec


def true_coefficients() -> torch.Tensor:
    """A sparse p(h) in the SRBF span (dyadic values), well inside the energy constraints."""
    c = torch.zeros(147, dtype=torch.float64)
    c[[0, 1, 7, 24, 60, 100]] = torch.tensor([0.5, 0.25, 0.5, 0.75, 0.25, 0.125], dtype=torch.float64)
    return c


def direct_render(px, ls, vis, c, kd=KD, f0=F0) -> torch.Tensor:
    """Brute-force oracle: sum over the light samples of f_r (the BRDF module) x L x V cos / pdf."""
    brdf = DistributionBased(SRBFDistribution(default_basis(), c), kd=kd, f0=f0).double()
    fr = Frame.from_normal(px.normal)
    frame = Frame(fr.s[:, None], fr.t[:, None], fr.n[:, None])  # (P, 1, 3): broadcast over samples
    wi = ls.directions[None].expand(px.count, -1, 3)
    wo = px.wo[:, None].expand_as(wi)
    with torch.no_grad():
        f = brdf.eval(wi, wo, frame)  # (P, S, 3), every (pixel, sample) pair
    return (f * vis[..., None] * ls.weight[None]).sum(1)


@pytest.fixture(scope="module")
def target_render(view):
    """The direct render of :func:`true_coefficients` with diffuse KD (computed once per module)."""
    _, px, ls, vis, _ = view
    return direct_render(px, ls, vis, true_coefficients())
