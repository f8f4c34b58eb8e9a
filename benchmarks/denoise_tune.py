"""Tune the linear guide-only filters on the cached frames of ``benchmarks/denoise.py``.

    python benchmarks/denoise_tune.py [the same size options as denoise.py] [--filters linear,regression]

Each filter A (``linear``: the à-trous :class:`AtrousSettings` grid; ``regression``: the
local polynomial :class:`RegressionSettings` grid) is linear and the emission term is zero
where the errors are measured, so the frame of the linear-denoised frozen tensor equals A
applied to the noisy frame (checked here against the cached ``linear`` frame). That makes a
grid cheap:
each setting is chosen on the lowest-spp run with the default material (seed 0) and reported
at the middle spp (another seed) on the default and the edited material, which it never saw.
Run ``denoise.py`` first (same options); prints one JSON object.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from denoise import SCENES, _cached, _load

from torch_brdf.data import cache_path
from torch_brdf.denoise import (
    AtrousSettings,
    EdgeAwareFilter,
    RegressionFilter,
    RegressionSettings,
    guide_buffers,
)
from torch_brdf.metrics import relative_rmse

INF = float("inf")
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


def tune(name: str, cfg: dict, folder: Path, filters: list[str]) -> dict:
    build, obj, edited = SCENES[name]
    scene = build(cfg["res"])
    bounces = len(cfg["series"].split(","))

    def missing():
        raise SystemExit(f"{name}: run benchmarks/denoise.py with the same options first")

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
    out["load"] = _load()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--series", default="64,1,1,1")
    ap.add_argument("--spp", default="16,64,256")
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--cache", default=None)
    ap.add_argument("--filters", default=",".join(GRIDS), help="comma-separated subset of " + ",".join(GRIDS))
    args, _ = ap.parse_known_args()
    spps = [int(s) for s in args.spp.split(",")]
    cfg = {"res": args.res, "series": args.series, "spp": spps, "ref_spp": args.ref_spp}
    folder = Path(args.cache) if args.cache else cache_path("benchmarks", "denoise")
    filters = args.filters.split(",")
    print(json.dumps({name: tune(name, cfg, folder, filters) for name in args.scenes.split(",")}))


if __name__ == "__main__":
    main()
