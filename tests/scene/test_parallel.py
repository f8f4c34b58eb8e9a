"""Tracing over several processes gives bitwise the results of one; the pool of forked
workers starts lazily, is reused, closes, survives interrupts and forks safely under torch."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time

import pytest
import torch
import trimesh

from torch_brdf.errors import ValueRangeError
from torch_brdf.scene import RayTracer, Scene, cornell_box
from torch_brdf.scene.embree import CHUNK
from torch_brdf.scene.raytrace import PARALLEL_MIN_RAYS

N = 300_000  # 18 full chunks and a partial one


def _meshes() -> tuple[list[trimesh.Trimesh], list[bool]]:
    """A smooth sphere, a flat box and a smooth torus-like ring: several objects, both normal kinds."""
    sphere = trimesh.creation.icosphere(subdivisions=5)
    box = trimesh.creation.box((1.5, 0.5, 1.0))
    box.apply_translation([2.2, 0.0, 0.0])
    ring = trimesh.creation.annulus(0.6, 1.0, height=0.3, sections=64)
    ring.apply_translation([-2.2, 0.3, 0.0])
    return [sphere, box, ring], [True, False, True]


def _rays(n: int, seed: int, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Origins around the objects, directions towards random points near them: hits and misses."""
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor([4.0, 2.0, 2.0], dtype=torch.float64)
    target = torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor([2.5, 1.0, 1.0], dtype=torch.float64)
    d = torch.nn.functional.normalize(target - o, dim=-1)
    return o.to(dtype), d.to(dtype)


@pytest.fixture(scope="module")
def tracers():
    meshes, smooth = _meshes()
    single, parallel = RayTracer(meshes, smooth, workers=1), RayTracer(meshes, smooth, workers=2)
    yield single, parallel
    parallel.close()


def _assert_same_hits(a, b):
    for name in ("t", "object_id", "prim_id", "barycentrics", "position", "geometric_normal", "normal"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert torch.equal(x, y), f"{name}: {int((x != y).sum())} entries differ"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_parallel_trace_is_bitwise_single(tracers, dtype):
    single, parallel = tracers
    o, d = _rays(N, 1, dtype)
    h1, h2 = single.trace(o, d), parallel.trace(o, d)
    assert parallel._pool.running
    _assert_same_hits(h1, h2)
    assert h2.t.dtype == dtype and h2.object_id.dtype == torch.int64
    hit = h2.hit
    assert 0.2 < float(hit.float().mean()) < 0.95  # both hits and misses
    assert set(h2.object_id[hit].unique().tolist()) == {0, 1, 2}
    assert float(h2.t[~hit].min()) == float("inf") and float(h2.position[~hit].abs().max()) == 0.0
    # the flat box's shading normal is its face normal, exactly
    box = h2.object_id == 1
    assert torch.equal(h2.normal[box], h2.geometric_normal[box])


def test_parallel_occluded_is_bitwise_single(tracers):
    single, parallel = tracers
    o, d = _rays(N, 2)
    t = single.trace(o, d).t
    for t_max in (float("inf"), 3.0, torch.where(torch.isinf(t), 10.0, t * 0.999), t * 1.001):
        a, b = single.occluded(o, d, t_max), parallel.occluded(o, d, t_max)
        assert torch.equal(a, b)
    assert torch.equal(parallel.occluded(o, d, float("inf")), torch.isfinite(t))


def test_repeated_calls_reuse_the_workers(tracers):
    single, parallel = tracers
    parallel.trace(*_rays(PARALLEL_MIN_RAYS, 3))
    pids = [p.pid for p in parallel._pool._procs]
    for seed in range(4, 8):
        o, d = _rays(PARALLEL_MIN_RAYS + 12_345 * seed, seed)
        _assert_same_hits(single.trace(o, d), parallel.trace(o, d))
    assert [p.pid for p in parallel._pool._procs] == pids


def test_small_and_empty_batches_stay_in_this_process():
    meshes, smooth = _meshes()
    tracer = RayTracer(meshes, smooth, workers=2)
    h = tracer.trace(*_rays(PARALLEL_MIN_RAYS - 1, 9))
    assert not tracer._pool.running
    assert len(h) == PARALLEL_MIN_RAYS - 1
    empty = tracer.trace(torch.zeros(0, 3), torch.zeros(0, 3))
    assert len(empty) == 0 and empty.position.shape == (0, 3)
    assert tracer.occluded(torch.zeros(0, 3), torch.zeros(0, 3), 1.0).shape == (0,)


def test_close_stops_workers_and_next_call_restarts():
    meshes, smooth = _meshes()
    single, tracer = RayTracer(meshes, smooth, workers=1), RayTracer(meshes, smooth, workers=2)
    o, d = _rays(2 * CHUNK + 5, 10)
    tracer.trace(o, d)
    procs = list(tracer._pool._procs)
    assert procs and all(p.is_alive() for p in procs)
    tracer.close()
    assert not any(p.is_alive() for p in procs) and not tracer._pool.running
    tracer.close()  # twice is fine
    _assert_same_hits(single.trace(o, d), tracer.trace(o, d))
    assert tracer._pool.running
    tracer.close()


def test_interrupt_during_a_call_closes_the_pool(monkeypatch):
    meshes, smooth = _meshes()
    single, parallel = RayTracer(meshes, smooth, workers=1), RayTracer(meshes, smooth, workers=2)
    pool = parallel._pool
    o, d = _rays(4 * CHUNK, 11)
    parallel.trace(o, d)
    procs = list(pool._procs)

    def interrupted(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(pool.kernel, "trace", interrupted)  # Ctrl-C while this process traces its chunks
    with pytest.raises(KeyboardInterrupt):
        parallel.trace(o, d)
    monkeypatch.undo()
    assert not pool.running and not any(p.is_alive() for p in procs)
    _assert_same_hits(single.trace(o, d), parallel.trace(o, d))  # a fresh pool, same results
    assert pool.running
    parallel.close()


def test_scene_workers_option():
    assert cornell_box(4).tracer.workers >= 1
    scene = cornell_box(4)
    assert Scene(scene.objects, scene.materials, scene.lights, scene.camera, workers=1).tracer.workers == 1
    with pytest.raises(ValueRangeError, match="workers"):
        RayTracer(*_meshes(), workers=0)


def _run_script(code: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=timeout,  # a deadlock fails the test instead of hanging the suite
        cwd=os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
    )


def test_fork_with_torch_threads_in_the_parent_does_not_deadlock():
    r = _run_script(
        """
        import torch, trimesh
        from torch_brdf.scene import RayTracer
        torch.set_num_threads(2)
        a = torch.randn(512, 512)
        for _ in range(3):
            a = torch.tanh(a @ a.T / 512)  # torch's thread pool is up and used
        m = trimesh.creation.icosphere(subdivisions=4)
        one, two = RayTracer([m], [True], workers=1), RayTracer([m], [True], workers=2)
        d = torch.nn.functional.normalize(torch.randn(100_000, 3), dim=-1)
        o = -3 * d + 0.5 * torch.randn(100_000, 3)
        for _ in range(3):
            assert torch.equal(one.trace(o, d).position, two.trace(o, d).position)
            a = torch.tanh(a @ a.T / 512)  # and still works between and after forks
        assert two._pool.running
        print("ok", float(a.sum()) == float(a.sum()))
        """
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "ok True"


def test_workers_exit_when_the_parent_dies():
    r = _run_script(
        """
        import os, torch, trimesh
        from torch_brdf.scene import RayTracer
        m = trimesh.creation.icosphere(subdivisions=3)
        t = RayTracer([m], [True], workers=2)
        t.trace(torch.randn(100_000, 3) * 3, torch.randn(100_000, 3))
        print(*[p.pid for p in t._pool._procs], flush=True)
        os._exit(0)  # no clean-up, as if killed
        """
    )
    assert r.returncode == 0, r.stderr
    pids = [int(p) for p in r.stdout.split()]
    assert pids
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline and any(_alive(p) for p in pids):
        time.sleep(0.2)
    assert not any(_alive(p) for p in pids)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (exited, not yet reaped by init) counts as gone
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False
