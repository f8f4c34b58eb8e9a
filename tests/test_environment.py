"""The user's environment variables (torch_brdf.data): a value the package cannot read is refused
with the variable's name and the allowed values, never silently taken as something else."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from torch_brdf.cli import app
from torch_brdf.data import progress_default
from torch_brdf.errors import ValueRangeError


@pytest.mark.parametrize(("value", "on"), [("1", True), ("on", True), ("Yes", True), ("0", False), ("off", False)])
def test_progress_switch_values(monkeypatch, value, on):
    monkeypatch.setenv("TORCH_BRDF_PROGRESS", value)
    assert progress_default() is on
    assert progress_default(not on) is (not on)  # the API argument wins over the variable


def test_invalid_progress_switch_is_refused(monkeypatch):
    monkeypatch.setenv("TORCH_BRDF_PROGRESS", "maybe")
    with pytest.raises(ValueRangeError, match=r"TORCH_BRDF_PROGRESS='maybe'.*1, true.*0, false"):
        progress_default()
    res = CliRunner().invoke(app, ["info", "cornell_box"])  # before any scene is built
    assert res.exit_code == 2
    assert "error: $TORCH_BRDF_PROGRESS='maybe' is not a switch" in res.output
    assert "objects" not in res.output


def test_fetched_data_is_found_without_setting_the_variable(monkeypatch, tmp_path):
    # `torch-brdf fetch-data` without --dest and $TORCH_BRDF_DATA writes under the cache folder;
    # the package must look there too, or fetched data would never be found
    import pooch

    from torch_brdf import data
    from torch_brdf.errors import DataNotFoundError

    def retrieve(url, known_hash, fname, path, progressbar):  # pooch without the network
        Path(path).mkdir(parents=True, exist_ok=True)
        (Path(path) / fname).write_text(url)
        return str(Path(path) / fname)

    monkeypatch.delenv("TORCH_BRDF_DATA", raising=False)
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(pooch, "retrieve", retrieve)
    with pytest.raises(
        DataNotFoundError, match=r"nothing\.ply' not found \(looked in .*cache/data; `python datasets/originals.py`"
    ):
        data.data_path("meshes", "nothing.ply")
    (path,) = data.fetch_data(base_url="http://127.0.0.1:9", files=["meshes/teapot.obj"], progress=False)
    assert path == tmp_path / "cache" / "data" / "meshes" / "teapot.obj"
    assert data.data_search_path() == [tmp_path / "cache" / "data"]
    assert data.data_path("meshes", "teapot.obj") == path
    monkeypatch.setenv("TORCH_BRDF_DATA", str(tmp_path / "elsewhere"))  # the variable alone, when set
    assert data.data_search_path() == [tmp_path / "elsewhere"] and data.data_root() is None
