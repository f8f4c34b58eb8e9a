r"""Cubemaps in world orientation, split into square blocks of texels.

Faces follow the OpenGL order and orientation: ``+x, -x, +y, -y, +z, -z``. Texel ``(i, j)``
of a face of resolution ``R`` (row ``i``, column ``j``) has face coordinates
:math:`a = 2(j + \tfrac12)/R - 1`, :math:`b = 2(i + \tfrac12)/R - 1` and direction

=====  ==================  =====  ==================
face   direction           face   direction
=====  ==================  =====  ==================
+x     (1, -b, -a)         -x     (-1, -b, a)
+y     (a, 1, b)           -y     (a, -1, -b)
+z     (a, -b, 1)          -z     (-a, -b, -1)
=====  ==================  =====  ==================

(normalised). Every per-vertex cubemap of the package uses this one orientation, so the
lighting is projected once per change and never per vertex (Inger et al., Sec. 4).

Blocks: each face is split into ``(R/S)^2`` blocks of ``S x S`` texels (``S = 16`` in the
seed); block ``k = face * (R/S)^2 + bi * (R/S) + bj``, and inside a block texel
``t = r * S + c`` (rows concatenated: the seed's 1-D visibility vector). Texel solid angles
are exact (the area of the texel's square projected on the unit sphere).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch

from ..errors import ShapeError, ValueRangeError

__all__ = ["CubemapBlocks", "cube_directions", "direction_to_cube", "texel_solid_angles_cube"]

# rows: face; columns: coefficients of (a, b, 1) for x, y, z
_FACE_MATRIX = torch.tensor(
    [
        [[0, 0, 1], [0, -1, 0], [-1, 0, 0]],  # +x: ( 1, -b, -a)
        [[0, 0, -1], [0, -1, 0], [1, 0, 0]],  # -x: (-1, -b,  a)
        [[1, 0, 0], [0, 0, 1], [0, 1, 0]],  # +y: ( a,  1,  b)
        [[1, 0, 0], [0, 0, -1], [0, -1, 0]],  # -y: ( a, -1, -b)
        [[1, 0, 0], [0, -1, 0], [0, 0, 1]],  # +z: ( a, -b,  1)
        [[-1, 0, 0], [0, -1, 0], [0, 0, -1]],  # -z: (-a, -b, -1)
    ],
    dtype=torch.float64,
)


def _check_resolution(resolution: int, block: int = 1) -> None:
    if int(resolution) != resolution or resolution < 1 or block < 1 or resolution % block:
        raise ValueRangeError(
            f"cubemap resolution must be a positive multiple of the block size {block}; got {resolution}"
        )


def cube_directions(face: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Unit directions of face coordinates.

    Args:
        face: (*B,) int64 face index in 0..5.
        a: (*B,) face coordinates in [-1, 1] (column and row axes).
        b: as ``a``.
    Returns:
        (*B, 3) unit directions in ``a``'s dtype.
    """
    m = _FACE_MATRIX.to(a.dtype)[face]  # (*B, 3, 3)
    v = torch.stack((a, b, torch.ones_like(a)), -1)
    d = (m * v.unsqueeze(-2)).sum(-1)
    return d / d.norm(dim=-1, keepdim=True)


def direction_to_cube(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Face and face coordinates of directions (inverse of :func:`cube_directions`).

    Args:
        d: (*B, 3) non-zero directions.
    Returns:
        ``face`` (*B,) int64, ``a`` (*B,), ``b`` (*B,) in [-1, 1].
    """
    if d.shape[-1] != 3:
        raise ShapeError(f"Expected directions of shape (..., 3); got {tuple(d.shape)}")
    ax = d.abs().argmax(-1)
    comp = d.gather(-1, ax.unsqueeze(-1)).squeeze(-1)
    face = 2 * ax + (comp < 0).long()
    m = _FACE_MATRIX.to(d.dtype)[face]  # d = m @ (a, b, 1) * s with s = |comp|
    local = (m.transpose(-1, -2) * d.unsqueeze(-2)).sum(-1) / comp.abs().unsqueeze(-1)
    return face, local[..., 0].clamp(-1, 1), local[..., 1].clamp(-1, 1)


def _corner_area(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    return torch.atan2(x * y, torch.sqrt(x * x + y * y + 1))


def texel_solid_angles_cube(resolution: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Exact solid angle of every texel of one face: (R, R), the same on all six faces.

    The six faces together sum to :math:`4\\pi`.
    """
    _check_resolution(resolution)
    e = torch.linspace(-1.0, 1.0, resolution + 1, dtype=torch.float64)
    x0, x1 = e[:-1][None, :], e[1:][None, :]
    y0, y1 = e[:-1][:, None], e[1:][:, None]
    om = _corner_area(x1, y1) - _corner_area(x0, y1) - _corner_area(x1, y0) + _corner_area(x0, y0)
    return om.to(dtype)


@dataclass(frozen=True)
class CubemapBlocks:
    """Geometry of a ``6 x R x R`` cubemap split into ``S x S`` blocks.

    Attributes:
        resolution: R, texels per face side (a multiple of ``block``).
        block: S, texels per block side (16 in the seed).
    """

    resolution: int = 64
    block: int = 16

    def __post_init__(self):
        _check_resolution(self.resolution, self.block)

    @property
    def blocks_per_side(self) -> int:
        return self.resolution // self.block

    @property
    def block_count(self) -> int:
        """NB = 6 (R/S)^2 (96 at 64x64x6, 384 at 128x128x6)."""
        return 6 * self.blocks_per_side**2

    @property
    def block_size(self) -> int:
        """S^2 texels per block (256)."""
        return self.block * self.block

    @property
    def texel_count(self) -> int:
        return 6 * self.resolution**2

    @cached_property
    def texel_index(self) -> torch.Tensor:
        """(NB, S^2) int64: flat index ``face * R^2 + row * R + col`` of each block texel."""
        R, S, n = self.resolution, self.block, self.blocks_per_side
        f = torch.arange(6).view(6, 1, 1, 1, 1)
        bi = torch.arange(n).view(1, n, 1, 1, 1)
        bj = torch.arange(n).view(1, 1, n, 1, 1)
        r = torch.arange(S).view(1, 1, 1, S, 1)
        c = torch.arange(S).view(1, 1, 1, 1, S)
        idx = f * R * R + (bi * S + r) * R + (bj * S + c)
        return idx.reshape(self.block_count, S * S)

    def to_blocks(self, x: torch.Tensor) -> torch.Tensor:
        """Face layout (..., 6, R, R, *rest) -> block layout (..., NB, S^2, *rest).

        ``rest`` is given by the number of trailing dims after the (6, R, R) group, found
        from the first dim equal to 6 followed by R, R.
        """
        lead = self._face_dims(x)
        flat = x.reshape(*x.shape[:lead], 6 * self.resolution**2, *x.shape[lead + 3 :])
        return flat[(slice(None),) * lead + (self.texel_index,)]

    def from_blocks(self, x: torch.Tensor, lead: int = 0) -> torch.Tensor:
        """Block layout (*lead, NB, S^2, *rest) -> face layout (*lead, 6, R, R, *rest)."""
        if x.shape[lead : lead + 2] != (self.block_count, self.block_size):
            raise ShapeError(
                f"Expected block layout (..., {self.block_count}, {self.block_size}, ...) at dim {lead}; "
                f"got {tuple(x.shape)}"
            )
        R = self.resolution
        out = x.new_zeros(*x.shape[:lead], 6 * R * R, *x.shape[lead + 2 :])
        out[(slice(None),) * lead + (self.texel_index.reshape(-1),)] = x.reshape(
            *x.shape[:lead], -1, *x.shape[lead + 2 :]
        )
        return out.reshape(*x.shape[:lead], 6, R, R, *x.shape[lead + 2 :])

    def _face_dims(self, x: torch.Tensor) -> int:
        R = self.resolution
        for i in range(x.ndim - 2):
            if tuple(x.shape[i : i + 3]) == (6, R, R):
                return i
        raise ShapeError(f"Expected a cubemap with dims (6, {R}, {R}); got {tuple(x.shape)}")

    def face_coordinates(self, rows: torch.Tensor, cols: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Face coordinates (a, b) of fractional texel positions (texel centres at integers)."""
        R = self.resolution
        return 2 * (cols + 0.5) / R - 1, 2 * (rows + 0.5) / R - 1

    def block_points(self, positions: torch.Tensor, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """Directions at fractional in-block positions, the same pattern in every block.

        Args:
            positions: (m,) in-block coordinates in texel units (texel centres at
                ``0 .. S-1``); the points are the grid ``positions x positions``, row-major.
        Returns:
            (NB, m^2, 3) unit directions.
        """
        S, n = self.block, self.blocks_per_side
        p = positions.to(torch.float64)
        m = p.numel()
        blk = torch.arange(self.block_count)
        face = blk // (n * n)
        bi, bj = (blk % (n * n)) // n, blk % n
        rows = (bi[:, None] * S + p[None, :])[:, :, None].expand(-1, m, m)
        cols = (bj[:, None] * S + p[None, :])[:, None, :].expand(-1, m, m)
        a, b = self.face_coordinates(rows, cols)
        d = cube_directions(face[:, None, None].expand(-1, m, m), a, b)
        return d.reshape(self.block_count, m * m, 3).to(dtype)

    @cached_property
    def directions(self) -> torch.Tensor:
        """(NB, S^2, 3) float64 texel-centre directions in block layout."""
        return self.block_points(torch.arange(self.block, dtype=torch.float64))

    @cached_property
    def solid_angles(self) -> torch.Tensor:
        """(NB, S^2) float64 exact texel solid angles in block layout."""
        om = texel_solid_angles_cube(self.resolution).expand(6, -1, -1)
        return self.to_blocks(om)

    @cached_property
    def centers(self) -> torch.Tensor:
        """(NB, 3) float64 directions of the block centres."""
        return self.block_points(torch.tensor([(self.block - 1) / 2.0]))[:, 0]

    @cached_property
    def angular_radius(self) -> float:
        """Largest angle (radians) between a block centre and a texel direction in that block."""
        cos = (self.directions * self.centers[:, None]).sum(-1)
        return float(torch.acos(cos.clamp(-1, 1)).max())

    def nearest_in_blocks(self, blocks: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """A point of each block close to direction ``d``: ``d`` projected on the block's
        face plane and clamped to the block (exact when ``d`` falls inside the block), or
        the block centre when ``d`` points away from that face.

        Args:
            blocks: (n,) int64 block ids.
            d: (n, 3) directions.
        Returns:
            (n, 3) unit directions in ``d``'s dtype.
        """
        S, nb, R = self.block, self.blocks_per_side, self.resolution
        face = blocks // (nb * nb)
        bi, bj = (blocks % (nb * nb)) // nb, blocks % nb
        m = _FACE_MATRIX.to(d.dtype)[face]  # d = s * m @ (a, b, 1)
        loc = (m.transpose(-1, -2) * d.unsqueeze(-2)).sum(-1)  # (a s, b s, s)
        s = loc[:, 2]
        front = s > 1e-6
        safe = torch.where(front, s, torch.ones_like(s))
        lo_a, hi_a = 2 * (bj * S) / R - 1, 2 * (bj * S + S) / R - 1
        lo_b, hi_b = 2 * (bi * S) / R - 1, 2 * (bi * S + S) / R - 1
        a = torch.where(front, torch.minimum(torch.maximum(loc[:, 0] / safe, lo_a), hi_a), (lo_a + hi_a) / 2)
        b = torch.where(front, torch.minimum(torch.maximum(loc[:, 1] / safe, lo_b), hi_b), (lo_b + hi_b) / 2)
        return cube_directions(face, a.to(d.dtype), b.to(d.dtype))

    def supersampled_directions(self, samples: int) -> torch.Tensor:
        """(NB, S^2, k^2, 3) float64 directions of a ``k x k`` grid inside every texel."""
        k = int(samples)
        if k < 1:
            raise ValueRangeError(f"samples per texel side must be >= 1; got {samples}")
        S, n = self.block, self.blocks_per_side
        off = (torch.arange(k, dtype=torch.float64) + 0.5) / k - 0.5
        blk = torch.arange(self.block_count)
        face = (blk // (n * n)).view(-1, 1, 1, 1, 1)
        bi, bj = ((blk % (n * n)) // n).view(-1, 1, 1, 1, 1), (blk % n).view(-1, 1, 1, 1, 1)
        r = torch.arange(S, dtype=torch.float64).view(1, S, 1, 1, 1)
        c = torch.arange(S, dtype=torch.float64).view(1, 1, S, 1, 1)
        rows = bi * S + r + off.view(1, 1, 1, k, 1)
        cols = bj * S + c + off.view(1, 1, 1, 1, k)
        rows, cols = torch.broadcast_tensors(rows, cols)
        a, b = self.face_coordinates(rows, cols)
        d = cube_directions(face.expand_as(a), a, b)
        return d.reshape(self.block_count, S * S, k * k, 3)

    def project(self, radiance_fn, samples: int = 4, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        r"""Solid-angle mean of a directional function over each texel, by a ``k x k`` grid per texel.

        The grid is uniform on the face, so each point is weighted by the face's Jacobian
        :math:`d\omega/dA = (1 + a^2 + b^2)^{-3/2} = \max_i |\omega_i|^3`: the texel sums
        :math:`\bar L_t\Omega_t` then converge to :math:`\int L\,d\omega` as ``k`` grows, even
        for a feature (a sun) smaller than a texel.

        Args:
            radiance_fn: callable (M, 3) float64 directions -> (M, C) values.
            samples: grid points per texel side.
        Returns:
            (NB, S^2, C) texel means in block layout.
        """
        d = self.supersampled_directions(samples)
        v = radiance_fn(d.reshape(-1, 3))
        w = d.to(torch.float64).abs().amax(-1, keepdim=True) ** 3  # (NB, S^2, k^2, 1)
        v = v.reshape(*d.shape[:3], -1).to(torch.float64)
        return ((v * w).sum(2) / w.sum(2)).to(dtype)
