"""What the scene readers share: options, file references kept inside the scene's folder,
errors that name the file and the element, and automatic framing."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from ...errors import SceneError, TorchBRDFError
from ..camera import Camera

#: largest scene file (XML, glTF JSON, MTL) read, and largest binary (GLB, buffers) in bytes
MAX_TEXT_BYTES = 16 * 2**20
MAX_BINARY_BYTES = 1 * 2**30
#: XML elements and nesting depth accepted in one Mitsuba file
MAX_ELEMENTS = 200_000
MAX_DEPTH = 64
#: triangles of one imported scene
MAX_TRIANGLES = 50_000_000


class SubstitutionWarning(UserWarning):
    """An unsupported part of a scene file was replaced by a stated substitute
    (``load_scene(..., substitute=True)``)."""


@dataclass(frozen=True)
class ImportOptions:
    """How a scene file is read.

    Attributes:
        allow_outside: follow file references that leave the scene file's folder (absolute
            paths, ``..``); refused by default.
        substitute: replace unsupported plugins or features by a stated substitute with a
            :class:`SubstitutionWarning` instead of raising :class:`SceneError`.
        resolution: square image size overriding the file's (None: the file's).
    """

    allow_outside: bool = False
    substitute: bool = False
    resolution: int | None = None


class SceneFile:
    """One scene file being read: its path, options and the errors it raises."""

    def __init__(self, path: str | Path, options: ImportOptions):
        self.path = Path(path)
        self.options = options
        self.root = self.path.parent.resolve()

    def error(self, where: str, problem: str) -> SceneError:
        """A :class:`SceneError` "FILE: WHERE: PROBLEM"."""
        return SceneError(f"{self.path}: {where}: {problem}" if where else f"{self.path}: {problem}")

    def unsupported(self, where: str, problem: str, substitute: str) -> None:
        """Raise for an unsupported feature, or warn and go on with ``substitute`` (a sentence)
        when the options allow it."""
        if not self.options.substitute:
            raise self.error(
                where, f"{problem} (load_scene(..., substitute=True) or torch-brdf --substitute uses {substitute})"
            )
        warnings.warn(f"{self.path}: {where}: {problem}; using {substitute}", SubstitutionWarning, stacklevel=3)

    def resolve(self, ref: str, where: str, must_exist: bool = True) -> Path:
        """``ref`` relative to the scene file's folder; refused when it leaves the folder
        (unless :attr:`ImportOptions.allow_outside`) or, with ``must_exist``, is not a file."""
        if not isinstance(ref, str) or not ref or "\x00" in ref:
            raise self.error(where, f"bad file reference {ref!r}")
        p = (self.root / ref).resolve()
        if not self.options.allow_outside and not p.is_relative_to(self.root):
            raise self.error(
                where,
                f"file reference {ref!r} leaves the scene's folder {self.root} "
                "(load_scene(..., allow_outside=True) or torch-brdf --allow-outside follows it)",
            )
        if must_exist and not p.is_file():
            raise self.error(where, f"referenced file not found: {ref!r} (looked for {p})")
        return p

    def read_bytes(self, path: Path, cap: int, where: str = "") -> bytes:
        try:
            size = path.stat().st_size
            if size > cap:
                raise self.error(where, f"{path.name} has {size} bytes; the cap is {cap}")
            return path.read_bytes()
        except FileNotFoundError:
            raise self.error(where, f"file not found: {path}") from None
        except IsADirectoryError:
            raise self.error(where, f"{path} is a directory") from None
        except OSError as exc:
            raise self.error(where, f"cannot read {path}: {exc.strerror or exc}") from None


def checked(file: SceneFile, where: str, fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` with the package's own errors re-raised as a SceneError naming
    the file and element."""
    try:
        return fn(*args, **kwargs)
    except SceneError as exc:
        msg = str(exc)
        if msg.startswith(str(file.path)):
            raise
        raise file.error(where, msg) from None
    except TorchBRDFError as exc:
        raise file.error(where, str(exc)) from None


def auto_camera(meshes: list[trimesh.Trimesh], width: int = 256, height: int = 256, fov_deg: float = 35.0) -> Camera:
    """A camera that frames the meshes' bounding sphere (~90% of the vertical field of view),
    looking from the front (+z, glTF's and Blender's front), a little from the side and above."""
    v = np.concatenate([np.asarray(m.vertices, dtype=np.float64) for m in meshes])
    lo, hi = v.min(0), v.max(0)
    centre = 0.5 * (lo + hi)
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)
    dist = 1.1 * radius / math.tan(math.radians(fov_deg / 2))
    view = np.array([0.35, 0.3, 1.0])
    eye = centre + dist * view / np.linalg.norm(view)
    return Camera(tuple(map(float, eye)), tuple(map(float, centre)), (0.0, 1.0, 0.0), fov_deg, width, height)


def unique_name(name: str, taken: set[str]) -> str:
    """``name``, or ``name.1``, ``name.2`` ... if taken; the result is added to ``taken``."""
    base = name or "object"
    out, k = base, 1
    while out in taken:
        out, k = f"{base}.{k}", k + 1
    taken.add(out)
    return out
