r"""Transfer functions :math:`T_j(x)` of the SRBF distribution-based BRDF (Iwasaki et al., Eq. 6, 21).

Under a fixed view and distant environment lighting the outgoing radiance of a pixel is
linear in the SRBF coefficients :math:`c_j` of :math:`p(h)` and in the diffuse albedo
:math:`\rho_d` (Eq. 3, 5-7):

.. math:: B(x) = \rho_d E(x) + \sum_j c_j T_j(x), \qquad
          T_j(x) = \int_\Omega L(\omega_i)\,\tilde V(x, \omega_i)\,G_j(h)\,s(\omega_i, \omega_o(x))\,d\omega_i,

with :math:`\tilde V = V\,(\omega_i\cdot n)` the cosine-weighted visibility (embree),
:math:`G_j` the SRBFs on the local half vector (:class:`~torch_brdf.brdf.srbf.SRBFBasis`),
:math:`s = F(\omega_i\cdot h)/\big((\omega_i\cdot n)+(\omega_o\cdot n)-(\omega_i\cdot n)(\omega_o\cdot n)\big)`
the static factor of Eq. 11 (Schlick :math:`F` with RGB :math:`F_0`), and
:math:`E(x) = \int L\tilde V/\pi\,d\omega_i` the irradiance over :math:`\pi` (so that
:math:`\rho_d E` is the Lambertian radiance :math:`\rho_d/\pi\cdot\int L\tilde V`).

Integration: one set of S light directions :math:`\omega_s` drawn from the environment map
(:class:`LightSamples`, importance sampled, seeded) is shared by every pixel, so that
:math:`T_j(x) = \sum_s w_s L_s \tilde V(x, \omega_s) G_j(h_s) s(\omega_s, \omega_o)` with
:math:`w_s = 1/(S\,\mathrm{pdf}_s)` -- the paper's "large number of directions" summed
densely. Rendering the BRDF with the same samples gives the same numbers (the tests'
oracle).

Visibility cuts (Akerlund et al. 2007, Iwasaki Sec. 4.1, Eq. 20-21), :class:`CutOptions`: the
S directions are arranged once in a binary tree (median splits along the widest axis). Per
pixel, the cut is the set of top-most tree nodes on which :math:`\tilde V` is *coherent*
(max minus min at most ``tolerance``) and whose directions lie within ``max_angle_deg`` of
the node's representative direction (the sharp SRBF lobes, 7.5 degrees wide, need small
clusters; nodes where :math:`\tilde V \equiv 0` may be any size). Each cut node contributes
:math:`(\sum_{s\in C_k} w_sL_s)\,\langle v_k\rangle\,G_j(h_k)\,s(\omega_k, \omega_o)` with
:math:`\langle v_k\rangle` the luminance-weighted mean of :math:`\tilde V` (Eq. 20 when the
weights are equal) and :math:`\omega_k` the luminance-weighted mean direction; all-zero nodes
contribute nothing. With ``tolerance = 0`` and ``max_angle_deg = 0`` the cut is the leaves and
the result equals the dense sum. Unlike Akerlund et al. we compute the cut per pixel from the
per-pixel visibility (no per-vertex interpolation), so the saving is in the SRBF products,
not the ray casts.

Tiles: :func:`precompute_transfer` casts the visibility and sums the transfer functions of
an object's pixels in tiles of consecutive pixels, through the tile executor shared with the
other precomputations (:func:`~torch_brdf.parallel.tiles.run_tiles`: ``local`` or
``ray``); a tile is a pure function of (scene, pixels, samples, settings, tile index), so the
record is the same bit for bit whichever executor ran it.

Records: :func:`transfer_functions` returns the package's shared "pixels x basis x channels"
record, :class:`~torch_brdf.records.BasisImage`, with J + 1 basis functions: the J
transfer functions and, last, :math:`E(x)` for the diffuse albedo. Its ``image`` evaluates
Eq. 5/22 for ``torch.cat([c, rho_d[None]])`` (coefficients (J + 1, C)).
"""

from __future__ import annotations

import hashlib
import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
import torch
from tqdm.auto import tqdm

from .._checks import check_finite
from ..brdf.srbf import SRBFBasis
from ..data import progress_default
from ..errors import FileFormatError, ShapeError, ValueRangeError
from ..frame import Frame, half_terms
from ..parallel.tiles import TileWork, run_tiles
from ..records.basis_image import BasisImage
from ..records.cache import ArraySpec, CacheSchema, MetaSpec, TileCache, settings_key
from ..scene.camera import Camera
from ..scene.gbuffer import GBuffer, trace_gbuffer
from ..scene.lights import LightSamples, luminance
from ..scene.scene import Scene
from .energy import default_basis

__all__ = [
    "CutOptions",
    "LightSamples",
    "ObjectPixels",
    "cosine_visibility",
    "diffuse_index",
    "object_pixels",
    "precompute_transfer",
    "split_record",
    "transfer_functions",
]


#: the pixels of one object in one view: a :class:`~torch_brdf.scene.gbuffer.GBuffer` (former name).
ObjectPixels = GBuffer


def object_pixels(scene: Scene, obj: str | int, camera: Camera | None = None) -> GBuffer:
    """The G-buffer of the pixels whose closest primary hit is ``obj`` (:func:`trace_gbuffer`).

    Args:
        scene: the scene.
        obj: object name or id.
        camera: the view (default ``scene.camera``); e.g. ``scene.camera.with_size(160, 120)``
            for the downsampled solving frame.
    Raises:
        SceneError: unknown object, or the object covers no pixel of the view.
    """
    return trace_gbuffer(scene, camera, objects=obj)


def cosine_visibility(
    scene: Scene, px: GBuffer, samples: LightSamples, chunk_rays: int = 1 << 20, progress: bool | None = None
) -> torch.Tensor:
    r"""Cosine-weighted visibility :math:`\tilde V(x_p, \omega_s) = V\max(0, n_p\cdot\omega_s)`.

    Shadow rays leave each pixel's hit point towards every sample direction (embree, through
    :meth:`Scene.visible` with infinite distance); the cosine uses the shading normal.

    Returns:
        (P, S) float64.
    """
    P, S = px.count, samples.count
    dirs = samples.directions
    cos = (px.normal @ dirs.T).clamp_min(0)  # (P, S)
    out = torch.zeros(P, S, dtype=torch.float64)
    step = max(1, chunk_rays // S)
    for a in tqdm(range(0, P, step), desc="visibility", disable=not progress_default(progress)):
        b = min(P, a + step)
        need = cos[a:b] > 0
        ii, ss = torch.nonzero(need, as_tuple=True)
        if ii.numel() == 0:
            continue
        pos = px.position[a:b][ii].float()
        ng = px.geometric_normal[a:b][ii].float()
        d = dirs[ss].float()
        vis = scene.visible(pos, ng, d, math.inf)
        out[a + ii, ss] = torch.where(vis, cos[a:b][ii, ss], torch.zeros((), dtype=torch.float64))
    return out


@dataclass(frozen=True)
class CutOptions:
    """Visibility-cut clustering of the light directions (see the module docstring).

    Attributes:
        tolerance: largest max - min of :math:`\\tilde V` inside a cluster (0 = exact).
        max_angle_deg: largest angle between a cluster's directions and its representative.
    """

    tolerance: float = 0.1
    max_angle_deg: float = 4.0

    def __post_init__(self):
        if not (self.tolerance >= 0 and self.max_angle_deg >= 0):
            raise ValueRangeError(f"cut tolerance and max angle must be >= 0; got {self}")


class _LightTree:
    """Binary median-split tree over the S sample directions (S a power of two)."""

    def __init__(self, samples: LightSamples):
        S = samples.count
        if S & (S - 1):
            raise ValueRangeError(f"visibility cuts need a power-of-two number of light samples; got {S}")
        d = samples.directions.numpy()
        segs = [np.arange(S)]
        while len(segs[0]) > 1:
            nxt = []
            for seg in segs:
                pts = d[seg]
                ax = int(np.argmax(pts.max(0) - pts.min(0)))
                o = np.argsort(pts[:, ax], kind="stable")
                half = len(seg) // 2
                nxt += [seg[o[:half]], seg[o[half:]]]
            segs = nxt
        self.order = torch.from_numpy(np.concatenate(segs))
        self.levels = S.bit_length() - 1
        dirs = samples.directions[self.order]
        wL = samples.weight[self.order]
        lum = luminance(wL).clamp_min(0)
        lum = torch.where(lum.sum() > 0, lum, torch.ones_like(lum))
        self.lum = lum  # (S,) cluster-mean weights, tree order
        self.rep, self.wsum, self.radius = [], [], []
        for level in range(self.levels + 1):
            n = 1 << level
            dr = dirs.reshape(n, S // n, 3)
            lw = lum.reshape(n, S // n, 1)
            m = (dr * lw).sum(1)
            m = torch.where(m.norm(dim=-1, keepdim=True) > 1e-12, m, dr.mean(1))
            m = m / m.norm(dim=-1, keepdim=True).clamp_min(1e-300)
            cosang = (dr * m[:, None, :]).sum(-1).clamp(-1, 1)
            self.rep.append(m)
            self.wsum.append(wL.reshape(n, S // n, 3).sum(1))
            self.radius.append(torch.rad2deg(torch.acos(cosang.min(1).values)))


def _static_weighted(wi: torch.Tensor, wo: torch.Tensor, f0: torch.Tensor, weight: torch.Tensor):
    r"""Local half vectors (n, 3) and ``weight * F(wi.h) / den`` (n, 3) of Eq. 11's static factor
    :math:`s` for local unit pairs (n, 3) (0 where either direction is at or below the horizon)."""
    ht = half_terms(wi, wo)
    ci, co = wi[:, 2:3].clamp(0, 1), wo[:, 2:3].clamp(0, 1)
    den = (ci + co - ci * co).clamp_min(1e-300)
    s = (f0 + (1 - f0) * ht.one_minus_cos_d[:, None] ** 5) * (weight / den)
    return ht.h, torch.where(ht.up[:, None], s, torch.zeros((), dtype=s.dtype))


def _srbf(basis: SRBFBasis, h: torch.Tensor) -> torch.Tensor:
    """:math:`G_j(h)` (n, J) float64, fused in place (the bulk of the work: n x J exponentials)."""
    xi = basis.centers.to(torch.float64)
    lam = basis.bandwidth
    g = torch.addmm(torch.full((1, xi.shape[0]), -lam, dtype=torch.float64), h, xi.T * lam)
    return g.exp_()


def _accumulate(T, ii, wi, wo, weight, f0, basis, chunk: int = 1 << 14) -> None:
    r"""``T[ii] += s(wi, wo)^T G(h)`` over (pixel, direction) pairs sorted by pixel: T (p, 3, J),
    ii (n,) sorted pixel indices into T, wi, wo (n, 3) local unit directions, weight (n, 3) the
    light weight times :math:`\tilde V`.

    The sum over pairs is, per channel, a sparse (p x n) @ (n x J) product (CSR: row p holds the
    pairs of pixel p, contiguous because ``ii`` is sorted), which avoids materialising the
    (n, 3, J) products."""
    p = T.shape[0]
    for a in range(0, ii.numel(), chunk):
        b = min(ii.numel(), a + chunk)
        h, s = _static_weighted(wi[a:b], wo[a:b], f0, weight[a:b])
        G = _srbf(basis, h)  # (n, J)
        crow = torch.zeros(p + 1, dtype=torch.int64)
        crow[1:] = torch.bincount(ii[a:b], minlength=p).cumsum(0)
        cols = torch.arange(b - a)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
            for c in range(3):
                A = torch.sparse_csr_tensor(crow, cols, s[:, c].contiguous(), (p, b - a))
                T[:, c] += A @ G


def transfer_functions(
    px: GBuffer,
    samples: LightSamples,
    visibility: torch.Tensor,
    basis: SRBFBasis | None = None,
    f0=1.0,
    cuts: CutOptions | None = None,
    progress: bool | None = None,
    meta: dict | None = None,
) -> BasisImage:
    r"""Transfer functions :math:`T_j(x)` (Eq. 6; Eq. 21 with ``cuts``) and :math:`E(x)` for one object.

    Args:
        px: the object's pixels (:func:`object_pixels`, a G-buffer).
        samples: the light directions (:class:`LightSamples`).
        visibility: (P, S) :math:`\tilde V` from :func:`cosine_visibility`.
        basis: the SRBFs (default 147 hemicube lobes, :math:`\sigma = \pi/40`).
        f0: Schlick :math:`F_0`, scalar or RGB in [0, 1] (1: no Fresnel falloff).
        cuts: None for the dense sum over all S directions, or :class:`CutOptions`.
        progress: tqdm bar over pixel chunks.
        meta: extra provenance stored in the record.
    Returns:
        :class:`BasisImage` with values (3, J + 1, P) float64: basis j < J is :math:`T_j`, the
        last is :math:`E` (coefficient :math:`\rho_d`); ``basis = "srbf:J+diffuse"``;
        ``meta`` holds ``f0``, the sample count, the method and (cuts) the mean cut size.
    """
    basis = basis if basis is not None else default_basis()
    P, S = px.count, samples.count
    if visibility.shape != (P, S):
        raise ShapeError(f"Expected visibility of shape ({P}, {S}); got {tuple(visibility.shape)}")
    check_finite(visibility, "visibility")
    f0t = torch.as_tensor(f0, dtype=torch.float64).reshape(-1).expand(3).clone()
    if not bool(torch.isfinite(f0t).all()) or bool(((f0t < 0) | (f0t > 1)).any()):
        raise ValueRangeError(f"f0 must lie in [0, 1]; got {f0t.tolist()}")
    J = basis.K
    vis = visibility.double()
    frames = Frame.from_normal(px.normal).matrix()  # (P, 3, 3): local = frames @ world
    wo_l = (frames @ px.wo[:, :, None])[..., 0]  # (P, 3)
    T = torch.zeros(P, 3, J, dtype=torch.float64)
    t0 = time.perf_counter()
    info: dict = {}
    if cuts is None:
        step = max(1, (1 << 16) // S)
        for a in tqdm(range(0, P, step), desc="transfer (dense)", disable=not progress_default(progress)):
            b = min(P, a + step)
            ii, ss = torch.nonzero(vis[a:b] > 0, as_tuple=True)  # zero terms add nothing
            w = samples.weight[ss] * vis[a:b][ii, ss, None]
            wi_l = (frames[a:b] @ samples.directions.T).permute(0, 2, 1)[ii, ss]  # (n, 3) local
            _accumulate(T[a:b], ii, wi_l, wo_l[a + ii], w, f0t, basis)
    else:
        info = _cut_transfer(samples, vis, basis, f0t, frames, wo_l, cuts, T, progress)
    seconds = time.perf_counter() - t0
    # f = 0 unless wo is above the shading horizon too (silhouettes of smoothly shaded meshes)
    front = ((px.wo * px.normal).sum(-1) > 0).to(torch.float64)
    E = (vis @ samples.weight) * (front / math.pi)[:, None]  # (P, 3)
    values = torch.cat((T.permute(1, 2, 0), E.T[:, None, :]), 1).contiguous()  # (3, J + 1, P)
    m = {
        "f0": f0t.tolist(),
        "light_samples": S,
        "method": "dense" if cuts is None else "cuts",
        "seconds": seconds,
        **info,
        **(meta or {}),
    }
    return BasisImage(values, px.pixels.clone(), px.height, px.width, None, None, f"srbf:{J}+diffuse", m)


def _cut_transfer(samples, vis, basis, f0t, frames, wo_l, cuts, T, progress) -> dict:
    tree = _LightTree(samples)
    P, S = vis.shape
    v = vis[:, tree.order]
    lum = tree.lum
    total_nodes = 0
    step = max(1, (1 << 16) // S)
    for a in tqdm(range(0, P, step), desc="transfer (cuts)", disable=not progress_default(progress)):
        b = min(P, a + step)
        vb = v[a:b]
        p = b - a
        covered = torch.zeros(p, 1, dtype=torch.bool)
        pix, vals, dirs, wsum = [], [], [], []
        for level in range(tree.levels + 1):
            n = 1 << level
            vr = vb.reshape(p, n, S // n)
            vmax, vmin = vr.amax(-1), vr.amin(-1)
            lw = lum.reshape(n, S // n)
            mean = (vr * lw).sum(-1) / lw.sum(-1).clamp_min(1e-300)
            small = (tree.radius[level] <= cuts.max_angle_deg)[None, :] | (vmax <= 0)
            coherent = (vmax - vmin <= cuts.tolerance) & small
            if level == tree.levels:
                coherent = torch.ones_like(coherent)
            sel = coherent & ~covered & (vmax > 0)
            ii, kk = torch.nonzero(sel, as_tuple=True)
            pix.append(ii)
            vals.append(mean[ii, kk])
            dirs.append(tree.rep[level][kk])
            wsum.append(tree.wsum[level][kk])
            covered = (covered | coherent).repeat_interleave(2, dim=1)
        ii, vk, dk, wk = torch.cat(pix), torch.cat(vals), torch.cat(dirs), torch.cat(wsum)
        total_nodes += ii.numel()
        order = torch.argsort(ii)  # pairs grouped by pixel
        ii, vk, dk, wk = ii[order], vk[order], dk[order], wk[order]
        wi_l = (frames[a + ii] @ dk[:, :, None])[..., 0]
        _accumulate(T[a:b], ii, wi_l, wo_l[a + ii], wk * vk[:, None], f0t, basis)
    return {
        "mean_cut_size": total_nodes / max(P, 1),
        "cut_tolerance": cuts.tolerance,
        "cut_max_angle_deg": cuts.max_angle_deg,
    }


def _check_tile_pixels(arrays: dict, meta: dict, sizes: dict) -> None:
    """A transfer tile's metadata names the pixels its values hold."""
    if meta["pixels"] != sizes["p"]:
        raise FileFormatError(f"transfer tile says {meta['pixels']} pixels; this run's tile has {sizes['p']}")


def _transfer_tile(work: TileWork, k: int):
    """Tile ``k`` (pixels ``k * tile_pixels ...``): visibility and transfer functions, values
    (3, J + 1, p); ``work``: scene, px, samples, basis, f0, cuts, tile_pixels."""
    a = k * work.tile_pixels
    px = work.px.select(torch.arange(a, min(work.px.count, a + work.tile_pixels)))
    vis = cosine_visibility(work.scene, px, work.samples, progress=False)
    rec = transfer_functions(px, work.samples, vis, work.basis, work.f0, work.cuts, progress=False)
    return {"values": rec.values.numpy()}, {"pixels": px.count, **rec.meta}


def precompute_transfer(
    scene: Scene,
    px: GBuffer,
    samples: LightSamples,
    basis: SRBFBasis | None = None,
    f0=1.0,
    cuts: CutOptions | None = None,
    tile_pixels: int = 4096,
    checkpoint=None,
    progress: bool | None = None,
    meta: dict | None = None,
    executor: str = "local",
    address: str | None = None,
    max_retries: int = 3,
) -> BasisImage:
    r"""Visibility (:func:`cosine_visibility`) and transfer functions (:func:`transfer_functions`)
    of ``px`` in tiles of ``tile_pixels`` pixels, through the tile executor.

    Args:
        scene: as :func:`cosine_visibility` and :func:`transfer_functions`.
        px: as ``scene``.
        samples: as ``scene``.
        basis: as ``scene``.
        f0: as ``scene``.
        cuts: as ``scene``.
        meta: as ``scene``.
        tile_pixels: pixels per tile (the unit of work, of checkpointing and of a Ray task).
        checkpoint: folder for finished tiles (resumed from; removed on success), or None.
        progress: tqdm bar over finished tiles.
        executor: ``"local"`` or ``"ray"``, see
            :func:`~torch_brdf.parallel.tiles.run_tiles`; the record is the same bit for bit.
        address: as ``executor``.
        max_retries: as ``executor``.
    Returns:
        :class:`BasisImage` as :func:`transfer_functions` (values (3, J + 1, P)); ``meta["seconds"]``
        sums the tiles' transfer seconds, ``meta["executor"]`` names the executor.
    """
    basis = basis if basis is not None else default_basis()
    if int(tile_pixels) != tile_pixels or tile_pixels < 1:
        raise ValueRangeError(f"tile_pixels must be an integer >= 1; got {tile_pixels}")
    f0 = f0.tolist() if isinstance(f0, torch.Tensor) else f0
    num = -(-px.count // tile_pixels)
    work = TileWork(scene=scene, px=px, samples=samples, basis=basis, f0=f0, cuts=cuts, tile_pixels=int(tile_pixels))
    digest = hashlib.sha256()
    for t in (px.pixels, px.position, px.normal, px.wo, samples.directions, samples.weight, basis.centers):
        digest.update(t.detach().contiguous().numpy().tobytes())
    settings = {"inputs": digest.hexdigest(), "f0": f0, "bandwidth": basis.bandwidth, "tile_pixels": tile_pixels}
    settings["cuts"] = None if cuts is None else [cuts.tolerance, cuts.max_angle_deg]
    schema = CacheSchema(
        arrays={"values": ArraySpec("float64", (3, basis.K + 1, "p"))},
        meta={
            "pixels": MetaSpec(int, 0),
            "seconds": MetaSpec(float, 0.0, required=False),
            "mean_cut_size": MetaSpec(float, 0.0, required=cuts is not None),
            "light_samples": MetaSpec(int, 1, required=False),
            "f0": MetaSpec(list, required=False, items=(int, float)),
            "method": MetaSpec(str, required=False),
        },
        check=_check_tile_pixels,
    )
    tp = int(tile_pixels)
    key = settings_key(settings, scene)
    cache = TileCache(checkpoint, "transfer-tile", key, "tile", schema, lambda k: {"p": min(tp, px.count - k * tp)})
    show = progress_default(progress)
    tiles = run_tiles(_transfer_tile, work, num, cache, executor, address, max_retries, "transfer functions", show)
    values = torch.cat([torch.from_numpy(a["values"]) for a, _ in tiles], 2) if tiles else None
    if values is None:
        values = torch.zeros(3, basis.K + 1, 0, dtype=torch.float64)
    metas = [m for _, m in tiles]
    m = {k: v for k, v in (metas[0] if metas else {}).items() if k not in ("pixels", "cached", "seconds")}
    m["seconds"] = sum(float(x.get("seconds", 0.0)) for x in metas)
    if cuts is not None and metas:
        m["mean_cut_size"] = sum(x["mean_cut_size"] * x["pixels"] for x in metas) / max(px.count, 1)
    m |= {"executor": executor, "tile_pixels": int(tile_pixels), **(meta or {})}
    cache.remove()
    return BasisImage(
        values.contiguous(), px.pixels.clone(), px.height, px.width, None, None, f"srbf:{basis.K}+diffuse", m
    )


def diffuse_index(record: BasisImage) -> int:
    """Index of the diffuse basis function (:math:`E`) in a transfer record: J."""
    if not record.basis.endswith("+diffuse"):
        raise ShapeError(f"expected a transfer record (basis 'srbf:J+diffuse'); got basis {record.basis!r}")
    return record.num_basis - 1


def split_record(record: BasisImage) -> tuple[torch.Tensor, torch.Tensor]:
    """The SRBF transfer functions (C, J, P) and the diffuse :math:`E` (C, P) of a transfer record."""
    j = diffuse_index(record)
    return record.values[:, :j], record.values[:, j]
