"""The user's environment: where the optional data folder lives (meshes, env maps,
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

from .errors import DataNotFoundError, ValueRangeError

ENV_VAR = "TORCH_BRDF_DATA"
CACHE_ENV_VAR = "TORCH_BRDF_CACHE"
PROGRESS_ENV_VAR = "TORCH_BRDF_PROGRESS"
#: the values ``$TORCH_BRDF_PROGRESS`` accepts (case-insensitive) and what they mean
_PROGRESS_VALUES = dict.fromkeys(("1", "true", "yes", "on"), True) | dict.fromkeys(("0", "false", "no", "off"), False)


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


def _in_kernel() -> bool:
    """Whether this code runs inside a Jupyter kernel (not merely a process that imported
    ipykernel, e.g. nbclient launching one)."""
    ipython = sys.modules.get("IPython")
    shell = ipython.get_ipython() if ipython is not None and hasattr(ipython, "get_ipython") else None
    return type(shell).__name__ == "ZMQInteractiveShell"


def progress_default(progress: bool | None = None) -> bool:
    """Whether to show progress bars: ``progress`` when given; else ``$TORCH_BRDF_PROGRESS``
    (``1``/``0``, or true/false, yes/no, on/off) when set; else True when stderr is a terminal or the code runs in a
    Jupyter kernel.

    Raises:
        ValueRangeError: ``$TORCH_BRDF_PROGRESS`` is set to anything else.
    """
    if progress is not None:
        return bool(progress)
    env = os.environ.get(PROGRESS_ENV_VAR, "").strip().lower()
    if env:
        if env not in _PROGRESS_VALUES:
            raise ValueRangeError(
                f"${PROGRESS_ENV_VAR}={os.environ[PROGRESS_ENV_VAR]!r} is not a switch: use 1, true, yes, on "
                "(bars on) or 0, false, no, off (bars off), or unset it (on in a terminal or notebook)"
            )
        return _PROGRESS_VALUES[env]
    if "ipykernel" in sys.modules and _in_kernel():
        return True
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def data_search_path() -> list[Path]:
    """Where :func:`data_root` looks: ``$TORCH_BRDF_DATA`` alone if set, else ``data`` in
    :func:`cache_dir` (where ``torch-brdf fetch-data`` and ``datasets/originals.py`` put the
    files by default)."""
    env = os.environ.get(ENV_VAR)
    if env:
        return [Path(env).expanduser()]
    return [cache_dir() / "data"]


def data_root() -> Path | None:
    """The data folder (the first folder of :func:`data_search_path` that exists), or
    ``None`` when there is none."""
    return next((p for p in data_search_path() if p.is_dir()), None)


def data_path(*parts: str, required: bool = True) -> Path | None:
    """Path of a file inside the data folder.

    Raises:
        DataNotFoundError: when ``required`` and the folder or file is missing.
    """
    root = data_root()
    p = None if root is None else root.joinpath(*parts)
    if p is None or not p.exists():
        if required:
            where = ", ".join(str(p) for p in data_search_path())
            raise DataNotFoundError(
                f"data file {'/'.join(parts)!r} not found (looked in {where}; "
                f"`python datasets/originals.py` rebuilds it from its original sources, "
                f"`torch-brdf fetch-data --url MIRROR` downloads it, `{ENV_VAR}=FOLDER` points elsewhere)"
            )
        return None
    return p


#: ``TORCH_BRDF_DATA_URL``: base URL of a mirror of the data folder (``<url>/meshes/bunny.ply``, ...).
URL_ENV_VAR = "TORCH_BRDF_DATA_URL"

#: The data files and their pinned SHA-256 (the versions the tests and figures use).
REGISTRY: dict[str, str] = {
    "envmaps/grace_latlong_512x256.exr": "b0199ac15c2ed181f6c0ee37cd6626d90de42f34b1372d896d7285fa76f25aed",
    "envmaps/overcast_soil_puresky_512x256.exr": "58c4bf79ba5033b90093d4b95a43dab76d3e72efcc75284c0a066a02e55b704b",
    "envmaps/quarry_01_sun_1024x512.exr": "4b3ca187ace5fe910e6e4fbc867d7e921d60b9fab26d0b41ee5741c9b710430a",
    "envmaps/quarry_01_sun_512x256.exr": "c14991b307c088982ad82d5b3598ec11675e8b7387517701daa56bc59f84b5de",
    "envmaps/venice_sunset_512x256.exr": "ed6fba4ddf3755af6c0e29f4358f69c977ed3df3a0aec870a6ae6fd6a71d80d6",
    "merl/merl_nbrdf_sample_f16.npz": "ae1727b03edb12d9fffe414256dfa07782f06b4cc4379e97fe2afa3cfbf5b0a9",
    "merl/nbrdf_merl100_weights.npz": "1172526e7ee8da7ba784a09dce7b6659df72005db86527c3c265933dcb4eb9a9",
    "meshes/bunny.ply": "b9b363c443640e9e0ad202188457037241d6eb671fd575e188821fea4bd2042d",
    "meshes/cornell/back.obj": "63e539b64aa20fccfa93a8462248f3cac78ecacf2303572aaaef907bfab25f23",
    "meshes/cornell/ceiling.obj": "4ede7ba66b96d174ada5cd81b60081e14d806f53f6f9de3419250fe75f44e2df",
    "meshes/cornell/floor.obj": "44a5588c3abc120c355eb19834ecafed4990b03a33809af0b3435d82a0c2d975",
    "meshes/cornell/left.obj": "b2ccbac7e04fcd0d6559a9c1ef79cefdda6a902e8553a0f312243e57af557589",
    "meshes/cornell/light.obj": "cf8e16ed99b2df23587605e17c497856fb261604afb1f54f0935091f6f28ccb4",
    "meshes/cornell/materials.json": "75355b77769b6eb3baafca039cc5c1a881ddc87eedb450edb1b8455912e6e4e8",
    "meshes/cornell/right.obj": "f682b8637bab6c17106bb171911e9c7106986e620c79a7f29eb364e300f69ed4",
    "meshes/cornell/short_box.obj": "1b86b843da9c102f295b55f12c6b2d6e7eac64ac6653379e6ced060df61ce955",
    "meshes/cornell/tall_box.obj": "848d9cd55ab782c534eb31697db1e4ec66e75abe5eece48a6e91d03859ed9492",
    "meshes/dragon_100k.ply": "47250c71e46492371637fe210e2a39c857704da929ea3789316fb62ad7eace50",
    "meshes/teapot.obj": "2f833c87e691d949dfa1325df94efe3c25e95b948c7f147e2d08e3ffb719fcda",
}


def fetch_data(
    dest: str | os.PathLike | None = None,
    base_url: str | None = None,
    files: list[str] | None = None,
    progress: bool | None = None,
) -> list[Path]:
    """Download the data files into ``dest`` and verify their pinned SHA-256 (pooch).

    Files already present with the right checksum are not downloaded again; a download whose
    checksum differs is deleted and refused.

    Args:
        dest: the data folder (default ``$TORCH_BRDF_DATA``, else ``data`` in :func:`cache_dir`,
            where :func:`data_root` finds it without setting ``$TORCH_BRDF_DATA``).
        base_url: mirror of the folder (default ``$TORCH_BRDF_DATA_URL``).
        files: paths relative to the folder (default every file of :data:`REGISTRY`).
        progress: a bar per file (None: on in a terminal or notebook).
    Returns:
        The local paths.
    Raises:
        DataNotFoundError: no URL, an unknown file, or a download that failed.
        FileFormatError: a downloaded file whose checksum is not the pinned one.
    """
    import pooch

    base_url = base_url or os.environ.get(URL_ENV_VAR)
    if not base_url:
        raise DataNotFoundError(
            f"no download URL: pass --url or set ${URL_ENV_VAR} to a mirror of the data folder; "
            "without a mirror, `python datasets/originals.py` (in a clone of the repository) rebuilds "
            "the files from their original public sources (see docs/getting-started.md)"
        )
    dest = Path(dest or os.environ.get(ENV_VAR) or cache_dir() / "data").expanduser()
    names = list(REGISTRY) if files is None else list(files)
    unknown = sorted(set(names) - set(REGISTRY))
    if unknown:
        raise DataNotFoundError(f"not in the data registry: {unknown}; known: {sorted(REGISTRY)}")
    out = []
    # pooch logs "Downloading data from ..." at INFO: the progress bar says it, and a failure
    # must stay the one line of the error below
    logger = pooch.get_logger()
    level = logger.level
    logger.setLevel("WARNING")
    try:
        for name in names:
            out.append(_fetch_one(pooch, base_url, name, dest, progress))
    finally:
        logger.setLevel(level)
    return out


def _reason(exc: BaseException) -> str:
    """The innermost cause of a download failure in a few words (requests wraps it thrice)."""
    while exc.__cause__ is not None or exc.__context__ is not None:
        exc = exc.__cause__ or exc.__context__
    text = str(exc)
    if "] " in text:  # "[Errno 111] Connection refused" -> "Connection refused"
        text = text.rsplit("] ", 1)[1]
    return text.rstrip(")\"'") or type(exc).__name__


def _fetch_one(pooch, base_url: str, name: str, dest: Path, progress: bool | None) -> Path:
    """Download and verify one registry file (see :func:`fetch_data`)."""
    from .errors import FileFormatError

    url = f"{base_url.rstrip('/')}/{name}"
    target = dest / name
    try:
        path = pooch.retrieve(
            url,
            known_hash=f"sha256:{REGISTRY[name]}",
            fname=target.name,
            path=target.parent,
            progressbar=progress_default(progress),
        )
    except ValueError as exc:
        if "does not match" not in str(exc):  # pooch: an unusable URL (protocol, ...)
            raise DataNotFoundError(f"{name}: cannot download from {url}: {exc}") from None
        # pooch: hash mismatch (the file was deleted)
        raise FileFormatError(f"{name}: downloaded file does not match its pinned SHA-256 ({exc})") from None
    except Exception as exc:  # requests' HTTP and connection errors
        raise DataNotFoundError(f"{name}: download from {url} failed ({_reason(exc)})") from None
    return Path(path)
