"""The Gram matrix a GPLVM fit of measured BRDFs starts from (``torch-brdf fit-gplvm``).

Data: by default the NBRDF fits of the 100 MERL materials (an APPROXIMATION of MERL,
``$TORCH_BRDF_DATA/merl/nbrdf_merl100_weights.npz``) tabulated on a :class:`MERLGrid`
(``"default"``: theta_h and theta_d every 3rd index, phi_d every 6th; valid bins only) and
cached atomically with a checksum in ``$TORCH_BRDF_CACHE`` (resumed if interrupted). ``"full"``
streams the full (90, 90, 180) grid into the Gram matrix block by block (minutes; the Gram
matrix is cached instead of Z). ``binaries`` reads real MERL ``.binary`` files through the same
code path. Fit weights: the clipped cosine map (``cosine=False`` for none); they only shape the
latents, the interpolants stay linear in the raw data.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from ..data import cache_dir, data_path
from ..errors import DataNotFoundError, ValueRangeError
from ..io.arrays import load_arrays, save_arrays
from .data import (
    MERLGrid,
    binary_column_blocks,
    binary_observations,
    default_grid,
    nbrdf_column_blocks,
    nbrdf_observations,
    read_split,
)
from .gplvm import gram

GRAM_KIND = "gplvm-gram"

__all__ = ["GRAM_KIND", "parse_grid", "training_gram"]


def parse_grid(spec: str) -> MERLGrid:
    """``"default"``, ``"full"`` or three strides ``"th,td,pd"`` -> :class:`MERLGrid`."""
    if spec == "default":
        return default_grid()
    if spec == "full":
        return MERLGrid.full()
    try:
        th, td, pd = (int(s) for s in spec.split(","))
    except ValueError:
        raise ValueRangeError(f"--grid must be 'default', 'full' or three strides 'th,td,pd'; got {spec!r}") from None
    return MERLGrid.strided(th, td, pd)


def training_gram(
    grid: str = "default",
    binaries: str | os.PathLike | None = None,
    split: str | os.PathLike | None = None,
    cache: str | os.PathLike | None = None,
    cosine: bool = True,
    progress: bool | None = None,
) -> tuple[torch.Tensor, int, tuple[str, ...], dict]:
    """The Gram matrix S = Z W Zᵀ of the training materials (:func:`~torch_brdf.manifold.gram`).

    Args:
        grid: :func:`parse_grid` spec. binaries: folder of ``.binary`` files (default: NBRDF).
        split: fit on the ``train`` names of this split file. cache: folder (default
            :func:`torch_brdf.data.cache_dir`). cosine: weight columns by the clipped cosine map.
    Returns:
        ``(S (N, N) float64, d columns, N names, meta)`` with meta ``source``, ``grid``, ``cosine``.
    """
    rows_grid = parse_grid(grid)
    cache = Path(cache) if cache is not None else cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    if binaries is not None:
        paths = sorted(Path(binaries).glob("*.binary"))
        if len(paths) < 2:
            raise DataNotFoundError(f"need at least two .binary files in {binaries}")
        names = tuple(p.stem for p in paths)
        if grid == "full":
            s, d = gram(binary_column_blocks(paths))  # unweighted: the cosine map needs the grid layout
            return s, d, names, {"source": "merl-binary", "grid": "full", "cosine": False}
        obs = binary_observations(paths, rows_grid, progress=progress)
    else:
        weights = data_path("merl", "nbrdf_merl100_weights.npz")
        if grid == "full":
            key = cache / f"gram_nbrdf_full_{'cos' if cosine else 'raw'}.npz"
            if key.exists():
                arrays, meta = load_arrays(key, kind=GRAM_KIND)
                return torch.from_numpy(arrays["s"]), int(meta["d"]), tuple(meta["names"]), meta
            from ..io.merl import load_nbrdf_weights

            names = load_nbrdf_weights(weights).names
            s, d = gram(nbrdf_column_blocks(weights, rows_grid, names, cosine_weighted=cosine))
            meta = {"source": "nbrdf", "grid": "full", "cosine": cosine, "d": d, "names": list(names)}
            save_arrays(key, {"s": s.numpy()}, kind=GRAM_KIND, meta=meta)
            return s, d, names, meta
        key = cache / f"merl_nbrdf_default_{rows_grid.digest()[:8]}.npz"
        obs = nbrdf_observations(weights, rows_grid, cache=key, progress=progress)
    names = obs.names
    if split is not None:
        train, _ = read_split(split)
        names = tuple(train)
        z = obs.rows(train)
    else:
        z = obs.z
    s, d = gram(z, obs.cosine_weights() if cosine else None)
    return s, d, names, {"source": obs.source, "grid": obs.grid.describe(), "cosine": cosine}
