"""Denoising under edits of one, two and all objects: the ``edits`` part of the denoising benchmark.

A generated scene (:func:`edit_scene`: a glossy floor, a diffuse and a glossy sphere under a
procedural sky, seeded) is precomputed three times with independent seeds: at ``spp`` (the frame
to denoise), at ``16 x spp`` (the undenoised frame a denoiser must match) and at ``ref x spp`` (the
reference). For each edit case (:data:`EDIT_CASES`: the default materials, then one, two and all
three objects edited to materials no denoiser saw) every method's frame is compared with the
reference:

* ``none``: the frame as is; ``none_16x``: the 16x-samples frame;
* ``frame``: :class:`~torch_brdf.denoise.FrameDenoiser` (OIDN when it imports, else the regression
  filter) keeping each object region's mean, the default;
* ``frame_plain``: the same denoiser without the mean correction;
* ``basis``: the whole-record path, :func:`~torch_brdf.denoise.denoise` with the regression filter
  (linear: the same operator for every edit), rendered as usual.

Keys per case: ``mean_shift`` ``{method: max over object regions of |mean / reference mean - 1|}``,
``mean_shift_added`` (the same against the noisy frame: what the denoiser itself moves),
``error_ratio`` ``{method: relative RMSE / that of none_16x}``, ``rel_rmse``, ``mean_error_estimate``
(the frame denoiser's own per-region estimate of its mean's standard error); per method
``entries_ratio`` (stored entries over the undenoised record's) and ``time_ratio`` (one edited
frame, denoising included, over one undenoised frame of the same record; the basis path's one-off
denoising seconds over one undenoised frame are ``basis_denoise_ratio``).
"""

from __future__ import annotations

import os
import time

import numpy as np
import torch
import trimesh

from torch_brdf.denoise import FrameDenoiser, denoise, oidn_available
from torch_brdf.metrics import relative_rmse
from torch_brdf.render import PolynomialRenderer
from torch_brdf.scene import Camera, EnvironmentMap, Scene, SceneObject
from torch_brdf.scene.mesh import mesh_from_arrays
from torch_brdf.transport import PolynomialSettings, precompute_polynomial

#: the edit cases: object name -> new material (objects not named keep the scene's)
EDIT_CASES: dict[str, dict[str, dict]] = {
    "default": {},
    "one": {"glossy": {"type": "blinn_phong", "kd": (0.3, 0.1, 0.05), "ks": 0.7, "exponent": 200.0}},
    "two": {
        "glossy": {"type": "blinn_phong", "kd": (0.3, 0.1, 0.05), "ks": 0.7, "exponent": 200.0},
        "floor": {"type": "blinn_phong", "kd": 0.05, "ks": 0.8, "exponent": 150.0},
    },
    "all": {
        "glossy": {"type": "blinn_phong", "kd": (0.3, 0.1, 0.05), "ks": 0.7, "exponent": 200.0},
        "floor": {"type": "blinn_phong", "kd": 0.05, "ks": 0.8, "exponent": 150.0},
        "diffuse": {"type": "lambert", "albedo": (0.2, 0.6, 0.8)},
    },
}


def edit_scene(size: int = 32, seed: int = 0, sun: float = 4.0, sun_degrees: float = 12.0) -> Scene:
    """A glossy floor with a diffuse and a glossy sphere under a procedural sky with a soft sun.

    Args:
        size: image width and height.
        seed: places the spheres and the sun.
        sun: the sun's radiance (0: the sky alone).
        sun_degrees: the sun's angular radius.
    """
    rng = np.random.default_rng(seed)
    s1 = trimesh.creation.icosphere(subdivisions=3, radius=0.6)
    s1.apply_translation([-0.75, 0.6, rng.uniform(-0.3, 0.3)])
    s2 = trimesh.creation.icosphere(subdivisions=3, radius=0.55)
    s2.apply_translation([0.75, 0.55, rng.uniform(-0.3, 0.3)])
    floor = mesh_from_arrays([(-3, 0, -3), (-3, 0, 3), (3, 0, 3), (3, 0, -3)], [[0, 1, 2], [0, 2, 3]], "floor")
    objects = [
        SceneObject("floor", floor, "floor"),
        SceneObject("diffuse", mesh_from_arrays(s1.vertices, s1.faces, "diffuse"), "diffuse", smooth=True),
        SceneObject("glossy", mesh_from_arrays(s2.vertices, s2.faces, "glossy"), "glossy", smooth=True),
    ]
    materials = {
        "floor": {"type": "blinn_phong", "kd": 0.2, "ks": 0.5, "exponent": 50.0},
        "diffuse": {"type": "lambert", "albedo": (0.7, 0.5, 0.3)},
        "glossy": {"type": "blinn_phong", "kd": (0.1, 0.15, 0.3), "ks": 0.6, "exponent": 80.0},
    }
    az = rng.uniform(0, 2 * np.pi)
    direction = (0.6 * np.cos(az), 0.6, 0.6 * np.sin(az))
    env = EnvironmentMap.sky(
        height=32,
        sun_direction=direction,
        sun_angular_radius_deg=sun_degrees,
        sun_radiance=(sun, 0.95 * sun, 0.87 * sun),
    )
    cam = Camera((0.0, 1.8, -3.6), (0.0, 0.45, 0.0), (0.0, 1.0, 0.0), 45.0, size, size)
    return Scene(objects, materials, [env], cam, name=f"edit_scene_{seed}")


def _coefficients(R: PolynomialRenderer, mats) -> dict[str, list[tuple]]:
    """Per edit case, every object's (c, d, c_hat) as ``R`` projects them: the projection is done
    once and given to the other records' renderers (same bases), which then skip it."""
    out = {}
    for case, edit in EDIT_CASES.items():
        for name, m in edit.items():
            R.set_material(name, m)
        out[case] = [(R.c[k], R.d[k], R.c_hat[k]) for k in range(R.tensors.num_objects)]
        for name in edit:
            R.set_material(name, mats[name])
    return out


def _frames(R: PolynomialRenderer, coefficients: dict[str, list[tuple]]) -> dict[str, torch.Tensor]:
    out = {}
    for case, per_object in coefficients.items():
        for k, (c, d, c_hat) in enumerate(per_object):
            if c is not None:
                R.set_coefficients(k, c, d, c_hat)
        out[case] = R.evaluate().detach()
    return out


def _best(fn, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def mean_shift(image: torch.Tensor, reference: torch.Tensor, regions: torch.Tensor) -> float:
    """The largest relative difference of an object region's mean (all channels) from the reference's.

    Args:
        image: (H, W, 3).
        reference: (H, W, 3).
        regions: (H, W) int64 object id per pixel (negative: no object, skipped).
    """
    out = 0.0
    for o in regions.unique().tolist():
        if o >= 0:
            m = regions == o
            out = max(out, abs(float(image[m].mean() / reference[m].mean()) - 1.0))
    return out


def run_edits(
    size: int = 32,
    spp: int = 16,
    series: str = "8,1,1",
    ref: int = 64,
    seed: int = 0,
    basis: bool = True,
    sun: float = 4.0,
) -> dict:
    """The edit sweep (module docstring) on :func:`edit_scene` ``(size, seed)``.

    Args:
        size: image width and height.
        spp: samples of the frame to denoise (the others: ``16 * spp`` and ``ref * spp``).
        series: the BRDF series (its length: bounces).
        ref: the reference's samples as a multiple of ``spp``.
        seed: the scene's and the precomputations' seed.
        basis: also run the whole-record path (``basis``).
        sun: the sky's sun radiance (:func:`edit_scene`).
    Returns:
        the JSON-ready dict of keys above.
    """
    scene = edit_scene(size, seed, sun)
    mats = {o.name: scene.materials[o.material] for o in scene.objects}

    def rec(n, s):
        return precompute_polynomial(scene, PolynomialSettings(series, spp=n), seed=s, progress=False)

    t0 = time.perf_counter()
    lo, hi, reference = rec(spp, seed + 1), rec(16 * spp, seed + 2), rec(ref * spp, seed + 3)
    precompute_s = time.perf_counter() - t0
    regions, mask = lo.guides.object_id, lo.guides.object_id >= 0
    method = "oidn" if oidn_available() else "regression"
    den = FrameDenoiser(lo.guides, method)
    plain = FrameDenoiser(lo.guides, method, keep_mean=False)
    R = PolynomialRenderer(lo, mats)
    coefficients = _coefficients(R, mats)
    f_lo = _frames(R, coefficients)
    f_hi = _frames(PolynomialRenderer(hi, mats), coefficients)
    f_ref = _frames(PolynomialRenderer(reference, mats), coefficients)
    frames = {"none": f_lo, "none_16x": f_hi, "frame": {}, "frame_plain": {}}
    estimate = {}
    for case, x in f_lo.items():
        frames["frame"][case] = den(x)
        estimate[case] = {lo.object_names[o]: e for o, e in den.last_mean_error.items()}
        frames["frame_plain"][case] = plain(x)
    out: dict = {
        "settings": {"size": size, "spp": spp, "series": series, "ref": ref, "seed": seed, "method": method, "sun": sun}
    }
    t_frame = _best(R.evaluate)
    entries = {"none": 1.0, "frame": 1.0, "frame_plain": 1.0}
    times = {"none": 1.0, "frame": _best(lambda: den(R.evaluate())) / t_frame}
    times["frame_plain"] = _best(lambda: plain(R.evaluate())) / t_frame
    if basis:
        t = time.perf_counter()
        B = denoise(lo, "regression", max_entries=None)
        out["basis_denoise_ratio"] = (time.perf_counter() - t) / t_frame
        RB = PolynomialRenderer(B, mats)
        frames["basis"] = _frames(RB, coefficients)
        entries["basis"] = B.num_entries / lo.num_entries
        times["basis"] = _best(RB.evaluate) / t_frame
    for case in EDIT_CASES:
        r = f_ref[case]
        e16 = relative_rmse(f_hi[case], r, mask)
        errs = {m: relative_rmse(f[case], r, mask) for m, f in frames.items()}
        out[case] = {
            "mean_shift": {m: mean_shift(f[case], r, regions) for m, f in frames.items()},
            "mean_shift_added": {m: mean_shift(f[case], f_lo[case], regions) for m, f in frames.items()},
            "error_ratio": {m: e / e16 for m, e in errs.items()},
            "rel_rmse": errs,
            "mean_error_estimate": estimate[case],
        }
    out.update(entries_ratio=entries, time_ratio=times, frame_s=t_frame, precompute_s=precompute_s)
    out["load"] = round(os.getloadavg()[0], 2)
    return out
