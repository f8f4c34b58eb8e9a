"""An area light is seen by camera rays whether or not it was given ``object_id``."""

from __future__ import annotations

import torch

from torch_brdf.scene import AreaLight, Camera, Scene, SceneObject, mesh_from_arrays
from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace

RADIANCE = 5.0
# a 1 x 1 quad at z = 1 facing -z (towards the camera): (v1 - v0) x (v2 - v0) = -z
LAMP_V = [(-0.5, -0.5, 1.0), (-0.5, 0.5, 1.0), (0.5, 0.5, 1.0), (0.5, -0.5, 1.0)]
LAMP_F = [[0, 1, 2], [0, 2, 3]]
FLOOR_V = [(-3, -1, -3), (-3, -1, 3), (3, -1, 3), (3, -1, -3)]


def scene_with(light_object: bool, object_id: int | None) -> tuple[Scene, list, AreaLight]:
    objects = [SceneObject("floor", mesh_from_arrays(FLOOR_V, LAMP_F), "grey")]
    if light_object:
        objects.append(SceneObject("lamp", mesh_from_arrays(LAMP_V, LAMP_F), "grey", editable=False))
    light = AreaLight(LAMP_V, LAMP_F, RADIANCE) if object_id is None else AreaLight(LAMP_V, LAMP_F, RADIANCE, object_id)
    cam = Camera((0.0, 0.0, -2.0), (0.0, 0.0, 1.0), fov_deg=40.0, width=8, height=8)
    return Scene(objects, {"grey": {"type": "lambert", "albedo": 0.5}}, [light], cam), objects, light


def centre(img: torch.Tensor) -> torch.Tensor:
    return img[3:5, 3:5].reshape(-1, 3)


def test_light_on_an_object_without_object_id_is_visible_and_the_same_as_with_it():
    scene, _, light = scene_with(light_object=True, object_id=None)
    assert scene.lights[0].object_id == 1 and light.object_id == -1  # the caller's light untouched
    img = path_trace(scene, PathTraceSettings(spp=2, max_bounces=1), seed=3, progress=False)
    torch.testing.assert_close(centre(img), torch.full((4, 3), RADIANCE))
    named, _, _ = scene_with(light_object=True, object_id=1)
    assert torch.equal(img, path_trace(named, PathTraceSettings(spp=2, max_bounces=1), seed=3, progress=False))


def test_light_without_any_object_gets_a_fixed_black_one():
    scene, objects, _ = scene_with(light_object=False, object_id=None)
    assert [o.name for o in scene.objects] == ["floor", "area_light_0"] and len(objects) == 1
    assert not scene.objects[1].editable and scene.lights[0].object_id == 1
    img = path_trace(scene, PathTraceSettings(spp=2, max_bounces=1), seed=3, progress=False)
    torch.testing.assert_close(centre(img), torch.full((4, 3), RADIANCE))
