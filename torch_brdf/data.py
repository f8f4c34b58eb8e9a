"""Where the optional shared data lives (meshes, env maps, MERL-derived BRDFs).

The package works without it: every built-in scene has a procedural fallback. Tests
that need real data find it through ``TORCH_BRDF_DATA`` and skip when it is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

from .errors import DataNotFoundError

ENV_VAR = "TORCH_BRDF_DATA"


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
