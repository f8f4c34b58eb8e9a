"""A new user's path through the command line (issue #19): the README's command table is the
typer app's real commands, options and defaults; the documented flows run end to end with the
default file names; cheap argument checks come before expensive work; long commands print
progress."""

from __future__ import annotations

import json
import re
from importlib.metadata import version
from pathlib import Path

import click
import pytest
import typer
from typer.testing import CliRunner

from torch_brdf.cli import app
from torch_brdf.io import read_exr
from torch_brdf.scene import BUILTIN_SCENES

from .test_cli import RELIGHT_TOML

README = Path(__file__).resolve().parents[1] / "README.md"
runner = CliRunner()


def last_json(output: str) -> dict:
    """The JSON summary a command prints last (after any progress bars)."""
    return json.loads(next(ln for ln in reversed(output.splitlines()) if ln.startswith("{")))


def cli_table() -> list[tuple[str, str]]:
    """(first cell, second cell) of every row of the README's "Command line" table."""
    text = README.read_text(encoding="utf-8")
    section = text.split("## Command line", 1)[1].split("\n## ", 1)[0]
    rows = []
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")] if line.startswith("| `") else []
        if cells:
            rows.append((cells[0], cells[1]))
    return rows


def commands() -> dict[str, click.Command]:
    return dict(typer.main.get_command(app).commands)


def test_version():
    res = runner.invoke(app, ["--version"])
    assert res.exit_code == 0 and res.output.strip() == f"torch_brdf {version('torch_brdf')}"


def test_readme_table_is_the_real_cli():
    cmds = commands()
    rows = cli_table()
    seen = set()
    for usage, what in rows:
        m = re.match(r"`torch-brdf ([\w-]+)([^`]*)`", usage)
        assert m, f"README row does not start with a torch-brdf command: {usage}"
        name, rest = m[1], m[2]
        assert name in cmds, f"README documents {name!r}, which the CLI does not have"
        seen.add(name)
        params = {o: p for p in cmds[name].params for o in (*p.opts, *p.secondary_opts)}
        for opt in re.findall(r"--[\w-]+", rest):
            assert opt in params, f"README: `torch-brdf {name}` has no option {opt}"
        # documented defaults "[--opt VALUE ...]" must be the real ones
        for opt, value in re.findall(r"(--[\w-]+) ([^\s\]-][^\s\]]*)", rest.split("[", 1)[-1] if "[" in rest else ""):
            if value.split(".")[0].isupper():  # a placeholder (JSON, K, FIT.npz, OBJECT.PARAM=VALUE)
                continue
            default = params[opt].default
            assert str(default) == value, f"README: {name} {opt} defaults to {default!r}, not {value!r}"
        if name == "render":
            listed = set(re.findall(r"`(\w+)`", what))
            assert set(BUILTIN_SCENES) <= listed, f"README's render row omits {set(BUILTIN_SCENES) - listed}"
    assert seen == set(cmds), f"commands missing from the README table: {set(cmds) - seen}"


def test_precompute_visibility_then_relight_with_default_names(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    Path("tiny.toml").write_text(RELIGHT_TOML)
    res = runner.invoke(app, ["precompute-visibility", "tiny.toml", "--resolution", "16", "--no-progress"])
    assert res.exit_code == 0, res.output
    assert last_json(res.output)["out"] == str(Path("out/vis.npz")) and Path("out/vis.npz").is_file()
    assert not Path("out/vis.chunks").exists()  # the checkpoint folder is removed on success
    res = runner.invoke(app, ["relight", "tiny.toml", "--resolution", "12"])  # reads out/vis.npz by default
    assert res.exit_code == 0, res.output
    assert read_exr(Path("out/relight.exr")).shape == (12, 12, 3)


def test_precompute_then_edit(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    base = ["precompute", "cornell_box_glossy", "--resolution", "8", "--spp", "2", "--series", "4,1"]
    res = runner.invoke(app, [*base, "--out", "out/cb.npz", "--no-progress"])
    assert res.exit_code == 0, res.output
    assert not Path("out/cb.tiles").exists()
    res = runner.invoke(app, ["edit", "out/cb.npz", "--out", "out/as_saved"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["edit", "out/cb.npz", "--set", "back.exponent=400", "--set", "back.kd=[0.5,0.1,0.1]"])
    assert res.exit_code == 0, res.output
    info = last_json(res.output)
    assert info["materials"]["back"]["exponent"] == 400 and info["png"] == str(Path("out/edit.png"))
    before, after = read_exr(Path("out/as_saved.exr")), read_exr(Path("out/edit.exr"))
    assert after.shape == (8, 8, 3) and after.isfinite().all()
    assert (after - before).abs().max() > 1e-3  # the edit changed the image
    bad = runner.invoke(app, ["edit", "out/cb.npz", "--set", "nosuch.exponent=4"])
    assert bad.exit_code == 2 and "editable" in bad.output
    bad = runner.invoke(app, ["edit", "out/cb.npz", "--set", "back.exponent"])
    assert bad.exit_code == 2 and "OBJECT.PARAM=VALUE" in bad.output


def test_cheap_checks_come_first(tmp_path, monkeypatch):
    import torch_brdf.records.visibility as recvis
    import torch_brdf.transport.polynomial as tp

    def expensive(*a, **k):
        raise AssertionError("the expensive step ran before the argument check")

    monkeypatch.setattr(tp, "precompute_polynomial", expensive)
    res = runner.invoke(app, ["precompute", "cornell_box", "--storage", "float8", "--out", str(tmp_path / "t.npz")])
    assert res.exit_code == 2 and "float8" in res.output
    monkeypatch.setattr(recvis.VertexVisibility, "load", classmethod(expensive))
    res = runner.invoke(app, ["relight", "cornell_box", "--visibility", str(tmp_path / "v.npz"), "--method", "fast"])
    assert res.exit_code == 2 and "fast" in res.output


TQDM = re.compile(r"\d+%\|")  # tqdm's "NN%|" bar


@pytest.mark.parametrize("method", ["adaptive", "standard", "haar"])
def test_visibility_and_relight_print_progress(tmp_path, monkeypatch, method):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("TORCH_BRDF_PROGRESS", "1")
    Path("tiny.toml").write_text(RELIGHT_TOML)
    res = runner.invoke(app, ["precompute-visibility", "tiny.toml", "--cubemap", "16", "--chunk", "4"])
    assert res.exit_code == 0 and TQDM.search(res.output), res.output
    assert "/4 [" in res.output  # 13 vertices in chunks of 4: a tick per chunk
    res = runner.invoke(app, ["relight", "tiny.toml", "--method", method])
    assert res.exit_code == 0, res.output
    if method != "adaptive":  # the adaptive frame is the fast one (under a second at full size)
        assert TQDM.search(res.output), res.output


def test_each_long_command_prints_progress(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("TORCH_BRDF_PROGRESS", "1")
    Path("tiny.toml").write_text(RELIGHT_TOML)
    strokes = {
        "strokes": [{"points": [[30, 20], [40, 22]], "color": [3, 3, 3], "diameter": 10}],
        "display_size": [64, 48],
    }
    Path("strokes.json").write_text(json.dumps(strokes))
    runs = {
        "demo": ["demo", "--resolution", "8", "--spp", "2"],
        "render": ["render", "tiny.toml", "--resolution", "8", "--spp", "2"],
        "precompute": ["precompute", "tiny.toml", "--resolution", "8", "--spp", "4", "--series", "2,1"],
        "fit-strokes": ["fit-strokes", "teatray", "--object", "teapot", "--strokes", "strokes.json"]
        + ["--width", "64", "--height", "48", "--downsample", "2", "--samples", "32"],
    }
    for name, args in runs.items():
        res = runner.invoke(app, args)
        assert res.exit_code == 0 and TQDM.search(res.output), f"{name}: {res.output}"
    res = runner.invoke(app, [*runs["precompute"], "--no-progress"])
    assert res.exit_code == 0 and not TQDM.search(res.output), res.output


def test_auto_exposure_for_previews(tmp_path):
    import math

    import torch

    from torch_brdf.io import auto_exposure, read_png

    g = torch.Generator().manual_seed(0)
    img = torch.rand(16, 16, 3, generator=g, dtype=torch.float64)
    assert auto_exposure(img * 1e-3) == pytest.approx(auto_exposure(img) + math.log2(1e3), abs=1e-9)
    assert auto_exposure(torch.zeros(4, 4, 3)) == 0.0
    toml = tmp_path / "dim.toml"
    toml.write_text(RELIGHT_TOML.replace('procedural = "sky"', 'procedural = "constant"\nradiance = 0.001'))
    res = runner.invoke(app, ["render", str(toml), "--resolution", "8", "--spp", "2", "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    assert last_json(res.output)["exposure"] > 5  # a dim scene is brightened for the preview ...
    assert read_png(tmp_path / "a.png").float().mean() > 40
    args = ["render", str(toml), "--resolution", "8", "--spp", "2", "--exposure", "0", "--out", str(tmp_path / "b")]
    res = runner.invoke(app, args)
    assert res.exit_code == 0 and last_json(res.output)["exposure"] == 0.0  # ... unless told otherwise
    assert read_png(tmp_path / "b.png").float().mean() < 5
    assert torch.equal(read_exr(tmp_path / "a.exr"), read_exr(tmp_path / "b.exr"))  # the EXR stays linear
