"""Shared fixtures: seeded generators, the data folder, per-dtype tolerances."""

from __future__ import annotations

import functools
import os
import shutil
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
import torch

from torch_brdf.data import REGISTRY, data_path, data_root

# The developer layout keeps the data folder beside the checkout, as shared/data in its parent. The
# package itself looks only in $TORCH_BRDF_DATA and the cache, so the tests default the variable
# to that folder when it exists (CONTRIBUTING.md, "Data").
_SIBLING = Path(__file__).resolve().parents[2] / "shared" / "data"
if "TORCH_BRDF_DATA" not in os.environ and _SIBLING.is_dir():
    os.environ["TORCH_BRDF_DATA"] = str(_SIBLING)

# Data fetched into the default folder ($TORCH_BRDF_CACHE/data) is found through the cache folder,
# which some tests point elsewhere: the folder found at the start holds for the whole run.
if data_root() is not None:
    os.environ.setdefault("TORCH_BRDF_DATA", str(data_root()))

#: per-dtype tolerances (relative) for comparisons against float64 oracles
RTOL = {torch.float32: 1e-4, torch.float64: 1e-10}


@pytest.fixture
def gen() -> torch.Generator:
    g = torch.Generator()
    g.manual_seed(1234)
    return g


def shared_file(*parts: str):
    """Path of a shared data file, or skip the test with the reason."""
    p = data_path(*parts, required=False)
    if p is None:
        pytest.skip(f"shared data not found: {'/'.join(parts)} (set TORCH_BRDF_DATA; see CONTRIBUTING.md)")
    return p


def corrupted_copy(path, dest):
    """Write ``path``'s bytes to ``dest`` with one byte in the middle flipped; returns ``dest``."""
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    dest.write_bytes(bytes(raw))
    return dest


def registry_root(why: str = "") -> Path:
    """The shared data folder holding every file of the fetch registry, else skip saying why
    (no folder, or an empty one as in a user's fresh clone)."""
    root = data_root()
    if root is None:
        pytest.skip(f"needs the shared data folder (TORCH_BRDF_DATA) {why}".strip())
    missing = sorted(n for n in REGISTRY if not (root / n).is_file())
    if missing:
        pytest.skip(f"shared data not found in {root}: {missing[:3]}{' ...' if len(missing) > 3 else ''}")
    return root


@pytest.fixture
def mirror(tmp_path):
    """(base URL, served folder): a copy of the shared data folder behind http.server."""
    root = registry_root("to serve")
    served = tmp_path / "served"
    for name in REGISTRY:
        (served / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(root / name, served / name)

    class Quiet(SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(served)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", served
    finally:
        server.shutdown()
        server.server_close()
