"""Crafted cache files of every kind, with fixed seeds: never trusted, never a raw exception.

A cache folder is shared, copied and restored by users and tools, so a file whose digest
matches may still not be what this run would have written. For every cache (the path-trace
checkpoint, polynomial tiles, visibility chunks, inverse-design transfer tiles and the cached
transfer record, the NBRDF observation matrix) a small run keeps its files; then each file is
rewritten with one seeded defect (an array missing, extra, of another dtype, one row short or
long, a NaN or an infinity, a metadata entry of the wrong type or out of range) and sealed
again, so only the content checks can catch it. The run is repeated on the damaged cache and
must give the undamaged result exactly: no exception, no NaN, no silently different tensor.
A defect that is caught leaves a ``.corrupt`` file and a warning.
"""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_brdf.io.arrays import load_arrays, save_arrays
from torch_brdf.records import CorruptCacheWarning, TileCache

SEED = 20261207
PER_FILE = 6  # defects drawn per cached file (of the ~30 possible)


def _defects(arrays: dict, meta: dict, rng: np.random.Generator, n: int) -> list[tuple[str, dict, dict]]:
    """``n`` seeded single defects of one cached file: (label, arrays, meta)."""
    out = []
    swap = {"f": {"float64": np.float32, "float32": np.float64}, "i": np.int32, "u": np.int16, "b": np.int16}
    for name, a in arrays.items():
        out.append((f"{name} missing", {k: v for k, v in arrays.items() if k != name}, meta))
        to = swap["f"].get(a.dtype.name) if a.dtype.kind == "f" else swap.get(a.dtype.kind, np.float64)
        out.append((f"{name} as {np.dtype(to).name}", {**arrays, name: a.astype(to)}, meta))
        if a.ndim and a.shape[0]:
            out.append((f"{name} one row short", {**arrays, name: a[:-1]}, meta))
            out.append((f"{name} one row long", {**arrays, name: np.concatenate([a, a[-1:]])}, meta))
        if a.dtype.kind == "f" and a.size:
            for bad in (np.nan, np.inf):
                b = a.copy()
                b.reshape(-1)[rng.integers(a.size)] = bad
                out.append((f"{name} with {bad}", {**arrays, name: b}, meta))
    out.append(("an extra array", {**arrays, "stray": np.zeros(3)}, meta))
    for key in [k for k in meta if k != "cache_key"]:
        for bad in (-5, 10**12, "text", None):
            out.append((f"meta {key}={bad!r}", arrays, {**meta, key: bad}))
    picks = rng.choice(len(out), size=min(n, len(out)), replace=False)
    return [out[i] for i in sorted(picks)]


def _same(a, b) -> bool:
    if isinstance(a, torch.Tensor):
        return a.shape == b.shape and a.dtype == b.dtype and torch.equal(a, b)
    return all(_same(x, y) for x, y in zip(a, b, strict=True))


def _has_nan(a) -> bool:
    if isinstance(a, torch.Tensor):
        return a.is_floating_point() and bool(torch.isnan(a).any())
    return any(_has_nan(x) for x in a)


def _campaign(run, folder: Path, files: list[Path], kind: str, rng, kind_version: int = 1) -> dict[str, int]:
    """Damage each of ``files`` (in ``folder``) in turn; ``run()`` must give the clean result."""
    clean = run()
    saved = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    tally = {"cases": 0, "caught": 0, "raw": 0, "nan": 0, "different": 0}
    failures = []
    for target in files:
        arrays, meta = load_arrays(target, kind=kind, kind_version=kind_version)
        for label, a, m in _defects(arrays, meta, rng, PER_FILE):
            shutil.rmtree(folder, ignore_errors=True)
            for p, data in saved.items():
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_bytes(data)
            save_arrays(
                target, a, kind=kind, meta=m, kind_version=kind_version
            )  # sealed: a valid digest over the damage
            tally["cases"] += 1
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                try:
                    got = run()
                except Exception as exc:  # the campaign counts what escapes
                    tally["raw"] += 1
                    failures.append(f"{target.name} {label}: {type(exc).__name__}: {exc}"[:200])
                    continue
            tally["caught"] += any(issubclass(w.category, CorruptCacheWarning) for w in caught)
            if _has_nan(got):
                tally["nan"] += 1
                failures.append(f"{target.name} {label}: NaN in the output")
            elif not _same(got, clean):
                tally["different"] += 1
                failures.append(f"{target.name} {label}: a different result")
    assert not failures, "\n".join(failures)
    assert tally["caught"] > 0  # the defects were seen, not all harmless
    return tally


@pytest.fixture
def rng():
    return np.random.default_rng(SEED)


@pytest.fixture
def keep_tiles(monkeypatch):
    """Runs keep their tile folders (the campaign damages them afterwards)."""
    monkeypatch.setattr(TileCache, "remove", lambda self: None)


def _box():
    from tests.records.test_stale_resume import _box_desc
    from torch_brdf.scene import Scene

    return Scene.from_dict(_box_desc(0.5, 1.0))


def test_path_trace_checkpoints(tmp_path, rng):
    from torch_brdf.transport.pathtrace import CHECKPOINT_KIND, PathTraceSettings, path_trace

    ckpt = tmp_path / "c" / "render.ckpt.npz"
    scene = _box()

    def run():
        return path_trace(scene, PathTraceSettings(spp=2, max_bounces=2), seed=1, progress=False, checkpoint=ckpt)

    tally = _campaign(run, ckpt.parent, [ckpt], CHECKPOINT_KIND, rng)
    assert tally["cases"] == PER_FILE


def test_polynomial_tiles(tmp_path, rng, keep_tiles):
    from torch_brdf.scene.builtin import cornell_box
    from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial
    from torch_brdf.transport.polynomial.driver import TILE_KIND

    scene = cornell_box(6)
    folder = tmp_path / "tiles"
    settings = PolynomialSettings("4,1", spp=2, tile_rows=3)

    def run():
        t = precompute_polynomial(scene, settings, seed=3, progress=False, processes=1, checkpoint=folder)
        return [t.emission, *[x for b in t.blocks for x in (b.values, b.pixels, b.terms, b.index)]]

    run()
    files = sorted(folder.glob("tile*.npz"))
    assert len(files) >= 2
    _campaign(run, folder, files, TILE_KIND, rng)


def test_visibility_chunks(tmp_path, rng, keep_tiles):
    from torch_brdf.transport.visibility import CHUNK_KIND, VisibilitySettings, precompute_visibility

    scene = _box()
    folder = tmp_path / "vis"

    def run():
        v = precompute_visibility(scene, VisibilitySettings(resolution=16, chunk=4), progress=False, checkpoint=folder)
        return [v.blocks.counts, v.blocks.index, v.blocks.states]

    run()
    files = sorted(folder.glob("vis*.npz"))[:2]
    _campaign(run, folder, files, CHUNK_KIND, rng)


def test_transfer_tiles_and_record(tmp_path, rng, keep_tiles):
    from torch_brdf.inverse.design import DesignConfig, design
    from torch_brdf.inverse.strokes import Brush, Stroke
    from torch_brdf.records import BasisImage
    from torch_brdf.scene import teatray

    scene = teatray((16, 12))
    strokes = [Stroke(torch.tensor([[7.0, 6.0]]), Brush(color=(2.0, 2.0, 2.0), diameter=3))]
    cfg = DesignConfig("teapot", downsample=1, light_samples=8, render_scale=1.0, constrained=False)
    out = tmp_path / "out"

    def run():
        design(scene, strokes, cfg, out, progress=False)
        return [BasisImage.load(out / "transfer.npz", dtype=torch.float64).values]

    run()
    record = out / "transfer.npz"
    # the tiles are read only when the record is gone: damage them with the record removed
    tiles = sorted((out / "transfer.tiles").glob("tile*.npz"))
    assert tiles

    def run_from_tiles():
        record.unlink(missing_ok=True)
        return run()

    _campaign(run_from_tiles, out, tiles[:1], "transfer-tile", rng)
    _campaign(run, out, [record], BasisImage.kind, rng, BasisImage.version)


def test_observation_matrix(tmp_path, rng):
    from torch_brdf.manifold.data import OBS_KIND, nbrdf_observations

    w = {"names": np.array(["a", "b"])}
    g = np.random.default_rng(SEED)
    for k, shape in (("W1", (2, 6, 4)), ("b1", (2, 4)), ("W2", (2, 4, 4)), ("b2", (2, 4)), ("W3", (2, 4, 3))):
        w[k] = (0.3 * g.standard_normal(shape)).astype(np.float32)
    w["b3"] = np.zeros((2, 3), np.float32)
    np.savez(tmp_path / "nbrdf.npz", **w)
    cache = tmp_path / "c" / "obs.npz"

    def run():
        return [nbrdf_observations(tmp_path / "nbrdf.npz", cache=cache, progress=False).z]

    _campaign(run, cache.parent, [cache], OBS_KIND, rng)
