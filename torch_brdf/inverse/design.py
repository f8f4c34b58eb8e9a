"""The stroke-fitting driver behind ``trainers/fit_strokes.py`` and ``torch-brdf fit-strokes``.

Strokes file (JSON)::

    {"display_size": [640, 480],
     "strokes": [{"points": [[300, 200], [340, 230]], "color": [3, 3, 3],
                  "diameter": 40, "kappa": 0.02},
                 {"points": [[250, 260]], "color": [-1, -1, -1], "diameter": 30, "kappa": 0}]}

(``"scale": S`` instead of ``"color"`` scales the current colour, Eq. 23.) Steps: the object's
pixels on the solving frame (display size / ``downsample``), seeded light samples, visibility and
transfer functions (the record is saved next to the outputs and reused when its settings match,
so an interrupted run resumes after the expensive part), the strokes on the diffuse-only image,
the fit, and a re-render at display size under the (optionally rotated) environment.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from ..errors import FileFormatError, TorchBRDFError
from ..records.basis_image import BasisImage
from ..records.cache import Checkpoint, settings_key
from ..scene.scene import Scene
from .energy import default_basis
from .solve import fit, save_fit
from .strokes import Brush, Stroke, paint
from .transfer import CutOptions, LightSamples, object_pixels, precompute_transfer

__all__ = ["DesignConfig", "design", "load_strokes"]


def load_strokes(path: str | Path) -> tuple[list[Stroke], tuple[int, int] | None]:
    """Read a strokes JSON file (module docstring): (strokes, display size or None).

    Raises:
        FileFormatError: missing or unreadable file, not UTF-8 JSON, or a stroke whose
            fields have the wrong types (the message names ``strokes[k]``).
        ShapeError, ValueRangeError: a brush or points out of range (from :class:`Brush`,
            :class:`Stroke`).
    """
    path = Path(path)
    try:
        desc = json.loads(path.read_bytes().decode("utf-8"))
    except FileNotFoundError as exc:
        raise FileFormatError(f"strokes file not found: {path}") from exc
    except OSError as exc:
        raise FileFormatError(f"cannot read strokes file {path}: {exc.strerror or exc}") from exc
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FileFormatError(f"strokes file {path} is not valid JSON: {exc}") from exc
    items = desc.get("strokes") if isinstance(desc, dict) else None
    if not isinstance(items, list):
        raise FileFormatError(f"{path}: expected an object with a list 'strokes'")
    strokes = []
    for k, s in enumerate(items):
        if not isinstance(s, dict) or "points" not in s:
            raise FileFormatError(f"{path}: strokes[{k}] needs 'points'")
        try:
            color = s.get("color", (1.0, 1.0, 1.0))
            brush = Brush(
                tuple(color) if isinstance(color, list | tuple) else color,
                float(s.get("diameter", 20.0)),
                float(s.get("kappa", 0.05)),
                None if s.get("scale") is None else float(s["scale"]),
            )
            strokes.append(Stroke(s["points"], brush))
        except (TypeError, ValueError) as exc:
            if isinstance(exc, TorchBRDFError):
                raise
            raise FileFormatError(f"{path}: strokes[{k}] has a field of the wrong type: {exc}") from exc
    size = desc.get("display_size")
    if size is None:
        return strokes, None
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
        raise FileFormatError(f"{path}: display_size must be two positive integers [width, height]; got {size!r}")
    return strokes, (size[0], size[1])


@dataclass(frozen=True)
class DesignConfig:
    """Settings of :func:`design` (see the trainer's ``--help``)."""

    object: str
    downsample: int = 4
    light_samples: int = 1024
    kd: float = 0.3
    f0: float = 0.9
    constrained: bool = True
    cuts: bool = False
    keep_weight: float = 1.0
    rotate: float = 0.0
    render_scale: float = 1.0
    seed: int = 0


def _check_transfer(rec: BasisImage, px) -> None:
    """A cached transfer record fits this run: its pixels are the object's, values finite."""
    if rec.pixels.shape != px.pixels.shape or not torch.equal(rec.pixels, px.pixels.to(rec.pixels.dtype)):
        raise FileFormatError(f"cached transfer covers {rec.pixels.numel()} other pixels; expected {px.count}")
    want = f"srbf:{default_basis().K}+diffuse"  # the basis precompute_transfer uses here
    if rec.basis != want or rec.values.shape[:2] != (3, default_basis().K + 1):
        raise FileFormatError(f"cached transfer has basis {rec.basis!r}, {tuple(rec.values.shape)}; expected {want!r}")
    if not bool(torch.isfinite(rec.values).all()):
        raise FileFormatError("cached transfer holds NaN or infinite values")


def design(
    scene: Scene,
    strokes: list[Stroke],
    config: DesignConfig,
    out: str | Path,
    display_size=None,
    progress: bool | None = None,
    executor: str = "local",
    address: str | None = None,
) -> dict:
    """Run the stroke fit end to end and write ``fit.npz``, ``transfer.npz``, ``render.exr/.png``.

    Args:
        scene: the scene; its camera is the display view.
        strokes: the strokes, in display coordinates.
        config: :class:`DesignConfig`.
        out: output folder.
        display_size: (width, height) of the stroke coordinates (default the camera's).
        executor: where the tiles of the visibility and transfer functions run
            (``"local"`` or ``"ray"``, :func:`~torch_brdf.inverse.transfer.precompute_transfer`).
        address: the Ray cluster's address (``executor="ray"``).
    Returns:
        A JSON-serialisable summary (pixels, objective, violation, iterations, timings, files).
    """
    from ..io import write_exr, write_png

    if config.downsample < 1 or config.render_scale <= 0:
        raise TorchBRDFError(f"downsample must be >= 1 and render_scale > 0; got {config}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cam = scene.camera
    display = display_size or (cam.width, cam.height)
    solve_cam = cam.with_size(max(1, cam.width // config.downsample), max(1, cam.height // config.downsample))
    t0 = time.perf_counter()
    px = object_pixels(scene, config.object, solve_cam)
    settings = {"scene": scene.name, **asdict(config), "size": [solve_cam.width, solve_cam.height]}
    key = settings_key(settings, scene)  # an edited scene (mesh, env map, camera) recomputes
    cache = Checkpoint(out / "transfer.npz", BasisImage.kind, key, on_corrupt="recompute")
    rec = cache.load_record(BasisImage, check=lambda r: _check_transfer(r, px), dtype=torch.float64)
    if rec is None:
        g = torch.Generator().manual_seed(config.seed)
        ls = LightSamples.from_environment(scene.environment, config.light_samples, g)
        rec = precompute_transfer(
            scene,
            px,
            ls,
            f0=config.f0,
            cuts=CutOptions() if config.cuts else None,
            checkpoint=out / "transfer.tiles",
            progress=progress,
            meta={"settings": settings},
            executor=executor,
            address=address,
        )
        cache.save_record(rec, storage="float64")
    transfer_s = time.perf_counter() - t0
    kd3 = torch.full((1, 3), float(config.kd), dtype=torch.float64)
    before = rec.pixel_values(torch.cat((torch.zeros(rec.num_basis - 1, 3, dtype=torch.float64), kd3)))
    target = paint(rec, before, strokes, display_size=display, keep_weight=config.keep_weight)
    result = fit(rec, target, kd=config.kd, constrained=config.constrained)
    save_fit(out / "fit.npz", result)
    from .render import rerender

    env = scene.environment.rotated(config.rotate) if config.rotate else scene.environment
    rcam = cam.with_size(
        max(1, round(cam.width * config.render_scale)), max(1, round(cam.height * config.render_scale))
    )
    g = torch.Generator().manual_seed(config.seed + 1)
    t1 = time.perf_counter()
    image = rerender(
        scene,
        config.object,
        result,
        camera=rcam,
        environment=env,
        light_samples=config.light_samples,
        generator=g,
        progress=progress,
    )
    render_s = time.perf_counter() - t1  # the re-render at render_scale x display size
    write_exr(out / "render.exr", image.float())
    write_png(out / "render.png", image.float())
    return {
        "pixels": rec.num_pixels,
        "painted": int(target.painted.sum()),
        "objective": result.objective,
        "violation": result.violation,
        "iterations": result.iterations,
        "max_energy": result.max_energy,
        "solve_s": round(result.seconds, 4),
        "transfer_s": round(transfer_s, 3),
        "render_s": round(render_s, 3),
        "render_size": [rcam.width, rcam.height],
        "files": [str(out / n) for n in ("fit.npz", "transfer.npz", "render.exr", "render.png")],
    }
