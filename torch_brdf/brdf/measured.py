r"""Measured (tabulated) BRDFs: MERL tables and the NBRDF neural approximation of them.

* :class:`MERLTabulated` (registry name ``"merl"``) looks a MERL table up: a full
  ``(3, 90, 90, 180)`` table from :func:`torch_brdf.io.merl.read_merl_binary`, or one
  material of the downsampled npz layout (:func:`torch_brdf.io.merl.load_merl_table`)
  with its kept index lists.
* :class:`NBRDF` (registry name ``"nbrdf"``) evaluates the small networks of Sztrajman,
  Rainer, Ritschel and Weyrich, "Neural BRDF Representation and Importance Sampling",
  CGF 40(6), 2021, fitted to the MERL materials. They are an **approximation** of MERL,
  loose near grazing angles — never measured ground truth.
* :func:`tabulate_nbrdf` evaluates an NBRDF on the MERL grid (what
  ``datasets/nbrdf_to_merl.py`` writes, and how ``merl_nbrdf_sample_f16.npz`` was made).

Both models are isotropic and written in Rusinkiewicz half/difference angles
(:func:`torch_brdf.frame.half_diff_angles`). Reciprocity holds by construction: swapping
``wi`` and ``wo`` keeps :math:`\theta_h, \theta_d` and maps :math:`\phi_d \to \phi_d \pm \pi`,
which the MERL fold (add :math:`\pi` where :math:`\phi_d < 0`) undoes.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from ..data import data_path
from ..errors import ShapeError, ValueRangeError
from ..frame import half_diff_angles, half_diff_to_directions
from ..io.merl import (
    MERL_RES,
    MERLTableData,
    NBRDFWeights,
    load_merl_table,
    load_nbrdf_weights,
    merl_coordinates,
    merl_fold_phi_d,
    merl_index_to_angles,
    merl_indices,
    read_merl_binary,
)
from .base import BRDF, register

_INTERPOLATIONS = ("nearest", "trilinear")


# -- lookup helpers -----------------------------------------------------------------------------
def _floor_position(idx: torch.Tensor, kept: torch.Tensor, periodic: bool) -> torch.Tensor:
    """Position in ``kept`` of the last kept index <= ``idx`` (the coarse bin holding a full
    MERL bin). Below ``kept[0]``: the last position if periodic, else 0."""
    k = torch.searchsorted(kept, idx.contiguous(), right=True) - 1
    return torch.where(k < 0, kept.numel() - 1, k) if periodic else k.clamp_min(0)


def _linear_positions(
    u: torch.Tensor, kept: torch.Tensor, period: int | None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Neighbouring kept positions (k0, k1) and the weight w1 of k1 for continuous index
    coordinates ``u`` (samples sit at the kept indices). Clamped (constant) outside
    ``[kept[0], kept[-1]]`` unless ``period`` is given, then wrapped."""
    kf = kept.to(u.dtype)
    n = kf.numel()
    if period is None:
        u = u.clamp(kf[0], kf[-1]).contiguous()
        k0 = (torch.searchsorted(kf, u, right=True) - 1).clamp(0, n - 1)
        k1 = (k0 + 1).clamp_max(n - 1)
        span = kf[k1] - kf[k0]
        w1 = torch.where(span > 0, (u - kf[k0]) / span.clamp_min(1), torch.zeros_like(u))
        return k0, k1, w1
    ext = torch.cat((kf[-1:] - period, kf, kf[:1] + period))
    ext_k = torch.cat((kept.new_tensor([n - 1]), torch.arange(n, device=kept.device), kept.new_tensor([0])))
    u = torch.remainder(u, period).contiguous()
    j = (torch.searchsorted(ext, u, right=True) - 1).clamp(0, n)
    w1 = (u - ext[j]) / (ext[j + 1] - ext[j])
    return ext_k[j], ext_k[j + 1], w1


def _as_index(x, name: str, res: int) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(x)).long().reshape(-1)
    if t.numel() == 0 or bool((t < 0).any()) or bool((t >= res).any()) or bool((t.diff() <= 0).any()):
        raise ValueRangeError(f"{name} must be strictly increasing MERL indices within 0..{res - 1}; got {t.tolist()}")
    return t


class _IsotropicMeasured(BRDF):
    """Shared evaluation of isotropic measured BRDFs given on Rusinkiewicz angles: the
    angles are computed in float64 and passed to :meth:`eval_angles`."""

    def eval_angles(self, theta_h: torch.Tensor, theta_d: torch.Tensor, phi_d: torch.Tensor) -> torch.Tensor:
        """f_r (*B, 3) float64 at half/difference angles (*B,) each."""
        raise NotImplementedError

    def eval_local(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """f_r (*B, 3) for local unit directions wi, wo (*B, 3); 0 at/below the horizon."""
        wi, wo = torch.broadcast_tensors(wi, wo)
        theta_h, _, theta_d, phi_d = half_diff_angles(wi.to(torch.float64), wo.to(torch.float64))
        f = self.eval_angles(theta_h, theta_d, phi_d).to(wi.dtype)
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        return torch.where(up.unsqueeze(-1), f, torch.zeros((), dtype=wi.dtype))


@register("merl")
class MERLTabulated(_IsotropicMeasured):
    r"""A tabulated MERL BRDF (RGB, 1/sr), looked up in half/difference angles.

    Lookup (``interpolation``):

    * ``"nearest"`` (default): MERL's own lookup (``BRDFRead.cpp``): the bin indices of
      :func:`torch_brdf.io.merl.merl_indices` (floor, :math:`\phi_d` folded). On a
      downsampled grid a full-resolution bin maps to the last kept index at or below it
      (the coarse bin ``[kept[k], kept[k+1])``). Exact at bin centres; piecewise constant.
    * ``"trilinear"``: linear in the continuous index coordinates
      :func:`torch_brdf.io.merl.merl_coordinates` (square-root-mapped :math:`\theta_h`,
      linear :math:`\theta_d`, :math:`\phi_d`), with each value placed at its bin's
      **lower edge** — the angle a table made by :func:`tabulate_nbrdf` was evaluated at,
      and the index -> angle map of :func:`~torch_brdf.io.merl.merl_index_to_angles` — so the
      two lookups agree on the lower edges. :math:`\phi_d` wraps with period :math:`\pi` (bin 179, or the last kept
      index, blends into bin 0); :math:`\theta_h, \theta_d` are held constant beyond the
      last kept index.

    Missing bins (negative values, -1 in the npz layout) count as 0 for ``"nearest"``;
    ``"trilinear"`` leaves them out and renormalises the weights of the valid corners
    (0 only if all eight corners are missing). This is per channel.

    Bin selection is done in float64 whatever the input dtype, so float32 and float64
    directions pick the same bins (up to the rounding of the directions themselves); the
    result has the dtype of ``wi``. ``f = 0`` when either direction is at or below the
    horizon. Sampling is the base class's cosine-weighted hemisphere.

    Args:
        table: (3, Th, Td, Tp) tensor/array (scale applied, RGB), or a path: a ``.binary``
            file (full table) or an ``.npz`` in the downsampled layout (with ``material``).
        material: material name (or position) in an ``.npz``; optional if it holds one.
        theta_h_index: the MERL bin indices the table axes
            keep (strictly increasing); default all bins when the table is (90, 90, 180).
        theta_d_index: as ``theta_h_index``.
        phi_d_index: as ``theta_h_index``.
        interpolation: ``"nearest"`` or ``"trilinear"``.
        name: label for ``repr`` (default: file stem or material name).
        source: where the values come from, e.g. ``"merl-binary"`` or ``"nbrdf"``; an
            ``"nbrdf"`` table is labelled an approximation of MERL.
    """

    def __init__(
        self,
        table,
        material: str | int | None = None,
        *,
        theta_h_index=None,
        theta_d_index=None,
        phi_d_index=None,
        interpolation: Literal["nearest", "trilinear"] = "nearest",
        name: str | None = None,
        source: str | None = None,
    ):
        super().__init__()
        if interpolation not in _INTERPOLATIONS:
            raise ValueRangeError(f"interpolation must be one of {_INTERPOLATIONS}; got {interpolation!r}")
        if isinstance(table, str | os.PathLike):
            path = Path(table)
            if path.suffix == ".npz":
                data = load_merl_table(path)
                if material is None and len(data) != 1:
                    raise ValueRangeError(f"{path} holds {len(data)} materials; pass material= one of {data.names}")
                k = 0 if material is None else material if isinstance(material, int) else data.index(material)
                table = data.table(k)
                theta_h_index, theta_d_index, phi_d_index = data.theta_h_index, data.theta_d_index, data.phi_d_index
                name = name or data.names[k]
                source = source or data.source
            else:
                table = read_merl_binary(path)
                name = name or path.stem
                source = source or "binary file"
        t = torch.as_tensor(np.asarray(table) if not isinstance(table, torch.Tensor) else table).detach()
        if t.ndim != 4 or t.shape[0] != 3 or not t.is_floating_point():
            raise ShapeError(
                f"Expected table to be a floating (3, Th, Td, Tp) RGB table; got {tuple(t.shape)} {t.dtype}"
            )
        if t.dtype not in (torch.float32, torch.float64):
            t = t.float()  # float16 files: look up in float32 (exact), not in slow half math
        if not bool(torch.isfinite(t).all()):
            raise ValueRangeError("table holds NaN/Inf values")
        idx = []
        for nm, given, res, size in zip(
            ("theta_h_index", "theta_d_index", "phi_d_index"),
            (theta_h_index, theta_d_index, phi_d_index),
            MERL_RES,
            t.shape[1:],
            strict=True,
        ):
            i = torch.arange(res) if given is None else _as_index(given, nm, res)
            if i.numel() != size:
                raise ShapeError(f"table axis of size {size} needs {nm} of that length; got {i.numel()} indices")
            idx.append(i)
        self.register_buffer("table", t.contiguous())
        self.register_buffer("theta_h_index", idx[0])
        self.register_buffer("theta_d_index", idx[1])
        self.register_buffer("phi_d_index", idx[2])
        self.interpolation = interpolation
        self.name = name or "table"
        self.source = source or "tensor"

    @classmethod
    def from_binary(cls, path: str | os.PathLike, **kwargs) -> MERLTabulated:
        """From a MERL ``.binary`` file (full 90 x 90 x 180 grid)."""
        return cls(Path(path), **kwargs)

    @classmethod
    def from_table(cls, data: MERLTableData, material: str | int, **kwargs) -> MERLTabulated:
        """From one material of a loaded downsampled table (:class:`MERLTableData`)."""
        k = material if isinstance(material, int) else data.index(material)
        kwargs.setdefault("name", data.names[k])
        kwargs.setdefault("source", data.source)
        return cls(
            data.table(k),
            theta_h_index=data.theta_h_index,
            theta_d_index=data.theta_d_index,
            phi_d_index=data.phi_d_index,
            **kwargs,
        )

    @property
    def is_approximation(self) -> bool:
        """True when the table came from the NBRDF networks (not measured)."""
        return self.source == "nbrdf"

    # -- lookup -------------------------------------------------------------------------------
    def eval_angles(self, theta_h: torch.Tensor, theta_d: torch.Tensor, phi_d: torch.Tensor) -> torch.Tensor:
        """The table value (see :meth:`lookup`)."""
        return self.lookup(theta_h, theta_d, phi_d)

    def lookup(self, theta_h: torch.Tensor, theta_d: torch.Tensor, phi_d: torch.Tensor) -> torch.Tensor:
        r"""Table value at half/difference angles (no horizon test).

        Args:
            theta_h: (*B,) radians (:math:`\phi_d \in (-\pi, \pi]`, folded here).
            theta_d: as ``theta_h``.
            phi_d: as ``theta_h``.
        Returns:
            (*B, 3) in the dtype of ``theta_h``; missing bins handled as in the class docstring.
        """
        shape, dtype = theta_h.shape, theta_h.dtype
        th, td, pd = (a.to(torch.float64).reshape(-1) for a in torch.broadcast_tensors(theta_h, theta_d, phi_d))
        _, n_d, n_p = self.table.shape[1:]
        flat_table = self.table.reshape(3, -1)
        if self.interpolation == "nearest":
            i_h, i_d, i_p = merl_indices(th, td, pd)
            k_h = _floor_position(i_h, self.theta_h_index, periodic=False)
            k_d = _floor_position(i_d, self.theta_d_index, periodic=False)
            k_p = _floor_position(i_p, self.phi_d_index, periodic=True)
            v = flat_table[:, (k_h * n_d + k_d) * n_p + k_p].clamp_min(0)
            return v.t().to(dtype).reshape(*shape, 3)
        u_h, u_d, u_p = merl_coordinates(th, td, pd)
        k_h0, k_h1, w_h = _linear_positions(u_h, self.theta_h_index, None)
        k_d0, k_d1, w_d = _linear_positions(u_d, self.theta_d_index, None)
        k_p0, k_p1, w_p = _linear_positions(u_p, self.phi_d_index, MERL_RES[2])
        # the 8 corners at once: (2, 1, 1, n) x (1, 2, 1, n) x (1, 1, 2, n) -> (2, 2, 2, n)
        k_h, k_d, k_p = torch.stack((k_h0, k_h1)), torch.stack((k_d0, k_d1)), torch.stack((k_p0, k_p1))
        flat = (k_h[:, None, None] * n_d + k_d[None, :, None]) * n_p + k_p[None, None, :]
        w = torch.stack((1 - w_h, w_h))[:, None, None] * torch.stack((1 - w_d, w_d))[None, :, None]
        w = w * torch.stack((1 - w_p, w_p))[None, None, :]
        v = flat_table[:, flat.reshape(-1)].to(torch.float64).reshape(3, 8, -1)
        w = w.reshape(1, 8, -1) * (v >= 0)  # missing corners get weight 0 ...
        den = w.sum(1)
        num = (w * v.clamp_min(0)).sum(1)  # ... and the rest is renormalised
        out = torch.where(den > 0, num / den.clamp_min(torch.finfo(torch.float64).tiny), torch.zeros_like(num))
        return out.t().to(dtype).reshape(*shape, 3)

    def extra_repr(self) -> str:
        s = (
            f"name={self.name!r}, grid={tuple(self.table.shape[1:])}, interpolation={self.interpolation!r}, "
            f"source={self.source!r}"
        )
        return s + (", APPROXIMATION of MERL (NBRDF), not measured" if self.is_approximation else "")


# -- NBRDF ----------------------------------------------------------------------------------------
def nbrdf_input(theta_h: torch.Tensor, theta_d: torch.Tensor, phi_d: torch.Tensor) -> torch.Tensor:
    r"""The NBRDF network input :math:`x = (h_x, h_y, h_z, d_x, d_y, d_z)`, with the half
    vector at :math:`\phi_h = 0`, :math:`h = (\sin\theta_h, 0, \cos\theta_h)`, and the
    difference vector :math:`d = (\sin\theta_d\cos\phi_d, \sin\theta_d\sin\phi_d, \cos\theta_d)`.

    Args:
        theta_h: (*B,) radians (broadcastable with the others).
        theta_d: (*B,) radians.
        phi_d: (*B,) radians.
    Returns:
        (*B, 6) in the input dtype.
    """
    # sin/cos on the un-broadcast inputs (a grid's axes), then broadcast: same values, less work
    sh, ch = torch.sin(theta_h), torch.cos(theta_h)
    st, ct = torch.sin(theta_d), torch.cos(theta_d)
    parts = (sh, torch.zeros_like(sh), ch, st * torch.cos(phi_d), st * torch.sin(phi_d), ct)
    return torch.stack(torch.broadcast_tensors(*parts), -1)


def nbrdf_mlp(
    x: torch.Tensor,
    W1: torch.Tensor,
    b1: torch.Tensor,
    W2: torch.Tensor,
    b2: torch.Tensor,
    W3: torch.Tensor,
    b3: torch.Tensor,
) -> torch.Tensor:
    r"""The NBRDF network: ``exp(relu(relu(x W1 + b1) W2 + b2) W3 + b3) - 1`` (not clamped).

    Args:
        x: (*B, 6) inputs (:func:`nbrdf_input`).
        W1: (6, H) in the dtype of x.
        b1: (H,).
        W2: (H, H).
        b2: (H,).
        W3: (H, 3).
        b3: (3,).
    Returns:
        (*B, 3) RGB BRDF values (1/sr, MERL scale included); may be slightly negative.
    """
    h = torch.relu(x @ W1 + b1)
    h = torch.relu(h @ W2 + b2)
    return torch.exp(h @ W3 + b3) - 1  # exp - 1 as trained (not expm1): same rounding as the reference


_WEIGHT_KEYS = ("W1", "b1", "W2", "b2", "W3", "b3")


def _default_weights() -> Path:
    return data_path("merl", "nbrdf_merl100_weights.npz")


@register("nbrdf")
class NBRDF(_IsotropicMeasured):
    r"""A neural BRDF (NBRDF, Sztrajman et al. 2021): an **approximation** of one MERL
    material by a 6-21-21-3 MLP, not measured data.

    .. math::
        f = \max(0, \exp(\mathrm{relu}(\mathrm{relu}(x W_1 + b_1) W_2 + b_2) W_3 + b_3) - 1)

    with :math:`x` from :func:`nbrdf_input` at the half/difference angles of
    :math:`(\omega_i, \omega_o)`; RGB in 1/sr with MERL's scale factors included;
    ``f = 0`` when either direction is at or below the horizon.

    :math:`\phi_d` is folded like MERL's lookup (add :math:`\pi` where negative) before
    it enters the network (``fold_phi_d=True``, the default). The networks were trained on
    :math:`\phi_d \in [0, 2\pi)` but are not exactly symmetric under
    :math:`\phi_d \to \phi_d + \pi` (about +-15 % for blue-acrylic even at
    :math:`\theta_h = 0`), so without the fold they are not reciprocal; with it reciprocity
    holds by construction, values match :func:`tabulate_nbrdf` tables, and :math:`f` jumps
    where :math:`\phi_d` crosses 0 / :math:`\pi` (as MERL's own table does).
    ``fold_phi_d=False`` evaluates the raw network (the original Mitsuba plugin).

    :meth:`eval` computes in float64 and rounds the result to the dtype of the directions
    (gradients flow through): the last layer is :math:`\exp(y) - 1` with :math:`y \approx 0`
    for dark values, where float32 cancellation leaves an absolute error of about
    :math:`10^{-7}` that depends on the summation order — so batch == loop, reciprocity and
    float32 == float64 would hold only to about 1e-4 relative. :func:`tabulate_nbrdf` keeps
    the float32 network of the reference tabulation.

    Args:
        material: material name in the weights file (see :meth:`names`).
        weights: path of an NBRDF weights ``.npz`` (``nbrdf_merl100_weights.npz`` layout)
            or loaded :class:`~torch_brdf.io.merl.NBRDFWeights`; default the shared
            ``merl/nbrdf_merl100_weights.npz`` (:class:`DataNotFoundError` if absent).
        fold_phi_d: fold :math:`\phi_d` into :math:`[0, \pi]` (see above).
    Raises:
        ValueRangeError: unknown material (the message lists the available names).
    """

    def __init__(
        self, material: str, weights: str | os.PathLike | NBRDFWeights | None = None, *, fold_phi_d: bool = True
    ):
        super().__init__()
        w = weights if isinstance(weights, NBRDFWeights) else load_nbrdf_weights(weights or _default_weights())
        k = w.index(material)
        for key in _WEIGHT_KEYS:
            self.register_buffer(key, torch.from_numpy(np.array(getattr(w, key)[k], dtype=np.float32)))
        self.material = material
        self.fold_phi_d = bool(fold_phi_d)

    @classmethod
    def names(cls, weights: str | os.PathLike | NBRDFWeights | None = None) -> list[str]:
        """Material names available in a weights file (default: the shared one)."""
        w = weights if isinstance(weights, NBRDFWeights) else load_nbrdf_weights(weights or _default_weights())
        return list(w.names)

    def eval_angles(self, theta_h: torch.Tensor, theta_d: torch.Tensor, phi_d: torch.Tensor) -> torch.Tensor:
        r"""The network at half/difference angles, clamped to >= 0 (no horizon test).

        Args:
            theta_h: (*B,) radians; :math:`\phi_d` is folded if ``fold_phi_d``.
            theta_d: as ``theta_h``.
            phi_d: as ``theta_h``.
        Returns:
            (*B, 3) in the dtype of the angles.
        """
        if self.fold_phi_d:
            phi_d = merl_fold_phi_d(phi_d)
        x = nbrdf_input(theta_h, theta_d, phi_d)
        return nbrdf_mlp(x, *(getattr(self, k).to(x.dtype) for k in _WEIGHT_KEYS)).clamp_min(0)

    def extra_repr(self) -> str:
        return f"material={self.material!r}, fold_phi_d={self.fold_phi_d}, APPROXIMATION of MERL (NBRDF), not measured"


@functools.lru_cache(maxsize=4)
def _below_horizon(theta_h_index: tuple[int, ...], theta_d_index: tuple[int, ...], phi_d_index: tuple[int, ...]):
    """(Th, Td, Tp) bool: bins whose wi or wo (phi_h = 0, lower-edge angles) has z <= 0.
    The same for every material, so cached (the script tabulates 100 on one grid)."""
    th, td, pd = merl_index_to_angles(theta_h_index, theta_d_index, phi_d_index, at="lower", dtype=torch.float64)
    TH, TD, PD = torch.meshgrid(th, td, pd, indexing="ij")
    wi, wo = half_diff_to_directions(TH, torch.zeros_like(TH), TD, PD)
    return (wi[..., 2] <= 0) | (wo[..., 2] <= 0)


def tabulate_nbrdf(
    model: NBRDF,
    theta_h_index=None,
    theta_d_index=None,
    phi_d_index=None,
    *,
    mask_horizon: bool = True,
    chunk: int = 1 << 19,
) -> torch.Tensor:
    r"""Evaluate an NBRDF on the MERL grid: an **approximation** of the MERL table.

    Matches ``shared/tools/make_merl_npz.py`` (and so ``merl_nbrdf_sample_f16.npz``): the
    network is evaluated at the **lower-edge** angles of each bin
    (:func:`~torch_brdf.io.merl.merl_index_to_angles`), inputs computed in float64 and
    rounded to float32, the network run in float32, clamped to >= 0; with
    ``mask_horizon`` the bins whose incoming or outgoing direction (for
    :math:`\phi_h = 0`) is at or below the horizon (``z <= 0``) are set to -1, the
    missing-bin marker (a geometric mask, not MERL's own missing-data pattern).

    Args:
        model: the :class:`NBRDF` (its ``fold_phi_d`` is irrelevant: the grid has
            :math:`\phi_d \in [0, \pi)`).
        theta_h_index: MERL bin indices to evaluate
            (default all: 90, 90, 180).
        theta_d_index: as ``theta_h_index``.
        phi_d_index: as ``theta_h_index``.
        mask_horizon: set below-horizon bins to -1.
        chunk: about this many bins per network call (memory only).
    Returns:
        (3, Th, Td, Tp) float64, RGB 1/sr.
    """
    idx = [
        torch.arange(res) if i is None else _as_index(i, nm, res)
        for i, nm, res in zip(
            (theta_h_index, theta_d_index, phi_d_index), ("theta_h_index", "theta_d_index", "phi_d_index"), MERL_RES,
            strict=True,
        )
    ]  # fmt: skip
    th, td, pd = merl_index_to_angles(*idx, at="lower", dtype=torch.float64)
    weights = [getattr(model, k).to(torch.float32) for k in _WEIGHT_KEYS]
    out = torch.empty(th.numel(), td.numel(), pd.numel(), 3, dtype=torch.float64)
    rows = max(1, chunk // (td.numel() * pd.numel()))
    with torch.no_grad():
        for s in range(0, th.numel(), rows):
            x = nbrdf_input(th[s : s + rows, None, None], td[:, None], pd).to(torch.float32)
            out[s : s + rows] = nbrdf_mlp(x, *weights).clamp_min(0)
    if mask_horizon:
        out[_below_horizon(*(tuple(i.tolist()) for i in idx))] = -1.0
    return out.permute(3, 0, 1, 2).contiguous()
