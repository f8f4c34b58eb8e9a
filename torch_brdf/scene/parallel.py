r"""The numpy + embree side of ray tracing, and a pool of forked processes that share it.

embreex holds the GIL for a whole ``EmbreeScene.run`` call, so threads do not trace in
parallel; processes do. Everything here uses numpy and embreex only, never torch, because
it also runs in children forked from a parent that may have torch's thread pools running
(a forked child has only the forking thread; torch would deadlock waiting for the others).

- :class:`TraceKernel` traces rays in chunks of :data:`CHUNK` rays and turns embree's
  output into hit arrays (:class:`HitArrays`). Chunks start at global ray indices
  ``k * CHUNK`` and every chunk runs the same numpy calls on arrays of the same shapes and
  strides, whichever process traces it, so results are bitwise identical for any number
  of workers (numpy's SIMD loops do not depend on alignment, only on shapes and strides).
- :class:`TracePool` lets the calling process and ``workers - 1`` forked children take
  chunks from a shared counter, with rays and results in shared memory.

The pool starts on first use (the embree scene is committed in the parent first, so the
children inherit the finished BVH and never build one), is reused across calls, and is
stopped by :meth:`TracePool.close`, when it is garbage collected, or at interpreter exit.
An exception or interrupt (Ctrl-C) in the parent during a call stops it too; the next call
starts a fresh one. Children ignore SIGINT and exit when the parent goes away.

Compiled loops (``transport/csrc``) may call embree themselves: :func:`embree_entry`
gives the committed scene's ``RTCScene`` handle and the address of ``rtcOccluded1`` from the
very library instance embreex loaded (so the same BVH and the same per-ray query as
``EmbreeScene.run``), or None where that cannot be checked.

Forked children share the parent's memory copy-on-write: while they live, memory the
parent frees is not returned to the system and pages it writes are copied once. Call
``close()`` on a tracer you are done with in a long-running process, or use ``workers=1``.
"""

from __future__ import annotations

import ctypes
import gc
import glob
import mmap
import multiprocessing
import os
import signal
import threading
import warnings
import weakref
from dataclasses import dataclass

import numpy as np
from embreex import rtcore, rtcore_scene

from .._threads import configure_worker, prepare_fork, worker_count
from ._bindings import EMBREE, declare

#: rays per embree call; results do not depend on it being shared by every process.
CHUNK = 1 << 14
#: chunks that go through embree before their hits are computed (at most).
BATCH = 16
#: most chunks a process of a :class:`TracePool` takes at once (smaller: less waiting for a
#: slow process at the end of a round, e.g. when another program shares its core).
GRAB = 4
#: rays per round trip of :class:`TracePool` (its shared memory holds ~85 B per ray).
ROUND = 32 * CHUNK


@dataclass
class HitArrays:
    """Closest-hit arrays of P rays (float32; ids int32 or int64), see ``raytrace.Hits``.

    Attributes:
        t: (P,) hit distance, ``inf`` on a miss.
        object_id: (P,) object (embree geometry) id, -1 on a miss.
        prim_id: (P,) triangle index within the object, -1 on a miss.
        barycentrics: (P, 2) embree's (u, v), 0 on a miss.
        position: (P, 3); geometric_normal: (P, 3); normal: (P, 3), 0 on a miss.
    """

    t: np.ndarray
    object_id: np.ndarray
    prim_id: np.ndarray
    barycentrics: np.ndarray
    position: np.ndarray
    geometric_normal: np.ndarray
    normal: np.ndarray

    @classmethod
    def empty(cls, n: int) -> HitArrays:
        """Uninitialised arrays for ``n`` rays (int64 ids)."""
        f, i = np.float32, np.int64
        return cls(np.empty(n, f), np.empty(n, i), np.empty(n, i), np.empty((n, 2), f), np.empty((n, 3), f),
                   np.empty((n, 3), f), np.empty((n, 3), f))  # fmt: skip

    def __getitem__(self, s: slice) -> HitArrays:
        """Views of a range of rays."""
        return HitArrays(*(a[s] for a in self.fields()))

    def fields(self) -> tuple[np.ndarray, ...]:
        """The seven arrays in declaration order."""
        return (self.t, self.object_id, self.prim_id, self.barycentrics, self.position, self.geometric_normal,
                self.normal)  # fmt: skip


class TraceKernel:
    r"""Closest-hit and occlusion queries on numpy arrays, chunk by chunk (fork-safe).

    Hit points interpolate the triangle's vertices with the barycentrics, shading normals
    the vertex normals (then normalised); flat objects take the geometric normal. All three
    come from one row per triangle of a table ``(F + 1, 21)``: 3 x (vertex xyz, vertex
    normal xyz), then the unit face normal; the last row is zeros, where misses land.

    Args:
        scene: the embree scene, geometry ``i`` = object ``i``.
        table: (F + 1, 21) float32 per-triangle rows over all objects, zero row last.
        face_offsets: (O,) int64 first global triangle of each object.
        smooth: (O,) bool, whether an object interpolates vertex normals.
    """

    def __init__(self, scene, table: np.ndarray, face_offsets: np.ndarray, smooth: np.ndarray):
        self.scene = scene
        self.table = table
        # geomID -1 (a miss) reads the extra 0 entry; with primID -1 that is the zero row (index -1)
        self.offsets = None if len(face_offsets) == 1 else np.append(face_offsets, 0).astype(np.intp)
        flat = ~np.append(smooth, True)  # misses count as smooth: nothing to override
        self.flat = None if not flat.any() else flat

    def commit(self) -> None:
        """Build embree's BVH now (embreex builds it on the first query); call before forking."""
        self.scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))

    def trace(self, o: np.ndarray, d: np.ndarray, out: HitArrays) -> None:
        """Closest hits of rays whose first one has a global index divisible by :data:`CHUNK`.

        Args:
            o: (P, 3) float32 C-contiguous origins.
            d: (P, 3) float32 C-contiguous directions.
            out: :class:`HitArrays` of P rays, filled in.
        """
        # BATCH chunks through embree, then through numpy: each keeps its data in cache
        for a in range(0, len(o), BATCH * CHUNK):
            starts = range(a, min(len(o), a + BATCH * CHUNK), CHUNK)
            runs = [self._embree(o[b : b + CHUNK], d[b : b + CHUNK]) for b in starts]
            for b, r in zip(starts, runs, strict=True):
                self._hits(r, out[b : b + CHUNK])

    def occluded(self, o: np.ndarray, d: np.ndarray, t_max: np.ndarray, out: np.ndarray) -> None:
        """Whether anything lies within ``(0, t_max)`` along each ray.

        Args:
            o: (P, 3) float32 C-contiguous origins.
            d: (P, 3) float32 C-contiguous directions.
            t_max: (P,) float32 (<= 1e37), overwritten.
            out: (P,) bool, filled in.
        """
        for a in range(0, len(o), CHUNK):
            b = a + CHUNK
            out[a:b] = self.scene.run(o[a:b], d[a:b], dists=t_max[a:b], query="OCCLUDED") != -1

    def occluded_fans(self, o: np.ndarray, fans: np.ndarray, d: np.ndarray, out: np.ndarray) -> None:
        """Unbounded occlusion of fans of rays that share their origin, one embree call per fan.

        The fan's origin goes to embree as a zero-stride view (no per-ray copy), its directions
        as a slice of ``d`` (fans may share one); each ray's result is the same as by
        :meth:`occluded` with ``t_max`` = ``1e37``.

        Args:
            o: (m, 3) float32 origins.
            fans: (m, 2) int64 ``(start, count)``: fan ``i`` casts ``d[start : start + count]``.
            d: (D, 3) float32 directions (any row stride).
            out: (sum of counts,) bool, filled in fan after fan.
        """
        s = 0
        for i, (a, n) in enumerate(fans.tolist()):
            if n:
                origin = np.lib.stride_tricks.as_strided(o[i], (n, 3), (0, o.strides[1]), writeable=False)
                out[s : s + n] = self.scene.run(origin, d[a : a + n], query="OCCLUDED") != -1
                s += n

    def native(self) -> tuple[int, int] | None:
        """:func:`embree_entry` of this kernel's scene (committed first), found once per kernel."""
        if not hasattr(self, "_native"):
            self.commit()
            self._native = embree_entry(self.scene)
        return self._native

    def native_hits(self) -> EmbreeHits | None:
        """:class:`EmbreeHits` of this kernel (its scene committed first), found once per kernel;
        None where :func:`embree_entry` is None."""
        if not hasattr(self, "_native_hits"):
            entry, intersect = self.native(), embree_function("rtcIntersect1")
            self._native_hits = None
            if entry is not None and intersect is not None:
                offsets = None if self.offsets is None else np.ascontiguousarray(self.offsets, np.int64)
                flat = None if self.flat is None else np.ascontiguousarray(self.flat, np.uint8)
                self._native_hits = EmbreeHits(entry[0], intersect, entry[1], self.table, offsets, flat)
        return self._native_hits

    def _embree(self, o: np.ndarray, d: np.ndarray) -> dict[str, np.ndarray]:
        # rays start with tfar = inf, which embree leaves on a miss (embreex returns, and
        # may overwrite, the ``dists`` array: it is a fresh one)
        return self.scene.run(o, d, dists=np.full(len(o), np.inf, np.float32), output=1)

    def _hits(self, r: dict[str, np.ndarray], out: HitArrays) -> None:
        geom, prim = r["geomID"], r["primID"]  # both -1 on a miss
        hit = geom >= 0
        face = prim if self.offsets is None else self.offsets[geom] + prim
        g = np.take(self.table, face, axis=0)  # (n, 21); the zero row on a miss
        n = len(g)
        w = np.empty((n, 3), np.float32)  # (1 - u - v, u, v)
        np.multiply(r["u"], hit, out=w[:, 1])
        np.multiply(r["v"], hit, out=w[:, 2])
        np.subtract(1, w[:, 1], out=w[:, 0])
        w[:, 0] -= w[:, 2]
        pn = np.einsum("pk,pkc->pc", w, g[:, :18].reshape(n, 3, 6))  # (n, 6): position, shading normal
        length = pn[:, 3] * pn[:, 3]
        length += pn[:, 4] * pn[:, 4]
        length += pn[:, 5] * pn[:, 5]
        np.maximum(np.sqrt(length, out=length), 1e-12, out=length)
        flat = None if self.flat is None else self.flat[geom]
        # column by column: numpy's loops over rows of 3 cost more than the arithmetic
        for c in range(3):
            out.position[:, c] = pn[:, c]
            np.divide(pn[:, 3 + c], length, out=out.normal[:, c])
            out.geometric_normal[:, c] = g[:, 18 + c]
            if flat is not None:
                np.copyto(out.normal[:, c], g[:, 18 + c], where=flat)
        out.barycentrics[:, 0] = w[:, 1]
        out.barycentrics[:, 1] = w[:, 2]
        out.t[:] = r["tfar"]
        out.object_id[:] = geom
        out.prim_id[:] = prim


def _embree_library() -> ctypes.CDLL | None:
    """The libembree4 that embreex's extension loaded (by the path the process mapped, so
    ``dlopen`` returns that very instance), or None when it is not found."""
    paths = []
    try:
        with open("/proc/self/maps") as f:  # Linux: the exact file in use
            paths = [line.split(None, 5)[-1].strip() for line in f if "libembree4" in line]
    except OSError:  # no /proc (not Linux): look beside the wheel's extensions below
        paths = []
    if not paths:  # elsewhere: the copy bundled beside the wheel's extensions
        here = os.path.dirname(rtcore_scene.__file__)
        for pattern in ("../embreex.libs/libembree4*", ".dylibs/libembree4*", "libembree4*"):
            paths += glob.glob(os.path.join(here, pattern))
    for path in paths:
        try:
            return ctypes.CDLL(path)
        except OSError:  # not loadable here: try the next candidate, else None (callers fall back)
            continue
    return None


def embree_function(name: str) -> int | None:
    """Address of embree's C function ``name`` (e.g. ``"rtcIntersect1"``) in the library
    embreex loaded (:func:`embree_entry` finds ``rtcOccluded1`` the same way), or None."""
    lib = _embree_library()
    fn = None if lib is None else getattr(lib, name, None)
    return None if fn is None else ctypes.cast(fn, ctypes.c_void_p).value


@dataclass(frozen=True)
class EmbreeHits:
    """What a compiled loop needs to cast a :class:`TraceKernel`'s closest-hit and shadow rays
    itself and to make :class:`HitArrays` as :meth:`TraceKernel.trace` does
    (``tb_trace_hits`` / ``tb_occluded_rays`` in ``transport/csrc/rays.c``).

    Attributes:
        scene: the committed ``RTCScene`` handle (:func:`embree_entry`).
        intersect, occluded: addresses of ``rtcIntersect1`` and ``rtcOccluded1``.
        table: (F + 1, 21) float32 per-triangle rows (see :class:`TraceKernel`).
        offsets: (O + 1,) int64 first row of each object, or None (one object).
        flat: (O + 1,) uint8, 1 where an object's shading normal is its face normal, or None.
    """

    scene: int
    intersect: int
    occluded: int
    table: np.ndarray
    offsets: np.ndarray | None
    flat: np.ndarray | None


def embree_entry(scene) -> tuple[int, int] | None:
    """``(RTCScene handle, address of rtcOccluded1)`` of a committed embreex ``EmbreeScene``,
    for compiled loops that cast rays without the Python binding's per-call costs.

    embreex does not expose the handle; it is the first field of the extension type's C struct
    (``scene_i``, then ``is_committed``, then the ``EmbreeDevice``). That layout is checked before
    the handle is used: the struct's size, ``is_committed`` read through the struct, the device
    field being the ``EmbreeDevice`` the object holds, and embree's own ``rtcGetSceneDevice`` of
    the handle being that device. Any mismatch (another embreex build, no loadable library) gives None, and callers keep
    ``EmbreeScene.run``.
    """
    if type(scene) is not rtcore_scene.EmbreeScene or not scene.is_committed:
        return None
    base, word = id(scene), ctypes.sizeof(ctypes.c_void_p)
    if word != 8 or type(scene).__basicsize__ != 5 * word or rtcore.EmbreeDevice.__basicsize__ != 3 * word:
        return None
    if ctypes.c_int.from_address(base + 3 * word).value != scene.is_committed:
        return None
    # the device field is the one object the struct holds (the type's gc traversal reports it)
    held = [o for o in gc.get_referents(scene) if type(o) is rtcore.EmbreeDevice]
    device = ctypes.c_void_p.from_address(base + 4 * word).value
    if len(held) != 1 or device != id(held[0]):
        return None
    lib = _embree_library()
    if lib is None:
        return None
    handle = ctypes.c_void_p.from_address(base + 2 * word).value
    rtc_device = ctypes.c_void_p.from_address(device + 2 * word).value
    declare(lib, EMBREE)
    got = lib.rtcGetSceneDevice(handle)  # takes a reference to the device
    if got:
        lib.rtcReleaseDevice(got)
    if not handle or got != rtc_device:
        return None
    return handle, ctypes.cast(lib.rtcOccluded1, ctypes.c_void_p).value


class _Shared:
    """A round's rays, the children's results and the chunk counter, in an anonymous
    shared mapping made before fork (so every process sees the same pages).

    Args:
        n: capacity in rays.
        lock: a ``multiprocessing`` lock that guards the counter.
    """

    _LAYOUT = (("next", np.int64, 1), ("o", np.float32, 3), ("d", np.float32, 3), ("t_max", np.float32, 1),
               ("occluded", np.bool_, 1), ("t", np.float32, 1), ("object_id", np.int32, 1),
               ("prim_id", np.int32, 1), ("barycentrics", np.float32, 2), ("position", np.float32, 3),
               ("geometric_normal", np.float32, 3), ("normal", np.float32, 3))  # fmt: skip

    def __init__(self, n: int, lock):
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

    def hits(self) -> HitArrays:
        """The result arrays (full capacity)."""
        a = self.arrays
        return HitArrays(*(a[k] for k in ("t", "object_id", "prim_id", "barycentrics", "position",
                                          "geometric_normal", "normal")))  # fmt: skip

    def grab(self, chunks: int, workers: int) -> range:
        """The next chunks to trace (guided scheduling: big pieces first, single chunks at the
        end, so that all processes finish together). Empty when the round is done."""
        with self.lock:
            k = int(self.next[0])
            take = min(GRAB, max(1, (chunks - k) // (2 * workers)), max(0, chunks - k))
            self.next[0] = k + take
        return range(k, k + take)


def _drain(kernel: TraceKernel, op: str, shared: _Shared, n: int, workers: int, src, dst) -> list[range]:
    """Trace chunks of a round of ``n`` rays until none is left; return the chunks traced.

    Args:
        src: (o, d, t_max) arrays of the round's rays (t_max only for occlusion).
        dst: :class:`HitArrays` or a bool array for the round's results.
    """
    done, chunks = [], -(-n // CHUNK)
    while got := shared.grab(chunks, workers):
        a, b = got.start * CHUNK, min(n, got.stop * CHUNK)
        if op == "trace":
            kernel.trace(src[0][a:b], src[1][a:b], dst[a:b])
        else:
            kernel.occluded(src[0][a:b], src[1][a:b], src[2][a:b], dst[a:b])
        done.append(got)
    return done


def _worker_main(kernel: TraceKernel, shared: _Shared, workers: int, conn, parent_end, ppid: int) -> None:
    """A child's loop: ``(op, n)`` in, chunks of the round traced, ``None`` or an error out."""
    parent_end.close()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle; it closes us
    gc.disable()  # never run finalisers of inherited (torch) objects here; fewer copied pages
    configure_worker()  # one torch thread, one BLAS thread: a worker shares the cores with its siblings
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


def default_workers() -> int:
    """Processes that trace a large batch: :func:`torch_brdf._threads.worker_count` (the usable
    cores, affinity and cgroup quota, at most 8; ``TORCH_BRDF_WORKERS`` overrides)."""
    return worker_count()


class TracePool:
    """The parent plus ``workers - 1`` forked children tracing the chunks of a call.

    A call goes in rounds of up to :data:`ROUND` rays: the parent copies the round's rays
    to shared memory, every process takes chunks from a shared counter until none is left
    (the parent reads the caller's arrays and writes the results in place, the children
    use shared memory), then the parent copies the children's results out.

    Args:
        kernel: the :class:`TraceKernel` (its embree scene is committed before forking).
        workers: processes that trace, the parent included (>= 2).
    """

    def __init__(self, kernel: TraceKernel, workers: int):
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
        prepare_fork()
        ctx = multiprocessing.get_context("fork")
        ppid = os.getpid()
        self._shared = _Shared(ROUND, ctx.Lock())
        with warnings.catch_warnings():  # Python >= 3.12 warns on fork with threads: our children use no torch
            warnings.filterwarnings("ignore", message=".*fork.*", category=DeprecationWarning)
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

    def trace(self, o: np.ndarray, d: np.ndarray, out: HitArrays) -> None:
        """:meth:`TraceKernel.trace` over all processes. o, d: (P, 3) float32; out: P rays."""
        self._run("trace", (o, d), out)

    def occluded(self, o: np.ndarray, d: np.ndarray, t_max: np.ndarray, out: np.ndarray) -> None:
        """:meth:`TraceKernel.occluded` over all processes. t_max: (P,) float32; out: (P,) bool."""
        self._run("occluded", (o, d, t_max), out)

    def _run(self, op: str, src: tuple[np.ndarray, ...], out) -> None:
        with self._lock:
            self.start()
            try:
                for a in range(0, len(src[0]), ROUND):
                    self._round(op, tuple(x[a : a + ROUND] for x in src), out[a : a + ROUND])
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
        theirs = np.ones(-(-n // CHUNK), bool)
        for r in mine:
            theirs[r.start : r.stop] = False
        for k in np.flatnonzero(theirs):
            a, b = k * CHUNK, min(n, (k + 1) * CHUNK)
            if op == "trace":
                for dst, s in zip(out[a:b].fields(), sh.hits()[a:b].fields(), strict=True):
                    dst[:] = s
            else:
                out[a:b] = sh.occluded[a:b]
