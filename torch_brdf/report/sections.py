"""From benchmark JSON to the report's sections: per capability, its figures and key numbers.

Each capability reads the keys its benchmarks print (see each script's docstring) and turns
them into :class:`Figure` s -- error against cost, log scales -- with every curve's default,
the planner's choice (read from ``benchmarks/planner.py``'s JSON, whatever else it grows), the
seed paper's published figure where it has one (cited), and the peer's point from the same run.
A key that is missing becomes a "not measured" note, never an exception.

Published figures of the papers the capabilities implement, used as reference points:

* Ben-Artzi et al. 2008, Table II: Cornell box 450x450, series 64,1,1,1, 12K samples per pixel,
  1461 MB in total, 5 h 58 min of precomputation (no error is published).
* Inger et al., Sec. 6 (Fig. 5): PSNR 45.67 dB for their method against 33.54 dB for Ng et al.'s
  Haar triple products; speed-ups over the standard-basis baseline x40 (theirs, exponents up to
  200) and ~x10 (Haar at 1 % of the coefficients).
* Iwasaki et al., Table 1 (Fig. 1): the least-squares solve T_s = 0.26 s at N = 2656 pixels;
  transfer functions T_trans = 28 s.
* Soler et al. 2017 publish no error or fit-time figure; their optimiser (Hooke-Jeeves) is run
  in the same benchmark (``hj_*``) and shown as the seed's point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

#: styles of a series: a measured curve, a marked point
STYLES = ("curve", "point", "default", "planner", "peer", "seed")


@dataclass
class Series:
    """One curve or marked point: ``points`` (x, y); ``style`` one of :data:`STYLES`;
    ``vline`` / ``hline`` draw a reference line instead of points (a published cost without an
    error, a requested error)."""

    label: str
    points: list[tuple[float, float]] = field(default_factory=list)
    style: str = "curve"
    vline: float | None = None
    hline: float | None = None


@dataclass
class Figure:
    """One plot: ``key`` names its PNG; axes log-scaled unless ``xlog`` / ``ylog`` say not."""

    key: str
    title: str
    xlabel: str
    ylabel: str
    series: list[Series]
    caption: str = ""
    xlog: bool = True
    ylog: bool = True

    def has_data(self) -> bool:
        """At least one measured point (a seed's published figure alone does not count)."""
        return any(s.points for s in self.series if s.style != "seed")


@dataclass
class Section:
    """One capability: its benchmarks, figures, key numbers (name -> value) and notes."""

    key: str
    title: str
    benchmarks: list[str]
    figures: list[Figure] = field(default_factory=list)
    numbers: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def add(self, *args: Any, **kwargs: Any) -> None:
        """Append ``Figure(*args, **kwargs)``."""
        self.figures.append(Figure(*args, **kwargs))


def get(d: Any, *path: Any) -> Any:
    """``d[path[0]][path[1]]...`` or None where any step is missing."""
    for p in path:
        if isinstance(d, list) and isinstance(p, int) and -len(d) <= p < len(d):
            d = d[p]
        elif isinstance(d, dict) and p in d:
            d = d[p]
        elif isinstance(d, dict) and str(p) in d:
            d = d[str(p)]
        else:
            return None
    return d


def num(x: Any) -> float | None:
    """``x`` as a finite float, else None."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return None
    return float(x) if math.isfinite(x) else None


def pt(x: Any, y: Any) -> list[tuple[float, float]]:
    """[(x, y)] if both are finite numbers, else []."""
    a, b = num(x), num(y)
    return [(a, b)] if a is not None and b is not None else []


class _Reader:
    """Reads one benchmark's result and remembers the keys it asked for and did not find."""

    def __init__(self, results: dict[str, dict], name: str):
        rec = results.get(name) or {}
        self.name, self.res, self.missing = name, rec.get("result") or {}, []
        self.ran = bool(rec.get("result"))

    def __call__(self, *path: Any) -> Any:
        v = get(self.res, *path)
        if v is None and self.ran:
            self.missing.append(".".join(map(str, path)))
        return v


def _finish(sec: Section, *readers: _Reader | tuple[_Reader, str]) -> Section:
    """Add each reader's key numbers (``(reader, "key key ...")``: ``<benchmark>.<key>`` -> value)
    and a "not measured" note for every key a benchmark that ran did not print."""
    for item in readers:
        r, keys = item if isinstance(item, tuple) else (item, "")
        for k in keys.split():
            sec.numbers[f"{r.name}.{k}"] = r(k)
    for item in readers:
        r = item[0] if isinstance(item, tuple) else item
        if r.missing:
            sec.notes.append(f"not measured (no such key in {r.name}'s JSON): {', '.join(dict.fromkeys(r.missing))}")
    return sec


# -- the planner's JSON: tolerant of the keys it may grow -----------------------------------------
def planner_choices(planner: dict | None) -> list[tuple[str, dict]]:
    """Every ``planned`` block in the planner's JSON, with the path that leads to it (the GI
    planner prints one at the top level; planners of other capabilities or scenes may nest
    theirs under any key). Each block is returned with its sibling ``defaults`` and ``error``
    merged in when they exist."""
    found: list[tuple[str, dict]] = []

    def walk(d: Any, path: str) -> None:
        if not isinstance(d, dict):
            return
        if isinstance(d.get("planned"), dict):
            block = dict(d["planned"])
            for k in ("defaults", "error", "scene", "best_default", "psnr", "target"):
                if k in d and k not in block:
                    block[k] = d[k]
            found.append((path or "gi", block))
        for k, v in d.items():
            if k != "planned":
                walk(v, f"{path}.{k}" if path else k)

    walk(planner, "")
    return found


def _choice_for(planner: dict | None, words: tuple[str, ...]) -> list[tuple[str, dict]]:
    return [(p, b) for p, b in planner_choices(planner) if any(w in p.lower() for w in words)]


def _planner_series(choices: list[tuple[str, dict]], xkeys=("seconds",), ykeys=("achieved_error",)) -> list[Series]:
    out = []
    for path, b in choices:
        x = next((b[k] for k in xkeys if num(b.get(k)) is not None), None)
        y = next((b[k] for k in ykeys if num(b.get(k)) is not None), None)
        if x is not None and y is not None:
            what = " ".join(str(b[k]) + (" spp" if k == "spp" else "") for k in ("series", "spp") if k in b)
            out.append(Series(f"planner's choice ({path}{': ' + what if what else ''})", pt(x, y), "planner"))
    return out


def _manifold_planner_series(choices: list[tuple[str, dict]]) -> list[Series]:
    """The manifold planner's plan at its q, by the held-out curves' own statistic (the mean over
    materials, ``achieved_mean``: ★) and, labelled apart, by the statistic it plans for
    (``achieved_error``, ``statistic``: ○); a run without ``achieved_mean`` shows only the latter,
    labelled by its statistic, never as a point of the curves' mean."""
    out = []
    for path, b in choices:
        q, what = b.get("q"), f"q {b.get('q')}, n {b.get('n')}; {b.get('heldout', '?')} held-out analytic materials"
        out.append(Series(f"planner's choice ({path}: {what}), mean", pt(q, b.get("achieved_mean")), "planner"))
        stat = b.get("statistic", "its planned statistic")
        out.append(Series(f"the same plan, {stat} (what it plans for)", pt(q, b.get("achieved_error")), "point"))
    return [s for s in out if s.points]


#: words in a planner JSON path that mark a planner of a capability other than GI editing
OTHER_PLANNERS = ("relight", "triple", "cubemap", "inverse", "srbf", "manifold", "gplvm", "denois")


# -- capabilities ---------------------------------------------------------------------------------
def _gi_planner_figures(sec: Section, pl) -> None:
    """One figure per planned scene: the GI planner against fixed default series (its own scene
    and reference)."""
    for path, b in planner_choices(pl.res):
        if any(w in path.lower() for w in OTHER_PLANNERS):  # another capability's planner
            continue
        ser = []
        for key, rows in (b.get("defaults") or {}).items():
            if isinstance(rows, list):
                ser.append(
                    Series(
                        f"fixed {key}, spp in steps of sqrt 2",
                        [p for row in rows for p in pt(row.get("seconds"), row.get("achieved_error"))],
                    )
                )
        cli = [row for row in get(b, "defaults", "64,1,1,1") or [] if isinstance(row, dict) and row.get("spp") == 64]
        if cli:
            ser.append(
                Series(
                    "default: the CLI's 64,1,1,1 at 64 spp",
                    pt(cli[0].get("seconds"), cli[0].get("achieved_error")),
                    "default",
                )
            )
        bd = b.get("best_default") or {}
        ser.append(
            Series(
                f"cheapest fixed default reaching the error ({bd.get('series')}, {bd.get('spp')} spp)",
                pt(bd.get("seconds"), bd.get("achieved_error")),
                "default",
            )
        )
        ser += _planner_series([(path, b)])
        if num(b.get("predicted_error")) is not None and num(b.get("predicted_seconds")) is not None:
            ser.append(Series("planner's prediction", pt(b["predicted_seconds"], b["predicted_error"]), "point"))
        if num(b.get("error")) is not None:
            ser.append(Series(f"requested error {b['error']:g}", style="default", hline=b["error"]))
        scene = str(b.get("scene") or path.rsplit(".", 1)[-1])  # one figure per scene, named by it
        key = "gi_planner_" + "".join(c if c.isalnum() else "_" for c in scene)
        sec.add(
            key,
            f"GI planner vs fixed defaults ({scene})",
            "precompute seconds",
            "relative RMSE (achieved)",
            ser,
            f"benchmarks/planner.py, scene {scene}",
        )


def gi_editing(results: dict) -> Section:
    """Ben-Artzi et al.: the polynomial tensors (benchmarks/polynomial.py, planner.py, brdf.py)."""
    sec = Section("gi", "GI editing (polynomial multibounce tensors)", ["polynomial", "planner", "brdf"])
    r, pl, br = _Reader(results, "polynomial"), _Reader(results, "planner"), _Reader(results, "brdf")
    rel = r("rel_rmse") or {}
    res = num(r("accuracy_resolution"))
    curve = sorted(
        (int(k[3:]), v) for k, v in rel.items() if k.startswith("spp") and k[3:].isdigit() and isinstance(v, dict)
    )
    series_pts = {k: v for k, v in rel.items() if not k.startswith("spp") and isinstance(v, dict)}
    t = [
        Series(
            "64,1,1,1, spp " + ",".join(str(s) for s, _ in curve),
            [p for _, v in curve for p in pt(v.get("seconds"), v.get("rel_rmse"))],
        )
    ]
    for k, v in series_pts.items():
        t.append(Series(f"{k} at 64 spp", pt(v.get("seconds"), v.get("rel_rmse")), "point"))
    t.append(
        Series(
            "default (CLI: 64,1,1,1 at 64 spp)",
            pt(get(rel, "spp64", "seconds"), get(rel, "spp64", "rel_rmse")),
            "default",
        )
    )
    mp = r("mitsuba_point")
    if mp:
        t.append(
            Series(
                f"peer: Mitsuba 3 path tracer, {mp.get('spp')} spp", pt(mp.get("seconds"), mp.get("rel_rmse")), "peer"
            )
        )
    ref = r("reference")
    cap = (
        f"relative RMSE against {ref or 'the reference'} at {int(res) if res else '?'}²; precompute seconds of each run"
    )
    sec.add("gi_time", "GI editing: error vs precompute time", "precompute seconds", "relative RMSE", t, cap)
    px = (res * res) / 1e6 if res else None
    m = [
        Series(
            "64,1,1,1 over spp",
            [p for _, v in curve for p in pt(num(v.get("mb")) and px and v["mb"] / px, v.get("rel_rmse"))],
        )
    ]
    for k, v in series_pts.items():
        m.append(Series(f"{k} at 64 spp", pt(num(v.get("mb")) and px and v["mb"] / px, v.get("rel_rmse")), "point"))
    m.append(
        Series(
            "default (64,1,1,1, 64 spp)",
            pt(px and num(get(rel, "spp64", "mb")) and get(rel, "spp64", "mb") / px, get(rel, "spp64", "rel_rmse")),
            "default",
        )
    )
    m.append(
        Series(
            "seed Table II: Cornell box 64,1,1,1, 12K spp, 1461 MB at 450² (no error published)",
            style="seed",
            vline=1461 / (450 * 450 / 1e6),
        )
    )
    sec.add("gi_memory", "GI editing: error vs tensor memory", "MB per megapixel (float32 values)", "relative RMSE", m)

    _gi_planner_figures(sec, pl)
    # band projection error of the BRDF layer: the bands' share of the error budget
    pre = br("projection_rel_err") or {}
    fams: dict[str, list[tuple[float, float]]] = {}
    for k, v in pre.items():
        if k.startswith("blinn_n") and "_J" in k:
            fam, j = k.rsplit("_J", 1)
            sqrt = j.endswith("_sqrt")
            j = j.removesuffix("_sqrt")
            if j.isdigit():
                fams.setdefault(fam + (" (sqrt spacing)" if sqrt else " (lobe spacing)"), []).extend(pt(int(j), v))
    if fams:
        sec.add(
            "gi_bands",
            "BRDF bands: projection error vs bands J",
            "bands J (memory per object grows with J)",
            "cosine-weighted relative L2 error",
            [Series(k.replace("blinn_n", "Blinn-Phong n="), sorted(v)) for k, v in sorted(fams.items())],
        )
    return _finish(
        sec,
        (
            r,
            "precompute_s precompute_over_rays precompute_over_mitsuba freeze_s frame_s frame_over_stream "
            "mitsuba_vs_reference_rel_rmse reference_seed_rel_rmse",
        ),
        (
            pl,
            "prediction_ratio planner_cost_ratio planner_cost_ratio_rays planner_cost_ratio_with_planning plan_seconds",
        ),
        br,
    )


def denoise(results: dict) -> Section:
    sec = Section("denoise", "Denoising the basis images", ["denoise"])
    r = _Reader(results, "denoise")
    rel, pre, den = r("rel_rmse_edited") or {}, r("precompute_s") or {}, r("denoise_s") or {}
    peer = {"oidn_frame": "peer: OIDN on every path-traced frame"}
    ser = []
    for method, by_spp in rel.items():
        if not isinstance(by_spp, dict):
            continue
        pts = []
        for spp, e in by_spp.items():
            secs = num(pre.get(spp)) if isinstance(pre, dict) else None
            if secs is not None:
                pts += pt(secs + (num(get(den, method, spp)) or 0.0), e)
        ser.append(Series(peer.get(method, method), sorted(pts), "peer" if method in peer else "curve"))
    mid = "16" if r("quick") else "64"
    ser.append(
        Series(
            f"default: the frozen tensor as is ({mid} spp)",
            pt((num(pre.get(mid)) if isinstance(pre, dict) else None), get(rel, "none", mid)),
            "default",
        )
    )
    sec.add(
        "denoise_time",
        "Denoising: error vs precompute + denoise time",
        "seconds (precompute + denoising)",
        "relative RMSE (emitters excluded)",
        ser,
        "glossy Cornell box, the edited material (exponent 1000, a colour the denoisers never saw)",
    )
    mb = r("frozen_mb") or {}
    ms = [
        Series(m, pt(mb.get(m), get(rel, m, mid)), "peer" if m in peer else "point") for m in mb if isinstance(mb, dict)
    ]
    sec.add(
        "denoise_memory",
        f"Denoising: error vs frozen memory ({mid} spp)",
        "MB of the frozen frame data",
        "relative RMSE",
        ms,
    )
    return _finish(sec, (r, "frame_s_before frame_s_after mean_ratio reference"))


def relighting(results: dict) -> Section:
    sec = Section(
        "relight", "All-frequency relighting (locally adaptive triple products)", ["triple_product", "planner"]
    )
    r, pl = _Reader(results, "triple_product"), _Reader(results, "planner")
    std = num(r("standard_frame_s"))
    curve = r("curve") or {}
    fam: dict[str, list] = {}
    for k, v in curve.items():
        name = k.rsplit("_x", 1)[0] if "_x" in k else "fixed samples"
        if std and isinstance(v, dict):
            fam.setdefault(name, []).extend(pt(num(v.get("frame_s")) and v["frame_s"] / std, v.get("psnr")))
    ser = [
        Series(
            f"{k} (thresholds scaled)" if k != "fixed samples" else "fixed 1/4/16/256 samples", v
        )  # in threshold order
        for k, v in fam.items()
    ]
    ser.append(
        Series(
            "default rule (PhongRule, generic fallback)",
            pt(num(r("frame_s")) and std and r("frame_s") / std, r("psnr")),
            "default",
        )
    )
    ser.append(
        Series(
            "peer: Haar triple products (Ng et al.), 1 % of coefficients",
            pt(num(r("haar_frame_s")) and std and r("haar_frame_s") / std, r("haar_psnr")),
            "peer",
        )
    )
    ser.append(Series("seed Sec. 6 / Fig. 5: ours x40 faster, 45.67 dB", [(1 / 40, 45.67)], "seed"))
    ser.append(Series("seed Sec. 6 / Fig. 5: Haar ~x10 faster, 33.54 dB", [(1 / 10, 33.54)], "seed"))
    sec.add(
        "relight_time",
        "Relighting: PSNR vs frame time",
        "frame time / standard-basis frame time",
        "PSNR (dB) against the standard basis",
        ser,
        "frame 1; the seed's points are relative to its own baseline",
        ylog=False,
    )
    vb, db = num(r("visibility_bytes_per_vertex")), num(r("dense_bytes_per_vertex"))
    mem = [
        Series("ours: varint visibility stream", pt(vb, r("psnr")), "default"),
        Series("dense bits (one per texel)", style="point", vline=db) if db else Series("dense", []),
    ]
    mem.append(Series("seed's storage goal ~1 KB per vertex", style="seed", vline=1024.0))
    sec.add(
        "relight_memory", "Relighting: PSNR vs visibility storage", "bytes per vertex", "PSNR (dB)", mem, ylog=False
    )
    # the planner against fixed defaults: its own scene, PSNR against the converged reference
    for path, b in _choice_for(pl.res, ("relight", "triple", "cubemap")):
        ser = [
            Series(
                f"fixed: cubemap {d.get('cubemap')}, {d.get('rule')}",
                pt(d.get("cost_s"), d.get("psnr")),
                "default" if i == 0 else "point",
            )
            for i, d in enumerate(b.get("defaults") or [])
            if isinstance(d, dict)
        ]
        what = ", ".join(f"{k} {b[k]}" for k in ("cubemap", "supersample", "bits", "rule") if k in b)
        ser.append(Series(f"planner's choice ({what})", pt(b.get("cost_s"), b.get("psnr")), "planner"))
        ser.append(Series("planner's prediction", pt(b.get("predicted_cost_s"), b.get("predicted_psnr")), "point"))
        req = num(get(pl.res, "relight", "psnr"))
        if req is not None:
            ser.append(Series(f"requested {req:g} dB", style="default", hline=req))
        sec.add(
            "relight_planner",
            "Relighting planner vs fixed defaults",
            "precompute + 100 frames (s)",
            "PSNR (dB) against the converged reference",
            ser,
            f"benchmarks/planner.py ({path}): {b.get('scene', 'bunny_relight')}; the first default is the CLI's",
            ylog=False,
        )
    return _finish(
        sec, (r, "precompute_s rays_s frame_s speedup_vs_standard haar_speedup_vs_standard psnr haar_psnr psnr_display")
    )


def manifold(results: dict) -> Section:
    sec = Section("manifold", "BRDF manifold (GPLVM)", ["manifold", "planner"])
    r = _Reader(results, "manifold")
    # y: the log-likelihood's relative gap to the best q = 2 fit of the run (log axis; floor 1e-16)
    runs = [
        ("ours: L-BFGS, q = 2", "fit_s_q2", "loglik_q2", "default"),
        ("torch.optim.LBFGS (strong Wolfe), q = 2", "lbfgs_wolfe_s_q2", "lbfgs_wolfe_loglik_q2", "point"),
        ("seed's optimiser (Hooke-Jeeves), q = 2, same run", "hj_fit_s_q2", "hj_loglik_q2", "seed"),
        ("peer: GPyTorch ExactGP MAP GPLVM, q = 2", "gpytorch_s_q2", "gpytorch_loglik_q2", "peer"),
    ]
    ll = {k: num(r(k)) for _, _, k, _ in runs}
    best = max((v for v in ll.values() if v is not None), default=None)
    fit = [
        Series(label, pt(r(t), None if ll[k] is None or best is None else max((best - ll[k]) / abs(best), 1e-16)), st)
        for label, t, k, st in runs
    ]
    cap = f"{r('data') or ''}; gap = (best L - L) / |best L|, L the log-likelihood of Eq. 6 at q = 2"
    sec.add(
        "manifold_fit",
        "GPLVM fit: log-likelihood gap vs fit time",
        "fit seconds",
        "relative log-likelihood gap",
        fit,
        cap,
    )
    held = []
    for label, key in (
        ("GPLVM", "heldout_logrmse_mean"),
        ("PCA (linear baseline)", "pca_heldout_logrmse_mean"),
        ("nearest training material", "nearest_heldout_logrmse_mean"),
    ):
        d = r(key) or {}
        held.append(Series(label, sorted(p for q, v in d.items() if str(q).isdigit() for p in pt(int(q), v))))
    held.append(Series("default q = 2", pt(2, get(r.res, "heldout_logrmse_mean", "2")), "default"))
    held += _manifold_planner_series(_choice_for(get(results, "planner", "result"), ("manifold", "gplvm")))
    sec.add(
        "manifold_heldout",
        "Held-out reconstruction: log-RMSE vs latent dimension",
        "latent dimension q (model size)",
        "held-out log-RMSE: mean over materials",
        held,
        "curves: the mean over held-out materials of the per-material log-RMSE, averaged over "
        f"{get(r.res, 'splits') or 'the'} random 80/20 splits of {r('data') or 'the benchmark data'}; "
        "★ the manifold planner's plan on its own data (the analytic family, benchmarks/planner.py), "
        "scored by the same mean over its held-out materials; "
        "○ the same plan by the statistic it plans for (the interquartile mean of the log errors)",
    )
    _manifold_default_figures(sec, r)
    return _finish(
        sec,
        (
            r,
            "interp_per_s predict_rows_per_s blend_fps_512 gi_blend_rel_l1 "
            "time_ratio_gpytorch_over_ours loglik_ours_minus_gpytorch "
            "default_validity negative_fraction_energy max_albedo_energy default_margin_ok default_below_pca_all "
            "path_monotone_share path_jump_max",
        ),
    )


def _manifold_default_figures(sec: Section, r: _Reader) -> None:
    """The default model (valid weights): margin over the nearest material and interpolation share
    per held-out case (random splits, drawn family hold-outs) against q."""
    cases = r("default_heldout") or {}

    def by_q(case: dict, key: str) -> list[tuple[float, float]]:
        return sorted(p for q, v in case.items() if str(q).isdigit() for p in pt(int(q), get(v, key)))

    margin = [Series(str(tag), by_q(case, "margin")) for tag, case in cases.items()]
    margin.append(Series("required margin (10%)", hline=0.10, style="default"))
    fams = ", ".join(get(r.res, "default_families") or [])
    sec.add(
        "manifold_default_margin",
        "Default model: held-out margin over the nearest training material",
        "latent dimension q",
        "1 - GPLVM log-RMSE / nearest material's",
        margin,
        "each curve one held-out case: a random 80/20 split or a family held out whole "
        f"({fams or 'none'}; drawn with seed {get(r.res, 'default_family_seed')}); valid (energy-bounded) "
        "weights, placement between the nearest materials",
        xlog=False,
        ylog=False,
    )
    share = [Series(str(tag), by_q(case, "interpolation_share")) for tag, case in cases.items()]
    sec.add(
        "manifold_interpolation",
        "Default model: held-out materials placed between training materials",
        "latent dimension q",
        "share at >= 0.1 of the local spacing from every training latent",
        share,
        "interpolation share per held-out case (0: every held-out material sits on a training latent, "
        f"i.e. is its nearest neighbour); straight paths between neighbours: "
        f"{get(r.res, 'path_monotone_share')} monotone in albedo or highlight width, largest step "
        f"{get(r.res, 'path_jump_max')} of the change between the ends",
        xlog=False,
        ylog=False,
    )


def inverse(results: dict) -> Section:
    sec = Section("inverse", "Inverse BRDF design (strokes, SRBF, constrained least squares)", ["inverse", "planner"])
    r = _Reader(results, "inverse")
    objs = {k: num(r(f"{k}objective")) for k in ("", "admm_", "proxqp_", "clarabel_")}
    best = min((v for v in objs.values() if v is not None), default=None)

    def gap(k: str) -> float | None:
        v = objs.get(k)
        return None if v is None or best is None else max(abs(v - best) / max(abs(best), 1e-300), 1e-16)

    ser = [
        Series("ours: interior point (default)", pt(r("solve_s"), gap("")), "default"),
        Series("ours: ADMM + polishing", pt(r("admm_solve_s"), gap("admm_")), "point"),
        Series("peer: ProxQP (qpsolvers, eps 1e-10)", pt(r("proxqp_solve_s"), gap("proxqp_")), "peer"),
        Series("peer: Clarabel", pt(r("clarabel_solve_s"), gap("clarabel_")), "peer"),
        Series("seed Table 1 (Fig. 1): T_s = 0.26 s at 2656 pixels", style="seed", vline=0.26),
    ]
    cap = f"{r('pixels')} pixels, J = {r('J')}, the three per-channel QPs; error: objective gap to the lowest "
    cap += "any solver reached (floor 1e-16)"
    sec.add(
        "inverse_solve",
        "Inverse design: QP objective gap vs solve time",
        "solve seconds (3 QPs)",
        "relative objective gap",
        ser,
        cap,
    )
    cuts = [
        Series("visibility cuts (default CutOptions)", pt(r("transfer_cuts_s"), r("cuts_rel_err")), "default"),
        Series("dense transfer functions (exact)", style="point", vline=num(r("transfer_s"))),
        Series("seed Table 1 (Fig. 1): T_trans = 28 s", style="seed", vline=28.0),
    ]
    sec.add(
        "inverse_transfer",
        "Transfer functions: cut error vs time",
        "seconds",
        "relative Frobenius error of the cut record",
        cuts,
    )
    for solver, v in (r("qp_set") or {}).items():
        if isinstance(v, dict) and "solved" in v:
            sec.numbers[f"inverse.qp_set.{solver}.solved"] = v["solved"]
    for path, b in _choice_for(get(results, "planner", "result"), ("inverse", "srbf")):
        what = ", ".join(f"{k} {b[k]}" for k in ("light_samples", "J", "hemicube", "cut_tolerance") if k in b)
        ser = _planner_series([(path, b)]) + [Series(f"planner's settings: {what}", [], "point")]
        d = b.get("default") or {}
        ser.append(
            Series(
                "default settings (1024 samples, 147 lobes, dense)",
                pt(d.get("seconds"), d.get("achieved_error")),
                "default",
            )
        )
        if num(b.get("error")) is not None:
            ser.append(Series(f"requested error {b['error']:g}", style="default", hline=b["error"]))
        cap = "benchmarks/planner.py: visibility + transfer functions + fit; error against a high-sample design"
        sec.add(
            "inverse_planner",
            "Inverse-design planner vs the default settings",
            "seconds",
            "relative error of the design",
            ser,
            cap,
        )
    return _finish(sec, (r, "solve_over_proxqp objective_rel_diff_proxqp fit_s active_rows mean_cut_size"))


def inverse_gi(results: dict) -> Section:
    sec = Section("inverse_gi", "Inverse design with global illumination", ["inverse_gi"])
    r = _Reader(results, "inverse_gi")
    ser = [
        Series(
            "ours: fit_image through the polynomial tensors", pt(r("ours_fit_s"), r("ours_peer_param_err")), "default"
        ),
        Series("peer: Mitsuba 3 (prb, Adam)", pt(r("mitsuba_fit_s"), r("mitsuba_param_rel_err")), "peer"),
    ]
    cap = "back wall of the glossy Cornell box, both sides fitting (kd, ks) to one Mitsuba target: "
    cap += "max |p - p*| / max |p*|; Mitsuba's time is to within 1% of the better final loss"
    sec.add(
        "inverse_gi_fit",
        "GI inverse design: parameter error vs fit time",
        "fit seconds",
        "parameter relative error",
        ser,
        cap,
    )
    gi = [
        Series("fit with all bounces", pt(r("gi_fit_s"), r("gi_fit_err")), "default"),
        Series("fit with direct light only", pt(r("direct_fit_s"), r("direct_fit_err")), "point"),
    ]
    sec.add(
        "inverse_gi_err",
        "GI vs direct-only fit of a GGX target",
        "fit seconds",
        "relative RMSE of the refit render",
        gi,
    )
    return _finish(sec, (r, "param_rel_err gi_fit_err direct_fit_err precompute_s"))


def editor(results: dict) -> Section:
    sec = Section("editor", "Material editor in the browser", ["editor"])
    r = _Reader(results, "editor")
    sizes = sorted(
        {int(k.rsplit("_", 1)[1]) for k in r.res if k.startswith("latency_ms_") and k.rsplit("_", 1)[1].isdigit()}
    )
    ser = [
        Series("median latency (key to paint)", [p for s in sizes for p in pt(s * s, r.res.get(f"latency_ms_{s}"))]),
        Series("95th percentile", [p for s in sizes for p in pt(s * s, r.res.get(f"p95_ms_{s}"))], "point"),
        Series("kernel frame", [p for s in sizes for p in pt(s * s, r.res.get(f"frame_ms_{s}"))], "point"),
        Series("seed: 15-25 fps (Table II)", style="seed", hline=1000 / 22),
    ]
    sec.add(
        "editor_latency",
        "Editor: latency vs frame size",
        "pixels",
        "milliseconds",
        ser,
        "no error axis: the editor shows the frozen frame exactly",
    )
    sec.numbers["editor.updates_per_s_512"] = r("updates_per_s_512")
    return _finish(sec, r)


def scaleout(results: dict) -> Section:
    sec = Section("scaleout", "Scale-out of the GI precompute (Ray)", ["scaleout"])
    r = _Reader(results, "scaleout")
    skipped = get(r.res, "ray_skipped")  # Ray did not start in its time: the local figures only
    local = Series(
        "local executor (its trace pool on every usable core)", pt(num(r("cpus")) or 1, r("local_s")), "default"
    )
    if skipped:
        sec.add("scaleout_time", "Scale-out: seconds vs workers", "workers", "seconds", [local], str(skipped))
        sec.numbers["scaleout.ray"] = str(skipped)
        return _finish(sec, (r, "local_s local_tiles_per_s"))
    ser = [
        local,
        Series("Ray", [p for w in (1, 2) for p in pt(w, r(f"ray{w}_s"))]),
        Series(
            "model: predicted seconds (1024², 1024 spp), nodes x 2 workers",
            [p for n in (1, 8, 64) for p in pt(2 * n, r(f"predicted_s_{n}"))],
            "point",
        ),
    ]
    sec.add(
        "scaleout_time",
        "Scale-out: seconds vs workers",
        "workers",
        "seconds",
        ser,
        "no error axis: results are equal bit for bit (ray_equals_local)",
    )
    return _finish(
        sec, (r, "ray2_over_local ray_equals_local task_overhead_s predicted_speedup_8 predicted_speedup_64")
    )


def others(results: dict) -> Section:
    """Benchmarks without a capability curve: ray tracing and load sensitivity (numbers only)."""
    sec = Section("other", "Ray tracing and load sensitivity", ["raytrace", "load"])
    r, ld = _Reader(results, "raytrace"), _Reader(results, "load")
    return _finish(
        sec,
        (r, "ratio single_ratio parallel_ratio occluded_ratio"),
        (ld, "max_slowdown embree_slowdown mitsuba_slowdown"),
    )


def scenes_out(results: dict) -> Section:
    """Scenes in and materials out: the GI texture approximation (Sec. 5.3) against the path
    tracer, and each export's fit error (numbers only)."""
    sec = Section("scenes_out", "Textured scenes and exported materials", ["textures", "export"])
    t, e = _Reader(results, "textures"), _Reader(results, "export")
    for source in ("lambert", "cook_torrance_plastic", "blinn_phong_n50", "gltf_metal", "gltf_dielectric"):
        for fmt in ("mitsuba", "gltf"):
            value = num(e(fmt, source, "error"))
            if value is not None:
                sec.numbers[f"export.{fmt}.{source}.error"] = value
    return _finish(
        sec,
        (t, "textured_rel_rmse untextured_rel_rmse texture_excess mean_ratio_textured"),
        (e, "merl_seconds"),
    )


#: the report's sections, in page order
CAPABILITIES = (gi_editing, denoise, relighting, manifold, inverse, inverse_gi, editor, scaleout, scenes_out, others)


def sections(results: dict[str, dict]) -> list[Section]:
    """Every capability's section from the run records (see :mod:`torch_brdf.report.run`)."""
    return [cap(results) for cap in CAPABILITIES]
