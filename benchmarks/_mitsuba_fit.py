"""The peer of benchmarks/inverse_gi.py: the same recovery in Mitsuba 3 (``llvm_ad_rgb``, ``prb``, ``mi.ad.Adam``).

The back wall is the bridge's Blinn-Phong Python BSDF (``torch_brdf.transport.mitsuba``; it
evaluates our formula, checked against our path tracer there) with ``kd`` and ``ks`` exposed as
differentiable parameters (exponent fixed at 100). Target: Mitsuba's own render of the truth
(kd 0.3, ks 0.5) at ``target_spp``; start kd 0.5, ks 0 (our start, Lambert 0.5); loss: mean
squared error over the image at ``spp`` per step; Adam, lr 0.02, values clamped to [0, 1].
"""

from __future__ import annotations

import time

import numpy as np

from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.transport.mitsuba import BLINN_PHONG_PLUGIN, _blinn_phong_class, set_variant, to_mitsuba_dict


def mitsuba_fit(res: int, quick: bool = False, steps: int | None = None) -> dict:
    import drjit as dr

    mi = set_variant("llvm_ad_rgb")
    base = _blinn_phong_class(mi)

    class DiffBlinnPhong(base):
        def traverse(self, callback):
            callback.put("kd", self.kd, mi.ParamFlags.Differentiable)
            callback.put("ks", self.ks, mi.ParamFlags.Differentiable)

        def parameters_changed(self, keys):
            pass

    mi.register_bsdf(BLINN_PHONG_PLUGIN, lambda props: DiffBlinnPhong(props))
    sc = cornell_box_glossy(res)
    sc.materials["glossy_back"] = {"type": "blinn_phong", "kd": 0.3, "ks": 0.5, "exponent": 100.0}
    spp, target_spp = (4, 64) if quick else (16, 1024)
    steps = steps or (40 if quick else 100)
    desc = to_mitsuba_dict(sc, spp, 4)
    desc["integrator"] = {"type": "prb", "max_depth": 5}
    scene = mi.load_dict(desc)
    target = mi.render(scene, seed=1000, spp=target_spp)
    params = mi.traverse(scene)
    keys = [k for k in params.keys() if k.endswith(".kd") or k.endswith(".ks")]
    truth = {k: np.array(params[k]).ravel().copy() for k in keys}
    opt = mi.ad.Adam(lr=0.02)
    for k in keys:
        opt[k] = mi.Color3f(0.5 if k.endswith(".kd") else 0.0)
    params.update(opt)
    mi.render(scene, params, seed=0, spp=1)  # compile the kernels first (not timed)
    losses = []
    t0 = time.perf_counter()
    for it in range(steps):
        img = mi.render(scene, params, seed=it + 1, spp=spp)
        loss = dr.mean(dr.square(img - target), axis=None)
        dr.backward(loss)
        opt.step()
        for k in keys:
            opt[k] = dr.clip(opt[k], 0.0, 1.0)
        params.update(opt)
        losses.append(float(loss.array[0]) if hasattr(loss, "array") else float(loss))
    fit_s = time.perf_counter() - t0
    final = mi.render(scene, params, seed=10_000, spp=target_spp)
    final_loss = float(np.mean((np.array(final) - np.array(target)) ** 2))
    err = max(float(np.abs(np.array(params[k]).ravel() - truth[k]).max() / np.abs(truth[k]).max()) for k in keys)
    return {
        "mitsuba_fit_s": round(fit_s, 3),
        "mitsuba_iterations": steps,
        "mitsuba_loss": final_loss,
        "mitsuba_loss_curve_last": losses[-5:],
        "mitsuba_param_rel_err": err,
        "mitsuba_spp": spp,
        "mitsuba_res": res,
        "mitsuba_params": {k: np.array(params[k]).ravel().round(4).tolist() for k in keys},
    }


if __name__ == "__main__":
    import json

    print(json.dumps(mitsuba_fit(32, quick=True)))
