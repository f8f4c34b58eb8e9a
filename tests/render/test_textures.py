"""Textures through the GI renderer (Ben-Artzi et al. 2008, Sec. 5.3): the weight map of a
texture at the eye vertex, its surface mean at later bounces; the editor's tint and swap."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from torch_brdf.render import PolynomialRenderer, apply_scene_textures
from torch_brdf.scene import Scene
from torch_brdf.scene.builtin import cornell_box
from torch_brdf.scene.textures import Texture, surface_mean, texture_weight_map
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial


def textured(sc: Scene, image: torch.Tensor) -> Scene:
    i = sc.object_id("floor")
    objects = list(sc.objects)
    o = copy.copy(objects[i])
    v = np.asarray(o.mesh.vertices)
    o.uv = (v[:, [0, 2]] - v[:, [0, 2]].min(0)) / np.ptp(v[:, [0, 2]], 0)
    o.textures = {"base_color": Texture(image)}
    objects[i] = o
    return Scene(objects, dict(sc.materials), sc.lights, sc.camera, name=sc.name, workers=1)


@pytest.fixture(scope="module")
def setup():
    sc = cornell_box(8)
    T = precompute_polynomial(sc, PolynomialSettings("4,1", spp=2), seed=1, progress=False)
    mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
    return sc, T, mats


def test_constant_texture_equals_the_scaled_albedo(setup):
    """A texture of constant c on a Lambert floor is the floor with albedo x c, exactly: the
    eye vertex sees c, later bounces its mean c."""
    sc, T, mats = setup
    c = torch.tensor([0.3, 0.6, 0.9])
    tsc = textured(sc, c.expand(4, 4, 3).clone())
    R = PolynomialRenderer(T, mats, dtype=torch.float64)
    assert apply_scene_textures(R, tsc) == ["floor"]
    scaled = dict(mats)
    scaled["floor"] = {"type": "lambert", "albedo": (torch.tensor(mats["floor"]["albedo"]) * c).tolist()}
    want = PolynomialRenderer(T, scaled, dtype=torch.float64).evaluate()
    torch.testing.assert_close(R.evaluate(), want, rtol=1e-6, atol=1e-9)
    R.freeze("floor")
    torch.testing.assert_close(R(), want, rtol=1e-6, atol=1e-9)


def test_weight_map_and_surface_mean_of_a_split_texture(setup):
    """Left half black, right half white: floor pixels see 0 or 1 (their mix on the seam),
    the surface mean is 1/2."""
    sc, _, _ = setup
    img = torch.zeros(2, 2, 3)
    img[:, 1] = 1.0
    tsc = textured(sc.with_resolution(32), img)
    w = texture_weight_map(tsc, "floor", samples=4)
    floor = tsc.trace(*tsc.camera.generate_rays()).object_id.reshape(32, 32) == tsc.object_id("floor")
    near = torch.nn.functional.max_pool2d(floor[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    assert bool((w[~near] == 1).all()) and float(w[floor].min()) < 0.3 and float(w[floor].max()) > 0.7
    assert surface_mean(tsc, "floor").tolist() == pytest.approx([0.5] * 3, abs=0.03)


def test_editor_tint_and_swap(setup):
    from torch_brdf.editor.session import EditorSession

    sc, T, _ = setup
    img = torch.rand(4, 4, 3, generator=torch.Generator().manual_seed(0))
    s = EditorSession(T, textured(sc, img))
    assert s.textured == ["floor"]
    before = s.render().clone()
    s.set_texture("floor", tint=[0.5, 0.5, 0.5])
    tinted = s.render()
    assert not torch.allclose(before, tinted)
    s.set_texture("floor", image=torch.ones(2, 2, 3) * 0.5)
    flat = s.render()
    s2 = EditorSession(T, textured(sc, torch.ones(2, 2, 3) * 0.5))
    torch.testing.assert_close(flat, s2.render(), rtol=1e-5, atol=1e-7)
    with pytest.raises(Exception, match="no texture"):
        s.set_texture("back", tint=0.5)


def test_relighting_samples_the_texture_per_vertex():
    """A texture of constant c on the Lambert floor scales the relit image of the floor by c
    (per-vertex sampling, then the vertex colours interpolated)."""
    from tests.transport.test_visibility import ball_on_plane
    from torch_brdf.render.triple import TripleProductRenderer
    from torch_brdf.scene import EnvironmentMap, SceneObject
    from torch_brdf.transport.visibility import VisibilitySettings, precompute_visibility

    sc = ball_on_plane(quads=2, box=False)
    sc.lights[:] = [EnvironmentMap.constant(1.0, 16)]
    vis = precompute_visibility(sc, VisibilitySettings(resolution=16), progress=False)
    plain = TripleProductRenderer(sc, vis, dtype=torch.float64)
    i = sc.object_id("floor")
    o = sc.objects[i]
    v = np.asarray(o.mesh.vertices)
    c = torch.tensor([0.2, 0.5, 0.8])
    objects = list(sc.objects)
    objects[i] = SceneObject(
        o.name,
        o.mesh,
        o.material,
        o.editable,
        o.smooth,
        v[:, [0, 2]],
        {"base_color": Texture(c.expand(2, 2, 3).clone())},
    )
    tsc = Scene(objects, sc.materials, sc.lights, sc.camera.with_size(12, 12), workers=1)
    tex = TripleProductRenderer(tsc, vis, dtype=torch.float64)
    assert tex.textured and not plain.textured
    cam = tsc.camera
    a, _ = plain.render(cam)
    b, _ = tex.render(cam)
    floor = tsc.trace(*cam.generate_rays()).object_id.reshape(12, 12) == i
    assert bool(floor.any())
    torch.testing.assert_close(b[floor], a[floor] * c, rtol=1e-5, atol=1e-6)


def test_fit_image_recovers_the_factor_of_a_textured_object(setup):
    """Inverse design through GI on a textured floor: the fit of the floor's band curve (the
    texture's factor) reproduces a target rendered with another factor."""
    from torch_brdf.render import fit_image

    sc, T, mats = setup
    img = 0.3 + 0.7 * torch.rand(4, 4, 3, generator=torch.Generator().manual_seed(2))
    tsc = textured(sc, img)
    truth = dict(mats)
    truth["floor"] = {"type": "lambert", "albedo": [0.7, 0.4, 0.2]}
    R_true = PolynomialRenderer(T, truth, dtype=torch.float64)
    apply_scene_textures(R_true, tsc)
    target = R_true.evaluate().detach()
    R = PolynomialRenderer(T, mats, dtype=torch.float64)
    apply_scene_textures(R, tsc)
    start = float(((R.evaluate() - target) ** 2).mean())
    res = fit_image(R, "floor", target, max_iter=20, progress=False)
    end = float(((R.evaluate().detach() - target) ** 2).mean())
    assert end < 1e-6 * start + 1e-14, (start, end, res.loss)


def test_cli_precompute_and_edit_a_textured_xml_scene(tmp_path):
    """precompute -> edit on a Mitsuba XML scene with a textured floor: the texture is visible
    in the edited frame (a 2 x 2 texture, left column black, right column white)."""
    from PIL import Image
    from typer.testing import CliRunner

    from torch_brdf.cli import app
    from torch_brdf.io import read_exr

    a = np.zeros((2, 2, 3), np.uint8)
    a[:, 1] = 255
    Image.fromarray(a).save(tmp_path / "split.png")
    (tmp_path / "s.xml").write_text(
        """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="50"/>
    <transform name="to_world"><lookat origin="0, 3, 0.01" target="0, 0, 0" up="0, 0, -1"/></transform>
    <film type="hdrfilm"><integer name="width" value="12"/><integer name="height" value="12"/></film></sensor>
  <shape type="rectangle" id="floor"><transform name="to_world"><rotate x="1" angle="-90"/></transform>
    <bsdf type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" value="split.png"/>
    </texture></bsdf></shape>
  <shape type="cube" id="block"><transform name="to_world"><scale value="0.2"/><translate y="0.2"/></transform>
    <bsdf type="diffuse"/></shape>
  <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
</scene>"""
    )
    runner = CliRunner()
    t = tmp_path / "T.npz"
    res = runner.invoke(
        app,
        ["precompute", str(tmp_path / "s.xml"), "--out", str(t), "--series", "4,1", "--spp", "2", "--no-resume"],
    )
    assert res.exit_code == 0, res.output
    res = runner.invoke(
        app,
        ["edit", str(t), "--scene", str(tmp_path / "s.xml"), "--set", "floor.albedo=0.8", "--out", str(tmp_path / "e")],
    )
    assert res.exit_code == 0, res.output
    img = read_exr(tmp_path / "e.exr")
    # columns 4 and 7 see the floor at u = 0.33 and 0.67: bilinear between the black and white texels
    left, right = img[2:10, 4].mean(), img[2:10, 7].mean()
    assert float(right) > 2.5 * float(left), (float(left), float(right))
