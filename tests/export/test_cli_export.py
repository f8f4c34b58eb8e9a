"""``torch-brdf export`` and ``torch-brdf edit --export`` (typer's test runner)."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from torch_brdf.cli import app

runner = CliRunner()


def test_export_json_material_scene_object_and_scene(tmp_path):
    res = runner.invoke(app, ["export", '{"type": "lambert", "albedo": 0.5}', str(tmp_path / "m.xml")])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout.strip().splitlines()[-1])["target"] == "diffuse"
    res = runner.invoke(app, ["export", "cornell_box:back", str(tmp_path / "back.gltf")])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "back.gltf").read_text())
    assert doc["materials"][0]["name"] == "back"
    res = runner.invoke(app, ["export", "cornell_box", str(tmp_path / "scene.xml")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "scene.xml").is_file() and (tmp_path / "scene.xml.export.json").is_file()
    assert len(list((tmp_path / "scene_meshes").glob("*.ply"))) == 8


def test_export_errors_are_one_line(tmp_path):
    cases = [
        (["export", "cornell_box:nope", str(tmp_path / "m.gltf")], "no object 'nope'"),
        (["export", "{not json", str(tmp_path / "m.xml")], "not valid JSON"),
        (["export", '{"type": "lambert"}', str(tmp_path / "m.txt")], "format"),
        (
            ["export", '{"type": "blinn_phong", "exponent": 50}', str(tmp_path / "m.xml"), "--tolerance", "0.01"],
            "above the tolerance 0.01",
        ),
    ]
    for args, message in cases:
        res = runner.invoke(app, args)
        assert res.exit_code == 2, (args, res.output)
        assert message in res.output and "Traceback" not in res.output
    assert not (tmp_path / "m.xml").exists()


def test_export_creates_the_output_folder(tmp_path):
    """Like every other command's ``--out``, OUT's missing folders are made."""
    res = runner.invoke(app, ["export", '{"type": "lambert", "albedo": 0.5}', str(tmp_path / "new" / "m.xml")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "new" / "m.xml").is_file()


def test_edit_export_is_checked_before_work(tmp_path):
    res = runner.invoke(app, ["edit", str(tmp_path / "none.npz"), "--export", "back:usd:x.usd"])
    assert res.exit_code == 2 and "unknown format 'usd'" in res.output
    res = runner.invoke(app, ["edit", str(tmp_path / "none.npz"), "--export", "back-only"])
    assert res.exit_code == 2 and "OBJECT:FORMAT:FILE" in res.output


def test_edit_save_scene_and_export(tmp_path):
    tensors = tmp_path / "t.npz"
    pre = ["precompute", "cornell_box_glossy", "--resolution", "8", "--spp", "1", "--series", "2,1"]
    assert runner.invoke(app, [*pre, "--out", str(tensors)]).exit_code == 0
    saved, xml = tmp_path / "edited.toml", tmp_path / "back.xml"
    edit = ["edit", str(tensors), "--out", str(tmp_path / "e"), "--set", "back.exponent=400", "--set", "back.ks=0.3"]
    res = runner.invoke(app, [*edit, "--save-scene", str(saved), "--export", f"back:mitsuba:{xml}"])
    assert res.exit_code == 0, res.output
    info = json.loads(res.stdout.strip().splitlines()[-1])
    edited = info["materials"]["back"]
    assert info["exports"][0]["object"] == "back" and xml.is_file()
    # the saved scene re-opens with the edit (bit for bit) and renders it through the CLI again
    from torch_brdf.scene import Scene

    back = Scene.from_toml(saved)
    obj = next(o for o in back.objects if o.name == "back")
    assert back.materials[obj.material] == json.loads(json.dumps(edited))
    res2 = runner.invoke(app, ["edit", str(tensors), "--scene", str(saved), "--out", str(tmp_path / "e2")])
    assert res2.exit_code == 0, res2.output
    from torch_brdf.io import read_exr

    assert torch_equal(read_exr(tmp_path / "e.exr"), read_exr(tmp_path / "e2.exr"))


def torch_equal(a, b) -> bool:
    import torch

    return bool(torch.equal(torch.as_tensor(a), torch.as_tensor(b)))
