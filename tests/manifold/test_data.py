from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.conftest import corrupted_copy, shared_file
from tests.manifold.common import SMALL_GRID, small_family
from torch_brdf.errors import FileFormatError, ShapeError, ValueRangeError
from torch_brdf.manifold.data import (
    MERLGrid,
    default_grid,
    fit_pca,
    nbrdf_observations,
    read_split,
    select,
    split_names,
    to_table,
    write_split,
)
from torch_brdf.records import CorruptCacheWarning


def test_grid_validation_and_default():
    g = default_grid()
    assert g.shape == (30, 30, 30)
    assert g.theta_h_index[:3] == (0, 3, 6) and g.phi_d_index[-1] == 174
    with pytest.raises(ValueRangeError):
        MERLGrid((0, 0), (1,), (2,))
    with pytest.raises(ValueRangeError):
        MERLGrid((0,), (90,), (2,))
    assert MERLGrid.full().shape == (90, 90, 180)


def test_select_and_to_table_roundtrip(gen):
    full = torch.rand(3, 90, 90, 180, generator=gen, dtype=torch.float64)
    row = select(full, SMALL_GRID)
    assert row.shape == (3 * SMALL_GRID.num_valid,)
    back = to_table(row, SMALL_GRID)
    ih, id_, ip = (torch.as_tensor(i) for i in SMALL_GRID.indices)
    sub = full[:, ih][:, :, id_][:, :, :, ip]
    v = SMALL_GRID.valid()
    assert torch.equal(back[:, v], sub[:, v])
    assert bool((back[:, ~v] == -1).all())
    full[0, 0, 0, 0] = -1.0  # a missing measurement in a kept, valid bin
    with pytest.raises(ValueRangeError, match="missing"):
        select(full, SMALL_GRID)
    with pytest.raises(ShapeError):
        select(torch.zeros(3, 90, 90), SMALL_GRID)


def test_cosine_map_is_clipped_product_of_cosines():
    c = SMALL_GRID.cosine_map()
    wi, wo = SMALL_GRID.directions()
    v = SMALL_GRID.valid()
    raw = (wi[..., 2] * wo[..., 2])[v]
    assert torch.equal(c, raw.clamp(0.01, 1.0))
    assert float(c.min()) >= 0.01 and float(c.max()) <= 1.0


def test_split_is_80_20_sorted_and_roundtrips(tmp_path):
    names = [f"m{i:03d}" for i in range(100)][::-1]
    train, test = split_names(names)
    assert len(train) == 80 and len(test) == 20 and not set(train) & set(test)
    assert test[0] == "m004" and test == sorted(test)
    p = write_split(tmp_path / "split.txt", train, test)
    assert read_split(p) == (train, test)
    (tmp_path / "bad.txt").write_text("train a\nvalidate b\n")
    with pytest.raises(FileFormatError, match="expected"):
        read_split(tmp_path / "bad.txt")
    with pytest.raises(FileFormatError, match="not found"):
        read_split(tmp_path / "missing.txt")


def test_published_split_matches_the_nbrdf_names():
    from pathlib import Path

    from torch_brdf.io.merl import load_nbrdf_weights

    names = load_nbrdf_weights(shared_file("merl", "nbrdf_merl100_weights.npz")).names
    train, test = read_split(Path(__file__).resolve().parents[2] / "datasets" / "merl_split.txt")
    assert (train, test) == split_names(names)


def test_pca_reconstructs_training_rows_and_projects(gen):
    obs, _ = small_family(10)
    z = obs.z.double()
    w = obs.cosine_weights()
    pca = fit_pca(z, 9, w)
    torch.testing.assert_close(pca.reconstruct(z), z, rtol=1e-8, atol=1e-8)
    p2 = fit_pca(z, 2, w)
    r = p2.reconstruct(z[:3])
    # the weighted residual is orthogonal to the subspace
    res = (z[:3] - r) * w
    assert float((res @ p2.components.T).abs().max()) < 1e-8 * float(res.abs().max() + 1)


def test_nbrdf_observations_cache_resume_and_corruption(tmp_path):
    from torch_brdf.brdf.measured import NBRDF, tabulate_nbrdf

    weights = shared_file("merl", "nbrdf_merl100_weights.npz")
    grid = MERLGrid.strided(15, 15, 30)
    names = ["blue-acrylic", "gold-metallic-paint", "chrome"]
    cache = tmp_path / "obs.npz"
    obs = nbrdf_observations(weights, grid, names, cache=cache, progress=False, save_every=1)
    assert obs.z.shape == (3, 3 * grid.num_valid) and obs.source == "nbrdf"
    t = tabulate_nbrdf(NBRDF("chrome", weights), *grid.indices, mask_horizon=False)
    np.testing.assert_array_equal(obs.z[2].numpy(), t[:, grid.valid()].reshape(-1).numpy().astype(np.float32))
    again = nbrdf_observations(weights, grid, names, cache=cache, progress=False)
    assert torch.equal(again.z, obs.z)
    corrupted_copy(cache, cache)
    with pytest.warns(CorruptCacheWarning, match="obs.npz"):  # moved aside, named, recomputed
        fresh = nbrdf_observations(weights, grid, names, cache=cache, progress=False)
    assert torch.equal(fresh.z, obs.z) and (tmp_path / "obs.npz.corrupt").exists()


def test_pca_gram_route_spans_the_svd_subspace(gen):
    """fit_pca goes through the N x N Gram matrix: orthonormal components spanning the same
    subspace as the SVD's top right singular vectors (projectors equal)."""
    obs, _ = small_family(12)
    z = obs.z.double()
    w = obs.cosine_weights()
    c = z * w - (z * w).mean(0)
    vh = torch.linalg.svd(c, full_matrices=False)[2]
    for q in (1, 2, 3):
        comps = fit_pca(z, q, w).components
        torch.testing.assert_close(comps @ comps.T, torch.eye(q, dtype=torch.float64), rtol=0, atol=1e-9)
        torch.testing.assert_close(comps.T @ comps, vh[:q].T @ vh[:q], rtol=0, atol=1e-8)
