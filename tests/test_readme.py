"""The README cannot drift: every ```python block runs as pasted, in a fresh folder.

A line ``NAME = VALUE  # small: SMALL`` runs here with ``NAME = SMALL`` (the sizes a
reader sees are the real ones; the comment documents the quick ones). Blocks that need
the shared data skip with the reason when it is absent (``DataNotFoundError``).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from torch_brdf.errors import DataNotFoundError

README = Path(__file__).resolve().parents[1] / "README.md"
SMALL = re.compile(r"^(?P<lhs>\s*[A-Za-z_][\w, ]*?)\s*=\s*(?P<rhs>.+?)\s*#\s*small:\s*(?P<small>.+?)\s*$")


def python_blocks(text: str) -> list[tuple[int, str]]:
    """``(first line number, code)`` of every fenced ```python block of a Markdown text."""
    blocks, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        if lines[i].strip() == "```python":
            start, j = i + 1, i + 1
            while lines[j].strip() != "```":
                j += 1
            blocks.append((start + 1, "\n".join(lines[start:j]) + "\n"))
            i = j
        i += 1
    return blocks


def shrink(code: str) -> tuple[str, int]:
    """The code with every ``# small:`` assignment replaced; and how many were replaced."""
    out, n = [], 0
    for line in code.splitlines():
        m = SMALL.match(line)
        if m:
            line, n = f"{m['lhs']} = {m['small']}", n + 1
        out.append(line)
    return "\n".join(out) + "\n", n


BLOCKS = python_blocks(README.read_text(encoding="utf-8"))


def test_blocks_found():
    # The sections that carry an API example: scene, BRDF, GI editing, relighting, manifold, inverse.
    assert len(BLOCKS) >= 6


def test_shrink_replaces_only_marked_assignments():
    code, n = shrink("size, spp = 256, 64   # small: 16, 2\nx = 3  # a comment\n")
    assert n == 1 and code == "size, spp = 16, 2\nx = 3  # a comment\n"


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One fresh cache for all blocks, as a user's would be (band albedos computed once)."""
    return tmp_path_factory.mktemp("readme_cache")


@pytest.mark.parametrize("line,code", BLOCKS, ids=[f"README.md:{ln}" for ln, _ in BLOCKS])
def test_readme_block_runs(line, code, tmp_path, monkeypatch, cache):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(cache))
    small, _ = shrink(code)
    try:
        exec(compile(small, f"README.md:{line}", "exec"), {"__name__": "__readme__"})
    except DataNotFoundError as exc:
        pytest.skip(f"needs the shared data: {exc}")
    # Outputs go where the snippet said: results under out/, caches under TORCH_BRDF_CACHE,
    # no checkpoint or tile folder left behind after a successful run.
    left = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file())
    stray = [p for p in left if not p.startswith("out" + os.sep)]
    assert not stray, f"README.md:{line} wrote outside out/ and $TORCH_BRDF_CACHE: {stray}"
    leftovers = [p for p in left if re.search(r"\.(tiles|chunks|ckpt)\b", p)]
    assert not leftovers, f"README.md:{line} left checkpoints behind: {leftovers}"


def test_readme_toml_scene_frames_its_subject(tmp_path):
    """The README's TOML example, with its mesh and map beside it: every bunny vertex projects
    inside the image and the linear render is bright enough to read at exposure 0."""
    import shutil

    import torch

    from torch_brdf.data import data_path
    from torch_brdf.scene import Scene
    from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace

    text = README.read_text(encoding="utf-8")
    toml = re.search(r"A TOML scene \(all paths relative to the file\):\n\n```toml\n(.*?)```", text, re.S)
    assert toml, "the README's TOML example is gone"
    try:
        for parts in (("meshes", "bunny.ply"), ("envmaps", "grace_latlong_512x256.exr")):
            shutil.copyfile(data_path(*parts), tmp_path / parts[1])
    except DataNotFoundError as exc:
        pytest.skip(f"needs the shared data: {exc}")
    (tmp_path / "scene.toml").write_text(toml[1], encoding="utf-8")
    scene = Scene.from_toml(tmp_path / "scene.toml").with_resolution(32)
    (bunny,) = scene.objects
    xy = scene.camera.project(torch.as_tensor(bunny.mesh.vertices, dtype=torch.float64))
    margin = 0.5  # pixels of the 32 x 32 frame
    assert bool((xy > margin).all() and (xy < 32 - margin).all()), "the camera crops the bunny"
    image = path_trace(scene, PathTraceSettings(spp=4, max_bounces=2), seed=0, progress=False)
    assert 0.02 < float(image.mean()) < 1.0  # readable at exposure 0 (the unscaled probe gave 0.003)
