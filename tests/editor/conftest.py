"""The editor's test scene: the glossy Cornell box at 32x32, 4 spp, precomputed once per session."""

from __future__ import annotations

import pytest

from torch_brdf.scene import cornell_box_glossy
from torch_brdf.transport import precompute_polynomial

SIZE = 32


@pytest.fixture(scope="session")
def small_scene():
    return cornell_box_glossy(SIZE)


@pytest.fixture(scope="session")
def small_tensors_file(tmp_path_factory, small_scene):
    """(path of the saved tensors, the tensors): series 64,1,1,1, 4 spp, seed 0."""
    tensors = precompute_polynomial(small_scene, "64,1,1,1", spp=4, seed=0, progress=False)
    path = tmp_path_factory.mktemp("editor") / "cb32.npz"
    tensors.save(path)
    return path, tensors


@pytest.fixture(scope="session")
def small_fit(tmp_path_factory):
    """A q = 2 GPLVM fit of the first 8 NBRDF materials (path), or None without the shared data."""
    from torch_brdf.data import data_path
    from torch_brdf.io.merl import load_nbrdf_weights
    from torch_brdf.manifold import fit_gplvm, gram, nbrdf_observations

    weights = data_path("merl", "nbrdf_merl100_weights.npz", required=False)
    if weights is None:
        return None
    names = list(load_nbrdf_weights(weights).names)[:8]
    obs = nbrdf_observations(weights, names=names, progress=False)
    s, d = gram(obs.z, obs.cosine_weights())
    path = tmp_path_factory.mktemp("gplvm") / "fit8.npz"
    fit_gplvm(s, d, q=2, names=obs.names, max_iter=50).save(path)
    return path
