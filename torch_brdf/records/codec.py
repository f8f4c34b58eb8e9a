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

from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..errors import FileFormatError
from ..io.arrays import load_arrays, save_arrays

Arrays = dict[str, np.ndarray]

__all__ = ["Arrays", "Record", "load_record", "save_record"]


def save_record(path: str | Path, record: Record, extra: dict[str, Any] | None = None, **options) -> Path:
    """Write ``record`` atomically; ``extra`` is merged into the file's metadata (e.g. a cache key)."""
    arrays, meta = record.to_arrays(**options)
    return save_arrays(path, arrays, kind=record.kind, meta={**meta, **(extra or {})}, kind_version=record.version)


def load_record(path: str | Path, cls: type[Record], **options) -> tuple[Record, dict[str, Any]]:
    """Read a file of ``cls`` (kind and layout version verified) -> (record, the file's metadata)."""
    arrays, meta = load_arrays(path, kind=cls.kind, kind_version=cls.version)
    try:
        return cls.from_arrays(arrays, meta, **options), meta
    except FileFormatError as exc:
        raise FileFormatError(f"{path}: {exc}") from exc
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise FileFormatError(f"{path}: not a valid {cls.kind} record ({exc!r})") from exc


class Record:
    """Base of the saved records (a mixin for frozen dataclasses).

    Subclasses set ``kind`` and ``version`` and implement :meth:`to_arrays` and
    :meth:`from_arrays`; ``save(path, **options)`` forwards ``options`` to :meth:`to_arrays`
    and ``load(path, **options)`` to :meth:`from_arrays`.
    """

    kind: ClassVar[str]
    version: ClassVar[int] = 1

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
