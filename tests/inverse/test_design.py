"""The stroke-fitting driver, the trainer script and the ``fit-strokes`` subcommand."""

from __future__ import annotations

import json
import runpy
import sys
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from torch_brdf.cli import app
from torch_brdf.errors import FileFormatError
from torch_brdf.inverse import load_fit
from torch_brdf.inverse.design import DesignConfig, design, load_strokes
from torch_brdf.render.record import BasisImage
from torch_brdf.scene import teatray

ROOT = Path(__file__).resolve().parents[2]
STROKES = {
    "display_size": [64, 48],
    "strokes": [
        {"points": [[28, 28], [36, 25]], "color": [3, 3, 2.7], "diameter": 6, "kappa": 0.1},
        {"points": [[40, 32]], "scale": 0.5, "diameter": 4},
    ],
}


def _write(tmp_path, desc=STROKES):
    p = tmp_path / "strokes.json"
    p.write_text(json.dumps(desc))
    return p


def test_load_strokes(tmp_path):
    strokes, size = load_strokes(_write(tmp_path))
    assert size == (64, 48) and len(strokes) == 2
    assert strokes[1].brush.scale == 0.5 and strokes[0].points.shape == (2, 2)
    with pytest.raises(FileFormatError):
        load_strokes(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(FileFormatError):
        load_strokes(bad)
    with pytest.raises(FileFormatError):
        load_strokes(_write(tmp_path, {"strokes": [{"color": [1, 1, 1]}]}))


def test_design_writes_outputs_and_resumes(tmp_path):
    scene = teatray((64, 48))
    strokes, size = load_strokes(_write(tmp_path))
    cfg = DesignConfig("teapot", downsample=2, light_samples=32, render_scale=0.5)
    a = design(scene, strokes, cfg, tmp_path / "out", display_size=size, progress=False)
    assert a["violation"] <= 1e-8 and a["painted"] > 0
    fit = load_fit(tmp_path / "out" / "fit.npz")
    rec = BasisImage.load(tmp_path / "out" / "transfer.npz", dtype=torch.float64)
    assert rec.meta["settings"]["light_samples"] == 32
    stamp = (tmp_path / "out" / "transfer.npz").stat().st_mtime_ns
    b = design(scene, strokes, cfg, tmp_path / "out", display_size=size, progress=False)
    assert (tmp_path / "out" / "transfer.npz").stat().st_mtime_ns == stamp  # reused, not recomputed
    assert b["objective"] == a["objective"]
    assert torch.equal(load_fit(tmp_path / "out" / "fit.npz").coefficients, fit.coefficients)


def test_trainer_and_cli(tmp_path, monkeypatch, capsys):
    p = _write(tmp_path)
    args = ["teatray", "--object", "teapot", "--strokes", str(p), "--width", "64", "--height", "48"]
    args += ["--downsample", "2", "--samples", "32"]
    monkeypatch.setattr(sys, "argv", ["fit_strokes.py", *args, "--out", str(tmp_path / "t"), "--render-scale", "0.5"])
    with pytest.raises(SystemExit) as ex:
        runpy.run_path(str(ROOT / "trainers" / "fit_strokes.py"), run_name="__main__")
    assert ex.value.code == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["violation"] <= 1e-8
    res = CliRunner().invoke(app, ["fit-strokes", *args, "--out", str(tmp_path / "c"), "--kd", "1.0"])
    assert res.exit_code == 2 and "kd" in res.output  # infeasible: a clear error, not a traceback
