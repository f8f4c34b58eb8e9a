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

Every cached file is also checked against a :class:`CacheSchema` of what its producer writes
(names, dtypes, shapes, finiteness, ranges of arrays and metadata) before anything reads it: a
digest only proves that the bytes are those that were written, not that a tool, a copy or an
older version wrote what this run expects. A file that fails is treated as a corrupt one.

Every write is atomic and checksummed (:func:`~torch_brdf.io.arrays.save_arrays`). The key is
:func:`settings_key` of a JSON-serialisable settings dict (or a string the caller computed):
the one place that decides when cached work may be reused.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FileFormatError
from ..io.arrays import VERSION as ARRAYS_VERSION
from ..io.arrays import encode_arrays, load_arrays, save_arrays, write_encoded
from ..scene.scene import Scene
from .codec import Record, load_record, save_record

__all__ = [
    "CACHE_VERSION",
    "ArraySpec",
    "CacheSchema",
    "Checkpoint",
    "CorruptCacheWarning",
    "MetaSpec",
    "TileCache",
    "remove_cache",
    "settings_key",
]

_KEY = "cache_key"


class CorruptCacheWarning(UserWarning):
    """A cached file was unreadable; it was moved aside and its work is done again."""


#: bump when a cache's content changes meaning without its settings changing (e.g. a new
#: sampling scheme): every key then differs and old checkpoints are recomputed, never mixed
CACHE_VERSION = 2


_Dim = int | str | None


@dataclass(frozen=True)
class ArraySpec:
    """What one cached array must be.

    Args:
        dtype: numpy dtype name(s) it may have (``"float64"``, ``("int16",)``); an exact match,
            so a tile written in another precision is refused rather than cast.
        shape: one entry per axis: an int (that length), a str (a named length, bound by the
            ``sizes`` given to :meth:`CacheSchema.check` or by the first array that uses it, so
            that arrays agree), or None (any length). None: any shape.
        finite: every value finite (floating dtypes).
        low: inclusive lower bound of every value (None: unbounded).
        high: inclusive upper bound of every value (None: unbounded).
    """

    dtype: str | tuple[str, ...]
    shape: tuple[_Dim, ...] | None = None
    finite: bool = True
    low: float | None = None
    high: float | None = None


@dataclass(frozen=True)
class MetaSpec:
    """What one metadata entry must be: of ``kind`` (bool is never an int here), within
    ``[low, high]`` when numeric; ``items``: the kind of every value of a dict or list."""

    kind: type | tuple[type, ...]
    low: float | None = None
    high: float | None = None
    required: bool = True
    items: type | tuple[type, ...] | None = None


def _is(value: Any, kind: type | tuple[type, ...]) -> bool:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if isinstance(value, bool) and bool not in kinds:
        return False
    if float in kinds and isinstance(value, int) and not isinstance(value, bool):
        return True  # JSON writes 2.0 as 2.0, but a producer may store an int where a float fits
    return isinstance(value, kinds)


def _in_range(x: np.ndarray | float, low: float | None, high: float | None) -> bool:
    a = np.asarray(x)
    if a.size == 0:
        return True
    return (low is None or bool((a >= low).all())) and (high is None or bool((a <= high).all()))


@dataclass(frozen=True)
class CacheSchema:
    """The content a cached file must have before any of it is used.

    Args:
        arrays: name -> :class:`ArraySpec` of every required array.
        optional: arrays that may be absent (checked when present).
        patterns: regular expression -> spec for families of arrays (``b\\d+_vals``); a name
            no entry covers is refused (a file of another producer or version).
        meta: name -> :class:`MetaSpec` of metadata entries.
        check: a further check of (arrays, meta, sizes) raising FileFormatError, for relations
            a spec cannot say (counts that add up, indices within their tables).
    """

    arrays: Mapping[str, ArraySpec] = field(default_factory=dict)
    optional: Mapping[str, ArraySpec] = field(default_factory=dict)
    patterns: Mapping[str, ArraySpec] = field(default_factory=dict)
    meta: Mapping[str, MetaSpec] = field(default_factory=dict)
    check: Callable[[dict[str, np.ndarray], dict[str, Any], dict[str, int]], None] | None = None

    def _spec(self, name: str) -> ArraySpec | None:
        if name in self.arrays:
            return self.arrays[name]
        if name in self.optional:
            return self.optional[name]
        for pattern, spec in self.patterns.items():
            if re.fullmatch(pattern, name):
                return spec
        return None

    def validate(
        self, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any], sizes: Mapping[str, int] | None = None
    ) -> None:
        """Check ``arrays`` and ``meta``; ``sizes`` binds named lengths (e.g. ``{"P": 64}``).

        Raises:
            FileFormatError: the first mismatch, naming the array or entry, what was expected
                and what came.
        """
        bound = dict(sizes or {})
        for name in self.arrays:
            if name not in arrays:
                raise FileFormatError(f"cached file lacks array {name!r}")
        for name, a in arrays.items():
            spec = self._spec(name)
            if spec is None:
                raise FileFormatError(f"cached file holds an unexpected array {name!r}")
            _check_array(name, a, spec, bound)
        for name, spec in self.meta.items():
            if name not in meta:
                if spec.required:
                    raise FileFormatError(f"cached file lacks metadata {name!r}")
                continue
            v = meta[name]
            if not _is(v, spec.kind):
                raise FileFormatError(f"cached metadata {name!r} is {type(v).__name__} {v!r:.60}; expected {spec.kind}")
            if spec.items is not None:
                values = v.values() if isinstance(v, dict) else v
                if not all(_is(x, spec.items) for x in values):
                    raise FileFormatError(f"cached metadata {name!r} holds values not of {spec.items}")
            if _is(v, (int, float)) and not (np.isfinite(v) and _in_range(v, spec.low, spec.high)):
                raise FileFormatError(f"cached metadata {name!r} = {v!r} is outside [{spec.low}, {spec.high}]")
        if self.check is not None:
            self.check(dict(arrays), dict(meta), bound)


def _check_array(name: str, a: np.ndarray, spec: ArraySpec, bound: dict[str, int]) -> None:
    dtypes = (spec.dtype,) if isinstance(spec.dtype, str) else spec.dtype
    if a.dtype.name not in dtypes:
        raise FileFormatError(f"cached array {name!r} has dtype {a.dtype.name}; expected {' or '.join(dtypes)}")
    if spec.shape is not None:
        if a.ndim != len(spec.shape):
            raise FileFormatError(f"cached array {name!r} has shape {a.shape}; expected {len(spec.shape)} axes")
        for axis, (n, want) in enumerate(zip(a.shape, spec.shape, strict=True)):
            if isinstance(want, str):
                want = bound.setdefault(want, n)
            if want is not None and n != want:
                raise FileFormatError(f"cached array {name!r} has shape {a.shape}; axis {axis} should be {want}")
    if spec.finite and a.dtype.kind in "fc" and not np.isfinite(a).all():
        raise FileFormatError(f"cached array {name!r} holds NaN or infinite values")
    if not _in_range(a, spec.low, spec.high):
        raise FileFormatError(f"cached array {name!r} has values outside [{spec.low}, {spec.high}]")


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
        schema: what the arrays and metadata must be (a file that fails counts as corrupt);
            None: any content of this kind and key.
        sizes: the named lengths of ``schema`` (e.g. ``{"P": 64}``).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        kind: str,
        key: dict[str, Any] | str,
        on_corrupt: str = "raise",
        schema: CacheSchema | None = None,
        sizes: Mapping[str, int] | None = None,
    ):
        if on_corrupt not in ("raise", "recompute"):
            raise ValueError(f"on_corrupt must be 'raise' or 'recompute'; got {on_corrupt!r}")
        self.path, self.kind, self.key, self.on_corrupt = Path(path), kind, settings_key(key), on_corrupt
        self.schema, self.sizes = schema, dict(sizes or {})

    def _validate(self, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
        """Raise FileFormatError (naming the file) unless the content fits the schema."""
        if self.schema is None:
            return
        try:
            self.schema.validate(arrays, meta, self.sizes)
        except FileFormatError as exc:
            raise FileFormatError(f"{self.path}: {exc}") from None
        except (KeyError, IndexError, TypeError, ValueError, OverflowError) as exc:
            # a check that met content too odd to compare: the file is not what we wrote
            raise FileFormatError(f"{self.path}: unreadable cached content ({type(exc).__name__}: {exc})") from None

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
            if meta.get(_KEY) != self.key:
                return None
            self._validate(arrays, meta)
        except FileFormatError as exc:
            self._corrupt(exc)
            return None
        return arrays, meta

    def save(self, arrays: dict[str, np.ndarray], meta: dict[str, Any] | None = None) -> Path:
        """Write ``arrays`` atomically under this key (``meta`` is kept beside it)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        return save_arrays(self.path, arrays, kind=self.kind, meta={**(meta or {}), _KEY: self.key})

    def load_record(self, cls: type[Record], check: Callable[[Record], None] | None = None, **options) -> Record | None:
        """The cached record of type ``cls`` when intact, of this key and accepted by ``check``
        (which raises FileFormatError for a record this run cannot use); else None."""
        if not self.path.is_file():
            return None
        try:
            record, meta = load_record(self.path, cls, **options)
            if meta.get(_KEY) != self.key:
                return None
            if check is not None:
                check(record)
        except FileFormatError as exc:
            self._corrupt(FileFormatError(f"{self.path}: {exc}") if str(self.path) not in str(exc) else exc)
            return None
        return record

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
        schema: what every tile must hold (a tile that fails is moved aside and recomputed).
        sizes: the named lengths of tile ``index`` for ``schema`` (e.g. its pixel count).
    """

    def __init__(
        self,
        folder: str | os.PathLike | None,
        kind: str,
        key: dict[str, Any] | str,
        prefix: str = "tile",
        schema: CacheSchema | None = None,
        sizes: Callable[[int], Mapping[str, int]] | None = None,
    ):
        self.folder = None if folder is None else Path(folder)
        self.kind, self.key, self.prefix = kind, settings_key(key), prefix
        self.schema, self.sizes = schema, sizes

    def _tile(self, index: int) -> Checkpoint | None:
        if self.folder is None:
            return None
        path = self.folder / f"{self.prefix}{index:05d}_{self.key}.npz"
        sizes = None if self.sizes is None or self.schema is None else self.sizes(index)
        return Checkpoint(path, self.kind, self.key, on_corrupt="recompute", schema=self.schema, sizes=sizes)

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
