"""Ray tracing throughput: ``Scene.trace`` / ``Scene.occluded`` against embreex called directly.

Casts the same seeded random rays (most of them hit) at an ~80k-triangle mesh (an
icosphere, subdivision 6: 81,920 triangles; or ``--mesh FILE``) with

- embreex directly: one ``EmbreeScene.run(o, d, output=1)`` call (the baseline),
- our ``Scene.trace`` with default settings (``workers=None``), with ``workers=1`` (one
  process) and with ``--workers`` processes (default 2),
- the same three for occlusion (``run(..., query="OCCLUDED")`` vs ``Scene.occluded``),

taking the best of ``--repeats`` interleaved runs of each in this process. Progress goes
to stdout; the LAST line is one JSON object, rates in rays/s and ratios against the direct
single embreex call of this run::

    python benchmarks/raytrace.py            # 1M rays
    python benchmarks/raytrace.py --quick    # 200k rays
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import torch
import trimesh
from embreex import mesh_construction, rtcore_scene

from torch_brdf.scene import Camera, Scene, SceneObject, load_mesh


def make_rays(mesh: trimesh.Trimesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) float32 origins, uniform on a sphere of 3 bounding radii about the mesh centre c,
    and unit directions towards ``c + s (v - c)``, v a random vertex and s uniform in
    [0.5, 1.2]: most rays hit, those aimed beyond the surface may miss."""
    rng = np.random.default_rng(seed)
    lo, hi = mesh.bounds
    c, r = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    u = rng.normal(size=(n, 3))
    o = c + 3 * r * u / np.linalg.norm(u, axis=1, keepdims=True)
    v = np.asarray(mesh.vertices)[rng.integers(0, len(mesh.vertices), n)]
    d = c + rng.uniform(0.5, 1.2, (n, 1)) * (v - c) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o.astype(np.float32), d.astype(np.float32)


def make_scene(mesh: trimesh.Trimesh, workers: int | None) -> Scene:
    obj = SceneObject("mesh", mesh, "white", smooth=True)
    camera = Camera(origin=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0))
    return Scene([obj], {"white": {"type": "lambert", "albedo": [0.5] * 3}}, [], camera, workers=workers)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rays", type=int, default=1_000_000, help="rays per call (default 1M)")
    ap.add_argument("--quick", action="store_true", help="200k rays, 3 repeats")
    ap.add_argument("--repeats", type=int, default=None, help="timed runs of each variant, the best counts (5)")
    ap.add_argument("--workers", type=int, default=2, help="processes of the parallel variant")
    ap.add_argument("--mesh", default=None, help="mesh file instead of the procedural icosphere")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    n = 200_000 if args.quick else args.rays
    repeats = args.repeats or (3 if args.quick else 5)

    mesh = load_mesh(args.mesh) if args.mesh else trimesh.creation.icosphere(subdivisions=6)
    o, d = make_rays(mesh, n, args.seed)
    ot, dt = torch.from_numpy(o), torch.from_numpy(d)

    direct = rtcore_scene.EmbreeScene()
    mesh_construction.TriangleMesh(direct, np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32))
    default, single, parallel = make_scene(mesh, None), make_scene(mesh, 1), make_scene(mesh, args.workers)
    print(f"{n} rays, {len(mesh.faces)} triangles, default workers {default.tracer.workers}, "
          f"torch threads {torch.get_num_threads()}, cores {os.cpu_count()}", flush=True)  # fmt: skip

    variants = {
        "embreex": lambda: direct.run(o, d, output=1),
        "default": lambda: default.trace(ot, dt),
        "single": lambda: single.trace(ot, dt),
        "parallel": lambda: parallel.trace(ot, dt),
        "embreex_occluded": lambda: direct.run(o, d, query="OCCLUDED"),
        "occluded": lambda: default.occluded(ot, dt, float("inf")),
        "single_occluded": lambda: single.occluded(ot, dt, float("inf")),
        "parallel_occluded": lambda: parallel.occluded(ot, dt, float("inf")),
    }
    for f in variants.values():  # warm-up: BVH builds, worker start-up, page faults
        f()
    hits, one = parallel.trace(ot, dt), single.trace(ot, dt)
    identical = all(torch.equal(getattr(hits, f), getattr(one, f)) for f in vars(one)) and torch.equal(
        parallel.occluded(ot, dt, float("inf")), single.occluded(ot, dt, float("inf"))
    )
    best = dict.fromkeys(variants, float("inf"))
    for r in range(repeats):
        for name, f in variants.items():
            t0 = time.perf_counter()
            f()
            best[name] = min(best[name], time.perf_counter() - t0)
        print(f"repeat {r + 1}/{repeats}: " + ", ".join(f"{k} {n / best[k] / 1e6:.2f}" for k in best) + " M rays/s",
              flush=True)  # fmt: skip
    for s in (default, single, parallel):
        s.tracer.close()

    rate = {k: n / v for k, v in best.items()}
    print(json.dumps({
        "rays": n,
        "triangles": len(mesh.faces),
        "hit_fraction": round(float(hits.hit.float().mean()), 4),
        "repeats": repeats,
        "embreex_rays_per_s": round(rate["embreex"]),
        "rays_per_s": round(rate["default"]),
        "ratio": round(rate["default"] / rate["embreex"], 3),
        "default_workers": default.tracer.workers,
        "single_rays_per_s": round(rate["single"]),
        "single_ratio": round(rate["single"] / rate["embreex"], 3),
        "workers": args.workers,
        "parallel_rays_per_s": round(rate["parallel"]),
        "parallel_ratio": round(rate["parallel"] / rate["embreex"], 3),
        "parallel_identical": identical,
        "embreex_occluded_rays_per_s": round(rate["embreex_occluded"]),
        "occluded_rays_per_s": round(rate["occluded"]),
        "occluded_ratio": round(rate["occluded"] / rate["embreex_occluded"], 3),
        "single_occluded_ratio": round(rate["single_occluded"] / rate["embreex_occluded"], 3),
        "parallel_occluded_ratio": round(rate["parallel_occluded"] / rate["embreex_occluded"], 3),
        "torch_threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
    }))  # fmt: skip


if __name__ == "__main__":
    main()
