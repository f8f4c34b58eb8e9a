"""Imported scene files rendered by our path tracer against Mitsuba 3 rendering the same file.

Each scene is written by the test: a Cornell box and a textured glossy floor in Mitsuba XML
(Mitsuba loads the file itself with ``mi.load_file``), an OBJ+MTL with a ``map_Kd`` texture
(Mitsuba renders an XML that references the same OBJ and PNG), and a textured multi-material
glTF written with trimesh (Mitsuba cannot read glTF: it renders our import through the
bridge, which checks the texture binding and UV orientation).

Agreement is measured against the noise: each renderer renders ``K`` seeds; the per-pixel
noise of one render is estimated from the A/B difference of two seeds
(:math:`\\sigma^2 \\approx \\overline{(a-b)^2}/2`), which gives the RMSE expected between the
two K-seed means if nothing but noise separates them,
:math:`\\sqrt{(\\sigma_o^2 + \\sigma_m^2)/K}`, and the standard error of the image-mean ratio.
Exact mappings must stay within 1.3x that RMSE and 4 standard errors of the mean;
``roughplastic`` within the same plus its stated pointwise residual.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

mi = pytest.importorskip("mitsuba")

from tests.brdf.test_plastic import ROUGH_RTOL  # noqa: E402
from torch_brdf.scene import load_scene  # noqa: E402
from torch_brdf.transport import mitsuba as tbm  # noqa: E402
from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace  # noqa: E402

pytestmark = pytest.mark.reference

K, SPP, SIZE = 2, 24, 24


def _variant() -> str:
    return tbm.default_variant()


def _mitsuba_file(path: Path, spp: int = SPP) -> torch.Tensor:
    mi_ = tbm.set_variant(_variant())
    scene = mi_.load_file(str(path))
    out = [np.array(mi_.render(scene, spp=spp, seed=s + 1), dtype=np.float64)[..., :3] for s in range(K)]
    return torch.from_numpy(np.stack(out))


def _ours(scene, bounces: int) -> torch.Tensor:
    return torch.stack(
        [path_trace(scene, PathTraceSettings(spp=SPP, max_bounces=bounces), seed=s, progress=False) for s in range(K)]
    ).double()


def compare(ours: torch.Tensor, theirs: torch.Tensor, allowance: float = 0.0) -> dict:
    """Mean ratio and RMSE of the K-seed means against the A/B noise (module docstring)."""
    var_o = float(((ours[0] - ours[1]) ** 2).mean()) / 2
    var_m = float(((theirs[0] - theirs[1]) ** 2).mean()) / 2
    expected = math.sqrt((var_o + var_m) / K)
    a, b = ours.mean(0), theirs.mean(0)
    rmse = float(((a - b) ** 2).mean().sqrt())
    se_ratio = expected / math.sqrt(a.numel()) / float(b.mean())
    out = {
        "ratio": float(a.mean() / b.mean()),
        "rmse": rmse,
        "noise_rmse": expected,
        "se_ratio": se_ratio,
    }
    print(out)
    assert abs(out["ratio"] - 1) <= 4 * se_ratio + allowance, out
    assert rmse <= 1.3 * expected + allowance * float(b.mean()), out
    return out


CORNELL = """<scene version="3.0.0">
  <default name="res" value="{size}"/>
  <integrator type="path"><integer name="max_depth" value="4"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="39.3"/>
    <string name="fov_axis" value="y"/>
    <transform name="to_world"><lookat origin="0, 1, 3.8" target="0, 1, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/>
      <rfilter type="box"/></film>
  </sensor>
  <bsdf type="twosided" id="white"><bsdf type="diffuse"><rgb name="reflectance" value="0.74, 0.74, 0.73"/></bsdf></bsdf>
  <bsdf type="diffuse" id="red"><rgb name="reflectance" value="0.53 0.05 0.05"/></bsdf>
  <bsdf type="diffuse" id="green"><rgb name="reflectance" value="0.05, 0.4, 0.09"/></bsdf>
  <shape type="rectangle" id="floor"><transform name="to_world"><rotate x="1" angle="-90"/></transform>
    <ref id="white"/></shape>
  <shape type="rectangle" id="ceiling"><transform name="to_world"><rotate x="1" angle="90"/><translate y="2"/>
    </transform><ref id="white"/></shape>
  <shape type="rectangle" id="back"><transform name="to_world"><translate y="1" z="-1"/></transform>
    <ref id="white"/></shape>
  <shape type="rectangle" id="left"><transform name="to_world"><rotate y="1" angle="90"/><translate x="-1" y="1"/>
    </transform><ref id="red"/></shape>
  <shape type="rectangle" id="right"><transform name="to_world"><rotate y="1" angle="-90"/><translate x="1" y="1"/>
    </transform><ref id="green"/></shape>
  <shape type="cube" id="box"><transform name="to_world"><scale value="0.3"/><rotate y="1" angle="20"/>
    <translate x="0.3" y="0.3" z="0.1"/></transform><ref id="white"/></shape>
  <shape type="rectangle" id="light"><transform name="to_world"><scale value="0.25"/><rotate x="1" angle="90"/>
    <translate y="1.99"/></transform><emitter type="area"><rgb name="radiance" value="15, 12, 8"/></emitter></shape>
</scene>
"""


def write_texture(path: Path, size: int = 8, seed: int = 0) -> np.ndarray:
    """An 8-bit RGB PNG of random texels (asymmetric, so a flipped UV axis shows)."""
    from PIL import Image

    a = (np.random.default_rng(seed).random((size, size, 3)) * 255).astype(np.uint8)
    a[0, :] = (255, 30, 30)  # a red top row
    Image.fromarray(a).save(path)
    return a


def test_cornell_box_xml_matches_mitsuba(tmp_path):
    path = tmp_path / "cornell.xml"
    path.write_text(CORNELL.format(size=SIZE))
    scene = load_scene(path)
    assert scene.max_bounces == 3 and scene.camera.width == SIZE
    assert {o.name for o in scene.objects} >= {"floor", "box", "light", "left"}
    compare(_ours(scene, 3), _mitsuba_file(path))


GLOSSY_FLOOR = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 2.2, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{size}"/><integer name="height" value="{size}"/>
      <rfilter type="box"/></film>
  </sensor>
  <texture type="bitmap" id="wood"><string name="filename" value="tex/wood.png"/></texture>
  <shape type="rectangle" id="floor">
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="2"/></transform>
    <bsdf type="{floor}">{floor_params}<ref name="{slot}" id="wood"/></bsdf>
  </shape>
  <shape type="cube" id="block">
    <transform name="to_world"><scale value="0.4"/><translate y="0.4"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.3, 0.6"/></bsdf>
  </shape>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
  <emitter type="directional"><vector name="direction" value="-0.4, -1, -0.3"/>
    <rgb name="irradiance" value="2, 1.9, 1.7"/></emitter>
</scene>
"""


def test_textured_diffuse_floor_xml_matches_mitsuba(tmp_path):
    """A ``bitmap`` reflectance (sRGB PNG) on a rectangle's UVs: exact."""
    (tmp_path / "tex").mkdir()
    write_texture(tmp_path / "tex" / "wood.png")
    path = tmp_path / "floor.xml"
    path.write_text(GLOSSY_FLOOR.format(size=SIZE, floor="diffuse", floor_params="", slot="reflectance"))
    scene = load_scene(path)
    assert list(scene.objects[0].textures) == ["base_color"]
    compare(_ours(scene, 2), _mitsuba_file(path))


def test_textured_glossy_floor_xml_matches_mitsuba_roughplastic(tmp_path):
    """``roughplastic`` with a textured diffuse reflectance maps to ``rough_plastic``, Mitsuba's
    function with its tables integrated by another rule: within the noise plus that rule's
    pointwise residual (``ROUGH_RTOL`` of ``tests/brdf/test_plastic.py``)."""
    (tmp_path / "tex").mkdir()
    write_texture(tmp_path / "tex" / "wood.png")
    path = tmp_path / "floor.xml"
    params = '<string name="distribution" value="ggx"/><float name="alpha" value="0.2"/>'
    path.write_text(
        GLOSSY_FLOOR.format(size=SIZE, floor="roughplastic", floor_params=params, slot="diffuse_reflectance")
    )
    scene = load_scene(path)
    assert scene.materials["floor"]["type"] == "rough_plastic"
    compare(_ours(scene, 2), _mitsuba_file(path), allowance=ROUGH_RTOL)


OBJ = """mtllib box.mtl
o floor
v -2 0 -2
v 2 0 -2
v 2 0 2
v -2 0 2
vt 0 0
vt 1 0
vt 1 1
vt 0 1
usemtl wood
f 1/1 4/4 3/3 2/2
"""
MTL = """newmtl wood
Kd 1 1 1
Ks 0 0 0
map_Kd wood.png
"""
OBJ_XML = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="2"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 4, 1" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{size}"/><integer name="height" value="{size}"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="obj"><string name="filename" value="box.obj"/><boolean name="face_normals" value="true"/>
    <bsdf type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" value="wood.png"/>
    </texture></bsdf></shape>
  <emitter type="directional"><vector name="direction" value="0.3, -1, -0.2"/><rgb name="irradiance" value="3"/>
  </emitter>
</scene>
"""


def test_obj_mtl_texture_matches_mitsuba(tmp_path):
    """OBJ + MTL (``Kd``, ``map_Kd``) read by our OBJ reader, lit and framed as an XML that
    references the same OBJ and PNG, against Mitsuba rendering that XML."""
    (tmp_path / "box.obj").write_text(OBJ)
    (tmp_path / "box.mtl").write_text(MTL)
    write_texture(tmp_path / "wood.png", seed=3)
    (tmp_path / "view.xml").write_text(OBJ_XML.format(size=SIZE))
    imported = load_scene(tmp_path / "box.obj")
    assert [o.name for o in imported.objects] == ["floor"] and imported.materials["wood"]["type"] == "lambert"
    view = load_scene(tmp_path / "view.xml")
    import dataclasses

    scene = dataclasses.replace(imported, camera=view.camera, lights=view.lights)
    compare(_ours(scene, 1), _mitsuba_file(tmp_path / "view.xml"))


def test_textured_multimaterial_gltf_matches_mitsuba_through_the_bridge(tmp_path):
    """A trimesh-written glTF (textured floor, coloured box, emissive panel, camera): our
    path tracer against Mitsuba on the imported scene (Mitsuba reads no glTF)."""
    from tests.scene.gltf_scenes import write_gltf_scene

    path = write_gltf_scene(tmp_path / "scene.glb")
    scene = load_scene(path, SIZE)
    assert [o.name for o in scene.objects] == ["floor", "box", "panel"]
    theirs = torch.stack([tbm.render_mitsuba(scene, SPP, 2, seed=s + 1, variant=_variant()) for s in range(K)])
    compare(_ours(scene, 2), theirs.double())
