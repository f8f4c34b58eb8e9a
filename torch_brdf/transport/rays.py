r"""The GI precompute's rays cast straight into embree by the compiled kernel.

:class:`NativeRays` casts closest-hit rays and shadow rays of a scene's
:class:`~torch_brdf.scene.raytrace.RayTracer` with ``tb_trace_hits`` and ``tb_occluded_rays`` of
``csrc/rays.c``: one C call per batch, which calls embree's ``rtcIntersect1`` / ``rtcOccluded1``
per ray (through the scene handle behind embreex, checked by
:func:`~torch_brdf.scene.embree.embree_entry`) and interpolates each hit at once, instead of
embreex's Python call per chunk, its result arrays and numpy's passes over them. The query per
ray is the one :meth:`~torch_brdf.scene.raytrace.RayTracer.trace` and ``occluded`` make, and the
hits come from the same per-triangle table with the same float32 formulas, so object and
triangle ids are the same and positions and normals agree to float32 rounding
(``tests/transport/test_rays.py``).

:meth:`NativeRays.make` gives None -- and callers keep the tracer's own methods -- without the
kernel (no compiler, ``TORCH_BRDF_NATIVE=0``) or when the embreex layout cannot be checked. A
tracer with forked workers gets one too: the rays are then cast on one core in the calling
process (the GI precompute's tiles already use the cores, and one code path gives the same hits
in one process as in forked tiles).
"""

from __future__ import annotations

import ctypes
import time

import torch

from ..errors import ShapeError, ValueRangeError
from ..scene.raytrace import Hits, RayTracer
from ._native import library
from ._native import ptr as _p

__all__ = ["NativeRays"]


class NativeRays:
    """Closest-hit and shadow rays of one :class:`~torch_brdf.scene.raytrace.RayTracer`, cast by
    the compiled kernel in the calling process. The hits of :meth:`trace` live in buffers this
    object reuses: they hold until its next :meth:`trace` (copy what you keep).

    Args:
        lib: :func:`~torch_brdf.transport._native.library`'s kernel.
        ray_tracer: the tracer whose scene is cast (its :attr:`seconds` count the calls' time).
        entry: ``ray_tracer.embree_hits()``.
    """

    def __init__(self, lib: ctypes.CDLL, ray_tracer: RayTracer, entry):
        self.lib, self.rt, self.entry = lib, ray_tracer, entry
        self._room = 0
        self._buf: dict[str, torch.Tensor] = {}

    @classmethod
    def make(cls, ray_tracer: RayTracer) -> NativeRays | None:
        """The kernel's rays for ``ray_tracer``, or None (see the module docstring)."""
        lib = library()
        entry = None if lib is None else ray_tracer.embree_hits()
        return None if entry is None else cls(lib, ray_tracer, entry)

    def _buffers(self, n: int) -> dict[str, torch.Tensor]:
        if n > self._room:
            self._room = max(n, int(1.25 * self._room))
            f, i, r = {"dtype": torch.float32}, {"dtype": torch.int64}, self._room
            # in the order of Hits' fields and of tb_trace_hits' outputs
            self._buf = {"t": torch.empty(r, **f), "object_id": torch.empty(r, **i), "prim_id": torch.empty(r, **i),
                         "barycentrics": torch.empty(r, 2, **f), "position": torch.empty(r, 3, **f),
                         "geometric_normal": torch.empty(r, 3, **f), "normal": torch.empty(r, 3, **f)}  # fmt: skip
        return {k: v[:n] for k, v in self._buf.items()}

    @staticmethod
    def _rays(x: torch.Tensor, name: str, n: int | None = None) -> torch.Tensor:
        if x.dtype != torch.float32 or x.ndim != 2 or x.shape[1] != 3 or (n is not None and x.shape[0] != n):
            raise ShapeError(
                f"Expected {name} as float32 ({'N' if n is None else n}, 3); got {x.dtype} {tuple(x.shape)}"
            )
        return x.contiguous()

    def trace(self, origins: torch.Tensor, directions: torch.Tensor) -> Hits:
        """:meth:`RayTracer.trace <torch_brdf.scene.raytrace.RayTracer.trace>` of float32 rays (other
        dtypes go to the tracer itself).

        Args:
            origins: (P, 3) float32.
            directions: (P, 3) float32.
        Returns:
            :class:`~torch_brdf.scene.raytrace.Hits` (float32 and int64 views of reused buffers).
        Raises:
            ShapeError: shapes; ValueRangeError: NaN/Inf rays.
        """
        if origins.dtype != torch.float32 or directions.dtype != torch.float32:
            return self.rt.trace(origins, directions)
        t0 = time.perf_counter()
        o = self._rays(origins, "origins")
        d = self._rays(directions, "directions", o.shape[0])
        n, e = o.shape[0], self.entry
        out = self._buffers(n)
        got = self.lib.tb_trace_hits(
            e.scene, e.intersect, n, _p(o), _p(d), _p(e.table), _p(e.offsets), _p(e.flat),
            *(_p(x) for x in out.values()),
        )  # fmt: skip
        self.rt.seconds += time.perf_counter() - t0
        if got < 0:
            raise ValueRangeError(f"ray {-1 - got} of {n} has a NaN or Inf origin or direction")
        return Hits(**out)

    def occluded(self, origins: torch.Tensor, directions: torch.Tensor, t_max: torch.Tensor, rows=None) -> torch.Tensor:
        """:meth:`RayTracer.occluded <torch_brdf.scene.raytrace.RayTracer.occluded>` of float32 rays
        with one ``t_max`` per ray, ray ``i`` along ``directions[rows[i]]`` (``rows`` None: ``i``).

        Args:
            origins: (P, 3) float32; directions: (D, 3) float32 (D = P without ``rows``);
            t_max: (P,) float32 (``inf`` allowed); rows: (P,) int64 in ``[0, D)`` or None.
        Returns:
            (P,) bool tensor.
        Raises:
            ShapeError: shapes and dtypes; ValueRangeError: NaN/Inf rays, NaN ``t_max``, rows outside.
        """
        t0 = time.perf_counter()
        o = self._rays(origins, "origins")
        n = o.shape[0]
        d = self._rays(directions, "directions", n if rows is None else None)
        if rows is not None:
            rows = rows.to(torch.int64).contiguous()
            if rows.shape != (n,):
                raise ShapeError(f"Expected rows of shape ({n},); got {tuple(rows.shape)}")
        tm = t_max.to(torch.float32).contiguous()
        if tm.shape != (n,):
            raise ShapeError(f"Expected t_max of shape ({n},); got {tuple(tm.shape)}")
        out = torch.empty(n, dtype=torch.bool)
        e = self.entry
        got = self.lib.tb_occluded_rays(e.scene, e.occluded, n, _p(o), _p(d), d.shape[0], _p(rows), _p(tm), _p(out))
        self.rt.seconds += time.perf_counter() - t0
        if got < 0:
            raise ValueRangeError(
                f"shadow ray {-1 - got} of {n} has a NaN or Inf origin or direction, a NaN t_max (use inf "
                f"for an unbounded ray) or a direction row outside [0, {d.shape[0]})"
            )
        return out
