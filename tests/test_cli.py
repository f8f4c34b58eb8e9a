"""The torch-brdf command line (typer's test runner, small images)."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from torch_brdf.cli import app
from torch_brdf.io import read_exr, read_png

runner = CliRunner()


def test_info_builtin():
    res = runner.invoke(app, ["info", "cornell_box"])
    assert res.exit_code == 0, res.output
    info = json.loads(res.stdout)
    assert info["name"] == "cornell_box" and len(info["objects"]) == 8 and info["triangles"] == 32


def test_demo_writes_exr_and_png(tmp_path):
    out = tmp_path / "sub" / "cb"
    res = runner.invoke(app, ["demo", "--out", str(out), "--resolution", "16", "--spp", "1", "--bounces", "2"])
    assert res.exit_code == 0, res.output
    img = read_exr(out.with_suffix(".exr"))
    assert img.shape == (16, 16, 3) and float(img.mean()) > 0
    assert read_png(out.with_suffix(".png")).shape == (16, 16, 3)
    assert json.loads(res.stdout.strip().splitlines()[-1])["spp"] == 1


def test_render_toml_and_errors(tmp_path):
    toml = tmp_path / "s.toml"
    toml.write_text(
        """
name = "tri"
[camera]
origin = [0, 0, -3]
target = [0, 0, 0]
width = 8
height = 8
[materials.m]
type = "lambert"
albedo = 0.5
[[objects]]
name = "quad"
material = "m"
vertices = [[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]
faces = [[0, 1, 2], [0, 2, 3]]
[[lights]]
type = "envmap"
procedural = "constant"
radiance = 1.0
"""
    )
    res = runner.invoke(app, ["render", str(toml), "--out", str(tmp_path / "r"), "--spp", "2", "--no-resume"])
    assert res.exit_code == 0, res.output
    assert read_exr(tmp_path / "r.exr").shape == (8, 8, 3)
    bad = runner.invoke(app, ["render", "no_such_scene"])
    assert bad.exit_code == 2 and "unknown scene" in bad.output


def test_precompute_writes_loadable_tensors(tmp_path):
    from torch_brdf.transport.polynomial import PolynomialTensors

    out = tmp_path / "t.npz"
    args = ["precompute", "cornell_box_glossy", "--resolution", "8", "--spp", "2", "--series", "4,1", "--out", str(out)]
    res = runner.invoke(app, [*args, "--bases", '{"left": {"J": 2}}', "--storage", "float16"])
    assert res.exit_code == 0, res.output
    info = json.loads(res.output[res.output.index('{"out"') :].splitlines()[0])  # after tqdm's bar
    assert set(info["mb_per_bounce"]) == {"1", "2"}
    T = PolynomialTensors.load(out)
    assert T.bases[T.object_id("left")].J == 2 and not (tmp_path / "t.tiles").exists()
    bad = runner.invoke(app, [*args, "--bases", "{not json"])
    assert bad.exit_code == 2 and "JSON" in bad.output
    bad = runner.invoke(app, [*args[:-2], "--out", str(out), "--series", "1,4"])
    assert bad.exit_code == 2


RELIGHT_TOML = """
name = "tiny_relight"
[camera]
origin = [0.0, 1.2, -2.0]
target = [0.0, 0.2, 0.0]
up = [0.0, 1.0, 0.0]
fov_deg = 45.0
width = 24
height = 16
[materials]
box = { type = "phong", kd = 0.3, ks = 0.4, exponent = 50.0 }
floor = { type = "lambert", albedo = 0.5 }
[[objects]]
name = "box"
material = "box"
vertices = [[-0.3, 0.2, -0.3], [0.3, 0.2, -0.3], [0.3, 0.2, 0.3], [-0.3, 0.2, 0.3],
            [-0.3, 0.6, -0.3], [0.3, 0.6, -0.3], [0.3, 0.6, 0.3], [-0.3, 0.6, 0.3]]
faces = [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
         [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]]
[[objects]]
name = "floor"
material = "floor"
vertices = [[-1.0, 0.0, -1.0], [-1.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 0.0, -1.0], [0.0, 0.0, 0.0]]
faces = [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]
[[lights]]
type = "envmap"
procedural = "sky"
height = 16
"""


def test_precompute_visibility_and_relight(tmp_path):
    from torch_brdf.transport.visibility import VertexVisibility

    toml = tmp_path / "tiny.toml"
    toml.write_text(RELIGHT_TOML)
    out = tmp_path / "vis.npz"
    res = runner.invoke(app, ["precompute-visibility", str(toml), "--resolution", "32", "--out", str(out)])
    assert res.exit_code == 0, res.output
    info = json.loads(res.output[res.output.index('{"out"') :].splitlines()[0])
    assert info["vertices"] == 13 and info["bytes_per_vertex"] > 0
    assert len(VertexVisibility.load(out).vertices) == 13 and not (tmp_path / "vis.chunks").exists()
    img_out = tmp_path / "frame"
    res = runner.invoke(app, ["relight", str(toml), "--visibility", str(out), "--out", str(img_out), "--rotate", "0.5"])
    assert res.exit_code == 0, res.output
    stats = json.loads(res.stdout.strip().splitlines()[-1])["stats"]
    assert stats["vertices"] > 0 and sum(stats["cases"].values()) == stats["blocks"]
    assert read_exr(img_out.with_suffix(".exr")).shape == (16, 24, 3)
    bad = runner.invoke(app, ["precompute-visibility", str(toml), "--resolution", "40", "--out", str(out)])
    assert bad.exit_code == 2 and "multiple" in bad.output
