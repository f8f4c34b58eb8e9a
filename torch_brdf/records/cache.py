"""One checkpoint / tile cache for every precomputation.

Long precomputations (the reference path tracer, the multibounce tensors, the visibility
cubemaps, the inverse-design transfer functions, the NBRDF observation matrix) save their
progress so that an interrupted run resumes where it stopped and gives the same result bit
for bit. They all do it through this module:

- :class:`Checkpoint`: one file (progress so far, or a finished record) tied to a *key*, the
  digest of everything that decides its content (:func:`settings_key`: the settings, the
  scene's content digest and the format versions). A file written under another key is
  ignored (the work is redone and the file overwritten); a corrupt file is either refused
  with :class:`~torch_brdf.errors.FileFormatError` (``on_corrupt="raise"``) or moved aside
  to ``<name>.corrupt`` with a :class:`CorruptCacheWarning` and recomputed
  (``on_corrupt="recompute"``).
- :class:`TileCache`: a folder of such files, one per finished work unit (tile, chunk); a
  corrupt tile is moved aside and recomputed. :meth:`TileCache.remove` deletes the folder
  once the result is saved.

Every write is atomic and checksummed (:func:`~torch_brdf.io.arrays.save_arrays`). The key is
:func:`settings_key` of a JSON-serialisable settings dict (or a string the caller computed):
the one place that decides when cached work may be reused.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FileFormatError
from ..io.arrays import VERSION as ARRAYS_VERSION
from ..io.arrays import encode_arrays, load_arrays, save_arrays, write_encoded
from ..scene.scene import Scene
from .codec import Record, load_record, save_record

__all__ = ["CACHE_VERSION", "Checkpoint", "CorruptCacheWarning", "TileCache", "remove_cache", "settings_key"]

_KEY = "cache_key"


class CorruptCacheWarning(UserWarning):
    """A cached file was unreadable; it was moved aside and its work is done again."""


#: bump when a cache's content changes meaning without its settings changing (e.g. a new
#: sampling scheme): every key then differs and old checkpoints are recomputed, never mixed
CACHE_VERSION = 2


def settings_key(
    settings: dict[str, Any] | str, scene: Scene | None = None, parts: tuple[str, ...] | None = None
) -> str:
    """The resume key: 16 hex digits of SHA-256 over everything a cached result depends on.

    Covers the sorted JSON of ``settings``, the content of ``scene``
    (:meth:`~torch_brdf.scene.scene.Scene.content_digest`: meshes, materials, lights with their
    env-map texels, camera; ``parts`` selects a subset, e.g. ``("geometry",)`` for visibility),
    the array-file format version, :data:`CACHE_VERSION` and the package version. A string
    is an already computed key and is returned as is.

    Raises:
        TypeError: ``settings`` is not JSON-serialisable.
    """
    if isinstance(settings, str):
        return settings
    content = None
    if scene is not None:
        content = scene.content_digest() if parts is None else scene.content_digest(parts)
    from .. import __version__

    full = {
        "settings": settings,
        "scene": content,
        "formats": [ARRAYS_VERSION, CACHE_VERSION, __version__],
    }
    return hashlib.sha256(json.dumps(full, sort_keys=True).encode()).hexdigest()[:16]


def remove_cache(path: str | os.PathLike | None) -> None:
    """Delete a checkpoint file or tile folder once its result is saved (nothing if absent)."""
    if path is None:
        return
    p = Path(path)
    if p.is_dir():
        shutil.rmtree(p, ignore_errors=True)
    else:
        p.unlink(missing_ok=True)


class Checkpoint:
    """One cached file tied to the settings that produced it.

    Args:
        path: the file (``.npz``).
        kind: what it holds (checked on load).
        key: the settings dict (or its :func:`settings_key`).
        on_corrupt: ``"raise"`` (FileFormatError) or ``"recompute"`` (move aside, warn, None).
    """

    def __init__(self, path: str | os.PathLike, kind: str, key: dict[str, Any] | str, on_corrupt: str = "raise"):
        if on_corrupt not in ("raise", "recompute"):
            raise ValueError(f"on_corrupt must be 'raise' or 'recompute'; got {on_corrupt!r}")
        self.path, self.kind, self.key, self.on_corrupt = Path(path), kind, settings_key(key), on_corrupt

    def _corrupt(self, exc: FileFormatError) -> None:
        if self.on_corrupt == "raise":
            raise exc
        aside = self.path.with_name(self.path.name + ".corrupt")
        os.replace(self.path, aside)
        warnings.warn(f"{exc}; moved aside to {aside.name} and recomputing", CorruptCacheWarning, stacklevel=3)

    def load(self) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
        """(arrays, meta) when the file exists, is intact and has this key; else None."""
        if not self.path.is_file():
            return None
        try:
            arrays, meta = load_arrays(self.path, kind=self.kind)
        except FileFormatError as exc:
            self._corrupt(exc)
            return None
        return (arrays, meta) if meta.get(_KEY) == self.key else None

    def save(self, arrays: dict[str, np.ndarray], meta: dict[str, Any] | None = None) -> Path:
        """Write ``arrays`` atomically under this key (``meta`` is kept beside it)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        return save_arrays(self.path, arrays, kind=self.kind, meta={**(meta or {}), _KEY: self.key})

    def load_record(self, cls: type[Record], **options) -> Record | None:
        """The cached record of type ``cls`` when intact and of this key; else None."""
        if not self.path.is_file():
            return None
        try:
            record, meta = load_record(self.path, cls, **options)
        except FileFormatError as exc:
            self._corrupt(exc)
            return None
        return record if meta.get(_KEY) == self.key else None

    def save_record(self, record: Record, **options) -> Path:
        """Write ``record`` (``options`` go to its ``to_arrays``) atomically under this key."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        return save_record(self.path, record, extra={_KEY: self.key}, **options)

    def remove(self) -> None:
        """Delete the file (after the result is saved)."""
        remove_cache(self.path)


class TileCache:
    """A folder of finished work units (``<prefix><index>_<key>.npz``), or nothing at all.

    ``TileCache(None, ...)`` caches nothing (``load`` gives None, ``save`` does nothing), so a
    precomputation runs the same loop with or without a checkpoint folder.

    Args:
        folder: the folder (created on the first save), or None.
        kind: what each tile holds. key: the settings dict (or its :func:`settings_key`);
            tiles of another key are never read.
        prefix: file name prefix of the tiles.
    """

    def __init__(self, folder: str | os.PathLike | None, kind: str, key: dict[str, Any] | str, prefix: str = "tile"):
        self.folder = None if folder is None else Path(folder)
        self.kind, self.key, self.prefix = kind, settings_key(key), prefix

    def _tile(self, index: int) -> Checkpoint | None:
        if self.folder is None:
            return None
        path = self.folder / f"{self.prefix}{index:05d}_{self.key}.npz"
        return Checkpoint(path, self.kind, self.key, on_corrupt="recompute")

    def load(self, index: int) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
        """(arrays, meta) of finished tile ``index``, or None (not done, other key, or corrupt)."""
        tile = self._tile(index)
        return None if tile is None else tile.load()

    def save(self, index: int, arrays: dict[str, np.ndarray], meta: dict[str, Any] | None = None) -> None:
        """Write finished tile ``index`` atomically."""
        tile = self._tile(index)
        if tile is not None:
            tile.save(arrays, meta)

    def encode(self, arrays: dict[str, np.ndarray], meta: dict[str, Any] | None = None) -> bytes | None:
        """The file bytes :meth:`save` would write for a tile (None without a folder): a
        worker encodes, the driver writes them with :meth:`save_encoded`."""
        if self.folder is None:
            return None
        return encode_arrays(arrays, self.kind, {**(meta or {}), _KEY: self.key})

    def save_encoded(self, index: int, data: bytes | None) -> None:
        """Write the bytes of :meth:`encode` as finished tile ``index``, atomically."""
        tile = self._tile(index)
        if tile is not None and data is not None:
            write_encoded(tile.path, data)

    def remove(self) -> None:
        """Delete this cache's tiles (every ``<prefix>*.npz``, any key, and moved-aside
        ``.corrupt`` files) after the result is saved, then the folder if that left it empty;
        other files in the folder are kept."""
        if self.folder is None or not self.folder.is_dir():
            return
        for p in [*self.folder.glob(f"{self.prefix}*.npz"), *self.folder.glob(f"{self.prefix}*.npz.corrupt")]:
            p.unlink(missing_ok=True)
        if not any(self.folder.iterdir()):
            self.folder.rmdir()
