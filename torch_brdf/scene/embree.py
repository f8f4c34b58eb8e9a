r"""The numpy + embree side of ray tracing: chunked closest-hit and occlusion queries.

embreex holds the GIL for a whole ``EmbreeScene.run`` call, so threads do not trace in
parallel; processes do (:class:`~torch_brdf.parallel.tracepool.TracePool`). Everything here
uses numpy and embreex only, never torch, because it also runs in children forked from a
parent that may have torch's thread pools running (a forked child has only the forking
thread; torch would deadlock waiting for the others).

:class:`TraceKernel` traces rays in chunks of :data:`CHUNK` rays and turns embree's output
into hit arrays (:class:`HitArrays`). Chunks start at global ray indices ``k * CHUNK`` and
every chunk runs the same numpy calls on arrays of the same shapes and strides, whichever
process traces it, so results are bitwise identical for any number of workers (numpy's SIMD
loops do not depend on alignment, only on shapes and strides).

Compiled loops (``transport/csrc``) may call embree themselves: :func:`embree_entry`
gives the committed scene's ``RTCScene`` handle and the address of ``rtcOccluded1`` from the
very library instance embreex loaded (so the same BVH and the same per-ray query as
``EmbreeScene.run``), or None where that cannot be checked.
"""

from __future__ import annotations

import ctypes
import gc
import glob
import os
from dataclasses import dataclass

import numpy as np
from embreex import rtcore, rtcore_scene

from ._bindings import EMBREE, declare

#: rays per embree call; results do not depend on it being shared by every process.
CHUNK = 1 << 14
#: chunks that go through embree before their hits are computed (at most).
BATCH = 16


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

    #: what a :class:`~torch_brdf.parallel.tracepool.TracePool` of this kernel reads: rays per
    #: chunk (every process's chunks start at multiples of it) and the type of its hit results
    chunk = CHUNK
    results = HitArrays

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
