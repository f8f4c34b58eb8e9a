"""The user's environment: where the optional shared data lives (meshes, env maps,
MERL-derived BRDFs), where caches go, and whether long steps show progress.

The package works without the data: every built-in scene has a procedural fallback. Tests
that need real data find it through ``TORCH_BRDF_DATA`` and skip when it is absent.
Caches (band albedos, NBRDF observation matrices) go to ``TORCH_BRDF_CACHE`` (default
``~/.cache/torch_brdf``, or ``$XDG_CACHE_HOME/torch_brdf``), never the working folder.
Progress bars default to on when attached to a terminal or a notebook;
``TORCH_BRDF_PROGRESS=1`` or ``0`` forces them on or off.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from .errors import DataNotFoundError

ENV_VAR = "TORCH_BRDF_DATA"
CACHE_ENV_VAR = "TORCH_BRDF_CACHE"
PROGRESS_ENV_VAR = "TORCH_BRDF_PROGRESS"


def cache_dir() -> Path:
    """The on-disk cache folder: ``$TORCH_BRDF_CACHE``, else ``$XDG_CACHE_HOME/torch_brdf``,
    else ``~/.cache/torch_brdf`` (not created here)."""
    env = os.environ.get(CACHE_ENV_VAR)
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "torch_brdf"


def cache_path(*parts: str) -> Path:
    """A file inside :func:`cache_dir` (its parent folder is created)."""
    p = cache_dir().joinpath(*parts)
    p.parent.mkdir(parents=True, exist_ok=True)
    return p


def progress_default(progress: bool | None = None) -> bool:
    """Whether to show progress bars: ``progress`` when given; else ``$TORCH_BRDF_PROGRESS``
    (``1``/``0``) when set; else True when stderr is a terminal or the code runs in a
    Jupyter kernel."""
    if progress is not None:
        return bool(progress)
    env = os.environ.get(PROGRESS_ENV_VAR, "").strip().lower()
    if env:
        return env not in ("0", "false", "no", "off")
    if "ipykernel" in sys.modules:
        return True
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def data_root() -> Path | None:
    """The shared data folder, or ``None`` when it cannot be found.

    ``$TORCH_BRDF_DATA`` if set; otherwise ``../shared/data`` relative to the current
    directory, then relative to the repository that holds this package.
    """
    env = os.environ.get(ENV_VAR)
    if env:
        p = Path(env).expanduser()
        return p if p.is_dir() else None
    for base in (Path.cwd(), Path(__file__).resolve().parents[1]):
        p = (base / ".." / "shared" / "data").resolve()
        if p.is_dir():
            return p
    return None


def data_path(*parts: str, required: bool = True) -> Path | None:
    """Path of a file inside the shared data folder.

    Raises:
        DataNotFoundError: when ``required`` and the folder or file is missing.
    """
    root = data_root()
    p = None if root is None else root.joinpath(*parts)
    if p is None or not p.exists():
        if required:
            where = f"${ENV_VAR}" if os.environ.get(ENV_VAR) else "../shared/data"
            raise DataNotFoundError(f"shared data file {'/'.join(parts)!r} not found (looked in {where})")
        return None
    return p
