"""Atomic file writes: every file torch_brdf writes goes through :func:`replacing`.

The temporary file of a write to ``dir/name`` is ``dir/.name.<pid>.<random>.tmp``: hidden,
next to its target, and carrying the id of the writing process. A writer killed with
SIGKILL (or a power cut) cannot remove its temporary file, so the next write of the same
target removes every such file whose process no longer runs (:func:`remove_stale_temporaries`);
files of a process that still runs (a concurrent writer) are left alone.
"""

from __future__ import annotations

import contextlib
import os
import re
import time
import uuid
from collections.abc import Iterator

# time this module was imported: temporaries without a process id (written by torch_brdf
# before it put one into the name) that are older than this cannot belong to a live writer
# of this version
_STARTED = time.time()


def _process_exists(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    except OSError:  # pragma: no cover - platform without signal 0: assume alive
        return True
    return True


def remove_stale_temporaries(path: str | os.PathLike) -> list[str]:
    """Remove temporaries of earlier, killed writes of ``path``; return the removed paths.

    A temporary ``.name.<pid>.<hex>.tmp`` is stale when process ``pid`` no longer runs (on
    this machine); an old-style ``.name.<hex>.tmp`` (no pid) when it predates this process.
    """
    path = os.fspath(path)
    head, tail = os.path.split(path)
    pattern = re.compile(rf"\.{re.escape(tail)}\.(?:(\d+)\.)?[0-9a-f]{{12}}\.tmp")
    removed = []
    try:
        names = os.listdir(head or ".")
    except OSError:
        return removed
    for name in names:
        m = pattern.fullmatch(name)
        if m is None:
            continue
        full = os.path.join(head, name)
        try:
            stale = not _process_exists(int(m.group(1))) if m.group(1) else os.path.getmtime(full) < _STARTED
            if stale:
                os.remove(full)
                removed.append(full)
        except OSError:  # vanished meanwhile, or not ours to remove: leave it
            continue
    return removed


@contextlib.contextmanager
def replacing(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary path next to ``path``; on success move it over ``path``.

    The temporary file is created by the caller (so it gets the usual permissions from the
    umask) in the same directory, which makes :func:`os.replace` atomic: an interrupted
    write leaves either the old file or the new one. On any error (or Ctrl-C) the
    temporary file is removed and ``path`` is left untouched; temporaries that killed
    writers of ``path`` left behind are removed first (:func:`remove_stale_temporaries`).

    Raises:
        FileNotFoundError: the destination directory does not exist.
        OSError: the temporary file cannot be created there (permission denied, read-only
            file system, ...).
    """
    path = os.fspath(path)
    head, tail = os.path.split(path)
    if not os.path.isdir(head or "."):
        raise FileNotFoundError(f"Cannot write {path}: directory {head} does not exist")
    remove_stale_temporaries(path)
    tmp = os.path.join(head, f".{tail}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp")
    # created here, so a folder that refuses files fails with the OSError that says why
    # (writers such as OpenEXR only raise a RuntimeError that names no errno)
    try:
        open(tmp, "xb").close()
    except OSError as exc:  # named by the target, not the hidden temporary
        raise type(exc)(exc.errno, exc.strerror, path) from None
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise
