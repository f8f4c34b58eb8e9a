"""Peak resident memory of the GI stages, each measured in a fresh subprocess.

A stage runs in ``python -m torch_brdf.report.benchmarks._memory STAGE RESOLUTION SPP FILE`` (one process, tiles
in that process) and prints one JSON line: its peak RSS (``ru_maxrss``), the RSS before the
stage's work (imports and scene) and the record's file size. :func:`stage_peaks` runs
precompute (which saves FILE), freeze (the glossy back wall) and the denoised freeze
(``freeze(obj, "linear")``) on the glossy Cornell box, and gives each stage's peak above its
start per pixel, per pixel and sample, and as a multiple of the saved record.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

SERIES = "64,1,1,1"


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def _stage(stage: str, resolution: int, spp: int, path: str) -> dict:
    import torch

    from torch_brdf.records.polynomial import PolynomialTensors
    from torch_brdf.render.polynomial import PolynomialRenderer
    from torch_brdf.scene.builtin import cornell_box_glossy
    from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial

    torch.set_num_threads(1)
    sc = cornell_box_glossy(resolution)
    mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
    start = _rss_mb()
    if stage == "precompute":
        T = precompute_polynomial(sc, PolynomialSettings(SERIES, spp=spp), progress=False, processes=1)
        T.save(path)
    elif stage in ("freeze", "denoise"):
        T = PolynomialTensors.load(path)
        R = PolynomialRenderer(T, mats)
        R.freeze("back", denoiser="linear" if stage == "denoise" else None)
        R()
    else:
        raise SystemExit(f"unknown stage {stage!r}")
    return {"peak_mb": _rss_mb(), "start_mb": start, "file_mb": os.path.getsize(path) / 2**20}


def stage_peaks(resolution: int, spp: int) -> dict:
    """Each stage's peak RSS on the ``resolution``² glossy Cornell box at ``spp`` (series 64,1,1,1)."""
    out: dict = {"resolution": resolution, "spp": spp, "series": SERIES}
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "t.npz")
        for stage in ("precompute", "freeze", "denoise"):
            res = subprocess.run(
                [sys.executable, "-m", "torch_brdf.report.benchmarks._memory", stage, str(resolution), str(spp), path],
                capture_output=True,
                text=True,
                check=True,
                env={**os.environ, "TORCH_BRDF_PROGRESS": "0"},
            )
            r = json.loads(res.stdout.strip().splitlines()[-1])
            above = r["peak_mb"] - r["start_mb"]
            pixels = resolution * resolution
            out[stage] = {
                "peak_mb": round(r["peak_mb"], 1),
                "start_mb": round(r["start_mb"], 1),
                "above_start_mb": round(above, 1),
                "bytes_per_pixel": round(above * 2**20 / pixels, 1),
                "bytes_per_pixel_sample": round(above * 2**20 / (pixels * spp), 2),
                "over_file": round(above / max(r["file_mb"], 1e-9), 2),
            }
            out["file_mb"] = round(r["file_mb"], 2)
    return out


if __name__ == "__main__":
    stage, resolution, spp, path = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
    print(json.dumps(_stage(stage, resolution, spp, path)))
