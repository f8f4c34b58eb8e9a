r"""MERL BRDF files: the ``.binary`` format, its index conventions, the downsampled table.

The MERL database (Matusik, Pfister, Brand, McMillan, "A Data-Driven Reflectance
Model", ACM TOG 22(3), 2003) tabulates isotropic BRDFs in Rusinkiewicz half/difference
angles :math:`(\theta_h, \theta_d, \phi_d)` (:func:`torch_brdf.frame.half_diff_angles`)
on a ``(90, 90, 180)`` grid.

``.binary`` layout: three little-endian int32 ``(90, 90, 180)``, then ``3 * 90 * 90 * 180``
little-endian float64: all red values, then green, then blue; within a channel the flat
index is ``phi_d_idx + 180 * (theta_d_idx + 90 * theta_h_idx)`` (C order
``[theta_h][theta_d][phi_d]``). Values times ``MERL_SCALE`` (1/1500, 1.15/1500, 1.66/1500)
are the RGB BRDF in 1/sr; negative values mark bins without a measurement.

**Missing bins.** :func:`read_merl_binary` returns the scaled table with missing bins
kept negative (scaling by a positive factor keeps the sign); ``table < 0`` is the mask.
One array instead of (values, mask) keeps the file's own convention and costs nothing.

**Angle -> index** (MERL's lookup, ``BRDFRead.cpp``, whose arithmetic this follows exactly):

* :math:`i_h = \lfloor \sqrt{\theta_h / (\pi/2)} \cdot 90 \rfloor` (0 for
  :math:`\theta_h \le 0`), clamped to 0..89 (square-root spacing: fine bins near the
  specular peak);
* :math:`i_d = \lfloor \theta_d / (\pi/2) \cdot 90 \rfloor`, clamped to 0..89;
* :math:`\phi_d` is folded first (if :math:`\phi_d < 0` add :math:`\pi`: an isotropic,
  reciprocal BRDF is unchanged by :math:`\phi_d \to \phi_d + \pi`), then
  :math:`i_p = \lfloor \phi_d / \pi \cdot 180 \rfloor`, clamped to 0..179.

The input domain of :math:`\phi_d` is :math:`(-\pi, \pi]` (what ``half_diff_angles``
returns); :math:`\phi_d = \pi` and :math:`\phi_d = -0^-` land in bin 179 by the clamp.
``floor`` puts an angle that sits exactly on an edge into the *upper* bin. Bin ``i``
covers :math:`[\text{lower}(i), \text{lower}(i+1))` with the **lower edges**
:math:`\theta_h = (i/90)^2 \pi/2`, :math:`\theta_d = i\,(\pi/2)/90`,
:math:`\phi_d = i\,\pi/180` (:func:`merl_index_to_angles`). Beware: those lower edges
computed in floating point are *not* safe lookup points — rounding puts several of them
one bin low (e.g. :math:`\theta_d` index 19 in float64); address a bin by its centre
(``at="centre"``).

The index functions reproduce MERL's float64 arithmetic bit for bit (for :math:`\theta_h`
that is :math:`\sqrt{\theta_h/(\pi/2)\cdot 90\cdot 90}`, which differs from the formula above
by an ulp at some edges) on every CPU: they compare against tables of exact bin edges
instead of evaluating square roots in vectorised code (see :func:`merl_theta_h_index`).

**Downsampled table** (``merl100_f16.npz`` / ``merl_nbrdf_sample_f16.npz`` layout):
:func:`load_merl_table` and :func:`write_merl_table`; see :class:`MERLTableData`.
"""

from __future__ import annotations

import functools
import math
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from ..errors import FileFormatError, ShapeError, ValueRangeError
from .arrays import read_npz
from .atomic import replacing

#: grid resolution of a MERL table: (theta_h, theta_d, phi_d) bins
MERL_RES: tuple[int, int, int] = (90, 90, 180)
#: RGB factors that turn stored values into BRDF values (1/sr)
MERL_SCALE: tuple[float, float, float] = (1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0)
_N_VALUES = 3 * MERL_RES[0] * MERL_RES[1] * MERL_RES[2]
#: size of every MERL ``.binary`` file: 12-byte header + float64 values
MERL_FILE_BYTES: int = 12 + 8 * _N_VALUES  # 34,992,012

_HALF_PI = math.pi / 2


# -- angles <-> indices ---------------------------------------------------------------------
def merl_fold_phi_d(phi_d: torch.Tensor) -> torch.Tensor:
    r"""Fold :math:`\phi_d \in (-\pi, \pi]` into :math:`[0, \pi]`: add :math:`\pi` where negative.

    Args:
        phi_d: (*B,) angles in radians.
    Returns:
        (*B,) folded angles, same dtype.
    """
    return torch.where(phi_d < 0, phi_d + math.pi, phi_d)


def merl_coordinates(
    theta_h: torch.Tensor, theta_d: torch.Tensor, phi_d: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    r"""Continuous MERL index coordinates (unclamped, not floored), in the input dtype.

    :math:`u_h = \sqrt{\max(\theta_h, 0)/(\pi/2)} \cdot 90`,
    :math:`u_d = \theta_d/(\pi/2) \cdot 90`, :math:`u_p = \mathrm{fold}(\phi_d)/\pi \cdot 180`.
    ``floor`` of these, clamped, are the MERL bin indices up to an ulp at bin edges (the
    exact bins are :func:`merl_indices`); integer values sit on the lower bin edges.

    Args:
        theta_h: (*B,) angles in radians (broadcastable with the others).
        theta_d: (*B,) angles in radians.
        phi_d: (*B,) angles in radians.
    Returns:
        u_h, u_d, u_p: (*B,) each.
    """
    # sqrt with a zero (not infinite) derivative at theta_h = 0, so gradients through a
    # trilinear lookup stay finite at the mirror direction (wi = wo gave NaN)
    x = theta_h.clamp_min(0) / _HALF_PI
    pos = x > 0
    u_h = torch.where(pos, torch.where(pos, x, torch.ones_like(x)).sqrt(), torch.zeros_like(x)) * MERL_RES[0]
    u_d = theta_d / _HALF_PI * MERL_RES[1]
    u_p = merl_fold_phi_d(phi_d) / math.pi * MERL_RES[2]
    return u_h, u_d, u_p


# MERL's own lookup (BRDFRead.cpp, theta_half_index / theta_diff_index / phi_diff_index),
# transliterated as scalar float64 arithmetic without the clamp. Every step is one IEEE
# operation (division, multiplication, addition, sqrt), correctly rounded on every CPU when
# done on Python floats, so these define the reference bin of every double exactly.
def _merl_scalar_h(theta_h: float) -> int:
    if theta_h <= 0.0:
        return 0
    return int(math.sqrt(theta_h / (math.pi / 2.0) * MERL_RES[0] * MERL_RES[0]))


def _merl_scalar_d(theta_d: float) -> int:
    return int(theta_d / (math.pi * 0.5) * MERL_RES[1])


def _merl_scalar_p(phi_d: float) -> int:
    return int((phi_d + math.pi if phi_d < 0.0 else phi_d) / math.pi * (2 * MERL_RES[2]) / 2)


def _double_ordinal(x: float) -> int:
    return struct.unpack("<q", struct.pack("<d", x))[0]


def _double_from_ordinal(i: int) -> float:
    return struct.unpack("<d", struct.pack("<q", i))[0]


@functools.cache
def _merl_edges(axis: str) -> tuple[float, ...]:
    """For bins 1..n-1 of ``axis``, the smallest double angle >= 0 that MERL's lookup puts in
    that bin or above (its composition of rounded monotone operations is monotone, so a
    bisection over the ordered bit patterns of non-negative doubles finds it exactly)."""
    f, n = {"h": (_merl_scalar_h, MERL_RES[0]), "d": (_merl_scalar_d, MERL_RES[1]), "p": (_merl_scalar_p, MERL_RES[2])}[
        axis
    ]
    edges = []
    for k in range(1, n):
        lo, hi = _double_ordinal(0.0), _double_ordinal(4.0)  # f(lo) < k <= f(hi)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if f(_double_from_ordinal(mid)) >= k:
                hi = mid
            else:
                lo = mid
        edges.append(_double_from_ordinal(hi))
    return tuple(edges)


def _merl_bin(angle: torch.Tensor, axis: str) -> torch.Tensor:
    # Comparisons against exact edges, never the last ulp of a vectorised sqrt or division:
    # the bin is the number of edges <= angle (float64; NaN lands in the last bin).
    x = torch.as_tensor(angle).to(torch.float64)
    edges = torch.tensor(_merl_edges(axis), dtype=torch.float64, device=x.device)
    return torch.bucketize(x, edges, right=True)


def merl_theta_h_index(theta_h: torch.Tensor) -> torch.Tensor:
    r"""MERL's :math:`\theta_h` bin: ``floor(sqrt(theta_h / (pi/2) * 90 * 90))`` clamped to 0..89.

    Exactly MERL's ``theta_half_index`` (``BRDFRead.cpp``) on the float64 value of every
    input, on every CPU: the index is found by comparing against a table of exact bin edges
    (:func:`_merl_edges`), not by evaluating the square root in vectorised code, whose last
    ulp differs between CPUs and decides the bin of angles one ulp from an edge.

    Args:
        theta_h: (*B,) radians (any floating dtype; float32 inputs are binned by their exact
            float64 value); values <= 0 give 0.
    Returns:
        (*B,) int64.
    """
    return _merl_bin(theta_h, "h")


def merl_theta_d_index(theta_d: torch.Tensor) -> torch.Tensor:
    r"""MERL's :math:`\theta_d` bin: ``floor(theta_d / (pi/2) * 90)`` clamped to 0..89
    (exactly MERL's ``theta_diff_index`` in float64, see :func:`merl_theta_h_index`).

    Args:
        theta_d: (*B,) radians.
    Returns:
        (*B,) int64.
    """
    return _merl_bin(theta_d, "d")


def merl_phi_d_index(phi_d: torch.Tensor) -> torch.Tensor:
    r"""MERL's :math:`\phi_d` bin: fold (add :math:`\pi` if negative), then
    ``floor(phi_d / pi * 180)`` clamped to 0..179 (exactly MERL's ``phi_diff_index`` in
    float64, see :func:`merl_theta_h_index`).

    Args:
        phi_d: (*B,) radians in :math:`(-\pi, \pi]`.
    Returns:
        (*B,) int64.
    """
    return _merl_bin(merl_fold_phi_d(torch.as_tensor(phi_d).to(torch.float64)), "p")


def merl_indices(
    theta_h: torch.Tensor, theta_d: torch.Tensor, phi_d: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The three MERL bin indices of half/difference angles (see the module docstring).

    Args:
        theta_h: (*B,) radians.
        theta_d: as ``theta_h``.
        phi_d: as ``theta_h``.
    Returns:
        i_h, i_d, i_p: (*B,) int64 each.
    """
    return merl_theta_h_index(theta_h), merl_theta_d_index(theta_d), merl_phi_d_index(phi_d)


def merl_flat_index(i_h: torch.Tensor, i_d: torch.Tensor, i_p: torch.Tensor) -> torch.Tensor:
    """Flat index within one channel of a ``.binary`` file: ``i_p + 180 * (i_d + 90 * i_h)``."""
    return i_p + MERL_RES[2] * (i_d + MERL_RES[1] * i_h)


def merl_index_to_angles(
    i_h, i_d, i_p, at: Literal["lower", "centre"] = "lower", dtype: torch.dtype = torch.float64
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    r"""Angles of MERL bins: their lower edges (the index -> angle map used for the
    ``theta_h``, ``theta_d``, ``phi_d`` arrays of the npz layout) or their centres.

    With :math:`t = i` (lower) or :math:`t = i + 1/2` (centre):
    :math:`\theta_h = (t/90)^2 \pi/2`, :math:`\theta_d = t\,(\pi/2)/90`,
    :math:`\phi_d = t\,\pi/180`. The centre is taken in index space, so for
    :math:`\theta_h` it is the midpoint of the square-root-mapped bin. Centres are the
    robust way to address a bin (:func:`merl_indices` of a centre is the bin itself).

    Args:
        i_h: (*B,) integer indices (tensors, arrays or sequences; any may be
            fractional too).
        i_d: as ``i_h``.
        i_p: as ``i_h``.
        at: ``"lower"`` or ``"centre"``.
        dtype: floating dtype of the result.
    Returns:
        theta_h, theta_d, phi_d: (*B,) radians each.
    """
    if at not in ("lower", "centre"):
        raise ValueRangeError(f"at must be 'lower' or 'centre'; got {at!r}")
    off = 0.5 if at == "centre" else 0.0
    t_h, t_d, t_p = (torch.as_tensor(i).to(dtype) + off for i in (i_h, i_d, i_p))
    theta_h = (t_h / MERL_RES[0]) ** 2 * _HALF_PI
    theta_d = t_d * _HALF_PI / MERL_RES[1]
    phi_d = t_p * math.pi / MERL_RES[2]
    return theta_h, theta_d, phi_d


# -- the .binary file -------------------------------------------------------------------------
def _scale_array() -> np.ndarray:
    return np.asarray(MERL_SCALE, dtype=np.float64)[:, None, None, None]


def read_merl_binary(path: str | os.PathLike, *, scaled: bool = True) -> torch.Tensor:
    """Read a MERL ``.binary`` file.

    Args:
        path: the file (34,992,012 bytes).
        scaled: multiply by :data:`MERL_SCALE` (BRDF in 1/sr, the default) or return the
            stored numbers unchanged (bit-exact file contents).
    Returns:
        (3, 90, 90, 180) float64 tensor, axes (RGB, theta_h, theta_d, phi_d); missing bins
        keep their negative sign (``table < 0`` is the mask of missing bins).
    Raises:
        FileFormatError: missing file, short header, header dims other than (90, 90, 180),
            wrong file size (truncated or trailing bytes), non-finite values.
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"MERL binary file not found: {path}")
    size = path.stat().st_size
    if size < 12:
        raise FileFormatError(f"MERL binary file {path} is truncated: {size} bytes, the header alone is 12")
    with open(path, "rb") as f:
        dims = tuple(int(d) for d in np.frombuffer(f.read(12), dtype="<i4"))
        if dims != MERL_RES:
            raise FileFormatError(
                f"MERL binary file {path}: header dims {dims}, expected {MERL_RES} (theta_h, theta_d, phi_d)"
            )
        if size != MERL_FILE_BYTES:
            what = "truncated" if size < MERL_FILE_BYTES else "longer than expected (trailing bytes)"
            raise FileFormatError(
                f"MERL binary file {path} is {what}: {size:,} bytes, expected {MERL_FILE_BYTES:,} "
                f"(12-byte header + 3*90*90*180 float64)"
            )
        vals = np.fromfile(f, dtype="<f8", count=_N_VALUES)
    if vals.size != _N_VALUES:  # the file shrank between stat and read
        raise FileFormatError(f"MERL binary file {path} is truncated: read {vals.size} of {_N_VALUES} values")
    table = vals.astype(np.float64, copy=False).reshape(3, *MERL_RES)
    if not np.isfinite(table).all():
        raise FileFormatError(f"MERL binary file {path} holds {int((~np.isfinite(table)).sum())} non-finite values")
    if scaled:
        table = table * _scale_array()
    return torch.from_numpy(np.ascontiguousarray(table))


def write_merl_binary(path: str | os.PathLike, brdf, *, scaled: bool = True) -> Path:
    r"""Write a MERL ``.binary`` file (header int32 (90, 90, 180) little-endian, then float64
    R, G, B blocks), atomically (temporary file in the same folder, then ``os.replace``).

    Round trips: with ``scaled=False`` the numbers are stored as given and
    ``read_merl_binary(path, scaled=False)`` returns them bit-exactly. With ``scaled=True``
    the stored number is the correctly rounded quotient ``value / scale``; reading
    multiplies by the scale again, so ``read(write(x)) == x`` bitwise for every ``x`` that
    any float64 file could reproduce — in particular for every table that was itself read
    from a MERL file (write -> read is idempotent). Other values (about 10-15 % of
    arbitrary float64s for the G and B scales) are not representable in the format at all;
    they come back within 1 ulp. The nearest quotient is provably the best choice: the
    set of stored numbers that reproduce ``x`` is an interval centred on ``x / scale``.

    Args:
        path: destination; its folder must exist.
        brdf: (3, 90, 90, 180) tensor or array (RGB, theta_h, theta_d, phi_d); negative
            values mark missing bins and are written as they are.
        scaled: ``brdf`` holds BRDF values (divide by :data:`MERL_SCALE` before writing)
            rather than raw stored numbers.
    Returns:
        The path written.
    Raises:
        ShapeError: wrong shape. ValueRangeError: NaN/Inf.
    """
    path = Path(path)
    if isinstance(brdf, torch.Tensor):
        brdf = brdf.detach().cpu().numpy()
    a = np.asarray(brdf)
    if a.shape != (3, *MERL_RES) or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ShapeError(f"Expected brdf to be a real array of shape (3, 90, 90, 180); got {a.shape} {a.dtype}")
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise ValueRangeError(f"brdf holds {int((~np.isfinite(a)).sum())} non-finite values; MERL files cannot")
    raw = a / _scale_array() if scaled else a
    header = np.asarray(MERL_RES, dtype="<i4").tobytes()
    with replacing(path) as tmp, open(tmp, "wb") as f:
        f.write(header)
        f.write(np.ascontiguousarray(raw, dtype="<f8").tobytes())
    return path


# -- the downsampled npz layout ---------------------------------------------------------------
_INDEX_KEYS = ("theta_h_index", "theta_d_index", "phi_d_index")
_ANGLE_KEYS = ("theta_h", "theta_d", "phi_d")
_TABLE_KEYS = ("brdf", "names", *_INDEX_KEYS, *_ANGLE_KEYS, "scale", "source")


@dataclass(frozen=True)
class MERLTableData:
    r"""A stack of MERL tables on a (possibly downsampled) MERL grid, as stored in the
    ``merl100_f16.npz`` layout. Downsampling is by index selection (no averaging).

    Attributes:
        brdf: (N, 3, Th, Td, Tp) tensor in the file's dtype (float16 for the shared files),
            RGB BRDF in 1/sr with the scale applied; missing bins are exactly -1.
        names: N material names (sorted in the shared files).
        theta_h_index, theta_d_index, phi_d_index: (Th,), (Td,), (Tp,) int64: the original
            MERL bin indices kept (strictly increasing).
        theta_h, theta_d, phi_d: (Th,), (Td,), (Tp,) float32: lower-edge angles (radians)
            of the kept bins (:func:`merl_index_to_angles`).
        scale: the RGB factors that were applied (:data:`MERL_SCALE`).
        source: ``"merl-binary"`` (measured) or ``"nbrdf"`` (a neural *approximation* of
            MERL, not measured data).
    """

    brdf: torch.Tensor
    names: tuple[str, ...]
    theta_h_index: torch.Tensor
    theta_d_index: torch.Tensor
    phi_d_index: torch.Tensor
    theta_h: torch.Tensor
    theta_d: torch.Tensor
    phi_d: torch.Tensor
    scale: tuple[float, float, float]
    source: str

    def __len__(self) -> int:
        return len(self.names)

    @property
    def is_approximation(self) -> bool:
        """True when the values are not measurements (source ``"nbrdf"``)."""
        return self.source != "merl-binary"

    def index(self, name: str) -> int:
        """Position of material ``name``; :class:`ValueRangeError` listing the names if absent."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueRangeError(f"unknown material {name!r}; this table has {list(self.names)}") from None

    def table(self, name: str | int) -> torch.Tensor:
        """One material's (3, Th, Td, Tp) table (by name or position), file dtype."""
        return self.brdf[name if isinstance(name, int) else self.index(name)]


def _fail(path, msg: str):
    raise FileFormatError(f"MERL table file {path}: {msg}")


def _index_problem(name: str, a: np.ndarray, res: int) -> str | None:
    """Why ``a`` is not a valid list of kept MERL indices, or None."""
    if a.ndim != 1 or a.size == 0 or not np.issubdtype(a.dtype, np.integer):
        return f"{name} must be a non-empty 1-D integer array; got shape {a.shape} dtype {a.dtype}"
    if (a < 0).any() or (a >= res).any() or (np.diff(a) <= 0).any():
        return f"{name} must be strictly increasing within 0..{res - 1}; got {a.tolist()}"
    return None


def load_merl_table(path: str | os.PathLike) -> MERLTableData:
    """Load and validate a downsampled MERL table (``.npz``, read without pickle).

    Expected arrays: ``brdf`` (N, 3, Th, Td, Tp) float, ``names`` (N,) str,
    ``theta_h_index`` / ``theta_d_index`` / ``phi_d_index`` 1-D int, ``theta_h`` /
    ``theta_d`` / ``phi_d`` their lower-edge angles (float), ``scale`` (3,), ``source`` ()
    str. Extra arrays are ignored.

    Args:
        path: the ``.npz`` file.
    Returns:
        The validated :class:`MERLTableData`.
    Raises:
        FileFormatError: missing or unreadable file, pickled (object) arrays, missing keys,
            wrong shapes or dtypes, indices out of range, angles that are not the lower
            edges of the indices, a scale other than MERL's, negative values other than -1,
            NaN/Inf.
    """
    path = Path(path)
    z = read_npz(path, "MERL table file")  # bounded, pickle-free; FileFormatError names the file
    missing = [k for k in _TABLE_KEYS if k not in z]
    if missing:
        _fail(path, f"missing arrays {missing} (has {sorted(z)})")
    d = {k: z[k] for k in _TABLE_KEYS}

    for k, res in zip(_INDEX_KEYS, MERL_RES, strict=True):
        problem = _index_problem(k, d[k], res)
        if problem:
            _fail(path, problem)
    shape = tuple(len(d[k]) for k in _INDEX_KEYS)
    brdf = d["brdf"]
    if brdf.ndim != 5 or brdf.shape[1] != 3 or brdf.shape[2:] != shape or brdf.shape[0] == 0:
        _fail(path, f"brdf must have shape (N>=1, 3, {shape[0]}, {shape[1]}, {shape[2]}); got {brdf.shape}")
    if not np.issubdtype(brdf.dtype, np.floating):
        _fail(path, f"brdf must be floating; got {brdf.dtype}")
    names = d["names"]
    if names.dtype.kind != "U" or names.shape != (brdf.shape[0],):
        _fail(path, f"names must be a ({brdf.shape[0]},) str array; got shape {names.shape} dtype {names.dtype}")
    names_t = tuple(str(n) for n in names)
    if len(set(names_t)) != len(names_t):
        _fail(path, "names are not unique")
    for k, ik in zip(_ANGLE_KEYS, _INDEX_KEYS, strict=True):
        a = d[k]
        if a.shape != d[ik].shape or not np.issubdtype(a.dtype, np.floating):
            _fail(path, f"{k} must be a float array of shape {d[ik].shape}; got {a.shape} {a.dtype}")
    lower = merl_index_to_angles(*(d[k].astype(np.int64) for k in _INDEX_KEYS), at="lower")
    for k, ref in zip(_ANGLE_KEYS, lower, strict=True):
        if not np.allclose(d[k].astype(np.float64), ref.numpy(), rtol=1e-6, atol=1e-7):
            _fail(path, f"{k} are not the lower-edge angles of the kept indices (MERL's index -> angle map)")
    scale = d["scale"]
    if scale.shape != (3,) or not np.allclose(scale, MERL_SCALE, rtol=1e-12, atol=0):
        _fail(path, f"scale must be {MERL_SCALE}; got {scale.tolist()}")
    source = d["source"]
    if source.dtype.kind != "U" or source.shape != ():
        _fail(path, f"source must be a 0-d str array; got shape {source.shape} dtype {source.dtype}")
    finite = np.isfinite(brdf)
    if not finite.all():
        _fail(path, f"brdf holds {int((~finite).sum())} NaN/Inf values")
    neg = brdf < 0
    if (brdf[neg] != -1).any():
        _fail(path, "brdf has negative values other than -1 (the missing-bin marker)")
    return MERLTableData(
        brdf=torch.from_numpy(np.ascontiguousarray(brdf)),
        names=names_t,
        **{k: torch.from_numpy(d[k].astype(np.int64)) for k in _INDEX_KEYS},
        **{k: torch.from_numpy(d[k].astype(np.float32)) for k in _ANGLE_KEYS},
        scale=tuple(float(s) for s in scale),
        source=str(source),
    )


def write_merl_table(
    path: str | os.PathLike,
    brdf,
    names: Sequence[str],
    theta_h_index: Sequence[int],
    theta_d_index: Sequence[int],
    phi_d_index: Sequence[int],
    source: str,
) -> Path:
    """Write the downsampled npz layout (compressed, atomically), float16 values.

    Negative (missing) values become exactly -1; values above the float16 maximum (65504)
    would overflow and are rejected (the caller decides how to clamp). Angles are the lower
    edges of the indices, stored float32; ``scale`` is :data:`MERL_SCALE`. Materials are
    written in the order given (the shared files sort them by name).

    Args:
        path: destination ``.npz``; its folder must exist.
        brdf: (N, 3, Th, Td, Tp) tensor or array, scale applied.
        names: N unique material names.
        theta_h_index: the kept MERL bin indices (Th,), (Td,), (Tp,).
        theta_d_index: as ``theta_h_index``.
        phi_d_index: as ``theta_h_index``.
        source: ``"merl-binary"`` or ``"nbrdf"``.
    Returns:
        The path written (readable by :func:`load_merl_table`).
    """
    path = Path(path)
    if isinstance(brdf, torch.Tensor):
        brdf = brdf.detach().cpu().numpy()
    b = np.asarray(brdf, dtype=np.float64)
    idx = [np.asarray(i, dtype=np.int64) for i in (theta_h_index, theta_d_index, phi_d_index)]
    want = (len(names), 3, *(len(i) for i in idx))
    if b.shape != want:
        raise ShapeError(f"Expected brdf to have shape {want}; got {b.shape}")
    if not np.isfinite(b).all():
        raise ValueRangeError("brdf holds NaN/Inf values")
    f16_max = float(np.finfo(np.float16).max)
    if (b > f16_max).any():
        raise ValueRangeError(f"brdf has {int((b > f16_max).sum())} values above the float16 maximum {f16_max}")
    for k, i, res in zip(_INDEX_KEYS, idx, MERL_RES, strict=True):
        problem = _index_problem(k, i, res)
        if problem:
            raise ValueRangeError(problem)
    if source not in ("merl-binary", "nbrdf"):
        raise ValueRangeError(f"source must be 'merl-binary' or 'nbrdf'; got {source!r}")
    angles = merl_index_to_angles(*idx, at="lower")
    arrays = {
        "brdf": np.where(b < 0, -1.0, b).astype(np.float16),
        "names": np.array([str(n) for n in names]),
        **{k: i.astype(np.int16) for k, i in zip(_INDEX_KEYS, idx, strict=True)},
        **{k: a.numpy().astype(np.float32) for k, a in zip(_ANGLE_KEYS, angles, strict=True)},
        "scale": np.asarray(MERL_SCALE, dtype=np.float64),
        "source": np.array(source),
    }
    with replacing(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    return path


# -- NBRDF weights -----------------------------------------------------------------------------
_NBRDF_KEYS = ("W1", "b1", "W2", "b2", "W3", "b3")


@dataclass(frozen=True)
class NBRDFWeights:
    """Weights of a set of NBRDF networks (6-H-H-3 MLPs, Sztrajman et al. 2021): a neural
    *approximation* of MERL materials, not measurements.

    Attributes:
        names: N material names.
        W1, b1, W2, b2, W3, b3: (N, 6, H), (N, H), (N, H, H), (N, H), (N, H, 3), (N, 3)
            float32 arrays.
    """

    names: tuple[str, ...]
    W1: np.ndarray
    b1: np.ndarray
    W2: np.ndarray
    b2: np.ndarray
    W3: np.ndarray
    b3: np.ndarray

    def index(self, name: str) -> int:
        """Position of material ``name``; :class:`ValueRangeError` listing the names if absent."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueRangeError(f"unknown NBRDF material {name!r}; available: {list(self.names)}") from None


def load_nbrdf_weights(path: str | os.PathLike) -> NBRDFWeights:
    """Load and validate an NBRDF weights file (``nbrdf_merl100_weights.npz`` layout, no pickle).

    Args:
        path: the ``.npz`` with ``names`` (N,) str and ``W1, b1, W2, b2, W3, b3``.
    Returns:
        :class:`NBRDFWeights`.
    Raises:
        FileFormatError: missing/unreadable file, missing keys, inconsistent shapes.
    """
    path = Path(path)
    z = read_npz(path, "NBRDF weights file")  # bounded, pickle-free; FileFormatError names the file
    missing = [k for k in ("names", *_NBRDF_KEYS) if k not in z]
    if missing:
        raise FileFormatError(f"NBRDF weights file {path}: missing arrays {missing}")
    d = {k: z[k] for k in ("names", *_NBRDF_KEYS)}
    names = d.pop("names")
    n = names.shape[0] if names.ndim == 1 else -1
    if names.dtype.kind != "U" or n < 1:
        raise FileFormatError(f"NBRDF weights file {path}: names must be a (N,) str array; got {names.shape}")
    hidden = d["W1"].shape[-1] if d["W1"].ndim == 3 else -1
    want = {
        "W1": (n, 6, hidden), "b1": (n, hidden), "W2": (n, hidden, hidden),
        "b2": (n, hidden), "W3": (n, hidden, 3), "b3": (n, 3),
    }  # fmt: skip
    for k, shape in want.items():
        if d[k].shape != shape or not np.issubdtype(d[k].dtype, np.floating):
            raise FileFormatError(
                f"NBRDF weights file {path}: {k} must be float {shape}; got {d[k].shape} {d[k].dtype}"
            )
        if not np.isfinite(d[k]).all():
            raise FileFormatError(f"NBRDF weights file {path}: {k} holds NaN/Inf")
    return NBRDFWeights(names=tuple(str(s) for s in names), **{k: d[k].astype(np.float32) for k in _NBRDF_KEYS})
