"""The tile executors: local vs Ray bit for bit, a killed Ray worker, a restarted driver.

The Ray tests start their own local instance (``ray.init(num_cpus=2)``) in a private
temporary folder (:mod:`tests.transport._ray`) and stop it; they skip, saying why, when the
``cluster`` extra (Ray) is not installed.
"""

from __future__ import annotations

import os
import pickle
import signal
import threading
import time
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import torch

from tests.transport._ray import init_local, private_ray_env
from torch_brdf.errors import ValueRangeError
from torch_brdf.parallel import tiles as executor
from torch_brdf.parallel.tiles import TileError, run_tiles, tile_tick
from torch_brdf.records.cache import TileCache
from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial

SETTINGS = {"settings": PolynomialSettings(series="64,1,1,1", spp=4, tile_rows=4), "seed": 3, "progress": False}


def _arrays(T) -> dict[str, np.ndarray]:
    return T.to_arrays()[0]


def _assert_identical(a, b) -> None:
    xa, xb = _arrays(a), _arrays(b)
    assert sorted(xa) == sorted(xb)
    for k in xa:
        assert xa[k].dtype == xb[k].dtype and np.array_equal(xa[k], xb[k]), k


@pytest.fixture(scope="module")
def scene():
    return cornell_box_glossy(16)


@pytest.fixture(scope="module")
def local(scene):
    return precompute_polynomial(scene, **SETTINGS)


# -- without Ray ---------------------------------------------------------------------------------
def test_scene_pickles_and_traces_the_same(scene):
    other = pickle.loads(pickle.dumps(scene))
    g = torch.Generator().manual_seed(0)
    o = torch.tensor([[0.0, 0.0, 0.0]]).expand(64, 3) + torch.rand(64, 3, generator=g) * 0.1
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1)
    a, b = scene.trace(o, d), other.trace(o, d)
    assert torch.equal(a.object_id, b.object_id) and torch.equal(a.position, b.position)


def test_local_resume_and_split(scene, local, tmp_path):
    part = precompute_polynomial(scene, **SETTINGS, checkpoint=tmp_path, keep_checkpoint=True)
    assert part.meta["tiles_cached"] == 0
    for f in sorted(tmp_path.glob("*.npz"))[2:]:  # as if the driver had died after two tiles
        f.unlink()
    again = precompute_polynomial(scene, **SETTINGS, checkpoint=tmp_path)
    assert again.meta["tiles_cached"] == 2
    _assert_identical(again, local)
    split = local.meta["split"]
    assert {"rays", "sampling", "brdf", "bookkeeping", "assemble", "write"} <= set(split)
    assert all(v >= 0 for v in split.values()) and split["rays"] > 0


def test_local_processes_equal_one_process(scene, local):
    """Tiles in two forked processes (the default on two cores) give the tensors of one process."""
    one = precompute_polynomial(scene, **SETTINGS, processes=1)
    two = precompute_polynomial(scene, **SETTINGS, processes=2)
    assert one.meta["processes"] == 1 and two.meta["processes"] == 2
    _assert_identical(one, two)
    _assert_identical(one, local)
    assert one.meta["rays"] == two.meta["rays"]


def _mixed_arrays(ctx, k):
    """A tile's arrays of several dtypes and shapes (one empty)."""
    return {
        "f": np.arange(7 * k + 3, dtype=np.float32).reshape(-1, 1) / 3,
        "i": np.full((2, k + 1), -k, dtype=np.int64),
        "b": np.array([k % 2 == 0] * 5),
        "e": np.zeros((0, 3), dtype=np.float64),
    }, {"k": k}


@pytest.mark.parametrize("limit", [0, 1 << 40])
def test_forked_arrays_handed_back_through_files(monkeypatch, limit):
    """Forked tiles hand large arrays back through files in a private folder (``limit`` 0: all
    of them), small ones through the pipe: the same arrays (dtype, shape, values), writable,
    and no file or folder left behind."""
    monkeypatch.setattr(executor, "HAND_BACK_BYTES", limit)
    made = []
    real = executor._hand_folder
    monkeypatch.setattr(executor, "_hand_folder", lambda: made.append(real()) or made[-1])
    tiles = run_tiles(_mixed_arrays, None, 5, TileCache(None, "t", "k"), progress=False, processes=2)
    for k, (a, m) in enumerate(tiles):
        want = _mixed_arrays(None, k)[0]
        assert m["k"] == k and sorted(a) == sorted(want)
        for n, v in want.items():
            assert a[n].dtype == v.dtype and a[n].shape == v.shape and np.array_equal(a[n], v), n
            assert a[n].flags.writeable
    assert made and all(f is None or not os.path.exists(f) for f in made)


def test_hand_folders_of_killed_drivers_removed(tmp_path):
    """A driver killed with SIGKILL leaves its hand-back folder behind: the next run removes the
    folders whose creating process is gone and keeps those of live processes and other names."""
    import subprocess
    import sys

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # reaped: its id names no process (until reused, which keeps a folder, never loses one)
    stale = tmp_path / f"{executor.HAND_PREFIX}{dead.pid}-abc"
    live = tmp_path / f"{executor.HAND_PREFIX}{os.getpid()}-def"
    other = tmp_path / "somebody-else"
    for d in (stale, live, other):
        d.mkdir()
        (d / "t0.bin").write_bytes(b"x")
    made = executor._hand_folder(str(tmp_path))
    assert made is not None and Path(made).name.startswith(f"{executor.HAND_PREFIX}{os.getpid()}-")
    assert not stale.exists() and live.exists() and other.exists()


def test_tiles_at_once_bounded_by_memory(scene, local, monkeypatch):
    """Fewer tiles at once when they would not fit in memory; the tensors stay the same."""
    from torch_brdf.transport.polynomial import driver

    monkeypatch.setattr(driver, "tile_processes", lambda: 2)
    tile_bytes = 4 * 16 * SETTINGS["settings"].spp * driver.TILE_BYTES_PER_PATH  # tile_rows x width x spp
    monkeypatch.setattr(driver, "available_memory", lambda: tile_bytes + 1)
    one = precompute_polynomial(scene, **SETTINGS)
    assert one.meta["processes"] == 1
    monkeypatch.setattr(driver, "available_memory", lambda: 2 * tile_bytes)
    two = precompute_polynomial(scene, **SETTINGS)
    assert two.meta["processes"] == 2
    _assert_identical(one, local)
    _assert_identical(two, local)


def _tile_or_fail(ctx, k):
    if k == ctx:
        raise ValueError(f"tile {k} is bad")
    if k == -ctx:
        raise KeyboardInterrupt
    return {"x": np.full(3, k)}, {"k": k}


def test_forked_tiles_in_order_and_errors_raised_here():
    cache = TileCache(None, "t", "k")
    tiles = run_tiles(_tile_or_fail, 99, 5, cache, progress=False, processes=2)
    assert tiles.processes == 2 and [m["k"] for _, m in tiles] == list(range(5))
    assert all(np.array_equal(a["x"], np.full(3, k)) for k, (a, _) in enumerate(tiles))
    with pytest.raises(ValueError, match="tile 3 is bad"):
        run_tiles(_tile_or_fail, 3, 5, cache, progress=False, processes=2)
    with pytest.raises(TileError, match="tile 2 stopped: KeyboardInterrupt"):  # a worker's Ctrl-C
        run_tiles(_tile_or_fail, -2, 5, cache, progress=False, processes=2)


@pytest.mark.parametrize("processes", [1, 2])
def test_tile_files_written_beside_the_assembly_before_run_tiles_returns(tmp_path, monkeypatch, processes):
    """The driver writes tile files in a background thread while it assembles; every
    file is on disk when run_tiles returns, and a failed write is raised after the others."""
    seen = []

    def consume(k, arrays, meta):  # the assembly goes on while files are written
        seen.append(k)

    cache = TileCache(tmp_path, "t", "k")
    tiles = run_tiles(_mixed_arrays, None, 6, cache, progress=False, processes=processes, consume=consume)
    assert seen == list(range(6)) and tiles.write_seconds > 0
    assert all(cache.load(k) is not None for k in range(6))
    real = TileCache.save_encoded if processes == 2 else TileCache.save

    def save(self, index, *args):
        if index == 3:
            raise OSError("disk full")
        return real(self, index, *args)

    monkeypatch.setattr(TileCache, "save_encoded" if processes == 2 else "save", save)
    other = TileCache(tmp_path / "other", "t", "k")
    with pytest.raises(OSError, match="disk full"):
        run_tiles(_mixed_arrays, None, 6, other, progress=False, processes=processes)
    assert [other.load(k) is not None for k in range(6)] == [True, True, True, False, True, True]


def test_forked_tiles_start_longest_first(scene, local, monkeypatch):
    """With ``cost``, forked processes are handed the tiles in decreasing cost (ties in tile
    order) and the result is still in tile order; the precompute gives its tiles' paths, so an
    adaptive run starts its most sampled rows first and equals one process bit for bit."""
    started = []
    real = executor._run_forked

    def recording(fn, ctx, todo, *args):
        started.append(list(todo))
        return real(fn, ctx, todo, *args)

    monkeypatch.setattr(executor, "_run_forked", recording)
    cache = TileCache(None, "t", "k")
    tiles = run_tiles(_tile_or_fail, 99, 5, cache, progress=False, processes=2, cost=[1, 5, 3, 5, 0])
    assert started[-1] == [1, 3, 2, 0, 4]
    assert [m["k"] for _, m in tiles] == list(range(5))
    run_tiles(_tile_or_fail, 99, 5, cache, progress=False, processes=2)
    assert started[-1] == [0, 1, 2, 3, 4]
    with pytest.raises(ValueRangeError, match="cost has 2 numbers for 5 tiles"):
        run_tiles(_tile_or_fail, 99, 5, cache, progress=False, processes=2, cost=[1, 2])
    spp = torch.full((16, 16), 2, dtype=torch.long)
    spp[8:12] = 6  # tile 2 (rows 8-11) takes the most paths, then the uniform ones in tile order
    kw = {**SETTINGS, "settings": SETTINGS["settings"].replace(spp=spp)}
    two = precompute_polynomial(scene, **kw, processes=2)
    assert started[-1] == [2, 0, 1, 3]
    _assert_identical(two, precompute_polynomial(scene, **kw, processes=1))


def _ticking_tile(ctx, k):
    for _ in range(ctx):  # one more tick than the tile's units when ctx = 4: capped
        tile_tick()
    return {"x": np.full(2, k)}, {}


class _Bar:
    """Records what a tqdm bar is given."""

    made: ClassVar[list] = []

    def __init__(self, total, initial, **kw):
        self.total, self.updates = total, [initial]
        _Bar.made.append(self)

    def update(self, n):
        self.updates.append(n)

    def close(self):
        pass


@pytest.mark.parametrize("processes", [1, 2])
def test_bar_moves_within_tiles(monkeypatch, processes):
    """Tiles report their pass groups through ``tile_tick`` (also from forked processes): the
    bar moves by single units, never by a whole tile at its end; extra ticks are capped."""
    monkeypatch.setattr(executor, "tqdm", _Bar)
    _Bar.made.clear()
    cache = TileCache(None, "t", "k")
    for ticks in (3, 4):
        run_tiles(_ticking_tile, ticks, 4, cache, processes=processes, steps_per_tile=[3] * 4)
        bar = _Bar.made[-1]
        assert bar.total == 12 and sum(bar.updates) == 12
        assert max(bar.updates) <= 1, bar.updates  # a whole tile at once would be a 3
    run_tiles(_ticking_tile, 0, 4, cache, processes=processes, steps_per_tile=[3] * 4)  # no ticks
    assert sum(_Bar.made[-1].updates) == 12 and max(_Bar.made[-1].updates) == 3
    with pytest.raises(ValueRangeError, match="steps_per_tile"):
        run_tiles(_ticking_tile, 0, 4, cache, steps_per_tile=[3] * 3)
    tile_tick()  # outside run_tiles: nothing to move, no error


@pytest.mark.parametrize("processes", [1, 2])
def test_precompute_bar_counts_pass_groups(scene, monkeypatch, processes):
    """The precompute's bar moves once per pass group of each tile (16² in tiles of 4 rows at
    4 spp, one pass per group: 4 tiles x 4 groups), forked tiles included."""
    monkeypatch.setattr(executor, "tqdm", _Bar)
    _Bar.made.clear()
    settings = SETTINGS["settings"].replace(group=1)
    T = precompute_polynomial(scene, **{**SETTINGS, "settings": settings, "progress": True}, processes=processes)
    bar = _Bar.made[-1]
    assert bar.total == 16 and sum(bar.updates) == 16 and max(bar.updates) == 1, bar.updates
    assert T.meta["processes"] == processes


def test_executor_arguments(scene):
    with pytest.raises(ValueRangeError):
        precompute_polynomial(scene, **SETTINGS, executor="dask")
    with pytest.raises(ValueRangeError):
        run_tiles(lambda c, k: ({}, {}), None, 1, TileCache(None, "t", "k"), max_retries=-1)


# -- Ray -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray", reason="the cluster extra (Ray) is not installed")
    with private_ray_env() as tmp:
        try:
            init_local(tmp, num_cpus=2)
            yield ray
        finally:
            ray.shutdown()


def _task_pids() -> list[int]:
    """PIDs of Ray workers running a tile now (Ray titles them ``ray::<function>``)."""
    out = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                if (p / "cmdline").read_bytes().startswith(b"ray::_run_in_worker"):
                    out.append(int(p.name))
            except OSError:
                pass
    return out


def test_ray_equals_local(ray_instance, scene, local):
    T = precompute_polynomial(scene, **SETTINGS, executor="ray")
    _assert_identical(T, local)
    assert T.meta["rays"] == local.meta["rays"]


def test_ray_worker_killed_loses_nothing(ray_instance):
    sc = cornell_box_glossy(32)
    settings = {**SETTINGS, "settings": SETTINGS["settings"].replace(spp=8, tile_rows=2)}  # 16 tiles
    box: dict = {}
    run = threading.Thread(target=lambda: box.update(T=precompute_polynomial(sc, **settings, executor="ray")))
    run.start()
    killed = None
    deadline = time.monotonic() + 120
    while killed is None and run.is_alive() and time.monotonic() < deadline:
        pids = _task_pids()
        if pids:
            os.kill(pids[0], signal.SIGKILL)
            killed = pids[0]
        time.sleep(0.02)
    run.join()
    assert killed is not None, "no tile task was seen running"
    _assert_identical(box["T"], precompute_polynomial(sc, **settings))


def test_ray_driver_restart_resumes(ray_instance, scene, local, tmp_path, monkeypatch):
    saves = []
    real = TileCache.save_encoded  # Ray workers encode the tile files; the driver writes them

    def dying_save(self, index, data):
        if len(saves) == 2:
            raise KeyboardInterrupt  # the driver dies after writing two tiles
        saves.append(index)
        real(self, index, data)

    monkeypatch.setattr(TileCache, "save_encoded", dying_save)
    with pytest.raises(KeyboardInterrupt):
        precompute_polynomial(scene, **SETTINGS, executor="ray", checkpoint=tmp_path)
    monkeypatch.setattr(TileCache, "save_encoded", real)
    T = precompute_polynomial(scene, **SETTINGS, executor="ray", checkpoint=tmp_path)
    assert T.meta["tiles_cached"] == 2
    _assert_identical(T, local)


def test_ray_retries_exhausted_names_the_tile(ray_instance):
    sc = cornell_box_glossy(32)
    settings = {**SETTINGS, "settings": SETTINGS["settings"].replace(spp=8, tile_rows=2)}
    box: dict = {}

    def go():
        try:
            precompute_polynomial(sc, **settings, executor="ray", max_retries=0)
        except TileError as exc:
            box["error"] = exc

    run = threading.Thread(target=go)
    run.start()
    killed = False
    deadline = time.monotonic() + 120
    while not killed and run.is_alive() and time.monotonic() < deadline:
        pids = _task_pids()
        if pids:
            os.kill(pids[0], signal.SIGKILL)
            killed = True
        time.sleep(0.02)
    run.join()
    assert killed
    assert "tile" in str(box.get("error", "")) and "retries" in str(box["error"])


def test_cli_precompute_ray_equals_local(ray_instance, tmp_path):
    from typer.testing import CliRunner

    from torch_brdf.cli import app
    from torch_brdf.records.polynomial import PolynomialTensors

    args = ["precompute", "cornell_box_glossy", "--resolution", "16", "--spp", "2", "--series", "4,1"]
    runner = CliRunner()
    a = runner.invoke(app, [*args, "--out", str(tmp_path / "a.npz")])
    b = runner.invoke(app, [*args, "--out", str(tmp_path / "b.npz"), "--ray", "auto"])  # the running instance
    assert a.exit_code == 0 and b.exit_code == 0, a.output + b.output
    _assert_identical(PolynomialTensors.load(tmp_path / "a.npz"), PolynomialTensors.load(tmp_path / "b.npz"))


# -- the other two precomputations through the same executor ---------------------------------------
@pytest.fixture(scope="module")
def teapot_view():
    from torch_brdf.inverse import LightSamples, object_pixels
    from torch_brdf.scene import teatray

    sc = teatray((32, 24))
    px = object_pixels(sc, "teapot")
    ls = LightSamples.from_environment(sc.environment, 32, torch.Generator().manual_seed(5))
    return sc, px, ls


def _transfer(view, **kw):
    from torch_brdf.inverse import CutOptions, precompute_transfer

    sc, px, ls = view
    return precompute_transfer(sc, px, ls, f0=0.875, tile_pixels=40, progress=False, **kw), CutOptions


def test_transfer_tiles_equal_the_untiled_sum(teapot_view, tmp_path):
    from torch_brdf.inverse import cosine_visibility, transfer_functions

    sc, px, ls = teapot_view
    rec, _ = _transfer(teapot_view)
    assert px.count > 2 * 40  # three tiles
    whole = transfer_functions(px, ls, cosine_visibility(sc, px, ls, progress=False), f0=0.875, progress=False)
    assert torch.equal(rec.pixels, whole.pixels)
    torch.testing.assert_close(rec.values, whole.values, rtol=1e-12, atol=1e-14)  # summation order only
    again, _ = _transfer(teapot_view, checkpoint=tmp_path)  # through a tile checkpoint: the same
    assert torch.equal(again.values, rec.values) and not tmp_path.exists()


def test_visibility_ray_equals_local(ray_instance):
    from tests.transport.test_visibility import ball_on_plane
    from torch_brdf.transport.visibility import VisibilitySettings, precompute_visibility

    sc = ball_on_plane()
    a = precompute_visibility(sc, VisibilitySettings(resolution=32, chunk=16), progress=False)
    b = precompute_visibility(sc, VisibilitySettings(resolution=32, chunk=16), progress=False, executor="ray")
    assert -(-len(a.vertices) // 16) >= 3  # several chunks
    xa, xb = a.to_arrays()[0], b.to_arrays()[0]
    assert sorted(xa) == sorted(xb) and all(np.array_equal(xa[k], xb[k]) for k in xa)


def test_transfer_ray_equals_local(ray_instance, teapot_view):
    local, CutOptions = _transfer(teapot_view)
    remote, _ = _transfer(teapot_view, executor="ray")
    assert torch.equal(local.values, remote.values) and torch.equal(local.pixels, remote.pixels)
    cut_local, _ = _transfer(teapot_view, cuts=CutOptions())
    cut_remote, _ = _transfer(teapot_view, cuts=CutOptions(), executor="ray")
    assert torch.equal(cut_local.values, cut_remote.values)
    assert cut_local.meta["mean_cut_size"] == cut_remote.meta["mean_cut_size"]


def test_cli_visibility_and_fit_strokes_ray_equal_local(ray_instance, tmp_path):
    import json

    from typer.testing import CliRunner

    from torch_brdf.cli import app
    from torch_brdf.inverse import load_fit
    from torch_brdf.io import load_arrays

    runner = CliRunner()
    vis = ["precompute-visibility", "cornell_box", "--cubemap", "16", "--chunk", "16", "--no-progress"]
    strokes = tmp_path / "strokes.json"
    strokes.write_text(json.dumps({"strokes": [{"points": [[28, 28], [36, 25]], "color": [3, 3, 2.7]}]}))
    fit = ["fit-strokes", "teatray", "--object", "teapot", "--strokes", str(strokes), "--width", "64"]
    fit += ["--height", "48", "--downsample", "2", "--samples", "32", "--no-progress"]
    for args, name in ((vis, "vis"), (fit, "fit")):
        a = runner.invoke(app, [*args, "--out", str(tmp_path / f"{name}_a" / "x.npz")])
        b = runner.invoke(app, [*args, "--out", str(tmp_path / f"{name}_b" / "x.npz"), "--ray", "auto"])
        assert a.exit_code == 0 and b.exit_code == 0, a.output + b.output
    xa, xb = (load_arrays(tmp_path / f"vis_{s}" / "x.npz")[0] for s in "ab")
    assert sorted(xa) == sorted(xb) and all(np.array_equal(xa[k], xb[k]) for k in xa)
    ta, tb = (load_arrays(tmp_path / f"fit_{s}" / "x.npz" / "transfer.npz")[0] for s in "ab")
    assert all(np.array_equal(ta[k], tb[k]) for k in ta)
    fa, fb = (load_fit(tmp_path / f"fit_{s}" / "x.npz" / "fit.npz") for s in "ab")
    assert torch.equal(fa.coefficients, fb.coefficients)
