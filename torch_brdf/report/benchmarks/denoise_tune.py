"""Tune the linear guide-only filters on the cached frames of ``benchmarks/denoise.py``.

    python benchmarks/denoise_tune.py [the same size options as denoise.py] [--filters linear,regression]

Each filter A (``linear``: the à-trous :class:`AtrousSettings` grid; ``regression``: the
local polynomial :class:`RegressionSettings` grid) is linear and the emission term is zero
where the errors are measured, so the frame of the linear-denoised frozen tensor equals A
applied to the noisy frame (checked here against the cached ``linear`` frame). That makes a
grid cheap:
each setting is chosen on the lowest-spp run with the default material (seed 0) and reported
at the middle spp (another seed) on the default and the edited material, which it never saw.
Run ``denoise.py`` first (same options), or pass ``--build`` (implied by ``--quick``, the
report's run): parts not cached are then made by running ``denoise.py`` with these options for
that scene. ``--quick``: ``denoise.py --quick``'s sizes (48², series 16,1,1, spp 4,16, hi 64,
reference 512). Prints one JSON object.

``--edit-robust`` reports only :func:`edit_robust`: the selection's pick from pilots at probe
materials and per band group, beside the benchmark's pick, on the same half records.

``--bound`` adds ``selection_bound``: how low *any* per-pixel choice among the local
regressions of :class:`SelectionSettings` (and the identity) could take the middle-spp error.
Each pixel takes the candidate whose squared error against the hi-spp mean (four runs at the
largest spp, the same ones ``denoise.py`` averages), box-smoothed over ``smooth`` pixels, is
lowest: an oracle no real selection (which sees only the noisy frame) can beat by much. Reported
beside each candidate's own error and the hi-spp undenoised error (the goal).
"""

from __future__ import annotations

import argparse
import itertools
import json
import subprocess
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

from torch_brdf.data import cache_path
from torch_brdf.denoise import (
    AtrousSettings,
    EdgeAwareFilter,
    RegressionFilter,
    RegressionSettings,
    SelectedRegressionFilter,
    SelectionSettings,
    guide_buffers,
    mean_tensors,
)
from torch_brdf.metrics import relative_rmse
from torch_brdf.render.polynomial import PolynomialRenderer

from .denoise import SCENES, _cached, _load, _materials
from .denoise import half_records as _half_records

INF = float("inf")
#: The probe materials of the edit-robust pick (chosen before any test, not the benchmark's
#: edit): Blinn-Phong exponents 10^(1 + 0.75 k), k = 0..4 (10, 56, 316, 1778, 10000), each with
#: a small diffuse part and a specular colour from a fixed cycle, plus one diffuse probe.
PROBE_COLOURS = ((0.7, 0.7, 0.7), (0.8, 0.5, 0.3), (0.3, 0.5, 0.8), (0.5, 0.8, 0.4), (0.6, 0.6, 0.8))
PROBES = tuple(
    {"type": "blinn_phong", "kd": 0.1, "ks": PROBE_COLOURS[k], "exponent": round(10 ** (1 + 0.75 * k), 1)}
    for k in range(5)
) + ({"type": "blinn_phong", "kd": (0.6, 0.55, 0.5), "ks": 0.02, "exponent": 10.0},)
GRIDS = {
    "linear": (
        EdgeAwareFilter,
        AtrousSettings,
        {"levels": (2, 3, 4), "sigma_half": (0.002, 0.02), "sigma_mirror": (0.25, 2.0), "sigma_plane": (1.0, 4.0)},
    ),
    "regression": (
        RegressionFilter,
        RegressionSettings,
        {
            "radius": (3, 5),
            "order": (1, 2),
            "sigma_space": (1.5, 100.0),
            "sigma_half": (0.02, INF),
            "min_taps": (0.0, 2.0),
        },
    ),
}


def _apply(A, img):
    return A(img.permute(2, 0, 1)).permute(1, 2, 0)


def _hi_mean(folder: Path, cfg: dict, scene, obj: str, edited: dict, missing) -> tuple:
    """The hi-spp means (default, edited) of ``denoise.py``: its runs at ``--hi-step`` spp (the
    full unit of that spp and the extra seeds after the ``--spp`` list)."""
    spps, step, runs = cfg["spp"], cfg["hi_step"], []
    for k in range(cfg["hi_spp"] // step):
        seed = spps.index(step) if k == 0 else len(spps) + k - 1
        settings = {"series": cfg["series"], "spp": step, "seed": seed, "edited": edited, "obj": obj}
        runs.append(_cached(folder, "unit", {**settings, "full": k == 0}, scene, missing)[0])
    return tuple(torch.stack([r[k] for r in runs]).mean(0) for k in ("none", "none_e"))


def half_records(name: str, cfg: dict, folder: Path) -> list:
    """The two half-spp records of ``denoise.py``'s ``halves`` part at the middle spp
    (:func:`denoise.half_records`, cached as record files under ``folder``)."""
    return _half_records(SCENES[name][0](cfg["res"]), cfg["series"], cfg["spp"][1], 1, folder)


def probe_pilots(name: str, cfg: dict, folder: Path) -> tuple[dict, dict]:
    """The half records (:func:`half_records`), each frozen on the benchmark's object and
    rendered at every material of :data:`PROBES` and at the scene's own: ``{"a{i}", "b{i}"}``
    (H, W, 3) frames (i = len(PROBES): the default material, which must equal the cached
    ``half_a``/``half_b`` of ``denoise.py``)."""
    build, obj, _ = SCENES[name]
    scene = build(cfg["res"])
    mats = _materials(scene)

    def compute():
        arrays = {}
        for tag, T in zip("ab", half_records(name, cfg, folder), strict=True):
            R = PolynomialRenderer(T, mats)
            R.freeze(obj)
            for i, m in enumerate((*PROBES, mats[obj])):
                R.set_material(obj, dict(m))
                arrays[f"{tag}{i}"] = R()
        return arrays, {}

    settings = {"series": cfg["series"], "spp": cfg["spp"][1], "seed": 1, "obj": obj, "probes": list(PROBES)}
    return _cached(folder, "probes", settings, scene, compute)


def selection_bound(g, gl, noisy: dict, refs: dict, means: tuple, mask, smooth=(2, 4)) -> dict:
    """The oracle per-pixel choice among the candidates of :class:`SelectionSettings` (see the
    module docstring): ``{material: {"candidates": {name: err}, "oracle_smooth{s}": err}}``."""
    s = SelectionSettings()
    cands = {"identity": None} | {
        f"r{r}o{o}": RegressionFilter(g, s.regression(r, o), glossy=gl) for r, o in s.candidates
    }
    out = {}
    for suf, ref, m in (("", refs["ref"], means[0]), ("_e", refs["ref_e"], means[1])):
        y = noisy["none" + suf]
        outs = torch.stack([y if A is None else _apply(A, y) for A in cands.values()])  # (K, H, W, 3)
        row = {"candidates": {k: relative_rmse(o, ref, mask) for k, o in zip(cands, outs, strict=True)}}
        err = ((outs - m) ** 2).sum(-1)[:, None]  # (K, 1, H, W)
        for r in smooth:
            e = F.avg_pool2d(err, 2 * r + 1, 1, r, count_include_pad=False)[:, 0]
            best = torch.gather(outs, 0, e.argmin(0)[None, ..., None].expand(1, *e.shape[1:], 3))[0]
            row[f"oracle_smooth{r}"] = relative_rmse(best, ref, mask)
        row["none_hi"] = relative_rmse(m, ref, mask)
        out["default" if not suf else "edited"] = row
    return out


class NotCached(Exception):
    """A part of ``denoise.py`` that these options need is not in the cache."""


def _band_parts(T, mats: dict, obj: str, material: dict, groups: int) -> tuple[list, torch.Tensor]:
    """The frozen frame of ``T`` at ``material`` split into ``groups`` images (3, H, W), one per
    group of consecutive bands of ``obj`` (its pixels' own records, Eq. 28: linear in the band
    coefficients), plus one image of the other records; and the emission (3, H, W)."""
    R = PolynomialRenderer(T, mats)
    R.freeze(obj)
    R.set_material(obj, dict(material))
    fz = R._frozen
    i, nb, K, h, w = fz["object"], R.max_bounces, fz["K"], T.height, T.width
    di = R.d[i] * R._map_mean(i)
    pw = torch.stack([di**k for k in range(nb)])  # (nb, C)
    sv = torch.cat([torch.ones(1, 3, dtype=R.dtype)] + ([R.c_hat[i]] if fz["slots"] else []), 0)
    gk = (sv[:, None, :] * pw[None, :, :]).reshape(K, 3).T  # (C, K), as the frozen frame
    if R._pixel_weights(i, fz["pix_i"]) is not None:
        raise SystemExit("band groups: per-pixel weights of the frozen object are not handled")
    p_i, c = fz["pix_i"].numel(), R.c[i]
    bounds = torch.linspace(0, c.shape[0], groups + 1).round().long().tolist()
    parts = []
    for a, b in itertools.pairwise(bounds):
        cg = torch.zeros_like(c)
        cg[a:b] = c[a:b]
        u = torch.bmm(cg.T.unsqueeze(1), fz["F"]).reshape(3, K, p_i)
        own = torch.bmm(gk.unsqueeze(1), u).squeeze(1)
        parts.append(torch.zeros(3, h * w, dtype=own.dtype).index_add(1, fz["pix_i"], own).reshape(3, h, w))
    other = torch.bmm(gk.unsqueeze(1), fz["V"]).squeeze(1)
    parts.append(torch.zeros(3, h * w, dtype=other.dtype).index_add(1, fz["pix_r"], other).reshape(3, h, w))
    emission = R.emission.T.reshape(h, w, 3).permute(2, 0, 1)
    frame = R().permute(2, 0, 1)
    assert float((sum(parts) + emission - frame).abs().max()) <= 1e-5 * float(frame.abs().max())
    return parts, emission


def edit_robust(name: str, cfg: dict, folder: Path, groups: int = 8) -> dict:
    """Picks of :class:`SelectedRegressionFilter` meant to hold under edits, on the mean record of
    ``denoise.py``'s ``halves`` part at the middle spp (rel. RMSE ``[default, edited]``; exact:
    the filters are linear per image and the emission is not filtered where errors are measured):
    ``selected`` (the benchmark's pick: default-material pilots, silhouette candidates),
    ``no_silhouette`` (silhouette pixels kept, the plain pick), ``probes`` (pilots at the
    :data:`PROBES` materials, ``relative=True``: not the benchmark's edit) and ``band_groups``
    (one pick per group of ``groups`` consecutive bands of the frozen object and one for the
    other records, each from the default-material halves of that group)."""
    build, obj, edited = SCENES[name]
    scene = build(cfg["res"])
    mats = _materials(scene)

    def missing():
        raise SystemExit(f"{name}: run benchmarks/denoise.py with the same options first")

    bounces = len(cfg["series"].split(","))
    refs, _ = _cached(folder, "reference", {"ref_spp": cfg["ref_spp"], "edited": edited, "b": bounces}, scene, missing)
    st = {"series": cfg["series"], "spp": cfg["spp"][1], "seed": 1, "edited": edited, "obj": obj, "full": True}
    unit, meta = _cached(folder, "unit", st, scene, missing)
    methods = [SelectedRegressionFilter.__name__, repr(SelectionSettings())]
    h, _ = _cached(folder, "halves", {**st, "methods": methods}, scene, missing)
    pilots, _ = probe_pilots(name, cfg, folder)
    mask, g, gl = unit["emitter_free"].bool(), guide_buffers(scene), meta["glossy"]
    n = len(PROBES)
    out = {"pilot_equals_halves_part": float((pilots[f"a{n}"] - h["half_a"]).abs().max() / h["half_a"].abs().max())}

    def perm(x):
        return x.permute(2, 0, 1)

    default = [(perm(h["half_a"]), perm(h["half_b"]))]
    probes = [(perm(pilots[f"a{i}"]), perm(pilots[f"b{i}"])) for i in range(n)]
    variants = {
        "selected": (default, SelectionSettings()),
        "no_silhouette": (default, SelectionSettings(silhouette=())),
        "probes": (probes, SelectionSettings(relative=True)),
    }
    for k, (pairs, s) in variants.items():
        A = SelectedRegressionFilter(g, pairs, s, glossy=gl)
        out[k] = [
            relative_rmse(_apply(A, h["none_h"]), refs["ref"], mask),
            relative_rmse(_apply(A, h["none_h_e"]), refs["ref_e"], mask),
        ]
        print(name, k, out[k], flush=True)
    halves = half_records(name, cfg, folder)
    pa, _ = _band_parts(halves[0], mats, obj, mats[obj], groups)
    pb, _ = _band_parts(halves[1], mats, obj, mats[obj], groups)
    filters = [SelectedRegressionFilter(g, [(a, b)], glossy=gl) for a, b in zip(pa, pb, strict=True)]
    mean = mean_tensors(halves)
    row = []
    for mat, ref in ((mats[obj], refs["ref"]), (edited, refs["ref_e"])):
        parts, e = _band_parts(mean, mats, obj, mat, groups)
        img = sum(A(p) for A, p in zip(filters, parts, strict=True)) + e
        row.append(relative_rmse(img.permute(1, 2, 0), ref, mask))
    out[f"band_groups{groups}"] = row
    print(name, f"band_groups{groups}", row, flush=True)
    out["probes_materials"] = list(PROBES)
    out["load"] = _load()
    return out


def tune(name: str, cfg: dict, folder: Path, filters: list[str], bound: bool = False) -> dict:
    build, obj, edited = SCENES[name]
    scene = build(cfg["res"])
    bounces = len(cfg["series"].split(","))

    def missing():
        raise NotCached(f"{name}: run benchmarks/denoise.py with the same options first")

    refs, _ = _cached(folder, "reference", {"ref_spp": cfg["ref_spp"], "edited": edited, "b": bounces}, scene, missing)
    units = {}
    for seed, spp in enumerate(cfg["spp"][:2]):
        settings = {"series": cfg["series"], "spp": spp, "seed": seed, "edited": edited, "obj": obj, "full": True}
        units[spp], meta = _cached(folder, "unit", settings, scene, missing)
    lo, mid = cfg["spp"][0], cfg["spp"][1]
    mask = units[lo]["emitter_free"].bool()
    g = guide_buffers(scene)
    gl = meta["glossy"]
    default = EdgeAwareFilter(g, glossy=gl)
    out = {
        "linear_frame_equals_filtered_noisy_frame": relative_rmse(
            _apply(default, units[mid]["none"]), units[mid]["linear"], mask
        ),
        "none": {
            "default": relative_rmse(units[mid]["none"], refs["ref"], mask),
            "edited": relative_rmse(units[mid]["none_e"], refs["ref_e"], mask),
        },
    }
    for f in filters:
        cls, settings_cls, grid = GRIDS[f]
        rows = []
        for values in itertools.product(*grid.values()):
            chosen = dict(zip(grid, values, strict=True))
            A = cls(g, settings_cls(**chosen), glossy=gl)
            rows.append(
                {
                    "settings": chosen,
                    "choose": relative_rmse(_apply(A, units[lo]["none"]), refs["ref"], mask),
                    "default": relative_rmse(_apply(A, units[mid]["none"]), refs["ref"], mask),
                    "edited": relative_rmse(_apply(A, units[mid]["none_e"]), refs["ref_e"], mask),
                }
            )
            print(name, f, rows[-1], flush=True)
        out[f] = {
            "default_settings": next(
                (r for r in rows if r["settings"] == {k: getattr(settings_cls(), k) for k in grid}), None
            ),
            "best": min(rows, key=lambda r: r["choose"]),
            "grid": rows,
        }
    if bound:
        means = _hi_mean(folder, cfg, scene, obj, edited, missing)
        out["selection_bound"] = selection_bound(g, gl, units[mid], refs, means, mask)
        print(name, "selection_bound", out["selection_bound"], flush=True)
    out["load"] = _load()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--series", default="64,1,1,1")
    ap.add_argument("--spp", default="16,64,256")
    ap.add_argument("--hi-spp", type=int, default=1024)
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--cache", default=None)
    ap.add_argument(
        "--filters", default=",".join(GRIDS), help="comma-separated subset of " + ",".join(GRIDS) + " or none"
    )
    ap.add_argument("--bound", action="store_true", help="also the oracle bound of per-pixel window selection")
    ap.add_argument("--quick", action="store_true", help="denoise.py --quick's sizes; implies --build")
    ap.add_argument("--build", action="store_true", help="run denoise.py (these options) for parts not cached")
    ap.add_argument("--hi-step", type=int, default=None, help="as denoise.py (default the middle spp)")
    ap.add_argument(
        "--edit-robust", action="store_true", help="only the edit-robust picks (edit_robust) on the halves part"
    )
    args, _ = ap.parse_known_args()  # denoise.py's other options (--figure, ...) are accepted
    if args.quick:
        args.res, args.series, args.spp, args.hi_spp, args.ref_spp = 48, "16,1,1", "4,16", 64, 512
    spps = [int(s) for s in args.spp.split(",")]
    mid = spps[len(spps) // 2] if len(spps) > 2 else spps[-1]
    cfg = {"res": args.res, "series": args.series, "spp": spps, "ref_spp": args.ref_spp, "hi_spp": args.hi_spp}
    cfg["hi_step"] = args.hi_step or mid
    folder = Path(args.cache) if args.cache else cache_path("benchmarks", "denoise")
    filters = [f for f in args.filters.split(",") if f != "none"]
    sizes = ["--res", str(args.res), "--series", args.series, "--spp", args.spp, "--hi-spp", str(args.hi_spp)]
    sizes += ["--ref-spp", str(args.ref_spp), "--hi-step", str(cfg["hi_step"]), "--cache", str(folder)]
    names = [n for n in SCENES if any(n.startswith(p) for p in args.scenes.split(","))]
    if args.edit_robust:
        print(json.dumps({name: edit_robust(name, cfg, folder) for name in names}))
        return
    out = {"quick": args.quick, "settings": cfg}
    for name in names:
        try:
            out[name] = tune(name, cfg, folder, filters, args.bound)
        except NotCached as exc:
            if not (args.build or args.quick):
                raise SystemExit(str(exc)) from exc
            print(f"{exc}: running it ({' '.join(sizes)})", flush=True)
            cmd = [sys.executable, "-m", "torch_brdf.report.benchmarks.denoise", *sizes, "--scenes", name]
            subprocess.run(cmd, check=True, stdout=sys.stderr)  # its JSON is not this script's last line
            out[name] = tune(name, cfg, folder, filters, args.bound)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
