"""A glTF round trip: import, edit a material, write the file back with the exporter (the
other materials, the buffers and the textures kept), import again."""

from __future__ import annotations

import pytest

from tests.scene.gltf_scenes import write_gltf_scene
from torch_brdf.scene import load_scene


def test_gltf_round_trip_keeps_names_materials_textures_and_camera(tmp_path):
    export = pytest.importorskip("torch_brdf.export")
    src = write_gltf_scene(tmp_path / "scene.gltf")
    first = load_scene(src, 16)
    edited = {"type": "metallic_roughness", "base_color": [0.1, 0.6, 0.3], "metallic": 0.0, "roughness": 0.4}
    export.replace_gltf_materials(src, tmp_path / "edited.gltf", {"red": edited})
    second = load_scene(tmp_path / "edited.gltf", 16)
    assert [o.name for o in second.objects] == [o.name for o in first.objects] == ["floor", "box", "panel"]
    assert [o.material for o in second.objects] == [o.material for o in first.objects]
    assert second.materials["wood"] == first.materials["wood"]
    red = second.materials["red"]
    assert red["type"] == "metallic_roughness"
    assert red["base_color"] == pytest.approx(edited["base_color"])
    assert (red["metallic"], red["roughness"]) == pytest.approx((0.0, 0.4))
    t1, t2 = first.objects[0].textures["base_color"], second.objects[0].textures["base_color"]
    assert (t1.image == t2.image).all() and (first.objects[0].uv == second.objects[0].uv).all()
    assert second.camera == first.camera
    assert [type(li).__name__ for li in second.lights] == [type(li).__name__ for li in first.lights]
