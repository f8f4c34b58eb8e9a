"""Resume never mixes code paths, and the final save never loses finished work.

* The polynomial precompute's torch path (``TORCH_BRDF_NATIVE=0``) and the compiled kernel
  agree only to rounding, so tiles of one must not finish a run of the other: the resume key
  names the code path, and a run interrupted on the torch path, resumed with the kernel,
  equals an uninterrupted kernel run bit for bit (the torch tiles are not reused).
* ``torch-brdf precompute`` and ``precompute-visibility`` keep their tiles (chunks) until the
  output file is written: a kill between the last tile and the save, then the same command
  again, recomputes nothing and writes the output.
"""

from __future__ import annotations

import pytest
import torch
from typer.testing import CliRunner

from torch_brdf.cli import app
from torch_brdf.scene.builtin import cornell_box
from torch_brdf.transport import _native, visibility
from torch_brdf.transport.polynomial import PolynomialSettings, PolynomialTensors, driver, precompute_polynomial
from torch_brdf.transport.visibility import VertexVisibility

from .test_stale_resume import _interrupt_after

runner = CliRunner()


def _never(module, name: str, monkeypatch) -> None:
    """Make ``module.name`` fail if called: every unit must come from the cache."""

    def recomputed(*args, **kwargs):
        raise AssertionError(f"{name} was called: a finished unit was recomputed")

    monkeypatch.setattr(module, name, recomputed)


def test_code_path_names_the_kernel_build_or_torch(monkeypatch):
    monkeypatch.setenv(_native.ENV_VAR, "0")
    assert _native.code_path() == "torch"
    monkeypatch.delenv(_native.ENV_VAR)
    if _native.library() is None:
        pytest.skip("no C compiler here: only the torch path runs")
    name = _native.code_path()
    assert name != "torch" and name.startswith("polynomial_") and name.endswith(".so")


def test_torch_tiles_resumed_with_the_kernel_equal_a_kernel_run(tmp_path, monkeypatch):
    if _native.library() is None:
        pytest.skip("no C compiler here: only the torch path runs")
    scene = cornell_box(8)
    # processes=1: the interruption counts tile calls in this process
    kw = dict(settings=PolynomialSettings(series="8,1", spp=2, tile_rows=2), seed=3, progress=False, processes=1)
    monkeypatch.setenv(_native.ENV_VAR, "0")
    _interrupt_after(driver, "_tile_entries", 3, monkeypatch)  # two torch tiles saved, then killed
    with pytest.raises(KeyboardInterrupt):
        precompute_polynomial(scene, checkpoint=tmp_path, **kw)
    monkeypatch.undo()
    assert len(list(tmp_path.glob("tile*.npz"))) == 2
    resumed = precompute_polynomial(scene, checkpoint=tmp_path, **kw)  # the kernel now
    fresh = precompute_polynomial(scene, **kw)
    assert resumed.meta["tiles_cached"] == 0  # the torch tiles were not taken for kernel tiles
    assert torch.equal(resumed.emission, fresh.emission)
    assert len(resumed.blocks) == len(fresh.blocks)
    for a, b in zip(resumed.blocks, fresh.blocks, strict=True):
        assert torch.equal(a.values, b.values) and torch.equal(a.pixels, b.pixels)
    # and the same path still resumes: a kernel run's tiles finish a kernel run
    _interrupt_after(driver, "_tile_entries", 3, monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        precompute_polynomial(scene, checkpoint=tmp_path / "k", **kw)
    monkeypatch.undo()
    again = precompute_polynomial(scene, checkpoint=tmp_path / "k", **kw)
    assert again.meta["tiles_cached"] == 2 and torch.equal(again.emission, fresh.emission)


def _save_fails_once(cls, monkeypatch) -> None:
    """Make ``cls.save`` raise KeyboardInterrupt (a kill just before the output is written)."""

    def killed(self, *args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(cls, "save", killed)


def test_cli_precompute_killed_before_the_save_recomputes_nothing(tmp_path, monkeypatch):
    out = tmp_path / "t.npz"
    args = ["precompute", "cornell_box", "--resolution", "8", "--spp", "1", "--series", "2,1", "--out", str(out)]
    _save_fails_once(PolynomialTensors, monkeypatch)
    killed = runner.invoke(app, args)
    monkeypatch.undo()
    assert killed.exit_code == 130 and not out.exists(), killed.output
    tiles = list((tmp_path / "t.tiles").glob("tile*.npz"))
    assert tiles  # every finished tile survived the kill
    _never(driver, "_tile_entries", monkeypatch)
    again = runner.invoke(app, args)
    assert again.exit_code == 0, again.output
    T = PolynomialTensors.load(out)
    assert T.meta["tiles_cached"] == len(tiles)
    assert not (tmp_path / "t.tiles").exists()  # removed once the output is written


def test_cli_precompute_visibility_killed_before_the_save_recomputes_nothing(tmp_path, monkeypatch):
    out = tmp_path / "vis.npz"
    args = ["precompute-visibility", "cornell_box", "--cubemap", "16", "--chunk", "64", "--out", str(out)]
    _save_fails_once(VertexVisibility, monkeypatch)
    killed = runner.invoke(app, args)
    monkeypatch.undo()
    assert killed.exit_code == 130 and not out.exists(), killed.output
    assert list((tmp_path / "vis.chunks").glob("vis*.npz"))
    _never(visibility, "_visibility_chunk", monkeypatch)
    again = runner.invoke(app, args)
    assert again.exit_code == 0, again.output
    assert out.exists() and not (tmp_path / "vis.chunks").exists()
