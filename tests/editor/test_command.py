"""``torch-brdf editor``: prints the URL of a Voilà server that answers, and stops it on SIGTERM."""

from __future__ import annotations

import contextlib
import importlib.util
import os
import signal
import subprocess
import sys
import time
import urllib.request

import pytest


@contextlib.contextmanager
def _editor(small_tensors_file, tmp_path):
    """``torch-brdf editor`` on a small tensors file, running until it prints its URL: yields
    (process, URL); the process is killed on exit if still running."""
    if importlib.util.find_spec("voila") is None:
        if os.environ.get("CI"):
            pytest.fail("CI must run the editor command test: voila is not installed")
        pytest.skip("voila is not installed (pip install -e '.[editor]')")
    cmd = [sys.executable, "-m", "torch_brdf.cli", "editor", str(small_tensors_file[0]), "--cache", str(tmp_path)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
    line = ""
    deadline = time.monotonic() + 240
    while "http://127.0.0.1:" not in line and time.monotonic() < deadline and proc.poll() is None:
        line = proc.stdout.readline()
    try:
        assert "http://127.0.0.1:" in line, f"no URL printed: {line!r}"
        yield proc, line.split()[2]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def test_editor_command_serves_and_stops(small_tensors_file, tmp_path):
    with _editor(small_tensors_file, tmp_path) as (proc, url):
        with urllib.request.urlopen(url + "voila/static/voila.js", timeout=60) as r:  # static: no kernel
            assert r.status == 200
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == 0
        with pytest.raises(OSError):
            urllib.request.urlopen(url + "voila/static/voila.js", timeout=5)


def test_killed_editor_command_leaves_no_server(small_tensors_file, tmp_path):
    """SIGKILL (no chance to clean up) of ``torch-brdf editor`` stops its Voila server too (an
    orphaned server per killed command was found after test runs on a loaded machine)."""
    with _editor(small_tensors_file, tmp_path) as (proc, url):
        proc.kill()
        proc.wait(10)
        deadline = time.monotonic() + 120  # the server shuts down on its own SIGTERM
        while time.monotonic() < deadline:
            try:
                urllib.request.urlopen(url + "voila/static/voila.js", timeout=5).close()
            except OSError:
                break
            time.sleep(0.5)
        with pytest.raises(OSError):
            urllib.request.urlopen(url + "voila/static/voila.js", timeout=5)
