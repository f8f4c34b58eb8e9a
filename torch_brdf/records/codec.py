"""One codec for every saved record: a record declares its arrays, the codec does the rest.

A record type subclasses :class:`Record` and sets ``kind`` (what the file holds) and
``version`` (the layout of its arrays; bump it when the layout changes), then implements
:meth:`Record.to_arrays` (numeric arrays plus JSON metadata) and :meth:`Record.from_arrays`.
:meth:`Record.save` and :meth:`Record.load` go through
:func:`~torch_brdf.io.arrays.save_arrays` / :func:`~torch_brdf.io.arrays.load_arrays`: atomic
write, SHA-256 checksum, no pickle; a file of another kind or layout version, a corrupt file or
one whose arrays do not make a valid record is refused with
:class:`~torch_brdf.errors.FileFormatError`.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..errors import FileFormatError
from ..io.arrays import load_arrays, save_arrays

Arrays = dict[str, np.ndarray]

__all__ = ["Arrays", "Member", "Record", "check_schema", "load_record", "save_record"]


def save_record(path: str | Path, record: Record, extra: dict[str, Any] | None = None, **options) -> Path:
    """Write ``record`` atomically; ``extra`` is merged into the file's metadata (e.g. a cache key)."""
    arrays, meta = record.arrays_to_save(**options)
    return save_arrays(path, arrays, kind=record.kind, meta={**meta, **(extra or {})}, kind_version=record.version)


@dataclass(frozen=True)
class Member:
    """What one array of a record file must be (an entry of :attr:`Record.schema`).

    Attributes:
        kinds: allowed numpy dtype kinds (``"f"`` float, ``"i"``/``"u"`` integer, ``"b"`` bool).
        ndim: required number of dimensions, or None (any).
        finite: NaN and Inf are refused.
        required: the file must hold it (patterns such as ``"b*_values"`` are never required).
    """

    kinds: str
    ndim: int | None = None
    finite: bool = False
    required: bool = True


_FINITE_CHUNK = 1 << 22


def check_schema(arrays: Arrays, schema: dict[str, Member], what: str) -> None:
    """Check every array against ``schema`` (name or ``fnmatch`` pattern -> :class:`Member`).

    Raises:
        FileFormatError: an array the schema does not know, a missing required one, another
            dtype kind or number of dimensions, NaN/Inf where the schema forbids them.
    """
    for name, spec in schema.items():
        if spec.required and not any(c in name for c in "*?[") and name not in arrays:
            raise FileFormatError(f"{what}: missing array {name!r} (has {sorted(arrays)})")
    for name, a in arrays.items():
        spec = schema.get(name) or next((m for p, m in schema.items() if fnmatch.fnmatchcase(name, p)), None)
        if spec is None:
            raise FileFormatError(f"{what}: unexpected array {name!r} (known: {sorted(schema)})")
        if a.dtype.kind not in spec.kinds or (spec.ndim is not None and a.ndim != spec.ndim):
            want = f"{spec.ndim}-d " if spec.ndim is not None else ""
            raise FileFormatError(
                f"{what}: array {name!r} must be {want}of dtype kind {spec.kinds!r}; got {a.dtype} {a.shape}"
            )
        if spec.finite and a.dtype.kind in "fc":
            flat = a.reshape(-1)
            for i in range(0, flat.size, _FINITE_CHUNK):  # bounded temporary, not a mask of the whole array
                if not np.isfinite(flat[i : i + _FINITE_CHUNK]).all():
                    raise FileFormatError(f"{what}: array {name!r} holds NaN or Inf")


#: what a record's ``from_arrays`` may raise on arrays or metadata that do not make a record
_INVALID = (KeyError, IndexError, TypeError, ValueError, AttributeError, OverflowError, RuntimeError, ZeroDivisionError)


def load_record(path: str | Path, cls: type[Record], **options) -> tuple[Record, dict[str, Any]]:
    """Read a file of ``cls`` -> (record, the file's metadata): kind, layout version, checksum
    and the arrays against ``cls.schema`` verified before ``from_arrays`` sees them."""
    arrays, meta = load_arrays(path, kind=cls.kind, kind_version=cls.version)
    check_schema(arrays, cls.schema, f"{path} ({cls.kind})")
    try:
        return cls.from_arrays(arrays, meta, **options), meta
    except FileFormatError as exc:
        raise FileFormatError(f"{path}: {exc}") from exc
    except _INVALID as exc:
        raise FileFormatError(f"{path}: not a valid {cls.kind} record ({exc!r})") from exc


class Record:
    """Base of the saved records (a mixin for frozen dataclasses).

    Subclasses set ``kind``, ``version`` and ``schema`` (the arrays of the file, their dtype
    kinds, dimensions and whether NaN/Inf are allowed) and implement :meth:`to_arrays` and
    :meth:`from_arrays`; ``save(path, **options)`` forwards ``options`` to :meth:`to_arrays`
    and ``load(path, **options)`` to :meth:`from_arrays`.
    """

    kind: ClassVar[str]
    version: ClassVar[int] = 1
    #: every array the file may hold (name or pattern -> :class:`Member`); checked on load
    schema: ClassVar[dict[str, Member]] = {}

    def arrays_to_save(self, **options) -> tuple[Arrays, dict[str, Any]]:
        """What :meth:`save` writes: :meth:`to_arrays`, where a large record may defer its dtype
        conversions (callables, see :func:`~torch_brdf.io.arrays.save_arrays`) so that they are
        made one at a time while the file is written."""
        return self.to_arrays(**options)

    def to_arrays(self, **options) -> tuple[Arrays, dict[str, Any]]:
        """-> (name -> numeric array, JSON-serialisable metadata)."""
        raise NotImplementedError

    @classmethod
    def from_arrays(cls, arrays: Arrays, meta: dict[str, Any], **options):
        """Rebuild the record; raise KeyError/ValueError/FileFormatError on inconsistent input."""
        raise NotImplementedError

    def save(self, path: str | Path, **options) -> Path:
        """Write atomically as a versioned, checksummed array file (no pickle)."""
        return save_record(path, self, **options)

    @classmethod
    def load(cls, path: str | Path, **options):
        """Read a file written by :meth:`save` (kind, version and checksum verified).

        Raises:
            FileFormatError: missing, corrupt, of another kind or version, or not a valid record.
        """
        return load_record(path, cls, **options)[0]
