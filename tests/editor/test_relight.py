"""The relighting tab without a browser: rotation, orbit, materials, clicks (triple products)."""

from __future__ import annotations

import math

import pytest
import torch

from torch_brdf.editor.relight import RelightSession, orbit_camera
from torch_brdf.errors import SceneError, ValueRangeError


@pytest.fixture(scope="module")
def rl(relight_files):
    return RelightSession(str(relight_files[0]), relight_files[1])


def test_orbit_keeps_the_distance_and_height(rl):
    cam = rl.scene.camera
    for deg in (0.0, 30.0, -75.0):
        c = orbit_camera(cam, deg)
        d0 = torch.tensor(cam.origin, dtype=torch.float64) - torch.tensor(cam.target, dtype=torch.float64)
        d1 = torch.tensor(c.origin, dtype=torch.float64) - torch.tensor(c.target, dtype=torch.float64)
        assert math.isclose(float(d0.norm()), float(d1.norm()), rel_tol=1e-9) and c.origin[1] == cam.origin[1]
        cos = float((d0[[0, 2]] @ d1[[0, 2]]) / d0[[0, 2]].norm() / d1[[0, 2]].norm())
        assert math.isclose(cos, math.cos(math.radians(deg)), abs_tol=1e-9)


def test_controls_change_the_frame(rl):
    base = rl.render()
    assert base.shape == (24, 32, 3) and float(base.mean()) > 0 and rl.stats.vertices > 0
    box = rl.view().gbuffer
    rl.set_rotation(90.0)
    turned = rl.render()
    assert float((turned - base).abs().max()) > 1e-3  # the sun moved
    rl.set_rotation(0.0)
    torch.testing.assert_close(rl.render(), base)  # back to the start: the same frame
    rl.set_material("box", {"type": "phong", "kd": 0.2, "ks": 0.6, "exponent": 5.0})
    duller = rl.render()
    seen_box = torch.zeros(24 * 32, dtype=torch.bool)
    seen_box[box.pixels[box.object_id == rl.objects.index("box")]] = True
    change = (duller - base).abs().amax(-1).reshape(-1)
    assert float(change[seen_box].mean()) > 1e-4
    rl.set_orbit(40.0)
    moved = rl.render()
    assert float((moved - duller).abs().max()) > 1e-3 and rl.view().gbuffer is not box
    rl.set_orbit(0.0)
    rl.set_material("box", {"type": "phong", "kd": 0.2, "ks": 0.6, "exponent": 60.0})


def test_clicks_and_bad_input(rl):
    gb = rl.view().gbuffer
    k = int((gb.object_id == rl.objects.index("box")).nonzero()[0, 0])
    y, x = divmod(int(gb.pixels[k]), gb.width)
    assert rl.object_at(x, y) == "box" and rl.object_at(-1, 0) is None
    with pytest.raises(ValueRangeError, match="exponent"):
        rl.set_material("box", {"type": "phong", "exponent": -3.0})
    with pytest.raises(SceneError):
        rl.set_material("nope", {"type": "lambert"})
    with pytest.raises(ValueRangeError):
        rl.set_rotation(float("nan"))


def test_wrong_record_is_refused(relight_files, small_scene):
    from torch_brdf.errors import TorchBRDFError

    with pytest.raises(TorchBRDFError, match="does not belong"):
        RelightSession(small_scene, relight_files[1])
