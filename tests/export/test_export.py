"""torch_brdf.export: glTF and MERL round trips per model, the exact Mitsuba mappings, the
reports beside every file, and one clear error for bad input."""

from __future__ import annotations

import json
import math

import pytest
import torch

from torch_brdf.brdf import MERLTabulated, create
from torch_brdf.errors import ExportError
from torch_brdf.export import export_material, read_gltf_material, replace_gltf_materials, tabulate_merl
from torch_brdf.frame import half_diff_to_directions
from torch_brdf.io.merl import merl_index_to_angles, read_merl_binary

MR_GOLD = {"type": "metallic_roughness", "base_color": [1.0, 0.78, 0.34], "metallic": 1.0, "roughness": 0.35}
MR_PLASTIC = {"type": "metallic_roughness", "base_color": [0.2, 0.4, 0.7], "metallic": 0.0, "roughness": 0.5}
LAMBERT = {"type": "lambert", "albedo": [0.7, 0.5, 0.3]}
GLOSSY = {"type": "blinn_phong", "kd": 0.3, "ks": 0.3, "exponent": 50.0}


def pairs(n: int = 500, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    w = torch.nn.functional.normalize(torch.randn(2, n, 3, generator=g, dtype=torch.float64), dim=-1)
    w[..., 2] = w[..., 2].abs() + 1e-3
    return torch.nn.functional.normalize(w, dim=-1).unbind(0)


def report(path):
    return json.loads((path.parent / (path.name + ".export.json")).read_text())


@pytest.mark.parametrize("material", [MR_GOLD, MR_PLASTIC, LAMBERT])
def test_gltf_exact_round_trip(tmp_path, material):
    out = tmp_path / "m.gltf"
    rep = export_material(material, out, name="paint")
    doc = json.loads(out.read_text())
    assert doc["asset"]["version"] == "2.0" and doc["materials"][0]["name"] == "paint"
    back = read_gltf_material(doc["materials"][0])
    assert back.model_name == material["type"]
    wi, wo = pairs()
    ours = create(material).double().eval(wi, wo).detach()
    torch.testing.assert_close(back.double().eval(wi, wo).detach(), ours, rtol=1e-6, atol=1e-9)
    assert rep.exact and rep.error == 0.0 and report(out)["exact"] is True
    if material is LAMBERT:  # the dielectric's specular removed by KHR_materials_specular
        assert doc["extensionsUsed"] == ["KHR_materials_specular"]


def test_gltf_fit_of_another_model(tmp_path):
    out = tmp_path / "glossy.gltf"
    rep = export_material(GLOSSY, out)
    saved = report(out)
    assert not rep.exact and saved["exact"] is False and 0 < saved["error"] < 1
    back = read_gltf_material(json.loads(out.read_text())["materials"][0])
    assert back.model_name == "metallic_roughness"
    # the written factors are the fit's (the glTF model is the fit's model itself)
    written = saved["params"]["pbrMetallicRoughness"]["roughnessFactor"]
    assert written == pytest.approx(float(back.roughness.detach()), abs=1e-7)


@pytest.mark.parametrize("material", [LAMBERT, MR_GOLD])
def test_merl_round_trip_within_quantisation(tmp_path, material):
    out = tmp_path / "m.binary"
    rep = export_material(material, out)
    assert rep.format == "merl" and report(out)["target"] == "merl"
    table = read_merl_binary(out)
    assert table.shape == (3, 90, 90, 180)
    brdf = create(material).double()
    # at the bins' lower-edge angles the re-imported table is the BRDF (to MERL's stored
    # precision: value / scale rounded in float64), and the MERL lookup returns it
    idx = torch.tensor([0, 7, 30, 61, 89]), torch.tensor([0, 11, 45, 80]), torch.tensor([0, 33, 90, 179])
    th, td, pd = merl_index_to_angles(*idx, at="lower", dtype=torch.float64)
    TH, TD, PD = torch.meshgrid(th, td, pd, indexing="ij")
    wi, wo = half_diff_to_directions(TH, torch.zeros_like(TH), TD, PD)
    want = brdf.eval_local(wi, wo).detach()
    got = table[:, idx[0][:, None, None], idx[1][None, :, None], idx[2][None, None, :]].permute(1, 2, 3, 0)
    up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    torch.testing.assert_close(got[up], want[up], rtol=1e-12, atol=0)
    assert bool((got[~up] == -1).all())
    merl = MERLTabulated(table=table)
    # nudged inside the bin (the lookup floors the continuous index)
    wi2, wo2 = half_diff_to_directions(TH + 1e-6, torch.zeros_like(TH), TD + 1e-6, PD + 1e-6)
    ok = up & (wi2[..., 2] > 0) & (wo2[..., 2] > 0)
    torch.testing.assert_close(merl.eval(wi2, wo2).double()[ok], want[ok], rtol=1e-5, atol=1e-7)


def test_tabulate_marks_the_horizon_missing():
    t = tabulate_merl(LAMBERT)
    assert bool((t == -1).any())
    albedo = create(LAMBERT).reflectance.detach().double()
    torch.testing.assert_close(t[:, 0, 0, 0], albedo / math.pi, rtol=1e-12, atol=0)


@pytest.mark.parametrize(
    ("material", "target"),
    [
        (LAMBERT, "diffuse"),
        ({"type": "cook_torrance", "roughness": 0.3, "f0": 1.0}, "roughconductor"),
    ],
)
def test_mitsuba_exact_mappings(tmp_path, material, target):
    out = tmp_path / "m.xml"
    rep = export_material(material, out, name="paint")
    text = out.read_text()
    assert f'type="{target}"' in text and 'id="paint"' in text and 'type="twosided"' in text
    assert rep.exact and rep.target == target and report(out)["error"] == 0.0


def test_tolerance_that_fails_is_one_clear_error(tmp_path):
    out = tmp_path / "glossy.xml"
    with pytest.raises(ExportError, match=r"above the tolerance 0\.01; nothing was written"):
        export_material(GLOSSY, out, tolerance=0.01, fmt="mitsuba")
    assert not out.exists() and not list(tmp_path.iterdir())


def test_bad_paths_and_formats(tmp_path):
    with pytest.raises(ExportError, match="does not exist"):
        export_material(LAMBERT, tmp_path / "missing" / "m.xml")
    with pytest.raises(ExportError, match="cannot tell the format"):
        export_material(LAMBERT, tmp_path / "m.txt")
    with pytest.raises(ExportError, match="unknown export format"):
        export_material(LAMBERT, tmp_path / "m.xml", fmt="usd")
    with pytest.raises(ExportError, match="cannot build the material"):
        export_material({"type": "nope"}, tmp_path / "m.xml")


def test_replace_gltf_materials(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    box = trimesh.creation.box()
    box.visual = trimesh.visual.TextureVisuals(material=trimesh.visual.material.PBRMaterial(name="paint"))
    ball = trimesh.creation.icosphere(subdivisions=1)
    ball.visual = trimesh.visual.TextureVisuals(material=trimesh.visual.material.PBRMaterial(name="metal"))
    scene = trimesh.Scene({"box": box, "ball": ball})
    files = scene.export(file_type="gltf")
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    src = tmp_path / "model.gltf"
    dst = tmp_path / "edited.gltf"
    reps = replace_gltf_materials(src, dst, {"metal": MR_GOLD})
    doc, before = json.loads(dst.read_text()), json.loads(src.read_text())
    assert [m["name"] for m in doc["materials"]] == [m["name"] for m in before["materials"]]
    metal = next(m for m in doc["materials"] if m["name"] == "metal")
    assert metal["pbrMetallicRoughness"]["metallicFactor"] == 1.0 and reps[0].exact
    assert doc["meshes"] == before["meshes"] and doc["nodes"] == before["nodes"]
    with pytest.raises(ExportError, match=r"no material named \['wood'\]"):
        replace_gltf_materials(src, dst, {"wood": LAMBERT})
