r"""A pool of forked processes that trace the chunks of a ray batch together.

Ray tracing through embreex holds the GIL for a whole call, so threads do not trace in
parallel; processes do. :class:`TracePool` lets the calling process and ``workers - 1``
forked children take chunks of a call from a shared counter, with rays and results in shared
memory. What a chunk computes is the kernel's
(:class:`~torch_brdf.scene.embree.TraceKernel`): the pool only needs its ``commit``, ``trace``
and ``occluded`` methods, its ``chunk`` size (chunks start at multiples of it in every process,
which keeps results bitwise the same for any number of workers) and its ``results`` type.
Nothing here uses torch: the children are forked from a parent that may have torch's thread
pools running (a forked child has only the forking thread; torch would deadlock waiting for
the others).

The pool starts on first use (the kernel's scene is committed in the parent first, so the
children inherit the finished BVH and never build one), is reused across calls, and is
stopped by :meth:`TracePool.close`, when it is garbage collected, or at interpreter exit.
An exception or interrupt (Ctrl-C) in the parent during a call stops it too; the next call
starts a fresh one. Children ignore SIGINT and exit when the parent goes away.

Forked children share the parent's memory copy-on-write: while they live, memory the
parent frees is not returned to the system and pages it writes are copied once. Call
``close()`` on a tracer you are done with in a long-running process, or use ``workers=1``.
"""

from __future__ import annotations

import gc
import mmap
import os
import threading
import weakref

import numpy as np

from .threads import forking, worker_setup

#: most chunks a process of a :class:`TracePool` takes at once (smaller: less waiting for a
#: slow process at the end of a round, e.g. when another program shares its core).
GRAB = 4
#: chunks per round trip of :class:`TracePool` (its shared memory holds ~85 B per ray).
ROUND_CHUNKS = 32


class _Shared:
    """A round's rays, the children's results and the chunk counter, in an anonymous
    shared mapping made before fork (so every process sees the same pages).

    Args:
        n: capacity in rays.
        lock: a ``multiprocessing`` lock that guards the counter.
        results: the kernel's hit-array type, made of the seven result arrays.
    """

    _LAYOUT = (("next", np.int64, 1), ("o", np.float32, 3), ("d", np.float32, 3), ("t_max", np.float32, 1),
               ("occluded", np.bool_, 1), ("t", np.float32, 1), ("object_id", np.int32, 1),
               ("prim_id", np.int32, 1), ("barycentrics", np.float32, 2), ("position", np.float32, 3),
               ("geometric_normal", np.float32, 3), ("normal", np.float32, 3))  # fmt: skip

    def __init__(self, n: int, lock, results: type):
        self.results = results
        sizes = [np.dtype(dt).itemsize * k * (1 if name == "next" else n) for name, dt, k in self._LAYOUT]
        self.map = mmap.mmap(-1, sum(-(-s // 64) * 64 for s in sizes))  # MAP_SHARED | MAP_ANONYMOUS
        self.lock = lock
        self.arrays, offset = {}, 0
        for (name, dt, k), size in zip(self._LAYOUT, sizes, strict=True):
            a = np.frombuffer(self.map, dt, size // np.dtype(dt).itemsize, offset)
            self.arrays[name] = a.reshape(-1, k) if k > 1 else a
            offset += -(-size // 64) * 64

    def __getattr__(self, name: str) -> np.ndarray:
        try:
            return self.__dict__["arrays"][name]
        except KeyError:
            raise AttributeError(name) from None

    def hits(self):
        """The result arrays (full capacity), as the kernel's ``results`` type."""
        a = self.arrays
        return self.results(*(a[k] for k in ("t", "object_id", "prim_id", "barycentrics", "position",
                                          "geometric_normal", "normal")))  # fmt: skip

    def grab(self, chunks: int, workers: int) -> range:
        """The next chunks to trace (guided scheduling: big pieces first, single chunks at the
        end, so that all processes finish together). Empty when the round is done."""
        with self.lock:
            k = int(self.next[0])
            take = min(GRAB, max(1, (chunks - k) // (2 * workers)), max(0, chunks - k))
            self.next[0] = k + take
        return range(k, k + take)


def _drain(kernel, op: str, shared: _Shared, n: int, workers: int, src, dst) -> list[range]:
    """Trace chunks of a round of ``n`` rays until none is left; return the chunks traced.

    Args:
        src: (o, d, t_max) arrays of the round's rays (t_max only for occlusion).
        dst: the kernel's hit arrays or a bool array for the round's results.
    """
    chunk = kernel.chunk
    done, chunks = [], -(-n // chunk)
    while got := shared.grab(chunks, workers):
        a, b = got.start * chunk, min(n, got.stop * chunk)
        if op == "trace":
            kernel.trace(src[0][a:b], src[1][a:b], dst[a:b])
        else:
            kernel.occluded(src[0][a:b], src[1][a:b], src[2][a:b], dst[a:b])
        done.append(got)
    return done


def _worker_main(kernel, shared: _Shared, workers: int, conn, parent_end, ppid: int) -> None:
    """A child's loop: ``(op, n)`` in, chunks of the round traced, ``None`` or an error out."""
    parent_end.close()
    worker_setup()  # Ctrl-C is the parent's to handle (it closes us); one torch and one BLAS thread
    gc.disable()  # never run finalisers of inherited (torch) objects here; fewer copied pages
    src = (shared.o, shared.d, shared.t_max)
    while True:
        try:
            while not conn.poll(1.0):
                if os.getppid() != ppid:  # orphaned
                    return
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        op, n = msg
        try:
            _drain(kernel, op, shared, n, workers, src, shared.hits() if op == "trace" else shared.occluded)
            conn.send(None)
        except Exception as exc:  # report, keep serving
            conn.send(f"{type(exc).__name__}: {exc}")


def _shutdown(owner: int, procs: list, conns: list, terminate: bool = False) -> None:
    """Stop the children (only from the process that forked them): ask, or ``terminate``."""
    if os.getpid() != owner:
        return
    for c in conns:
        try:
            c.send(None)
        except (OSError, ValueError):
            pass
    for p in procs:
        if terminate:
            p.terminate()
        p.join(timeout=2.0)
        if p.is_alive():
            p.terminate()
            p.join(timeout=2.0)
    for c in conns:
        c.close()
    procs.clear()
    conns.clear()


class TracePool:
    """The parent plus ``workers - 1`` forked children tracing the chunks of a call.

    A call goes in rounds of up to :data:`ROUND_CHUNKS` chunks: the parent copies the round's rays
    to shared memory, every process takes chunks from a shared counter until none is left
    (the parent reads the caller's arrays and writes the results in place, the children
    use shared memory), then the parent copies the children's results out.

    Args:
        kernel: the :class:`~torch_brdf.scene.embree.TraceKernel` (its scene is committed before
            forking).
        workers: processes that trace, the parent included (>= 2).
    """

    def __init__(self, kernel, workers: int):
        if workers < 2:
            raise ValueError(f"a TracePool needs workers >= 2; got {workers}")
        self.kernel = kernel
        self.workers = int(workers)
        self._lock = threading.Lock()
        self._procs: list = []
        self._conns: list = []
        self._shared: _Shared | None = None
        self._owner = -1
        self._finalizer = None

    @property
    def running(self) -> bool:
        """Whether this process's children are up."""
        return bool(self._procs) and self._owner == os.getpid()

    def start(self) -> None:
        """Fork the children now (otherwise done by the first call)."""
        if self.running:
            return
        self._procs, self._conns = [], []  # after a fork: the parent's children are not ours
        self.kernel.commit()
        ppid = os.getpid()
        with forking() as ctx:  # our children use no torch
            self._shared = _Shared(self._round_rays, ctx.Lock(), self.kernel.results)
            for i in range(self.workers - 1):
                parent_end, child_end = ctx.Pipe()
                args = (self.kernel, self._shared, self.workers, child_end, parent_end, ppid)
                p = ctx.Process(target=_worker_main, args=args, name=f"torch_brdf-trace-{i + 1}", daemon=True)
                p.start()
                child_end.close()
                self._procs.append(p)
                self._conns.append(parent_end)
        self._owner = ppid
        self._finalizer = weakref.finalize(self, _shutdown, ppid, self._procs, self._conns)

    def close(self, terminate: bool = False) -> None:
        """Stop the children (after their current round, or at once if ``terminate``);
        a later call starts new ones."""
        if self._finalizer is not None and self._finalizer.alive:
            _shutdown(*self._finalizer.detach()[2], terminate=terminate)
        self._procs, self._conns, self._shared = [], [], None

    @property
    def _round_rays(self) -> int:
        return ROUND_CHUNKS * self.kernel.chunk

    def trace(self, o: np.ndarray, d: np.ndarray, out) -> None:
        """The kernel's ``trace`` over all processes. o, d: (P, 3) float32; out: P rays."""
        self._run("trace", (o, d), out)

    def occluded(self, o: np.ndarray, d: np.ndarray, t_max: np.ndarray, out: np.ndarray) -> None:
        """The kernel's ``occluded`` over all processes. t_max: (P,) float32; out: (P,) bool."""
        self._run("occluded", (o, d, t_max), out)

    def _run(self, op: str, src: tuple[np.ndarray, ...], out) -> None:
        with self._lock:
            self.start()
            try:
                step = self._round_rays
                for a in range(0, len(src[0]), step):
                    self._round(op, tuple(x[a : a + step] for x in src), out[a : a + step])
            except BaseException:
                self.close(terminate=True)  # a child may be mid-round: never reuse it
                raise

    def _round(self, op: str, src: tuple[np.ndarray, ...], out) -> None:
        sh, n = self._shared, len(src[0])
        for name, x in zip(("o", "d", "t_max"), src, strict=False):  # t_max only for occlusion
            getattr(sh, name)[:n] = x
        sh.next[0] = 0
        for conn in self._conns:
            conn.send((op, n))
        mine = _drain(self.kernel, op, sh, n, self.workers, src, out)
        for conn in self._conns:
            try:
                err = conn.recv()
            except EOFError:
                err = "it exited"
            if err is not None:
                raise RuntimeError(f"a trace worker failed: {err}")
        chunk = self.kernel.chunk
        theirs = np.ones(-(-n // chunk), bool)
        for r in mine:
            theirs[r.start : r.stop] = False
        for k in np.flatnonzero(theirs):
            a, b = k * chunk, min(n, (k + 1) * chunk)
            if op == "trace":
                for dst, s in zip(out[a:b].fields(), sh.hits()[a:b].fields(), strict=True):
                    dst[:] = s
            else:
                out[a:b] = sh.occluded[a:b]
