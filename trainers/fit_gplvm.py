"""Fit the GPLVM of the BRDF manifold on the MERL materials and save the fit.

    python trainers/fit_gplvm.py --q 2 --out out/gplvm_q2.npz [--split datasets/merl_split.txt]
    python trainers/fit_gplvm.py --q 5 --grid full --out out/gplvm_q5_full.npz     # streamed Gram
    python trainers/fit_gplvm.py --q 2 --binaries /path/to/brdfs --out out/merl_q2.npz

Data: by default the NBRDF fits of the 100 MERL materials (an APPROXIMATION of MERL,
``$TORCH_BRDF_DATA/merl/nbrdf_merl100_weights.npz``) on the default grid (theta_h and theta_d
every 3rd index, phi_d every 6th; valid bins only), cached atomically with a checksum under
``--cache`` (default ``$TORCH_BRDF_CACHE`` or ``~/.cache/torch_brdf``) and resumed if
interrupted. ``--grid full`` streams the full (90, 90, 180) grid into the Gram matrix block by
block (minutes; the Gram matrix is cached instead of Z). ``--binaries DIR`` reads real MERL
``.binary`` files (the same code path: the grid selection, or with ``--grid full`` memory-mapped
column blocks). Fit weights: the clipped cosine map (``--no-cosine`` for none); they only
shape the latents, the interpolants stay linear in the raw data.

The fit goes through :func:`torch_brdf.manifold.fit_gplvm` (seeded with ``--seed``, tqdm
progress) and is saved with :meth:`GPLVMFit.save` (versioned, checksummed, atomic). Prints one
JSON summary as the last line.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import torch

from torch_brdf.data import data_path
from torch_brdf.errors import TorchBRDFError
from torch_brdf.io.arrays import load_arrays, save_arrays
from torch_brdf.manifold.data import (
    MERLGrid,
    binary_column_blocks,
    binary_observations,
    default_grid,
    nbrdf_column_blocks,
    nbrdf_observations,
    read_split,
)
from torch_brdf.manifold.gplvm import fit_gplvm, gram

GRAM_KIND = "gplvm-gram"


def _cache_dir(arg: Path | None) -> Path:
    p = arg or Path(os.environ.get("TORCH_BRDF_CACHE") or Path.home() / ".cache" / "torch_brdf")
    p.mkdir(parents=True, exist_ok=True)
    return p


def _grid(spec: str) -> MERLGrid:
    if spec == "default":
        return default_grid()
    if spec == "full":
        return MERLGrid.full()
    try:
        th, td, pd = (int(s) for s in spec.split(","))
    except ValueError:
        raise SystemExit(f"--grid must be 'default', 'full' or three strides 'th,td,pd'; got {spec!r}") from None
    return MERLGrid.strided(th, td, pd)


def build_gram(args) -> tuple[torch.Tensor, int, tuple[str, ...], dict]:
    grid = _grid(args.grid)
    cache = _cache_dir(args.cache)
    cosine = not args.no_cosine
    if args.binaries is not None:
        paths = sorted(Path(args.binaries).glob("*.binary"))
        if len(paths) < 2:
            raise SystemExit(f"need at least two .binary files in {args.binaries}")
        names = tuple(p.stem for p in paths)
        if args.grid == "full":
            s, d = gram(binary_column_blocks(paths))  # unweighted: the cosine map needs the grid layout
            return s, d, names, {"source": "merl-binary", "grid": "full", "cosine": False}
        obs = binary_observations(paths, grid)
    else:
        weights = data_path("merl", "nbrdf_merl100_weights.npz")
        if args.grid == "full":
            key = cache / f"gram_nbrdf_full_{'cos' if cosine else 'raw'}.npz"
            if key.exists():
                arrays, meta = load_arrays(key, kind=GRAM_KIND)
                return torch.from_numpy(arrays["s"]), int(meta["d"]), tuple(meta["names"]), meta
            from torch_brdf.io.merl import load_nbrdf_weights

            names = load_nbrdf_weights(weights).names
            s, d = gram(nbrdf_column_blocks(weights, grid, names, cosine_weighted=cosine))
            meta = {"source": "nbrdf", "grid": "full", "cosine": cosine, "d": d, "names": list(names)}
            save_arrays(key, {"s": s.numpy()}, kind=GRAM_KIND, meta=meta)
            return s, d, names, meta
        obs = nbrdf_observations(weights, grid, cache=cache / f"merl_nbrdf_default_{grid.digest()[:8]}.npz")
    names = obs.names
    if args.split is not None:
        train, _ = read_split(args.split)
        names = tuple(train)
        z = obs.rows(train)
    else:
        z = obs.z
    s, d = gram(z, obs.cosine_weights() if cosine else None)
    return s, d, names, {"source": obs.source, "grid": obs.grid.describe(), "cosine": cosine}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description="Fit the GPLVM BRDF manifold (Soler et al. 2017).")
    ap.add_argument("--q", type=int, default=2, help="latent dimension (2..5 in the paper)")
    ap.add_argument("--out", type=Path, required=True, help="fit file to write (.npz)")
    ap.add_argument("--grid", default="default", help="'default', 'full' or strides 'th,td,pd'")
    ap.add_argument("--binaries", type=Path, default=None, help="folder of real MERL .binary files")
    ap.add_argument("--split", type=Path, default=None, help="fit on the 'train' names of this split file")
    ap.add_argument("--cache", type=Path, default=None, help="cache folder")
    ap.add_argument("--method", default="lbfgs", choices=["lbfgs", "adam", "hooke-jeeves"])
    ap.add_argument("--max-iter", type=int, default=1000)
    ap.add_argument("--mu", type=float, default=1e-6)
    ap.add_argument("--lengthscale", type=float, default=1.0)
    ap.add_argument("--no-cosine", action="store_true", help="fit on the raw values (no cosine weights)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    try:
        s, d, names, meta = build_gram(args)
        fit = fit_gplvm(
            s, d, args.q, lengthscale=args.lengthscale, mu=args.mu, method=args.method, max_iter=args.max_iter,
            names=names, generator=torch.Generator().manual_seed(args.seed), progress=True,
        )  # fmt: skip
    except TorchBRDFError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from exc
    fit = type(fit)(**{**fit.__dict__, "meta": {**fit.meta, **{k: v for k, v in meta.items() if k != "names"}}})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fit.save(args.out)
    out = {
        "out": str(args.out), "q": fit.q, "n": fit.n, "d": fit.d, "loglik": fit.final_loglik,
        "iterations": fit.iterations, "seconds": round(fit.seconds, 3), "jitter": fit.jitter, **meta,
    }  # fmt: skip
    out.pop("names", None)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
