r"""Latitude-longitude (equirectangular) maps: directions <-> angles <-> texels.

The convention is fixed for the whole package. World :math:`+y` is up. A lat-long map is
``(H, W, C)`` with ``W = 2H``; row 0 is the zenith. Texel ``(i, j)`` covers the polar angle
:math:`\theta \in [i, i+1]\,\pi/H` measured from :math:`+y` and the azimuth
:math:`\phi \in [j, j+1]\,2\pi/W`, with

.. math::
    \omega(\theta, \phi) = (\sin\theta\sin\phi,\ \cos\theta,\ -\sin\theta\cos\phi),
    \qquad \theta = \operatorname{acos} y,\quad \phi = \operatorname{atan2}(x, -z) \bmod 2\pi,

so :math:`\phi = 0` looks down :math:`-z` and :math:`\phi = \pi/2` down :math:`+x`. This is
Mitsuba 3's ``envmap`` emitter mapping (``uv_to_direction`` / ``direction_to_uv`` in
``src/emitters/envmap.cpp``) with an identity ``to_world``, so a map used here and handed to
Mitsuba lights the scene from the same directions.

Two readings of the same array exist:

* **texels** (piecewise constant): entry ``(i, j)`` covers the cell above;
* **nodes** (bilinear, Mitsuba's reading): entry ``(i, j)`` is the value *at*
  :math:`\theta_i = i\pi/(H-1)` (row 0 on the zenith, row ``H-1`` on the nadir, "align
  corners") and :math:`\phi_j = (j+\tfrac12)\,2\pi/W` (periodic), interpolated bilinearly in
  :math:`(\phi, \theta)` between them (:func:`bilinear_lookup`, :func:`node_directions`,
  :func:`node_solid_angles`).
"""

from __future__ import annotations

import math

import torch

from .._checks import as_float_tensor
from ..errors import ShapeError

__all__ = [
    "bilinear_coordinates",
    "bilinear_lookup",
    "direction_to_latlong",
    "direction_to_texel",
    "latlong_to_direction",
    "node_directions",
    "node_row_weights",
    "node_solid_angles",
    "row_cos_bounds",
    "texel_centers",
    "texel_solid_angles",
]


def _check_dirs(d) -> torch.Tensor:
    d = as_float_tensor(d, "directions")
    if d.ndim < 1 or d.shape[-1] != 3:
        raise ShapeError(f"Expected directions to have shape (..., 3); got {tuple(d.shape)}")
    return d


def _check_size(height: int, width: int) -> None:
    if int(height) < 1 or int(width) < 1:
        raise ShapeError(f"lat-long size must be positive; got H={height}, W={width}")


def direction_to_latlong(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    r"""Polar angle from :math:`+y` and azimuth of directions (need not be unit length).

    :math:`\theta = \operatorname{atan2}(\sqrt{x^2+z^2}, y)` (accurate near the poles) and
    :math:`\phi = \operatorname{atan2}(x, -z) \bmod 2\pi`.

    Args:
        d: (..., 3) directions.
    Returns:
        theta (...) in :math:`[0, \pi]` and phi (...) in :math:`[0, 2\pi)`, in ``d``'s dtype.
    """
    d = _check_dirs(d)
    x, y, z = d.unbind(-1)
    theta = torch.atan2(torch.hypot(x, z), y)
    phi = torch.remainder(torch.atan2(x, -z), 2 * math.pi)
    phi = torch.where(phi >= 2 * math.pi, torch.zeros_like(phi), phi)  # rounding of -tiny mod 2pi
    return theta, phi


def latlong_to_direction(theta: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    r"""Unit direction :math:`(\sin\theta\sin\phi, \cos\theta, -\sin\theta\cos\phi)`.

    Args:
        theta: (...) polar angle from :math:`+y`.
        phi: (...) azimuth (broadcast against ``theta``).
    Returns:
        (..., 3) unit vectors in the dtype of the inputs.
    """
    st = theta.sin()
    return torch.stack(torch.broadcast_tensors(st * phi.sin(), theta.cos(), -st * phi.cos()), dim=-1)


def direction_to_texel(d: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Row and column of the texel that contains each direction (nearest-texel lookup).

    Angles are computed in float64 so that directions sampled inside a texel map back to it;
    indices are clamped to the map (directions on the last edge belong to the last texel).

    Args:
        d: (..., 3) directions (need not be unit length).
        height: H, number of rows.
        width: W, number of columns.
    Returns:
        row (...) and col (...), int64.
    """
    _check_size(height, width)
    theta, phi = direction_to_latlong(_check_dirs(d).to(torch.float64))
    row = (theta * (height / math.pi)).floor().long().clamp_(0, height - 1)
    col = (phi * (width / (2 * math.pi))).floor().long().clamp_(0, width - 1)
    return row, col


def row_cos_bounds(height: int, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    r""":math:`\cos\theta_i` at the row edges :math:`\theta_i = i\pi/H`, i = 0..H: (H+1,).

    Decreasing; the end points are exactly 1 and -1.
    """
    _check_size(height, 1)
    c = torch.cos(torch.arange(height + 1, dtype=torch.float64, device=device) * (math.pi / height))
    c[0], c[-1] = 1.0, -1.0
    return c.to(dtype)


def texel_solid_angles(height: int, width: int, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    r"""Exact solid angle of every texel, :math:`(\cos\theta_i - \cos\theta_{i+1})\,2\pi/W`.

    Computed in float64; the sum over the map is :math:`4\pi` to rounding (~1e-15 relative).

    Args:
        height: H.
        width: W.
        dtype: output dtype (float64 by default; these are tables, not per-ray math).
    Returns:
        (H, W) solid angles in steradians.
    """
    _check_size(height, width)
    c = row_cos_bounds(height, device=device)
    omega = (c[:-1] - c[1:]) * (2 * math.pi / width)
    return omega[:, None].expand(height, width).to(dtype).contiguous()


def texel_centers(height: int, width: int, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    r"""Direction of every texel's angular centre :math:`((i+\tfrac12)\pi/H, (j+\tfrac12)2\pi/W)`.

    Args:
        height: H.
        width: W.
        dtype: output dtype (computed in float64).
    Returns:
        (H, W, 3) unit vectors.
    """
    _check_size(height, width)
    theta = (torch.arange(height, dtype=torch.float64, device=device) + 0.5) * (math.pi / height)
    phi = (torch.arange(width, dtype=torch.float64, device=device) + 0.5) * (2 * math.pi / width)
    return latlong_to_direction(theta[:, None], phi[None, :]).to(dtype)


# ------------------------------------------------------------------ nodes (bilinear reading)
def node_directions(height: int, width: int, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    r"""Direction of every node :math:`(\theta_i, \phi_j) = (i\pi/(H-1), (j+\tfrac12)\,2\pi/W)`.

    Args:
        height: H >= 2.
        width: W.
        dtype: output dtype (computed in float64).
    Returns:
        (H, W, 3) unit vectors; rows 0 and H-1 are the poles :math:`\pm y`.
    """
    _check_size(height, width)
    if int(height) < 2:
        raise ShapeError(f"a bilinear lat-long map needs H >= 2 rows; got H={height}")
    theta = torch.arange(height, dtype=torch.float64, device=device) * (math.pi / (height - 1))
    phi = (torch.arange(width, dtype=torch.float64, device=device) + 0.5) * (2 * math.pi / width)
    d = latlong_to_direction(theta[:, None], phi[None, :])
    d[0, :, 0], d[0, :, 2], d[-1, :, 0], d[-1, :, 2] = 0.0, 0.0, 0.0, 0.0  # exactly the poles
    return d.to(dtype)


def node_row_weights(height: int, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    r""":math:`w_i = \int \Lambda_i(\theta)\sin\theta\,d\theta` for the hat functions of the rows.

    :math:`\Lambda_i` is 1 at :math:`\theta_i = i\Delta` (:math:`\Delta = \pi/(H-1)`) and falls
    linearly to 0 at its neighbours. Closed forms per side (:math:`a < b` the interval):
    :math:`\int_a^b \tfrac{\theta-a}{\Delta}\sin\theta = -\cos b + (\sin b - \sin a)/\Delta` and
    :math:`\int_a^b \tfrac{b-\theta}{\Delta}\sin\theta = \cos a - (\sin b - \sin a)/\Delta`.
    The weights sum to 2 (the integral of :math:`\sin\theta`) to rounding.

    Returns:
        (H,) float64 (or ``dtype``).
    """
    _check_size(height, 1)
    if int(height) < 2:
        raise ShapeError(f"a bilinear lat-long map needs H >= 2 rows; got H={height}")
    delta = math.pi / (height - 1)
    t = torch.arange(height, dtype=torch.float64, device=device) * delta
    a, b = t[:-1], t[1:]
    ds = (b.sin() - a.sin()) / delta
    rising = -b.cos() + ds  # the hat of node i+1 on [a, b]
    falling = a.cos() - ds  # the hat of node i on [a, b]
    w = torch.zeros(height, dtype=torch.float64, device=device)
    w[1:] += rising
    w[:-1] += falling
    return w.to(dtype)


def node_solid_angles(height: int, width: int, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    r"""The solid angle each node stands for: :math:`\Omega_{ij} = w_i\,2\pi/W` (:func:`node_row_weights`).

    :math:`\int L\,d\omega = \sum_{ij} L_{ij}\Omega_{ij}` exactly for the bilinear map; the sum
    of the table is :math:`4\pi`.

    Returns:
        (H, W) steradians.
    """
    w = node_row_weights(height, device=device) * (2 * math.pi / width)
    return w[:, None].expand(height, width).to(dtype).contiguous()


def bilinear_coordinates(d: torch.Tensor, height: int, width: int):
    r"""Where directions fall in the node grid: the lower row and column and the weights.

    Args:
        d: (..., 3) directions (need not be unit length).
        height: H >= 2.
        width: W.
    Returns:
        ``(i0, j0, j1, fy, fx, theta)``: rows ``i0`` and ``i0 + 1``, columns ``j0`` and
        ``j1 = (j0 + 1) mod W`` (int64), the fractions ``fy``, ``fx`` in [0, 1] towards the
        second row and column, and the polar angle, all float64 (...).
    """
    _check_size(height, width)
    if int(height) < 2:
        raise ShapeError(f"a bilinear lat-long map needs H >= 2 rows; got H={height}")
    theta, phi = direction_to_latlong(_check_dirs(d).to(torch.float64))
    y = theta * ((height - 1) / math.pi)
    i0 = y.floor().clamp_(0, height - 2)
    fy = (y - i0).clamp_(0, 1)
    x = phi * (width / (2 * math.pi)) - 0.5
    j0 = x.floor()
    fx = (x - j0).clamp_(0, 1)
    j0 = torch.remainder(j0.long(), width)
    return i0.long(), j0, torch.remainder(j0 + 1, width), fy, fx, theta


def bilinear_lookup(values: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Mitsuba's ``envmap`` reconstruction: ``values`` read as nodes, interpolated bilinearly.

    Args:
        values: (H, W, C) or (H, W) node values.
        d: (..., 3) directions.
    Returns:
        (..., C) or (...) in ``values``' dtype (weights in float64).
    """
    H, W = values.shape[:2]
    i0, j0, j1, fy, fx, _ = bilinear_coordinates(d, H, W)
    v = values.double()
    if v.ndim == 3:
        fy, fx = fy[..., None], fx[..., None]
    top = v[i0, j0] * (1 - fx) + v[i0, j1] * fx
    bottom = v[i0 + 1, j0] * (1 - fx) + v[i0 + 1, j1] * fx
    return (top * (1 - fy) + bottom * fy).to(values.dtype)
