r"""Environment maps: a distant light given by a lat-long radiance map.

The map layout and the direction convention are those of :mod:`torch_brdf.sphere.latlong`
(world :math:`+y` up, row 0 the zenith, :math:`\phi = \operatorname{atan2}(x, -z)`), i.e.
Mitsuba 3's ``envmap`` emitter with an identity ``to_world``. The radiance is piecewise
constant per texel (nearest-texel lookup), and everything here is exact for that function:

* sampling picks texel :math:`t` with probability :math:`\propto Y_t\,\Omega_t` (luminance
  times solid angle) and then a point uniform *in solid angle* inside it (uniform
  :math:`\cos\theta` over the row, uniform :math:`\phi` over the column), so the solid-angle
  pdf is exactly :math:`p(\omega) = Y_t / \sum_s Y_s\Omega_s` for :math:`\omega` in texel
  :math:`t`; a black map falls back to uniform sphere sampling;
* :meth:`EnvironmentMap.integral` is :math:`\sum_t L_t\Omega_t`;
* :meth:`EnvironmentMap.point_lights` is Debevec's median cut, "A median cut algorithm for
  light probe sampling" (SIGGRAPH 2005 poster / ShaderX4), whose K lights carry exactly the
  map's power.

Rotation about :math:`+y` (``rotation_y`` = :math:`\alpha`) uses ``to_world`` =
:math:`R_y(\alpha)`, right-handed, the same as Mitsuba's
``to_world=mi.ScalarTransform4f().rotate([0, 1, 0], degrees(alpha))``. World azimuth
:math:`\phi_w` sees map azimuth :math:`\phi_w + \alpha`, so a feature of the map at
azimuth :math:`\phi` appears at :math:`\phi - \alpha`; rotating by :math:`2\pi k/W` equals
``torch.roll(radiance, -k, dims=1)``.
"""

from __future__ import annotations

import heapq
import math
import os

import torch
import torch.nn.functional as F

from .._checks import MAX_ENVMAP_HEIGHT, as_float_tensor, check_count, check_real, check_rgb, check_vectors
from ..errors import FileFormatError, ShapeError, ValueRangeError
from ..io.exr import read_exr
from ..sphere.latlong import (
    direction_to_texel,
    latlong_to_direction,
    row_cos_bounds,
    texel_centers,
    texel_solid_angles,
)
from .lights import Light, LightSample, PointLightSet, luminance

__all__ = ["EnvironmentMap", "PointLightSet"]


def _rotation_y(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)


class EnvironmentMap(Light):
    r"""An infinitely distant light from a lat-long radiance map (:math:`W = 2H`).

    Args:
        radiance: (H, W, 3) linear RGB radiance, finite and >= 0, with ``W == 2H`` and
            ``H >= 2``. Stored as a float32 buffer.
        rotation_y: rotation of the map about world :math:`+y` in radians (see the module
            docstring for the sign).
        source: what the radiance came from, used in error messages (e.g. a file name).

    Raises:
        ShapeError: not (H, W, 3), ``W != 2H`` or ``H < 2``.
        ValueRangeError: NaN, Inf or negative texels (the message gives the counts).

    Buffers: ``radiance`` (H, W, 3) float32, ``to_world`` (3, 3) float64, and the float64
    sampling tables ``solid_angle`` (H, W), ``texel_pdf`` (H, W) (solid-angle pdf per
    texel), ``cdf`` (H*W,) and ``cos_bounds`` (H+1,).
    """

    is_delta = False
    is_infinite = True

    def __init__(self, radiance, rotation_y: float = 0.0, source: str = "radiance"):
        super().__init__()
        L = as_float_tensor(radiance, source).detach()
        if L.ndim != 3 or L.shape[-1] != 3:
            raise ShapeError(f"{source}: expected an environment map of shape (H, W, 3); got {tuple(L.shape)}")
        H, W = L.shape[:2]
        if W != 2 * H or H < 2:
            raise ShapeError(f"{source}: expected a lat-long map with W == 2H and H >= 2; got H={H}, W={W}")
        n_nan, n_inf = int(L.isnan().any(-1).sum()), int(L.isinf().any(-1).sum())
        n_neg = int((L < 0).any(-1).sum())
        if n_nan or n_inf or n_neg:
            raise ValueRangeError(
                f"{source}: environment map radiance must be finite and >= 0; found {n_nan} NaN, "
                f"{n_inf} Inf and {n_neg} negative texels (of {H * W})"
            )
        n_big = int((L > torch.finfo(torch.float32).max).any(-1).sum())
        if n_big:
            raise ValueRangeError(
                f"{source}: {n_big} texels exceed the float32 range (max {torch.finfo(torch.float32).max:.4g}, "
                f"largest here {float(L.max()):.4g}) and would become Inf; rescale the map"
            )
        self.source, self.rotation_y = source, check_real(rotation_y, "rotation_y")
        self.register_buffer("radiance", L.to(torch.float32).contiguous())
        self.register_buffer("to_world", _rotation_y(self.rotation_y).to(L.device))
        omega = texel_solid_angles(H, W, device=L.device)
        lum = luminance(self.radiance.double()).clamp_min(0)
        if not bool((lum > 0).any()):  # black map: uniform sphere sampling
            lum = torch.ones_like(lum)
        w = (lum * omega).reshape(-1)
        cdf = w.cumsum(0)
        self.register_buffer("solid_angle", omega)
        self.register_buffer("texel_pdf", lum / cdf[-1])
        self.register_buffer("cdf", cdf / cdf[-1])  # trailing zero-weight texels get exactly 1
        self.register_buffer("cos_bounds", row_cos_bounds(H, device=L.device))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_exr(cls, path: str | os.PathLike, scale: float = 1.0, rotation_y: float = 0.0) -> EnvironmentMap:
        """Load a lat-long OpenEXR file (R, G, B channels) with :func:`torch_brdf.io.exr.read_exr`.

        Args:
            path: the ``.exr`` file.
            scale: factor applied to the radiance (finite, >= 0).
            rotation_y: see the class.
        Raises:
            FileFormatError: missing or unreadable file, or channels other than R, G, B (+A).
            ShapeError / ValueRangeError: as for the constructor; messages name the file.
        """
        scale = check_real(scale, "scale", minimum=0.0)
        src = os.fspath(path)
        # scaled in float64, so a scale that overflows float32 is reported, not turned into Inf
        return cls(read_exr(src).double() * scale, rotation_y=rotation_y, source=f"environment map file {src}")

    @classmethod
    def from_file(cls, path: str | os.PathLike, scale: float = 1.0, rotation_y: float = 0.0) -> EnvironmentMap:
        """Load a lat-long map from OpenEXR (``.exr``) or Radiance RGBE (``.hdr``, ``.pic``), by suffix.

        Raises:
            FileFormatError: unknown suffix, missing or unreadable file; as :meth:`from_exr` otherwise.
        """
        src = os.fspath(path)
        suffix = os.path.splitext(src)[1].lower()
        if suffix == ".exr":
            return cls.from_exr(src, scale, rotation_y)
        if suffix not in (".hdr", ".pic"):
            raise FileFormatError(f"environment map {src}: unknown image type {suffix!r}; known: .exr, .hdr, .pic")
        from ..io.hdr import read_hdr

        scale = check_real(scale, "scale", minimum=0.0)
        return cls(read_hdr(src).double() * scale, rotation_y=rotation_y, source=f"environment map file {src}")

    @classmethod
    def constant(cls, rgb=1.0, height: int = 64) -> EnvironmentMap:
        """A uniform map of radiance ``rgb`` (scalar or 3 values) with ``height`` rows."""
        c = torch.tensor(check_rgb(rgb, "rgb"), dtype=torch.float32)
        h = check_count(height, "height", MAX_ENVMAP_HEIGHT)
        return cls(c.expand(h, 2 * h, 3).clone(), source="constant environment map")

    @classmethod
    def sky(
        cls,
        height: int = 128,
        sun_direction=(0.5, 0.6, -0.62),
        sun_angular_radius_deg: float = 1.5,
        sun_radiance=(3000.0, 2850.0, 2600.0),
        zenith_color=(0.25, 0.45, 0.9),
        horizon_color=(0.8, 0.85, 0.95),
        ground_color=(0.25, 0.22, 0.2),
        supersample: int = 6,
    ) -> EnvironmentMap:
        r"""A procedural sky: zenith-to-horizon gradient, flat ground, and a small bright sun.

        Units are relative (not calibrated). The sky above the horizon is
        :math:`L = L_h + (L_z - L_h)\sqrt{\cos\theta}`, the lower hemisphere is
        ``ground_color``, and each texel adds ``sun_radiance`` times the fraction of the
        texel (``supersample``\ :sup:`2` subsamples, uniform in solid angle) inside the sun
        disk, so the sun's power :math:`\approx L_\mathrm{sun}\,2\pi(1-\cos r)` does not
        depend on the resolution. With the defaults the sun (radius 1.5 deg, about 2 texels
        across at 128 rows) gives roughly as much irradiance as the sky.

        Args:
            height: H (the map is H x 2H).
            sun_direction: 3 numbers, direction towards the sun (normalised here).
            sun_angular_radius_deg: angular radius of the sun disk in degrees.
            sun_radiance: RGB (scalar or 3 values).
            zenith_color: as ``sun_radiance``.
            horizon_color: as ``sun_radiance``.
            ground_color: as ``sun_radiance``.
            supersample: subsamples per texel side for the sun's coverage.
        """
        H, s = check_count(height, "sky: height", MAX_ENVMAP_HEIGHT), check_count(supersample, "sky: supersample", 64)
        sun_angular_radius_deg = check_real(sun_angular_radius_deg, "sky: sun_angular_radius_deg")
        W = 2 * H
        if H < 2 or s < 1 or not 0 < sun_angular_radius_deg < 90:
            raise ValueRangeError(
                f"sky: need height >= 2, supersample >= 1 and 0 < sun radius < 90 deg; got "
                f"{height}, {supersample}, {sun_angular_radius_deg}"
            )
        sun = check_vectors(torch.as_tensor(sun_direction, dtype=torch.float64).reshape(1, 3), "sun_direction")[0]
        if float(sun.norm()) == 0:
            raise ValueRangeError("sky: sun_direction must be non-zero")
        sun = sun / sun.norm()
        names = ("sun_radiance", "zenith_color", "horizon_color", "ground_color")
        values = (sun_radiance, zenith_color, horizon_color, ground_color)
        sun_L, zen, hor, gnd = (
            torch.tensor(check_rgb(v, k), dtype=torch.float64) for k, v in zip(names, values, strict=True)
        )
        y = texel_centers(H, W)[..., 1:2]
        L = torch.where(y >= 0, hor + (zen - hor) * y.clamp_min(0).sqrt(), gnd)
        # sun coverage of the rows near the sun: s x s subsamples per texel, uniform in
        # (cos theta, phi)
        radius = math.radians(sun_angular_radius_deg)
        theta_sun = math.acos(max(-1.0, min(1.0, float(sun[1]))))
        i0 = max(0, math.floor((theta_sun - radius) * H / math.pi) - 1)
        i1 = min(H, math.ceil((theta_sun + radius) * H / math.pi) + 1)
        c = row_cos_bounds(H)[i0 : i1 + 1]
        f = (torch.arange(s, dtype=torch.float64) + 0.5) / s
        cos_t = c[:-1, None] + (c[1:] - c[:-1])[:, None] * f  # (rows, s)
        phi = (torch.arange(W, dtype=torch.float64)[:, None] + f) * (2 * math.pi / W)  # (W, s)
        d = latlong_to_direction(cos_t.clamp(-1, 1).acos()[:, None, :, None], phi[None, :, None, :])
        inside = (d @ sun) >= math.cos(radius)  # (rows, W, s, s)
        L[i0:i1] += inside.double().mean((-1, -2))[..., None] * sun_L
        return cls(L.float(), source="procedural sky")

    def rotated(self, angle_rad: float) -> EnvironmentMap:
        """The map turned by a further ``angle_rad`` about +y (a new module, same radiance)."""
        angle = check_real(angle_rad, "rotated: angle_rad")
        return EnvironmentMap(self.radiance, rotation_y=self.rotation_y + angle, source=self.source)

    def extra_repr(self) -> str:
        H, W = self.radiance.shape[:2]
        return f"{H}x{W}, rotation_y={self.rotation_y:.4g}, source={self.source!r}"

    # ------------------------------------------------------------------ lookups
    @property
    def height(self) -> int:
        return self.radiance.shape[0]

    @property
    def width(self) -> int:
        return self.radiance.shape[1]

    def _texel(self, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        d_map = directions.to(torch.float64) @ self.to_world  # row vectors: R^T d
        return direction_to_texel(d_map, self.height, self.width)

    def eval_miss(self, directions: torch.Tensor) -> torch.Tensor:
        """Radiance along escaping rays, nearest texel (consistent with :meth:`pdf`).

        Args:
            directions: (..., 3) world directions (need not be unit length).
        Returns:
            (..., 3) radiance in ``directions``' dtype.
        """
        d = check_vectors(directions, "directions", ndim=None)
        row, col = self._texel(d)
        return self.radiance[row, col].to(d.dtype)

    def pdf(self, directions: torch.Tensor) -> torch.Tensor:
        """Solid-angle density of :meth:`sample_directions` / :meth:`sample`.

        Args:
            directions: (..., 3) world directions.
        Returns:
            (...) pdf in ``directions``' dtype.
        """
        d = check_vectors(directions, "directions", ndim=None)
        row, col = self._texel(d)
        return self.texel_pdf[row, col].to(d.dtype)

    # ------------------------------------------------------------------ sampling
    def _sample(self, n: int, generator: torch.Generator | None):
        """float64 world directions (n, 3), texel rows and columns (n,)."""
        W = self.width
        u = torch.rand(n, 3, generator=generator, dtype=torch.float64, device=self.cdf.device)
        idx = torch.searchsorted(self.cdf, u[:, 0].contiguous(), right=True).clamp_max(self.cdf.numel() - 1)
        row, col = idx // W, idx % W
        c0, c1 = self.cos_bounds[row], self.cos_bounds[row + 1]
        cos_t = c0 + u[:, 1] * (c1 - c0)
        sin_t = (1 - cos_t * cos_t).clamp_min(0).sqrt()
        phi = (col + u[:, 2]) * (2 * math.pi / W)
        d_map = torch.stack([sin_t * phi.sin(), cos_t, -sin_t * phi.cos()], dim=-1)
        return d_map @ self.to_world.T, row, col

    def sample_directions(
        self, n: int, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float32
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Importance-sample ``n`` directions.

        Returns:
            directions (n, 3) unit world vectors and their solid-angle pdf (n,), in ``dtype``.
        """
        d, row, col = self._sample(int(n), generator)
        return d.to(dtype), self.texel_pdf[row, col].to(dtype)

    def sample(self, points: torch.Tensor, generator: torch.Generator | None = None) -> LightSample:
        """One importance-sampled direction per point (the map is the same from every point).

        Args:
            points: (P, 3) shading positions.
            generator: random source.
        Returns:
            :class:`LightSample` with direction (P, 3), distance ``inf`` (P,), weight =
            radiance / pdf (P, 3) (0 where pdf = 0) and pdf (P,), in ``points.dtype``.
        """
        points = check_vectors(points, "points")
        d, row, col = self._sample(points.shape[0], generator)
        pdf = self.texel_pdf[row, col]
        L = self.radiance[row, col].double()
        weight = torch.where(pdf[:, None] > 0, L / pdf.clamp_min(1e-300)[:, None], torch.zeros_like(L))
        dt = points.dtype
        return LightSample(
            direction=d.to(dt),
            distance=torch.full_like(pdf, math.inf).to(dt),
            weight=weight.to(dt),
            pdf=pdf.to(dt),
        )

    # ------------------------------------------------------------------ exact sums
    def integral(self) -> torch.Tensor:
        r""":math:`\int L\,d\omega = \sum_t L_t\Omega_t` (exact for the piecewise-constant map).

        Returns:
            (3,) float64.
        """
        return (self.radiance.double() * self.solid_angle[..., None]).sum((0, 1))

    def power_estimate(self) -> float:
        return float(luminance(self.integral()))

    def irradiance(self, normals: torch.Tensor, chunk: int = 1 << 22) -> torch.Tensor:
        r"""Dense oracle :math:`E(n) = \sum_t L_t \max(0, n\cdot\omega_t)\,\Omega_t`.

        :math:`\omega_t` are the texel centres (:func:`~torch_brdf.sphere.latlong.texel_centers`).

        Args:
            normals: (N, 3) unit world normals.
            chunk: at most this many normal x texel products at a time.
        Returns:
            (N, 3) irradiance, summed in float64, in ``normals``' dtype.
        """
        n = check_vectors(normals, "normals")
        dirs = texel_centers(self.height, self.width, device=n.device).reshape(-1, 3) @ self.to_world.T
        LO = (self.radiance.double() * self.solid_angle[..., None]).reshape(-1, 3)
        step = max(1, chunk // dirs.shape[0])
        out = [(nb @ dirs.T).clamp_min(0) @ LO for nb in n.double().split(step)]
        return torch.cat(out).to(n.dtype) if out else n.new_zeros(0, 3)

    # ------------------------------------------------------------------ median cut
    def point_lights(self, k: int, dtype: torch.dtype = torch.float32) -> PointLightSet:
        r"""K representative distant point lights by median cut (Debevec 2005).

        Starting from the whole map, the region with the largest energy
        :math:`E = \sum Y\Omega` is split along its longer side, the azimuthal extent being
        measured as :math:`\Delta\phi\,\sin\theta_\mathrm{mid}` against :math:`\Delta\theta`,
        at the texel boundary closest to the energy median (ties broken towards the middle,
        so a single bright texel is isolated in O(log) cuts); single-texel regions are not
        split. Regions never wrap around :math:`\phi = 0`. Region sums come from 2-D prefix
        sums. Each region becomes one light: direction = normalised energy-weighted mean of
        its texel-centre directions (solid-angle weighted if the region is black),
        radiance = :math:`\sum L\Omega / \sum\Omega`, solid angle = :math:`\sum\Omega`, so
        the intensities sum to :meth:`integral`.

        Args:
            k: number of lights, 1 <= k <= H*W.
            dtype: dtype of the returned tensors (computed in float64).
        Returns:
            :class:`PointLightSet` with K lights, deterministic for a given map.
        """
        H, W = self.height, self.width
        if not 1 <= int(k) <= H * W:
            raise ValueRangeError(f"point_lights: k must be in [1, {H * W}] for a {H}x{W} map; got {k}")
        omega = self.solid_angle
        L = self.radiance.double()
        e = luminance(L) * omega
        dirs = texel_centers(H, W, device=omega.device)
        w = torch.where(e.sum() > 0, e, omega)[..., None]  # direction weights
        # prefix sums (H+1, W+1, C) of [energy, L*omega (3), omega, w*dir (3)]
        table = torch.cat([e[..., None], L * omega[..., None], omega[..., None], w * dirs], dim=-1)
        S = F.pad(table.cumsum(0).cumsum(1), (0, 0, 1, 0, 1, 0))
        Se = S[..., 0]

        def energy(r0, r1, c0, c1):
            return float(Se[r1, c1] - Se[r0, c1] - Se[r1, c0] + Se[r0, c0])

        def cut(cum, total, lo, hi):  # boundary in (lo, hi) whose prefix energy is nearest total/2
            s = torch.arange(lo + 1, hi, device=cum.device)
            score = (cum - 0.5 * total).abs()
            tie = score <= score.min() * (1 + 1e-9) + 1e-300
            dist = torch.where(tie, (2 * s - lo - hi).abs().double(), torch.inf)
            return int(s[dist.argmin()])

        heap, done, count = [(-energy(0, H, 0, W), 0, (0, H, 0, W))], [], 1
        while heap and len(heap) + len(done) < k:
            neg_e, _, (r0, r1, c0, c1) = heapq.heappop(heap)
            if (r1 - r0) * (c1 - c0) == 1:
                done.append((r0, r1, c0, c1))
                continue
            mid_theta = 0.5 * (r0 + r1) * math.pi / H
            wide = (c1 - c0) * (2 * math.pi / W) * math.sin(mid_theta) > (r1 - r0) * (math.pi / H)
            if (wide and c1 - c0 > 1) or r1 - r0 == 1:  # cut between columns
                col_e = Se[r1, c0:c1] - Se[r0, c0:c1]  # energy of columns [c0, s)
                s = cut(col_e[1:] - col_e[0], -neg_e, c0, c1)
                parts = ((r0, r1, c0, s), (r0, r1, s, c1))
            else:
                row_e = Se[r0:r1, c1] - Se[r0:r1, c0]
                s = cut(row_e[1:] - row_e[0], -neg_e, r0, r1)
                parts = ((r0, s, c0, c1), (s, r1, c0, c1))
            for p in parts:
                heapq.heappush(heap, (-energy(*p), count, p))
                count += 1
        regions = torch.tensor(done + [p for _, _, p in heap], dtype=torch.long, device=S.device)
        r0, r1, c0, c1 = regions.unbind(-1)
        sums = S[r1, c1] - S[r0, c1] - S[r1, c0] + S[r0, c0]  # (K, 8)
        power, solid = sums[:, 1:4], sums[:, 4]
        d, norm = sums[:, 5:8], sums[:, 5:8].norm(dim=-1, keepdim=True)
        centre = latlong_to_direction(
            (r0 + r1).double()[:, None] * (0.5 * math.pi / H),
            (c0 + c1).double()[:, None] * (math.pi / W),
        )
        d = torch.where(norm > 1e-9 * sums[:, 4:5], d / norm, centre[:, 0])  # symmetric region: its centre
        d = d @ self.to_world.T
        return PointLightSet(d.to(dtype), (power / solid[:, None]).to(dtype), solid.to(dtype))
