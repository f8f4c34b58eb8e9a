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
