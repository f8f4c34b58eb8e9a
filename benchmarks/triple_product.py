"""All-frequency relighting with locally adaptive triple products: speed, accuracy, storage.

    python benchmarks/triple_product.py [--quick] [--checkpoint DIR] [--precompute-only] [--baseline]

Scene: ``bunny_relight`` (Inger et al.'s test: the Stanford bunny, Phong exponent 200, on a
96x96-quad plane with Phong exponent 20) under a sun-like map (the shared HDR
``quarry_01_sun``, a sunny quarry with a very small, very bright sun; the procedural sun and
sky when the data is absent), 64x64x6
binary visibility (``--quick``: the procedural stand-in bunny, a 32x32-quad plane, a
smaller image). Three frames: the scene camera; the map turned by 2 rad about +y; the camera
moved around the bunny. Every figure compares methods run in this process on the same
culled vertices. Prints progress, then one JSON object as the last line:

* ``vertices`` (all), ``shaded_vertices`` (per frame, after culling), ``precompute_s`` (the
  visibility cubemaps; a ``--checkpoint`` folder resumes) beside ``rays_s`` (embree alone
  on as many rays, the physical limit; chunks run in one forked process per core unless the
  machine is busy, with ``--baseline`` whatever the load); with
  ``--baseline`` also ``one_process_s`` (chunks one after another in this process, rays on
  the scene's trace pool), ``speedup_over_one_process``, ``equals_one_process`` (bit for
  bit); ``visibility_bytes_per_vertex``
  (varint stream) beside ``dense_bytes_per_vertex`` (one bit per texel) and the seed's
  ~1 KB goal; ``lighting_s`` (a lighting update); ``cull_s`` (primary rays + culling).
* ``frame_s`` (ours, default rule: Appendix A for Phong), ``standard_frame_s`` (dense
  texel sum; visibility expanded beforehand, as a standard-basis system stores it),
  ``haar_frame_s`` (Ng et al.'s product on 1% of the lighting and BRDF wavelet coefficients;
  the BRDF wavelets, which they tabulate, are computed outside that figure:
  ``haar_brdf_s``), ``speedup_vs_standard`` = standard / ours, ``haar_speedup_vs_standard``.
  Times are the mean over the frames (best of ``--repeat`` runs each).
* ``psnr`` / ``haar_psnr``: dB against the standard-basis image over the pixels that see the
  scene, peak = the reference's maximum (mean over frames; ``psnr_frames``); ``psnr_display``
  the same on sRGB-encoded images with the reference's 99th-percentile luminance mapped to 1.
* ``cases`` / ``sampling``: the seed's Tables 1 and 2 (percent, frame 1), ``brdf_evals``.
* ``curve``: frame time and PSNR as the BRDF-sampling thresholds vary (the generic rule's
  thresholds times 0.1..10, the Appendix A angles times 0.5..2, and fixed 1/4/16/256 samples).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import torch
from _timing import best_of

from torch_brdf._threads import usable_cores
from torch_brdf.data import data_path
from torch_brdf.metrics import psnr
from torch_brdf.render.triple import FixedRule, GenericRule, PhongRule, TripleProductRenderer
from torch_brdf.scene.builtin import bunny_relight
from torch_brdf.scene.camera import Camera
from torch_brdf.scene.envmap import EnvironmentMap
from torch_brdf.sphere.cubemap import CubemapBlocks
from torch_brdf.transport.visibility import HORIZON_EPS, precompute_visibility


def _display(img: torch.Tensor, exposure: float) -> torch.Tensor:
    x = (img.double() / exposure).clamp(0, 1)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.pow(1 / 2.4) - 0.055)


def _psnrs(img, ref, mask) -> tuple[float, float]:
    lum = (ref[mask] * torch.tensor([0.2126, 0.7152, 0.0722])).sum(-1)
    exposure = float(torch.quantile(lum.double(), 0.99)) or 1.0
    return psnr(img, ref, mask), psnr(_display(img, exposure), _display(ref, exposure), mask, peak=1.0)


def _orbit(cam: Camera, angle: float) -> Camera:
    ox, oy, oz = cam.origin
    tx, _, tz = cam.target
    c, s = math.cos(angle), math.sin(angle)
    dx, dz = ox - tx, oz - tz
    return Camera(
        (tx + c * dx + s * dz, oy, tz - s * dx + c * dz), cam.target, cam.up, cam.fov_deg, cam.width, cam.height
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small scene and image")
    ap.add_argument("--checkpoint", default=None, help="folder for resumable visibility chunks")
    ap.add_argument("--precompute-only", action="store_true", help="stop after the visibility precompute vs embree")
    ap.add_argument(
        "--baseline", action="store_true", help="also time the visibility with its chunks in one process (processes=1)"
    )
    ap.add_argument("--repeat", type=int, default=2, help="timed runs per frame (best is kept)")
    ap.add_argument("--haar-fraction", type=float, default=0.01)
    args = ap.parse_args()
    torch.manual_seed(0)
    sun = None if args.quick else data_path("envmaps", "quarry_01_sun_512x256.exr", required=False)
    env = EnvironmentMap.from_exr(sun) if sun is not None else None  # else the procedural sun and sky
    if args.quick:
        scene = bunny_relight((160, 120), plane_quads=32, use_data=False)
    else:
        scene = bunny_relight((320, 240), envmap=env)
    res = 64
    print(f"scene {scene.name}: {[len(o.mesh.vertices) for o in scene.objects]} vertices", flush=True)

    t = time.perf_counter()
    forked = {"processes": usable_cores()} if args.baseline else {}  # else the default (load-aware)
    vis = precompute_visibility(scene, res, checkpoint=args.checkpoint, chunk=512, **forked)
    precompute_s = time.perf_counter() - t
    baseline = {}
    if args.baseline:  # chunks one after another in this process, rays on the scene's trace pool
        t = time.perf_counter()
        vis1 = precompute_visibility(scene, res, chunk=512, processes=1)
        baseline["one_process_s"] = time.perf_counter() - t
        baseline["speedup_over_one_process"] = baseline["one_process_s"] / precompute_s
        a, b = vis1.blocks, vis.blocks
        names = ("counts", "offsets", "index", "states")
        baseline["equals_one_process"] = all(torch.equal(getattr(a, n), getattr(b, n)) for n in names) and (
            (a.delta is None and b.delta is None) or torch.equal(a.delta, b.delta)
        )
        del vis1
    # the physical limit: embree alone on the same number of rays (one ray per texel above
    # each vertex's horizon), timed on the rays of the first 512 vertices and scaled
    geom = vis.geometry
    up = (vis.vertices.normals @ geom.directions.reshape(-1, 3).T) > HORIZON_EPS
    rays = int(up.sum())
    vi, ti = up[:512].nonzero(as_tuple=True)
    o = (vis.vertices.positions[vi] + scene.ray_epsilon * vis.vertices.normals[vi]).float()
    d = geom.directions.reshape(-1, 3)[ti].float()
    t = time.perf_counter()
    scene.occluded(o, d, float("inf"))
    rays_s = (time.perf_counter() - t) * rays / len(vi)
    del up
    if args.precompute_only:
        load = list(os.getloadavg())
        print(
            json.dumps(
                {
                    "vertices": len(vis.vertices),
                    "precompute_s": precompute_s,
                    "rays": rays,
                    "rays_s": rays_s,
                    "precompute_over_rays": precompute_s / rays_s,
                    **baseline,
                    "load_avg": load,
                }
            )
        )
        return
    r = TripleProductRenderer(scene, vis)
    env = r.envmap
    lighting_s, _ = best_of(lambda: r.set_lighting(env), 3)

    frames = [
        ("camera", scene.camera, 0.0),
        ("rotated_map", scene.camera, 2.0),
        ("orbit", _orbit(scene.camera, 0.7), 0.0),
    ]
    out: dict = {
        "scene": scene.name,
        "quick": args.quick,
        "vertices": len(vis.vertices),
        "cubemap": f"{res}x{res}x6",
        "blocks_per_vertex": vis.geometry.block_count,
        "envmap": str(sun.name) if sun is not None else "procedural sky",
        "precompute_s": precompute_s,
        "rays": rays,
        "rays_s": rays_s,
        "precompute_over_rays": precompute_s / rays_s,
        **baseline,
        "visibility_bytes_per_vertex": vis.bytes_per_vertex,
        "dense_bytes_per_vertex": CubemapBlocks(res).texel_count / 8,
        "seed_bytes_per_vertex": 1024,
        "lighting_s": lighting_s,
        "haar_fraction": args.haar_fraction,
    }
    per = {k: [] for k in ("frame_s", "standard_frame_s", "haar_frame_s", "haar_brdf_s", "cull_s", "shaded_vertices")}
    per.update({k: [] for k in ("psnr", "psnr_display", "haar_psnr", "haar_psnr_display")})
    first = None
    for name, cam, angle in frames:
        r.set_lighting(env.rotated(angle) if angle else env)
        cull_s, view = best_of(lambda cam=cam: r.view(cam), 1)
        mask = view.mask
        frame_s, (rad, stats) = best_of(lambda view=view: r.shade(view), args.repeat)
        dense = view.blocks.decode()  # the standard basis stores visibility expanded
        std_s, ref_rad = best_of(lambda view=view, dense=dense: r.shade_standard(view, dense_visibility=dense), 1)
        del dense
        tim: dict = {}
        haar_rad = r.shade_haar(view, fraction=args.haar_fraction, timings=tim)
        img, ref, himg = r.image(view, rad), r.image(view, ref_rad), r.image(view, haar_rad)
        p, pd = _psnrs(img, ref, mask)
        hp, hpd = _psnrs(himg, ref, mask)
        for k, v in (
            ("frame_s", frame_s),
            ("standard_frame_s", std_s),
            ("haar_frame_s", tim["product_s"]),
            ("haar_brdf_s", tim["brdf_s"]),
            ("cull_s", cull_s),
            ("shaded_vertices", len(view.vertex_ids)),
            ("psnr", p),
            ("psnr_display", pd),
            ("haar_psnr", hp),
            ("haar_psnr_display", hpd),
        ):
            per[k].append(v)
        print(
            f"frame {name}: {len(view.vertex_ids)} vertices, ours {frame_s:.3f} s, standard {std_s:.2f} s, "
            f"haar product {tim['product_s']:.2f} s (+{tim['brdf_s']:.2f} s BRDF wavelets); "
            f"PSNR ours {p:.2f} dB, haar {hp:.2f} dB",
            flush=True,
        )
        if first is None:
            first = (view, ref, mask, stats)
    for k, v in per.items():
        out[k] = sum(v) / len(v)
    out["psnr_frames"] = per["psnr"]
    out["haar_psnr_frames"] = per["haar_psnr"]
    out["speedup_vs_standard"] = out["standard_frame_s"] / out["frame_s"]
    out["haar_speedup_vs_standard"] = out["standard_frame_s"] / out["haar_frame_s"]
    view, ref, mask, stats = first
    pct = stats.percentages()
    out["cases"] = {**pct["cases"], "occluded_of_all": pct["occluded"]}
    out["sampling"] = pct["sampling"]
    out["brdf_evals"] = stats.brdf_evals
    out["brdf_evals_per_vertex"] = stats.brdf_evals / max(1, stats.vertices)

    # the speed/accuracy curve of the BRDF-sampling thresholds (frame 1)
    r.set_lighting(env)
    base = GenericRule()
    auto = vis.geometry.angular_radius / CubemapBlocks(64).angular_radius  # PhongRule's default scale
    rules = {
        f"generic_x{m:g}": GenericRule(base.constant * m, base.linear * m, base.smooth * m)
        for m in (0.1, 0.3, 1, 3, 10)
    }
    rules.update({f"appendix_a_angles_x{m:g}": PhongRule(scale=auto * m) for m in (0.5, 1, 2)})
    rules.update({f"fixed_{l * l}": FixedRule(l) for l in (1, 2, 4, 16)})
    curve = {}
    for key, rule in rules.items():
        s, (rad, st) = best_of(lambda rule=rule: r.shade(view, rule=rule), args.repeat)
        curve[key] = {
            "frame_s": s,
            "psnr": psnr(r.image(view, rad), ref, mask),
            "sampling": st.percentages()["sampling"],
            "brdf_evals_per_vertex": st.brdf_evals / max(1, st.vertices),
        }
        print(f"curve {key}: {s:.3f} s, {curve[key]['psnr']:.2f} dB", flush=True)
    out["curve"] = curve
    print(json.dumps(out))


if __name__ == "__main__":
    main()
