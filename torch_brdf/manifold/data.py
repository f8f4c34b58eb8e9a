r"""Observation matrices of measured BRDFs on a MERL grid, the published split, error metrics, PCA.

**Grid.** A :class:`MERLGrid` is a choice of kept MERL bin indices (by index selection, no
averaging, as in the ``merl100_f16.npz`` layout). The default, :func:`default_grid`, keeps
every 3rd :math:`\theta_h` index (30: 0, 3, ..., 87), every 3rd :math:`\theta_d` index
(30: 0, ..., 87) and every 6th :math:`\phi_d` index (30: 0, 6, ..., 174): 27,000 bins;
``MERLGrid.full()`` is the full (90, 90, 180) grid. Bins whose incoming or outgoing
direction (for :math:`\phi_h = 0`, lower-edge angles) is at or below the horizon are
dropped (the NBRDF tables mark them missing; real MERL files also miss data there). A row of
``Z`` is ``[R bins, G bins, B bins]`` over the valid bins, in 1/sr with MERL's scale applied.
Missing measurements of a real file (negative values) in a valid bin are bad input for the
manifold (:class:`~torch_brdf.errors.ValueRangeError`); use :meth:`~torch_brdf.manifold.gplvm.GPLVM.project` with a mask
for partially observed BRDFs.

**Sources.** :func:`nbrdf_observations` tabulates the NBRDF networks (an *approximation* of
MERL; see the data section of ``docs/getting-started.md``) through
:func:`torch_brdf.brdf.measured.tabulate_nbrdf`, with a resumable, checksummed cache;
:func:`binary_observations` reads real ``.binary`` files through the same selection, and
:func:`binary_column_blocks` streams the full grid from memory-mapped ``.binary`` files in
column blocks for :func:`~torch_brdf.manifold.gplvm.gram`, so the full-resolution Gram matrix
never needs the whole ``Z`` in memory.

**Metrics** of held-out reconstructions: :func:`~torch_brdf.metrics.log_relative_rmse` (after
Nielsen, Jensen and Ramamoorthi 2015, with the per-bin median of the training set as
:math:`\rho_{\mathrm{ref}}`) and :func:`~torch_brdf.metrics.cosine_weighted_rmse`, both on
the cosine map :math:`c = \cos\theta_i\cos\theta_o` clipped to [0.01, 1]; they live in
:mod:`torch_brdf.metrics` and are re-exported here.
"""

from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from ..data import progress_default
from ..errors import FileFormatError, ShapeError, ValueRangeError
from ..frame import half_diff_to_directions
from ..io.merl import MERL_FILE_BYTES, MERL_RES, MERL_SCALE, merl_index_to_angles
from ..metrics import cosine_weighted_rmse as cosine_weighted_rmse  # re-exported
from ..metrics import log_relative_rmse as log_relative_rmse  # re-exported
from ..parallel.threads import single_thread
from ..records.cache import ArraySpec, CacheSchema, Checkpoint, MetaSpec

OBS_KIND = "merl-observations"


# -- grid --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MERLGrid:
    """Kept MERL bin indices (strictly increasing) along theta_h, theta_d, phi_d."""

    theta_h_index: tuple[int, ...]
    theta_d_index: tuple[int, ...]
    phi_d_index: tuple[int, ...]

    def __post_init__(self):
        for name, idx, res in zip(("theta_h", "theta_d", "phi_d"), self.indices, MERL_RES, strict=True):
            a = np.asarray(idx)
            if a.ndim != 1 or a.size == 0 or (a < 0).any() or (a >= res).any() or (np.diff(a) <= 0).any():
                raise ValueRangeError(f"{name}_index must be strictly increasing indices in 0..{res - 1}; got {idx}")

    @classmethod
    def strided(cls, th: int = 3, td: int = 3, pd: int = 6) -> MERLGrid:
        """Every ``th``-th theta_h, ``td``-th theta_d and ``pd``-th phi_d index, from 0."""
        if min(th, td, pd) < 1:
            raise ValueRangeError(f"strides must be >= 1; got {(th, td, pd)}")
        return cls(tuple(range(0, MERL_RES[0], th)), tuple(range(0, MERL_RES[1], td)), tuple(range(0, MERL_RES[2], pd)))

    @classmethod
    def full(cls) -> MERLGrid:
        return cls.strided(1, 1, 1)

    @property
    def indices(self) -> tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]:
        return self.theta_h_index, self.theta_d_index, self.phi_d_index

    @property
    def shape(self) -> tuple[int, int, int]:
        return len(self.theta_h_index), len(self.theta_d_index), len(self.phi_d_index)

    def describe(self) -> str:
        return "x".join(str(s) for s in self.shape) + f" (theta_h/theta_d/phi_d, digest {self.digest()[:8]})"

    def digest(self) -> str:
        return hashlib.sha256(repr(self.indices).encode()).hexdigest()

    def directions(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(wi, wo): (Th, Td, Tp, 3) float64 local directions at lower-edge angles, phi_h = 0."""
        th, td, pd = merl_index_to_angles(*self.indices, at="lower", dtype=torch.float64)
        TH, TD, PD = torch.meshgrid(th, td, pd, indexing="ij")
        return half_diff_to_directions(TH, torch.zeros_like(TH), TD, PD)

    def valid(self) -> torch.Tensor:
        """(Th, Td, Tp) bool: both directions strictly above the horizon."""
        wi, wo = self.directions()
        return (wi[..., 2] > 0) & (wo[..., 2] > 0)

    def cosine_map(self, clip: tuple[float, float] = (0.01, 1.0)) -> torch.Tensor:
        r"""(B,) float64 :math:`\cos\theta_i\cos\theta_o` over the valid bins, clipped (Nielsen et al. 2015)."""
        wi, wo = self.directions()
        c = (wi[..., 2] * wo[..., 2])[self.valid()]
        return c.clamp(*clip)

    @property
    def num_valid(self) -> int:
        return int(self.valid().sum())


def default_grid() -> MERLGrid:
    """The documented default: theta_h every 3rd, theta_d every 3rd, phi_d every 6th index (30^3 bins)."""
    return MERLGrid.strided(3, 3, 6)


def select(table: torch.Tensor | np.ndarray, grid: MERLGrid, name: str = "table") -> torch.Tensor:
    """One material's row of ``Z``: the valid bins of ``grid`` from a full (3, 90, 90, 180) table.

    Args:
        table: (3, 90, 90, 180) RGB table (scale applied), e.g. :func:`~torch_brdf.io.merl.read_merl_binary`.
    Returns:
        (3 * B,) float64, channels outermost.
    Raises:
        ShapeError: wrong shape. ValueRangeError: NaN/Inf or missing (negative) values in valid bins.
    """
    t = torch.as_tensor(np.asarray(table), dtype=torch.float64)
    if t.shape != (3, *MERL_RES):
        raise ShapeError(f"Expected {name} of shape (3, 90, 90, 180); got {tuple(t.shape)}")
    ih, id_, ip = (torch.as_tensor(i) for i in grid.indices)
    sub = t[:, ih][:, :, id_][:, :, :, ip]
    row = sub[:, grid.valid()]
    if not bool(torch.isfinite(row).all()):
        raise ValueRangeError(f"{name} holds NaN/Inf in the kept bins")
    if bool((row < 0).any()):
        raise ValueRangeError(
            f"{name} has {int((row < 0).sum())} missing (negative) values in kept bins; the manifold needs complete "
            "rows (project partial BRDFs with a mask instead)"
        )
    return row.reshape(-1)


def to_table(row: torch.Tensor, grid: MERLGrid, missing: float = -1.0) -> torch.Tensor:
    """Inverse of :func:`select` on the grid: (3 * B,) -> (3, Th, Td, Tp), invalid bins = ``missing``.

    The result with ``grid.indices`` makes a :class:`~torch_brdf.brdf.measured.MERLTabulated`
    (negative entries are treated as missing there, so clamp interpolants first if needed).
    """
    v = grid.valid()
    b = int(v.sum())
    row = torch.as_tensor(row, dtype=torch.float64)
    if row.shape != (3 * b,):
        raise ShapeError(f"Expected a row of shape ({3 * b},) for grid {grid.describe()}; got {tuple(row.shape)}")
    out = torch.full((3, *grid.shape), float(missing), dtype=torch.float64)
    out[:, v] = row.reshape(3, b)
    return out


# -- sources -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Observations:
    """An observation matrix of measured BRDFs.

    Attributes:
        z: (N, 3 * B) float32 raw BRDF values (1/sr) over the grid's valid bins, RGB blocks.
        names: N material names. grid: the :class:`MERLGrid`. source: ``"nbrdf"`` (approximation
            of MERL) or ``"merl-binary"``.
    """

    z: torch.Tensor
    names: tuple[str, ...]
    grid: MERLGrid
    source: str

    def rows(self, names: Sequence[str]) -> torch.Tensor:
        idx = [self.names.index(n) for n in names]
        return self.z[idx]

    def cosine_weights(self) -> torch.Tensor:
        """(3 * B,) float64 clipped cosine map per column (the fit weights of the trainer)."""
        return self.grid.cosine_map().repeat(3)


def _cache_meta(names, grid: MERLGrid, source: str, weights_digest: str) -> dict:
    return {"names": list(names), "grid": [list(i) for i in grid.indices], "source": source, "weights": weights_digest}


def _file_digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def nbrdf_observations(
    weights_path: str | os.PathLike,
    grid: MERLGrid | None = None,
    names: Sequence[str] | None = None,
    cache: str | os.PathLike | None = None,
    progress: bool | None = None,
    save_every: int = 10,
) -> Observations:
    """Tabulate NBRDF networks on ``grid`` into an observation matrix (an APPROXIMATION of MERL).

    With ``cache`` the matrix is stored as a :class:`~torch_brdf.records.cache.Checkpoint` (atomic,
    checksummed) every ``save_every`` materials and at the end; a later call with the same
    weights file, names and grid resumes from it (or just loads it). A cache written for other
    settings is recomputed; a corrupt cache is moved aside (``<name>.corrupt``, with a
    :class:`~torch_brdf.records.cache.CorruptCacheWarning`) and recomputed.

    Args:
        weights_path: ``nbrdf_merl100_weights.npz``. grid: default :func:`default_grid`.
        names: materials (default all, sorted as in the file). cache: ``.npz`` path or None.
    Returns:
        :class:`Observations` with source ``"nbrdf"``.
    """
    from ..brdf.measured import NBRDF, tabulate_nbrdf
    from ..io.merl import load_nbrdf_weights

    grid = grid or default_grid()
    w = load_nbrdf_weights(weights_path)
    names = tuple(names) if names is not None else w.names
    for n in names:
        w.index(n)
    meta = _cache_meta(names, grid, "nbrdf", _file_digest(Path(weights_path)))
    b = grid.num_valid
    z = np.zeros((len(names), 3 * b), dtype=np.float32)
    done = 0
    schema = CacheSchema(
        arrays={"z": ArraySpec("float32", z.shape)}, meta={"done": MetaSpec(int, 0, len(names), required=False)}
    )
    ckpt = None if cache is None else Checkpoint(cache, OBS_KIND, meta, "recompute", schema)
    saved = None if ckpt is None else ckpt.load()
    if saved is not None:
        z = np.asarray(saved[0]["z"], dtype=np.float32).copy()
        done = int(saved[1].get("done", 0))
    valid = grid.valid()
    bar = tqdm(
        range(done, len(names)),
        initial=done,
        total=len(names),
        desc="tabulate NBRDF",
        disable=not progress_default(progress),
    )
    for i in bar:
        t = tabulate_nbrdf(NBRDF(names[i], w), *grid.indices, mask_horizon=False)
        z[i] = t[:, valid].reshape(-1).numpy().astype(np.float32)
        if ckpt is not None and ((i + 1) % save_every == 0 or i + 1 == len(names)):
            ckpt.save({"z": z}, meta={**meta, "done": i + 1})
    return Observations(torch.from_numpy(z), names, grid, "nbrdf")


def binary_observations(
    paths: Sequence[str | os.PathLike], grid: MERLGrid | None = None, progress: bool | None = None
) -> Observations:
    """Observation matrix from real MERL ``.binary`` files (the same selection as for NBRDF).

    Args:
        paths: one ``.binary`` per material; the name is the file stem.
    """
    from ..io.merl import read_merl_binary

    grid = grid or default_grid()
    rows = [
        select(read_merl_binary(p), grid, name=str(p)).to(torch.float32)
        for p in tqdm(list(paths), desc="read MERL", disable=not progress_default(progress))
    ]
    if len(rows) < 2:
        raise ShapeError(f"need at least 2 materials; got {len(rows)}")
    return Observations(torch.stack(rows), tuple(Path(p).stem for p in paths), grid, "merl-binary")


def binary_column_blocks(paths: Sequence[str | os.PathLike], chunk: int = 1 << 18) -> Iterator[torch.Tensor]:
    """Stream the FULL-grid observation matrix of ``.binary`` files in (N, chunk) column blocks.

    Each file is memory-mapped (header checked, size checked); a block holds the same flat
    columns (channel-major, scale applied) of every file, so
    ``gram(binary_column_blocks(paths))`` gives the full-resolution Gram matrix with one block
    in memory at a time. Missing (negative) values are set to 0 here (the Gram matrix of raw
    files; prefer :func:`binary_observations` on a grid for complete rows).
    """
    maps = []
    for p in paths:
        p = Path(p)
        if not p.is_file() or p.stat().st_size != MERL_FILE_BYTES:
            raise FileFormatError(f"MERL binary file {p} is missing or not {MERL_FILE_BYTES:,} bytes")
        dims = tuple(np.fromfile(p, dtype="<i4", count=3))
        if dims != MERL_RES:
            raise FileFormatError(f"MERL binary file {p}: header dims {dims}, expected {MERL_RES}")
        maps.append(np.memmap(p, dtype="<f8", mode="r", offset=12))
    n = 3 * math.prod(MERL_RES)
    per = n // 3
    scale = np.repeat(np.asarray(MERL_SCALE), per)
    for a in range(0, n, chunk):
        blk = np.stack([np.asarray(m[a : a + chunk]) for m in maps]) * scale[a : a + chunk]
        yield torch.from_numpy(np.where(blk < 0, 0.0, blk))


# -- split ---------------------------------------------------------------------------------------
def split_names(names: Sequence[str], test_every: int = 5) -> tuple[list[str], list[str]]:
    """The published split: sort by name, every ``test_every``-th material (positions 4, 9, ...) is held out.

    With 100 materials and the default that is 80 train / 20 test.
    """
    s = sorted(names)
    test = [n for i, n in enumerate(s) if i % test_every == test_every - 1]
    return [n for n in s if n not in test], test


def write_split(path: str | os.PathLike, train: Sequence[str], test: Sequence[str]) -> Path:
    """Write a split file: one ``train <name>`` or ``test <name>`` per line, ``#`` comments."""
    path = Path(path)
    lines = ["# MERL train/test split of torch_brdf.manifold (sorted names; every 5th held out)"]
    lines += [f"train {n}" for n in train] + [f"test {n}" for n in test]
    path.write_text("\n".join(lines) + "\n")
    return path


def read_split(path: str | os.PathLike) -> tuple[list[str], list[str]]:
    """Read a split file written by :func:`write_split`."""
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"split file not found: {path}")
    train, test = [], []
    for k, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 2 or parts[0] not in ("train", "test"):
            raise FileFormatError(f"{path}:{k}: expected 'train <name>' or 'test <name>'; got {line!r}")
        (train if parts[0] == "train" else test).append(parts[1])
    if not train or not test or set(train) & set(test):
        raise FileFormatError(f"{path}: needs non-empty, disjoint train and test sets")
    return train, test


# -- the PCA baseline ------------------------------------------------------------------------------
@dataclass(frozen=True)
class PCABasis:
    """Linear baseline: mean (d,) and q orthonormal components (q, d) of weighted rows."""

    mean: torch.Tensor
    components: torch.Tensor
    weights: torch.Tensor

    def reconstruct(self, z: torch.Tensor) -> torch.Tensor:
        """Best weighted-L2 reconstruction of rows (M, d) in the affine subspace, raw scale."""
        zw = torch.as_tensor(z, dtype=torch.float64) * self.weights - self.mean
        coef = zw @ self.components.T
        return (coef @ self.components + self.mean) / self.weights


def fit_pca(z: torch.Tensor, q: int, weights: torch.Tensor | None = None) -> PCABasis:
    """PCA of the (weighted) rows of ``z`` (N, d): the affine q-dimensional subspace baseline.

    Through the N x N Gram matrix of the centred rows (its top-q eigenvectors U, eigenvalues
    s^2; components (U / s)^T C), one thread: on the full MERL grid (80 x 63,339) an SVD of C took
    5-17 s on the loaded 2-core machine, the Gram route well under 1 s. Falls back to the SVD
    when a requested component has below 1e-6 of the largest variance (the Gram route's error
    grows as eps over that ratio).
    """
    z = torch.as_tensor(z, dtype=torch.float64)
    w = torch.ones(z.shape[1], dtype=torch.float64) if weights is None else torch.as_tensor(weights).double()
    if not 1 <= q < z.shape[0]:
        raise ValueRangeError(f"q must be in 1..{z.shape[0] - 1}; got {q}")
    zw = z * w
    mean = zw.mean(0)
    c = zw - mean
    with single_thread():
        evals, evecs = torch.linalg.eigh(c @ c.T)
        evals, evecs = evals.flip(0)[:q], evecs.flip(1)[:, :q]
        if float(evals[-1]) > 1e-6 * float(evals[0]) > 0:  # components accurate to ~eps / 1e-6
            comps = (evecs / evals.sqrt()).T @ c
        else:
            comps = torch.linalg.svd(c, full_matrices=False)[2][:q]
    return PCABasis(mean, comps.contiguous(), w)


# -- a synthetic family (tests, notebook, --quick benchmark) ------------------------------------------
def analytic_rows(params: torch.Tensor, grid: MERLGrid) -> torch.Tensor:
    r"""Rows of a 2-parameter family of analytic isotropic BRDFs on ``grid`` (no data needed).

    :math:`\rho = k_d/\pi + k_s\,\frac{n+2}{2\pi}\cos^n\theta_h\,F(\theta_d)` with Schlick's
    :math:`F = F_0 + (1 - F_0)(1 - \cos\theta_d)^5`, :math:`n = 10^{1 + 2 t_1}`,
    :math:`k_d = (0.05 + 0.5 t_2)\,(1, 0.8, 0.6)`, :math:`k_s = 0.5`, :math:`F_0 = 0.04`. Reciprocal
    and non-negative; a smooth 2-D manifold in :math:`(t_1, t_2) \in [0, 1]^2`.

    Args:
        params: (N, 2) values of :math:`(t_1, t_2)`.
    Returns:
        (N, 3 * B) float64 rows (RGB blocks over ``grid``'s valid bins).
    """
    params = torch.as_tensor(params, dtype=torch.float64)
    if params.ndim != 2 or params.shape[1] != 2:
        raise ShapeError(f"Expected params of shape (N, 2); got {tuple(params.shape)}")
    th, td, _ = merl_index_to_angles(*grid.indices, at="lower", dtype=torch.float64)
    TH, TD = torch.meshgrid(th, td, indexing="ij")
    v = grid.valid()
    ch = TH.cos()[..., None].expand(*grid.shape)[v]
    cd = TD.cos()[..., None].expand(*grid.shape)[v]
    fres = 0.04 + 0.96 * (1 - cd) ** 5
    n = 10 ** (1 + 2 * params[:, :1])
    spec = 0.5 * (n + 2) / (2 * math.pi) * ch[None] ** n * fres[None]
    tint = torch.tensor([1.0, 0.8, 0.6], dtype=torch.float64)
    kd = (0.05 + 0.5 * params[:, 1:])[:, :, None] * tint[None, :, None]  # (N, 1, 3) -> per channel
    rows = kd.reshape(-1, 3, 1) / math.pi + spec[:, None, :]
    return rows.reshape(params.shape[0], -1)


def analytic_observations(
    n: int = 30, grid: MERLGrid | None = None, generator: torch.Generator | None = None
) -> tuple[Observations, torch.Tensor]:
    """``n`` random members of :func:`analytic_rows` (parameters uniform in [0, 1]^2, seeded).

    Returns:
        (observations with source ``"analytic"``, params (n, 2)).
    """
    grid = grid or MERLGrid.strided(9, 9, 18)
    params = torch.rand(n, 2, generator=generator, dtype=torch.float64)
    z = analytic_rows(params, grid).to(torch.float32)
    return Observations(z, tuple(f"analytic-{i:03d}" for i in range(n)), grid, "analytic"), params


def nbrdf_column_blocks(
    weights_path: str | os.PathLike,
    grid: MERLGrid,
    names: Sequence[str] | None = None,
    theta_h_per_block: int = 3,
    cosine_weighted: bool = True,
    progress: bool | None = None,
) -> Iterator[torch.Tensor]:
    """Stream the NBRDF observation matrix on ``grid`` (e.g. the FULL grid) in column blocks.

    Each block holds the valid bins of ``theta_h_per_block`` theta_h indices for every material
    (RGB), optionally multiplied by the clipped cosine map, so ``gram(nbrdf_column_blocks(...))``
    is the (weighted) Gram matrix of the full-resolution ``Z`` with one block in memory at a
    time (the full grid: 100 x 4.4 M values would be 1.7 GB in float32). Column order differs
    from :func:`nbrdf_observations` (theta_h-major here), which the Gram matrix does not see.
    """
    from ..brdf.measured import NBRDF, tabulate_nbrdf
    from ..io.merl import load_nbrdf_weights

    w = load_nbrdf_weights(weights_path)
    names = tuple(names) if names is not None else w.names
    models = [NBRDF(n, w) for n in names]
    th_all = grid.theta_h_index
    valid = grid.valid()
    wi, wo = grid.directions()
    cos = (wi[..., 2] * wo[..., 2]).clamp(0.01, 1.0)
    steps = range(0, len(th_all), theta_h_per_block)
    for a in tqdm(steps, desc="NBRDF Gram blocks", disable=not progress_default(progress)):
        sl = slice(a, a + theta_h_per_block)
        idx = (th_all[sl], grid.theta_d_index, grid.phi_d_index)
        v = valid[sl]
        rows = []
        for m in models:
            t = tabulate_nbrdf(m, *idx, mask_horizon=False)  # (3, th, Td, Tp)
            if cosine_weighted:
                t = t * cos[sl]
            rows.append(t[:, v].reshape(-1))
        yield torch.stack(rows)
