"""The editor's test scene: the glossy Cornell box at 32x32, 4 spp, precomputed once per session."""

from __future__ import annotations

import pytest

from torch_brdf.scene import cornell_box_glossy
from torch_brdf.transport import PolynomialSettings, precompute_polynomial

SIZE = 32


@pytest.fixture(scope="session")
def small_scene():
    return cornell_box_glossy(SIZE)


@pytest.fixture(scope="session")
def small_tensors_file(tmp_path_factory, small_scene):
    """(path of the saved tensors, the tensors): series 64,1,1,1, 4 spp, seed 0."""
    tensors = precompute_polynomial(small_scene, PolynomialSettings("64,1,1,1", spp=4), seed=0, progress=False)
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


def _rows(a) -> str:
    return (
        "["
        + ", ".join(
            "[" + ", ".join(repr(float(x)) if isinstance(x, float) else str(int(x)) for x in r) + "]" for r in a
        )
        + "]"
    )


@pytest.fixture(scope="session")
def relight_files(tmp_path_factory):
    """(scene .toml, visibility .npz): a glossy box over a 6x6-quad plane under a sky with a
    sun, camera 32x24, visibility cubemaps 32x32x6 (the relighting tab's test scene)."""
    import trimesh

    from torch_brdf.scene import load_scene
    from torch_brdf.scene.builtin import grid_plane
    from torch_brdf.transport.visibility import VisibilitySettings, precompute_visibility

    box = trimesh.creation.box(extents=(0.6, 0.3, 0.6))
    box.apply_translation([0.1, 0.45, 0.0])
    plane = grid_plane(2.0, 6)

    def mesh(m) -> str:
        return f"vertices = {_rows(m.vertices.tolist())}, faces = {_rows(m.faces.tolist())}"

    sun = "sun_direction = [0.5, 0.6, -0.3], sun_angular_radius_deg = 6.0, sun_radiance = [40.0, 38.0, 34.0]"
    d = tmp_path_factory.mktemp("relight")
    toml = d / "box_sky.toml"
    toml.write_text(
        f"""name = "box_sky"
camera = {{ origin = [0.0, 1.5, -2.5], target = [0.0, 0.2, 0.0], fov_deg = 45.0, width = 32, height = 24 }}
materials.glossy = {{ type = "phong", kd = 0.2, ks = 0.6, exponent = 60.0 }}
materials.floor = {{ type = "lambert", albedo = 0.6 }}
objects = [
  {{ name = "box", material = "glossy", {mesh(box)} }},
  {{ name = "floor", material = "floor", {mesh(plane)} }},
]
lights = [{{ type = "envmap", procedural = "sky", height = 32, {sun} }}]
"""
    )
    vis = precompute_visibility(load_scene(str(toml)), VisibilitySettings(resolution=32, chunk=64), progress=False)
    path = d / "vis.npz"
    vis.save(path)
    return toml, path
