"""The ``torch-brdf`` command line: ``demo``, ``render``, ``info``, ``precompute``, ``edit``,
``fit-gplvm``, ``manifold``, ``fit-strokes``, ``fit-image``, ``precompute-visibility``, ``relight``,
``editor``, ``fetch-data`` and ``report``.

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
import hashlib
import json
import re
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import typer

from ._checks import (
    MAX_IMAGE_SIDE,
    check_image_size,
    check_real,
)
from .errors import FileFormatError, SceneError, TorchBRDFError, ValueRangeError, WriteError

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

_STATE = {"debug": False, "progress": False}

#: ``--progress/--no-progress`` of the long commands (default: on when attached to a terminal).
PROGRESS = typer.Option(None, "--progress/--no-progress", help="Progress bars (default: on in a terminal).")
#: ``--width`` / ``--height`` of every command that makes an image (``--resolution``: both at once)
WIDTH = typer.Option(None, min=8, max=MAX_IMAGE_SIDE, help="Image width (default: --resolution, else the scene's).")
HEIGHT = typer.Option(None, min=8, max=MAX_IMAGE_SIDE, help="Image height (default: --resolution, else the scene's).")


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            typer.echo(f"torch_brdf {version('torch_brdf')}")
        except PackageNotFoundError:  # pragma: no cover - a source tree that is not installed
            typer.echo("torch_brdf (not installed)")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the package version and exit."
    ),
    debug: bool = typer.Option(False, "--debug", help="On failure print the full traceback, not just one line."),
    allow_outside: bool = typer.Option(
        False, "--allow-outside", help="Scene files may reference files outside their folder."
    ),
    substitute: bool = typer.Option(
        False, "--substitute", help="Replace unsupported parts of scene files by stated substitutes (a warning)."
    ),
):
    """torch_brdf: BRDF design in the final scene."""
    _STATE["debug"] = debug
    _STATE["allow_outside"], _STATE["substitute"] = allow_outside, substitute
    from .data import progress_default

    try:  # a bad $TORCH_BRDF_PROGRESS fails every command up front, not after the work
        progress = progress_default()
    except ValueRangeError as exc:
        typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=2) from None
    _STATE["progress"] = progress


#: commands that never import torch (no "loading torch" line)
_NO_TORCH = frozenset({"fetch_data_cmd"})


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
    if isinstance(exc, TorchBRDFError) and not isinstance(exc, WriteError):
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
        on = kwargs.get("progress")
        on = _STATE["progress"] if on is None else on
        if on and fn.__name__ not in _NO_TORCH and "torch" not in sys.modules:
            # importing torch takes 1-2 s on a quiet machine and 5-10 s on a busy one: say so
            typer.echo(f"torch-brdf {fn.__name__.removesuffix('_cmd').replace('_', '-')}: loading torch ...", err=True)
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


def _file_out(out: Path) -> None:
    """Refuse an ``--out`` without a file name before any work (the outputs add suffixes)."""
    if out.name in ("", ".", ".."):
        raise ValueRangeError(f"--out needs a file name; got {str(out)!r}")


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


def load_scene(
    spec: str, resolution: int | None = None, width: int | None = None, height: int | None = None, make=None
):
    """:func:`torch_brdf.scene.load_scene` (built-in name or scene file; or ``make(resolution)``) at
    ``--width`` x ``--height``; ``--resolution`` N is the N x N shorthand; an unset side keeps
    ``resolution``, else the scene's."""
    from .scene import load_scene as load

    if resolution is not None:
        check_image_size(resolution, resolution, "--resolution")
    if width is not None or height is not None:
        check_image_size(width or 8, height or 8, "--width/--height")  # before the scene is loaded
    options = {"allow_outside": bool(_STATE.get("allow_outside")), "substitute": bool(_STATE.get("substitute"))}
    scene = make(resolution or 256) if make is not None else load(spec, resolution, **options)
    if width is None and height is None:
        return scene
    return scene.with_resolution(width or scene.camera.width, height or scene.camera.height)


#: per settings kind: its class (module, name) and the options named otherwise than their field
_SETTINGS = {
    "polynomial": ("torch_brdf.transport.polynomial.settings", "PolynomialSettings", {"mixture": "--sampler"}),
    "visibility": ("torch_brdf.transport.visibility", "VisibilitySettings", {"resolution": "--cubemap"}),
    "path": ("torch_brdf.transport.pathtrace", "PathTraceSettings", {"max_bounces": "--bounces"}),
}


def _settings(kind: str, **options):
    """The settings object of a producer (``kind`` in :data:`_SETTINGS`) from command-line
    options, checked by the object itself; a refused value is named as its option (``--series ...``)."""
    import importlib

    from .errors import TorchBRDFError

    module, name, renamed = _SETTINGS[kind]
    try:
        return getattr(importlib.import_module(module), name)(**options)
    except TorchBRDFError as exc:
        field = getattr(exc, "setting", None)
        if field is not None:
            option, message = renamed.get(field, "--" + field.replace("_", "-")), str(exc)
            exc.args = (option + message[len(field) :] if message.startswith(field + " ") else f"{option}: {message}",)
        raise


def _quick_scene(spec: str | None, mesh: Path | None, envmap: Path | None, resolution, width, height):
    """SCENE, or ``--mesh FILE`` (:func:`torch_brdf.scene.mesh_scene`); ``--envmap FILE`` replaces
    the scene's lights by that lat-long map."""
    import dataclasses

    from .scene import EnvironmentMap, mesh_scene

    if (spec is None) == (mesh is None):
        which = "not both" if mesh is not None else "neither was given"  # `render --envmap X` said "not both"
        raise ValueRangeError(
            f"give a SCENE (built-in name or a .toml, .gltf, .glb, .xml or .obj file) or --mesh FILE; {which}"
        )
    for path, option in ((mesh, "--mesh"), (envmap, "--envmap")):
        if path is not None and not path.is_file():
            raise SceneError(f"{option}: no such file: {path}")
    env = EnvironmentMap.from_file(envmap) if envmap is not None else None
    if mesh is not None:
        sc = load_scene(f"mesh:{mesh}", resolution, width, height, lambda r: mesh_scene(mesh, r, env))
        return sc
    sc = load_scene(spec, resolution, width, height)
    return sc if env is None else dataclasses.replace(sc, lights=[env])


def _render_to(scene, out: Path, settings, seed: int, exposure, checkpoint: bool, progress: bool | None = None) -> dict:
    """Path-trace ``scene`` at ``settings`` (a :class:`~torch_brdf.transport.pathtrace.PathTraceSettings`)
    to ``out`` .exr and .png."""
    from .io import write_exr
    from .transport.pathtrace import path_trace

    out = out.with_suffix("")
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    ckpt = out.parent / (out.name + ".ckpt.npz") if checkpoint else None
    image = path_trace(scene, settings, seed=seed, checkpoint=ckpt, progress=progress)
    seconds = time.perf_counter() - t0
    write_exr(out.with_suffix(".exr"), image)
    stops = _preview(out.with_suffix(".png"), image, exposure)
    if ckpt is not None and ckpt.exists():
        ckpt.unlink()
    return {
        "exr": str(out.with_suffix(".exr")),
        "png": str(out.with_suffix(".png")),
        "seconds": round(seconds, 3),
        "spp": settings.spp,
        "max_bounces": settings.max_bounces,
        "size": [scene.camera.width, scene.camera.height],
        "exposure": stops,
    }


def _preview(path: Path, image, exposure: float | None) -> float:
    """Write the sRGB PNG preview; ``exposure`` None: automatic (the 99th percentile of the
    lit pixels' luminance at white). Returns the exposure used (stops)."""
    from .io import auto_exposure, write_png

    stops = auto_exposure(image) if exposure is None else float(exposure)
    write_png(path, image, exposure=stops)
    return round(stops, 3)


def _write_image(out: Path, image, exposure: float | None, seconds: float) -> dict:
    """Write ``out``.exr (linear) and ``out``.png (sRGB preview, :func:`_preview`); returns the
    summary fields every image-making command prints (paths, seconds, exposure in stops)."""
    from .io import write_exr

    out = out.with_suffix("")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_exr(out.with_suffix(".exr"), image)
    stops = _preview(out.with_suffix(".png"), image, exposure)
    paths = {"exr": str(out.with_suffix(".exr")), "png": str(out.with_suffix(".png"))}
    return paths | {"seconds": round(seconds, 3), "exposure": stops}


#: ``relight`` warns about objects with fewer vertices (per-vertex lighting cannot show detail on them)
COARSE_VERTICES = 64
_RESOLUTION = {"min": 8, "max": MAX_IMAGE_SIDE}
_SPP = {"min": 1, "max": MAX_SAMPLES}
_BOUNCES = {"min": 1, "max": MAX_BOUNCES}


@app.command()
@_cli
def demo(
    out: Path = typer.Option(Path("out/cornell_box"), help="Output path without suffix (.exr and .png are written)."),
    resolution: int = typer.Option(256, **_RESOLUTION, help="Image width = height."),
    width: int = WIDTH,
    height: int = HEIGHT,
    spp: int = typer.Option(16, **_SPP, help="Samples per pixel."),
    bounces: int = typer.Option(4, **_BOUNCES, help="Surface vertices per path (1 = direct lighting)."),
    seed: int = typer.Option(0, min=0, help="Random seed."),
    progress: bool = PROGRESS,
):
    """Path-trace the built-in Cornell box and write an EXR and an sRGB PNG."""
    _file_out(out)
    settings = _settings("path", spp=spp, max_bounces=bounces)
    scene = load_scene("cornell_box", resolution, width, height)
    info = _render_to(scene, out, settings, seed, exposure=0.0, checkpoint=False, progress=progress)
    typer.echo(json.dumps(info))


@app.command()
@_cli
def render(
    scene: str = typer.Argument(
        None, help="Built-in scene name or a scene file: .toml, .gltf, .glb, .xml, .obj (or --mesh)."
    ),
    mesh: Path = typer.Option(None, help="Quick scene: this mesh file (OBJ, PLY, ...) on a plane, framed."),
    envmap: Path = typer.Option(None, help="Light the scene with this lat-long EXR instead of its own lights."),
    out: Path = typer.Option(Path("out/render"), help="Output path without suffix (.exr and .png)."),
    resolution: int = typer.Option(None, **_RESOLUTION, help="Override the image size (square)."),
    width: int = WIDTH,
    height: int = HEIGHT,
    spp: int = typer.Option(16, **_SPP),
    bounces: int = typer.Option(4, **_BOUNCES, help="Surface vertices per path (1 = direct lighting)."),
    seed: int = typer.Option(0, min=0),
    exposure: float = typer.Option(None, help="PNG exposure in stops (default: automatic, see _preview)."),
    resume: bool = typer.Option(True, help="Keep a checkpoint next to the output and resume from it."),
    progress: bool = PROGRESS,
):
    """Path-trace a scene (its materials' BRDFs) to EXR and PNG."""
    _file_out(out)
    if exposure is not None:
        check_real(exposure, "--exposure")
    settings = _settings("path", spp=spp, max_bounces=bounces)
    sc = _quick_scene(scene, mesh, envmap, resolution, width, height)
    info = _render_to(sc, out, settings, seed, exposure, checkpoint=resume, progress=progress)
    typer.echo(json.dumps(info))


@app.command()
@_cli
def info(scene: str = typer.Argument(..., help="Built-in scene name or a scene file: .toml .gltf .glb .xml .obj.")):
    """Print scene statistics as JSON: objects, triangles, bounds, lights, camera."""
    typer.echo(json.dumps(load_scene(scene).info(), indent=2))


#: ``--ray`` of the three precomputations (their tiles run as Ray tasks; default: this process)
RAY = typer.Option(
    None, help="Run tiles on Ray: 'auto' (start a local instance) or a cluster ADDRESS (pip install .[cluster])."
)
#: seconds ``--ray ADDRESS`` may take to accept a connection before the command gives up
RAY_CONNECT_TIMEOUT = 5.0
_LABEL = r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_HOST = re.compile(rf"(?=.{{1,253}}$){_LABEL}(\.{_LABEL})*")


def check_ray_address(address: str | None, timeout: float = RAY_CONNECT_TIMEOUT) -> None:
    """Refuse a ``--ray`` value before any work: ``auto``, or ``[ray://]HOST:PORT`` with a valid
    IPv4 address or host name and a port in 1..65535 that accepts a TCP connection within
    ``timeout`` seconds (Ray itself would retry for minutes).

    Raises:
        ValueRangeError: bad syntax, or nothing answers at the address.
    """
    import ipaddress
    import socket

    if address is None or address == "auto":
        return
    rest = address.removeprefix("ray://")
    host, sep, port = rest.rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise ValueRangeError(f"--ray must be 'auto' or HOST:PORT (e.g. 10.0.0.5:6379); got {address!r}")
    if not 1 <= int(port) <= 65535:
        raise ValueRangeError(f"--ray {address}: port must be in 1..65535; got {port}")
    if host.startswith("[") and host.endswith("]"):  # [IPv6]:PORT
        try:
            host = str(ipaddress.IPv6Address(host[1:-1]))
        except ValueError:
            raise ValueRangeError(f"--ray {address}: {host!r} is not an IPv6 address") from None
    elif host.replace(".", "").isdigit():
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            raise ValueRangeError(f"--ray {address}: {host!r} is not an IPv4 address") from None
    elif not _HOST.fullmatch(host):
        raise ValueRangeError(f"--ray {address}: {host!r} is not a host name")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as exc:
        why = f"no answer within {timeout:g} s" if isinstance(exc, TimeoutError) else exc.strerror
        raise ValueRangeError(f"--ray {address}: cannot connect ({(why or type(exc).__name__).lower()})") from None


def _parse_series(text: str):
    """``--series`` as a :class:`~torch_brdf.records.polynomial.Series`; its errors name the option."""
    from .records.polynomial import Series

    try:
        return Series.parse(text)
    except ValueRangeError as exc:
        raise ValueRangeError(f"--series {text!r}: {exc}") from None


def _check_record(path: Path | str, kind: str, option: str) -> None:
    """Refuse ``path`` before any work unless it is a record file of ``kind``."""
    from .io.arrays import read_kind

    if not Path(path).is_file():
        raise FileFormatError(f"{option}: no such file: {path}")
    found = read_kind(path)
    if found != kind:
        raise FileFormatError(f"{option}: {path} holds a {found!r} record; expected {kind!r}")


@app.command()
@_cli
def precompute(
    scene: str = typer.Argument(..., help="Built-in scene name or a scene file: .toml .gltf .glb .xml .obj."),
    out: Path = typer.Option(Path("out/tensors.npz"), help="Output tensor file (.npz, versioned, checksummed)."),
    series: str = typer.Option(
        None,
        help="A fixed BRDF series (J_N,...,J_1) from the eye, its length = bounces, instead of a plan (e.g. 64,16,1).",
    ),
    spp: int = typer.Option(None, **_SPP, help="Paths per pixel of a fixed series (default 64)."),
    resolution: int = typer.Option(None, **_RESOLUTION, help="Override the image size (square)."),
    width: int = WIDTH,
    height: int = HEIGHT,
    seed: int = typer.Option(0, min=0),
    bases: str = typer.Option(None, help='JSON per-object basis overrides, e.g. \'{"left": {"J": 8}}\'.'),
    env_point_lights: int = typer.Option(None, min=1, help="Sample the environment as K median-cut point lights."),
    storage: str = typer.Option("float32", help="float32 or float16 (half the bytes, rel. error <= 4.9e-4)."),
    resume: bool = typer.Option(
        True, help="Keep finished tiles in OUT with .tiles for .npz (out/tensors.tiles/) and resume from them."
    ),
    progress: bool = PROGRESS,
    error: float = typer.Option(
        None, min=0.0, help="Plan series, bases and spp for this relative RMSE (default 0.03 when planning)."
    ),
    seconds: float = typer.Option(
        None, min=0.0, help="The plan's precompute time budget in seconds (default 600 when planning)."
    ),
    ray: str = RAY,
    sampler: str = typer.Option(
        "default",
        help="Direction sampling: 'default' (70% cosine + Blinn 200, compiled), 'lobes' (LobeMixture: lobe "
        "widths + MIS on the glossy objects, for sharp edits) or 'stratified' (lobes, the eye vertex's light "
        "and direction samples stratified over each pixel's paths).",
    ),
):
    """Precompute the multibounce polynomial tensors of a scene's view (Ben-Artzi et al. 2008).

    By default the planner chooses series, bases, spp and light samples for a relative RMSE of
    0.03 within 600 s (--error, --seconds); --series (with --spp, --bases) runs a fixed series
    instead. The plan is printed and saved in the record."""
    _file_out(out)
    from .planner.gi import DEFAULT_ERROR, DEFAULT_SECONDS, precompute_planned
    from .records.cache import remove_cache
    from .transport.polynomial import LobeMixture, precompute_polynomial

    # every option is checked before the scene is loaded and the precompute starts
    samplers = {"default": None, "lobes": LobeMixture(), "stratified": LobeMixture(stratified=True)}
    if sampler not in samplers:
        raise ValueRangeError(f"--sampler must be one of {tuple(samplers)}; got {sampler!r}")
    fixed_series = series is not None or spp is not None or bases is not None
    if fixed_series and (error is not None or seconds is not None):
        raise ValueRangeError("--error/--seconds plan the series; --series/--spp/--bases fix it: give one or the other")
    settings = _settings(
        "polynomial",
        series="64,1,1,1" if series is None else series,
        spp=64 if spp is None else spp,
        bases=_json_object(bases, "--bases"),
        mixture=samplers[sampler],
        env_point_lights=env_point_lights,
        storage=storage,
    )
    check_ray_address(ray)
    sc = load_scene(scene, resolution, width, height)
    tiles = out.with_suffix(".tiles") if resume else None
    t0 = time.perf_counter()
    run = {"seed": seed, "checkpoint": tiles, "progress": progress, "executor": "local" if ray is None else "ray"}
    run["address"] = ray
    if not fixed_series:  # the planner decides series, bases, spp and light samples
        error = DEFAULT_ERROR if error is None else error
        seconds = DEFAULT_SECONDS if seconds is None else seconds
        T = precompute_planned(sc, settings, error=error, seconds=seconds, **run)
    else:
        T = precompute_polynomial(sc, settings, **run)
    if "plan" in T.meta:
        typer.echo(T.meta["plan"], err=True)
    seconds = time.perf_counter() - t0
    T.save(out, storage=settings.storage)
    remove_cache(tiles)
    mb = {str(k): round(v / 2**20, 3) for k, v in T.memory_per_bounce().items()}
    info = {"out": str(out), "seconds": round(seconds, 3), "series": T.series.key, "spp": T.meta["spp"]}
    info["mb_per_bounce"] = mb
    info["rays"] = T.meta["rays"]
    typer.echo(json.dumps(info))


def _tensors_scene(T, scene: str | None, resolution: int):
    """The scene of saved polynomial tensors ``T``: ``--scene``, else the name saved in them; its
    objects must be the tensors' (another scene's materials would be rendered onto them)."""
    name = scene or str(T.meta.get("scene", ""))
    try:
        sc = load_scene(name, resolution)
    except SceneError as exc:
        if scene is not None:
            raise
        raise SceneError(f"{exc}; the tensors were precomputed from scene {name!r}: pass it with --scene") from None
    names = [o.name for o in sc.objects]
    if names != list(T.object_names):
        raise SceneError(
            f"scene {sc.name!r} does not match the tensors: they hold objects {list(T.object_names)}, "
            f"the scene {names}; pass the precomputed scene with --scene"
        )
    return sc


def _retyped(material: dict, kind) -> dict:
    """``--set OBJECT.type=KIND``: a ``kind`` material keeping the parameters that model takes."""
    from .brdf.base import model_parameters

    params = model_parameters(str(kind))
    if params is None:
        return {**material, "type": kind}
    return {"type": kind, **{k: v for k, v in material.items() if k in params}}


def _parse_set(item: str) -> tuple[str, str, object]:
    """``OBJECT.PARAM=VALUE`` -> (object, param, value); VALUE is JSON or else a plain word."""
    key, sep, raw = item.partition("=")
    obj, dot, param = key.strip().rpartition(".")
    if not sep or not dot or not obj or not param:
        raise ValueRangeError(f"--set expects OBJECT.PARAM=VALUE (e.g. back.exponent=400); got {item!r}")
    try:
        value = json.loads(raw, parse_constant=lambda c: _not_finite(item))
    except json.JSONDecodeError:
        if re.search(r"(?i)\b(nan|inf|infinity)\b", raw):  # [0.5,0.5,inf] went on as a string
            _not_finite(item)
        value = raw.strip()
    return obj, param, value


def _not_finite(item: str):
    raise ValueRangeError(f"--set {item!r}: numbers must be finite (no nan or inf)")


@app.command()
@_cli
def edit(
    tensors: Path = typer.Argument(..., help="Tensors written by precompute."),
    sets: list[str] = typer.Option(
        [], "--set", help="OBJECT.PARAM=VALUE, repeatable: back.exponent=400, back.kd=[0.2,0.1,0.1], back.type=phong."
    ),
    scene: str = typer.Option(
        None, help="The precomputed scene, for its materials (default: the name saved in TENSORS)."
    ),
    out: Path = typer.Option(Path("out/edit"), help="Output path without suffix (.exr and .png)."),
    exposure: float = typer.Option(None, help="PNG exposure in stops (default: automatic, see _preview)."),
    exports: list[str] = typer.Option(
        [], "--export", help="OBJECT:FORMAT:FILE, repeatable: write the edited material (mitsuba, gltf, merl)."
    ),
    save_scene: Path = typer.Option(
        None, "--save-scene", help="Write the scene with the edits as a TOML scene file (re-opens with them)."
    ),
):
    """Render saved polynomial tensors with edited materials (no path tracing: dot products per pixel)."""
    _file_out(out)
    targets = [_parse_export(e) for e in exports]
    if save_scene is not None:
        _file_out(save_scene)
        save_scene.parent.mkdir(parents=True, exist_ok=True)
    from .records import PolynomialTensors
    from .render import PolynomialRenderer, apply_scene_textures

    edits = [_parse_set(s) for s in sets]  # before loading anything
    if exposure is not None:
        check_real(exposure, "--exposure")
    T = PolynomialTensors.load(tensors)
    sc = _tensors_scene(T, scene, 16)
    editable = {T.object_names[k] for k, b in enumerate(T.bases) if b is not None}
    by_name = {o.name: o for o in sc.objects}
    materials = {n: dict(sc.materials[by_name[n].material]) for n in editable}
    for obj, param, _ in edits:
        if obj not in materials:
            raise SceneError(f"--set {obj}.{param}: {obj!r} is not an editable object; choose from {sorted(materials)}")
    for obj, param, value in edits:  # a new model first: it keeps only the scene's parameters it takes
        if param == "type":
            materials[obj] = _retyped(materials[obj], value)
    for obj, param, value in edits:
        if param != "type":
            materials[obj][param] = value
    for obj, _, _ in targets:
        if obj not in materials:
            raise SceneError(f"--export {obj}: {obj!r} is not an editable object; choose from {sorted(materials)}")
    t0 = time.perf_counter()
    renderer = PolynomialRenderer(T, materials)
    apply_scene_textures(renderer, sc)  # textured objects: the texture at the eye vertex, its mean after
    image = renderer().detach()
    seconds = time.perf_counter() - t0
    info = _write_image(out, image, exposure, seconds)
    info["materials"] = {o: materials[o] for o in sorted({e[0] for e in edits})}
    if save_scene is not None:
        info["scene_file"] = str(_save_edited_scene(sc, T, materials, {e[0] for e in edits}, save_scene))
    if targets:
        from .export import export_material

        info["exports"] = [
            {"object": o, **asdict_report(export_material(materials[o], f, fmt, name=o))} for o, fmt, f in targets
        ]
    typer.echo(json.dumps(info))


def _save_edited_scene(sc, T, materials: dict, edited: set, path: Path) -> Path:
    """Save ``sc`` at the tensors' image size with each edited object's material under a key of
    its own (objects that shared the material keep the old one)."""
    import dataclasses

    from .export.scene_file import save_scene_toml
    from .scene import Scene

    table = {k: dict(v) for k, v in sc.materials.items()}
    objects = []
    for o in sc.objects:
        if o.name in edited:
            key = o.name if o.name not in table else f"{o.name}_edited"
            table[key] = materials[o.name]
            o = dataclasses.replace(o, material=key)
        objects.append(o)
    scene = Scene(objects, table, sc.lights, sc.camera, name=sc.name).with_resolution(T.width, T.height)
    return save_scene_toml(scene, path)


def _parse_export(item: str) -> tuple[str, str, Path]:
    """``OBJECT:FORMAT:FILE`` of ``--export`` (checked before any work)."""
    from .export import FORMATS

    parts = item.split(":", 2)
    if len(parts) != 3 or not all(parts):
        raise ValueRangeError(f"--export {item!r}: expected OBJECT:FORMAT:FILE, e.g. back:mitsuba:out/back.xml")
    obj, fmt, file = parts
    if fmt not in FORMATS:
        raise ValueRangeError(f"--export {item!r}: unknown format {fmt!r}; choose from {list(FORMATS)}")
    path = Path(file)
    _file_out(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return obj, fmt, path


def asdict_report(report) -> dict:
    """An :class:`~torch_brdf.export.ExportReport` as a JSON-ready dict."""
    import dataclasses

    return dataclasses.asdict(report)


@app.command("export")
@_cli
def export_cmd(
    material: str = typer.Argument(
        ..., help='A material as JSON (\'{"type": "lambert", "albedo": 0.5}\'), or SCENE:OBJECT, or a SCENE.'
    ),
    out: Path = typer.Argument(..., help="File to write: .xml (Mitsuba 3), .gltf (glTF 2.0) or .binary (MERL)."),
    fmt: str = typer.Option(None, "--format", help="mitsuba, gltf or merl (default: from the suffix of OUT)."),
    tolerance: float = typer.Option(None, min=0.0, help="Refuse a fit whose error is above this (relative L2)."),
    name: str = typer.Option("material", help="The material's id / name in the file."),
):
    """Export a material (exact where a stock model matches, else fitted) or a whole scene (Mitsuba XML)."""
    from .export import export_material, export_scene_mitsuba

    _file_out(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if material.lstrip().startswith("{"):
        try:
            spec = json.loads(material)
        except json.JSONDecodeError as exc:
            raise ValueRangeError(f"MATERIAL is not valid JSON: {exc}") from None
        report = export_material(spec, out, fmt, tolerance, name)
        typer.echo(json.dumps(asdict_report(report)))
        return
    spec_scene, _, obj = material.partition(":")
    sc = load_scene(spec_scene, None)
    if not obj:
        if (fmt or out.suffix.lstrip(".")) not in ("mitsuba", "xml"):
            raise ValueRangeError("a whole SCENE exports to Mitsuba XML only (OUT.xml)")
        reports = export_scene_mitsuba(sc, out, tolerance)
        typer.echo(json.dumps([asdict_report(r) for r in reports]))
        return
    by_name = {o.name: o for o in sc.objects}
    if obj not in by_name:
        raise SceneError(f"{material}: no object {obj!r} in the scene; objects: {sorted(by_name)}")
    label = obj if name == "material" else name
    report = export_material(sc.materials[by_name[obj].material], out, fmt, tolerance, label)
    typer.echo(json.dumps(asdict_report(report)))


@app.command("fit-gplvm")
@_cli
def fit_gplvm_cmd(
    q: int = typer.Option(2, min=1, max=16, help="Latent dimension (2..5 in the paper)."),
    out: Path = typer.Option(Path("out/gplvm.npz"), help="Fit file to write (.npz, versioned, checksummed)."),
    grid: str = typer.Option("default", help="MERL grid: 'default', 'full' (streamed Gram) or strides 'th,td,pd'."),
    binaries: Path = typer.Option(None, help="Folder of real MERL .binary files (default: the NBRDF data)."),
    split: Path = typer.Option(None, help="Fit on the 'train' names of this split file (datasets/merl_split.txt)."),
    cache: Path = typer.Option(None, help="Cache folder (default $TORCH_BRDF_CACHE, else ~/.cache/torch_brdf)."),
    method: str = typer.Option("lbfgs", help="lbfgs, adam or hooke-jeeves."),
    max_iter: int = typer.Option(1000, min=1, help="Optimiser iterations."),
    mu: float = typer.Option(1e-6, min=0.0, help="Kernel shift mu (Eq. 5)."),
    lengthscale: float = typer.Option(1.0, min=0.0, help="Kernel length scale."),
    cosine: bool = typer.Option(True, help="Weight the fit by the clipped cosine map (--no-cosine: raw values)."),
    seed: int = typer.Option(0, min=0),
    progress: bool = PROGRESS,
):
    """Fit the GPLVM BRDF manifold (Soler et al. 2017) on measured materials and save the fit."""
    _file_out(out)
    import torch

    from .manifold import fit_gplvm
    from .manifold.train import parse_grid, training_gram

    if method not in ("lbfgs", "adam", "hooke-jeeves"):
        raise ValueRangeError(f"--method must be lbfgs, adam or hooke-jeeves; got {method!r}")
    parse_grid(grid)  # before any data is read
    s, d, names, meta = training_gram(grid, binaries, split, cache, cosine, progress)
    gen = torch.Generator().manual_seed(seed)
    fit = fit_gplvm(s, d, q, lengthscale=lengthscale, mu=mu, method=method, max_iter=max_iter, names=names,
                    generator=gen, progress=progress)  # fmt: skip
    fit = type(fit)(**{**fit.__dict__, "meta": {**fit.meta, **{k: v for k, v in meta.items() if k != "names"}}})
    out.parent.mkdir(parents=True, exist_ok=True)
    fit.save(out)
    info = {"out": str(out), "q": fit.q, "n": fit.n, "d": fit.d, "loglik": fit.final_loglik}
    info |= {"iterations": fit.iterations, "seconds": round(fit.seconds, 3), "jitter": fit.jitter}
    info |= {k: v for k, v in meta.items() if k != "names"}
    typer.echo(json.dumps(info))
    return info


def _latent_list(text: str, option: str) -> list:
    """``A:B:...`` of latent points (``0.1,-0.2``) or material names -> [tensor | name, ...]."""
    import torch

    out = []
    for part in text.split(":"):
        part = part.strip()
        if not part:
            raise ValueRangeError(f"{option}: empty point in {text!r} (points are 'x0,x1' or names, ':' between)")
        if part[0].isdigit() or part[0] in "+-.":
            try:
                values = [float(v) for v in part.split(",")]
            except ValueError:
                raise ValueRangeError(f"{option}: {part!r} is neither a latent point 'x0,x1,...' nor a name") from None
            for v in values:
                check_real(v, option)
            out.append(torch.tensor(values, dtype=torch.float64))
        else:
            out.append(part)
    return out


@app.command()
@_cli
def manifold(
    fit: Path = typer.Argument(..., help="A GPLVM fit of NBRDF materials (trainers/fit_gplvm.py)."),
    point: str = typer.Option(None, help="Latent point 'x0,x1' (one value per latent dimension) or a material name."),
    path: str = typer.Option(
        None, help="Waypoints 'A:B[:C...]' (latent points or names), rendered as --frames frames."
    ),
    frames: int = typer.Option(8, min=2, max=10000, help="Frames along --path, evenly spaced by latent length."),
    best: bool = typer.Option(False, help="Follow the least-uncertain path (Dijkstra) between waypoints."),
    grid: str = typer.Option("3,3,6", help="MERL strides th,td,pd of the rendered table (3,3,6: the default grid)."),
    width: int = WIDTH,
    height: int = HEIGHT,
    resolution: int = typer.Option(128, **_RESOLUTION, help="Image width = height (unless --width/--height)."),
    spp: int = typer.Option(16, **_SPP),
    bounces: int = typer.Option(1, **_BOUNCES, help="Surface vertices per path (1 = direct lighting)."),
    seed: int = typer.Option(0, min=0),
    exposure: float = typer.Option(None, help="PNG exposure in stops (default: automatic, one for all frames)."),
    out: Path = typer.Option(Path("out/manifold"), help="Output path without suffix; a path adds _000, _001, ..."),
    progress: bool = PROGRESS,
):
    """Render the interpolated material at a latent point, or a path of frames, on a sphere (Soler et al.)."""
    _file_out(out)
    from itertools import pairwise

    import torch

    from .data import cache_path, data_path
    from .manifold import GPLVM, GPLVMFit, MERLGrid, best_path, latent_points, nbrdf_observations, resample_path
    from .manifold.materials import sphere_scene
    from .render.manifold import render_rows

    # every option is checked before the fit is read and the materials are tabulated
    if (point is None) == (path is None):
        raise ValueRangeError("give exactly one of --point (one image) and --path (frames)")
    points = _latent_list(point, "--point") if point is not None else _latent_list(path, "--path")
    if path is not None and len(points) < 2:
        raise ValueRangeError(f"--path needs at least two waypoints 'A:B'; got {path!r}")
    w, h = width or resolution, height or resolution
    check_image_size(w, h, "--width/--height")
    try:
        strides = [int(v) for v in grid.split(",")]
    except ValueError:
        strides = []
    if len(strides) != 3:
        raise ValueRangeError(f"--grid must be three strides th,td,pd (e.g. 3,3,6); got {grid!r}")
    rows_grid = MERLGrid.strided(*strides)
    if exposure is not None:
        check_real(exposure, "--exposure")
    model = GPLVM(GPLVMFit.load(fit))
    way = latent_points(model, points)
    if path is None:
        xs = way
    elif best:
        legs = [best_path(model, a, b).waypoints for a, b in pairwise(way)]
        xs = resample_path(torch.cat([legs[0], *[leg[1:] for leg in legs[1:]]]), frames)
    else:
        xs = resample_path(way, frames)
    names = model.fit.names
    key = f"merl_nbrdf_{rows_grid.digest()[:8]}_{hashlib.sha256(chr(10).join(names).encode()).hexdigest()[:8]}.npz"
    t0 = time.perf_counter()
    obs = nbrdf_observations(
        data_path("merl", "nbrdf_merl100_weights.npz"), rows_grid, names, cache=cache_path(key), progress=progress
    )
    scene = sphere_scene(64).with_resolution(w, h)
    images = render_rows(scene, "sample", model.blend(xs, obs.z), rows_grid, spp, bounces, seed, progress=progress)
    seconds = time.perf_counter() - t0
    if exposure is None:
        from .io import auto_exposure

        exposure = auto_exposure(images.reshape(-1, w, 3))  # one exposure for every frame
    b, var = model.weights(xs), model.variance(xs)
    results = []
    for i, image in enumerate(images):
        target = out if path is None else out.with_name(f"{out.name}_{i:03d}")
        info = _write_image(target, image, exposure, seconds / len(images))
        top = torch.argsort(b[i].abs(), descending=True)[:3].tolist()
        info["latent"] = [round(float(v), 4) for v in xs[i]]
        info["variance"] = round(float(var[i]), 6)
        info["heaviest"] = [[names[k], round(float(b[i, k]), 3)] for k in top]
        results.append(info)
    summary = {"frames": results, "seconds": round(seconds, 3), "size": [w, h], "spp": spp, "grid": grid}
    typer.echo(json.dumps(summary))


@app.command("fit-strokes")
@_cli
def fit_strokes(
    scene: str = typer.Argument(..., help="Built-in scene name or a scene file: .toml .gltf .glb .xml .obj."),
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
    keep_weight: float = typer.Option(1.0, min=0.0, help="Fit weight of the object's unpainted pixels."),
    render_scale: float = typer.Option(1.0, min=0.01, max=16.0, help="Re-render size relative to the display."),
    seed: int = typer.Option(0, min=0),
    progress: bool = PROGRESS,
    ray: str = RAY,
):
    """Inverse BRDF design: fit SRBF coefficients to painted strokes and re-render (Iwasaki et al.)."""
    from .inverse.design import DesignConfig, design, load_strokes

    check_image_size(width, height, "--width/--height")
    for value, option in ((kd, "--kd"), (f0, "--f0"), (rotate, "--rotate"), (keep_weight, "--keep-weight")):
        check_real(value, option)
    check_ray_address(ray)
    st, size = load_strokes(strokes)
    sc = load_scene(scene).with_resolution(width, height)
    constrained = not unconstrained
    cfg = DesignConfig(obj, downsample, samples, kd, f0, constrained, cuts, keep_weight, rotate, render_scale, seed)
    run = {"executor": "local" if ray is None else "ray", "address": ray}
    typer.echo(json.dumps(design(sc, st, cfg, out, display_size=size, progress=progress, **run)))


@app.command("fit-image")
@_cli
def fit_image_cmd(
    source: str = typer.Argument(..., help="Tensors file (.npz from precompute), built-in scene name or scene file."),
    target: Path = typer.Option(None, help="Target image (.exr or .png) at the tensors' size."),
    strokes: Path = typer.Option(None, help="Strokes JSON (as fit-strokes) painted on the current render: the target."),
    keep_weight: float = typer.Option(1.0, min=0.0, help="With --strokes: weight of unpainted object pixels."),
    mask: Path = typer.Option(None, help="Painted pixels (.png/.exr; > 0 is painted); default the objects' pixels."),
    objects: list[str] = typer.Option(..., "--object", help="Edited object (repeat for several)."),
    out: Path = typer.Option(Path("out/fit_image"), help="Output folder: fit.npz, render.exr/png, report.json."),
    scene: str = typer.Option(None, help="The scene of a tensors file (default: the one named in the file)."),
    resolution: int = typer.Option(64, min=8, help="Image size when precomputing a scene."),
    spp: int = typer.Option(16, min=1, help="Paths per pixel when precomputing a scene."),
    series: str = typer.Option("64,1,1,1", help="BRDF series when precomputing a scene."),
    bounces: int = typer.Option(None, min=1, help="Fit with bounces 1..B only (1: direct lighting only)."),
    smoothness: float = typer.Option(0.0, min=0.0, help="Weight of the first-difference curve regulariser."),
    iterations: int = typer.Option(30, min=1, help="Gauss-Newton iterations."),
    progress: bool = PROGRESS,
):
    """Fit band curves of objects to a target image through the GI polynomial tensors."""
    import numpy as np
    import torch

    from .errors import ValueRangeError
    from .inverse.design import load_strokes
    from .io import read_exr, read_png, save_arrays, write_exr, write_png
    from .records.polynomial import PolynomialTensors
    from .render import PolynomialRenderer, apply_scene_textures, fit_image, object_mask, paint_image
    from .transport.polynomial import precompute_polynomial

    def read(path: Path):
        return read_exr(path, allow_gray=True) if path.suffix.lower() == ".exr" else read_png(path)

    if (target is None) == (strokes is None):
        raise ValueRangeError("give exactly one of --target (an image) and --strokes (a strokes JSON)")
    t0 = time.perf_counter()
    if source.endswith(".npz") and Path(source).is_file():
        T = PolynomialTensors.load(source)
        sc = _tensors_scene(T, scene, T.width)
    else:
        sc = load_scene(source, resolution)
        T = precompute_polynomial(sc, _settings("polynomial", series=series, spp=spp), seed=0, progress=progress)
    pre = time.perf_counter() - t0
    mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
    R = PolynomialRenderer(T, mats, dtype=torch.float64, max_bounces=bounces)
    apply_scene_textures(R, sc)
    if mask is None:
        w = sum(object_mask(T, o).double() for o in objects).clamp(max=1)
    else:
        m = read(mask).double()
        w = (m.reshape(m.shape[0], m.shape[1], -1).amax(-1) > 0).double()
    if strokes is not None:
        st, size = load_strokes(strokes)
        img, w = paint_image(R().detach(), st, w > 0, size, keep_weight)
        out.mkdir(parents=True, exist_ok=True)
        write_exr(out / "target.exr", img.float())
    else:
        img = read(target).double()[..., :3]
    t0 = time.perf_counter()
    res = fit_image(R, objects, img, weights=w, smoothness=smoothness, max_iter=iterations, progress=progress)
    fit_s = time.perf_counter() - t0
    out.mkdir(parents=True, exist_ok=True)
    arrays = {f"c_{k}": v.numpy() for k, v in res.coefficients.items()}
    save_arrays(out / "fit.npz", arrays, "gi-image-fit", {"objects": list(res.coefficients)})
    full = PolynomialRenderer(T, mats, dtype=torch.float64)
    apply_scene_textures(full, sc)
    for k, v in res.coefficients.items():
        full.set_coefficients(k, v)
    image = full().detach().float()
    write_exr(out / "render.exr", image)
    write_png(out / "render.png", image)
    report = {"out": str(out), "precompute_s": round(pre, 3), "fit_s": round(fit_s, 3), "loss": res.loss}
    report |= {"iterations": res.iterations, "kkt_residual": res.kkt_residual, "violation": res.violation}
    report["albedo"] = {k: np.round(v.numpy(), 6).tolist() for k, v in res.albedo.items()}
    (out / "report.json").write_text(json.dumps(report | {"loss_curve": res.loss_curve}))
    typer.echo(json.dumps(report))


@app.command("precompute-visibility")
@_cli
def precompute_visibility_cmd(
    scene: str = typer.Argument(..., help="Built-in scene name or a scene file: .toml .gltf .glb .xml .obj."),
    out: Path = typer.Option(Path("out/vis.npz"), help="Output record (.npz, versioned, checksummed)."),
    cubemap: int = typer.Option(64, help="Cubemap texels per face side (a multiple of 16: 64 or 128)."),
    resolution: int = typer.Option(None, hidden=True, help="Deprecated here: the cubemap size (use --cubemap)."),
    supersample: int = typer.Option(1, min=1, max=16, help="k x k rays per texel (k > 1: anti-aliased, needs --bits)."),
    bits: int = typer.Option(0, help="0 = binary maps; 2, 6 or 8 = quantised graded maps."),
    chunk: int = typer.Option(512, min=1, help="Vertices per checkpointed work unit."),
    resume: bool = typer.Option(
        True, help="Keep finished chunks in OUT with .chunks for .npz (out/vis.chunks/) and resume from them."
    ),
    progress: bool = PROGRESS,
    ray: str = RAY,
):
    """Per-vertex visibility cubemaps for all-frequency relighting (Inger et al.)."""
    _file_out(out)
    from .records.cache import remove_cache
    from .transport.visibility import precompute_visibility

    if resolution is not None:  # the old name: a cubemap size here, an image size everywhere else
        typer.echo(f"warning: precompute-visibility --resolution is deprecated; use --cubemap {resolution} "
                   "(elsewhere --resolution is the image size)", err=True)  # fmt: skip
        cubemap = resolution
    settings = _settings("visibility", resolution=cubemap, block=16, supersample=supersample, bits=bits, chunk=chunk)
    check_ray_address(ray)
    sc = load_scene(scene)
    ck = out.with_suffix(".chunks") if resume else None  # out/vis.npz -> out/vis.chunks/
    t0 = time.perf_counter()
    run = {"executor": "local" if ray is None else "ray", "address": ray}
    vis = precompute_visibility(sc, settings, checkpoint=ck, progress=progress, **run)
    seconds = time.perf_counter() - t0
    out.parent.mkdir(parents=True, exist_ok=True)
    vis.save(out)
    remove_cache(ck)
    info = {
        "out": str(out),
        "vertices": len(vis.vertices),
        "cubemap": f"{settings.resolution}x{settings.resolution}x6",
        "bytes_per_vertex": round(vis.bytes_per_vertex, 1),
        "seconds": round(seconds, 3),
    }
    typer.echo(json.dumps(info))


@app.command()
@_cli
def relight(
    scene: str = typer.Argument(
        ..., help="Built-in scene name or a scene file: .toml .gltf .glb .xml .obj (as precomputed)."
    ),
    visibility: Path = typer.Option(Path("out/vis.npz"), help="Record written by precompute-visibility."),
    out: Path = typer.Option(Path("out/relight"), help="Output path without suffix (.exr and .png)."),
    rotate: float = typer.Option(0.0, help="Turn the environment map about +y (radians)."),
    method: str = typer.Option("adaptive", help="adaptive (ours), standard, or haar (1% of coefficients)."),
    exposure: float = typer.Option(None, help="PNG exposure in stops (default: automatic, see _preview)."),
    resolution: int = typer.Option(None, **_RESOLUTION, help="Override the image size (square)."),
    width: int = WIDTH,
    height: int = HEIGHT,
    progress: bool = PROGRESS,
    error: float = typer.Option(
        None, min=0.0, help="Plan cubemap, visibility bits and rule for this RMSE / peak (--visibility ignored)."
    ),
    psnr: float = typer.Option(None, help="The same budget in dB (instead of --error)."),
):
    """Render a frame of per-vertex direct lighting with locally adaptive triple products."""
    _file_out(out)
    from .render.triple import METHODS, TripleProductRenderer
    from .transport.visibility import VertexVisibility

    if method not in METHODS:
        raise ValueRangeError(f"--method must be one of {METHODS}; got {method!r}")
    check_real(rotate, "--rotate")
    if exposure is not None:
        check_real(exposure, "--exposure")
    if error is not None and psnr is not None:
        raise ValueRangeError("give --error or --psnr, not both")
    # an error budget is a fraction of the peak in (0, 1]: PSNR = -20 log10(error) >= 0 dB; below
    # 1e-7 (140 dB) lies float32 rounding, which no plan can reach
    if psnr is not None:
        check_real(psnr, "--psnr", 0.0, 140.0)
    if error is not None:
        check_real(error, "--error", 1e-7, 1.0)
        if error == 0:
            raise ValueRangeError("--error must be > 0 (a fraction of the peak)")
    sc = load_scene(scene, resolution, width, height)
    if sc.environment is None:  # before the record loads; the renderer's "pass envmap=" is the API's
        raise SceneError(f"relight needs an environment map; scene {sc.name!r} has none (add an envmap light)")
    coarse = [f"{o.name} ({n} vertices)" for o in sc.objects if (n := len(o.mesh.vertices)) < COARSE_VERTICES]
    if coarse:  # lighting is computed per vertex and interpolated: a big triangle shows one smooth gradient
        typer.echo(f"warning: relight shades per vertex; {', '.join(coarse)} too coarse to show shadows or "
                   "highlights on (tessellate the mesh, e.g. the bunny_relight scene)", err=True)  # fmt: skip
    if error is None and psnr is None:  # a missing or wrong record: before the renderer is built
        _check_record(visibility, "vertex-visibility", "--visibility")
    plan = None
    if error is not None or psnr is not None:  # plan, then the visibility at the plan's settings
        from .planner.relight_pilots import plan_relighting, planned_renderer

        env = sc.environment.rotated(rotate) if rotate and sc.environment is not None else None
        plan = plan_relighting(sc, error=error, psnr=psnr, envmap=env)
        typer.echo(str(plan), err=True)
        r = planned_renderer(sc, plan, env, progress=progress)
        visibility = out.with_name(out.name + ".vis.npz")
        visibility.parent.mkdir(parents=True, exist_ok=True)
        r.visibility.save(visibility)
    else:
        r = TripleProductRenderer(sc, VertexVisibility.load(visibility))
        if rotate:
            r.set_lighting(r.envmap.rotated(rotate))
    t0 = time.perf_counter()
    image, stats = r.render(method=method, progress=progress)
    seconds = time.perf_counter() - t0
    info = _write_image(out, image, exposure, seconds)
    if plan is not None:
        info["plan"] = dict(plan.settings, predicted_error=plan.predicted_error, visibility=str(visibility))
    if stats is not None:
        info["stats"] = stats.as_dict()
    typer.echo(json.dumps(info))


@app.command()
@_cli
def editor(
    source: str = typer.Argument(..., help="Tensors file (.npz from precompute), built-in scene name or scene file."),
    scene: str = typer.Option(None, help="The scene of a tensors file (default: the one named in the file)."),
    resolution: int = typer.Option(128, **_RESOLUTION, help="Image size when precomputing a scene."),
    spp: int = typer.Option(16, **_SPP, help="Paths per pixel when precomputing a scene."),
    series: str = typer.Option("64,1,1,1", help="BRDF series when precomputing a scene."),
    cache: Path = typer.Option(
        None, help="Where precomputed tensors are kept for the next start (default $TORCH_BRDF_CACHE/editor)."
    ),
    gplvm: Path = typer.Option(None, help="A GPLVM fit of NBRDF materials: shows the measured-material map."),
    relight: str = typer.Option(None, help="Scene of the relighting tab (built-in name or file; with --visibility)."),
    visibility: Path = typer.Option(None, help="Its record from precompute-visibility (the relighting tab)."),
    port: int = typer.Option(None, min=1, max=65535, help="Port on 127.0.0.1 (default: a free one)."),
):
    """Serve the interactive material editor (Voila) on 127.0.0.1 and print its URL."""
    from .editor.server import serve

    _settings("polynomial", series=series, spp=spp)  # checked before the server starts
    _check_editor_inputs(source, gplvm, relight, visibility)
    config = {"source": source, "scene": scene, "resolution": resolution, "spp": spp, "series": series}
    config["gplvm"] = str(gplvm.resolve()) if gplvm else None
    if (relight is None) != (visibility is None):
        raise ValueRangeError("--relight and --visibility go together (a scene and its visibility record)")
    if relight is not None:
        rel = Path(relight)
        config["relight_scene"] = str(rel.resolve()) if rel.is_file() else relight
        config["relight_visibility"] = str(visibility.resolve())
    from .data import cache_dir

    serve({**config, "seed": 0, "cache_dir": str(cache or cache_dir() / "editor")}, port=port, echo=typer.echo)


def _check_editor_inputs(source: str, gplvm: Path | None, relight: str | None, visibility: Path | None) -> None:
    """Every file the editor will read exists and holds the record it needs, before the server
    starts (the server would otherwise report them one page load later, or not at all)."""
    from .records import GPLVMFit, PolynomialTensors
    from .records.visibility import VertexVisibility
    from .scene import BUILTIN_SCENES

    for spec, option in ((source, "SOURCE"), (relight, "--relight")):
        if spec is None:
            continue
        if spec.endswith(".npz") and option == "SOURCE":
            _check_record(spec, PolynomialTensors.kind, "SOURCE")
        elif spec not in BUILTIN_SCENES and not Path(spec).is_file():
            raise SceneError(f"{option}: {spec!r} is neither a file nor one of {sorted(BUILTIN_SCENES)}")
    if gplvm is not None:
        _check_record(gplvm, GPLVMFit.kind, "--gplvm")
    if visibility is not None:
        _check_record(visibility, VertexVisibility.kind, "--visibility")


@app.command("fetch-data")
@_cli
def fetch_data_cmd(
    dest: Path = typer.Option(None, help="Data folder (default $TORCH_BRDF_DATA, else ~/.cache/torch_brdf/data)."),
    url: str = typer.Option(None, help="Base URL of a mirror of the data folder (default $TORCH_BRDF_DATA_URL)."),
    file: list[str] = typer.Option(None, help="Only these files (relative paths, repeatable)."),
    progress: bool = PROGRESS,
):
    """Download the shared data (meshes, HDR maps, NBRDF weights) and verify pinned SHA-256s."""
    from .data import fetch_data

    paths = fetch_data(dest, url, file or None, progress)
    typer.echo(json.dumps({"files": [str(p) for p in paths]}))


@app.command()
@_cli
def report(
    out: Path = typer.Option(Path("out/report"), help="Folder for report.html, its PNGs and the run records."),
    quick: bool = typer.Option(False, "--quick", help="Run every benchmark with --quick (the small version)."),
    results: Path = typer.Option(None, help="Read saved benchmark JSON from this folder instead of running."),
    only: list[str] = typer.Option(None, help="Run only this benchmark (repeatable; e.g. --only extremes)."),
    benchmarks: Path = typer.Option(None, help="Run this folder's scripts instead of the package's benchmarks."),
    timeout: float = typer.Option(None, min=1.0, help="Seconds per benchmark (default 1800 quick, 14400 full)."),
    progress: bool = PROGRESS,
):
    """Run every benchmark (or read their JSON) and write the speed/accuracy report page."""
    from .report import make_report

    page = make_report(out, quick, results, only or None, benchmarks, timeout, progress)
    typer.echo(json.dumps({"report": str(page), "pngs": sorted(str(p) for p in page.parent.glob("*.png"))}))


if __name__ == "__main__":  # pragma: no cover
    app()
