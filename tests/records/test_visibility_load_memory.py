"""Loading a visibility record costs memory in proportion to its file: a record of a few MB
(real-like maps: a tilted horizon and spherical caps per vertex) is loaded in a fresh process
whose peak resident memory is reset first (after a load of a tiny record, so that the code
the load runs is paged in); the record keeps the file's stream, so the whole peak stays
within a generous multiple of the file (measured ~1.5x; the CSR layout kept ~4x the file
after the load and its parse once reached ~70 times the file)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_brdf.records import BlockVisibility
from torch_brdf.records.visibility import SceneVertices, VertexVisibility
from torch_brdf.sphere.cubemap import CubemapBlocks

CLEAR_REFS = Path("/proc/self/clear_refs")

# reset the peak (VmHWM), load, then read the peak and what stays resident (kB -> bytes)
CHILD = """
import json, sys
from torch_brdf.records.visibility import VertexVisibility

VertexVisibility.load(sys.argv[2])

def status():
    with open("/proc/self/status") as f:
        return {k: int(v.split()[0]) * 1024 for k, v in (line.split(":", 1) for line in f) if k in ("VmHWM", "VmRSS")}

with open("/proc/self/clear_refs", "w") as f:
    f.write("5")
before = status()["VmRSS"]
rec = VertexVisibility.load(sys.argv[1])
after = status()
print(json.dumps({"peak": after["VmHWM"] - before, "kept": after["VmRSS"] - before, "vertices": len(rec.vertices)}))
"""


def horizon_and_caps(p: int, geom: CubemapBlocks, gen: torch.Generator, caps: int = 3) -> np.ndarray:
    """``(p, NB, 32)`` packed binary maps: per vertex a tilted horizon and ``caps`` occluding caps."""
    dirs = geom.supersampled_directions(1).reshape(geom.block_count * geom.block_size, 3).to(torch.float64)
    out = []
    for start in range(0, p, 512):
        n = min(512, p - start)
        normal = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=1)
        tilt = 0.3 * (torch.rand(n, 1, generator=gen, dtype=torch.float64) - 0.5)
        visible = normal @ dirs.T > tilt
        for _ in range(caps):
            centre = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=1)
            radius = 0.2 + 0.6 * torch.rand(n, 1, generator=gen, dtype=torch.float64)
            visible &= centre @ dirs.T < torch.cos(radius)
        out.append(np.packbits(visible.reshape(n, geom.block_count, 256).numpy(), axis=2))
    return np.concatenate(out)


@pytest.mark.skipif(not CLEAR_REFS.exists(), reason="needs Linux /proc/self/clear_refs to reset the peak RSS")
def test_load_peak_is_proportional_to_the_file(tmp_path):
    gen = torch.Generator().manual_seed(0)
    geom = CubemapBlocks(64, 16)
    p = 4000
    blocks = BlockVisibility.encode_packed(horizon_and_caps(p, geom, gen))
    pos = torch.randn(p, 3, generator=gen, dtype=torch.float64)
    normals = pos / pos.norm(dim=1, keepdim=True)
    verts = SceneVertices(pos, normals, torch.zeros(p, dtype=torch.int64), torch.tensor([0, p]))
    path = VertexVisibility(geom, verts, blocks).save(tmp_path / "vis.npz")
    size = path.stat().st_size
    assert size > 1 << 21  # large enough that page and allocator granularity do not matter
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    tiny = VertexVisibility(
        geom,
        SceneVertices(pos[:2], normals[:2], torch.zeros(2, dtype=torch.int64), torch.tensor([0, 2])),
        blocks.select([0, 1]),
    ).save(tmp_path / "tiny.npz")
    cmd = [sys.executable, "-c", CHILD, str(path), str(tiny)]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["vertices"] == p
    assert got["peak"] <= 2.5 * size, f"load peak {got['peak']:,} B, kept {got['kept']:,} B, file {size:,} B"
