"""The ``torch-brdf`` command line: ``demo``, ``render``, ``info``, ``precompute``,
``fit-strokes``, ``precompute-visibility``, ``relight`` and ``editor``.

Failures end a command with ONE line on stderr (``error: ...``) and a non-zero exit status,
never a traceback (``torch-brdf --debug COMMAND ...`` prints it as well):

* 2 — bad input: a :class:`~torch_brdf.errors.TorchBRDFError` (bad scene file, option,
  JSON, record, ...); options are checked before any scene is loaded or work is started;
* 1 — the system failed us: I/O errors (missing folder, permission denied, read-only file
  system, disk full, ...), out of memory, or an internal error (a bug: please report it
  with the ``--debug`` traceback);
* 130 — interrupted (Ctrl-C); finished tiles/chunks/checkpoints are kept for ``--resume``.
"""

from __future__ import annotations

import errno
import functools
import json
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import typer

from ._checks import (
    MAX_BANDS,
    MAX_CUBEMAP_RESOLUTION,
    MAX_IMAGE_SIDE,
    check_count,
    check_image_size,
    check_int,
    check_real,
)
from .errors import SceneError, TorchBRDFError, ValueRangeError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="torch_brdf: BRDF design in the final scene.",
)

#: samples per pixel (or light samples) accepted on the command line
MAX_SAMPLES = 1 << 20
#: surface vertices per path accepted on the command line
MAX_BOUNCES = 64

_STATE = {"debug": False}


@app.callback()
def _main(
    debug: bool = typer.Option(False, "--debug", help="On failure print the full traceback, not just one line."),
):
    _STATE["debug"] = debug


_OS_ERRORS = {
    errno.ENOSPC: "disk full",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.ENOENT: "no such file or folder",
    errno.ENOTDIR: "not a folder",
    errno.EISDIR: "is a folder",
    errno.EEXIST: "exists already (a file where a folder is needed?)",
}


def describe_failure(exc: BaseException) -> tuple[str, int]:
    """The one-line message and exit status of a failed command (module docstring)."""
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted; finished tiles, chunks and checkpoints are kept for --resume", 130
    if isinstance(exc, TorchBRDFError):
        return str(exc), 2
    if isinstance(exc, MemoryError):
        return "out of memory; lower --resolution, --spp or the series, or free memory", 1
    if isinstance(exc, OSError):
        what = _OS_ERRORS.get(exc.errno, exc.strerror or type(exc).__name__)
        where = exc.filename if exc.filename is not None else str(exc)
        return f"{what}: {where}", 1
    return f"internal error ({type(exc).__name__}: {exc}); rerun with --debug and report the traceback", 1


def _cli(fn: Callable) -> Callable:
    """Run a command; turn any failure into one line on stderr and an exit status."""

    @functools.wraps(fn)
    def run(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except typer.Exit:
            raise
        except (Exception, KeyboardInterrupt) as exc:
            message, code = describe_failure(exc)
            if _STATE["debug"]:
                traceback.print_exc()
            typer.secho("error: " + " ".join(message.split()), fg=typer.colors.RED, err=True)
            raise typer.Exit(code=code) from None

    return run


def _json_object(text: str | None, option: str) -> dict | None:
    """Parse a JSON option that must be an object (``None`` stays ``None``)."""
    if text is None:
        return None
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueRangeError(f"{option} is not valid JSON: {exc}") from None
    if not isinstance(value, dict):
        raise ValueRangeError(f"{option} must be a JSON object; got {type(value).__name__}")
    return value


def load_scene(spec: str, resolution: int | None = None):
    """A built-in scene by name (``cornell_box``, ``teatray``, ``ring``, ``bunny_plane``) or
    a TOML scene file; ``resolution`` overrides the image size (square)."""
    from .scene import BUILTIN_SCENES, Scene

    if resolution is not None:
        check_image_size(resolution, resolution, "--resolution")
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


_RESOLUTION = {"min": 8, "max": MAX_IMAGE_SIDE}
_SPP = {"min": 1, "max": MAX_SAMPLES}
_BOUNCES = {"min": 1, "max": MAX_BOUNCES}


@app.command()
@_cli
def demo(
    out: Path = typer.Option(Path("out/cornell_box"), help="Output path without suffix (.exr and .png are written)."),
    resolution: int = typer.Option(256, **_RESOLUTION, help="Image width = height."),
    spp: int = typer.Option(16, **_SPP, help="Samples per pixel."),
    bounces: int = typer.Option(4, **_BOUNCES, help="Surface vertices per path (1 = direct lighting)."),
    seed: int = typer.Option(0, min=0, help="Random seed."),
):
    """Path-trace the built-in Cornell box and write an EXR and an sRGB PNG."""
    scene = load_scene("cornell_box", resolution)
    typer.echo(json.dumps(_render_to(scene, out, spp, bounces, seed, exposure=0.0, checkpoint=False)))


@app.command()
@_cli
def render(
    scene: str = typer.Argument(..., help="Built-in scene name or a TOML scene file."),
    out: Path = typer.Option(Path("out/render"), help="Output path without suffix (.exr and .png)."),
    resolution: int = typer.Option(None, **_RESOLUTION, help="Override the image size (square)."),
    spp: int = typer.Option(16, **_SPP),
    bounces: int = typer.Option(4, **_BOUNCES, help="Surface vertices per path (1 = direct lighting)."),
    seed: int = typer.Option(0, min=0),
    exposure: float = typer.Option(0.0, help="PNG exposure in stops."),
    resume: bool = typer.Option(True, help="Keep a checkpoint next to the output and resume from it."),
):
    """Path-trace a scene (its materials' BRDFs) to EXR and PNG."""
    check_real(exposure, "--exposure")
    info = _render_to(load_scene(scene, resolution), out, spp, bounces, seed, exposure, checkpoint=resume)
    typer.echo(json.dumps(info))


@app.command()
@_cli
def info(scene: str = typer.Argument(..., help="Built-in scene name or a TOML scene file.")):
    """Print scene statistics as JSON: objects, triangles, bounds, lights, camera."""
    typer.echo(json.dumps(load_scene(scene).info(), indent=2))


_STORAGES = ("float32", "float16")


@app.command()
@_cli
def precompute(
    scene: str = typer.Argument(..., help="Built-in scene name or a TOML scene file."),
    out: Path = typer.Option(Path("out/tensors.npz"), help="Output tensor file (.npz, versioned, checksummed)."),
    series: str = typer.Option("64,1,1,1", help="BRDF series (J_N,...,J_1) from the eye; its length = bounces."),
    spp: int = typer.Option(64, **_SPP, help="Paths per pixel."),
    resolution: int = typer.Option(None, **_RESOLUTION, help="Override the image size (square)."),
    seed: int = typer.Option(0, min=0),
    bases: str = typer.Option(None, help='JSON per-object basis overrides, e.g. \'{"left": {"J": 8}}\'.'),
    env_point_lights: int = typer.Option(None, min=1, help="Sample the environment as K median-cut point lights."),
    storage: str = typer.Option("float32", help="float32 or float16 (half the bytes, rel. error <= 4.9e-4)."),
    resume: bool = typer.Option(True, help="Keep finished tiles in OUT.tiles/ and resume from them."),
):
    """Precompute the multibounce polynomial tensors of a scene's view (Ben-Artzi et al. 2008)."""
    from .records.cache import remove_cache
    from .transport.polynomial import Series, precompute_polynomial

    # every option is checked before the scene is loaded and the precompute starts
    parsed = Series.parse(series)
    check_count(parsed.eye, "--series bands per bounce", MAX_BANDS)
    if storage not in _STORAGES:
        raise ValueRangeError(f"--storage must be one of {_STORAGES}; got {storage!r}")
    overrides = _json_object(bases, "--bases")
    for name, spec in (overrides or {}).items():
        if not isinstance(spec, dict):
            raise ValueRangeError(f"--bases: the value for {name!r} must be a JSON object; got {spec!r}")
        if "J" in spec:
            check_int(spec["J"], f"--bases {name}.J", 1, MAX_BANDS)
    sc = load_scene(scene, resolution)
    tiles = out.with_suffix(".tiles") if resume else None
    t0 = time.perf_counter()
    T = precompute_polynomial(
        sc, parsed, spp=spp, seed=seed, bases=overrides, env_point_lights=env_point_lights, checkpoint=tiles
    )
    seconds = time.perf_counter() - t0
    T.save(out, storage=storage)
    remove_cache(tiles)
    mb = {str(k): round(v / 2**20, 3) for k, v in T.memory_per_bounce().items()}
    info = {"out": str(out), "seconds": round(seconds, 3), "series": series, "spp": spp, "mb_per_bounce": mb}
    info["rays"] = T.meta["rays"]
    typer.echo(json.dumps(info))


@app.command("fit-strokes")
@_cli
def fit_strokes(
    scene: str = typer.Argument(..., help="Built-in scene name or a TOML scene file."),
    obj: str = typer.Option(..., "--object", help="Object whose BRDF is designed."),
    strokes: Path = typer.Option(..., help="Strokes JSON file (see torch_brdf.inverse.design)."),
    out: Path = typer.Option(Path("out/inverse"), help="Output folder."),
    width: int = typer.Option(640, **_RESOLUTION),
    height: int = typer.Option(480, **_RESOLUTION),
    downsample: int = typer.Option(4, min=1, max=64, help="Solving frame = display / downsample."),
    samples: int = typer.Option(1024, **_SPP, help="Light samples."),
    kd: float = typer.Option(0.3, help="Diffuse albedo rho_d."),
    f0: float = typer.Option(0.9, help="Schlick F0."),
    unconstrained: bool = typer.Option(False, help="Allow physically impossible BRDFs."),
    cuts: bool = typer.Option(False, help="Visibility-cut clustering for the transfer functions."),
    rotate: float = typer.Option(0.0, help="Environment rotation (radians) for the re-render."),
    seed: int = typer.Option(0, min=0),
):
    """Inverse BRDF design: fit SRBF coefficients to painted strokes and re-render (Iwasaki et al.)."""
    from .inverse.design import DesignConfig, design, load_strokes

    check_image_size(width, height, "--width/--height")
    for value, option in ((kd, "--kd"), (f0, "--f0"), (rotate, "--rotate")):
        check_real(value, option)
    st, size = load_strokes(strokes)
    sc = load_scene(scene).with_resolution(width, height)
    cfg = DesignConfig(obj, downsample, samples, kd, f0, not unconstrained, cuts, 1.0, rotate, 1.0, seed)
    typer.echo(json.dumps(design(sc, st, cfg, out, display_size=size)))


@app.command("precompute-visibility")
@_cli
def precompute_visibility_cmd(
    scene: str = typer.Argument(..., help="Built-in scene name or a TOML scene file."),
    out: Path = typer.Option(Path("out/visibility.npz"), help="Output record (.npz, versioned, checksummed)."),
    resolution: int = typer.Option(64, help="Cubemap texels per face side (a multiple of 16: 64 or 128)."),
    supersample: int = typer.Option(1, min=1, max=16, help="k x k rays per texel (k > 1: anti-aliased, needs --bits)."),
    bits: int = typer.Option(0, help="0 = binary maps; 2, 6 or 8 = quantised graded maps."),
    chunk: int = typer.Option(512, min=1, help="Vertices per checkpointed work unit."),
    resume: bool = typer.Option(True, help="Keep finished chunks in OUT.chunks/ and resume from them."),
):
    """Per-vertex visibility cubemaps for all-frequency relighting (Inger et al.)."""
    from .records.cache import remove_cache
    from .sphere.cubemap import CubemapBlocks
    from .transport.visibility import BITS, precompute_visibility

    check_int(resolution, "--resolution", 16, MAX_CUBEMAP_RESOLUTION)
    CubemapBlocks(resolution, 16)  # a multiple of the block size
    if bits not in BITS:
        raise ValueRangeError(f"--bits must be one of {BITS}; got {bits}")
    sc = load_scene(scene)
    ck = out.parent / (out.name + ".chunks") if resume else None
    t0 = time.perf_counter()
    vis = precompute_visibility(sc, resolution, 16, supersample, bits, chunk, checkpoint=ck)
    seconds = time.perf_counter() - t0
    out.parent.mkdir(parents=True, exist_ok=True)
    vis.save(out)
    remove_cache(ck)
    info = {
        "out": str(out),
        "vertices": len(vis.vertices),
        "cubemap": f"{resolution}x{resolution}x6",
        "bytes_per_vertex": round(vis.bytes_per_vertex, 1),
        "seconds": round(seconds, 3),
    }
    typer.echo(json.dumps(info))


@app.command()
@_cli
def relight(
    scene: str = typer.Argument(..., help="Built-in scene name or a TOML scene file (as precomputed)."),
    visibility: Path = typer.Option(..., help="Record written by precompute-visibility."),
    out: Path = typer.Option(Path("out/relight"), help="Output path without suffix (.exr and .png)."),
    rotate: float = typer.Option(0.0, help="Turn the environment map about +y (radians)."),
    method: str = typer.Option("adaptive", help="adaptive (ours), standard, or haar (1% of coefficients)."),
    exposure: float = typer.Option(0.0, help="PNG exposure in stops."),
):
    """Render a frame of per-vertex direct lighting with locally adaptive triple products."""
    from .io import write_exr, write_png
    from .render.triple import METHODS, TripleProductRenderer
    from .transport.visibility import VertexVisibility

    if method not in METHODS:
        raise ValueRangeError(f"--method must be one of {METHODS}; got {method!r}")
    check_real(rotate, "--rotate")
    check_real(exposure, "--exposure")
    sc = load_scene(scene)
    vis = VertexVisibility.load(visibility)
    r = TripleProductRenderer(sc, vis)
    if rotate:
        r.set_lighting(r.envmap.rotated(rotate))
    t0 = time.perf_counter()
    image, stats = r.render(method=method)
    seconds = time.perf_counter() - t0
    out = out.with_suffix("")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_exr(out.with_suffix(".exr"), image)
    write_png(out.with_suffix(".png"), image, exposure=exposure)
    info = {"exr": str(out.with_suffix(".exr")), "png": str(out.with_suffix(".png")), "seconds": round(seconds, 3)}
    if stats is not None:
        info["stats"] = stats.as_dict()
    typer.echo(json.dumps(info))


@app.command()
@_cli
def editor(
    source: str = typer.Argument(..., help="Tensors file (.npz from precompute), built-in scene name or TOML scene."),
    scene: str = typer.Option(None, help="The scene of a tensors file (default: the one named in the file)."),
    resolution: int = typer.Option(128, **_RESOLUTION, help="Image size when precomputing a scene."),
    spp: int = typer.Option(16, **_SPP, help="Paths per pixel when precomputing a scene."),
    series: str = typer.Option("64,1,1,1", help="BRDF series when precomputing a scene."),
    cache: Path = typer.Option(Path("out/editor"), help="Where precomputed tensors are kept for the next start."),
    gplvm: Path = typer.Option(None, help="A GPLVM fit of NBRDF materials: shows the measured-material map."),
    port: int = typer.Option(None, min=1, max=65535, help="Port on 127.0.0.1 (default: a free one)."),
):
    """Serve the interactive material editor (Voila) on 127.0.0.1 and print its URL."""
    from .editor.server import serve
    from .transport.polynomial import Series

    check_count(Series.parse(series).eye, "--series bands per bounce", MAX_BANDS)
    config = {"source": source, "scene": scene, "resolution": resolution, "spp": spp, "series": series}
    config["gplvm"] = str(gplvm.resolve()) if gplvm else None
    serve({**config, "seed": 0, "cache_dir": str(cache)}, port=port, echo=typer.echo)


if __name__ == "__main__":  # pragma: no cover
    app()
