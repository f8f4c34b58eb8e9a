"""Atomic file writes: every file torch_brdf writes goes through :func:`replacing`."""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator


@contextlib.contextmanager
def replacing(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary path next to ``path``; on success move it over ``path``.

    The temporary file is created by the caller (so it gets the usual permissions from the
    umask) in the same directory, which makes :func:`os.replace` atomic: an interrupted
    write leaves either the old file or the new one. On any error (or Ctrl-C) the
    temporary file is removed and ``path`` is left untouched.

    Raises:
        FileNotFoundError: the destination directory does not exist.
    """
    path = os.fspath(path)
    head, tail = os.path.split(path)
    if not os.path.isdir(head or "."):
        raise FileNotFoundError(f"Cannot write {path}: directory {head} does not exist")
    tmp = os.path.join(head, f".{tail}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise
