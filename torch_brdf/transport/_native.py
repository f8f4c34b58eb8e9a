"""The compiled kernel of the GI precompute (``_native.c``: the entries and their per-key sums,
area-light next-event samples, the tracer's per-vertex steps of
:mod:`torch_brdf.transport.polynomial.vertex`) and of the visibility cubemaps (ray fans cast
straight into embree, flips per block): built on first use, cached, optional.

:func:`library` compiles ``_native.c`` with the system C compiler (``$CC``, else Python's
own compiler, else ``cc``) into ``$TORCH_BRDF_CACHE/native/`` under a name keyed by the
hash of the source and the compiler command, once per machine (later processes load the
cached file in milliseconds), and loads it with :mod:`ctypes`: no Python or torch headers,
no build step beyond ``pip install``. Without a working compiler (or with
``TORCH_BRDF_NATIVE=0``) it returns None after one warning and the precomputation keeps
its torch path. The entries and sums equal the torch path's bit for bit on the same paths
(``tests/transport/test_native.py``); the per-vertex steps use libm's scalar math (and their own
cos/sin) where torch uses its vectorised math, so whole precomputations agree to float32 rounding, not bit for bit
(``tests/transport/test_vertex.py``). The visibility fans give the same records bit for bit as
the numpy path (``tests/transport/test_visibility.py``).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shlex
import shutil
import subprocess
import sysconfig
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from ..data import cache_dir
from ..errors import ValueRangeError
from ..scene.lights import AreaLight, LightSample

__all__ = [
    "ENV_VAR",
    "Accumulator",
    "TileSums",
    "area_light_sample",
    "build_seconds",
    "key_bits",
    "library",
    "occluded_fans",
    "visibility_fans",
]

#: ``TORCH_BRDF_NATIVE=0`` keeps the torch path (no compiler call)
ENV_VAR = "TORCH_BRDF_NATIVE"
_SOURCE = Path(__file__).with_name("_native.c")
# -O3 vectorises the sampling passes (the AVX2 copies of TB_SIMD functions in _native.c);
# -fno-math-errno and -fno-trapping-math change no value (no FMA, no reassociation: the
# tensors are the same bit for bit as with -O2, checked in session 9), they let sqrtf inline and
# selects replace branches so the loops vectorise
_FLAGS = ["-O3", "-fPIC", "-shared", "-ffp-contract=off", "-fno-fast-math", "-fno-math-errno", "-fno-trapping-math"]
_state: dict = {"lib": None, "tried": False, "build_s": 0.0}


def _compiler() -> list[str] | None:
    cc = os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc"
    cmd = shlex.split(cc)
    if not cmd or shutil.which(cmd[0]) is None:
        cmd = ["cc"]
    return cmd if shutil.which(cmd[0]) is not None else None


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    lib.tb_new.restype, lib.tb_new.argtypes = p, [i32, i32, p]
    lib.tb_free.restype, lib.tb_free.argtypes = None, [p]
    lib.tb_clear.restype, lib.tb_clear.argtypes = None, [p]
    lib.tb_size.restype, lib.tb_size.argtypes = i64, [p]
    lib.tb_max_count.restype, lib.tb_max_count.argtypes = i32, [p]
    lib.tb_add_sums.restype, lib.tb_add_sums.argtypes = i32, [p, i64, p, p, p, p, p, p, p]
    lib.tb_emit.restype = i32
    lib.tb_emit.argtypes = [p, i64, i64, i64, p, p, p, p, p, p, p, p, p, p, p, i64, i64, p, p, i32, i64, p, p, i32]
    lib.tb_reduce.restype, lib.tb_reduce.argtypes = i32, [p, i32, p, p, ctypes.POINTER(i64)]
    lib.tb_reduce_into.restype, lib.tb_reduce_into.argtypes = i32, [p, i32, p]
    lib.tb_blocks.restype, lib.tb_blocks.argtypes = i64, [i64, i32, p, p, p, p, i64, i64, p, p, p, p, p, p]
    lib.tb_area_points.restype, lib.tb_area_points.argtypes = None, [i64, p, p, p, i64, p, p, p, p, p]
    lib.tb_area_finish.restype = None
    lib.tb_area_finish.argtypes = [i64, p, p, p, p, p, p, ctypes.c_float, p, p, p, p, p, p, p]
    f32 = ctypes.c_float
    lib.tb_frame.restype, lib.tb_frame.argtypes = None, [i64, p, p, p, p, p]
    lib.tb_area_sample.restype = i64
    lib.tb_area_sample.argtypes = [i64, p, p, i64, p, p, p, f32, p, p, p, f32, p, p, p, p, p, p, p]
    lib.tb_unoccluded.restype, lib.tb_unoccluded.argtypes = i64, [i64, p, p, p]
    lib.tb_light_gather.restype = None
    lib.tb_light_gather.argtypes = [i64, p, p, p, p, f32, p, p, p, p, p, p, p, p, p]
    lib.tb_layers.restype, lib.tb_layers.argtypes = None, [i64, i32, i64, p, p, p, p, p, p, p, p]
    lib.tb_fixed_f.restype, lib.tb_fixed_f.argtypes = None, [i64, p, p, p, p, p, p]
    lib.tb_gather.restype, lib.tb_gather.argtypes = None, [i64, p, i32, p, p, p]
    lib.tb_mixture.restype, lib.tb_mixture.argtypes = None, [i64, p, p, f32, f32, f32, f32, p, p, p, p]
    lib.tb_sincos.restype, lib.tb_sincos.argtypes = None, [i64, p, p, p]
    lib.tb_advance.restype = i64
    lib.tb_advance.argtypes = [i64, p, p, p, p, i32, p, p, i32, p, p, p, p, p, i64, p, i64, p, f32, p, p, p]
    lib.tb_vis_fans.restype = i64
    lib.tb_vis_fans.argtypes = [p, p, i64, p, p, i64, p, p, i64, ctypes.c_double, i64, p, p, p]
    lib.tb_occluded_fans.restype, lib.tb_occluded_fans.argtypes = i64, [p, p, i64, p, p, p, p, p]
    # GI ray casting (transport/rays.py)
    lib.tb_trace_hits.restype, lib.tb_trace_hits.argtypes = i64, [p, p, i64, p, p, p, p, p, p, p, p, p, p, p, p]
    lib.tb_occluded_rays.restype, lib.tb_occluded_rays.argtypes = i64, [p, p, i64, p, p, i64, p, p, p]
    lib.tb_intersect_only.restype, lib.tb_intersect_only.argtypes = i64, [p, p, i64, p, p, p, p]
    # a tile's sums by record (TileSums)
    lib.tb_tile_new.restype, lib.tb_tile_new.argtypes = p, [i32, p]
    lib.tb_tile_free.restype, lib.tb_tile_free.argtypes = None, [p]
    lib.tb_tile_size.restype, lib.tb_tile_size.argtypes = i64, [p]
    lib.tb_tile_max_count.restype, lib.tb_tile_max_count.argtypes = i32, [p]
    lib.tb_tile_add.restype, lib.tb_tile_add.argtypes = i32, [p, p]
    lib.tb_tile_export.restype, lib.tb_tile_export.argtypes = i64, [p, i32, p, p]
    lib.tb_tile_blocks.restype, lib.tb_tile_blocks.argtypes = i64, [p, p, i64, i64, p, p, p, p, p, p, p]
    # a pass group's eye rays (polynomial/driver.py eye_rays)
    lib.tb_camera_local.restype, lib.tb_camera_local.argtypes = (
        i64,
        [i64, p, p, i64, i64, p, ctypes.c_double, ctypes.c_double, p],
    )
    lib.tb_camera_finish.restype, lib.tb_camera_finish.argtypes = None, [i64, p, p, p, p, p]
    # the GI tracer's wavefront in reused buffers (polynomial/vertex.py Wavefront)
    lib.tb_rand.restype, lib.tb_rand.argtypes = None, [p, i64, i32, p]
    lib.tb_wf_start.restype, lib.tb_wf_start.argtypes = i64, [i64, p, p, p, p, p, p, i64, i64, i64]
    lib.tb_wf_compact.restype, lib.tb_wf_compact.argtypes = i64, [i64, p, p, p, p, p, p, p, i64, i64, i64]
    lib.tb_wf_area_sample.restype = i64
    lib.tb_wf_area_sample.argtypes = [p, i64, p, i64, p, p, p, f32, p, p, p, f32, p, p, p, p, p, p, p]
    lib.tb_wf_light_hits.restype = i64
    lib.tb_wf_light_hits.argtypes = [i64, p, p, p, p, p, f32, p, p, p, p, i32, p, p, p, p, p, p, p, p, p]
    return lib


def _build() -> ctypes.CDLL:
    cc = _compiler()
    if cc is None:
        raise OSError("no C compiler found ($CC, Python's CC or cc)")
    src = _SOURCE.read_bytes()
    tag = hashlib.sha256(src + " ".join(cc + _FLAGS).encode()).hexdigest()[:16]
    out = cache_dir() / "native" / f"polynomial_{tag}.so"
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
            part = Path(tmp) / out.name
            res = subprocess.run(
                [*cc, *_FLAGS, "-o", str(part), str(_SOURCE)], capture_output=True, text=True, timeout=300
            )
            if res.returncode != 0:
                raise OSError(f"{cc[0]} failed ({res.returncode}): {res.stderr.strip()[-500:]}")
            os.replace(part, out)  # atomic: concurrent builders leave one complete file
        _state["build_s"] = time.perf_counter() - t0
    return _declare(ctypes.CDLL(str(out)))


def library() -> ctypes.CDLL | None:
    """The loaded kernel, building it on first use; None (after one warning) without a compiler
    or with ``TORCH_BRDF_NATIVE=0``."""
    if os.environ.get(ENV_VAR, "1") == "0":
        return None
    if not _state["tried"]:
        _state["tried"] = True
        try:
            _state["lib"] = _build()
        except (OSError, subprocess.SubprocessError) as e:
            warnings.warn(
                f"torch_brdf: the compiled reduction kernel could not be built ({e}); "
                "the precomputation uses its torch path (slower; its tensors agree with the kernel's to "
                "rounding, ~1e-6 relative, not bit for bit)",
                stacklevel=2,
            )
    return _state["lib"]


def build_seconds() -> float:
    """Seconds this process spent compiling the kernel (0 when it loaded a cached build)."""
    return _state["build_s"]


def ptr(t: torch.Tensor | np.ndarray | None) -> int | None:
    """The address of a contiguous tensor's or numpy array's data for a ctypes call (None: NULL)."""
    if t is None:
        return None
    return t.ctypes.data if isinstance(t, np.ndarray) else t.data_ptr()


def _c(t: torch.Tensor | None, dtype: torch.dtype) -> torch.Tensor | None:
    return None if t is None else t.to(dtype).contiguous()


def _bits(largest: int) -> int:
    return max(1, int(largest).bit_length())


def key_bits(sizes: dict[str, int], num_objects: int, max_count: int, by_path: bool) -> list[int] | None:
    """Bit widths of the packed key fields (record, object, bounce, j, w + 1, one count digit,
    path or 0), or None when a key would not fit in the kernel's 127 bits.

    Args:
        sizes: as for :func:`~.reduce._reduce`: ``rec``, ``obj``, ``bounce``, ``j`` (values
            below), ``w`` (w + 1 at most), ``path`` (values below).
        max_count: the largest count an entry can hold (the bounces).
    """
    out = [_bits(sizes[k] - 1) for k in ("rec", "obj", "bounce", "j")] + [_bits(sizes["w"]), _bits(max_count)]
    out.append(_bits(sizes["path"] - 1) if by_path else 0)
    return out if sum(out[:5]) + num_objects * out[5] + out[6] <= 127 else None


class Accumulator:
    """Entries keyed by (rec, obj, bounce, j, w, counts[, path]) and their float64 sums per
    key: the compiled twin of the tracer's entries and :func:`~.reduce._reduce` (same entries,
    same sums in the same order, same key order).

    Args:
        lib: :func:`library`'s kernel.
        num_objects: M, the count digits per key.
        values: V, float64 values per entry (3 for entries, 6 for sums and squares).
        bits: :func:`key_bits` (not None).
    """

    def __init__(self, lib: ctypes.CDLL, num_objects: int, values: int, bits: list[int]):
        self.lib, self.M, self.V, self.bits = lib, num_objects, values, list(bits)
        b = torch.tensor(bits, dtype=torch.int32)
        self._h = lib.tb_new(num_objects, values, b.data_ptr())
        if not self._h:
            raise MemoryError("the reduction kernel could not allocate its table")

    def __del__(self):
        if getattr(self, "_h", None):
            self.lib.tb_free(self._h)
            self._h = None

    @staticmethod
    def _check(rc: int) -> None:
        if rc == -2:
            raise ValueRangeError("an entry key exceeds the widths the reduction kernel was given")
        if rc:
            raise MemoryError("the reduction kernel ran out of memory")

    def add_sums(self, rec, obj, bounce, j, w, counts, values) -> None:
        """Add rows of sums: (n,) int64 keys, (n, M) int8 counts, (n, V) float64 values."""
        n = int(rec.shape[0])
        if n:
            cols = [_c(x, torch.int64) for x in (rec, obj, bounce, j, w)]
            cnt, vals = _c(counts, torch.int8), _c(values, torch.float64)
            self._check(self.lib.tb_add_sums(self._h, n, *map(ptr, cols), ptr(cnt), ptr(vals)))

    def emit(self, bounce: int, p: int, kk, raw, idx, rec, m1, counts, ob, ed, lw, f, scale, x, x_rows, y, y_rows):
        """The entries of light samples ``kk`` at vertex ``bounce`` (see ``tb_emit`` in
        ``_native.c``): weight ``((raw[kk] * lw [* f] [* scale[sum(counts[kk])]]) * xw[a]) * yw[b]``
        per layer combination (a major), rows with a NaN or all-zero weight dropped.

        Args:
            p: the tile's records (rec = ray % p, path = ray // p).
            kk: (n,) rows of the path state. raw: (N, 3) float32 or None (a factor 1).
            idx, m1: (N,) int64.
            rec: (rays,) int64 ray ids (ray of row r: ``rec[idx[r]]``). counts: (N, M) int8.
            ob: (n,) objects; ed: (n,) bool, add one to the count of ``ob`` (or None).
            lw: (n, 3) float32; f: (n, 3) float32 or None; scale: (E,) float32 by the sum of
                counts, or None.
            x: (xi (., La) int64 slots j, xw (., La, 3) float32); rows of the state when ``x_rows``
                else of the samples. y: likewise (yi: slots w) or None (w = -1, factor 1).
        """
        n = int(kk.numel())
        if n == 0:
            return
        xi, xw = _c(x[0], torch.int64), _c(x[1], torch.float32)
        yi, yw = (None, None) if y is None else (_c(y[0], torch.int64), _c(y[1], torch.float32))
        args = [_c(t, torch.int64) for t in (kk,)] + [_c(raw, torch.float32)]
        args += [_c(t, torch.int64) for t in (idx, rec, m1)] + [_c(counts, torch.int8), _c(ob, torch.int64)]
        args += [_c(ed, torch.uint8), _c(lw, torch.float32), _c(f, torch.float32)]
        sc = _c(scale, torch.float32)
        rc = self.lib.tb_emit(
            self._h,
            n,
            bounce,
            p,
            *map(ptr, args),
            ptr(sc),
            0 if sc is None else sc.numel(),
            xi.shape[1],
            ptr(xi),
            ptr(xw),
            int(x_rows),
            1 if yi is None else yi.shape[1],
            ptr(yi),
            ptr(yw),
            int(y_rows),
        )
        self._check(rc)

    def reduce_into(self, forward: bool, into: Accumulator | TileSums) -> None:
        """Append this accumulator's per-key sums ``s`` (ascending key order, as :meth:`reduce`)
        to ``into`` as values ``(s, s * s)`` under the keys without their path field (``into``:
        twice the values, the same widths with no path field), without unpacking the keys; a
        :class:`TileSums` adds them to its per-key sums instead (the same sums)."""
        if isinstance(into, TileSums):
            self._check(self.lib.tb_tile_add(into._h, self._h))
        else:
            self._check(self.lib.tb_reduce_into(self._h, int(forward), into._h))

    def clear(self) -> None:
        """Remove every entry (the memory stays for the next ones)."""
        self.lib.tb_clear(self._h)

    def __len__(self) -> int:
        return int(self.lib.tb_size(self._h))

    def max_count(self) -> int:
        return int(self.lib.tb_max_count(self._h))

    def reduce(self, forward: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """-> fields (U, 5 + M) int64 (rec, obj, bounce, j, w, counts) and sums (U, V) float64
        per distinct key, in ascending key order (counts compared first object first when
        ``forward``, else last object first)."""
        n = len(self)
        keys = torch.empty(n, 5 + self.M, dtype=torch.int64)
        vals = torch.empty(n, self.V, dtype=torch.float64)
        u = ctypes.c_int64(0)
        self._check(self.lib.tb_reduce(self._h, int(forward), keys.data_ptr(), vals.data_ptr(), ctypes.byref(u)))
        return keys[: u.value], vals[: u.value]


class TileSums:
    """A tile's per-key sums and sums of per-path squares, from its pass groups
    (:meth:`Accumulator.reduce_into`) bucketed by (record, path) and summed record by record
    (``tb_tile_add`` in ``_native.c``) instead of sorted and merged: the same sums, added in the
    same order, as an :class:`Accumulator` of 6 values receiving the groups' sorted runs.

    Args:
        lib: :func:`library`'s kernel.
        num_objects: M.
        bits: the pass groups' :func:`key_bits` with the path width 0 (:meth:`fits` says when
            the groups' record and path fields are narrow enough).
    """

    V = 6

    def __init__(self, lib: ctypes.CDLL, num_objects: int, bits: list[int]):
        self.lib, self.M, self.bits = lib, num_objects, list(bits)
        b = torch.tensor(bits, dtype=torch.int32)
        self._h = lib.tb_tile_new(num_objects, b.data_ptr())
        if not self._h:
            raise MemoryError("the tile's sums could not allocate their tables")

    @staticmethod
    def fits(bits: list[int]) -> bool:
        """Whether groups of these :func:`key_bits` (with a path field) fit the kernel's buckets
        (record + path bits <= 22; else the sorted runs of :class:`Accumulator`)."""
        return bits[0] <= 22 and 1 <= bits[-1] and bits[0] + bits[-1] <= 22

    def __del__(self):
        if getattr(self, "_h", None):
            self.lib.tb_tile_free(self._h)
            self._h = None

    def __len__(self) -> int:
        """The keys (the first call sums each record's rows; groups cannot be added after it)."""
        n = int(self.lib.tb_tile_size(self._h))
        if n < 0:
            raise MemoryError("the tile's sums ran out of memory")
        return n

    def max_count(self) -> int:
        return int(self.lib.tb_tile_max_count(self._h))

    def reduce(self, forward: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """-> fields (U, 5 + M) int64 (rec, obj, bounce, j, w, counts) and (U, 6) float64 sums and
        sums of squares per key, ascending as :meth:`Accumulator.reduce` returns them."""
        n = len(self)
        keys = torch.empty(n, 5 + self.M, dtype=torch.int64)
        vals = torch.empty(n, self.V, dtype=torch.float64)
        u = self.lib.tb_tile_export(self._h, int(forward), keys.data_ptr(), vals.data_ptr())
        if u != n:
            raise MemoryError("the tile's sums could not be exported")
        return keys, vals


def area_light_sample(light, pos: torch.Tensor, ng: torch.Tensor, ns: torch.Tensor, gen, u: torch.Tensor | None = None):
    """Next-event samples of an :class:`~torch_brdf.scene.lights.AreaLight` in the kernel: the
    same uniforms (one ``torch.rand``), the same float64/float32 arithmetic in the same order
    as ``AreaLight.sample`` and the cosines of ``sample_light``, so the same bits.

    Args:
        pos, ng, ns: (n, 3) float32 points, geometric and shading normals.
        u: (n, 3) float64 uniforms to use instead of drawing them from ``gen``
            (``AreaLight.sample_points``'s ``u``).
    Returns:
        (:class:`LightSample`, cos (n,) at the shading normal, ok (n,) bool: cos > 0, the light
        in front of ``ng`` and pdf > 0), or None (another light, another dtype, no kernel): use
        the torch path.
    """
    lib = library()
    if lib is None or type(light) is not AreaLight or pos.dtype != torch.float32:
        return None
    n = pos.shape[0]
    if u is None:
        u = torch.rand(n, 3, generator=gen, dtype=torch.float64)  # as AreaLight.sample_points draws them
    u = u.to(torch.float64).contiguous()
    sq = u[:, 1].sqrt()  # square roots in torch: its vectorised sqrt decides the last bit
    tri, nrm = light.triangles.contiguous(), light.normals.contiguous()
    cdf, rad = light.cdf.contiguous(), light.radiance.to(torch.float32).contiguous()
    pos, ng, ns = (_c(x, torch.float32) for x in (pos, ng, ns))
    f32 = {"dtype": torch.float32}
    d, d2, idx = torch.empty(n, 3, **f32), torch.empty(n, **f32), torch.empty(n, dtype=torch.int64)
    lib.tb_area_points(n, *map(ptr, (u, sq, cdf)), cdf.numel(), *map(ptr, (tri, pos, d, d2, idx)))
    dist = d2.sqrt()
    w, wt = torch.empty(n, 3, **f32), torch.empty(n, 3, **f32)
    pdf, cos, ok = torch.empty(n, **f32), torch.empty(n, **f32), torch.empty(n, dtype=torch.bool)
    area = ctypes.c_float(light.total_area)
    lib.tb_area_finish(n, *map(ptr, (d, d2, dist, idx, nrm, rad)), area, *map(ptr, (ng, ns, w, wt, pdf, cos, ok)))
    return LightSample(direction=w, distance=dist, weight=wt, pdf=pdf), cos, ok


def _np(a: np.ndarray, dtype) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=dtype)


def visibility_fans(
    lib: ctypes.CDLL,
    entry: tuple[int, int],
    origins: np.ndarray,
    normals: np.ndarray,
    centres: np.ndarray,
    dirs: np.ndarray,
    eps: float,
    side: int,
) -> tuple[np.ndarray, np.ndarray] | np.ndarray:
    """The visibility of a few vertices, every ray cast by embree from the kernel (``tb_vis_fans``).

    Args:
        lib: :func:`library`'s kernel. entry: ``(RTCScene, rtcOccluded1)`` of
            :func:`~torch_brdf.scene.parallel.embree_entry`.
        origins: (m, 3) float32 ray origins; normals: (m, 3) float64 unit normals.
        centres: (3, T) float64 texel-centre directions in block order (the horizon test
            ``n . c > eps``), blocks of ``side x side`` texels row by row on one cube face.
        dirs: (T, k^2, 3) float32 ray directions per texel.
    Returns:
        ``k = 1``: ``counts`` (m, NB) int16 and ``index`` (F,) uint8, the flips of each block
        as :func:`~torch_brdf.records.visibility_codec.packed_entries` gives them; else (m, T)
        float32, the fraction of each texel's rays that escape (0 below the horizon).
    """
    m, T, k2 = len(origins), centres.shape[1], dirs.shape[1]
    if T % (side * side) or len(dirs) != T or (k2 == 1 and side * side > 256):
        raise ValueRangeError(f"{T} texels, blocks of {side} x {side} (<= 256 for flips), {len(dirs)} ray sets")
    o, n, c, d = _np(origins, np.float32), _np(normals, np.float64), _np(centres, np.float64), _np(dirs, np.float32)
    args = [*entry, m, o.ctypes.data, n.ctypes.data, T, c.ctypes.data, d.ctypes.data, k2, float(eps), side]
    if k2 > 1:
        frac = np.empty((m, T), np.float32)
        lib.tb_vis_fans(*args, None, None, frac.ctypes.data)
        return frac
    counts = np.empty((m, T // (side * side)), np.int16)
    index = np.empty(m * T, np.uint8)  # the bound; only the pages written are touched
    f = lib.tb_vis_fans(*args, counts.ctypes.data, index.ctypes.data, None)
    return counts, index[:f].copy()


def occluded_fans(
    lib: ctypes.CDLL,
    entry: tuple[int, int],
    origins: np.ndarray,
    counts: np.ndarray,
    texels: np.ndarray,
    dirs: np.ndarray,
    out: np.ndarray | None = None,
) -> int:
    """Embree alone on fans of rays, from the kernel (``tb_occluded_fans``): fan ``v`` casts
    ``counts[v]`` rays from ``origins[v]`` along ``dirs[texels[i]]`` (the same query per ray as
    :func:`visibility_fans`). Returns the occluded rays; ``out`` ((sum counts,) uint8) gets
    each ray's occlusion when given.

    Args:
        origins: (m, 3) float32; counts: (m,) int64; texels: (n,) uint16; dirs: (D, 3) float32.
    """
    o, k, t, d = _np(origins, np.float32), _np(counts, np.int64), _np(texels, np.uint16), _np(dirs, np.float32)
    if int(k.sum()) != len(t) or (len(t) and int(t.max()) >= len(d)):
        raise ValueRangeError(f"{int(k.sum())} rays in the fans, {len(t)} texels, {len(d)} directions")
    if out is not None and (out.dtype != np.uint8 or out.shape != t.shape or not out.flags.c_contiguous):
        raise ValueRangeError(f"out must be a contiguous ({len(t)},) uint8 array")
    return int(lib.tb_occluded_fans(*entry, len(o), o.ctypes.data, k.ctypes.data, t.ctypes.data, d.ctypes.data,
                                    None if out is None else out.ctypes.data))  # fmt: skip
