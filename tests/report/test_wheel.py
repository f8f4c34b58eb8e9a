"""``torch-brdf report --quick`` from a wheel install: the benchmarks ship with the package, so a
clean environment without the source checkout writes its report.

The wheel is built from a copy of the package's sources (building in the checkout would leave
``build/`` there), installed without dependencies into a fresh venv that sees the system's
site-packages (torch, embree, matplotlib ...), and run from an empty folder, so the
``torch_brdf`` imported is the wheel's (checked), never the source tree.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

#: a cheap subset of the benchmarks: their quick runs take seconds each, where a whole quick
#: report takes about ten minutes. Not ``extremes``: it evaluates the test suite's cases
#: (``tests/test_extremes.py``), which a wheel does not hold (the page then says it did not run).
ONLY = ("brdf", "raytrace")


def _run(cmd: list[str], **kwargs) -> subprocess.CompletedProcess:
    p = subprocess.run(cmd, capture_output=True, text=True, **kwargs)
    assert p.returncode == 0, f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stdout[-3000:]}\n{p.stderr[-5000:]}"
    return p


def _wheel(tmp: Path) -> Path:
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    shutil.copytree(REPO / "torch_brdf", src / "torch_brdf", ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    out = tmp / "dist"
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", str(out)]
    _run([*cmd, str(src)], cwd=tmp)
    (wheel,) = out.glob("torch_brdf-*.whl")
    return wheel


def test_quick_report_runs_from_a_wheel_in_a_clean_venv(tmp_path):
    pytest.importorskip("matplotlib", reason="the report's figures need matplotlib (the report extra)")
    wheel = _wheel(tmp_path)
    env_dir = tmp_path / "venv"
    base = getattr(sys, "_base_executable", sys.executable)  # a venv's python makes its venv from the base
    _run([base, "-m", "venv", "--system-site-packages", str(env_dir)])
    py = env_dir / "bin" / "python"
    _run([str(py), "-m", "pip", "install", "--no-deps", "--no-index", str(wheel)])

    work = tmp_path / "work"  # an empty folder: no benchmarks/, no tests/, no torch_brdf/ beside it
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["TORCH_BRDF_CACHE"] = str(tmp_path / "cache")
    where = _run([str(py), "-c", "import torch_brdf; print(torch_brdf.__file__)"], cwd=work, env=env)
    assert Path(where.stdout.strip()).resolve().is_relative_to(env_dir.resolve()), where.stdout

    cmd = [str(env_dir / "bin" / "torch-brdf"), "report", "--quick", "--out", "out", "--no-progress"]
    for name in ONLY:
        cmd += ["--only", name]
    res = _run(cmd, cwd=work, env=env)
    page = work / "out" / "report.html"
    assert json.loads(res.stdout.strip().splitlines()[-1])["report"] == "out/report.html"
    assert page.is_file() and page.stat().st_size > 0
    for name in ONLY:
        rec = json.loads((work / "out" / "runs" / f"{name}.json").read_text())
        assert rec["error"] is None and isinstance(rec["result"], dict), rec
        assert rec["command"].startswith(f"python -m torch_brdf.report.benchmarks.{name} --quick"), rec["command"]
