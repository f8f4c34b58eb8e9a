r"""Ray tracing on torch tensors with embreex.

:class:`RayTracer` puts every scene object into one embree scene as its own geometry,
so embree's ``geomID`` is the object id and ``primID`` the triangle index inside that
object. Rays go in and :class:`Hits` come out as torch tensors; the per-ray work after
embree (positions, normals) is a handful of batched numpy gathers, no Python loop per ray.

Embree traces in float32. Positions are interpolated from the triangle's vertices with
the hit's barycentrics (more accurate on the surface than ``o + t d``), geometric normals
are the counter-clockwise face normals :math:`\mathrm{normalize}((v_1-v_0)\times(v_2-v_0))`
(trimesh's convention, *not* flipped towards the ray), shading normals interpolate the
vertex normals of smooth objects and equal the geometric normal on flat ones.

The numpy side (embree calls and the per-hit gathers, in chunks) lives in
:mod:`torch_brdf.scene.embree`; this module checks and converts tensors, in numpy too (a torch
op waits for torch's thread pool, milliseconds whenever another process holds a core). Batches
of at least :data:`PARALLEL_MIN_RAYS` rays are traced by ``workers`` processes (the caller plus
forked children, see :class:`~torch_brdf.parallel.tracepool.TracePool`) with bitwise the same
results as by one.
``benchmarks/raytrace.py`` measures both against embreex called directly.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from embreex import mesh_construction, rtcore_scene

from .._checks import as_float_tensor, check_finite, check_vectors
from ..errors import ShapeError, ValueRangeError
from ..parallel.threads import worker_count
from ..parallel.tracepool import TracePool
from .embree import CHUNK, EmbreeHits, HitArrays, TraceKernel

#: largest ``t_max`` handed to embree for occlusion (embreex's own default far distance).
_EMBREE_FAR = 1e37
#: smallest batch traced by several processes: two chunks (one per process on 2 cores, 1.4x
#: faster at 32k rays); a single chunk is traced by one process anyway.
PARALLEL_MIN_RAYS = 2 * CHUNK


@dataclass(frozen=True)
class Hits:
    """Closest hits of a batch of P rays. Misses have ``object_id == -1``.

    Attributes:
        t: (P,) ray parameter of the hit (distance for unit directions); ``inf`` on a miss.
        object_id: (P,) int64 scene object index; -1 on a miss.
        prim_id: (P,) int64 triangle index within that object; -1 on a miss.
        barycentrics: (P, 2) embree's (u, v): position = (1-u-v) v0 + u v1 + v v2.
        position: (P, 3) hit point; 0 on a miss.
        geometric_normal: (P, 3) unit counter-clockwise face normal; 0 on a miss.
        normal: (P, 3) unit shading normal; 0 on a miss.
    """

    t: torch.Tensor
    object_id: torch.Tensor
    prim_id: torch.Tensor
    barycentrics: torch.Tensor
    position: torch.Tensor
    geometric_normal: torch.Tensor
    normal: torch.Tensor

    @property
    def hit(self) -> torch.Tensor:
        """(P,) bool, True where the ray hit something."""
        return self.object_id >= 0

    def __len__(self) -> int:
        return self.t.shape[0]


def _ray_array(x, name: str) -> tuple[np.ndarray, torch.dtype]:
    """(N, 3) float32 C-contiguous copy (or view) of ``x`` and ``x``'s float dtype."""
    x = as_float_tensor(x, name)
    if x.ndim != 2 or x.shape[-1] != 3:
        raise ShapeError(f"Expected {name} to have shape (N, 3); got {tuple(x.shape)}")
    if x.dtype not in (torch.float32, torch.float64):
        raise ShapeError(
            f"Expected {name} as float32 or float64; got {x.dtype}: half precision holds unit directions to "
            "only ~1e-3 and distances only up to 65504, too coarse for ray tracing"
        )
    a = x.detach().cpu().numpy()
    if not np.isfinite(a).all():
        check_finite(x, name)  # raises, with counts
    return np.ascontiguousarray(a, dtype=np.float32), x.dtype


def _rays_to_numpy(origins, directions) -> tuple[np.ndarray, np.ndarray, torch.dtype]:
    o, dtype = _ray_array(origins, "origins")
    d, _ = _ray_array(directions, "directions")
    if o.shape != d.shape:
        raise ShapeError(f"Expected origins and directions of the same shape; got {o.shape} and {d.shape}")
    return o, d, dtype


def _tensor(a: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
    """``a`` (float32) as a tensor of ``dtype`` (converted in numpy)."""
    if dtype == torch.float64:
        a = a.astype(np.float64)
    return torch.from_numpy(a).to(dtype)


class RayTracer:
    """An embree scene over a list of meshes, one geometry per mesh.

    Args:
        meshes: the objects' meshes, in object-id order.
        smooth: per mesh, whether shading normals interpolate vertex normals (True) or
            equal the face normal (False).
        workers: processes that trace batches of at least :data:`PARALLEL_MIN_RAYS` rays,
            this one included; ``None`` = :func:`~torch_brdf.parallel.threads.worker_count`
            (the usable cores, ``TORCH_BRDF_WORKERS`` overrides), 1 = never fork. Children are forked on first use
            and stopped by :meth:`close` (or garbage collection, or exit).
    """

    def __init__(self, meshes: Sequence[trimesh.Trimesh], smooth: Sequence[bool], workers: int | None = None):
        if len(meshes) == 0:
            raise ShapeError("RayTracer needs at least one mesh")
        if workers is not None and int(workers) < 1:
            raise ValueRangeError(f"workers must be >= 1 (or None for the default); got {workers}")
        self._scene = rtcore_scene.EmbreeScene()
        verts, faces, vnormals, fnormals = [], [], [], []
        offsets_v, offsets_f = [0], [0]
        for m in meshes:
            v = np.asarray(m.vertices, dtype=np.float32)
            f = np.asarray(m.faces, dtype=np.int32)
            mesh_construction.TriangleMesh(self._scene, v, f)
            verts.append(v)
            faces.append(f.astype(np.int64) + offsets_v[-1])
            tri = v.astype(np.float64)[f]
            fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            fn /= np.linalg.norm(fn, axis=1, keepdims=True)
            fnormals.append(fn)
            vnormals.append(np.asarray(m.vertex_normals, dtype=np.float64))
            offsets_v.append(offsets_v[-1] + len(v))
            offsets_f.append(offsets_f[-1] + len(f))
        self.num_objects = len(meshes)
        self.vertices = torch.from_numpy(np.concatenate(verts))  # (V, 3) float32
        self.faces = torch.from_numpy(np.concatenate(faces))  # (F, 3) global vertex ids
        self.face_normals = torch.from_numpy(np.concatenate(fnormals).astype(np.float32))
        self.vertex_normals = torch.from_numpy(np.concatenate(vnormals).astype(np.float32))
        self.face_offsets = torch.tensor(offsets_f[:-1], dtype=torch.int64)
        self.smooth = torch.tensor([bool(s) for s in smooth], dtype=torch.bool)
        if len(self.smooth) != len(meshes):
            raise ShapeError(f"smooth has {len(self.smooth)} flags for {len(meshes)} meshes")
        # per triangle: 3 x (vertex, vertex normal), face normal; flat objects' normals are unused
        table = np.zeros((offsets_f[-1] + 1, 7, 3), np.float32)
        fv = self.faces.numpy()
        table[:-1, 0:6:2] = self.vertices.numpy()[fv]
        table[:-1, 1:6:2] = self.vertex_normals.numpy()[fv]
        table[:-1, 6] = self.face_normals.numpy()
        self._kernel = TraceKernel(self._scene, table.reshape(-1, 21), self.face_offsets.numpy(), self.smooth.numpy())
        #: processes that trace large batches, this one included.
        self.workers = worker_count() if workers is None else int(workers)
        self._pool = TracePool(self._kernel, self.workers) if self.workers > 1 else None
        lo, hi = self.vertices.min(0).values.double(), self.vertices.max(0).values.double()
        self.bbox = (lo, hi)
        extent = float((hi - lo).norm())
        magnitude = float(torch.maximum(lo.abs(), hi.abs()).max())
        #: wall seconds spent in :meth:`trace` and :meth:`occluded` (profiles of callers).
        self.seconds = 0.0
        #: distance by which ray origins are pushed off surfaces (self-intersection).
        self.ray_epsilon = max(1e-5 * extent, 64 * float(np.finfo(np.float32).eps) * magnitude, 1e-7)

    # -- queries ---------------------------------------------------------------------------
    def trace(self, origins, directions) -> Hits:
        """Closest hit of each ray.

        Args:
            origins: (P, 3) ray origins (already offset from surfaces, see :meth:`spawn`).
            directions: (P, 3) ray directions (unit length for ``t`` to be a distance).
        Returns:
            :class:`Hits` with fields in the dtype of ``origins``.
        """
        t0 = time.perf_counter()
        o_np, d_np, dtype = _rays_to_numpy(origins, directions)
        out = HitArrays.empty(len(o_np))
        if self._parallel(len(o_np)):
            self._pool.trace(o_np, d_np, out)
        else:
            self._kernel.trace(o_np, d_np, out)
        self.seconds += time.perf_counter() - t0
        t, obj, prim, *vectors = out.fields()
        return Hits(
            _tensor(t, dtype), torch.from_numpy(obj), torch.from_numpy(prim), *(_tensor(a, dtype) for a in vectors)
        )

    def occluded(self, origins, directions, t_max) -> torch.Tensor:
        """Whether anything lies on each ray within ``(0, t_max)``.

        Args:
            origins: (P, 3); directions: (P, 3); t_max: (P,) or a scalar (``inf`` allowed).
        Returns:
            (P,) bool tensor.
        Raises:
            ShapeError: shapes, or half-precision rays; ValueRangeError: NaN/Inf rays or NaN t_max.
        """
        t0 = time.perf_counter()
        o_np, d_np, _ = _rays_to_numpy(origins, directions)
        if isinstance(t_max, torch.Tensor):
            t_max = t_max.detach().cpu()
            t_max = t_max if t_max.dtype in (torch.float32, torch.float64) else t_max.float()
        tm = np.asarray(t_max)
        try:
            tm = np.broadcast_to(tm.astype(np.float32), len(o_np))
        except (TypeError, ValueError):
            raise ShapeError(f"Expected t_max of numbers, shape ({len(o_np)},) or a scalar; got {tm.shape}") from None
        if np.isnan(tm).any():
            raise ValueRangeError(f"t_max holds {int(np.isnan(tm).sum())} NaN values; use inf for an unbounded ray")
        tm_np = np.minimum(tm, np.float32(_EMBREE_FAR))
        out = np.empty(len(o_np), bool)
        if self._parallel(len(o_np)):
            self._pool.occluded(o_np, d_np, tm_np, out)
        else:
            self._kernel.occluded(o_np, d_np, tm_np, out)
        self.seconds += time.perf_counter() - t0
        return torch.from_numpy(out)

    def occluded_fans(self, origins: np.ndarray, fans: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Unbounded occlusion of fans of rays with a shared origin (e.g. a vertex's cubemap
        texels), on numpy arrays: the same per ray as :meth:`occluded` with ``t_max = inf``,
        without an (P, 3) origin array or tensor conversions.

        Args:
            origins: (m, 3) fan origins (float32, or converted).
            fans: (m, 2) integer ``(start, count)``: fan ``i`` casts ``directions[start : start + count]``
                from ``origins[i]`` (fans may share directions).
            directions: (D, 3) float32 numpy array (rows may be strided, e.g. a view of (D, 4)).
        Returns:
            (P,) bool numpy array, P = the sum of the counts, fan after fan.
        Raises:
            ShapeError: shapes or dtypes; ValueRangeError: a fan outside ``directions``, NaN/Inf rays.
        """
        t0 = time.perf_counter()
        o = np.ascontiguousarray(origins, dtype=np.float32)
        f = np.asarray(fans)
        d = directions
        if o.ndim != 2 or o.shape[1] != 3 or f.shape != (len(o), 2) or f.dtype.kind not in "iu":
            raise ShapeError(f"Expected origins (m, 3) and integer fans (m, 2); got {o.shape} and {f.dtype} {f.shape}")
        if not isinstance(d, np.ndarray) or d.dtype != np.float32 or d.ndim != 2 or d.shape[1] != 3:
            raise ShapeError(f"Expected directions as a (D, 3) float32 numpy array; got {type(d).__name__}")
        f = f.astype(np.int64)
        if len(f) and (f.min() < 0 or int((f[:, 0] + f[:, 1]).max()) > len(d)):
            raise ValueRangeError(f"fans must be (start >= 0, count >= 0) within the {len(d)} directions")
        if not (np.isfinite(o).all() and np.isfinite(d).all()):
            raise ValueRangeError("fan origins and directions must be finite")
        out = np.empty(int(f[:, 1].sum()), bool)
        if self._parallel(len(out)):  # the pool traces chunks of full ray arrays
            rays = np.concatenate([np.arange(a, a + n) for a, n in f.tolist()]) if len(f) else np.zeros(0, np.int64)
            o_all = np.ascontiguousarray(np.repeat(o, f[:, 1], axis=0))
            d_all = np.ascontiguousarray(d[rays])
            self._pool.occluded(o_all, d_all, np.full(len(out), _EMBREE_FAR, np.float32), out)
        else:
            self._kernel.occluded_fans(o, f, d, out)
        self.seconds += time.perf_counter() - t0
        return out

    def spawn(self, position, geometric_normal, directions) -> torch.Tensor:
        """Ray origins pushed off a surface to the side ``directions`` leave towards.

        Args:
            position: (P, 3) surface points; geometric_normal: (P, 3) unit normals;
            directions: (P, 3) outgoing directions.
        Returns:
            (P, 3) origins ``position + sign(d . n) * ray_epsilon * n``.
        Raises:
            ShapeError, ValueRangeError: not (P, 3), or NaN/Inf entries.
        """
        position = check_vectors(position, "position")
        geometric_normal = check_vectors(geometric_normal, "geometric_normal")
        directions = check_vectors(directions, "directions")
        side = torch.where((directions * geometric_normal).sum(-1, keepdim=True) >= 0, 1.0, -1.0)
        return position + (side * self.ray_epsilon).to(position.dtype) * geometric_normal

    def embree_entry(self) -> tuple[int, int] | None:
        """``(RTCScene handle, address of rtcOccluded1)`` for a compiled loop that casts this
        scene's rays itself, in the calling process (:func:`~torch_brdf.scene.embree.embree_entry`:
        the same BVH and per-ray query as :meth:`occluded`). None when this tracer spreads large
        batches over its forked workers (such a loop would use one core) or the handle cannot be
        checked; callers then use :meth:`occluded_fans`."""
        return None if self._pool is not None else self._kernel.native()

    def embree_hits(self) -> EmbreeHits | None:
        """:class:`~torch_brdf.scene.embree.EmbreeHits` (scene handle, embree's closest-hit and
        occlusion calls, the hit tables) for a compiled loop that casts this scene's rays and
        makes the :meth:`trace` hits itself, in the calling process, or None where the handle
        cannot be checked. Unlike :meth:`embree_entry`, also for a tracer with forked workers: the
        GI precompute then casts on one core in each tile's process whatever the tile layout
        (one code path, so the same hits in one process as in forked tiles). Such a loop adds
        its wall seconds to :attr:`seconds`."""
        return self._kernel.native_hits()

    def in_process(self) -> RayTracer:
        """A shallow copy that traces in the calling process only (no pool; shares the embree
        scene and tables): for a process that is itself one of several workers."""
        out = copy.copy(self)
        out.workers, out._pool, out.seconds = 1, None, 0.0
        return out

    def close(self) -> None:
        """Stop the worker processes, if any (the next large batch starts them again)."""
        if self._pool is not None:
            self._pool.close()

    # -- internals -------------------------------------------------------------------------
    def _parallel(self, n: int) -> bool:
        return self._pool is not None and n >= PARALLEL_MIN_RAYS
