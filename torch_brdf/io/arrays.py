"""Versioned, checksummed array files (``.npz``, never pickle).

Every file we write for later reading (checkpoints, precomputed tensors, visibility
records) goes through :func:`save_arrays`: the arrays plus a JSON header with the
format name, a ``kind`` (what the file holds), the format version, the version of the kind's
layout (``kind_version``), user metadata and a SHA-256 checksum over every array's name,
dtype, shape and bytes. The zip's comment carries a second SHA-256, of every byte of the file
before its end-of-central-directory record, so a flipped byte anywhere (zip headers,
timestamps, padding, metadata) is refused before any parsing. The write is atomic
(temporary file in the same folder, then ``os.replace``), so an interrupted run leaves
either the old file or the new one. :func:`save_arrays` streams: the arrays go from memory
to the file in chunks (no copy of an array, no image of the file in memory) and the file
digest is a second, chunked pass over what was written, so saving holds little more than
the arrays themselves; :func:`encode_arrays` builds the same bytes in memory for the small
files a worker hands to its driver.
:func:`load_arrays` refuses object arrays (no pickle), a wrong kind, a newer format
version, another layout version of the kind or a checksum mismatch, with a clear error.

:func:`read_npz` is the one reader of every ``.npz`` (ours, MERL tables, NBRDF weights): it
bounds what a file declares before allocating (each ``.npy`` header's shape x itemsize equals
its member's size; the total is at most :func:`max_array_bytes`, ``TORCH_BRDF_MAX_ARRAY_BYTES``,
default 8 GiB; no deflated member expands more than :data:`MAX_COMPRESSION_RATIO` times beyond
:data:`RATIO_FREE_BYTES`) and turns every zip, inflate and header error into
:class:`~torch_brdf.errors.FileFormatError` naming the file.
"""

from __future__ import annotations

import ast
import hashlib
import io
import json
import math
import os
import struct
import tokenize
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FileFormatError, WriteError
from .atomic import replacing

FORMAT = "torch_brdf-arrays"
VERSION = 1
_HEADER = "__header__"
_DIGEST = b"torch_brdf-sha256:"
_EOCD = 22  # size of the zip end-of-central-directory record without its comment

#: default of :func:`max_array_bytes` (``TORCH_BRDF_MAX_ARRAY_BYTES`` overrides it)
DEFAULT_MAX_ARRAY_BYTES = 8 << 30
#: a deflated member may expand at most this many times (beyond :data:`RATIO_FREE_BYTES`);
#: :func:`save_arrays` stores a member uncompressed rather than write one that would not load
MAX_COMPRESSION_RATIO = 200
RATIO_FREE_BYTES = 1 << 20
_MAX_NPY_HEADER = 1 << 16
_CHUNK = 1 << 24
#: bytes read at once into an array: a zip member's ``readinto`` reads them into a temporary
#: bytes object first, so this bounds the transient beside the array
_READ_CHUNK = 1 << 20
#: everything the zip, inflate and .npy header layers raise on a damaged or crafted file
_READ_ERRORS = (
    OSError, EOFError, ValueError, KeyError, IndexError, TypeError, AttributeError,
    zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, NotImplementedError, RuntimeError,
    struct.error, OverflowError, MemoryError, SyntaxError, RecursionError, tokenize.TokenError,
)  # fmt: skip


class Converted:
    """An array to be saved in another dtype, converted only while it is checksummed and while
    it is written (one converted array in memory at a time, see :func:`save_arrays`).

    Args:
        array: the array. dtype: the dtype it is saved in.
    """

    def __init__(self, array: np.ndarray, dtype):
        self.array, self.dtype = array, np.dtype(dtype)

    def __call__(self) -> np.ndarray:
        return self.array.astype(self.dtype)


def _materialise(v) -> np.ndarray:
    """An array, or the array a deferred entry (a callable, see :func:`save_arrays`) makes."""
    a = np.asarray(v() if callable(v) else v)
    if a.dtype == object:
        raise FileFormatError("an array of object dtype cannot be stored")
    return a


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(_materialise(arrays[name]))
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.reshape(-1).view(np.uint8).data if a.size else b"")  # the bytes, not a copy
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
        arrays: name -> numeric array (no object dtype), or a callable that returns one (e.g.
            :class:`Converted`): the converted copy is then made once for the checksum and once
            for the write, and freed in between, instead of held with all the others.
        kind: what the file holds, checked again on load (e.g. ``"pathtrace-checkpoint"``).
        meta: JSON-serialisable metadata (settings, progress).
        compress: zip-deflate the arrays (stored instead when an array would inflate more
            than :data:`MAX_COMPRESSION_RATIO` times, which :func:`read_npz` refuses).
        kind_version: version of the layout of ``kind`` (checked on load; files written
            before it was recorded count as version 1).
    """
    arrays, blob = _prepare(arrays, kind, meta, kind_version)
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with replacing(path) as tmp, open(tmp, "w+b") as f:
            _write_zip(f, arrays, blob, compress)
            if compress and _has_bomb_like(f):  # would be refused as a zip bomb: store instead
                f.seek(0)
                f.truncate()
                _write_zip(f, arrays, blob, False)
            _append_digest(f)
    except WriteError:
        raise
    except OSError as exc:
        raise _write_error(path, exc) from exc
    return path


def _prepare(arrays, kind: str, meta, kind_version: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The arrays (views, not copies) and the header blob with their checksum."""
    arrays = {k: v if callable(v) else np.asarray(v) for k, v in arrays.items()}
    for k, a in arrays.items():
        if k == _HEADER or (not callable(a) and a.dtype == object):
            raise FileFormatError(f"array {k!r} cannot be stored (object dtype or reserved name)")
    header = {"format": FORMAT, "kind": kind, "version": VERSION, "meta": meta or {}, "checksum": _checksum(arrays)}
    header["file_digest"] = True  # the zip comment holds the whole-file digest
    if int(kind_version) != 1:  # absent means 1, so files of version-1 layouts keep their bytes
        header["kind_version"] = int(kind_version)
    return arrays, np.frombuffer(json.dumps(header, sort_keys=True).encode(), dtype=np.uint8)


def _write_zip(f, arrays: dict[str, np.ndarray], blob: np.ndarray, compress: bool) -> None:
    """The npz numpy's ``savez`` writes (``NAME.npy`` members in order, zip64 sizes, then the
    header member), streamed into ``f`` without copying contiguous arrays."""
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(f, mode="w", compression=method, allowZip64=True) as z:
        for name, a in [*arrays.items(), (_HEADER, blob)]:
            with z.open(name + ".npy", "w", force_zip64=True) as out:
                _write_npy(out, _materialise(a))


def _write_npy(out, a: np.ndarray) -> None:
    """``np.lib.format.write_array`` for numeric arrays, the bytes of a contiguous array passed
    as views in :data:`_CHUNK` slices (numpy's writer copies each buffer)."""
    fmt = np.lib.format
    if not (a.flags.c_contiguous or a.flags.f_contiguous) or a.dtype.hasobject:
        fmt.write_array(out, a, allow_pickle=False)
        return
    head = fmt.header_data_from_array_1_0(a)
    try:
        fmt.write_array_header_1_0(out, head)
    except ValueError:  # a header too long for version 1.0
        fmt.write_array_header_2_0(out, head)
    flat = (a.T if head["fortran_order"] else a).reshape(-1)
    data = memoryview(flat.view(np.uint8)) if flat.size else memoryview(b"")
    for i in range(0, len(data), _CHUNK):
        out.write(data[i : i + _CHUNK])


def _has_bomb_like(f) -> bool:
    f.seek(0)
    with zipfile.ZipFile(f) as z:
        return any(_bomb_like(i) for i in z.infolist())


def _append_digest(f) -> None:
    """Replace the (empty) comment length that ends the zip by the length and the digest of
    every byte before it, hashed in chunks from the file."""
    f.flush()
    end = f.seek(0, os.SEEK_END)
    f.seek(end - 2)
    if f.read(2) != b"\x00\x00":
        raise FileFormatError("internal: the zip written does not end with an empty comment")
    h = hashlib.sha256()
    f.seek(0)
    left = end - 2
    while left > 0:
        chunk = f.read(min(left, _CHUNK))
        if not chunk:
            raise FileFormatError("internal: the zip written is shorter than its size")
        h.update(chunk)
        left -= len(chunk)
    comment = _DIGEST + h.hexdigest().encode()
    f.seek(end - 2)
    f.write(len(comment).to_bytes(2, "little") + comment)
    f.truncate()


def encode_arrays(
    arrays: dict[str, np.ndarray],
    kind: str,
    meta: dict[str, Any] | None = None,
    compress: bool = False,
    kind_version: int = 1,
) -> bytes:
    """The bytes :func:`save_arrays` writes (arguments as there), built in memory: a tile
    executor's worker encodes (checksums, zip) and the driver only writes them
    (:func:`write_encoded`). For small files: this holds the whole file in memory."""
    arrays, blob = _prepare(arrays, kind, meta, kind_version)
    buf = io.BytesIO()
    _write_zip(buf, arrays, blob, compress)
    if compress and _has_bomb_like(buf):
        buf = io.BytesIO()
        _write_zip(buf, arrays, blob, False)
    _append_digest(buf)
    return buf.getvalue()


def write_encoded(path: str | Path, data: bytes) -> Path:
    """Write the bytes of :func:`encode_arrays` to ``path`` atomically."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with replacing(path) as tmp, open(tmp, "wb") as f:
            f.write(data)
    except OSError as exc:
        raise _write_error(path, exc) from exc
    return path


def _write_error(path: Path, exc: OSError) -> WriteError:
    """A full disk's error names no file (or a temporary one): say which file was being written."""
    return WriteError(exc.errno, f"cannot write {path}: {exc.strerror or type(exc).__name__}", str(path))


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


def max_array_bytes() -> int:
    """The cap on the bytes one array file may declare: ``TORCH_BRDF_MAX_ARRAY_BYTES`` (an
    integer number of bytes) or :data:`DEFAULT_MAX_ARRAY_BYTES` (8 GiB)."""
    raw = os.environ.get("TORCH_BRDF_MAX_ARRAY_BYTES")
    if raw is None:
        return DEFAULT_MAX_ARRAY_BYTES
    try:
        cap = int(raw)
    except ValueError:
        raise FileFormatError(f"TORCH_BRDF_MAX_ARRAY_BYTES must be an integer number of bytes; got {raw!r}") from None
    if cap < 1:
        raise FileFormatError(f"TORCH_BRDF_MAX_ARRAY_BYTES must be >= 1; got {cap}")
    return cap


def check_declared_size(nbytes: int, what: str, path: str | Path) -> None:
    """Refuse an allocation a file asks for that exceeds :func:`max_array_bytes`.

    Readers call it with sizes computed from a file's headers or metadata (in Python integers,
    so nothing overflows) before they allocate.

    Raises:
        FileFormatError: ``nbytes`` above the cap (the message names the file, the size and
            the environment variable that raises the cap).
    """
    cap = max_array_bytes()
    if nbytes > cap:
        raise FileFormatError(
            f"{path}: {what} declares {nbytes:,} bytes, more than the cap of {cap:,} "
            "(set TORCH_BRDF_MAX_ARRAY_BYTES to read larger files)"
        )


def _bomb_like(info: zipfile.ZipInfo) -> bool:
    """A deflated member that would expand more than :data:`MAX_COMPRESSION_RATIO` times
    (members up to :data:`RATIO_FREE_BYTES` are not counted: they cannot hurt)."""
    return info.file_size > RATIO_FREE_BYTES and info.file_size > MAX_COMPRESSION_RATIO * max(info.compress_size, 1)


def _check_members(z: zipfile.ZipFile, size: int, path) -> list[zipfile.ZipInfo]:
    """The members of an npz, each checked before any byte of it is inflated."""
    infos = z.infolist()
    names = [i.filename for i in infos]
    if len(set(names)) != len(names):
        raise FileFormatError(f"{path}: duplicate zip members")
    total = 0
    for info in infos:
        if not info.filename.endswith(".npy"):
            raise FileFormatError(f"{path}: member {info.filename!r} is not an .npy array")
        if info.flag_bits & 0x1:
            raise FileFormatError(f"{path}: member {info.filename!r} is encrypted")
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise FileFormatError(f"{path}: member {info.filename!r} uses compression method {info.compress_type}")
        if info.compress_size > size or info.header_offset > size:
            raise FileFormatError(f"{path}: member {info.filename!r} claims more bytes than the file holds")
        if info.compress_type == zipfile.ZIP_STORED and info.file_size != info.compress_size:
            raise FileFormatError(f"{path}: stored member {info.filename!r} has inconsistent sizes")
        if _bomb_like(info):
            raise FileFormatError(
                f"{path}: member {info.filename!r} would inflate {info.compress_size:,} bytes to "
                f"{info.file_size:,} (more than {MAX_COMPRESSION_RATIO}:1; a zip bomb?)"
            )
        total += info.file_size
    check_declared_size(total, "its arrays", path)
    return infos


def _read_member(z: zipfile.ZipFile, info: zipfile.ZipInfo, path) -> np.ndarray:
    """One ``.npy`` member: its header parsed and checked against the member's size before
    the array is allocated, then the data read in bounded chunks."""
    with z.open(info) as f:
        head = f.read(8)  # magic, version
        if len(head) < 8 or head[:6] != b"\x93NUMPY" or head[6] not in (1, 2, 3):
            raise FileFormatError(f"{path}: member {info.filename!r} is not an .npy array (version 1-3)")
        major = head[6]
        start = 10 if major == 1 else 12
        head += f.read(start - 8)
        hlen = int.from_bytes(head[8:start], "little")
        if len(head) != start or hlen > _MAX_NPY_HEADER or start + hlen > info.file_size:
            raise FileFormatError(f"{path}: member {info.filename!r} has a corrupt .npy header")
        f_head = head + f.read(hlen)
        if len(f_head) != start + hlen:
            raise FileFormatError(f"{path}: member {info.filename!r} has a corrupt .npy header")
        text = f_head[start:].decode("latin1" if major < 3 else "utf8")
        header = ast.literal_eval(text)
        if not isinstance(header, dict) or set(header) != {"descr", "fortran_order", "shape"}:
            raise FileFormatError(f"{path}: member {info.filename!r} has a corrupt .npy header")
        shape, fortran = header["shape"], header["fortran_order"]
        if not isinstance(shape, tuple) or not all(type(d) is int and d >= 0 for d in shape):
            raise FileFormatError(f"{path}: member {info.filename!r} declares shape {shape!r}")
        if not isinstance(fortran, bool):
            raise FileFormatError(f"{path}: member {info.filename!r} has a corrupt .npy header")
        dtype = np.lib.format.descr_to_dtype(header["descr"])
        if dtype.hasobject or dtype.kind not in "biufcSU" or dtype.names or dtype.shape or dtype.itemsize == 0:
            raise FileFormatError(
                f"{path}: member {info.filename!r} has dtype {dtype}: "
                "only numeric or str arrays are read (without pickle)"
            )
        nbytes = math.prod(shape) * dtype.itemsize
        if nbytes != info.file_size - len(f_head):
            raise FileFormatError(
                f"{path}: member {info.filename!r} declares {shape} {dtype} ({nbytes:,} bytes) but holds "
                f"{info.file_size - len(f_head):,}"
            )
        check_declared_size(nbytes, f"member {info.filename!r}", path)
        out = np.empty(math.prod(shape), dtype=dtype)
        view = memoryview(out.view(np.uint8) if out.size else np.empty(0, np.uint8))
        pos = 0
        while pos < nbytes:
            got = f.readinto(view[pos : pos + _READ_CHUNK])
            if not got:
                raise FileFormatError(f"{path}: member {info.filename!r} ends early")
            pos += got
        if f.read(1):
            raise FileFormatError(f"{path}: member {info.filename!r} holds trailing bytes")
    return out.reshape(shape, order="F" if fortran else "C")


def read_npz(path: str | Path, what: str = "array file") -> dict[str, np.ndarray]:
    """Read every array of an ``.npz`` without pickle, never allocating what the file only claims.

    The one reader of every array file (:func:`load_arrays`, MERL tables, NBRDF weights):
    each member's compression method, encryption flag, declared size (against the file's size,
    :func:`max_array_bytes` and :data:`MAX_COMPRESSION_RATIO`) and ``.npy`` header (shape x
    itemsize against the member's size; numeric or str dtypes only) are checked before its
    array is allocated, and any error of the zip, inflate or header layers becomes a
    :class:`~torch_brdf.errors.FileFormatError` naming the file.

    Args:
        path: the file. what: what it should be, for messages (e.g. ``"MERL table file"``).
    Returns:
        name (without ``.npy``) -> array.
    Raises:
        FileFormatError: missing, not a zip of ``.npy`` arrays, corrupt, or above the caps.
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{what} not found: {path}")
    try:
        size = path.stat().st_size
        with zipfile.ZipFile(path) as z:
            return {i.filename[:-4]: _read_member(z, i, path) for i in _check_members(z, size, path)}
    except FileFormatError:
        raise
    except _READ_ERRORS as exc:
        raise FileFormatError(
            f"{what} {path} is not a readable npz without pickle: {type(exc).__name__}: {exc}"
        ) from exc


def _header_int(header: dict, key: str, default: int, path) -> int:
    value = header.get(key, default)
    if type(value) is not int:
        raise FileFormatError(f"{path}: corrupt header ({key} = {value!r} is not an integer)")
    return value


def read_kind(path: str | Path) -> str:
    """The ``kind`` in the header of an array file, read without its arrays (a command checks
    that a record is of the kind it needs before it starts anything).

    Raises:
        FileFormatError: missing, not an array file of this package, or a header without a kind.
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"array file not found: {path}")
    try:
        with zipfile.ZipFile(path) as z:
            info = z.getinfo(_HEADER + ".npy")
            header = json.loads(_read_member(z, info, path).tobytes().decode())
    except (zipfile.BadZipFile, KeyError, UnicodeDecodeError, json.JSONDecodeError, OSError, ValueError) as exc:
        raise FileFormatError(f"{path}: not a torch_brdf array file ({type(exc).__name__})") from None
    kind = header.get("kind") if isinstance(header, dict) else None
    if not isinstance(kind, str):
        raise FileFormatError(f"{path}: the header names no kind of record")
    return kind


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
    data = read_npz(path, "torch_brdf array file")
    blob = data.pop(_HEADER, None)
    if blob is None:
        raise FileFormatError(f"{path} has no torch_brdf header")
    if blob.dtype != np.uint8 or blob.ndim != 1:
        raise FileFormatError(f"{path}: corrupt header (not a byte string)")
    try:
        header = json.loads(blob.tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise FileFormatError(f"{path}: corrupt header") from exc
    if not isinstance(header, dict):
        raise FileFormatError(f"{path}: corrupt header (not a JSON object)")
    if header.get("file_digest") and not digested:
        raise FileFormatError(f"{path}: the file digest is missing (file corrupt or modified)")
    if header.get("format") != FORMAT:
        raise FileFormatError(f"{path}: format {header.get('format')!r}, expected {FORMAT!r}")
    version = _header_int(header, "version", -1, path)
    if version > VERSION:
        raise FileFormatError(f"{path}: format version {version} is newer than this reader ({VERSION})")
    if kind is not None and header.get("kind") != kind:
        raise FileFormatError(f"{path} holds {header.get('kind')!r}, expected {kind!r}")
    layout = _header_int(header, "kind_version", 1, path)
    if kind_version is not None and layout != kind_version:
        raise FileFormatError(
            f"{path}: {header.get('kind')!r} layout version {layout}, this reader reads version {kind_version}"
        )
    meta = header.get("meta", {})
    if not isinstance(meta, dict):
        raise FileFormatError(f"{path}: corrupt header (meta is not a JSON object)")
    if _checksum(data) != header.get("checksum"):
        raise FileFormatError(f"{path}: checksum mismatch (file corrupt or modified)")
    return data, meta
