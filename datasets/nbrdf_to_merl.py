"""Tabulate NBRDF networks on the MERL grid: an APPROXIMATION of MERL, not measured data.

The NBRDF networks (Sztrajman et al. 2021, fitted to the 100 MERL materials) are evaluated
at the lower-edge angles of every MERL bin (as ``shared/tools/make_merl_npz.py`` did for
``merl_nbrdf_sample_f16.npz``) and written in one of two forms:

    # full resolution: one real-format MERL .binary per material (34,992,012 bytes each)
    python datasets/nbrdf_to_merl.py binary OUT_DIR [--materials blue-acrylic,gold-metallic-paint]

    # the downsampled npz layout of torch_brdf.io.merl (float16, source 'nbrdf')
    python datasets/nbrdf_to_merl.py npz OUT.npz [--materials ...] [--theta-d-step 2] [--phi-d-step 4]

Bins whose incoming or outgoing direction (for phi_h = 0) is at or below the horizon are
set to -1 (missing) in both forms: a geometric mask, not MERL's missing-data pattern.
Nothing is random (no seed needed); the output is deterministic. Writes are atomic
(temporary file + rename), so the run is resumable: existing outputs that read back
correctly are skipped (``--force`` recomputes them). The weights default to
``merl/nbrdf_merl100_weights.npz`` of the data folder (``$TORCH_BRDF_DATA``). Prints one
line per material, then one JSON object.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from torch_brdf.brdf.measured import NBRDF, tabulate_nbrdf
from torch_brdf.data import data_path
from torch_brdf.errors import TorchBRDFError
from torch_brdf.io.merl import (
    MERL_RES,
    load_merl_table,
    load_nbrdf_weights,
    read_merl_binary,
    write_merl_binary,
    write_merl_table,
)

LABEL = "NBRDF approximation of MERL (not measured data)"
F16_MAX = float(np.finfo(np.float16).max)


def _stats(table: np.ndarray) -> str:
    r = table[0][table[0] >= 0]
    return f"valid R bins {r.size}/{table[0].size}, R min/max/mean {r.min():.4g}/{r.max():.4g}/{r.mean():.4g}"


def _binary_ok(path: Path) -> bool:
    try:
        read_merl_binary(path, scaled=False)
        return True
    except TorchBRDFError:
        return False


def run_binary(weights, names: list[str], out_dir: Path, force: bool) -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    written, skipped = [], []
    for name in tqdm(names, desc="nbrdf -> .binary", unit="material", file=sys.stderr):
        path = out_dir / f"{name}.binary"
        if not force and path.exists() and _binary_ok(path):
            skipped.append(name)
            tqdm.write(f"{name}: {path} exists and reads back, skipped")
            continue
        table = tabulate_nbrdf(NBRDF(name, weights)).numpy()
        write_merl_binary(path, table)
        written.append(name)
        tqdm.write(f"{name}: {_stats(table)} -> {path} ({LABEL})")
    return {"written": written, "skipped": skipped, "out": str(out_dir)}


def run_npz(weights, names: list[str], out: Path, td_step: int, pd_step: int, force: bool) -> dict:
    idx = (np.arange(MERL_RES[0]), np.arange(0, MERL_RES[1], td_step), np.arange(0, MERL_RES[2], pd_step))
    if not force and out.exists():
        try:
            old = load_merl_table(out)
            same = (
                list(old.names) == names
                and old.source == "nbrdf"
                and all(
                    np.array_equal(a.numpy(), b)
                    for a, b in zip((old.theta_h_index, old.theta_d_index, old.phi_d_index), idx, strict=True)
                )
            )
        except TorchBRDFError:
            same = False
        if same:
            print(f"{out} exists with the same materials and grid, skipped ({LABEL})")
            return {"written": [], "skipped": names, "out": str(out)}
    tables, clamped = [], 0
    for name in tqdm(names, desc="nbrdf -> npz", unit="material", file=sys.stderr):
        t = tabulate_nbrdf(NBRDF(name, weights), *idx).numpy()
        clamped += int((t > F16_MAX).sum())
        tables.append(np.minimum(t, F16_MAX))
        tqdm.write(f"{name}: {_stats(t)} ({LABEL})")
    if clamped:
        print(f"warning: {clamped} values above the float16 maximum {F16_MAX} clamped", file=sys.stderr)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_merl_table(out, np.stack(tables), names, *idx, source="nbrdf")
    print(f"wrote {out}: {len(names)} materials, {out.stat().st_size / 2**20:.2f} MiB ({LABEL})")
    return {"written": names, "skipped": [], "out": str(out), "clamped_f16": clamped}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=["binary", "npz"], help="full-resolution .binary files, or the downsampled npz")
    ap.add_argument("out", type=Path, help="output folder (binary) or .npz file (npz)")
    ap.add_argument("--weights", type=Path, default=None, help="NBRDF weights .npz (default: shared data)")
    ap.add_argument("--materials", default="", help="comma-separated subset (default: all)")
    ap.add_argument("--theta-d-step", type=int, default=2, help="npz: keep every n-th theta_d bin")
    ap.add_argument("--phi-d-step", type=int, default=4, help="npz: keep every n-th phi_d bin")
    ap.add_argument("--force", action="store_true", help="recompute outputs that already exist")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    try:
        weights = load_nbrdf_weights(args.weights or data_path("merl", "nbrdf_merl100_weights.npz"))
        wanted = [m for m in args.materials.split(",") if m]
        for m in wanted:
            weights.index(m)  # clear error listing the names
        names = sorted(set(wanted) if wanted else weights.names)
        if args.theta_d_step < 1 or args.phi_d_step < 1:
            raise SystemExit("steps must be >= 1")
        if args.mode == "binary":
            report = run_binary(weights, names, args.out, args.force)
        else:
            report = run_npz(weights, names, args.out, args.theta_d_step, args.phi_d_step, args.force)
    except TorchBRDFError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    report.update(mode=args.mode, note=LABEL, seconds=round(time.perf_counter() - t0, 2))
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
