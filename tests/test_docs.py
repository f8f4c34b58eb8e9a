"""The docs cannot drift: every code block of README.md and docs/**/*.md runs, and every quoted
figure equals the saved benchmark result it names.

Code blocks, per page, in document order, in one empty temporary folder and (for Python) one
namespace, so a page can precompute with the command line and then load the file in Python:

* ```python blocks run as pasted, except that a line ``NAME = VALUE  # small: SMALL`` runs with
  ``NAME = SMALL`` (the sizes a reader sees are the real ones; the comment gives the quick ones).
* ```bash blocks: every ``torch-brdf ...`` command runs (in process, through the CLI app). A
  command may end with ``# small: --opt VALUE ...``: each option given there replaces the
  command's value of that option, or is added when the command lacks it. ``export NAME=VALUE``
  sets a variable for the rest of the page. Setup commands (creating the venv, activating it,
  ``pip install``, ``python -m pytest``, ``mkdocs``, ``ruff``) are the one exception: they build
  the environment this test runs in, so they are checked for form only (CI runs the README's
  test command itself, ``tests/test_repo.py``). A command that starts a server or needs the
  network (``torch-brdf editor``, ``torch-brdf fetch-data``, ``ray start``) must say
  ``# not run: REASON``. Other lines (``mkdir -p out && printf ... > out/strokes.json``) run in
  bash, in the same folder. Use ```console or ```text for anything that must not run.
* A page stops, skipped with the reason, at the first block that needs the data folder
  (``DataNotFoundError``), since the blocks after it build on it.

Outputs must go under ``out/`` (caches under ``$TORCH_BRDF_CACHE``), and no checkpoint or tile
folder may be left behind.

Figures: a number followed by ``<!-- fig: BENCH KEY.PATH -->`` (optionally ``<!-- fig: BENCH
KEY.PATH *1000 -->`` for a scale) must equal ``result.KEY.PATH`` of ``docs/results/BENCH.json``
(the saved report run) at the precision written.
"""

from __future__ import annotations

import json
import math
import os
import re
import shlex
import subprocess
from pathlib import Path

import pytest

from torch_brdf.errors import DataNotFoundError

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
SMALL = re.compile(r"^(?P<lhs>\s*[A-Za-z_][\w, ]*?)\s*=\s*(?P<rhs>.+?)\s*#\s*small:\s*(?P<small>.+?)\s*$")
RUN_LANGS = ("python", "bash")
#: commands that build the environment the tests run in (checked for form, not run)
SETUP = re.compile(
    r"^(python3? -m venv \.venv|\. \.venv/bin/activate|source \.venv/bin/activate|pip install .+|"
    r"python -m pytest.*|mkdocs (build|serve).*|ruff (check|format).*)$"
)
#: commands that may carry "# not run: REASON" (a server, or the network)
NOT_RUN_OK = ("torch-brdf editor", "torch-brdf fetch-data", "ray start", "ray stop")
FIG = re.compile(r"<!--\s*fig:\s*(?P<bench>[\w-]+)\s+(?P<path>[^\s*/]+)\s*(?P<scale>[*/]\s*[\d.eE+-]+)?\s*-->")
NUMBER = re.compile(r"[-+]?(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?(?:[eE][-+]?\d+)?")


def rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


def blocks(text: str) -> list[tuple[str, int, str]]:
    """``(language, first line number, code)`` of every fenced block of a Markdown text."""
    out, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        m = re.match(r"^(\s*)```(\w*)\s*$", lines[i])
        if m:
            j = i + 1
            while j < len(lines) and lines[j].strip() != "```":
                j += 1
            indent = len(m[1])
            code = "\n".join(ln[indent:] for ln in lines[i + 1 : j])
            out.append((m[2], i + 2, code + "\n"))
            i = j
        i += 1
    return out


def shrink(code: str) -> tuple[str, int]:
    """The code with every ``# small:`` assignment replaced; and how many were replaced."""
    out, n = [], 0
    for line in code.splitlines():
        m = SMALL.match(line)
        if m:
            line, n = f"{m['lhs']} = {m['small']}", n + 1
        out.append(line)
    return "\n".join(out) + "\n", n


def commands(code: str) -> list[str]:
    """The shell commands of a bash block: continuation lines joined, comments and blanks dropped
    (a trailing ``# small:`` or ``# not run:`` comment stays with its command)."""
    out, cur = [], ""
    for line in code.splitlines():
        if not cur and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if line.rstrip().endswith("\\"):
            cur += line.rstrip()[:-1] + " "
            continue
        out.append((cur + line).strip())
        cur = ""
    return out


def split_comment(command: str) -> tuple[str, str, str]:
    """``(command, kind, text)``: kind is ``small``, ``not run`` or ``""``."""
    m = re.match(r"^(?P<cmd>.*?)\s+#\s*(?P<kind>small|not run):\s*(?P<text>.*)$", command)
    return (m["cmd"], m["kind"], m["text"]) if m else (command, "", "")


def apply_small(args: list[str], small: list[str]) -> list[str]:
    """``args`` with each option of ``small`` (``--opt VALUE`` or a bare ``--flag``) replacing the
    command's own value of it, or added when the command lacks it."""
    args = list(args)
    i = 0
    while i < len(small):
        opt = small[i]
        assert opt.startswith("-"), f"# small: takes options, got {opt!r}"
        has_value = i + 1 < len(small) and not small[i + 1].startswith("--")
        value = small[i + 1] if has_value else None
        if opt in args:
            k = args.index(opt)
            if has_value:
                args[k + 1] = value
        else:
            args += [opt, value] if has_value else [opt]
        i += 2 if has_value else 1
    return args


def page_items(page: Path) -> list[tuple[str, int, str]]:
    return [b for b in blocks(page.read_text(encoding="utf-8")) if b[0] in RUN_LANGS]


RUNNABLE = [p for p in PAGES if page_items(p)]


def test_pages_found():
    assert (ROOT / "README.md") in RUNNABLE and any(p.parent.name == "guides" for p in PAGES)
    assert sum(len(page_items(p)) for p in PAGES) >= 6


def test_shrink_replaces_only_marked_assignments():
    code, n = shrink("size, spp = 256, 64   # small: 16, 2\nx = 3  # a comment\n")
    assert n == 1 and code == "size, spp = 16, 2\nx = 3  # a comment\n"


def test_bash_small_replaces_or_adds_options():
    cmd, kind, text = split_comment("torch-brdf render ring --spp 64 --out out/a  # small: --spp 2 --resolution 16")
    assert kind == "small" and cmd == "torch-brdf render ring --spp 64 --out out/a"
    args = apply_small(shlex.split(cmd)[1:], shlex.split(text))
    assert args == ["render", "ring", "--spp", "2", "--out", "out/a", "--resolution", "16"]
    assert [" ".join(c.split()) for c in commands("a \\\n  --b 1\n# c\n\nd\n")] == ["a --b 1", "d"]


def test_setup_commands_are_only_setup():
    assert SETUP.match("pip install -e .") and SETUP.match("python3 -m venv .venv")
    assert not SETUP.match("torch-brdf demo") and not SETUP.match("rm -rf out")


def test_shell_lines_run_in_the_page_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run_bash("t", "mkdir -p out && printf '%s' '{\"a\": 1}' > out/a.json\n", monkeypatch)
    assert json.loads((tmp_path / "out" / "a.json").read_text()) == {"a": 1}
    with pytest.raises(AssertionError, match="failed"):
        run_bash("t", "false\n", monkeypatch)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One fresh cache for all pages, as a user's would be (band albedos computed once)."""
    return tmp_path_factory.mktemp("docs_cache")


def run_bash(where: str, code: str, monkeypatch) -> None:
    from typer.testing import CliRunner

    from torch_brdf.cli import app

    for line in commands(code):
        cmd, kind, text = split_comment(line)
        # a line without torch-brdf or setup (mkdir, printf > file, ...) runs whole, in bash
        split = "torch-brdf" in cmd or SETUP.match(cmd.split("&&")[0].strip())
        for part in [c.strip() for c in cmd.split("&&")] if split else [cmd]:
            if SETUP.match(part):
                continue
            if kind == "not run":
                assert part.startswith(NOT_RUN_OK), f"{where}: only {NOT_RUN_OK} may be 'not run': {part!r}"
                assert text, f"{where}: '# not run:' needs its reason"
                continue
            m = re.match(r"^export (\w+)=(.*)$", part)
            if m:
                monkeypatch.setenv(m[1], os.path.expandvars(m[2].strip("\"'")))
                continue
            if not part.startswith("torch-brdf "):
                res = subprocess.run(["bash", "-c", part], capture_output=True, text=True, timeout=600)
                assert res.returncode == 0, f"{where}: {part!r} failed:\n{res.stdout}{res.stderr}"
                continue
            argv = shlex.split(part)
            args = apply_small(argv[1:], shlex.split(text)) if kind == "small" else argv[1:]
            res = CliRunner().invoke(app, ["--debug", *args], env={"TORCH_BRDF_PROGRESS": "0"})
            if isinstance(res.exception, DataNotFoundError) or "DataNotFoundError" in (res.output or ""):
                raise DataNotFoundError(f"{where}: {part}")
            assert res.exit_code == 0, f"{where}: {' '.join(argv)} failed:\n{res.output}"


@pytest.mark.parametrize("page", RUNNABLE, ids=[rel(p) for p in RUNNABLE])
def test_page_blocks_run(page, tmp_path, monkeypatch, cache):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(cache))
    monkeypatch.setenv("TORCH_BRDF_PROGRESS", "0")
    namespace = {"__name__": "__docs__"}
    for lang, line, code in page_items(page):
        where = f"{rel(page)}:{line}"
        try:
            if lang == "python":
                small, _ = shrink(code)
                exec(compile(small, where, "exec"), namespace)
            else:
                run_bash(where, code, monkeypatch)
        except DataNotFoundError as exc:
            pytest.skip(f"{where} needs the data folder (TORCH_BRDF_DATA): {exc}")
        # Outputs go where the page said: results under out/, caches under TORCH_BRDF_CACHE,
        # no checkpoint or tile folder left behind after a successful run.
        left = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file())
        stray = [p for p in left if not p.startswith("out" + os.sep)]
        assert not stray, f"{where} wrote outside out/ and $TORCH_BRDF_CACHE: {stray}"
        leftovers = [p for p in left if re.search(r"\.(tiles|chunks|ckpt)\b", p)]
        assert not leftovers, f"{where} left checkpoints behind: {leftovers}"


def test_every_fence_is_closed_and_named():
    # an unnamed fence is neither run nor visibly exempt: say ```text or ```console instead
    for page in PAGES:
        for lang, line, _ in blocks(page.read_text(encoding="utf-8")):
            assert lang, f"{rel(page)}:{line - 1}: a code block needs a language (```text if it must not run)"


# ---------------------------------------------------------------------------- quoted figures


def lookup(obj, path: str):
    """``obj`` at the dotted ``path``; a key that itself holds dots is matched whole."""
    parts = path.split(".")
    while parts:
        for k in range(len(parts), 0, -1):
            key = ".".join(parts[:k])
            if isinstance(obj, dict) and key in obj:
                obj, parts = obj[key], parts[k:]
                break
            if isinstance(obj, list) and k == 1 and key.lstrip("-").isdigit():
                obj, parts = obj[int(key)], parts[1:]
                break
        else:
            raise KeyError(".".join(parts))
    return obj


def saved(bench: str) -> dict:
    rec = json.loads((RESULTS / f"{bench}.json").read_text())
    return (
        rec["result"] if isinstance(rec, dict) and str(rec.get("format", "")).startswith("torch_brdf.report") else rec
    )


def prose(text: str) -> str:
    """``text`` with code (fenced blocks, inline spans) blanked out, lines kept: a marker shown as
    an example is not a quoted figure."""
    text = re.sub(r"```.*?```", lambda m: re.sub(r"[^\n]", " ", m[0]), text, flags=re.S)
    return re.sub(r"`[^`\n]*`", lambda m: " " * len(m[0]), text)


def figures(text: str) -> list[tuple[int, str, str, str, str | None]]:
    """``(line, number written, bench, key path, scale)`` of every figure marker of a page."""
    text, out = prose(text), []
    for m in FIG.finditer(text):
        before = text[: m.start()].splitlines()[-1] if text[: m.start()].strip() else ""
        nums = NUMBER.findall(before[-40:])
        line = text[: m.start()].count("\n") + 1
        out.append((line, nums[-1] if nums else "", m["bench"], m["path"], m["scale"]))
    return out


def matches(written: str, value: float, scale: str | None) -> bool:
    if scale:
        op, factor = scale[0], float(scale[1:].strip())
        value = value * factor if op == "*" else value / factor
    mantissa = written.replace(",", "").lstrip("+")
    places = len(re.split(r"[eE]", mantissa)[0].partition(".")[2])
    exp = int(re.split(r"[eE]", mantissa)[1]) if re.search(r"[eE]", mantissa) else 0
    return math.isclose(float(mantissa), value, abs_tol=0.5 * 10.0 ** (exp - places) * (1 + 1e-9))


FIGS = [(p, *f) for p in PAGES for f in figures(p.read_text(encoding="utf-8"))]


def test_figure_markers_parse():
    assert matches("1.28", 1.2849, None) and not matches("1.28", 1.2851, None)
    assert matches("12", 0.01194, "*1000") and matches("1,405,367", 1405367, None)
    assert figures("about 0.091 <!-- fig: brdf projection_rel_err.blinn_n10_J8 --> here") == [
        (1, "0.091", "brdf", "projection_rel_err.blinn_n10_J8", None)
    ]
    assert lookup({"a.b": {"c": [1, 2]}}, "a.b.c.1") == 2
    # a marker the pattern does not read would be checked by nothing
    for page in PAGES:
        text = prose(page.read_text(encoding="utf-8"))
        assert len(re.findall(r"<!--\s*fig:", text)) == len(FIG.findall(text)), f"{rel(page)}: malformed fig marker"


@pytest.mark.parametrize(
    "page,line,written,bench,path,scale", FIGS, ids=[f"{rel(f[0])}:{f[1]}:{f[3]}" for f in FIGS] or None
)
def test_quoted_figure_is_the_saved_result(page, line, written, bench, path, scale):
    where = f"{rel(page)}:{line}"
    assert (RESULTS / f"{bench}.json").is_file(), f"{where}: no saved results docs/results/{bench}.json"
    try:
        value = lookup(saved(bench), path)
    except KeyError as exc:
        raise AssertionError(f"{where}: {bench} has no {path!r} (missing part {exc})") from None
    assert written, f"{where}: no number right before the fig marker"
    assert isinstance(value, (int, float)), f"{where}: {bench} {path} is not a number: {value!r}"
    assert matches(written, float(value), scale), f"{where}: {written} is written, {bench} {path} is {value}"


# ---------------------------------------------------------------------------- architecture


def test_architecture_lists_the_layers_the_layer_test_enforces():
    from tests.test_layers import LAYERS

    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    rows = re.findall(r"^\| (\d+) \| (`.*`) \|$", text, flags=re.M)
    documented = [set(re.findall(r"`(\w+)`", names)) for _, names in rows]
    assert documented == [set(layer) for layer in LAYERS], (
        "docs/architecture.md's layer table is not tests/test_layers.py's"
    )


# ---------------------------------------------------------------------------- the TOML example


def test_getting_started_toml_scene_frames_its_subject(tmp_path):
    """The TOML example of getting-started, with its mesh and map beside it: every bunny vertex
    projects inside the image and the linear render is bright enough to read at exposure 0."""
    import shutil

    import torch

    from torch_brdf.data import data_path
    from torch_brdf.scene import Scene
    from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace

    text = (ROOT / "docs" / "getting-started.md").read_text(encoding="utf-8")
    toml = [code for lang, _, code in blocks(text) if lang == "toml" and "bunny.ply" in code]
    assert toml, "the getting-started TOML example is gone"
    try:
        for parts in (("meshes", "bunny.ply"), ("envmaps", "grace_latlong_512x256.exr")):
            shutil.copyfile(data_path(*parts), tmp_path / parts[1])
    except DataNotFoundError as exc:
        pytest.skip(f"needs the data folder: {exc}")
    (tmp_path / "scene.toml").write_text(toml[0], encoding="utf-8")
    scene = Scene.from_toml(tmp_path / "scene.toml").with_resolution(32)
    (bunny,) = scene.objects
    xy = scene.camera.project(torch.as_tensor(bunny.mesh.vertices, dtype=torch.float64))
    margin = 0.5  # pixels of the 32 x 32 frame
    assert bool((xy > margin).all() and (xy < 32 - margin).all()), "the camera crops the bunny"
    image = path_trace(scene, PathTraceSettings(spp=4, max_bounces=2), seed=0, progress=False)
    assert 0.02 < float(image.mean()) < 1.0  # readable at exposure 0 (an unscaled probe gives 0.003)
