"""Every latent point a valid BRDF: the constrained blend weights of :class:`GPLVM` (``valid=``)."""

from __future__ import annotations

import pytest
import torch

from tests.manifold.common import small_model
from torch_brdf.errors import ValueRangeError
from torch_brdf.manifold import GPLVM, directional_albedo, simplex_projection


def _inside_hull(latents: torch.Tensor, m: int, seed: int = 0) -> torch.Tensor:
    """(m, Q) random convex combinations of the training latents: points inside their hull."""
    g = torch.Generator().manual_seed(seed)
    w = -torch.log(torch.rand(m, latents.shape[0], generator=g, dtype=torch.float64))  # Dirichlet(1) ...
    w = w**3  # ... sharpened, so points also come near the vertices and edges, not only the centre
    return (w / w.sum(1, keepdim=True)) @ latents


def test_simplex_projection_satisfies_its_optimality_conditions():
    """KKT of min |w - b|^2 on the simplex: w >= 0, sum 1, b_i - w_i = tau where w_i > 0, b_i <= tau elsewhere."""
    g = torch.Generator().manual_seed(1)
    b = (
        torch.randn(200, 9, generator=g, dtype=torch.float64)
        * torch.tensor([0.1, 1.0, 10.0]).repeat_interleave(67)[:200, None].double()
    )
    w = simplex_projection(b)
    assert float(w.min()) >= 0
    torch.testing.assert_close(w.sum(1), torch.ones(200, dtype=torch.float64))
    pos = w > 0
    tau = ((b - w) * pos).sum(1) / pos.sum(1)
    assert bool(((b - w - tau[:, None]).abs()[pos] < 1e-12 * (1 + b.abs().max())).all())
    assert bool((b[~pos] <= tau[:, None].expand_as(b)[~pos] + 1e-12).all())
    # points of the simplex are kept
    on = torch.softmax(b, 1)
    torch.testing.assert_close(simplex_projection(on), on, rtol=0, atol=1e-15)


@pytest.fixture(scope="module")
def family():
    model, obs, _ = small_model(n=24, q=2)
    return model, obs, directional_albedo(obs.z.double(), obs.grid)


def _max_albedo(model: GPLVM, xs: torch.Tensor, train_albedo: torch.Tensor, pred: torch.Tensor, grid) -> float:
    """Max directional albedo of the predictions: blended from the training albedos (it is linear in
    the BRDF) for every point, checked against the quadrature of the predicted rows on a few."""
    blended = torch.einsum("mn,nkc->mkc", model.weights(xs), train_albedo)
    torch.testing.assert_close(directional_albedo(pred[:8], grid), blended[:8])
    return float(blended.max())


def test_latent_points_inside_the_hull_are_valid_brdfs(family):
    model, obs, train_albedo = family
    z = obs.z.double()
    assert float(z.min()) >= 0
    assert float(train_albedo.max()) <= 1.0  # the analytic family conserves energy
    xs = _inside_hull(model.latents, 1500)
    seed = model.predict(xs, valid="none")
    assert float((seed < 0).double().mean()) > 0.05  # the seed's interpolant is not valid here
    valid = model.predict(xs)  # the default: simplex-projected weights
    assert model.valid == "simplex"
    assert int((valid < 0).sum()) == 0
    assert _max_albedo(model, xs, train_albedo, valid, obs.grid) <= 1 + 1e-3
    # a blend of the training rows with the same weights, so images blend with them too
    torch.testing.assert_close(valid, model.weights(xs) @ z)
    # the training rows themselves are reproduced exactly
    torch.testing.assert_close(model.predict(model.latents), z)


def test_energy_option_bounds_albedo_when_training_rows_do_not(family):
    model, obs, train_albedo = family
    z = obs.z.double() * 2.5  # albedos above 1, as fits loose at grazing angles can have
    albedo = train_albedo * 2.5
    assert float(albedo.max()) > 1.2
    xs = _inside_hull(model.latents, 1000, seed=1)
    simplex = GPLVM(model.fit, z)
    energy = GPLVM(model.fit, z, valid="energy", albedo=albedo)
    assert _max_albedo(simplex, xs, albedo, simplex.predict(xs), obs.grid) > 1.1
    pred = energy.predict(xs)
    assert int((pred < 0).sum()) == 0
    assert _max_albedo(energy, xs, albedo, pred, obs.grid) <= 1 + 1e-3
    b = energy.weights(xs)
    assert float(b.min()) >= 0 and float(b.sum(1).max()) <= 1 + 1e-12  # the rest is a black material


def test_bad_validity_options_are_refused(family):
    model, obs, _ = family
    with pytest.raises(ValueRangeError, match="valid must be one of"):
        GPLVM(model.fit, obs.z, valid="positive")
    with pytest.raises(ValueRangeError, match="albedo"):
        GPLVM(model.fit, obs.z, valid="energy")
    with pytest.raises(ValueRangeError, match="valid must be one of"):
        model.weights(model.latents[:2], valid="clamp")


def test_default_with_albedos_bounds_energy_and_without_is_simplex(family):
    model, obs, train_albedo = family
    assert GPLVM(model.fit, obs.z).valid == "simplex"
    z = obs.z.double() * 2.5
    albedo = train_albedo * 2.5
    default = GPLVM(model.fit, z, albedo=albedo)  # no valid=: the default with albedos
    assert default.valid == "energy"
    xs = _inside_hull(model.latents, 1000, seed=2)
    pred = default.predict(xs)
    assert int((pred < 0).sum()) == 0
    assert _max_albedo(default, xs, albedo, pred, obs.grid) <= 1 + 1e-3
    # the simplex alone would have let the blends exceed 1 (what the bound is for)
    assert float(torch.einsum("mn,nkc->mkc", default.weights(xs, valid="simplex"), albedo).max()) > 1.1


def test_nbrdf_model_default_is_valid_at_random_latents(tmp_path):
    """Data-backed: a q = 2 model of a few NBRDF fits (chrome's albedo exceeds 1 on this grid)."""
    from tests.conftest import shared_file
    from torch_brdf.manifold import MERLGrid, fit_gplvm, gram, nbrdf_observations

    weights = shared_file("merl", "nbrdf_merl100_weights.npz")
    names = ["blue-acrylic", "chrome", "gold-metallic-paint", "pink-fabric", "red-plastic", "steel", "white-paint"]
    obs = nbrdf_observations(weights, MERLGrid.strided(15, 15, 30), names, cache=tmp_path / "obs.npz", progress=False)
    z = obs.z.double()
    albedo = directional_albedo(z, obs.grid)
    assert float(albedo.max()) > 1  # so the default's bound is tested, not inherited from the rows
    s, d = gram(obs.z, obs.cosine_weights())
    fit = fit_gplvm(s, d, 2, max_iter=80, names=names, generator=torch.Generator().manual_seed(0), progress=False)
    model = GPLVM(fit, z, albedo=albedo)
    xs = _inside_hull(model.latents, 2000, seed=3)
    pred = model.predict(xs)
    assert float(z.min()) >= 0 and int((pred < 0).sum()) == 0
    assert _max_albedo(model, xs, albedo, pred, obs.grid) <= 1 + 1e-3
    assert float((model.weights(xs, valid="none") @ z < 0).double().mean()) > 0  # the seed's has negatives
