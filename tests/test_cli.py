"""The torch-brdf command line (typer's test runner, small images)."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import pytest
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
    bad = runner.invoke(app, [*args, "--bases", '{"left": {"j": 2}}'])  # was an internal error (TypeError)
    assert bad.exit_code == 2 and "--bases left: unknown key(s) ['j']; known keys: ['J'," in bad.output
    bad = runner.invoke(app, [*args, "--bases", '{"left": {"fresnel": "yes"}}'])  # was taken as true
    assert bad.exit_code == 2 and "--bases left.fresnel must be true or false" in bad.output
    bad = runner.invoke(app, [*args, "--bases", '{"left": {"second": 2}}'])  # one check: CLI and planner agree
    assert bad.exit_code == 2 and "--bases left: unknown key(s) ['second']" in bad.output
    bad = runner.invoke(app, [*args[:-2], "--out", str(out), "--series", "1,4"])
    assert bad.exit_code == 2


def test_precompute_sampler_option(tmp_path):
    from torch_brdf.transport.polynomial import PolynomialTensors

    out = tmp_path / "t.npz"
    args = ["precompute", "cornell_box_glossy", "--resolution", "8", "--spp", "4", "--series", "4,1", "--out", str(out)]
    metas = {}
    for name in ("default", "lobes", "stratified"):
        res = runner.invoke(app, [*args, "--sampler", name])
        assert res.exit_code == 0, res.output
        metas[name] = PolynomialTensors.load(out).meta["mixture"]
    assert len(metas["default"]) == 2  # Mixture: [diffuse, exponent]
    assert metas["lobes"][-1] is True and metas["stratified"][-1] == "stratified"
    bad = runner.invoke(app, [*args, "--sampler", "sobol"])
    want = "--sampler must be one of ('default', 'lobes', 'stratified'); got 'sobol'"
    assert bad.exit_code == 2 and want in bad.output
    assert "Traceback" not in bad.output


def test_edit_checks_its_scene_and_changes_models(tmp_path):
    out = tmp_path / "t.npz"
    args = ["precompute", "cornell_box_glossy", "--resolution", "8", "--spp", "1", "--series", "2,1", "--out", str(out)]
    assert runner.invoke(app, args).exit_code == 0
    edit = ["edit", str(out), "--out", str(tmp_path / "e")]
    # a lambert wall made glossy: the scene's albedo was kept and Blinn-Phong refused it
    res = runner.invoke(app, [*edit, "--set", "left.type=blinn_phong", "--set", "left.exponent=50"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout.splitlines()[-1])["materials"]["left"] == {"type": "blinn_phong", "exponent": 50}
    res = runner.invoke(app, [*edit, "--set", "back.ks=0.2", "--set", "back.type=phong"])  # phong keeps kd, ks, n
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, [*edit, "--set", "back.type=lambert"])  # blinn_phong's kd/ks are not lambert's
    assert res.exit_code == 0, res.output
    for value in ("back.kd=[0.5,0.5,inf]", "back.exponent=inf", "back.exponent=NaN"):  # was "invalid data type 'str'"
        bad = runner.invoke(app, [*edit, "--set", value])
        assert bad.exit_code == 2 and "numbers must be finite" in bad.output, bad.output
    # another scene's objects: its materials were rendered onto the tensors' objects without a word
    toml = tmp_path / "other.toml"
    toml.write_text(RELIGHT_TOML)
    bad = runner.invoke(app, [*edit, "--scene", str(toml)])
    assert bad.exit_code == 2 and "does not match the tensors" in bad.output


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


def test_relight_plans_for_a_psnr(tmp_path):
    """--psnr plans the visibility and rule (the plan on stderr), saves the planned record beside
    the image and renders with it."""
    from torch_brdf.transport.visibility import VertexVisibility

    toml = tmp_path / "tiny.toml"
    toml.write_text(RELIGHT_TOML)
    img_out = tmp_path / "frame"
    res = runner.invoke(app, ["relight", str(toml), "--out", str(img_out), "--psnr", "30"])
    assert res.exit_code == 0, res.output
    assert "relighting plan for error" in res.stderr and "dB" in res.stderr
    plan = json.loads(res.stdout.strip().splitlines()[-1])["plan"]
    vis = VertexVisibility.load(plan["visibility"])
    assert vis.geometry.resolution == plan["cubemap"] and vis.bits == plan["bits"]
    assert plan["predicted_error"] <= 10 ** (-30 / 20)
    assert read_exr(img_out.with_suffix(".exr")).shape == (16, 24, 3)


# -- failures: one line on stderr, a non-zero exit, no traceback (unless --debug) -------------
def _one_line_error(res, code: int, *words: str) -> str:
    assert res.exit_code == code, (res.exit_code, res.stdout, res.stderr)
    # progress bars share stderr; the failure itself is the last line and the only error line
    lines = [ln for ln in res.stderr.strip().splitlines() if "%|" not in ln]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    assert "Traceback" not in res.stderr and res.stderr.rstrip().endswith(lines[0])
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def _raiser(exc: BaseException):
    def go(*args, **kwargs):
        raise exc

    return go


RENDER = ["render", "cornell_box", "--resolution", "8", "--spp", "1", "--bounces", "1", "--no-resume"]


@pytest.mark.parametrize(
    ("exc", "code", "words"),
    [
        (OSError(errno.ENOSPC, "No space left on device", "x.exr"), 1, ("disk full", "x.exr")),
        (PermissionError(errno.EACCES, "Permission denied", "x.exr"), 1, ("permission denied", "x.exr")),
        (OSError(errno.EROFS, "Read-only file system", "x.exr"), 1, ("read-only file system",)),
        (MemoryError(), 1, ("out of memory",)),
        (KeyboardInterrupt(), 130, ("interrupted",)),
        (RuntimeError("boom"), 1, ("internal error", "RuntimeError: boom", "--debug")),
    ],
    ids=["disk-full", "permission", "read-only", "memory", "ctrl-c", "bug"],
)
def test_failures_while_writing_are_one_line(tmp_path, monkeypatch, exc, code, words):
    import torch_brdf.io

    monkeypatch.setattr(torch_brdf.io, "write_exr", _raiser(exc))
    _one_line_error(runner.invoke(app, [*RENDER, "--out", str(tmp_path / "r")]), code, *words)


def test_debug_shows_the_traceback(tmp_path, monkeypatch):
    import torch_brdf.io

    monkeypatch.setattr(torch_brdf.io, "write_exr", _raiser(OSError(errno.ENOSPC, "No space left on device")))
    res = runner.invoke(app, ["--debug", *RENDER, "--out", str(tmp_path / "r")])
    assert res.exit_code == 1 and "Traceback" in res.stderr and "error: disk full" in res.stderr


class _FullDisk:
    """A file whose writes fail with ENOSPC (the file itself is created, as on a full disk)."""

    def __init__(self, path, mode="r", *args, **kwargs):
        self.f = open(path, mode, *args, **kwargs)
        self.name = path

    def write(self, data):
        raise OSError(errno.ENOSPC, "No space left on device", self.name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()


def test_disk_full_during_a_record_save_is_one_line(tmp_path, monkeypatch):
    import torch_brdf.io.arrays

    monkeypatch.setattr(torch_brdf.io.arrays, "open", _FullDisk, raising=False)
    args = ["precompute", "cornell_box", "--resolution", "8", "--spp", "1", "--series", "2,1", "--no-resume"]
    _one_line_error(runner.invoke(app, [*args, "--out", str(tmp_path / "t.npz")]), 1, "disk full")
    assert [p.name for p in tmp_path.iterdir()] == []  # no temporary file left behind


def test_output_under_a_file_is_one_line(tmp_path):
    (tmp_path / "file").write_text("x")
    _one_line_error(runner.invoke(app, [*RENDER, "--out", str(tmp_path / "file" / "sub" / "r")]), 1, "not a folder")


def test_bad_scene_files_are_one_line(tmp_path):
    (tmp_path / "dir.toml").mkdir()
    _one_line_error(runner.invoke(app, ["info", str(tmp_path / "dir.toml")]), 2, "is a directory")
    (tmp_path / "nan.toml").write_text("[camera]\norigin = [0, 0, nan]\ntarget = [0, 0, 0]\n[materials]\n[[objects]]\n")
    _one_line_error(runner.invoke(app, ["info", str(tmp_path / "nan.toml")]), 2, "camera.origin")


@pytest.mark.parametrize(
    ("content", "words"),
    [
        ("{not json", ("not valid JSON",)),
        ('{"strokes": [{"points": [[1, 2]], "diameter": "wide"}]}', ("strokes[0]",)),
        ('{"strokes": 5}', ("'strokes'",)),
    ],
)
def test_bad_strokes_files_are_one_line(tmp_path, monkeypatch, content, words):
    import torch_brdf.cli

    monkeypatch.setattr(torch_brdf.cli, "load_scene", _raiser(AssertionError("the scene must not be loaded")))
    path = tmp_path / "s.json"
    path.write_text(content)
    res = runner.invoke(app, ["fit-strokes", "cornell_box", "--object", "back", "--strokes", str(path)])
    _one_line_error(res, 2, *words)


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["precompute", "cornell_box", "--series", "1000000000,1"], ("--series", "4096")),
        (["precompute", "cornell_box", "--series", "4,x"], ("series",)),
        (["precompute", "cornell_box", "--storage", "float8"], ("--storage", "float8")),
        (["precompute", "cornell_box", "--bases", "{not json"], ("--bases", "JSON")),
        (["precompute", "cornell_box", "--bases", "[1]"], ("--bases", "object")),
        (["precompute", "cornell_box", "--bases", '{"left": {"J": 1e12}}'], ("left.J",)),
        (["precompute-visibility", "cornell_box", "--cubemap", "1048576"], ("--cubemap", "1024")),
        (["precompute-visibility", "cornell_box", "--cubemap", "40"], ("multiple",)),
        (["precompute-visibility", "cornell_box", "--bits", "3"], ("--bits",)),
        (["relight", "cornell_box", "--visibility", "v.npz", "--method", "fast"], ("--method", "fast")),
        (["relight", "cornell_box", "--visibility", "v.npz", "--rotate", "nan"], ("--rotate",)),
        (["relight", "cornell_box", "--error", "0.1", "--psnr", "40"], ("--error", "--psnr")),
        (["relight", "cornell_box", "--psnr", "nan"], ("--psnr",)),
        (["render", "cornell_box", "--exposure", "inf"], ("--exposure",)),
        (["demo", "--out", ""], ("--out", "file name")),  # was an internal error after the render
        (["edit", "t.npz", "--out", "."], ("--out", "file name")),
        (["precompute", "cornell_box", "--out", ""], ("--out", "file name")),
        (
            ["fit-strokes", "cornell_box", "--object", "o", "--strokes", "s", "--width", "16384", "--height", "16384"],
            (),
        ),
    ],
)
def test_options_are_checked_before_any_work(monkeypatch, args, words):
    import torch_brdf.cli
    from torch_brdf.transport.visibility import VertexVisibility

    monkeypatch.setattr(torch_brdf.cli, "load_scene", _raiser(AssertionError("the scene must not be loaded")))
    monkeypatch.setattr(VertexVisibility, "load", _raiser(AssertionError("the record must not be loaded")))
    _one_line_error(runner.invoke(app, args), 2, *words)


def test_sizes_beyond_the_caps_are_usage_errors():
    for args in (["demo", "--resolution", "100000"], ["render", "cornell_box", "--spp", str(2**40)]):
        res = runner.invoke(app, args)
        assert res.exit_code == 2 and "Traceback" not in res.stderr and "Invalid value" in res.stderr


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc (a folder that refuses files)")
def test_an_output_folder_that_refuses_files_is_an_io_error():
    # OpenEXR's RuntimeError there was reported as "internal error ... report the traceback"
    res = runner.invoke(app, [*RENDER, "--out", "/proc/refused"])
    assert res.exit_code == 1 and "internal error" not in res.output and "/proc/refused.exr" in res.output


def test_render_with_neither_scene_nor_mesh_says_so():
    res = runner.invoke(app, ["render", "--envmap", "sky.exr"])  # was "..., not both"
    assert res.exit_code == 2 and "neither was given" in res.output


def test_relight_without_an_environment_map_says_so_before_reading_the_record(tmp_path):
    toml = tmp_path / "dark.toml"
    toml.write_text(RELIGHT_TOML.split("[[lights]]")[0])
    res = runner.invoke(app, ["relight", str(toml), "--visibility", str(tmp_path / "none.npz")])
    assert res.exit_code == 2 and "relight needs an environment map" in res.output  # not "array file not found"


def test_material_keys_come_from_one_helper(monkeypatch):
    # `edit --set OBJECT.type=` and the scene description both ask brdf.base.model_parameters
    # which keys a model takes (they read the constructor's signature each on their own)
    import torch_brdf.brdf.base as base
    from torch_brdf.cli import _retyped
    from torch_brdf.errors import SceneError
    from torch_brdf.scene.description import _material

    phong = {"type": "phong", "kd": [0.5, 0.5, 0.5], "ks": [0.2, 0.2, 0.2], "exponent": 50.0}
    assert _retyped(phong, "blinn_phong") == {**phong, "type": "blinn_phong"}
    assert set(_retyped(phong, "lambert")) == {"type"} | set(phong) & set(base.model_parameters("lambert"))
    monkeypatch.setattr(base, "model_parameters", lambda name: [] if name == "phong" else None)
    assert _retyped({**phong, "type": "lambert"}, "phong") == {"type": "phong"}
    with pytest.raises(SceneError, match=r"unknown key\(s\) \['exponent', 'kd', 'ks'\].*known keys: \['type'\]"):
        _material(phong, "materials.m")
