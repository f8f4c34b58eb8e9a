"""``torch-brdf fetch-data`` against a local HTTP server on 127.0.0.1 serving a copy of the data
folder (no internet; the ``mirror`` fixture of conftest.py): it fetches, verifies the pinned SHA-256s and
refuses a corrupted file."""

from __future__ import annotations

import hashlib
import json

import pytest
from typer.testing import CliRunner

from tests.conftest import registry_root
from torch_brdf.cli import app
from torch_brdf.data import REGISTRY, fetch_data
from torch_brdf.errors import DataNotFoundError, FileFormatError

pytest.importorskip("pooch")


def test_registry_pins_the_shared_files():
    root = registry_root()
    for name, digest in REGISTRY.items():
        assert hashlib.sha256((root / name).read_bytes()).hexdigest() == digest, name


def test_fetch_verifies_and_refuses_a_corrupted_file(mirror, tmp_path):
    url, served = mirror
    dest = tmp_path / "data"
    paths = fetch_data(dest, url, progress=False)
    assert len(paths) == len(REGISTRY)
    for name, digest in REGISTRY.items():
        assert hashlib.sha256((dest / name).read_bytes()).hexdigest() == digest
    # a flipped byte on the server: refused, and nothing half-verified is left behind
    bad = served / "meshes" / "teapot.obj"
    data = bytearray(bad.read_bytes())
    data[100] ^= 0x01
    bad.write_bytes(bytes(data))
    fresh = tmp_path / "fresh"
    with pytest.raises(FileFormatError, match="SHA-256"):
        fetch_data(fresh, url, files=["meshes/teapot.obj"], progress=False)
    assert not (fresh / "meshes" / "teapot.obj").exists()
    with pytest.raises(DataNotFoundError, match="registry"):
        fetch_data(fresh, url, files=["meshes/nothing.ply"])
    with pytest.raises(DataNotFoundError, match="failed"):
        fetch_data(fresh, url + "/missing", files=["meshes/bunny.ply"])


def test_cli_fetch_data(mirror, tmp_path, monkeypatch):
    url, _ = mirror
    monkeypatch.delenv("TORCH_BRDF_DATA_URL", raising=False)
    runner = CliRunner()
    res = runner.invoke(app, ["fetch-data", "--dest", str(tmp_path / "d"), "--file", "meshes/cornell/floor.obj"])
    assert res.exit_code == 2 and "TORCH_BRDF_DATA_URL" in res.output  # no URL: says how
    args = ["fetch-data", "--dest", str(tmp_path / "d"), "--url", url, "--file", "meshes/cornell/floor.obj"]
    res = runner.invoke(app, [*args, "--file", "merl/nbrdf_merl100_weights.npz", "--no-progress"])
    assert res.exit_code == 0, res.output
    assert len(json.loads(res.output.strip().splitlines()[-1])["files"]) == 2
    assert (tmp_path / "d" / "merl" / "nbrdf_merl100_weights.npz").is_file()


def test_a_url_pooch_cannot_use_is_not_blamed_on_the_checksum(tmp_path):
    with pytest.raises(DataNotFoundError, match="cannot download from notaurl"):
        fetch_data(tmp_path, "notaurl", files=["meshes/bunny.ply"], progress=False)
