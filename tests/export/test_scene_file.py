"""save_scene_toml: an edited scene saved as a TOML scene file re-opens with every material bit
for bit, the same objects, lights and camera; values TOML cannot hold are refused."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torch_brdf.errors import ExportError
from torch_brdf.export.scene_file import save_scene_toml
from torch_brdf.scene import DirectionalLight, EnvironmentMap, Scene, load_scene


def _plain(m: dict) -> dict:
    return json.loads(json.dumps(m))  # tuples as lists, as TOML gives them back


def test_saved_scene_reopens_bit_for_bit(tmp_path):
    scene = load_scene("cornell_box", 24)
    scene.lights.append(DirectionalLight((0.3, 0.8, -0.2), (0.5, 0.4, 0.3)))
    scene.lights.append(EnvironmentMap.sky(height=8).rotated(0.3))
    mats = {k: dict(v) for k, v in scene.materials.items()}
    # values whose shortest decimal form is long: any rounding on the way would show
    mats["white"] = {"type": "blinn_phong", "kd": [0.1, 0.2, 0.30000000000000004], "ks": 1 / 3, "exponent": 401.7}
    path = save_scene_toml(scene, tmp_path / "edited.toml", mats)
    back = Scene.from_toml(path)
    assert back.materials == _plain(mats)
    assert back.materials["white"]["ks"] == 1 / 3  # bit for bit
    assert [(o.name, o.material, o.editable, o.smooth) for o in back.objects] == [
        (o.name, o.material, o.editable, o.smooth) for o in scene.objects
    ]
    for a, b in zip(scene.objects, back.objects, strict=True):
        # traced in float32: the same float32 vertices
        assert np.array_equal(a.mesh.vertices.astype(np.float32), b.mesh.vertices.astype(np.float32)), a.name
        assert np.array_equal(a.mesh.faces, b.mesh.faces)
    assert [type(x).__name__ for x in back.lights] == [type(x).__name__ for x in scene.lights]
    assert torch.equal(back.lights[2].radiance, scene.lights[2].radiance)
    assert back.camera.fov_deg == scene.camera.fov_deg and back.camera.width == 24
    # saving the re-opened scene again writes the same text
    again = save_scene_toml(back, tmp_path / "again.toml")
    assert again.read_text().replace("again_", "edited_") == path.read_text().replace('"edited"', '"again"')


def test_values_toml_cannot_hold_are_refused(tmp_path):
    scene = load_scene("cornell_box", 16)
    mats = {**scene.materials, "white": {"type": "lambert", "albedo": float("nan")}}
    with pytest.raises(ExportError, match=r"materials\.white\.albedo"):
        save_scene_toml(scene, tmp_path / "bad.toml", mats)
    with pytest.raises(ExportError, match="does not exist"):
        save_scene_toml(scene, tmp_path / "missing" / "x.toml")
