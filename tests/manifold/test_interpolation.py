"""Between materials, not on them: interpolation share of placements and monotone straight paths."""

from __future__ import annotations

import pytest
import torch

from tests.manifold.common import SMALL_GRID
from torch_brdf.errors import ValueRangeError
from torch_brdf.manifold import (
    GPLVM,
    GPLVMFit,
    Observations,
    directional_albedo,
    heldout_reconstruction,
    highlight_width,
    interpolation_share,
    straight_paths,
)
from torch_brdf.manifold.data import analytic_rows


def _fit_at(latents) -> GPLVMFit:
    """A fit whose latents are given (the known answers below depend on where the materials sit)."""
    x = torch.as_tensor(latents, dtype=torch.float64)
    return GPLVMFit(x, 1.0, 1e-6, 0.0, torch.zeros(1, dtype=torch.float64), 10)


def test_interpolation_share_known_answers():
    lat = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [4.0, 0.0]], dtype=torch.float64)
    on = interpolation_share(lat, lat)
    assert on.share == 0 and float(on.ratio.max()) == 0
    mid = interpolation_share(lat, torch.tensor([[0.5, 0.0], [1.5, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(mid.ratio, torch.tensor([0.5, 0.5], dtype=torch.float64))
    assert mid.share == 1
    # the spacing is the nearest latent's own: 0.3 from the latent at 4 (spacing 2) is 0.15 of it
    near = interpolation_share(lat, torch.tensor([[0.05, 0.0], [4.3, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(near.ratio, torch.tensor([0.05, 0.15], dtype=torch.float64))
    assert near.share == 0.5 and near.nearest.tolist() == [0, 3]
    with pytest.raises(ValueRangeError, match="threshold"):
        interpolation_share(lat, lat, threshold=0)


def test_held_out_members_of_a_one_parameter_family_are_placed_between_materials():
    """Training members at t = 0, 0.1, ..., 1 of a family, held out at the midpoints: the answer is
    known, every held-out member lies halfway between two training members."""
    t_train = torch.linspace(0, 1, 11, dtype=torch.float64)
    t_test = t_train[:-1] + 0.05
    t = torch.cat([t_train, t_test])
    params = torch.stack([t, 0.3 + 0.4 * t], 1)
    z = analytic_rows(params, SMALL_GRID).float()
    names = tuple(f"m{i:02d}" for i in range(t.shape[0]))
    obs = Observations(z, names, SMALL_GRID, "analytic")
    train, test = list(names[:11]), list(names[11:])
    kw = {"max_iter": 150, "mu": 1e-6, "generator": torch.Generator().manual_seed(0)}
    h = heldout_reconstruction(obs, train, test, 2, **kw)
    assert float((h.interpolation >= 0.1).double().mean()) >= 0.7
    assert float(h.top_weight.mean()) < 0.9
    assert float(h.gplvm_logrmse.mean()) < 0.9 * float(h.nearest_logrmse.mean())
    # starting from the training latents only, placements stay on them (the weights are e_i there)
    only = heldout_reconstruction(obs, train, test, 2, neighbours=1, **kw)
    assert float((only.interpolation >= 0.1).double().mean()) < float((h.interpolation >= 0.1).double().mean())


def _pair_model(params, latents):
    z = analytic_rows(torch.tensor(params, dtype=torch.float64), SMALL_GRID)
    alb = directional_albedo(z, SMALL_GRID)
    return GPLVM(_fit_at(latents), z, albedo=alb), z, alb


def test_straight_path_between_a_glossy_and_a_broad_material_is_monotone():
    model, z, alb = _pair_model([[0.9, 0.1], [0.1, 0.8]], [[0.0], [1.5]])
    prof = straight_paths(model, [(0, 1)], z, alb, SMALL_GRID)
    assert bool(prof.monotone.all())
    assert float(prof.jump.max()) < 0.25
    # the ends are the materials themselves
    torch.testing.assert_close(prof.width[0, [0, -1]], highlight_width(z, SMALL_GRID))
    assert float(prof.width[0, 0]) < float(prof.width[0, -1])  # glossy (n = 10^2.8) to broad (n = 10^1.2)


def test_straight_path_through_a_third_material_is_not_monotone():
    """Bright glossy -> dark broad -> bright glossy on a line: the path from the first to the last
    passes the dark one, so neither its albedo nor its highlight width is monotone (the test can fail)."""
    model, z, alb = _pair_model([[0.9, 0.9], [0.1, 0.0], [0.9, 0.9]], [[0.0], [1.5], [3.0]])
    prof = straight_paths(model, [(0, 2), (0, 1)], z, alb, SMALL_GRID)
    assert prof.monotone.tolist() == [False, True]
