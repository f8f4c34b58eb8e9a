"""Textures through the GI precompute and renderer (Ben-Artzi et al. 2008, Sec. 5.3): the
error of "exact at the eye vertex through H^m(x), mean albedo at later bounces".

    python -m torch_brdf.report.benchmarks.textures [--quick]   (or python benchmarks/textures.py)

Scene: the Cornell box (Lambert walls) with its floor textured (a random 8x8 sRGB texture of
high contrast, repeated 4 times across the floor). The reference is our path tracer on the
textured scene (exact textures at every vertex). The GI renderer renders tensors precomputed
from the same scene with the texture's factor, with the texture applied by
:func:`torch_brdf.render.apply_scene_textures`. To separate the texture approximation from the
series' own error, the same pipeline renders the scene with the floor's albedo set to the
texture's surface mean (untextured), against the path tracer of that scene.

Prints one JSON object as the last line:

* ``textured_rel_rmse``: relative RMSE (outside directly seen emitters) of the textured GI
  render against the textured path-traced reference;
* ``untextured_rel_rmse``: the same for the mean-albedo scene (the series' and the noise's
  error alone); ``texture_excess``: their difference (the approximation's own share);
* ``mean_ratio_textured``: image-mean ratio GI / path tracer on the textured scene;
* ``later_bounce_ratio``: the floor pixels' mean ratio GI / path tracer;
* ``reference_noise_rel_rmse``: the relative RMSE between two reference renders of different
  seeds divided by sqrt(2) (the noise of one reference);
* settings (``size``, ``spp``, ``series``, ``bounces``).
"""

from __future__ import annotations

import argparse
import copy
import json
import time

import numpy as np
import torch


def textured_cornell(size: int):
    from torch_brdf.scene.builtin import cornell_box
    from torch_brdf.scene.textures import Texture, srgb_to_linear

    sc = cornell_box(size)
    a = np.random.default_rng(7).random((8, 8, 3))
    tex = Texture(torch.from_numpy(srgb_to_linear(np.round(a * 255) / 255)).float(), "checker")
    i = sc.object_id("floor")
    floor = sc.objects[i]
    v = np.asarray(floor.mesh.vertices)
    uv = (v[:, [0, 2]] - v[:, [0, 2]].min(0)) / np.ptp(v[:, [0, 2]], 0) * 2.0  # 2 x 2 repeats
    objects = list(sc.objects)
    objects[i] = copy.copy(floor)
    objects[i].uv, objects[i].textures = uv, {"base_color": tex}
    mats = dict(sc.materials)
    mats["floor_mat"] = {"type": "lambert", "albedo": 0.9}
    objects[i].material = "floor_mat"
    from torch_brdf.scene import Scene

    return Scene(objects, mats, sc.lights, sc.camera, name="cornell_textured")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    from torch_brdf.metrics import relative_rmse
    from torch_brdf.render import PolynomialRenderer, apply_scene_textures
    from torch_brdf.render.polynomial import emitter_mask
    from torch_brdf.scene import Scene
    from torch_brdf.scene.textures import surface_mean
    from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace
    from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial

    size, spp, ref_spp, series, bounces = (24, 16, 64, "8,1,1", 3) if args.quick else (64, 64, 1024, "16,1,1", 3)
    t0 = time.perf_counter()
    sc = textured_cornell(size)
    mean = surface_mean(sc, "floor")
    flat_mats = dict(sc.materials)
    flat_mats["floor_mat"] = {"type": "lambert", "albedo": (0.9 * mean).tolist()}
    flat_objects = [copy.copy(o) for o in sc.objects]
    i = sc.object_id("floor")
    flat_objects[i].uv, flat_objects[i].textures = None, {}
    flat = Scene(flat_objects, flat_mats, sc.lights, sc.camera, name="cornell_mean_albedo")
    out = {"size": size, "spp": spp, "reference_spp": ref_spp, "series": series, "bounces": bounces}
    for name, scene, textured in (("textured", sc, True), ("untextured", flat, False)):
        print(f"{name}: reference path trace ...", flush=True)
        ref = path_trace(scene, PathTraceSettings(spp=ref_spp, max_bounces=bounces), seed=1, progress=False).double()
        T = precompute_polynomial(scene, PolynomialSettings(series, spp=spp), seed=2, progress=False)
        mats = {o.name: scene.materials[o.material] for o in scene.objects if o.editable}
        R = PolynomialRenderer(T, mats, dtype=torch.float64, max_bounces=bounces)
        if textured:
            assert apply_scene_textures(R, scene) == ["floor"]
        img = R.evaluate().detach()
        mask = emitter_mask(T)
        out[f"{name}_rel_rmse"] = float(relative_rmse(img[mask], ref[mask]))
        if textured:
            ref2 = path_trace(
                scene, PathTraceSettings(spp=ref_spp, max_bounces=bounces), seed=3, progress=False
            ).double()
            out["reference_noise_rel_rmse"] = float(relative_rmse(ref2[mask], ref[mask])) / 2**0.5
            out["mean_ratio_textured"] = float(img[mask].mean() / ref[mask].mean())
            floor_px = torch.zeros(T.height * T.width, dtype=torch.bool)
            floor_px[T.first_order("floor").pixels] = True
            fm = floor_px.reshape(T.height, T.width) & mask
            out["floor_mean_ratio"] = float(img[fm].mean() / ref[fm].mean())
            out["other_mean_ratio"] = float(img[mask & ~fm].mean() / ref[mask & ~fm].mean())
    out["texture_excess"] = out["textured_rel_rmse"] - out["untextured_rel_rmse"]
    out["seconds"] = time.perf_counter() - t0
    print(json.dumps(out))


if __name__ == "__main__":
    main()
