"""A new user's path through the command line: the command table is the
typer app's real commands, options and defaults; the documented flows run end to end with the
default file names; cheap argument checks come before expensive work; long commands print
progress."""

from __future__ import annotations

import importlib.util
import json
import re
from importlib.metadata import version
from pathlib import Path

import click
import pytest
import typer
from typer.testing import CliRunner

from torch_brdf.cli import app
from torch_brdf.data import data_path
from torch_brdf.io import read_exr
from torch_brdf.scene import BUILTIN_SCENES

from .test_cli import RELIGHT_TOML

README = Path(__file__).resolve().parents[1] / "README.md"
runner = CliRunner()


def last_json(output: str) -> dict:
    """The JSON summary a command prints last (after any progress bars, maybe on their line)."""
    return json.loads(next(ln[ln.index('{"') :] for ln in reversed(output.splitlines()) if '{"' in ln))


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


def _load_trainer(name: str):
    """trainers/NAME.py as a module (the trainers are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, README.parent / "trainers" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


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
    assert "--resolution is deprecated; use --cubemap 16" in res.stderr  # the old name still works, and says so
    assert last_json(res.output)["out"] == str(Path("out/vis.npz")) and Path("out/vis.npz").is_file()
    assert not Path("out/vis.chunks").exists()  # the checkpoint folder is removed on success
    res = runner.invoke(app, ["relight", "tiny.toml", "--resolution", "12"])  # reads out/vis.npz by default
    assert res.exit_code == 0, res.output
    assert "box (8 vertices), floor (5 vertices) too coarse" in res.stderr  # per-vertex shading: says so
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


def test_fit_gplvm_then_manifold(tmp_path, monkeypatch):
    """trainers/fit_gplvm.py -> ``torch-brdf manifold FIT --point/--path`` at small sizes."""
    import torch

    from tests.conftest import shared_file

    shared_file("merl", "nbrdf_merl100_weights.npz")
    monkeypatch.chdir(tmp_path)
    cache = tmp_path / "cache"
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(cache))
    trainer = _load_trainer("fit_gplvm")
    trainer.main(["--q", "2", "--out", "out/fit.npz", "--grid", "15,15,30", "--max-iter", "20"])
    small = ["--grid", "15,15,30", "--spp", "2"]
    res = runner.invoke(app, ["manifold", "out/fit.npz", "--point", "chrome", "--resolution", "16", *small])
    assert res.exit_code == 0, res.output
    (one,) = last_json(res.output)["frames"]
    assert one["png"] == str(Path("out/manifold.png")) and one["heaviest"][0] == ["chrome", 1.0]
    monkeypatch.setenv("TORCH_BRDF_PROGRESS", "1")
    args = ["manifold", "out/fit.npz", "--path", "chrome:silver-paint", "--frames", "3", "--width", "16"]
    res = runner.invoke(app, [*args, "--height", "12", "--out", "out/path", *small])
    assert res.exit_code == 0 and "3/3 [" in res.output, res.output  # a tick per frame
    frames = last_json(res.output)["frames"]
    assert [f["exr"] for f in frames] == [str(Path(f"out/path_{i:03d}.exr")) for i in range(3)]
    assert len({f["exposure"] for f in frames}) == 1  # one exposure for the whole path
    imgs = [read_exr(Path(f["exr"])) for f in frames]
    assert imgs[0].shape == (12, 16, 3)
    # the path starts exactly at chrome (same row, same seed: the same pixels as the --point render)
    res = runner.invoke(
        app, ["manifold", "out/fit.npz", "--point", "chrome", "--width", "16", "--height", "12"] + small
    )
    assert res.exit_code == 0 and torch.equal(read_exr(Path("out/manifold.exr")), imgs[0])
    assert (imgs[1] - imgs[0]).abs().max() > 1e-3 and frames[2]["heaviest"][0] == ["silver-paint", 1.0]
    # the rows were tabulated into the cache, nothing but out/ in the working folder
    assert list(cache.glob("merl_nbrdf_*.npz"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", "out"]
    bad = {
        "--point and --path": ["--point", "chrome", "--path", "chrome:teflon"],
        "neither": [],
        "unknown material": ["--point", "nosuch-material"],
        "one waypoint": ["--path", "chrome"],
        "wrong dimension": ["--point", "0.1,0.2,0.3"],
        "bad grid": ["--point", "chrome", "--grid", "3,3"],
    }
    for what, extra in bad.items():
        res = runner.invoke(app, ["manifold", "out/fit.npz", *extra])
        assert res.exit_code == 2 and res.output.startswith("error: "), f"{what}: {res.output}"


#: small arguments for every row of the README table, in its order; each row reads what the
#: rows above it wrote with the documented default names (out/tensors.npz, out/vis.npz, ...)
ROW_ARGS = {
    "demo": ["--resolution", "8", "--spp", "2"],
    "render": ["cornell_box_glossy", "--resolution", "8", "--spp", "2"],
    "info": ["cornell_box_glossy"],
    "precompute": ["cornell_box_glossy", "--resolution", "8", "--spp", "2", "--series", "4,1"],
    "edit": ["out/tensors.npz", "--set", "back.exponent=400"],
    "export": ["cornell_box:left", "out/left.xml"],
    "fit-strokes": ["teatray", "--object", "teapot", "--strokes", "strokes.json"]
    + ["--width", "64", "--height", "48", "--downsample", "2", "--samples", "32"],
    "precompute-visibility": ["tiny.toml", "--cubemap", "16", "--chunk", "4"],
    "relight": ["tiny.toml", "--resolution", "12"],
    "fit-image": ["out/tensors.npz", "--target", "out/edit.exr", "--object", "back", "--iterations", "2"],
    "fit-gplvm": ["--grid", "15,15,30", "--max-iter", "20"],
    "manifold": ["out/gplvm.npz", "--point", "chrome", "--grid", "15,15,30", "--resolution", "16", "--spp", "2"],
    "editor": ["tiny.toml", "--resolution", "8", "--spp", "2", "--series", "2,1"],
    "fetch-data": ["--dest", "data", "--file", "meshes/teapot.obj"],
    "report": ["--results", str(README.parent / "docs" / "results")],  # saved JSON: no benchmark runs
}
#: the commands that are quick at any size (dot products, JSON): no progress bar expected; report
#: only reads saved JSON here (its benchmark runs have a bar per script: torch_brdf.report)
QUICK = {"info", "edit", "export", "report"}


def _run_editor(args: list[str], cwd: Path) -> str:
    """``torch-brdf editor`` in a process until it prints its URL; SIGTERM; its whole output."""
    import os
    import signal
    import subprocess
    import sys
    import time

    if importlib.util.find_spec("voila") is None:
        if os.environ.get("CI"):
            pytest.fail("CI must run the editor row: voila is not installed")
        pytest.skip("voila is not installed (pip install -e '.[editor]')")
    cmd = [sys.executable, "-m", "torch_brdf.cli", "editor", *args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=cwd)
    seen = []
    try:
        deadline = time.monotonic() + 240
        while not any("http://127.0.0.1:" in ln for ln in seen) and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line and proc.poll() is not None:
                break
            seen.append(line)
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    text = "".join(seen)
    assert "http://127.0.0.1:" in text, text
    return text


def test_every_row_of_the_readme_table_runs(tmp_path, monkeypatch, request):
    """Each README row in order, at small sizes, with the default file names between rows; every
    command that can take more than a few seconds prints a tqdm bar on stderr."""
    rows = [re.match(r"`torch-brdf ([\w-]+)", usage)[1] for usage, _ in cli_table()]
    assert list(ROW_ARGS) == rows, "ROW_ARGS must follow the README table (add small arguments for a new row)"
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("TORCH_BRDF_PROGRESS", "1")
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(tmp_path / "cache"))
    Path("tiny.toml").write_text(RELIGHT_TOML)
    strokes = {"strokes": [{"points": [[30, 20], [40, 22]], "color": [3, 3, 3], "diameter": 10}]}
    Path("strokes.json").write_text(json.dumps(strokes | {"display_size": [64, 48]}))
    skipped = {}
    for name, args in ROW_ARGS.items():
        if name in ("fit-gplvm", "manifold") and data_path("merl", "nbrdf_merl100_weights.npz", required=False) is None:
            skipped[name] = "needs the shared NBRDF data"
            continue
        if name == "fetch-data":
            try:
                url, _ = request.getfixturevalue("mirror")
            except pytest.skip.Exception as exc:
                skipped[name] = str(exc)
                continue
            args = [*args, "--url", url]
        if name == "editor":
            try:
                text = _run_editor(args, tmp_path)
            except pytest.skip.Exception as exc:
                skipped[name] = str(exc)
                continue
            assert TQDM.search(text), f"editor printed no progress while precomputing: {text}"
            continue
        res = runner.invoke(app, [name, *args])
        assert res.exit_code == 0, f"{name}: {res.output}"
        json.loads(res.stdout) if name == "info" else last_json(res.stdout)  # the JSON is on stdout ...
        if name not in QUICK:  # ... and the progress on stderr
            assert TQDM.search(res.stderr), f"{name} printed no progress: {res.stderr!r}"
    # the documented default outputs exist, nothing outside out/, the data folder and the cache
    assert {"cornell_box.png", "render.png", "tensors.npz", "edit.png", "vis.npz", "relight.png"} <= {
        p.name for p in Path("out").iterdir()
    }
    assert {p.name for p in tmp_path.iterdir()} <= {"out", "data", "cache", "served", "tiny.toml", "strokes.json"}
    if skipped:
        pytest.skip(f"rows not run: {skipped}")


@pytest.mark.parametrize("script", sorted(p.stem for p in (README.parent / "trainers").glob("*.py")))
def test_trainer_help_is_the_cli_and_does_not_import_torch(script):
    """``python trainers/X.py --help`` prints the matching CLI command's options without loading
    torch (checked with ``-X importtime``, not a wall clock)."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": str(README.parent)}
    cmd = [sys.executable, "-X", "importtime", str(README.parent / "trainers" / f"{script}.py"), "--help"]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    loaded = {ln.rsplit("|", 1)[-1].strip() for ln in res.stderr.splitlines() if ln.startswith("import time:")}
    assert "torch" not in loaded and "numpy" not in loaded, "--help imported torch/numpy"
    usage = re.search(r"Usage: torch-brdf ([\w-]+)", res.stdout)
    assert usage, res.stdout
    cli = commands()[usage[1]]
    for p in cli.params:  # the trainer's options are the command's
        for opt in () if getattr(p, "hidden", False) else p.opts:
            if opt.startswith("--"):
                assert opt in res.stdout, f"{script}: {opt} missing from --help"


def test_width_and_height_everywhere_an_image_is_made(tmp_path, monkeypatch):
    from torch_brdf.records import PolynomialTensors

    monkeypatch.chdir(tmp_path)
    Path("tiny.toml").write_text(RELIGHT_TOML)
    small = ["--spp", "1", "--no-progress"]
    for name, extra in {"demo": [], "render": ["tiny.toml"]}.items():
        res = runner.invoke(app, [name, *extra, "--width", "16", "--height", "8", *small, "--out", f"out/{name}"])
        assert res.exit_code == 0, res.output
        assert read_exr(Path(f"out/{name}.exr")).shape == (8, 16, 3)
    res = runner.invoke(app, ["render", "tiny.toml", "--resolution", "12", "--height", "8", *small])
    assert res.exit_code == 0 and last_json(res.output)["size"] == [12, 8]  # one side from --resolution
    args = ["precompute", "tiny.toml", "--width", "10", "--height", "8", "--series", "2,1", *small]
    assert runner.invoke(app, args).exit_code == 0
    T = PolynomialTensors.load("out/tensors.npz")
    assert (T.width, T.height) == (10, 8)
    assert runner.invoke(app, ["precompute-visibility", "tiny.toml", "--cubemap", "16", *small[2:]]).exit_code == 0
    res = runner.invoke(app, ["relight", "tiny.toml", "--width", "12", "--height", "9"])
    assert res.exit_code == 0 and read_exr(Path("out/relight.exr")).shape == (9, 12, 3)
    res = runner.invoke(app, ["render", "tiny.toml", "--width", "99999"])
    assert res.exit_code == 2 and "--width" in res.output


def test_render_quick_mesh_and_envmap(tmp_path, monkeypatch):
    import torch
    import trimesh

    from torch_brdf.io import write_exr
    from torch_brdf.scene import mesh_scene

    monkeypatch.chdir(tmp_path)
    trimesh.creation.capsule(height=2.0, radius=0.4).export("thing.ply")  # tall: scaled to 1.6 high
    write_exr(Path("red.exr"), torch.tensor([1.0, 0.05, 0.05]).expand(16, 32, 3).contiguous())
    sc = mesh_scene("thing.ply", 32)
    xy = sc.camera.project(torch.as_tensor(sc.objects[0].mesh.vertices, dtype=torch.float64))
    assert bool((xy > 0).all() and (xy < 32).all())  # framed: the whole mesh is in view
    args = ["render", "--mesh", "thing.ply", "--width", "24", "--height", "16", "--spp", "2", "--no-progress"]
    assert runner.invoke(app, [*args, "--out", "out/sky"]).exit_code == 0
    res = runner.invoke(app, [*args, "--envmap", "red.exr", "--out", "out/red"])
    assert res.exit_code == 0, res.output
    sky, red = read_exr(Path("out/sky.exr")), read_exr(Path("out/red.exr"))
    assert sky.shape == red.shape == (16, 24, 3)
    assert float(red[..., 0].mean()) > 5 * float(red[..., 2].mean())  # lit by the red map, not the sky
    res = runner.invoke(app, ["render", "tiny.toml", "--mesh", "thing.ply"])
    assert res.exit_code == 2 and "not both" in res.output
    res = runner.invoke(app, ["render", "--mesh", "nothing.ply"])
    assert res.exit_code == 2 and "--mesh" in res.output


@pytest.mark.parametrize("progress", ["1", "0"])
def test_loading_torch_is_announced(progress):
    """Importing torch takes seconds on a busy machine: with progress on, a command says so on
    stderr before it starts (and not with progress off, nor for --help)."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": str(README.parent), "TORCH_BRDF_PROGRESS": progress}
    cmd = [sys.executable, "-m", "torch_brdf.cli", "info", "cornell_box"]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert json.loads(res.stdout)["name"] == "cornell_box"
    assert ("torch-brdf info: loading torch ..." in res.stderr) == (progress == "1"), res.stderr
    res = subprocess.run([*cmd, "--help"], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0 and "loading torch" not in res.stderr + res.stdout
