"""Denoising precomputed basis images against a path tracer with a per-frame denoiser.

    python benchmarks/denoise.py [--quick] [--figure noisy_denoised_reference.png]

For the glossy Cornell box (back wall Blinn-Phong n = 100; frozen object: the back wall) and
the teatray (glossy tray under sun and sky; frozen object: the tray), tensors of series
(64,1,1,1) (``--quick``: (16,1,1), 48x48) are precomputed at 16, 64 and 256 spp
(``--quick``: 4, 16), frozen on the edited object, and rendered by four methods:

* ``none``: the precomputed frame as is (also at 1024 spp, ``--quick`` 64, as the mean of
  independent runs' frames, which is the higher-spp estimate: frames are linear in the tensors);
* ``linear``: the guide-only à-trous filter (torch_brdf.denoise.EdgeAwareFilter) applied once
  to every basis image of the frozen tensor;
* ``oidn_basis``: Open Image Denoise applied once per grouped basis image;
* ``oidn_frame``: the path-tracer user's baseline: OIDN on every final frame.

Prints progress, then one JSON object as the last line: for the Cornell box at top level
and per scene under ``scenes``: ``rel_rmse`` / ``rel_rmse_edited`` / ``flip`` /
``flip_edited`` as ``{method: {spp: value}}`` (``"1024"`` only for ``none``), against a
high-spp reference (Mitsuba 3 llvm at 4096 spp when it runs here, else
``reference_path_trace`` with MIS), pixels that see an emitter excluded (their value is
emission, the same in every method); ``precompute_s`` ``{spp: s}``, ``denoise_s``
``{method: {spp: s}}``, ``frame_s_before`` (noisy frozen frame), ``frame_s_after``
``{method: s}`` (per edited frame: the denoised frozen frame; for ``oidn_frame`` frame + OIDN),
``mean_ratio`` ``{method: mean over the reference mean}`` at 64 spp (``--quick``: 16),
``frozen_mb`` ``{method: MB}``. Edited material: exponent -> 1000 and another colour, a
material the denoisers never saw (they see only guides and basis images).
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from torch_brdf.denoise import EdgeAwareFilter, OIDNBasis, denoise_frozen, guide_buffers, oidn_frame
from torch_brdf.metrics import hdr_flip, relative_rmse
from torch_brdf.render.polynomial import PolynomialRenderer, emitter_mask
from torch_brdf.scene.builtin import cornell_box_glossy, teatray
from torch_brdf.transport.pathtrace import reference_path_trace
from torch_brdf.transport.polynomial import precompute_polynomial

METHODS = ("none", "linear", "oidn_basis", "oidn_frame")
SCENES = {
    "cornell_box_glossy": (
        cornell_box_glossy,
        "back",
        {"type": "blinn_phong", "kd": (0.35, 0.2, 0.1), "ks": (0.45, 0.55, 0.7), "exponent": 1000.0},
    ),
    "teatray": (
        teatray,
        "tray",
        {"type": "blinn_phong", "kd": (0.2, 0.1, 0.08), "ks": (0.7, 0.6, 0.45), "exponent": 1000.0},
    ),
}


def _materials(scene):
    return {o.name: scene.materials[o.material] for o in scene.objects if o.editable}


def _reference(scene, spp_mitsuba: int, spp_ours: int, bounces: int):
    """(image, label): Mitsuba llvm when it runs, else our MIS reference tracer."""
    try:
        from torch_brdf.transport import mitsuba as tm

        if tm.mitsuba_available() and tm.default_variant().startswith("llvm"):
            img = tm.render_mitsuba(scene, spp=spp_mitsuba, max_bounces=bounces, seed=7)
            return img, f"mitsuba {tm.default_variant()} {spp_mitsuba} spp"
    except ImportError:
        pass
    img = reference_path_trace(scene, spp=spp_ours, max_bounces=bounces, seed=7, progress=False)
    return img, f"reference_path_trace (MIS) {spp_ours} spp"


def _timed(fn, repeat: int = 1):
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def _frame_time(R, obj: str) -> float:
    """Best of 5 frozen frames (the interactive path; asserted, not a silent full evaluation)."""
    assert R.frozen_object == obj, (R.frozen_object, obj)
    return _timed(R, repeat=5)[1]


def run_scene(name: str, q: bool, figure: str | None) -> dict:
    build, obj, edited = SCENES[name]
    res = 48 if q else 256
    series = "16,1,1" if q else "64,1,1,1"
    spps = (4, 16) if q else (16, 64, 256)
    hi_spp = 64 if q else 1024
    mid = str(spps[1] if q else 64)
    bounces = len(series.split(","))
    scene = build(res)
    mats = _materials(scene)
    scene_edit = build(res)
    scene_edit.materials[scene_edit.objects[scene_edit.object_id(obj)].material] = dict(edited)
    print(f"[{name}] references ...", flush=True)
    ref, label = _reference(scene, 512 if q else 4096, 64 if q else 512, bounces)
    ref_e, _ = _reference(scene_edit, 512 if q else 4096, 64 if q else 512, bounces)
    guides = guide_buffers(scene)
    linear = None  # built from the first tensors: which objects are banded (glossy) is in the record
    out: dict = {
        "resolution": res,
        "series": series,
        "reference": label,
        "edited_material": edited,
        "frozen_object": obj,
    }
    keys = ("rel_rmse", "rel_rmse_edited", "flip", "flip_edited", "denoise_s")
    for k in keys:
        out[k] = {m: {} for m in METHODS}
    out["precompute_s"], out["frame_s_after"], out["mean_ratio"], out["frozen_mb"] = {}, {}, {}, {}
    mask = None
    hi_frames: dict[str, list] = {"default": [], "edited": []}

    def score(method, spp, img, img_e):
        out["rel_rmse"][method][spp] = relative_rmse(img, ref, mask)
        out["rel_rmse_edited"][method][spp] = relative_rmse(img_e, ref_e, mask)
        out["flip"][method][spp] = hdr_flip(img, ref, mask)
        out["flip_edited"][method][spp] = hdr_flip(img_e, ref_e, mask)
        if spp == mid:
            out["mean_ratio"][method] = float(img[mask].double().mean() / ref[mask].double().mean())

    runs = list(spps) + [spps[-1]] * (hi_spp // spps[-1] - 1)  # extra seeds for the 1024-spp mean
    for k, spp in enumerate(runs):
        key = str(spp)
        extra = k >= len(spps)
        print(f"[{name}] precompute {spp} spp{' (extra seed)' if extra else ''} ...", flush=True)
        T, secs = _timed(lambda spp=spp, k=k: precompute_polynomial(scene, series, spp=spp, seed=k, progress=False))
        if mask is None:
            mask = emitter_mask(T)
            linear = EdgeAwareFilter(guides, glossy=[m for m, b in enumerate(T.bases) if b is not None and b.J > 1])
        R = PolynomialRenderer(T, mats)
        R.freeze(obj)
        frames = {}
        frozen = R._frozen
        R.set_material(obj, mats[obj])
        noisy = R()
        R.set_material(obj, edited)
        noisy_e = R()
        if spp == spps[-1]:
            hi_frames["default"].append(noisy)
            hi_frames["edited"].append(noisy_e)
        if extra:
            continue
        out["precompute_s"][key] = secs
        out["frame_s_before"] = _frame_time(R, obj)
        out["frozen_mb"]["none"] = R.frozen_nbytes / 2**20
        frames["none"] = (noisy, noisy_e)
        out["denoise_s"]["none"][key] = 0.0
        for method, den in (("linear", linear), ("oidn_basis", OIDNBasis(guides, linear))):
            print(f"[{name}] {method} at {spp} spp ...", flush=True)
            R._frozen, secs = _timed(lambda den=den, frozen=frozen: denoise_frozen(frozen, den, (res, res)))
            out["denoise_s"][method][key] = secs
            R.set_material(obj, mats[obj])
            img = R()
            R.set_material(obj, edited)
            img_e = R()
            out["frame_s_after"][method] = _frame_time(R, obj)
            out["frozen_mb"][method] = R.frozen_nbytes / 2**20
            frames[method] = (img, img_e)
        (img, secs) = _timed(lambda noisy=noisy: oidn_frame(noisy, guides))
        img_e = oidn_frame(noisy_e, guides)
        out["denoise_s"]["oidn_frame"][key] = secs
        out["frame_s_after"]["oidn_frame"] = out["frame_s_before"] + secs
        frames["oidn_frame"] = (img, img_e)
        for method, (a, b) in frames.items():
            score(method, key, a, b)
        if figure and key == mid:
            from torch_brdf.io.png import write_png

            strip = torch.cat([frames["none"][0], frames["linear"][0], frames["oidn_basis"][0], ref], 1)
            write_png(figure, strip, tonemap="clip")
        print(f"[{name}] {spp} spp rel_rmse", {m: round(out["rel_rmse"][m][key], 4) for m in METHODS}, flush=True)
    hi = str(hi_spp)
    a = torch.stack(hi_frames["default"]).mean(0)
    b = torch.stack(hi_frames["edited"]).mean(0)
    out["rel_rmse"]["none"][hi] = relative_rmse(a, ref, mask)
    out["rel_rmse_edited"]["none"][hi] = relative_rmse(b, ref_e, mask)
    out["flip"]["none"][hi] = hdr_flip(a, ref, mask)
    out["flip_edited"]["none"][hi] = hdr_flip(b, ref_e, mask)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    ap.add_argument("--figure", default=None, help="PNG: noisy | linear | oidn_basis | reference (Cornell, 64 spp)")
    ap.add_argument("--scenes", default=",".join(SCENES), help="comma-separated subset of " + ",".join(SCENES))
    args = ap.parse_args()
    result: dict = {"quick": args.quick, "scenes": {}}
    for name in args.scenes.split(","):
        result["scenes"][name] = run_scene(name, args.quick, args.figure if name == "cornell_box_glossy" else None)
    first = result["scenes"].get("cornell_box_glossy") or next(iter(result["scenes"].values()))
    result.update({k: v for k, v in first.items() if k not in ("edited_material",)})
    print(json.dumps(result))


if __name__ == "__main__":
    main()
