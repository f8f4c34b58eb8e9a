"""Load sensitivity: the key stages quiet and beside one competing CPU-bound process.

    python benchmarks/load.py [--quick] [--stages a,b,...] [--busy-seconds S]

Each stage is timed quiet, then while one busy process (a Python spin loop that this
script starts and stops itself, and that exits on its own after ``--busy-seconds``) runs;
quiet and loaded runs of a stage alternate (``--rounds``) so that a change in the rest of
the machine's load affects both figures of a stage alike. On a 2-core machine the busy
process's fair share leaves one core: an ideal slowdown is at most 2x (the goal: <= 2.2x,
and no stage slower than Mitsuba's slowdown + 0.5).

Stages (``--quick`` sizes in brackets), each the median of its timed runs over ``--rounds``
alternations of quiet and loaded (after warm-up calls in each phase):

* ``ray_casting``: ``Scene.trace`` of 1M [256k] random rays in the 128² glossy Cornell box
  (the trace pool: this process plus forked workers); ``embree`` is embreex alone (one
  process) on the same rays: the reference ``embree_slowdown``.
* ``gi_precompute``: ``precompute_polynomial`` at 128² [64²], series (64,1,1,1), 16 [4] spp.
* ``freeze`` and ``frame``: ``PolynomialRenderer.freeze("back")`` and a frozen frame at
  512² [128²] (tensors precomputed at 2 [1] spp, outside the timing).
* ``triple_frame``: ``TripleProductRenderer.shade`` of the stand-in bunny scene (visibility
  cubemaps 32x32x6 [16x16x6], precomputed outside the timing).
* ``gplvm_fit``: ``fit_gplvm`` (L-BFGS, q = 2, 200 [50] iterations) on the Gram matrix of a
  100 x 20000 [100 x 5000] low-rank matrix.
* ``inverse_solve``: ``inverse.fit`` (normal equations + ADMM) on the teatray teapot at
  160x120 [80x60] with 512 [128] light samples.
* ``mitsuba``: Mitsuba 3's path tracer on the 128² [64²] box at 16 [4] spp, ``llvm_ad_rgb``
  when it runs here (needs Debian's libllvm19), else ``scalar_rgb`` (``mitsuba_variant``,
  ``mitsuba_note`` say which and why): the reference ``mitsuba_slowdown``.

The last line printed is one JSON object: per stage ``{quiet_s, loaded_s, slowdown}`` (and
every timed run in ``quiet_runs`` / ``loaded_runs``) under ``stages``, ``slowdown`` (stage ->
ratio), ``embree_slowdown``, ``mitsuba_slowdown``, ``max_slowdown`` (our stages), ``threads``
(what ``torch_brdf.parallel.threads`` chose), the cores, ``OMP_WAIT_POLICY`` as torch's OpenMP read
it, and ``loadavg`` before and after: on a shared machine the other programs' load is part
of every figure.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as torch_brdf sets it: before torch loads

import argparse
import json
import statistics
import subprocess
import sys
import time
from contextlib import contextmanager

import numpy as np
import torch

from torch_brdf.parallel import threads as _threads

BUSY = "import time\nend = time.monotonic() + {s}\nwhile time.monotonic() < end:\n    pass\n"


def _loadavg() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


@contextmanager
def busy_process(seconds: float):
    """One CPU-bound process for the block (stopped on exit; it also exits by itself after
    ``seconds``)."""
    p = subprocess.Popen([sys.executable, "-c", BUSY.format(s=float(seconds))])
    try:
        time.sleep(0.3)  # let it get scheduled
        yield p
    finally:
        p.terminate()
        try:
            p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _times(fn, repeats: int, warmup: int, self_timed: bool = False) -> list[float]:
    """Seconds of ``repeats`` calls after ``warmup`` calls (``self_timed``: ``fn`` returns its
    own seconds)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        r = fn()
        times.append(r if self_timed else time.perf_counter() - t0)
    return times


# -- stages: each returns (run, repeats, warmup) after its untimed setup ---------------------------
def _rays(scene, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = (x.numpy() for x in scene.tracer.bbox)
    rng = np.random.default_rng(seed)
    o = lo + (hi - lo) * rng.uniform(0.05, 0.95, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o.astype(np.float32), d.astype(np.float32)


def stage_rays(q: bool, ctx: dict):
    from torch_brdf.scene.builtin import cornell_box_glossy

    sc = ctx.setdefault("box", cornell_box_glossy(64 if q else 128))
    o, d = _rays(sc, (1 << 18) if q else (1 << 20))
    ot, dt = torch.from_numpy(o), torch.from_numpy(d)
    return (lambda: sc.trace(ot, dt)), 3, 1


def stage_embree(q: bool, ctx: dict):
    from embreex import mesh_construction, rtcore_scene

    from torch_brdf.scene.builtin import cornell_box_glossy

    sc = ctx.setdefault("box", cornell_box_glossy(64 if q else 128))
    es = rtcore_scene.EmbreeScene()
    for obj in sc.objects:
        v = np.ascontiguousarray(obj.mesh.vertices, dtype=np.float32)
        f = np.ascontiguousarray(obj.mesh.faces, dtype=np.int32)
        mesh_construction.TriangleMesh(es, v, f)
    o, d = _rays(sc, (1 << 18) if q else (1 << 20))
    return (lambda: es.run(o, d, output=1)), 3, 1


def stage_precompute(q: bool, ctx: dict):
    from torch_brdf.scene.builtin import cornell_box_glossy
    from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial

    sc = ctx.setdefault("box", cornell_box_glossy(64 if q else 128))
    spp = 4 if q else 16
    return (
        (lambda: precompute_polynomial(sc, PolynomialSettings("64,1,1,1", spp=spp), seed=0, progress=False)),
        3 if q else 2,
        1,
    )


def _frozen_renderer(q: bool, ctx: dict):
    if "renderer" not in ctx:
        from torch_brdf.render.polynomial import PolynomialRenderer
        from torch_brdf.scene.builtin import cornell_box_glossy
        from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial

        sc = cornell_box_glossy(128 if q else 512)
        t = precompute_polynomial(sc, PolynomialSettings("64,1,1,1", spp=1 if q else 2), seed=1, progress=False)
        mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
        ctx["renderer"] = PolynomialRenderer(t, mats)
    return ctx["renderer"]


def stage_freeze(q: bool, ctx: dict):
    r = _frozen_renderer(q, ctx)
    # warm-up: the tuner measures each thread count on the first calls
    return (lambda: r.freeze("back", cached=False)), 3, 2 * _threads.TRIALS


def stage_frame(q: bool, ctx: dict):
    r = _frozen_renderer(q, ctx)
    if r.frozen_object != "back":
        r.freeze("back")
    m = r.tensors.object_id("back")
    c = r.c[m].clone()
    k = [0]

    def frame():
        k[0] += 1
        r.set_coefficients("back", c * (1 + 0.01 * (k[0] % 7)))
        return r()

    return frame, 20, 10


def stage_triple(q: bool, ctx: dict):
    from torch_brdf.render.triple import TripleProductRenderer
    from torch_brdf.scene.builtin import bunny_relight
    from torch_brdf.transport.visibility import VisibilitySettings, precompute_visibility

    sc = bunny_relight((160, 120), plane_quads=16 if q else 32, use_data=False)
    vis = precompute_visibility(sc, VisibilitySettings(resolution=16 if q else 32, chunk=512), progress=False)
    r = TripleProductRenderer(sc, vis)
    view = r.view()
    return (lambda: r.shade(view)), 7, 2 * _threads.TRIALS


def stage_gplvm(q: bool, ctx: dict):
    from torch_brdf.manifold.gplvm import fit_gplvm, gram

    g = torch.Generator().manual_seed(0)
    n, d = 100, 5000 if q else 20000
    z = torch.randn(n, 6, generator=g, dtype=torch.float64) @ torch.randn(6, d, generator=g, dtype=torch.float64)
    z = z + 0.05 * torch.randn(n, d, generator=g, dtype=torch.float64)
    s, dd = gram(z)
    it = 50 if q else 200
    return (lambda: fit_gplvm(s, dd, 2, max_iter=it, tol=0.0, generator=torch.Generator().manual_seed(0))), 3, 0


def stage_inverse(q: bool, ctx: dict):
    from torch_brdf.inverse import LightSamples, cosine_visibility, energy_rows, fit, object_pixels
    from torch_brdf.scene import teatray

    scene = teatray((640, 480))
    size = (80, 60) if q else (160, 120)
    px = object_pixels(scene, "teapot", scene.camera.with_size(*size))
    ls = LightSamples.from_environment(scene.environment, 128 if q else 512, torch.Generator().manual_seed(0))
    vis = cosine_visibility(scene, px, ls)
    from torch_brdf.inverse import transfer_functions

    from .inverse import F0, KD, _strokes  # the inverse benchmark's problem

    rec = transfer_functions(px, ls, vis, f0=F0)
    target, energy = _strokes(rec), energy_rows()
    return (lambda: fit(rec, target, kd=KD, energy=energy)), 5, 1


def stage_mitsuba(q: bool, ctx: dict):
    from torch_brdf.scene.builtin import cornell_box_glossy
    from torch_brdf.transport import mitsuba as tm

    if not tm.mitsuba_available():
        ctx["mitsuba_note"] = "mitsuba is not installed (the reference extra)"
        return None
    if tm.llvm_available():
        variant, note = "llvm_ad_rgb", "llvm_ad_rgb ran its subprocess probe"
    else:
        variant = "scalar_rgb"
        note = "llvm_ad_rgb failed its probe (apt-get install -y libllvm19); fell back to scalar_rgb"
    ctx["mitsuba_variant"], ctx["mitsuba_note"] = variant, note
    sc = ctx.setdefault("box", cornell_box_glossy(64 if q else 128))
    spp = 4 if q else 16
    tm.render_mitsuba(sc, spp=spp, max_bounces=4, variant=variant)  # JIT, scene translation

    def run():  # mitsuba's own render seconds (scene translation excluded)
        return tm.render_mitsuba(sc, spp=spp, max_bounces=4, variant=variant, return_seconds=True)[1]

    return run, 3, 0, True


STAGES = {
    "ray_casting": stage_rays,
    "embree": stage_embree,
    "gi_precompute": stage_precompute,
    "freeze": stage_freeze,
    "frame": stage_frame,
    "triple_frame": stage_triple,
    "gplvm_fit": stage_gplvm,
    "inverse_solve": stage_inverse,
    "mitsuba": stage_mitsuba,
}
REFERENCES = ("embree", "mitsuba")


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    ap.add_argument("--stages", default=",".join(STAGES), help="comma-separated subset of " + ",".join(STAGES))
    ap.add_argument("--rounds", type=int, default=2, help="quiet/loaded alternations per stage (default 2)")
    ap.add_argument("--busy-seconds", type=float, default=None, help="bound on each busy process (default 600)")
    args = ap.parse_args(argv)
    q = args.quick
    names = [s for s in args.stages.split(",") if s]
    unknown = sorted(set(names) - set(STAGES))
    if unknown:
        ap.error(f"unknown stages {unknown}")
    bound = args.busy_seconds or (300.0 if q else 600.0)
    out: dict = {
        "quick": q,
        "usable_cores": _threads.usable_cores(),
        "workers": _threads.worker_count(),
        "torch_threads": torch.get_num_threads(),
        "omp_wait_policy": _threads.omp_wait_policy(),
        "loadavg_before": _loadavg(),
        "stages": {},
    }
    ctx: dict = {}
    for name in names:
        made = STAGES[name](q, ctx)
        if made is None:
            print(f"{name}: skipped ({ctx.get(name + '_note', 'unavailable')})", flush=True)
            continue
        fn, repeats, warmup, *self_timed = made
        row = {"loadavg": _loadavg()}
        times = {"quiet": [], "loaded": []}
        for _ in range(args.rounds):  # alternate: drifts in the machine's other load hit both
            for phase in times:
                with busy_process(bound) if phase == "loaded" else _nothing():
                    # warm-up calls in each phase: a measured thread count may be measured again
                    times[phase] += _times(fn, repeats, warmup, *self_timed)
        for phase, ts in times.items():
            row[f"{phase}_s"] = round(statistics.median(ts), 5)
            row[f"{phase}_runs"] = [round(t, 5) for t in ts]  # the spread: a shared machine is noisy
        row["slowdown"] = round(row["loaded_s"] / row["quiet_s"], 3)
        out["stages"][name] = row
        print(f"{name}: quiet {row['quiet_s']:.4f} s, loaded {row['loaded_s']:.4f} s, "
              f"slowdown {row['slowdown']:.2f}x (load {row['loadavg']})", flush=True)  # fmt: skip
    ours = {k: v["slowdown"] for k, v in out["stages"].items() if k not in REFERENCES}
    out["slowdown"] = ours
    out["max_slowdown"] = max(ours.values(), default=None)
    out["embree_slowdown"] = out["stages"].get("embree", {}).get("slowdown")
    out["mitsuba_slowdown"] = out["stages"].get("mitsuba", {}).get("slowdown")
    out["mitsuba_variant"] = ctx.get("mitsuba_variant")
    out["mitsuba_note"] = ctx.get("mitsuba_note")
    out["threads"] = {f"{op}@2^{c}": v["chosen"] for (op, c), v in _threads.tuning_state().items()}
    out["loadavg_after"] = _loadavg()
    print(json.dumps(out))
    return out


@contextmanager
def _nothing():
    yield


if __name__ == "__main__":
    main()
