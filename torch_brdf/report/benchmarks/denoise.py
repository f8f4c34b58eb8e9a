"""Denoising precomputed basis images against a path tracer with a per-frame denoiser.

    python benchmarks/denoise.py [--quick] [--res 256] [--series 64,1,1,1] [--spp 16,64,256]
        [--hi-spp 1024] [--ref-spp 4096] [--figure docs/denoise_cornell.png] [--cache DIR]
        [--lobe-mixture | --stratified] [--scenes cornell,teatray] [--skip-spp 16,256] [--only-hi]
        [--edits-only]

For the glossy Cornell box (back wall Blinn-Phong n = 100; frozen object: the back wall) and
the teatray (glossy tray under sun and sky; frozen object: the tray), tensors of ``--series``
are precomputed at each ``--spp`` (with the view's guides, which the precomputation attaches),
frozen on the edited object and rendered by four methods:

* ``none``: the precomputed frame as is (also at ``--hi-spp`` as the mean of independent runs'
  frames at ``--hi-step`` spp, default the middle one, which is the higher-spp estimate: frames
  are linear in the tensors);
* ``linear``: the guide-only à-trous filter applied once to every basis image of the frozen
  tensor (``PolynomialRenderer.freeze(obj, denoiser="linear")``);
* ``oidn_basis``: Open Image Denoise once per grouped basis image (``denoiser="oidn"``);
* ``oidn_frame``: the path-tracer user's baseline: OIDN on every final frame;
* ``regression``: the guide-only local polynomial regression (:class:`RegressionFilter`, NFOR-
  style, linear) applied once to every basis image of the frozen tensor
  (``denoiser="regression"``). It is computed in its own cached part (the precompute is redone
  with the same seed, and its noisy frame is checked to equal the cached one), so runs cached
  before it existed are reused;
* ``selected``: the per-pixel choice among local regressions (:class:`SelectedRegressionFilter`,
  NFOR's selection, linear once picked): the spp is spent as two half-spp precomputations
  (other seeds), whose frames at the default material pick the window per pixel (and, on
  silhouette pixels, the along-edge mean, the along-edge fit in the pixels' coverage
  (:func:`pixel_coverage` at ``COVERAGE_SAMPLES`` x ``COVERAGE_SAMPLES`` rays; its
  seconds are in the pick's and in ``coverage_s``) or the pixel itself: :class:`SelectionSettings`);
  the mean record of both (:func:`mean_tensors`, the same spp) is frozen and denoised with it. With
  ``--stratified`` the halves are complementary shares of one stratification
  (``LobeMixture(share=(k, 2))``), so that mean samples as one stratified run does. Its own
  part (``halves``) also reports ``none`` and ``regression`` on that same mean record under
  ``same_samples`` ``{method: {spp: [default, edited]}}``, so the comparison holds the samples fixed;
* ``oidn_cumulative``: OIDN once per cumulative band sum of each term (:class:`CumulativeOIDN`:
  the prefix sums of a term's bands are box-lobe images OIDN can read; the bands are their
  differences again), the other records and silhouette pixels by ``selected``'s pick, on the
  same mean record of the halves (its own part ``cumulative``, reusing the half records cached
  as record files, which ``benchmarks/denoise_tune.py`` shares), with the class's default ``mix``
  (0: OIDN's share alone; the average with ``selected`` is no better);
  ``oidn_cumulative_mix_half`` ``{spp: [default, edited]}`` is that average (exact: the frame is
  linear in the denoised bases). The class keeps each denoised prefix sum's local mean
  (``keep_mean``) and divides each prefix sum of the frozen object by its area
  lights' noise-free light lobe (``lobes``: :func:`light_lobe_images`; its seconds
  are in ``denoise_s`` and ``lobes_s``); in the same part, ``oidn_cumulative_no_lobes`` and
  ``oidn_cumulative_raw`` (neither: the plain method) ``{spp: [default,
  edited]}`` (without an area light, as the teatray, ``no_lobes`` is ``oidn_cumulative`` itself).

Prints progress, then one JSON object as the last line: for the Cornell box at top level and
per scene under ``scenes``: ``rel_rmse`` / ``rel_rmse_edited`` / ``flip`` / ``flip_edited`` as
``{method: {spp: value}}`` (the hi spp only for ``none``) against a high-spp reference
(Mitsuba 3 llvm at ``--ref-spp`` when it runs here, else ``reference_path_trace`` with MIS),
pixels that see an emitter excluded; ``regions`` ``{region: {method: rel RMSE}}`` at the middle
spp where filters blur (``glossy``: pixels of banded objects; ``contact``: pixels within 3
pixels of another object at nearly the same depth, i.e. contact shadows; ``rest``);
``precompute_s`` ``{spp: s}``, ``denoise_s`` ``{method: {spp: s}}`` (freeze + denoise minus
freeze), ``frame_s_before`` (noisy frozen frame) and ``frame_s_after`` ``{method: s}`` (the
denoised frozen frame; for ``oidn_frame`` frame + OIDN) timed interleaved in one process,
``frame_ratio`` (after / before; figures, load-noisy at the ms scale), ``frozen_ratio``
(the denoised frozen tensor's stored size over the noisy one's of the same part: the frame's
cost, which the frame-time goal reads), ``mean_ratio`` ``{method: mean / reference mean}`` at the
middle spp, ``record_mb`` (sparse tensors) and ``frozen_mb`` ``{method: MB}``, ``goals``
(the denoising goals, each with its figures), ``budget`` (per region and material:
the hi-spp noise, the bias left at hi spp, the reference's own noise and each method's excess
over that bias; see :func:`_budget`), ``load`` (1-min load average at the
start and end of each part). Edited material: exponent 1000 and another colour, a material
the denoisers never saw (they see only guides and basis images).

``edits`` (also alone with ``--edits-only``): denoising under edits of one, two and all objects
of a generated scene (glossy floor, diffuse and glossy spheres, sky), the frame denoiser that keeps
each object's mean against the undenoised 16x-samples frame and the whole-record path; its keys
are in :mod:`torch_brdf.report.benchmarks.denoise_edits` (``--quick``: 32², series 8,1,1, 16 spp;
else 64², series 16,1,1).

Order: the middle spp's parts first, then the hi-spp runs, then the other spps from the smallest
up (``--skip-spp`` leaves some out), so a run cut short has cached what the goals need.
``--only-hi`` computes just the hi-spp runs, from the last: started beside a full run with the
same options, it shares that work (each skips the parts the other has cached).

Resumable: each part (a reference, a precompute at one spp and seed with its denoised frames)
is saved atomically under ``--cache`` (default ``$TORCH_BRDF_CACHE/benchmarks/denoise``), keyed
by its settings and the scene's content, so a rerun redoes only what is missing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from torch_brdf.data import cache_path
from torch_brdf.denoise import (
    KEEP_MEAN_SIGMA,
    CumulativeOIDN,
    EdgeAwareFilter,
    RegressionFilter,
    RegressionSettings,
    SelectedRegressionFilter,
    SelectionSettings,
    glossy_objects,
    guide_buffers,
    mean_tensors,
    oidn_frame,
    pixel_coverage,
)
from torch_brdf.metrics import hdr_flip, relative_rmse
from torch_brdf.records.cache import Checkpoint, settings_key
from torch_brdf.records.polynomial import PolynomialTensors
from torch_brdf.render.polynomial import PolynomialRenderer, emitter_mask
from torch_brdf.report.benchmarks.denoise_edits import run_edits
from torch_brdf.scene.builtin import cornell_box_glossy, teatray
from torch_brdf.transport.guides import light_lobe_images
from torch_brdf.transport.pathtrace import reference_path_trace
from torch_brdf.transport.polynomial import LobeMixture, PolynomialSettings, precompute_polynomial

METHODS = ("none", "linear", "oidn_basis", "oidn_frame", "regression", "selected", "oidn_cumulative")
DENOISERS = {"linear": "linear", "oidn_basis": "oidn"}
EXTRA = ("regression",)  # computed in the "extra" part
HALVES = ("selected",)  # computed in the "halves" part
CUMULATIVE = ("oidn_cumulative",)  # computed in the "cumulative" part
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
KIND = "benchmark-denoise"
#: extra precompute_polynomial options of every precompute (``--lobe-mixture``, ``--stratified``), and their key
PRECOMPUTE: dict = {}
PRECOMPUTE_KEY: dict = {}


def _half(k: int) -> tuple[dict, dict]:
    """The precompute options and key of half ``k`` of a halves part: under stratified eye
    samples the two halves are complementary shares of one stratification
    (``LobeMixture(share=(k, 2))``: their mean samples as one stratified full-spp run), else
    :data:`PRECOMPUTE` as it is."""
    mix = PRECOMPUTE.get("mixture")
    if mix is None or not mix.stratified:
        return PRECOMPUTE, PRECOMPUTE_KEY
    half = dataclasses.replace(mix, share=(k, 2))
    return {**PRECOMPUTE, "mixture": half}, {**PRECOMPUTE_KEY, "mixture": half.spec()}


def _shares() -> list[str]:
    """What the halves parts' keys add when their halves are complementary shares."""
    return ["complementary shares"] if _half(1)[0] is not PRECOMPUTE else []


#: subpixel rays per side of the pixel coverage the selecting filter's silhouette fits use
#: (:func:`pixel_coverage`)
COVERAGE_SAMPLES = 8


def _cov() -> str:
    return f"pixel coverage {COVERAGE_SAMPLES}"


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def _materials(scene):
    return {o.name: scene.materials[o.material] for o in scene.objects if o.editable}


def _cached(folder: Path, what: str, settings: dict, scene, compute):
    """(arrays {name: tensor}, meta) of one part: loaded when cached, else computed and saved."""
    key = settings_key({"what": what, **settings}, scene)
    ck = Checkpoint(folder / f"{scene.name}_{what}_{key}.npz", KIND, key, on_corrupt="recompute")
    hit = ck.load()
    if hit is not None:
        print(f"[{scene.name}] {what}: cached", flush=True)
        arrays, meta = hit
        return {k: torch.from_numpy(np.array(v)) for k, v in arrays.items()}, meta
    l0 = _load()
    arrays, meta = compute()
    meta = {**meta, "load": [l0, _load()]}
    ck.save({k: v.numpy() for k, v in arrays.items()}, meta)
    return arrays, meta


def _reference(scene, spp_mitsuba: int, spp_ours: int, bounces: int, seed: int = 7):
    """(image, label): Mitsuba llvm when it runs, else our MIS reference tracer."""
    try:
        from torch_brdf.transport import mitsuba as tm

        if tm.mitsuba_available() and tm.default_variant().startswith("llvm"):
            img = tm.render_mitsuba(scene, spp=spp_mitsuba, max_bounces=bounces, seed=seed)
            return img, f"mitsuba {tm.default_variant()} {spp_mitsuba} spp"
    except ImportError:
        pass
    img = reference_path_trace(scene, spp=spp_ours, max_bounces=bounces, seed=seed, progress=False)
    return img, f"reference_path_trace (MIS) {spp_ours} spp"


def _secs(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def _frames(R, obj, mats, edited):
    """(default-material frame, edited frame) of a renderer frozen on ``obj``."""
    R.set_material(obj, mats[obj])
    a = R()
    R.set_material(obj, edited)
    b = R()
    R.set_material(obj, mats[obj])
    return a, b


def _interleaved_frame_times(renderers: dict, obj: str, repeat: int = 7) -> dict:
    """Best-of-``repeat`` frozen-frame seconds per renderer, timed in turns (same load for all)."""
    best = dict.fromkeys(renderers, float("inf"))
    for _ in range(repeat):
        for k, R in renderers.items():
            assert R.frozen_object == obj, (R.frozen_object, obj)  # the interactive path
            best[k] = min(best[k], _secs(R)[1])
    return best


def _unit(scene, obj, mats, edited, series, spp, seed, full: bool, keep: dict | None = None):
    """One precompute at (spp, seed): its frames per method (only ``none`` unless ``full``);
    a full unit's record is left in ``keep["T"]`` for the extra part of the same run."""
    T, pre_s = _secs(
        lambda: precompute_polynomial(
            scene, PolynomialSettings(series, spp=spp, **PRECOMPUTE), seed=seed, progress=False
        )
    )
    if full and keep is not None:
        keep["T"] = T
    R = PolynomialRenderer(T, mats)
    _, freeze_s = _secs(lambda: R.freeze(obj))
    arrays = dict(zip(("none", "none_e"), _frames(R, obj, mats, edited), strict=True))
    meta = {"precompute_s": pre_s, "freeze_s": freeze_s, "spp": spp, "seed": seed}
    if not full:
        return arrays, meta
    meta["record_mb"] = sum(b.nbytes for b in T.blocks) / 2**20
    meta["glossy"] = glossy_objects(T)
    arrays["emitter_free"] = emitter_mask(T)
    g = T.guides
    arrays["object_id"], arrays["depth"] = g.object_id, torch.where(torch.isfinite(g.depth), g.depth, -1.0)
    renderers = {"none": R}
    meta["denoise_s"], meta["frozen_mb"] = {"none": 0.0}, {"none": R.frozen_nbytes / 2**20}
    for method, name in DENOISERS.items():
        print(f"[{scene.name}] {method} at {spp} spp ...", flush=True)
        D = PolynomialRenderer(T, mats)
        _, secs = _secs(lambda D=D, name=name: D.freeze(obj, denoiser=name))
        meta["denoise_s"][method] = max(secs - freeze_s, 0.0)
        meta["frozen_mb"][method] = D.frozen_nbytes / 2**20
        arrays[method], arrays[method + "_e"] = _frames(D, obj, mats, edited)
        renderers[method] = D
    (arrays["oidn_frame"], secs) = _secs(lambda: oidn_frame(arrays["none"], g))
    arrays["oidn_frame_e"] = oidn_frame(arrays["none_e"], g)
    meta["denoise_s"]["oidn_frame"] = secs  # per frame
    meta["frame_s"] = _interleaved_frame_times(renderers, obj)
    meta["frame_s"]["oidn_frame"] = meta["frame_s"]["none"] + secs
    return arrays, meta


def _extra_unit(scene, obj, mats, edited, series, spp, seed, noisy, T=None):
    """The ``EXTRA`` methods of one full unit: its record ``T`` when the unit was computed in
    this run, else the same precompute (seed) again; its frozen tensor denoised by each,
    frames, denoise seconds and frame seconds timed in turns with the noisy frozen frame of
    this run (the ratio's baseline)."""
    if T is None:
        T, pre_s = _secs(
            lambda: precompute_polynomial(
                scene, PolynomialSettings(series, spp=spp, **PRECOMPUTE), seed=seed, progress=False
            )
        )
    else:
        pre_s = 0.0  # reused: same_as_cached_unit is then 0 by construction
    R = PolynomialRenderer(T, mats)
    _, freeze_s = _secs(lambda: R.freeze(obj))
    frame = _frames(R, obj, mats, edited)[0]
    same = float((frame - noisy).abs().max() / noisy.abs().max().clamp_min(1e-30))
    meta = {"precompute_s": pre_s, "freeze_s": freeze_s, "same_as_cached_unit": same, "denoise_s": {}}
    arrays, renderers = {}, {"none": R}
    for method in EXTRA:
        print(f"[{scene.name}] {method} at {spp} spp ...", flush=True)
        D = PolynomialRenderer(T, mats)
        A = RegressionFilter.for_tensors(T)
        _, secs = _secs(lambda D=D, A=A: D.freeze(obj, denoiser=A))
        meta["denoise_s"][method] = max(secs - freeze_s, 0.0)
        meta["settings_" + method] = A.description
        arrays[method], arrays[method + "_e"] = _frames(D, obj, mats, edited)
        renderers[method] = D
    meta["frozen_mb"] = {k: D.frozen_nbytes / 2**20 for k, D in renderers.items()}
    meta["frame_s"] = _interleaved_frame_times(renderers, obj)
    return arrays, meta


def _halves_unit(scene, obj, mats, edited, series, spp, seed):
    """``selected`` at ``spp``: two precomputations at spp / 2 (seeds 1000 + 2 seed and the
    next), the filter picked from their default-material frames, their mean record frozen and
    denoised with it; also ``none`` and ``regression`` of that mean record (``*_h``), the
    halves' frames (``half_a``, ``half_b``: to rebuild the filter) and frame seconds timed in
    turns with the mean record's noisy frozen frame."""
    halves, secs = [], 0.0
    for k in range(2):
        T, t = _secs(
            lambda k=k: precompute_polynomial(
                scene, PolynomialSettings(series, spp=spp // 2, **_half(k)[0]), seed=1000 + 2 * seed + k, progress=False
            )
        )
        halves.append(T)
        secs += t
    pilots = [PolynomialRenderer(T, mats).evaluate() for T in halves]
    T = mean_tensors(halves)
    gl = glossy_objects(T)
    cov, cov_s = _secs(lambda: pixel_coverage(scene, COVERAGE_SAMPLES, T.guides.object_id))
    A, pick_s = _secs(
        lambda: SelectedRegressionFilter(T.guides, [tuple(p.permute(2, 0, 1) for p in pilots)], glossy=gl, coverage=cov)
    )
    pick_s += cov_s
    arrays = {"half_a": pilots[0], "half_b": pilots[1]}
    meta = {"precompute_s": secs, "pick_s": pick_s, "coverage_s": cov_s, "settings_selected": A.description}
    meta["denoise_s"] = {}
    R = PolynomialRenderer(T, mats)
    _, freeze_s = _secs(lambda: R.freeze(obj))
    arrays["none_h"], arrays["none_h_e"] = _frames(R, obj, mats, edited)
    renderers = {"none": R}
    for method, den in (("selected", A), ("regression_h", RegressionFilter.for_tensors(T))):
        print(f"[{scene.name}] {method} at {spp} spp ...", flush=True)
        D = PolynomialRenderer(T, mats)
        _, secs = _secs(lambda D=D, den=den: D.freeze(obj, denoiser=den))
        meta["denoise_s"][method] = max(secs - freeze_s, 0.0) + (pick_s if method == "selected" else 0.0)
        arrays[method], arrays[method + "_e"] = _frames(D, obj, mats, edited)
        renderers[method] = D
    meta["frozen_mb"] = {k: D.frozen_nbytes / 2**20 for k, D in renderers.items()}
    meta["frame_s"] = _interleaved_frame_times(renderers, obj)
    return arrays, meta


def half_records(scene, series: str, spp: int, seed: int, folder: Path) -> list:
    """The two half-spp records of the ``halves`` part at ``spp`` (the same seeds, so the same
    records), each cached as a record file under ``folder``."""
    out = []
    for k in range(2):
        s = {"what": "half_record", "series": series, "spp": spp // 2, "seed": 1000 + 2 * seed + k, **_half(k)[1]}
        key = settings_key(s, scene)
        ck = Checkpoint(folder / f"{scene.name}_half_record_{key}.npz", KIND, key, on_corrupt="recompute")
        T = ck.load_record(PolynomialTensors)
        if T is None:
            print(f"[{scene.name}] half record {k} at {spp // 2} spp (load {_load()}) ...", flush=True)
            T = precompute_polynomial(
                scene, PolynomialSettings(series, spp=spp // 2, **_half(k)[0]), seed=s["seed"], progress=False
            )
            ck.save_record(T)
        else:
            print(f"[{scene.name}] half record {k}: cached", flush=True)
        out.append(T)
    return out


def _cumulative_unit(scene, obj, mats, edited, series, spp, seed, h, folder):
    """``oidn_cumulative`` at ``spp``: the mean record of the halves (:func:`half_records`)
    frozen and denoised with :class:`CumulativeOIDN` over ``selected``'s pick (rebuilt from
    the ``halves`` part's frames ``h``); its ``none`` frame is checked against that part's."""
    T = mean_tensors(half_records(scene, series, spp, seed, folder))
    gl = glossy_objects(T)
    pilots = [(h["half_a"].permute(2, 0, 1), h["half_b"].permute(2, 0, 1))]
    cov, cov_s = _secs(lambda: pixel_coverage(scene, COVERAGE_SAMPLES, T.guides.object_id))
    A, pick_s = _secs(lambda: SelectedRegressionFilter(T.guides, pilots, glossy=gl, coverage=cov))
    pick_s += cov_s
    R = PolynomialRenderer(T, mats)
    _, freeze_s = _secs(lambda: R.freeze(obj))
    noisy = _frames(R, obj, mats, edited)
    same = max(
        float((a - b).abs().max() / b.abs().max()) for a, b in zip(noisy, (h["none_h"], h["none_h_e"]), strict=True)
    )
    print(f"[{scene.name}] oidn_cumulative at {spp} spp ...", flush=True)
    lobes, lobes_s = _secs(lambda: light_lobe_images(scene, T.bases[T.object_id(obj)], obj))
    D = PolynomialRenderer(T, mats)
    den = CumulativeOIDN(T.guides, A, lobes=lobes)  # the class's defaults (mix 0, keep_mean)
    _, secs = _secs(lambda: D.freeze(obj, denoiser=den))
    arrays = dict(zip(("oidn_cumulative", "oidn_cumulative_e"), _frames(D, obj, mats, edited), strict=True))
    # the same without the light lobes (none without an area light: the same frames) and without both
    variants = {"oidn_cumulative_raw": {"keep_mean": 0}}
    if lobes is not None:
        variants["oidn_cumulative_no_lobes"] = {}
    for key, kw in variants.items():
        print(f"[{scene.name}] {key} at {spp} spp ...", flush=True)
        V = PolynomialRenderer(T, mats)
        V.freeze(obj, denoiser=CumulativeOIDN(T.guides, A, **kw))
        arrays[key], arrays[key + "_e"] = _frames(V, obj, mats, edited)
    if lobes is None:
        arrays["oidn_cumulative_no_lobes"], arrays["oidn_cumulative_no_lobes_e"] = (
            arrays["oidn_cumulative"],
            arrays["oidn_cumulative_e"],
        )
    # the frames are linear in the denoised bases: the average with selected (mix 1/2)
    for suf in ("", "_e"):
        arrays["oidn_cumulative_mix_half" + suf] = (arrays["oidn_cumulative" + suf] + h["selected" + suf]) / 2
    meta = {
        "denoise_s": {"oidn_cumulative": max(secs - freeze_s, 0.0) + pick_s + lobes_s},
        "lobes_s": lobes_s,
        "oidn_calls": den.calls,
        "settings_oidn_cumulative": den.description,
        "same_as_halves_part": same,
        "frozen_mb": {"none": R.frozen_nbytes / 2**20, "oidn_cumulative": D.frozen_nbytes / 2**20},
        "frame_s": _interleaved_frame_times({"none": R, "oidn_cumulative": D}, obj),
    }
    return arrays, meta


def _regions(object_id: torch.Tensor, depth: torch.Tensor, glossy: list[int], mask: torch.Tensor, radius: int = 3):
    """(H, W) bool masks where a filter can blur: glossy objects' pixels, contact regions
    (within ``radius`` pixels of another object at a depth within 3%) and the rest."""
    h, w = object_id.shape
    contact = torch.zeros(h, w, dtype=torch.bool)
    oid = torch.nn.functional.pad(object_id[None, None].double(), (radius,) * 4, value=-5.0)[0, 0]
    dep = torch.nn.functional.pad(depth[None, None].double(), (radius,) * 4, value=-1.0)[0, 0]
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            o = oid[radius + dy : radius + dy + h, radius + dx : radius + dx + w]
            d = dep[radius + dy : radius + dy + h, radius + dx : radius + dx + w]
            near = (d > 0) & (depth > 0) & ((d - depth).abs() < 0.03 * depth)
            contact |= (o >= 0) & (o != object_id) & near
    contact &= (object_id >= 0) & mask
    gl = torch.isin(object_id, torch.tensor(glossy, dtype=torch.long)) & mask & ~contact
    return {"glossy": gl, "contact": contact, "rest": mask & ~gl & ~contact & (object_id >= 0)}


@dataclasses.dataclass
class _SceneRun:
    """One scene's run: its settings, scenes (default and edited material), references and
    the figures gathered so far (``out``)."""

    name: str
    cfg: dict
    folder: Path
    obj: str
    edited: dict
    bounces: int
    scene: object
    mats: dict
    ref: torch.Tensor
    ref_e: torch.Tensor
    out: dict


def _start_scene(name: str, cfg: dict, folder: Path) -> _SceneRun:
    """The scene's references (cached) and its figures' skeleton."""
    build, obj, edited = SCENES[name]
    res, series = cfg["res"], cfg["series"]
    bounces = len(series.split(","))
    scene = build(res)
    mats = _materials(scene)
    scene_edit = build(res)
    scene_edit.materials[scene_edit.objects[scene_edit.object_id(obj)].material] = dict(edited)

    def reference():
        print(f"[{name}] references ...", flush=True)
        (a, label), secs = _secs(lambda: _reference(scene, cfg["ref_spp"], cfg["ref_spp_ours"], bounces))
        b, _ = _reference(scene_edit, cfg["ref_spp"], cfg["ref_spp_ours"], bounces)
        return {"ref": a, "ref_e": b}, {"label": label, "seconds": secs}

    refs, rmeta = _cached(
        folder, "reference", {"ref_spp": cfg["ref_spp"], "edited": edited, "b": bounces}, scene, reference
    )
    out: dict = {
        "resolution": res,
        "series": series,
        "reference": rmeta["label"],
        "reference_s": rmeta["seconds"],
        "edited_material": edited,
        "frozen_object": obj,
        "load": {"reference": rmeta["load"]},
    }
    for k in ("rel_rmse", "rel_rmse_edited", "flip", "flip_edited", "denoise_s"):
        out[k] = {m: {} for m in METHODS}
    for k in ("precompute_s", "frame_s_after", "frame_ratio", "frozen_ratio", "mean_ratio", "frozen_mb"):
        out[k] = {}
    return _SceneRun(name, cfg, folder, obj, edited, bounces, scene, mats, refs["ref"], refs["ref_e"], out)


def _run_order(cfg: dict) -> list[tuple[int, int]]:
    """The (spp, seed) precomputes in the order they run."""
    spps, mid, step = cfg["spp"], str(cfg["mid"]), cfg["hi_step"]
    runs = [(spp, k) for k, spp in enumerate(spps)]
    runs += [(step, len(spps) + k) for k in range(cfg["hi_spp"] // step - 1)]  # seeds for the hi-spp mean
    # what the goals need first (the middle spp's full unit, then the hi-spp runs), then the
    # other full units from the smallest spp up, so a run cut short leaves the parts that
    # matter cached; the seeds stay the positions in the full list (cached parts are reused)
    runs.sort(key=lambda r: (0 if str(r[0]) == mid and r[1] < len(spps) else 1 if r[1] >= len(spps) else 2, r[0]))
    return [r for r in runs if r[0] not in cfg["skip"]]


def _unit_settings(s: _SceneRun, spp: int, seed: int, full: bool) -> dict:
    settings = {"series": s.cfg["series"], "spp": spp, "seed": seed, "edited": s.edited, "obj": s.obj, "full": full}
    settings.update(PRECOMPUTE_KEY)
    return settings


def _only_hi(s: _SceneRun, runs: list[tuple[int, int]]) -> None:
    """A second process beside a full run: the hi-spp runs from the last."""
    for spp, seed in reversed([r for r in runs if r[1] >= len(s.cfg["spp"])]):
        print(f"[{s.name}] precompute {spp} spp seed {seed} (load {_load()}) ...", flush=True)
        _cached(
            s.folder,
            "unit",
            _unit_settings(s, spp, seed, False),
            s.scene,
            lambda sp=spp, k=seed: _unit(s.scene, s.obj, s.mats, s.edited, s.cfg["series"], sp, k, False),
        )


def _other_parts(s: _SceneRun, settings: dict, a: dict, keep: dict) -> tuple:
    """A full unit's extra, halves and cumulative parts (cached): (x, xmeta, h, hmeta, c, cmeta)."""
    scene, obj, mats, edited, series = s.scene, s.obj, s.mats, s.edited, s.cfg["series"]
    spp, seed = settings["spp"], settings["seed"]
    x, xmeta = _cached(
        s.folder,
        "extra",
        {**settings, "methods": [RegressionFilter.__name__, repr(RegressionSettings())]},
        scene,
        lambda: _extra_unit(scene, obj, mats, edited, series, spp, seed, a["none"], keep.pop("T", None)),
    )
    keep.clear()
    h, hmeta = _cached(
        s.folder,
        "halves",
        {**settings, "methods": [SelectedRegressionFilter.__name__, repr(SelectionSettings()), *_shares(), _cov()]},
        scene,
        lambda: _halves_unit(scene, obj, mats, edited, series, spp, seed),
    )
    c, cmeta = _cached(
        s.folder,
        "cumulative",
        {
            **settings,
            "methods": [CumulativeOIDN.__name__, "default mix", SelectedRegressionFilter.__name__]
            + [repr(SelectionSettings()), f"keep_mean {KEEP_MEAN_SIGMA}", "light lobes 16", *_shares(), _cov()],
        },
        scene,
        lambda: _cumulative_unit(scene, obj, mats, edited, series, spp, seed, h, s.folder),
    )
    return x, xmeta, h, hmeta, c, cmeta


def _record_parts(s: _SceneRun, spp: int, seed: int, a: dict, parts: tuple) -> None:
    """The other parts' own figures at ``spp``: loads, the cumulative variants, same samples."""
    out, ref, ref_e = s.out, s.ref, s.ref_e
    _, xmeta, h, hmeta, c, cmeta = parts
    out["load"][f"{spp}_{seed}_extra"] = xmeta["load"]
    out["load"][f"{spp}_{seed}_halves"] = hmeta["load"]
    out["load"][f"{spp}_{seed}_cumulative"] = cmeta["load"]
    out.setdefault("cumulative_same_as_halves", {})[str(spp)] = cmeta["same_as_halves_part"]
    out.setdefault("lobes_s", {})[str(spp)] = cmeta["lobes_s"]
    for key in ("oidn_cumulative_mix_half", "oidn_cumulative_raw", "oidn_cumulative_no_lobes"):
        out.setdefault(key, {})[str(spp)] = [
            relative_rmse(c[key], ref, a["emitter_free"].bool()),
            relative_rmse(c[key + "_e"], ref_e, a["emitter_free"].bool()),
        ]
    for m in ("none", "regression", "selected"):
        k = m if m == "selected" else m + "_h"
        pair = [
            relative_rmse(h[k], ref, a["emitter_free"].bool()),
            relative_rmse(h[k + "_e"], ref_e, a["emitter_free"].bool()),
        ]
        out.setdefault("same_samples", {}).setdefault(m, {})[str(spp)] = pair
    out.setdefault("extra_same_as_cached_unit", {})[str(spp)] = xmeta["same_as_cached_unit"]


def _record_methods(s: _SceneRun, key: str, a: dict, meta: dict, mask: torch.Tensor) -> None:
    """Every method's errors and denoise seconds at spp ``key``."""
    out = s.out
    out["precompute_s"][key] = meta["precompute_s"]
    for m in METHODS:
        img, img_e = a[m], a[m + "_e"]
        out["rel_rmse"][m][key] = relative_rmse(img, s.ref, mask)
        out["rel_rmse_edited"][m][key] = relative_rmse(img_e, s.ref_e, mask)
        out["flip"][m][key] = hdr_flip(img, s.ref, mask)
        out["flip_edited"][m][key] = hdr_flip(img_e, s.ref_e, mask)
        out["denoise_s"][m][key] = meta["denoise_s"][m]


def _record_mid(s: _SceneRun, a: dict, meta: dict, parts: tuple, mask: torch.Tensor, figure: str | None) -> dict:
    """The middle spp's figures (sizes, frame times, means, regions; the figure): returns the regions."""
    out, ref, ref_e = s.out, s.ref, s.ref_e
    _, xmeta, _, hmeta, _, cmeta = parts
    out["record_mb"] = meta["record_mb"]
    out["frozen_mb"] = {**meta["frozen_mb"], **{m: xmeta["frozen_mb"][m] for m in EXTRA}}
    out["frozen_mb"]["selected"] = hmeta["frozen_mb"]["selected"]
    out["frozen_mb"]["oidn_cumulative"] = cmeta["frozen_mb"]["oidn_cumulative"]
    out["regression_settings"] = xmeta["settings_regression"]
    out["selected_settings"] = hmeta["settings_selected"]
    out["selected_pick_s"] = hmeta["pick_s"]
    out["coverage_s"] = hmeta["coverage_s"]
    out["frame_s_before"] = meta["frame_s"]["none"]
    part_of = {**dict.fromkeys(EXTRA, xmeta), **dict.fromkeys(HALVES, hmeta), **dict.fromkeys(CUMULATIVE, cmeta)}
    for m in METHODS:
        fs = part_of.get(m, meta)["frame_s"]
        # ratio to the same run's noisy frame
        out["frame_s_after"][m] = fs[m]
        out["frame_ratio"][m] = fs[m] / fs["none"]
        out["mean_ratio"][m] = float(a[m][mask].double().mean() / ref[mask].double().mean())
    for m in ("none", *DENOISERS, *EXTRA, *HALVES, *CUMULATIVE):
        # the frame's cost is its frozen tensor's size (same pixels, same matmuls): the
        # goal reads this ratio; the timings above are figures (load-noisy at ms scale)
        part = part_of.get(m, meta)
        out["frozen_ratio"][m] = part["frozen_mb"][m] / part["frozen_mb"]["none"]
    regions = _regions(a["object_id"].long(), a["depth"], meta["glossy"], mask)
    out["region_pixels"] = {r: int(v.sum()) for r, v in regions.items()}
    out["regions"] = {r: {m: relative_rmse(a[m], ref, v) for m in METHODS} for r, v in regions.items() if int(v.sum())}
    out["regions_edited"] = {
        r: {m: relative_rmse(a[m + "_e"], ref_e, v) for m in METHODS} for r, v in regions.items() if int(v.sum())
    }
    if figure:
        _figure(
            figure, ref, *(a[m] for m in ("none", "linear", "oidn_basis", "regression", "selected", "oidn_cumulative"))
        )
    return regions


def _finish(s: _SceneRun, hi: dict, mask, at_mid: dict, mid_meta: dict, regions: dict) -> None:
    """Sorted tables, the hi-spp figures, the goals and the error budget."""
    out, ref, ref_e, cfg = s.out, s.ref, s.ref_e, s.cfg
    for k in ("rel_rmse", "rel_rmse_edited", "flip", "flip_edited", "denoise_s", "same_samples"):
        out[k] = {m: dict(sorted(d.items(), key=lambda kv: int(kv[0]))) for m, d in out.get(k, {}).items()}
    out["precompute_s"] = dict(sorted(out["precompute_s"].items(), key=lambda kv: int(kv[0])))
    top = str(cfg["hi_spp"])
    a, b = torch.stack(hi["none"]).mean(0), torch.stack(hi["none_e"]).mean(0)
    out["rel_rmse"]["none"][top] = relative_rmse(a, ref, mask)
    out["rel_rmse_edited"]["none"][top] = relative_rmse(b, ref_e, mask)
    out["flip"]["none"][top] = hdr_flip(a, ref, mask)
    out["flip_edited"]["none"][top] = hdr_flip(b, ref_e, mask)
    out["goals"] = _goals(out, str(cfg["mid"]), top)

    def check():  # a second, independent reference at a quarter of the spp: the reference's own noise
        img, label = _reference(s.scene, cfg["ref_spp"] // 4, cfg["ref_spp_ours"] // 4, s.bounces, seed=8)
        return {"ref": img}, {"label": label}

    second, _ = _cached(s.folder, "reference_check", {"ref_spp": cfg["ref_spp"], "b": s.bounces}, s.scene, check)
    g, gl = guide_buffers(s.scene), mid_meta["glossy"]
    filters = {"linear": EdgeAwareFilter(g, glossy=gl), "regression": RegressionFilter(g, glossy=gl)}
    pilots = (at_mid["half_a"].permute(2, 0, 1), at_mid["half_b"].permute(2, 0, 1))
    cov = pixel_coverage(s.scene, COVERAGE_SAMPLES, g.object_id)
    filters["selected"] = SelectedRegressionFilter(g, [pilots], glossy=gl, coverage=cov)  # the mid unit's pick
    out["budget"] = _budget(hi, at_mid, ref, ref_e, second["ref"], regions, mask, filters)


def run_scene(name: str, cfg: dict, folder: Path, figure: str | None) -> dict:
    s = _start_scene(name, cfg, folder)
    out, spps, mid, step = s.out, cfg["spp"], str(cfg["mid"]), cfg["hi_step"]
    runs = _run_order(cfg)
    if cfg["only_hi"]:
        _only_hi(s, runs)
        return out
    hi = {"none": [], "none_e": []}
    mask = None
    keep: dict = {}
    for spp, seed in runs:
        full = seed < len(spps)
        print(f"[{name}] precompute {spp} spp seed {seed} (load {_load()}) ...", flush=True)
        settings = _unit_settings(s, spp, seed, full)
        keep.clear()
        a, meta = _cached(
            folder,
            "unit",
            settings,
            s.scene,
            lambda spp=spp, seed=seed, full=full: _unit(
                s.scene, s.obj, s.mats, s.edited, cfg["series"], spp, seed, full, keep
            ),
        )
        out["load"][f"{spp}_{seed}"] = meta["load"]
        if spp == step:
            hi["none"].append(a["none"])
            hi["none_e"].append(a["none_e"])
        if not full:
            continue
        parts = _other_parts(s, settings, a, keep)
        x, xmeta, h, hmeta, c, cmeta = parts
        a = {**a, **x, **h, **c}
        _record_parts(s, spp, seed, a, parts)
        meta["denoise_s"] = {
            **meta["denoise_s"],
            **xmeta["denoise_s"],
            "selected": hmeta["denoise_s"]["selected"],
            **cmeta["denoise_s"],
        }
        key = str(spp)
        mask = a["emitter_free"].bool()
        _record_methods(s, key, a, meta, mask)
        if key == mid:
            at_mid, mid_meta = a, meta
            regions = _record_mid(s, a, meta, parts, mask, figure)
        print(f"[{name}] {spp} spp rel_rmse", {m: round(out["rel_rmse"][m][key], 4) for m in METHODS}, flush=True)
    _finish(s, hi, mask, at_mid, mid_meta, regions)
    return out


def _budget(hi, at_mid, ref, ref_e, second_ref, regions, mask, filters) -> dict:
    """Where each method's error at the middle spp comes from, per region and material, as
    relative RMS figures (squares add): ``noise_hi`` (the hi-spp mean's noise, from the spread
    of its independent runs), ``bias_hi`` (what is left of the hi-spp error: the series' and
    model's bias plus the reference's noise), ``ref_noise`` (the reference's own noise, from a
    second reference at a quarter of the spp and another seed; default material), ``excess``
    ``{method: sqrt(err^2 - bias_hi^2)}`` (what a denoiser adds or leaves: residual noise and
    blur; the goal needs it <= noise_hi) and ``blur_le`` ``{linear filter: |A m - m|}`` on the
    hi-spp mean m (an upper bound of the filter's blur: it includes the part of m's noise the
    filter removes)."""
    out = {}
    regions = {**regions, "all": mask}
    for suf, r_img in (("", ref), ("_e", ref_e)):
        runs = torch.stack(hi["none" + suf]).double()
        m, var = runs.mean(0), runs.var(0) / runs.shape[0]
        rd = r_img.double()
        for name, v in regions.items():
            if not int(v.sum()):
                continue
            r2 = float((rd**2)[v].sum())
            noise2 = float(var[v].sum()) / r2
            bias2 = float(((m - rd) ** 2)[v].sum()) / r2 - noise2
            row = {"noise_hi": noise2**0.5, "bias_hi": max(bias2, 0.0) ** 0.5, "excess": {}, "blur_le": {}}
            if not suf:
                # E|second - ref|^2 = s2 (1/n + 4/n): the reference's noise^2 s2/n is a fifth of it
                row["ref_noise"] = (float(((second_ref.double() - rd) ** 2)[v].sum()) / 5 / r2) ** 0.5
            for meth in METHODS:
                e2 = float(((at_mid[meth + suf].double() - rd) ** 2)[v].sum()) / r2
                row["excess"][meth] = max(e2 - max(bias2, 0.0), 0.0) ** 0.5
            for meth, A in filters.items():
                am = A(m.permute(2, 0, 1)).permute(1, 2, 0)
                row["blur_le"][meth] = (float(((am - m) ** 2)[v].sum()) / r2) ** 0.5
            out[name + suf] = row
    return out


def _goals(out: dict, mid: str, top: str) -> dict:
    """The denoising goals per method at the middle spp, each with its figures."""
    goals = {}
    for m in ("linear", "oidn_basis", "regression", "selected", "oidn_cumulative"):
        e, e_e = out["rel_rmse"][m][mid], out["rel_rmse_edited"][m][mid]
        n, n_e = out["rel_rmse"]["none"][top], out["rel_rmse_edited"]["none"][top]
        goals[m] = {
            f"error_at_{mid}_le_none_at_{top}": bool(e <= n and e_e <= n_e),
            "errors": [e, n, e_e, n_e],
            "frame_ratio_le_1.1": bool(out["frozen_ratio"][m] <= 1.1),  # stored sizes, not timings
            "frame_ratio_timed": out["frame_ratio"][m],
            "mean_within_1pct": bool(abs(out["mean_ratio"][m] - 1) <= 0.01),
        }
    return goals


def _figure(path: str, ref, *frames) -> None:
    """the frames (noisy | linear | oidn_basis | regression | selected | oidn_cumulative) and the
    reference side by side (exposure from the reference)."""
    from torch_brdf.io.png import write_png

    strip = torch.cat([*frames, ref], 1)
    exposure = -float(np.log2(max(float(ref.quantile(0.99)), 1e-6)))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_png(path, strip, exposure=exposure, tonemap="clip")


def _scene_names(arg: str) -> list[str]:
    """The ``--scenes`` list with each entry a scene name or a unique prefix of one
    (``cornell`` -> ``cornell_box_glossy``)."""
    names = []
    for part in arg.split(","):
        hits = [n for n in SCENES if n == part] or [n for n in SCENES if n.startswith(part)]
        if len(hits) != 1:
            raise SystemExit(f"--scenes: {part!r} names none or several of {', '.join(SCENES)}")
        names.append(hits[0])
    return names


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a smoke run: 48x48, series 16,1,1, spp 4,16, hi 64")
    ap.add_argument("--res", type=int, default=256, help="image width and height")
    ap.add_argument("--series", default="64,1,1,1", help="BRDF series (its length: bounces)")
    ap.add_argument("--spp", default="16,64,256", help="precomputation spp (the middle one: goals, figure)")
    ap.add_argument("--hi-spp", type=int, default=1024, help="undenoised comparison (a multiple of --hi-step)")
    ap.add_argument(
        "--hi-step",
        type=int,
        default=None,
        help="spp of the independent runs whose mean is the --hi-spp frame (one of --spp; default the middle: "
        "sixteen 64-spp runs keep the peak memory of a 64-spp precompute)",
    )
    ap.add_argument("--ref-spp", type=int, default=4096, help="Mitsuba reference spp")
    ap.add_argument(
        "--figure",
        default=None,
        help="PNG: noisy | linear | oidn_basis | regression | selected | oidn_cumulative | reference (Cornell)",
    )
    ap.add_argument(
        "--skip-spp",
        default="",
        help="comma-separated spps of --spp whose parts are not computed (not the middle or --hi-step; "
        "the seeds of the others stay, so cached parts are reused)",
    )
    ap.add_argument(
        "--only-hi",
        action="store_true",
        help="compute only the hi-spp runs, from the last (a second process beside a full run; no JSON)",
    )
    ap.add_argument("--scenes", default=",".join(SCENES), help="comma-separated subset of " + ",".join(SCENES))
    ap.add_argument(
        "--lobe-mixture",
        action="store_true",
        help="precompute with LobeMixture() (a defensive mixture of lobe widths and MIS on the glossy objects); "
        "every precompute, the hi-spp runs included",
    )
    ap.add_argument(
        "--stratified",
        action="store_true",
        help="precompute with LobeMixture(stratified=True): --lobe-mixture with the eye vertex's light and mixture "
        "samples stratified over each pixel's paths (EyeStrata)",
    )
    ap.add_argument("--cache", default=None, help="parts cache (default $TORCH_BRDF_CACHE/benchmarks/denoise)")
    ap.add_argument(
        "--edits-only",
        action="store_true",
        help="run only the edits part (denoise_edits: one, two and all objects edited on a generated scene)",
    )
    args = ap.parse_args()
    edits_cfg = (
        {"size": 32, "spp": 16, "series": "8,1,1", "ref": 64}
        if args.quick
        else {"size": 64, "spp": 16, "series": "16,1,1", "ref": 256}
    )
    if args.edits_only:
        result = {"quick": args.quick, "load_start": _load(), "edits": run_edits(**edits_cfg)}
        result["load_end"] = _load()
        print(json.dumps(result))
        return
    if args.quick:
        args.res, args.series, args.spp, args.hi_spp, args.ref_spp = 48, "16,1,1", "4,16", 64, 512
    spps = [int(s) for s in args.spp.split(",")]
    mid = spps[len(spps) // 2] if len(spps) > 2 else spps[-1]
    step = mid if args.hi_step is None else args.hi_step
    if step not in spps or args.hi_spp % step or args.hi_spp <= step:
        raise SystemExit(f"--hi-step: {step} must be one of --spp and divide --hi-spp ({args.hi_spp}) at least twice")
    skip = [int(x) for x in args.skip_spp.split(",") if x]
    if not set(skip) <= set(spps) - {mid, step}:
        raise SystemExit(f"--skip-spp: {skip} must be spps of --spp other than the middle ({mid}) and --hi-step")
    cfg = {
        "skip": skip,
        "only_hi": args.only_hi,
        "hi_step": step,
        "res": args.res,
        "series": args.series,
        "spp": spps,
        "mid": mid,
        "hi_spp": args.hi_spp,
        "ref_spp": args.ref_spp,
        "ref_spp_ours": max(64, args.ref_spp // 8),
    }
    if args.lobe_mixture or args.stratified:
        mix = LobeMixture(stratified=args.stratified)
        PRECOMPUTE["mixture"] = mix
        PRECOMPUTE_KEY["mixture"] = mix.spec()  # absent for the default (cached parts stay)
    cfg["lobe_mixture"] = args.lobe_mixture or args.stratified
    cfg["stratified"] = args.stratified
    folder = Path(args.cache) if args.cache else cache_path("benchmarks", "denoise")
    result: dict = {"quick": args.quick, "settings": cfg, "load_start": _load(), "scenes": {}}
    t0 = time.perf_counter()
    for name in _scene_names(args.scenes):
        result["scenes"][name] = run_scene(name, cfg, folder, args.figure if name == "cornell_box_glossy" else None)
    if args.only_hi:
        return
    print("[edits] one, two and all objects edited", flush=True)
    result["edits"] = run_edits(**edits_cfg)
    result["load_end"], result["seconds"] = _load(), time.perf_counter() - t0
    first = result["scenes"].get("cornell_box_glossy") or next(iter(result["scenes"].values()))
    result.update({k: v for k, v in first.items() if k not in ("edited_material",)})
    print(json.dumps(result))


if __name__ == "__main__":
    main()
