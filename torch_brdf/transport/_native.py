"""The compiled kernel of the precomputations (the C files of ``transport/csrc``, one job per file:
torch's random generator, the entries and their per-key sums, sparse blocks, a tile's sums,
area-light samples, eye rays, the tracer's per-vertex steps and wavefront, visibility fans and
GI rays cast straight into embree): built on first use, cached, optional.

:func:`library` compiles every ``csrc/*.c`` with the system C compiler (``$CC``, else Python's
own compiler, else ``cc``) and ``-Wall -Wextra -Werror`` into ``$TORCH_BRDF_CACHE/native/``
under a name keyed by the hash of every source file (``*.c`` and ``*.h``, names and contents),
the compiler command and the flags, once per machine (later processes load the cached file in
milliseconds), loads it with :mod:`ctypes` and declares its entry points from the one table of
signatures (:data:`torch_brdf.scene._bindings.KERNEL`): no Python or torch headers, no build step
beyond ``pip install``. Without a working compiler (or with ``TORCH_BRDF_NATIVE=0``) it returns
None after one warning and the precomputation keeps its torch path. The entries and sums equal
the torch path's bit for bit on the same paths (``tests/transport/test_native.py``); the
per-vertex steps use libm's scalar math (and their own cos/sin) where torch uses its vectorised
math, so whole precomputations agree to float32 rounding, not bit for bit
(``tests/transport/test_vertex.py``). The visibility fans give the same records bit for bit as
the numpy path (``tests/transport/test_visibility.py``). Each entry point, its torch twin and
its test: ``docs/kernel.md``.

``TORCH_BRDF_NATIVE_SANITIZE=1`` builds the kernel with AddressSanitizer and
UndefinedBehaviorSanitizer instead (:data:`SANITIZE_FLAGS`, a cache entry of its own); the
process must have the ASan runtime loaded first (``LD_PRELOAD`` of :func:`sanitizer_runtime`,
as ``.ci/sanitize`` does; without it :func:`library` raises instead of letting the loader abort
the process).
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
from ..errors import TorchBRDFError, ValueRangeError
from ..scene._bindings import KERNEL, declare
from ..scene.lights import AreaLight, LightSample

__all__ = [
    "ENV_VAR",
    "SANITIZE_ENV_VAR",
    "SANITIZE_FLAGS",
    "Accumulator",
    "TileSums",
    "area_light_sample",
    "build_name",
    "build_seconds",
    "key_bits",
    "library",
    "occluded_fans",
    "sanitizer_runtime",
    "sources",
    "visibility_fans",
]

#: ``TORCH_BRDF_NATIVE=0`` keeps the torch path (no compiler call)
ENV_VAR = "TORCH_BRDF_NATIVE"
#: ``TORCH_BRDF_NATIVE_SANITIZE=1`` builds and loads the kernel with the sanitizers
SANITIZE_ENV_VAR = "TORCH_BRDF_NATIVE_SANITIZE"
_SOURCE_DIR = Path(__file__).with_name("csrc")
# -O3 vectorises the sampling passes (the AVX2 copies of TB_SIMD functions in csrc);
# -ffp-contract=off and no -ffast-math keep every operation IEEE's in the order written (no FMA,
# no reassociation: the torch path's bits); -fno-math-errno and -fno-trapping-math change no
# value, they let sqrtf inline and selects replace branches so the loops vectorise;
# -fvisibility=hidden exports only the entry points (TB_API in kernel.h)
_FLAGS = [
    "-O3",
    "-fPIC",
    "-shared",
    "-ffp-contract=off",
    "-fno-fast-math",
    "-fno-math-errno",
    "-fno-trapping-math",
    "-fvisibility=hidden",
    "-Wall",
    "-Wextra",
    "-Werror",
]
#: added to the flags of the sanitized build (``TORCH_BRDF_NATIVE_SANITIZE=1``)
SANITIZE_FLAGS = ["-fsanitize=address,undefined", "-fno-omit-frame-pointer"]
_state: dict = {"lib": None, "tried": False, "build_s": 0.0}


def _compiler() -> list[str] | None:
    cc = os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc"
    cmd = shlex.split(cc)
    if not cmd or shutil.which(cmd[0]) is None:
        cmd = ["cc"]
    return cmd if shutil.which(cmd[0]) is not None else None


def sources() -> list[Path]:
    """The kernel's source files (``csrc/*.c`` and ``csrc/*.h``), sorted by name."""
    return sorted([*_SOURCE_DIR.glob("*.c"), *_SOURCE_DIR.glob("*.h")])


def _sanitize() -> bool:
    return os.environ.get(SANITIZE_ENV_VAR, "0") not in ("", "0")


def sanitizer_runtime(cc: list[str] | None = None) -> str | None:
    """The path of the compiler's AddressSanitizer runtime (``libasan.so``), which a Python
    process must preload (``LD_PRELOAD``) to load the sanitized kernel; None when the compiler
    has none."""
    cc = cc or _compiler()
    if cc is None:
        return None
    res = subprocess.run([*cc, "-print-file-name=libasan.so"], capture_output=True, text=True, timeout=60)
    path = res.stdout.strip()
    return path if res.returncode == 0 and os.path.isabs(path) and os.path.exists(path) else None


def _asan_loaded() -> bool:
    try:
        with open("/proc/self/maps") as f:
            return any("libasan" in line for line in f)
    except OSError:  # no /proc: let the loader decide
        return True


def build_name(cc: list[str], flags: list[str], files: list[Path], sanitize: bool = False) -> str:
    """The cache file name of a build: a hash of the compiler command, the flags and every
    source file's name and bytes (``polynomial_sanitize_*`` for the sanitized build)."""
    h = hashlib.sha256("\0".join(cc + flags).encode())
    for f in files:
        data = f.read_bytes()
        h.update(f"\0{f.name}\0{len(data)}\0".encode() + data)
    return f"polynomial_{'sanitize_' if sanitize else ''}{h.hexdigest()[:16]}.so"


def _build(sanitize: bool = False) -> ctypes.CDLL:
    cc = _compiler()
    if cc is None:
        raise OSError("no C compiler found ($CC, Python's CC or cc)")
    if sanitize and not _asan_loaded():
        # loading the build would abort the process (ASan's runtime must be the first library)
        raise TorchBRDFError(
            f"{SANITIZE_ENV_VAR}=1 needs the AddressSanitizer runtime preloaded: "
            f"LD_PRELOAD={sanitizer_runtime(cc) or 'libasan.so'} (see .ci/sanitize)"
        )
    flags = [*_FLAGS, *SANITIZE_FLAGS] if sanitize else list(_FLAGS)
    files = sources()
    if not any(f.suffix == ".c" for f in files):
        raise OSError(f"no kernel sources in {_SOURCE_DIR}")
    try:
        return declare(ctypes.CDLL(str(_compile(cc, flags, files, sanitize))), KERNEL)
    except OSError as strict:
        if "-Werror" not in flags:
            raise
        # A newer compiler may warn where ours does not: the kernel is still correct C, so a
        # user's build goes on without -Werror (CI keeps the warnings fatal) and says why.
        lenient = [f for f in flags if f != "-Werror"]
        lib = declare(ctypes.CDLL(str(_compile(cc, lenient, files, sanitize))), KERNEL)
        warnings.warn(f"torch_brdf: the compiled kernel built only with warnings allowed ({strict})", stacklevel=3)
        return lib


def _compile(cc: list[str], flags: list[str], files: list[Path], sanitize: bool) -> Path:
    """The cached shared library for these sources and flags, compiled (atomically) if absent."""
    out = cache_dir() / "native" / build_name(cc, flags, files, sanitize)
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
            part = Path(tmp) / out.name
            cmd = [*cc, *flags, "-o", str(part), *(str(f) for f in files if f.suffix == ".c")]
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
            if res.returncode != 0:
                raise OSError(f"{cc[0]} failed ({res.returncode}): {res.stderr.strip()[-500:]}")
            os.replace(part, out)  # atomic: concurrent builders leave one complete file
        _state["build_s"] = time.perf_counter() - t0
    return out


def library() -> ctypes.CDLL | None:
    """The loaded kernel, building it on first use; None (after one warning) without a compiler
    or with ``TORCH_BRDF_NATIVE=0``. With ``TORCH_BRDF_NATIVE_SANITIZE=1``, the sanitized kernel
    (an error when the process lacks the preloaded ASan runtime it needs).

    Raises:
        TorchBRDFError: a sanitized kernel asked for in a process without the ASan runtime.
    """
    if os.environ.get(ENV_VAR, "1") == "0":
        return None
    if not _state["tried"]:
        _state["tried"] = True
        try:
            _state["lib"] = _build(_sanitize())
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
        ``csrc/reduce.c``): weight ``((raw[kk] * lw [* f] [* scale[sum(counts[kk])]]) * xw[a]) * yw[b]``
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
    (``tb_tile_add`` in ``csrc/tile.c``) instead of sorted and merged: the same sums, added in the
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
            :func:`~torch_brdf.scene.embree.embree_entry`.
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
