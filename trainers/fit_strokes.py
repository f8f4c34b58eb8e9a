"""Fit a BRDF to painted strokes (Iwasaki et al.): transfer functions, strokes, constrained fit, re-render.

    python trainers/fit_strokes.py teatray --object teapot --strokes strokes.json --out out/inverse

The strokes file format is documented in :mod:`torch_brdf.inverse.design`. Outputs (atomic,
versioned and checksummed where they are arrays): ``fit.npz`` (coefficients, kd, f0 and the
solver report), ``transfer.npz`` (the transfer record; reused on a rerun with the same settings,
so an interrupted run resumes after it), ``render.exr`` and ``render.png``. The summary is
printed as one JSON line. Seeded (``--seed``), tqdm progress.
"""

from __future__ import annotations

import argparse
import json
import sys

from torch_brdf.cli import load_scene
from torch_brdf.errors import TorchBRDFError
from torch_brdf.inverse.design import DesignConfig, design, load_strokes


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="built-in scene name or TOML scene file")
    ap.add_argument("--object", required=True, help="name of the object whose BRDF is designed")
    ap.add_argument("--strokes", required=True, help="strokes JSON file")
    ap.add_argument("--out", default="out/inverse", help="output folder")
    ap.add_argument("--width", type=int, default=640, help="display width (the camera is resized)")
    ap.add_argument("--height", type=int, default=480, help="display height")
    ap.add_argument("--downsample", type=int, default=4, help="solving frame = display / downsample")
    ap.add_argument("--samples", type=int, default=1024, help="light samples (a power of two with --cuts)")
    ap.add_argument("--kd", type=float, default=0.3, help="diffuse albedo rho_d")
    ap.add_argument("--f0", type=float, default=0.9, help="Schlick F0")
    ap.add_argument("--unconstrained", action="store_true", help="allow physically impossible BRDFs")
    ap.add_argument("--cuts", action="store_true", help="visibility-cut clustering for the transfer functions")
    ap.add_argument("--keep-weight", type=float, default=1.0, help="fit weight of unpainted object pixels")
    ap.add_argument("--rotate", type=float, default=0.0, help="rotate the environment (radians) for the re-render")
    ap.add_argument("--render-scale", type=float, default=1.0, help="re-render size relative to the display")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    try:
        scene = load_scene(args.scene)
        scene = scene.with_resolution(args.width, args.height)
        strokes, size = load_strokes(args.strokes)
        cfg = DesignConfig(
            args.object,
            args.downsample,
            args.samples,
            args.kd,
            args.f0,
            not args.unconstrained,
            args.cuts,
            args.keep_weight,
            args.rotate,
            args.render_scale,
            args.seed,
        )
        summary = design(scene, strokes, cfg, args.out, display_size=size)
    except TorchBRDFError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
