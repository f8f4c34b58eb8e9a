"""The ``torch-brdf`` command line: ``demo``, ``render``, ``info`` and ``precompute``."""

from __future__ import annotations

import json
import time
from pathlib import Path

import typer

from .errors import SceneError, TorchBRDFError

app = typer.Typer(add_completion=False, no_args_is_help=True, help="torch_brdf: BRDF design in the final scene.")


def load_scene(spec: str, resolution: int | None = None):
    """A built-in scene by name (``cornell_box``, ``teatray``, ``ring``, ``bunny_plane``) or
    a TOML scene file; ``resolution`` overrides the image size (square)."""
    from .scene import BUILTIN_SCENES, Scene

    if spec in BUILTIN_SCENES:
        return BUILTIN_SCENES[spec](resolution or 256)
    if spec.endswith(".toml") or Path(spec).is_file():
        scene = Scene.from_toml(spec)
        return scene.with_resolution(resolution) if resolution else scene
    raise SceneError(f"unknown scene {spec!r}: give a TOML file or one of {sorted(BUILTIN_SCENES)}")


def _render_to(scene, out: Path, spp: int, bounces: int, seed: int, exposure: float, checkpoint: bool) -> dict:
    from .io import write_exr, write_png
    from .transport.pathtrace import path_trace

    out = out.with_suffix("")
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    ckpt = out.parent / (out.name + ".ckpt.npz") if checkpoint else None
    image = path_trace(scene, spp=spp, max_bounces=bounces, seed=seed, checkpoint=ckpt)
    seconds = time.perf_counter() - t0
    write_exr(out.with_suffix(".exr"), image)
    write_png(out.with_suffix(".png"), image, exposure=exposure)
    if ckpt is not None and ckpt.exists():
        ckpt.unlink()
    return {
        "exr": str(out.with_suffix(".exr")),
        "png": str(out.with_suffix(".png")),
        "seconds": round(seconds, 3),
        "spp": spp,
        "max_bounces": bounces,
        "size": [scene.camera.width, scene.camera.height],
    }


def _fail(exc: TorchBRDFError) -> None:
    typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code=2)


@app.command()
def demo(
    out: Path = typer.Option(Path("out/cornell_box"), help="Output path without suffix (.exr and .png are written)."),
    resolution: int = typer.Option(256, min=8, help="Image width = height."),
    spp: int = typer.Option(16, min=1, help="Samples per pixel."),
    bounces: int = typer.Option(4, min=1, help="Surface vertices per path (1 = direct lighting)."),
    seed: int = typer.Option(0, help="Random seed."),
):
    """Path-trace the built-in Cornell box and write an EXR and an sRGB PNG."""
    try:
        scene = load_scene("cornell_box", resolution)
        info = _render_to(scene, out, spp, bounces, seed, exposure=0.0, checkpoint=False)
    except TorchBRDFError as exc:
        _fail(exc)
    typer.echo(json.dumps(info))


@app.command()
def render(
    scene: str = typer.Argument(..., help="Built-in scene name or a TOML scene file."),
    out: Path = typer.Option(Path("out/render"), help="Output path without suffix (.exr and .png)."),
    resolution: int = typer.Option(None, min=8, help="Override the image size (square)."),
    spp: int = typer.Option(16, min=1),
    bounces: int = typer.Option(4, min=1, help="Surface vertices per path (1 = direct lighting)."),
    seed: int = typer.Option(0),
    exposure: float = typer.Option(0.0, help="PNG exposure in stops."),
    resume: bool = typer.Option(True, help="Keep a checkpoint next to the output and resume from it."),
):
    """Path-trace a scene (its materials' BRDFs) to EXR and PNG."""
    try:
        info = _render_to(load_scene(scene, resolution), out, spp, bounces, seed, exposure, checkpoint=resume)
    except TorchBRDFError as exc:
        _fail(exc)
    typer.echo(json.dumps(info))


@app.command()
def info(scene: str = typer.Argument(..., help="Built-in scene name or a TOML scene file.")):
    """Print scene statistics as JSON: objects, triangles, bounds, lights, camera."""
    try:
        typer.echo(json.dumps(load_scene(scene).info(), indent=2))
    except TorchBRDFError as exc:
        _fail(exc)


@app.command()
def precompute(
    scene: str = typer.Argument(..., help="Built-in scene name or a TOML scene file."),
    out: Path = typer.Option(Path("out/tensors.npz"), help="Output tensor file (.npz, versioned, checksummed)."),
    series: str = typer.Option("64,1,1,1", help="BRDF series (J_N,...,J_1) from the eye; its length = bounces."),
    spp: int = typer.Option(64, min=1, help="Paths per pixel."),
    resolution: int = typer.Option(None, min=8, help="Override the image size (square)."),
    seed: int = typer.Option(0),
    bases: str = typer.Option(None, help='JSON per-object basis overrides, e.g. \'{"left": {"J": 8}}\'.'),
    env_point_lights: int = typer.Option(None, min=1, help="Sample the environment as K median-cut point lights."),
    storage: str = typer.Option("float32", help="float32 or float16 (half the bytes, rel. error <= 4.9e-4)."),
    resume: bool = typer.Option(True, help="Keep finished tiles in OUT.tiles/ and resume from them."),
):
    """Precompute the multibounce polynomial tensors of a scene's view (Ben-Artzi et al. 2008)."""
    import shutil

    from .transport.polynomial import precompute_polynomial

    try:
        sc = load_scene(scene, resolution)
        overrides = json.loads(bases) if bases else None
        tiles = out.with_suffix(".tiles") if resume else None
        t0 = time.perf_counter()
        T = precompute_polynomial(
            sc, series, spp=spp, seed=seed, bases=overrides, env_point_lights=env_point_lights, checkpoint=tiles
        )
        seconds = time.perf_counter() - t0
        T.save(out, storage=storage)
        if tiles is not None and tiles.exists():
            shutil.rmtree(tiles)
    except json.JSONDecodeError as exc:
        typer.secho(f"error: --bases is not valid JSON: {exc}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=2) from None
    except TorchBRDFError as exc:
        _fail(exc)
    mb = {str(k): round(v / 2**20, 3) for k, v in T.memory_per_bounce().items()}
    info = {"out": str(out), "seconds": round(seconds, 3), "series": series, "spp": spp, "mb_per_bounce": mb}
    info["rays"] = T.meta["rays"]
    typer.echo(json.dumps(info))


@app.command("fit-strokes")
def fit_strokes(
    scene: str = typer.Argument(..., help="Built-in scene name or a TOML scene file."),
    obj: str = typer.Option(..., "--object", help="Object whose BRDF is designed."),
    strokes: Path = typer.Option(..., help="Strokes JSON file (see torch_brdf.inverse.design)."),
    out: Path = typer.Option(Path("out/inverse"), help="Output folder."),
    width: int = typer.Option(640, min=8),
    height: int = typer.Option(480, min=8),
    downsample: int = typer.Option(4, min=1, help="Solving frame = display / downsample."),
    samples: int = typer.Option(1024, min=1, help="Light samples."),
    kd: float = typer.Option(0.3, help="Diffuse albedo rho_d."),
    f0: float = typer.Option(0.9, help="Schlick F0."),
    unconstrained: bool = typer.Option(False, help="Allow physically impossible BRDFs."),
    cuts: bool = typer.Option(False, help="Visibility-cut clustering for the transfer functions."),
    rotate: float = typer.Option(0.0, help="Environment rotation (radians) for the re-render."),
    seed: int = typer.Option(0),
):
    """Inverse BRDF design: fit SRBF coefficients to painted strokes and re-render (Iwasaki et al.)."""
    from .inverse.design import DesignConfig, design, load_strokes

    try:
        sc = load_scene(scene).with_resolution(width, height)
        st, size = load_strokes(strokes)
        cfg = DesignConfig(obj, downsample, samples, kd, f0, not unconstrained, cuts, 1.0, rotate, 1.0, seed)
        typer.echo(json.dumps(design(sc, st, cfg, out, display_size=size)))
    except TorchBRDFError as exc:
        _fail(exc)


if __name__ == "__main__":  # pragma: no cover
    app()
