"""Scene files: Mitsuba 3 XML, glTF 2.0, OBJ+MTL and Radiance .hdr through ``load_scene``;
textures on UVs; malformed files of every format give a SceneError naming file, element
and problem, never a raw exception."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.scene.gltf_scenes import write_gltf_scene
from torch_brdf.errors import FileFormatError, SceneError
from torch_brdf.io.hdr import read_hdr, write_hdr
from torch_brdf.scene import DirectionalLight, PointLight, load_scene
from torch_brdf.scene.formats import SubstitutionWarning
from torch_brdf.scene.textures import Texture, read_texture, srgb_to_linear


def bitmap(name: str) -> str:
    """A diffuse BSDF with a bitmap reflectance read from ``name``."""
    return (
        '<bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
        f'<string name="filename" value="{name}"/></texture></bsdf>'
    )


HEAD = """<scene version="3.0.0">
  <default name="w" value="16"/>
  <sensor type="perspective">
    <float name="fov" value="60"/>
    <transform name="to_world"><lookat origin="0, 1, 4" target="0, 0, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="$w"/><integer name="height" value="8"/></film>
  </sensor>
"""
FLOOR = """  <shape type="rectangle" id="floor"><transform name="to_world"><rotate x="1" angle="-90"/></transform>
    {bsdf}</shape>
"""
TAIL = """  <emitter type="directional"><vector name="direction" value="0, -1, 0"/>
    <rgb name="irradiance" value="1"/></emitter>
</scene>
"""


def xml(tmp_path, bsdf='<bsdf type="diffuse"/>', extra="", name="s.xml"):
    p = tmp_path / name
    p.write_text(HEAD + FLOOR.format(bsdf=bsdf) + extra + TAIL)
    return p


def png(path, rows=4, cols=4, seed=0):
    from PIL import Image

    a = (np.random.default_rng(seed).random((rows, cols, 3)) * 255).astype(np.uint8)
    Image.fromarray(a).save(path)
    return a


# -- Mitsuba XML ------------------------------------------------------------------------------
def test_xml_defaults_camera_and_fov_axis(tmp_path):
    sc = load_scene(xml(tmp_path))
    assert (sc.camera.width, sc.camera.height) == (16, 8)
    # Mitsuba's default fov_axis is x: 60 deg across 16 px is 2 atan(tan 30 deg / 2) vertically
    assert sc.camera.fov_deg == pytest.approx(np.degrees(2 * np.arctan(np.tan(np.radians(30)) / 2)))
    assert isinstance(sc.lights[0], DirectionalLight)
    assert sc.lights[0].direction.tolist() == pytest.approx([0, 1, 0])
    assert sc.materials["floor"] == {"type": "lambert", "albedo": [0.5, 0.5, 0.5]}


@pytest.mark.parametrize(
    ("bsdf", "want"),
    [
        (
            '<bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.2 0.3 0.4"/></bsdf></bsdf>',
            {"type": "lambert", "albedo": [0.2, 0.3, 0.4]},
        ),
        (
            '<bsdf type="roughconductor"><float name="alpha" value="0.3"/><rgb name="eta" value="1.5"/>'
            '<rgb name="k" value="0"/></bsdf>',
            {"type": "cook_torrance", "distribution": "beckmann", "roughness": 0.3, "f0": [0.04] * 3, "kd": 0.0},
        ),
        (
            '<bsdf type="principled"><rgb name="base_color" value="0.8 0.5 0.2"/><float name="metallic" value="1"/>'
            '<float name="roughness" value="0.3"/></bsdf>',
            {"type": "metallic_roughness", "base_color": [0.8, 0.5, 0.2], "metallic": 1.0, "roughness": 0.3},
        ),
    ],
)
def test_xml_bsdf_mapping(tmp_path, bsdf, want):
    got = load_scene(xml(tmp_path, bsdf)).materials["floor"]
    assert got.keys() == want.keys()
    for k, v in want.items():
        assert got[k] == (pytest.approx(v) if not isinstance(v, str) else v)


def test_xml_refs_textures_and_point_lights(tmp_path):
    png(tmp_path / "t.png")
    extra = (
        '<emitter type="point"><point name="position" x="0" y="2" z="0"/><rgb name="intensity" value="3"/></emitter>'
    )
    p = tmp_path / "s.xml"
    p.write_text(
        HEAD
        + '<texture type="bitmap" id="tex"><string name="filename" value="t.png"/></texture>'
        + '<bsdf type="diffuse" id="mat"><ref name="reflectance" id="tex"/></bsdf>'
        + FLOOR.format(bsdf='<ref id="mat"/>')
        + extra
        + TAIL
    )
    sc = load_scene(p)
    assert sc.objects[0].material == "mat" and sc.objects[0].textures["base_color"].name == "t.png"
    assert any(isinstance(li, PointLight) for li in sc.lights)


def test_xml_unsupported_plugin_names_plugin_and_line(tmp_path):
    p = xml(tmp_path, '<bsdf type="dielectric"/>')
    with pytest.raises(
        SceneError, match=r"s\.xml: line 9, <bsdf type='dielectric'>: unsupported BSDF plugin 'dielectric'"
    ):
        load_scene(p)
    with pytest.warns(SubstitutionWarning, match="grey diffuse"):
        sc = load_scene(p, substitute=True)
    assert sc.materials["floor"]["type"] == "lambert"


def test_xml_entities_dtds_and_unknown_parameters_refused(tmp_path):
    bomb = '<?xml version="1.0"?><!DOCTYPE s [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;">]><scene>&b;</scene>'
    (tmp_path / "bomb.xml").write_text(bomb)
    with pytest.raises(SceneError, match=r"bomb\.xml: refused XML"):
        load_scene(tmp_path / "bomb.xml")
    ext = '<?xml version="1.0"?><!DOCTYPE s [<!ENTITY x SYSTEM "file:///etc/passwd">]><scene>&x;</scene>'
    (tmp_path / "ext.xml").write_text(ext)
    with pytest.raises(SceneError, match="refused XML"):
        load_scene(tmp_path / "ext.xml")
    p = xml(tmp_path, '<bsdf type="diffuse"><rgb name="reflectance" value="$nope"/></bsdf>')
    with pytest.raises(SceneError, match=r"unknown parameter \$nope"):
        load_scene(p)


def test_references_outside_the_folder_are_refused(tmp_path):
    inner = tmp_path / "scene"
    inner.mkdir()
    png(tmp_path / "outside.png")
    p = xml(inner, bitmap("../outside.png"))
    with pytest.raises(SceneError, match="leaves the scene's folder"):
        load_scene(p)
    assert "base_color" in load_scene(p, allow_outside=True).objects[0].textures
    (inner / "o.obj").write_text("mtllib /etc/x.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(SceneError, match="leaves the scene's folder"):
        load_scene(inner / "o.obj")


def test_missing_texture_and_textures_without_uvs(tmp_path):
    with pytest.raises(SceneError, match=r"referenced file not found: 'no\.png'"):
        load_scene(xml(tmp_path, bitmap("no.png")))
    png(tmp_path / "t.png")
    (tmp_path / "m.mtl").write_text("newmtl a\nKd 1 1 1\nmap_Kd t.png\n")
    (tmp_path / "m.obj").write_text("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl a\nf 1 2 3\n")
    with pytest.raises(
        SceneError, match=r"m\.obj: object 'm', material 'a': uses texture 't\.png' but its faces have no UVs"
    ):
        load_scene(tmp_path / "m.obj")


# -- OBJ + MTL -------------------------------------------------------------------------------
def test_obj_parts_materials_and_textures(tmp_path):
    png(tmp_path / "t.png")
    (tmp_path / "m.mtl").write_text(
        "newmtl wood\nKd 0.5 0.5 0.5\nmap_Kd t.png\nnewmtl shiny\nKd 0.2 0.2 0.2\nKs 0.5 0.5 0.5\nNs 50\n"
        "newmtl lamp\nKd 0 0 0\nKe 4 4 4\n"
    )
    (tmp_path / "m.obj").write_text(
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 1 0 1\nv 0 0 1\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "o floor\nusemtl wood\nf 1/1 4/4 3/3 2/2\no tri\nusemtl shiny\nf 1 2 5\no lamp\nusemtl lamp\nf 2 3 5\n"
    )
    sc = load_scene(tmp_path / "m.obj")
    assert [o.name for o in sc.objects] == ["floor", "tri", "lamp"]
    assert sc.materials["shiny"] == {"type": "blinn_phong", "kd": [0.2] * 3, "ks": [0.5] * 3, "exponent": 50.0}
    assert sc.objects[0].uv.shape == (4, 2) and "base_color" in sc.objects[0].textures
    assert list(sc.area_lights) == [2]


# -- glTF ------------------------------------------------------------------------------------
@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_gltf_names_materials_textures_camera_lights(tmp_path, suffix):
    path = write_gltf_scene(tmp_path / f"s{suffix}")
    sc = load_scene(path, 32)
    assert [o.name for o in sc.objects] == ["floor", "box", "panel"]
    assert [o.material for o in sc.objects] == ["wood", "red", "glow"]
    assert list(sc.objects[0].textures) == ["base_color"] and not sc.objects[1].textures
    want = np.random.default_rng(0).random((8, 8, 3))
    want = (want * 255).astype(np.uint8)
    want[0] = (255, 30, 30)
    torch.testing.assert_close(
        sc.objects[0].textures["base_color"].image, torch.from_numpy(srgb_to_linear(want / 255.0)).float()
    )
    assert sc.camera.origin == pytest.approx((0, 2.5, 4)) and sc.camera.fov_deg == pytest.approx(np.degrees(0.9))
    d = np.array(sc.camera.target) - np.array(sc.camera.origin)
    assert d / np.linalg.norm(d) == pytest.approx(-np.array([0, 2.5, 4]) / np.hypot(2.5, 4))
    kinds = sorted(type(li).__name__ for li in sc.lights)
    assert kinds == ["AreaLight", "DirectionalLight"]
    area = next(li for li in sc.lights if type(li).__name__ == "AreaLight")
    assert area.radiance.tolist() == pytest.approx([3.0, 2.7, 2.4])  # emissiveFactor * emissive strength
    # glTF UV (0, 0) is the image's top-left: our (u, 1 - v); the floor's corner 0 has glTF uv (0, 0)
    import trimesh

    tm = trimesh.load(path, force="scene", process=False)
    floor = tm.geometry["floor_mesh"]
    np.testing.assert_allclose(sc.objects[0].uv, floor.visual.uv, atol=1e-6)


def test_gltf_spot_light_refused_by_name_or_substituted(tmp_path):
    path = write_gltf_scene(tmp_path / "s.glb", light="spot")
    with pytest.raises(SceneError, match=r"KHR_lights_punctual.lights\[0\] \('sun'\): spot lights are not supported"):
        load_scene(path)
    with pytest.warns(SubstitutionWarning):
        sc = load_scene(path, substitute=True)
    assert any(isinstance(li, PointLight) for li in sc.lights)


def test_gltf_texture_without_uvs_and_buffers_outside(tmp_path):
    path = write_gltf_scene(tmp_path / "s.gltf")
    doc = json.loads(path.read_text())
    floor_mesh = next(m for m in doc["meshes"] if m["name"] == "floor_mesh")
    del floor_mesh["primitives"][0]["attributes"]["TEXCOORD_0"]
    path.write_text(json.dumps(doc))
    with pytest.raises(SceneError, match="has a base-colour texture but the mesh has no UVs"):
        load_scene(path)
    doc["buffers"][0]["uri"] = "../../x.bin"
    path.write_text(json.dumps(doc))
    with pytest.raises(SceneError, match=r"buffers\[0\]: file reference '../../x.bin' leaves"):
        load_scene(path)


# -- malformed files: always a SceneError ----------------------------------------------------
def _mutate(data: bytes, edits) -> bytes:
    b = bytearray(data)
    for pos, kind, byte in edits:
        if not b:
            break
        i = pos % len(b)
        if kind == 0:
            b[i] = byte
        elif kind == 1:
            del b[i]
        else:
            b.insert(i, byte)
    return bytes(b)


EDITS = st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 2), st.integers(0, 255)), min_size=1, max_size=6)
SETTINGS = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _loads_or_scene_error(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            load_scene(path)
        except SceneError as exc:
            assert str(path.name) in str(exc), exc


@SETTINGS
@given(edits=EDITS)
def test_mutated_xml_gives_scene_error(tmp_path, edits):
    png(tmp_path / "t.png")
    good = (HEAD + FLOOR.format(bsdf=bitmap("t.png")) + TAIL).encode()
    p = tmp_path / "m.xml"
    p.write_bytes(_mutate(good, edits))
    _loads_or_scene_error(p)


@SETTINGS
@given(edits=EDITS)
def test_mutated_gltf_gives_scene_error(tmp_path, edits):
    src = tmp_path / "src.gltf"
    if not src.exists():
        write_gltf_scene(src)
    p = tmp_path / "m.gltf"
    p.write_bytes(_mutate(src.read_bytes(), edits))
    _loads_or_scene_error(p)


@SETTINGS
@given(edits=EDITS)
def test_mutated_glb_gives_scene_error(tmp_path, edits):
    src = tmp_path / "src.glb"
    if not src.exists():
        write_gltf_scene(src)
    p = tmp_path / "m.glb"
    p.write_bytes(_mutate(src.read_bytes(), edits))
    _loads_or_scene_error(p)


@SETTINGS
@given(edits=EDITS)
def test_mutated_obj_and_mtl_give_scene_error(tmp_path, edits):
    png(tmp_path / "t.png")
    (tmp_path / "m.mtl").write_bytes(_mutate(b"newmtl a\nKd 0.5 0.5 0.5\nKs 0.1 0.1 0.1\nNs 20\nmap_Kd t.png\n", edits))
    (tmp_path / "m.obj").write_text(
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl a\nf 1/1 2/2 3/3\n"
    )
    _loads_or_scene_error(tmp_path / "m.obj")


def test_unknown_suffix_names_the_accepted_formats(tmp_path):
    (tmp_path / "s.fbx").write_text("x")
    with pytest.raises(
        SceneError, match=r"unknown scene file type '\.fbx'; accepted: \.toml .*\.gltf .*\.glb .*\.xml .*\.obj"
    ):
        load_scene(tmp_path / "s.fbx")


def test_cli_info_reads_an_xml_scene(tmp_path):
    from typer.testing import CliRunner

    from torch_brdf.cli import app

    res = CliRunner().invoke(app, ["info", str(xml(tmp_path))])
    assert res.exit_code == 0 and '"floor"' in res.output
    png(tmp_path / "t.png")
    res = CliRunner().invoke(app, ["info", str(xml(tmp_path, bitmap("t.png"), name="t.xml"))])
    assert res.exit_code == 0 and '"base_color": "t.png"' in res.output, res.output
    res = CliRunner().invoke(app, ["info", str(xml(tmp_path, '<bsdf type="dielectric"/>', name="d.xml"))])
    assert res.exit_code != 0 and "unsupported BSDF plugin 'dielectric'" in res.output
    res = CliRunner().invoke(app, ["--substitute", "info", str(tmp_path / "d.xml")])
    assert res.exit_code == 0 and '"floor"' in res.output, res.output
    res = CliRunner().invoke(app, ["info", str(tmp_path / "nothing.abc")])
    assert res.exit_code != 0 and ".gltf" in res.output and "Traceback" not in res.output


# -- textures and .hdr ----------------------------------------------------------------------
def test_texture_lookup_is_bilinear_between_texel_centres():
    img = torch.arange(12, dtype=torch.float32).reshape(2, 2, 3)
    t = Texture(img)
    # texel (row 0, col 0) is the top-left: its centre is at uv (0.25, 0.75)
    torch.testing.assert_close(t.lookup(torch.tensor([[0.25, 0.75]])), img[0, 0][None])
    torch.testing.assert_close(t.lookup(torch.tensor([[0.75, 0.25]])), img[1, 1][None])
    torch.testing.assert_close(t.lookup(torch.tensor([[0.5, 0.75]])), ((img[0, 0] + img[0, 1]) / 2)[None])
    torch.testing.assert_close(t.lookup(torch.tensor([[1.25, 1.75]])), img[0, 0][None])  # repeat


def test_png_textures_decode_srgb_and_linear_maps_do_not(tmp_path):
    a = png(tmp_path / "t.png")
    torch.testing.assert_close(
        read_texture(tmp_path / "t.png").image, torch.from_numpy(srgb_to_linear(a / 255.0)).float()
    )
    torch.testing.assert_close(read_texture(tmp_path / "t.png", srgb=False).image, torch.from_numpy(a / 255.0).float())
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\nrubbish")
    with pytest.raises(FileFormatError, match=r"bad\.png"):
        read_texture(tmp_path / "bad.png")


def test_hdr_round_trip_and_run_length_scanlines(tmp_path):
    img = torch.rand(5, 9, 3, generator=torch.Generator().manual_seed(0)) * 10
    write_hdr(tmp_path / "a.hdr", img)
    err = (read_hdr(tmp_path / "a.hdr") - img).abs()
    assert bool((err <= img.amax(-1, keepdim=True) / 128).all())  # 8 mantissa bits of the largest channel
    # one RLE scanline of width 8: R a run of 8 x 128, G literal 8 values, B run, E run (e = 129: x 2^-7)
    head = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 1 +X 8\n"
    line = bytes([2, 2, 0, 8, 128 + 8, 128, 8, *range(8), 128 + 8, 0, 128 + 8, 129])
    (tmp_path / "r.hdr").write_bytes(head + line)
    got = read_hdr(tmp_path / "r.hdr")
    assert got[0, :, 0].tolist() == pytest.approx([128.5 / 128] * 8)
    assert got[0, :, 1].tolist() == pytest.approx([(g + 0.5) / 128 for g in range(8)])
    (tmp_path / "t.hdr").write_bytes(head + line[:-3])
    with pytest.raises(FileFormatError, match=r"truncated|bad run length"):
        read_hdr(tmp_path / "t.hdr")


def test_constant_texture_equals_scaled_albedo_in_the_path_tracer():
    """Shared random numbers: a texture of constant c on albedo a renders as albedo a * c."""
    from torch_brdf.scene import Camera, Scene, SceneObject, mesh_from_arrays
    from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace

    m = mesh_from_arrays([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], [[0, 2, 1], [0, 3, 2]], "f")
    box = mesh_from_arrays([[-0.3, 0, 0], [0.3, 0, 0], [0, 0.6, 0]], [[0, 1, 2]], "t")
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    c = torch.tensor([0.5, 0.8, 0.25])
    cam = Camera((0, 2, 2), (0, 0, 0), fov_deg=50, width=12, height=12)
    light = [DirectionalLight((0.2, 1, 0.4), 2.0)]
    # Lambert: its sampling does not depend on the albedo, so both scenes draw the same paths
    mats = {"a": {"type": "lambert", "albedo": [0.6, 0.5, 0.9]}}
    tex = SceneObject("f", m, "a", uv=uv, textures={"base_color": Texture(c.expand(3, 3, 3).clone())})
    textured = Scene([tex, SceneObject("t", box, "a")], mats, light, cam, workers=1)
    mats2 = {"a": mats["a"], "b": {**mats["a"], "albedo": (torch.tensor(mats["a"]["albedo"]) * c).tolist()}}
    plain = Scene([SceneObject("f", m, "b"), SceneObject("t", box, "a")], mats2, light, cam, workers=1)
    a = path_trace(textured, PathTraceSettings(spp=4, max_bounces=3), progress=False)
    b = path_trace(plain, PathTraceSettings(spp=4, max_bounces=3), progress=False)
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    assert textured.content_digest() != plain.content_digest()
