r"""Exploring the latent space: 2-D slices with variance, best paths, and the seed's limitation made visible.

Seed (Soler et al. 2017) Sec. 3.2 and 4: the user picks points in 2-D slices of the latent
space shown with the predictive variance; paths between two materials minimise a combination
of length and uncertainty, found by Dijkstra on a coarse latent grid.

Edge cost (our choice; the seed only says "a combination of the length of the path and the
maximum variance along that path"): for neighbouring grid nodes ``u, v``,
:math:`c(u, v) = \lVert u - v\rVert\,(1 + w \max(\sigma^2(u), \sigma^2(v)))`, so a path's cost is
its length weighted by the variance it crosses (``w = 0``: the straight shortest path on the
grid). Neighbours: all :math:`3^Q - 1` offsets.

Limitation (seed Sec. 5): interpolants are linear in the data but need not be non-negative
nor energy conserving. :func:`interpolant_diagnostics` reports the fraction of negative BRDF
values and the maximum directional albedo of interpolants; directional albedo is linear in
the BRDF, so it is blended from per-material albedos (:func:`directional_albedo`) exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from ..errors import ValueRangeError
from ..io.merl import merl_index_to_angles
from .data import MERLGrid, to_table
from .gplvm import GPLVM

#: default grid nodes per latent axis for best paths, by latent dimension
DEFAULT_PATH_RESOLUTION = {1: 256, 2: 48, 3: 16, 4: 9, 5: 7}


def latent_bounds(latents: torch.Tensor, pad: float = 0.15) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounding box of the training latents (N, Q), padded by ``pad`` of its extent per axis."""
    lo, hi = latents.min(0).values, latents.max(0).values
    ext = (hi - lo).clamp_min(1e-6)
    return lo - pad * ext, hi + pad * ext


@dataclass(frozen=True)
class LatentSlice:
    """A 2-D slice of the latent space.

    Attributes:
        points: (H, W, Q) latent points (rows vary ``dims[1]``, columns ``dims[0]``).
        variance: (H, W) predictive variance there (seed Eq. 2).
        dims: the two latent axes spanned. center: (Q,) the fixed coordinates of the other axes.
        extent: (x_min, x_max, y_min, y_max) for plotting (matplotlib ``imshow(..., origin="lower")``).
    """

    points: torch.Tensor
    variance: torch.Tensor
    dims: tuple[int, int]
    center: torch.Tensor
    extent: tuple[float, float, float, float]


def latent_slice(
    model: GPLVM, dims: tuple[int, int] = (0, 1), center=None, resolution: int = 64, bounds=None
) -> LatentSlice:
    """Variance map over a 2-D slice through ``center`` (default: the mean latent).

    Args:
        model: fitted :class:`GPLVM`. dims: two distinct latent axes. center: (Q,) or None.
        resolution: pixels per side. bounds: (lo (Q,), hi (Q,)) or None (:func:`latent_bounds`).
    """
    q = model.q
    if len(dims) != 2 or dims[0] == dims[1] or not all(0 <= k < q for k in dims):
        raise ValueRangeError(f"dims must be two distinct axes in 0..{q - 1}; got {dims}")
    if resolution < 2:
        raise ValueRangeError(f"resolution must be >= 2; got {resolution}")
    lo, hi = latent_bounds(model.latents) if bounds is None else (torch.as_tensor(b).double() for b in bounds)
    c = model.latents.mean(0) if center is None else torch.as_tensor(center, dtype=torch.float64)
    u = torch.linspace(float(lo[dims[0]]), float(hi[dims[0]]), resolution, dtype=torch.float64)
    v = torch.linspace(float(lo[dims[1]]), float(hi[dims[1]]), resolution, dtype=torch.float64)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    pts = c.expand(resolution, resolution, q).clone()
    pts[..., dims[0]] = uu
    pts[..., dims[1]] = vv
    var = model.variance(pts.reshape(-1, q)).reshape(resolution, resolution)
    extent = (float(u[0]), float(u[-1]), float(v[0]), float(v[-1]))
    return LatentSlice(pts, var, (int(dims[0]), int(dims[1])), c, extent)


@dataclass(frozen=True)
class LatentPath:
    """A best path between two latent points.

    Attributes:
        waypoints: (K, Q) latents: the exact start, the grid nodes of the Dijkstra path (the
            start's and end's nearest nodes included), the exact end.
        weights: (K, N) blending weights b of each waypoint (z = weights @ Z).
        variance: (K,) predictive variance at the waypoints.
        length: Euclidean latent length. max_variance: largest waypoint variance.
        cost: the Dijkstra cost of the grid part. variance_weight: ``w`` of the edge cost.
    """

    waypoints: torch.Tensor
    weights: torch.Tensor
    variance: torch.Tensor
    length: float
    max_variance: float
    cost: float
    variance_weight: float


def _as_point(model: GPLVM, p) -> torch.Tensor:
    if isinstance(p, int):
        if not 0 <= p < model.latents.shape[0]:
            raise ValueRangeError(f"material index {p} outside 0..{model.latents.shape[0] - 1}")
        return model.latents[p]
    if isinstance(p, str):
        names = model.fit.names
        if p not in names:
            raise ValueRangeError(f"unknown material {p!r}; the fit has {list(names)}")
        return model.latents[names.index(p)]
    return model._queries(p)[0][0]


def best_path(
    model: GPLVM, start, end, variance_weight: float = 10.0, resolution: int | None = None, bounds=None
) -> LatentPath:
    """Dijkstra (``scipy.sparse.csgraph``) on a coarse latent grid between two materials or points.

    Args:
        model: fitted :class:`GPLVM`. start, end: material index, material name or (Q,) latent.
        variance_weight: ``w`` >= 0 in the edge cost (module docstring).
        resolution: grid nodes per axis (default :data:`DEFAULT_PATH_RESOLUTION` by Q).
        bounds: (lo, hi) of the grid (default :func:`latent_bounds`, widened to hold both endpoints).
    Returns:
        :class:`LatentPath` (blending weights of every waypoint included).
    """
    if not (math.isfinite(variance_weight) and variance_weight >= 0):
        raise ValueRangeError(f"variance_weight must be finite and >= 0; got {variance_weight}")
    q = model.q
    res = resolution or DEFAULT_PATH_RESOLUTION.get(q, 5)
    if res < 2 or res**q > 2_000_000:
        raise ValueRangeError(f"path grid resolution {res}^{q} is out of range (2 .. 2e6 nodes)")
    a, b = _as_point(model, start), _as_point(model, end)
    lo, hi = latent_bounds(model.latents) if bounds is None else (torch.as_tensor(x).double() for x in bounds)
    lo, hi = torch.minimum(lo, torch.minimum(a, b)), torch.maximum(hi, torch.maximum(a, b))
    axes = [torch.linspace(float(lo[k]), float(hi[k]), res, dtype=torch.float64) for k in range(q)]
    nodes = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, q)
    var = model.variance(nodes).numpy()
    idx = np.arange(res**q).reshape((res,) * q)
    rows, cols, costs = [], [], []
    step = ((hi - lo) / (res - 1)).numpy()
    for off in np.ndindex(*(3,) * q):
        o = np.asarray(off) - 1
        if not o.any():
            continue
        src = idx[tuple(slice(max(0, -k), res - max(0, k)) for k in o)].ravel()
        dst = idx[tuple(slice(max(0, k), res - max(0, -k)) for k in o)].ravel()
        length = float(np.linalg.norm(o * step))
        rows.append(src)
        cols.append(dst)
        costs.append(length * (1 + variance_weight * np.maximum(var[src], var[dst])))
    graph = csr_matrix((np.concatenate(costs), (np.concatenate(rows), np.concatenate(cols))), shape=(res**q,) * 2)
    s_node = int(torch.cdist(a[None], nodes).argmin())
    e_node = int(torch.cdist(b[None], nodes).argmin())
    dist, pred = dijkstra(graph, indices=s_node, return_predecessors=True)
    chain = [e_node]
    while chain[-1] != s_node:
        chain.append(int(pred[chain[-1]]))
    chain.reverse()
    pts = [a, *[nodes[k] for k in chain], b]
    way = torch.stack(pts)
    variance = model.variance(way)
    return LatentPath(
        waypoints=way,
        weights=model.weights(way),
        variance=variance,
        length=float((way[1:] - way[:-1]).norm(dim=1).sum()),
        max_variance=float(variance.max()),
        cost=float(dist[e_node]),
        variance_weight=float(variance_weight),
    )


def latent_points(model: GPLVM, points) -> torch.Tensor:
    """(K, Q) float64 latents of ``points``: material names, material indices or (Q,) latents."""
    if len(points) == 0:
        raise ValueRangeError("expected at least one latent point or material name")
    return torch.stack([_as_point(model, p) for p in points])


def resample_path(waypoints: torch.Tensor, frames: int) -> torch.Tensor:
    """``frames`` points evenly spaced by arc length along the polyline through ``waypoints``.

    Args:
        waypoints: (K, Q) latents, K >= 1 (the first and last are the path's ends).
        frames: number of points, >= 1 (1: the start only).
    Returns:
        (frames, Q) float64; the first is ``waypoints[0]`` and, for ``frames >= 2``, the last
        is ``waypoints[-1]``, bit for bit (a material's latent stays that material).
    """
    way = torch.as_tensor(waypoints, dtype=torch.float64)
    if way.ndim != 2 or way.shape[0] < 1:
        raise ValueRangeError(f"Expected waypoints of shape (K, Q), K >= 1; got {tuple(way.shape)}")
    if frames < 1:
        raise ValueRangeError(f"frames must be >= 1; got {frames}")
    seg = (way[1:] - way[:-1]).norm(dim=1)
    arc = torch.cat([seg.new_zeros(1), seg.cumsum(0)])
    if way.shape[0] == 1 or float(arc[-1]) == 0.0:
        return way[:1].expand(frames, -1).clone()
    s = torch.linspace(0.0, float(arc[-1]), frames, dtype=torch.float64)
    k = (torch.searchsorted(arc, s, right=True) - 1).clamp(0, len(seg) - 1)
    t = ((s - arc[k]) / seg[k].clamp_min(1e-300)).clamp(0, 1)[:, None]
    out = way[k] + t * (way[k + 1] - way[k])
    out[0], out[-1] = way[0], way[-1]
    return out


# -- the limitation, measured -------------------------------------------------------------------------
def directional_albedo(
    z: torch.Tensor, grid: MERLGrid, theta_i: torch.Tensor | None = None, samples: int = 48
) -> torch.Tensor:
    r"""Directional albedo :math:`a(\theta_i) = \int \rho(\omega_i, \omega_o)\cos\theta_o\,d\omega_o` per row.

    Midpoint quadrature over :math:`(\cos\theta_o, \phi_o)` with ``samples`` x ``2 * samples`` cells and the
    MERL ``"nearest"`` lookup of each row's table on ``grid``. Linear in the row (negative
    values of interpolants included: the lookup here is done directly on the table, not through
    :class:`~torch_brdf.brdf.measured.MERLTabulated`, which would treat them as missing).

    Args:
        z: (M, 3 * B) rows on ``grid``. theta_i: (K,) incidence angles (default 8 in [0, 80] deg).
    Returns:
        (M, K, 3) float64.
    """
    from ..frame import half_diff_angles
    from ..io.merl import merl_indices

    theta_i = torch.linspace(0, math.radians(80), 8, dtype=torch.float64) if theta_i is None else theta_i.double()
    u = (torch.arange(samples, dtype=torch.float64) + 0.5) / samples
    ph = (torch.arange(2 * samples, dtype=torch.float64) + 0.5) / (2 * samples) * 2 * math.pi
    ct, pp = torch.meshgrid(u, ph, indexing="ij")
    st = (1 - ct**2).sqrt()
    wo = torch.stack((st * pp.cos(), st * pp.sin(), ct), -1).reshape(-1, 3)
    wi = torch.stack((theta_i.sin(), torch.zeros_like(theta_i), theta_i.cos()), -1)
    th, _, td, pd = half_diff_angles(wi[:, None].expand(-1, wo.shape[0], 3), wo[None].expand(wi.shape[0], -1, 3))
    ih, id_, ip = merl_indices(th, td, pd)
    pos = []
    for full, kept in zip((ih, id_, ip), grid.indices, strict=True):
        k = torch.as_tensor(kept)
        pos.append((torch.searchsorted(k, full.contiguous(), right=True) - 1).clamp_min(0))
    z = torch.as_tensor(z, dtype=torch.float64)
    out = []
    weight = 2 * math.pi / (samples * 2 * samples) * wo[:, 2]  # d omega = dcos dphi, times cos theta_o
    for row in z:
        t = to_table(row, grid, missing=0.0)  # (3, Th, Td, Tp)
        f = t[:, pos[0], pos[1], pos[2]]  # (3, K, S)
        out.append((f * weight).sum(-1).T)
    return torch.stack(out)


@dataclass(frozen=True)
class Diagnostics:
    """Per interpolant: fraction of negative values (M,), max directional albedo over angles and RGB (M,)."""

    negative_fraction: torch.Tensor
    max_albedo: torch.Tensor


def interpolant_diagnostics(weights: torch.Tensor, z: torch.Tensor, albedo: torch.Tensor) -> Diagnostics:
    """Negative fraction and max albedo of the interpolants ``weights @ z`` (albedo blended linearly).

    Args:
        weights: (M, N) blending weights. z: (N, d) raw rows. albedo: (N, K, 3) from :func:`directional_albedo`.
    """
    w = torch.as_tensor(weights, dtype=torch.float64)
    zi = w @ torch.as_tensor(z, dtype=torch.float64)
    neg = (zi < 0).double().mean(-1)
    alb = torch.einsum("mn,nkc->mkc", w, albedo.double()).flatten(1).max(-1).values
    return Diagnostics(neg, alb)


# -- does a designer move *between* materials? ---------------------------------------------------------
@dataclass(frozen=True)
class Interpolation:
    """Where latent points sit relative to the training latents.

    Attributes:
        ratio: (M,) distance of each point to its nearest training latent, divided by that training
            latent's distance to its own nearest other training latent (the local spacing).
        nearest: (M,) index of that training latent.
        share: fraction of points with ``ratio >= threshold``: placed between materials, not on one.
        threshold: the ratio above which a point counts as between materials.
    """

    ratio: torch.Tensor
    nearest: torch.Tensor
    share: float
    threshold: float


def interpolation_share(latents: torch.Tensor, xs: torch.Tensor, threshold: float = 0.1) -> Interpolation:
    r"""How far points ``xs`` are from the training latents, relative to the neighbour spacing there.

    A held-out material placed within ``threshold`` (default 0.1) of the local spacing from a
    training latent is, for a blend, that training material (the valid weights are :math:`e_i`
    on a neighbourhood of each latent): the manifold then only finds its nearest neighbour.

    Args:
        latents: (N, Q) training latents, N >= 2. xs: (M, Q) points. threshold: > 0.
    Returns:
        :class:`Interpolation`.
    """
    lat = torch.as_tensor(latents, dtype=torch.float64)
    xs = torch.as_tensor(xs, dtype=torch.float64)
    if lat.ndim != 2 or lat.shape[0] < 2 or xs.ndim != 2 or xs.shape[1] != lat.shape[1]:
        raise ValueRangeError(
            f"Expected latents (N >= 2, Q) and points (M, Q); got {tuple(lat.shape)}, {tuple(xs.shape)}"
        )
    if not (math.isfinite(threshold) and threshold > 0):
        raise ValueRangeError(f"threshold must be finite and > 0; got {threshold}")
    own = torch.cdist(lat, lat)
    own.fill_diagonal_(math.inf)
    spacing = own.min(1).values.clamp_min(1e-300)
    d, i = torch.cdist(xs, lat).min(1)
    ratio = d / spacing[i]
    share = float((ratio >= threshold).double().mean()) if xs.shape[0] else 0.0
    return Interpolation(ratio, i, share, float(threshold))


@dataclass(frozen=True)
class PathProfile:
    """Albedo and highlight width along straight latent paths (one row per path, ``steps`` points).

    Attributes:
        albedo: (P, S) mean directional albedo (over incidence angles and RGB) of the blends.
        width: (P, S) highlight width (rad): :math:`\\sqrt{\\sum f \\theta_h^2 / \\sum f}` of the
            blended BRDF at the smallest :math:`\\theta_d`, :math:`\\phi_d` of the grid (RGB mean).
        jump: (P,) largest log-mapped RMS change between two consecutive points, as a share of the
            change between the ends (a smooth path of S points: about 1/(S-1); a snap: near 1).
        monotone: (P,) bool, albedo or width changes monotonically (up to ``tol`` of its range).
    """

    albedo: torch.Tensor
    width: torch.Tensor
    jump: torch.Tensor
    monotone: torch.Tensor


def _monotone(v: torch.Tensor, tol: float) -> torch.Tensor:
    """(P, S) -> (P,) bool: every step has the sign of the overall change (up to ``tol`` of the range)."""
    dv = v[:, 1:] - v[:, :-1]
    slack = tol * (v.max(1).values - v.min(1).values)[:, None] + 1e-12
    return ((dv >= -slack).all(1)) | ((dv <= slack).all(1))


def highlight_width(z: torch.Tensor, grid: MERLGrid) -> torch.Tensor:
    r"""(M,) highlight width :math:`\sqrt{\sum f\theta_h^2/\sum f}` (rad) of rows (M, 3 B) on ``grid``.

    ``f``: the RGB mean at the grid's smallest :math:`\theta_d` and :math:`\phi_d`, clamped at 0,
    over :math:`\theta_h` (the centres of MERL's bins).
    A ratio of two linear functionals: monotone along a blend of two materials.
    """
    th = merl_index_to_angles(*grid.indices, at="centre")[0]
    f = torch.stack(
        [to_table(r, grid, missing=0.0)[:, :, 0, 0].mean(0) for r in torch.as_tensor(z, dtype=torch.float64)]
    )
    f = f.clamp_min(0)
    return ((f * th**2).sum(1) / f.sum(1).clamp_min(1e-300)).sqrt()


def straight_paths(
    model: GPLVM,
    pairs,
    z: torch.Tensor,
    albedo: torch.Tensor,
    grid: MERLGrid,
    steps: int = 33,
    tol: float = 1e-3,
    valid: str | None = None,
) -> PathProfile:
    r"""Albedo, highlight width and jumps along straight latent paths between pairs of materials.

    A designer dragging from one material to another expects no sudden snap and a steady change
    of what distinguishes them: :func:`_monotone` on the albedo (linear in the blend) or the
    highlight width (:func:`highlight_width`). Jumps are measured on the whole row in the log
    mapping of :func:`~torch_brdf.metrics.log_relative_rmse` (cosine-weighted, clamped at 0).

    Args:
        model: fitted :class:`GPLVM`. pairs: (P, 2) material indices or names.
        z: (N, 3 B) the model's raw rows. albedo: (N, K, C) from :func:`directional_albedo`.
        grid: the rows' grid. steps: points per path (>= 3). tol: monotonicity slack (share of range).
        valid: blend weights (None = the model's).
    Returns:
        :class:`PathProfile`.
    """
    if steps < 3:
        raise ValueRangeError(f"steps must be >= 3; got {steps}")
    z = torch.as_tensor(z, dtype=torch.float64)
    a_mean = torch.as_tensor(albedo, dtype=torch.float64).flatten(1).mean(1)
    t = torch.linspace(0, 1, steps, dtype=torch.float64)[:, None]
    cos = (
        grid.cosine_map().repeat(3) if z.shape[1] == 3 * grid.num_valid else torch.ones(z.shape[1], dtype=torch.float64)
    )
    alb, wid, jump = [], [], []
    for p0, p1 in pairs:
        a, b = _as_point(model, p0), _as_point(model, p1)
        xs = a + t * (b - a)
        xs[0], xs[-1] = a, b  # the ends bit for bit: the materials themselves
        w = model.weights(xs, valid)
        rows = w @ z
        alb.append(w @ a_mean)
        wid.append(highlight_width(rows, grid))
        m = torch.log(rows.clamp_min(0) * cos + 1e-3)
        step = (m[1:] - m[:-1]).pow(2).mean(1).sqrt()
        whole = (m[-1] - m[0]).pow(2).mean().sqrt().clamp_min(1e-300)
        jump.append(step.max() / whole)
    alb, wid = torch.stack(alb), torch.stack(wid)
    return PathProfile(alb, wid, torch.stack(jump), _monotone(alb, tol) | _monotone(wid, tol))
