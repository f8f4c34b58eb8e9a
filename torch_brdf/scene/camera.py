"""Pinhole look-at camera and its primary rays."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .._checks import as_float_tensor, check_finite, check_image_size, check_real, check_vectors
from ..errors import CameraError, ShapeError, ValueRangeError


@dataclass(frozen=True)
class Camera:
    """A pinhole camera looking from ``origin`` at ``target``.

    Image conventions: (H, W) with row 0 at the top; ``fov_deg`` is the vertical field of
    view; pixel (r, c) spans [c, c+1] x [r, r+1] in raster space, centre at +0.5. The
    camera frame: ``forward`` points at the target, ``right = forward x up`` (normalised)
    runs along increasing columns and ``right x forward`` up along decreasing rows, so
    images are not mirrored (in the Cornell box, looking along +z with +y up, +x is on
    the left of the image, as in the published photographs).

    Args:
        origin: the eye position (3 numbers).
        target: the point looked at (3 numbers).
        up: the up direction (3 numbers).
        fov_deg: vertical field of view in degrees, in (0, 180).
        width: image width in pixels.
        height: image height in pixels.
    """

    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_deg: float = 39.3
    width: int = 256
    height: int = 256

    def __post_init__(self):
        try:
            for name in ("origin", "target", "up"):
                v = check_vectors(getattr(self, name), f"camera {name}", torch.float64, ndim=1)
                object.__setattr__(self, name, tuple(float(x) for x in v))
            fov = check_real(self.fov_deg, "camera fov_deg")
            w, h = check_image_size(self.width, self.height, "camera image")
        except (ShapeError, ValueRangeError) as exc:
            raise CameraError(str(exc)) from exc
        if not (0.0 < fov < 180.0):
            raise CameraError(f"fov_deg must be in (0, 180); got {self.fov_deg}")
        object.__setattr__(self, "fov_deg", float(self.fov_deg))
        object.__setattr__(self, "width", w)
        object.__setattr__(self, "height", h)
        f = torch.tensor(self.target, dtype=torch.float64) - torch.tensor(self.origin, dtype=torch.float64)
        if float(f.norm()) == 0.0:
            raise CameraError("camera origin and target coincide: no viewing direction")
        f = f / f.norm()
        up = torch.tensor(self.up, dtype=torch.float64)
        if float(up.norm()) == 0.0:
            raise CameraError("camera up vector is zero")
        right = torch.linalg.cross(f, up / up.norm())
        if float(right.norm()) < 1e-9:
            raise CameraError(f"camera up {self.up} is parallel to the viewing direction {tuple(f.tolist())}")
        right = right / right.norm()
        true_up = torch.linalg.cross(right, f)
        object.__setattr__(self, "_frame", torch.stack((right, true_up, f)))  # rows: x, y, z

    @property
    def frame(self) -> torch.Tensor:
        """(3, 3) float64 rows: right, up, forward (world space)."""
        return self._frame

    def with_size(self, width: int, height: int) -> Camera:
        """The same camera at another image size (same vertical field of view)."""
        return Camera(self.origin, self.target, self.up, self.fov_deg, width, height)

    def generate_rays(
        self,
        jitter: bool = False,
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Primary rays, one per pixel, in row-major order.

        Args:
            jitter: sample a uniform point in each pixel instead of its centre.
            generator: random source for the jitter.
            dtype: output dtype.
        Returns:
            origins (H*W, 3) and unit directions (H*W, 3).
        """
        h, w = self.height, self.width
        rows = torch.arange(h, dtype=torch.float64)
        cols = torch.arange(w, dtype=torch.float64)
        r, c = torch.meshgrid(rows, cols, indexing="ij")
        r, c = r.reshape(-1), c.reshape(-1)
        if jitter:
            off = torch.rand(h * w, 2, generator=generator, dtype=torch.float64)
            r, c = r + off[:, 0], c + off[:, 1]
        else:
            r, c = r + 0.5, c + 0.5
        return self.rays_through(c, r, dtype)

    @property
    def tan_half(self) -> float:
        """tan(fov / 2): the half-height of the image plane at distance 1."""
        return math.tan(math.radians(self.fov_deg) / 2)

    def rays_through(self, x, y, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through raster positions ``x`` (column, may be fractional) and ``y`` (row).

        Args:
            x: (P,) raster x in [0, W]; y: (P,) raster y in [0, H].
        Returns:
            origins (P, 3), unit directions (P, 3).
        Raises:
            ValueRangeError: NaN or Inf raster positions.
        """
        x = check_finite(as_float_tensor(x, "x", torch.float64), "raster x")
        y = check_finite(as_float_tensor(y, "y", torch.float64), "raster y")
        tan_half = self.tan_half
        aspect = self.width / self.height
        sx = (2 * x / self.width - 1) * tan_half * aspect
        sy = (1 - 2 * y / self.height) * tan_half
        local = torch.stack((sx, sy, torch.ones_like(sx)), -1)
        d = local @ self.frame
        d = d / d.norm(dim=-1, keepdim=True)
        o = torch.tensor(self.origin, dtype=torch.float64).expand_as(d)
        return o.to(dtype).contiguous(), d.to(dtype)

    def project(self, points) -> torch.Tensor:
        """Raster coordinates (P, 2) as (x, y) of world points (P, 3); NaN-free, behind -> inf."""
        p = check_vectors(points, "points").to(torch.float64) - torch.tensor(self.origin, dtype=torch.float64)
        local = p @ self.frame.T
        z = local[:, 2]
        tan_half = self.tan_half
        aspect = self.width / self.height
        safe = torch.where(z > 0, z, torch.ones_like(z))
        x = (local[:, 0] / safe / (tan_half * aspect) + 1) * self.width / 2
        y = (1 - local[:, 1] / safe / tan_half) * self.height / 2
        out = torch.stack((x, y), -1)
        return torch.where((z > 0)[:, None], out, torch.full_like(out, float("inf")))
