"""Shared fixtures: seeded generators, the shared data folder, per-dtype tolerances."""

from __future__ import annotations

import pytest
import torch

from torch_brdf.data import data_path

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
        pytest.skip(f"shared data not found: {'/'.join(parts)} (set TORCH_BRDF_DATA or place ../shared/data)")
    return p


def corrupted_copy(path, dest):
    """Write ``path``'s bytes to ``dest`` with one byte in the middle flipped; returns ``dest``."""
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    dest.write_bytes(bytes(raw))
    return dest
