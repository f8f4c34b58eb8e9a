"""Command-line mistakes refused before any work: one line on stderr, a non-zero exit.

Each case replaces the first expensive step of its command (loading the scene, starting the
editor's server) with a trap, so a check that came too late fails the test instead of
passing after minutes of work. Also: a failed download is one line, and a save on a full
disk names the file in the package's exception hierarchy.
"""

from __future__ import annotations

import errno

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

import torch_brdf.cli
from tests.test_cli import _one_line_error
from torch_brdf.cli import app, check_ray_address
from torch_brdf.errors import TorchBRDFError, ValueRangeError, WriteError

runner = CliRunner()


@pytest.fixture
def no_work(monkeypatch):
    """Loading a scene or starting the editor's server fails the test: checks come first."""

    def trap(*args, **kwargs):
        raise AssertionError("work started before the options were checked")

    from torch_brdf.editor import server

    monkeypatch.setattr(torch_brdf.cli, "load_scene", trap)
    monkeypatch.setattr(server, "serve", trap)


@pytest.mark.parametrize(
    "address, words",
    [
        ("127.0.0.1:1", ("cannot connect",)),  # nothing listens on port 1
        ("256.1.1.1:0", ("port must be in 1..65535",)),
        ("256.1.1.1:6379", ("not an IPv4 address",)),
        ("head_node:6379", ("not a host name",)),
        ("6379", ("HOST:PORT",)),
    ],
)
@pytest.mark.parametrize("command", ["precompute", "precompute-visibility"])
def test_ray_address_refused_before_work(tmp_path, no_work, command, address, words):
    args = [command, "cornell_box", "--out", str(tmp_path / "o.npz"), "--ray", address]
    _one_line_error(runner.invoke(app, args), 2, "--ray", *words)


def test_ray_connect_times_out(monkeypatch):
    import socket

    def slow(*args, timeout=None, **kwargs):
        raise TimeoutError("timed out")  # what a silent address does after ``timeout`` seconds

    monkeypatch.setattr(socket, "create_connection", slow)
    with pytest.raises(ValueRangeError, match="no answer within 5 s"):
        check_ray_address("10.255.255.1:6379")
    check_ray_address("auto")  # a local instance: nothing to check
    check_ray_address(None)


def _record(tmp_path, name: str, kind: str):
    from torch_brdf.io.arrays import save_arrays

    return save_arrays(tmp_path / name, {"x": np.zeros(2)}, kind=kind)


def test_editor_refuses_missing_and_wrong_records_before_the_server(tmp_path, no_work):
    _one_line_error(runner.invoke(app, ["editor", str(tmp_path / "missing.npz")]), 2, "no such file", "missing.npz")
    vis = _record(tmp_path, "vis.npz", "vertex-visibility")
    _one_line_error(runner.invoke(app, ["editor", str(vis)]), 2, "vertex-visibility", "expected")
    gplvm = ["editor", "cornell_box", "--gplvm", str(vis)]
    _one_line_error(runner.invoke(app, gplvm), 2, "--gplvm", "vertex-visibility", "gplvm")
    rel = ["editor", "cornell_box", "--relight", "bunny_relight", "--visibility", str(tmp_path / "none.npz")]
    _one_line_error(runner.invoke(app, rel), 2, "--visibility", "no such file")
    _one_line_error(runner.invoke(app, ["editor", "no_such_scene"]), 2, "no_such_scene")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    _one_line_error(runner.invoke(app, ["editor", str(junk)]), 2, "not a torch_brdf array file")


@pytest.mark.parametrize(
    "option, words",
    [
        (["--psnr", "-5"], ("--psnr", ">= 0")),
        (["--psnr", "200"], ("--psnr", "<= 140")),
        (["--psnr", "nan"], ("--psnr",)),
        (["--error", "0"], ("--error",)),
        (["--error", "2"], ("--error", "<= 1")),
        (["--error", "0.01", "--psnr", "30"], ("not both",)),
    ],
)
def test_relight_budget_ranges(tmp_path, no_work, option, words):
    args = ["relight", "bunny_relight", "--out", str(tmp_path / "r"), *option]
    _one_line_error(runner.invoke(app, args), 2, *words)


def test_relight_missing_visibility_refused_before_rendering(tmp_path):
    args = ["relight", "bunny_relight", "--out", str(tmp_path / "r"), "--visibility", str(tmp_path / "v.npz")]
    _one_line_error(runner.invoke(app, args), 2, "--visibility", "no such file")


def test_unreachable_download_is_one_line(tmp_path):
    args = ["fetch-data", "--dest", str(tmp_path), "--url", "http://127.0.0.1:1/data", "--file", "meshes/bunny.ply"]
    line = _one_line_error(runner.invoke(app, [*args, "--no-progress"]), 2, "meshes/bunny.ply", "failed")
    assert "Max retries" not in line and "HTTPConnectionPool" not in line  # the cause, not requests' wrapping


def test_api_save_on_a_full_disk_names_the_path(tmp_path, monkeypatch):
    import torch_brdf.io.arrays
    from tests.test_cli import _FullDisk
    from torch_brdf.records import BasisImage

    monkeypatch.setattr(torch_brdf.io.arrays, "open", _FullDisk, raising=False)
    rec = BasisImage(torch.zeros(3, 1, 2), torch.tensor([0, 1]), 1, 2)
    target = tmp_path / "sub" / "b.npz"
    with pytest.raises(WriteError) as info:
        rec.save(target)
    exc = info.value
    assert isinstance(exc, OSError) and isinstance(exc, TorchBRDFError)
    assert exc.errno == errno.ENOSPC and exc.filename == str(target) and str(target) in str(exc)
    assert not any(p.is_file() for p in tmp_path.rglob("*"))  # nothing half-written


@pytest.mark.parametrize("series", ["4,,1", "64,1,", "4;1"])
def test_series_with_an_empty_or_bad_entry_is_refused(tmp_path, no_work, series):
    args = ["precompute", "cornell_box", "--out", str(tmp_path / "t.npz"), "--series", series]
    _one_line_error(runner.invoke(app, args), 2, "--series", "cannot parse")
