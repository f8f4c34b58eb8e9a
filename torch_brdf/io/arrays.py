"""Versioned, checksummed array files (``.npz``, never pickle).

Every file we write for later reading (checkpoints, precomputed tensors, visibility
records) goes through :func:`save_arrays`: the arrays plus a JSON header with the
format name, a ``kind`` (what the file holds), the format version, the version of the kind's
layout (``kind_version``), user metadata and a SHA-256 checksum over every array's name,
dtype, shape and bytes. The zip's comment carries a second SHA-256, of every byte of the file
before its end-of-central-directory record, so a flipped byte anywhere (zip headers,
timestamps, padding, metadata) is refused before any parsing. The write is atomic
(temporary file in the same folder, then ``os.replace``), so an interrupted run leaves
either the old file or the new one.
:func:`load_arrays` refuses object arrays (no pickle), a wrong kind, a newer format
version, another layout version of the kind or a checksum mismatch, with a clear error.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FileFormatError
from .atomic import replacing

FORMAT = "torch_brdf-arrays"
VERSION = 1
_HEADER = "__header__"
_DIGEST = b"torch_brdf-sha256:"
_EOCD = 22  # size of the zip end-of-central-directory record without its comment


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_arrays(
    path: str | Path,
    arrays: dict[str, np.ndarray],
    kind: str,
    meta: dict[str, Any] | None = None,
    compress: bool = False,
    kind_version: int = 1,
) -> Path:
    """Write ``arrays`` with a header (format, kind, version, meta, checksum) atomically.

    Args:
        path: destination (``.npz``).
        arrays: name -> numeric array (no object dtype).
        kind: what the file holds, checked again on load (e.g. ``"pathtrace-checkpoint"``).
        meta: JSON-serialisable metadata (settings, progress).
        compress: zip-deflate the arrays.
        kind_version: version of the layout of ``kind`` (checked on load; files written
            before it was recorded count as version 1).
    """
    path = Path(path)
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    for k, a in arrays.items():
        if a.dtype == object or k == _HEADER:
            raise FileFormatError(f"array {k!r} cannot be stored (object dtype or reserved name)")
    header = {"format": FORMAT, "kind": kind, "version": VERSION, "meta": meta or {}, "checksum": _checksum(arrays)}
    header["file_digest"] = True  # the zip comment holds the whole-file digest
    if int(kind_version) != 1:  # absent means 1, so files of version-1 layouts keep their bytes
        header["kind_version"] = int(kind_version)
    blob = np.frombuffer(json.dumps(header, sort_keys=True).encode(), dtype=np.uint8)
    buf = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(buf, **arrays, **{_HEADER: blob})
    raw = buf.getbuffer()
    comment = _DIGEST + hashlib.sha256(raw[:-2]).hexdigest().encode()
    path.parent.mkdir(parents=True, exist_ok=True)
    with replacing(path) as tmp, open(tmp, "wb") as f:
        f.write(raw[:-2])  # the zip as numpy wrote it, up to its (empty) comment length ...
        f.write(len(comment).to_bytes(2, "little") + comment)  # ... then the file digest
    return path


def _verify_file_digest(path: Path) -> bool:
    """Check the whole-file digest of the zip comment; False when the file has none (files
    written before it; :func:`load_arrays` then requires that the header agrees).

    Our files end with the end-of-central-directory record (20 bytes), the comment length
    (2 bytes) and the comment ``_DIGEST + hex``; the digest covers every byte before the
    comment length, the directory record included."""
    size = path.stat().st_size
    n = len(_DIGEST) + 64
    if size < _EOCD + n:
        return False
    with open(path, "rb") as f:
        f.seek(size - _EOCD - n)
        tail = f.read()
        if tail[_EOCD : _EOCD + len(_DIGEST)] != _DIGEST:
            return False
        if tail[:4] != b"PK\x05\x06" or int.from_bytes(tail[_EOCD - 2 : _EOCD], "little") != n:
            raise FileFormatError(f"{path}: corrupt end of file (zip directory record)")
        h = hashlib.sha256()
        f.seek(0)
        left = size - n - 2
        while left > 0:
            chunk = f.read(min(left, 1 << 24))
            if not chunk:
                break
            h.update(chunk)
            left -= len(chunk)
    if tail[_EOCD + len(_DIGEST) :] != h.hexdigest().encode():
        raise FileFormatError(f"{path}: file digest mismatch (file corrupt or modified)")
    return True


def load_arrays(
    path: str | Path, kind: str | None = None, kind_version: int | None = None
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a file written by :func:`save_arrays` and verify it.

    Args:
        kind: the expected ``kind`` (None: any).
        kind_version: the expected layout version of ``kind`` (None: any).

    Returns:
        (arrays, meta).
    Raises:
        FileFormatError: missing, not an array file, wrong kind, newer format version, other
            layout version, corrupt.
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"array file not found: {path}")
    digested = _verify_file_digest(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise FileFormatError(f"{path} is not a readable torch_brdf array file: {exc}") from exc
    if _HEADER not in data:
        raise FileFormatError(f"{path} has no torch_brdf header")
    try:
        header = json.loads(data.pop(_HEADER).tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FileFormatError(f"{path}: corrupt header") from exc
    if not isinstance(header, dict):
        raise FileFormatError(f"{path}: corrupt header (not a JSON object)")
    if header.get("file_digest") and not digested:
        raise FileFormatError(f"{path}: the file digest is missing (file corrupt or modified)")
    if header.get("format") != FORMAT:
        raise FileFormatError(f"{path}: format {header.get('format')!r}, expected {FORMAT!r}")
    if int(header.get("version", -1)) > VERSION:
        raise FileFormatError(f"{path}: format version {header.get('version')} is newer than this reader ({VERSION})")
    if kind is not None and header.get("kind") != kind:
        raise FileFormatError(f"{path} holds {header.get('kind')!r}, expected {kind!r}")
    if kind_version is not None and int(header.get("kind_version", 1)) != kind_version:
        raise FileFormatError(
            f"{path}: {header.get('kind')!r} layout version {header.get('kind_version', 1)}, "
            f"this reader reads version {kind_version}"
        )
    if _checksum(data) != header.get("checksum"):
        raise FileFormatError(f"{path}: checksum mismatch (file corrupt or modified)")
    return data, header.get("meta", {})
