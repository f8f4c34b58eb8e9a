"""notebooks/brdf_manifold.ipynb shows its figures inline: the latent slice, the best path and
the blended renders each leave an image in the executed notebook (nbmake only checks that it runs)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from torch_brdf.data import progress_default

NOTEBOOK = Path(__file__).resolve().parents[2] / "notebooks" / "brdf_manifold.ipynb"


def test_manifold_notebook_shows_slice_path_and_blends(tmp_path, monkeypatch):
    nbclient = pytest.importorskip("nbclient")
    nbformat = pytest.importorskip("nbformat")
    if importlib.util.find_spec("ipykernel") is None:
        pytest.skip("ipykernel is not installed")
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(tmp_path / "cache"))
    nb = nbformat.reads(NOTEBOOK.read_text(encoding="utf-8"), as_version=4)
    nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()
    shown = {}
    for cell in nb.cells:
        if cell.cell_type == "code":
            images = sum("image/png" in o.get("data", {}) for o in cell.outputs)
            for marker in ("latent_slice(", "best_path(model", "blend(rec"):
                if marker in cell.source:
                    shown[marker] = images
    assert shown == {"latent_slice(": 1, "best_path(model": 1, "blend(rec": 1}, json.dumps(shown)
    assert {p.name for p in tmp_path.iterdir()} <= {"cache"}  # nothing in the working folder
    # launching a kernel imported ipykernel here: that alone must not turn progress bars on
    monkeypatch.delenv("TORCH_BRDF_PROGRESS", raising=False)
    assert "ipykernel" in sys.modules and not progress_default()
