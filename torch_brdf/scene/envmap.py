r"""Environment maps: a distant light given by a lat-long radiance map.

The map layout and the direction convention are those of :mod:`torch_brdf.sphere.latlong`
(world :math:`+y` up, row 0 the zenith, :math:`\phi = \operatorname{atan2}(x, -z)`), i.e.
Mitsuba 3's ``envmap`` emitter with an identity ``to_world``. Two lookups exist:

``lookup="bilinear"`` (the default, Mitsuba 3's ``envmap``)
    Entry ``(i, j)`` is the radiance at :math:`\theta_i = i\pi/(H-1)`,
    :math:`\phi_j = (j+\tfrac12)\,2\pi/W`, interpolated bilinearly in :math:`(\phi,\theta)`
    (:func:`~torch_brdf.sphere.latlong.bilinear_lookup`), so a map loaded here and in Mitsuba
    lights a scene identically. Sampling is Mitsuba's too: with
    :math:`g_{ij} = Y_{ij}\sin\theta_i` (luminance times the row's sine), a cell between four
    nodes is picked with probability :math:`\propto` the mean of its corners, then a point in it
    from the bilinear density of :math:`g` (two inverted linear marginals), so the solid-angle
    pdf is :math:`p(\omega) = \tilde g(u, v) / (Z\,2\pi^2\sin\theta)` with :math:`\tilde g` the
    bilinear interpolant and :math:`Z = \int\!\!\int \tilde g\,du\,dv`.
    :meth:`EnvironmentMap.integral` is :math:`\sum L_{ij}\Omega_{ij}` with the exact hat
    weights of :func:`~torch_brdf.sphere.latlong.node_solid_angles`.

``lookup="nearest"`` (piecewise constant per texel, texel-centred rows)
    Everything is exact for that function: sampling picks texel :math:`t` with probability
    :math:`\propto Y_t\,\Omega_t` and then a point uniform in solid angle inside it, so
    :math:`p(\omega) = Y_t / \sum_s Y_s\Omega_s`; :meth:`EnvironmentMap.integral` is
    :math:`\sum_t L_t\Omega_t`.

In both, a black map samples as if it were a constant one, and
:meth:`EnvironmentMap.point_lights` is Debevec's median cut, "A median cut algorithm for
light probe sampling" (SIGGRAPH 2005 poster / ShaderX4), over the entries with their solid
angles, whose K lights carry exactly :meth:`EnvironmentMap.integral`.

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
    bilinear_lookup,
    direction_to_latlong,
    direction_to_texel,
    latlong_to_direction,
    node_directions,
    node_solid_angles,
    row_cos_bounds,
    texel_centers,
    texel_solid_angles,
)
from .lights import Light, LightSample, PointLightSet, luminance

__all__ = ["LOOKUPS", "EnvironmentMap", "PointLightSet"]

LOOKUPS = ("bilinear", "nearest")


def _sample_linear(a: torch.Tensor, b: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    r"""Invert the CDF of the density :math:`\propto a(1-x) + bx` on [0, 1] (a, b >= 0).

    :math:`x = (a - s)/(a - b)` with :math:`s = \sqrt{(1-u)a^2 + ub^2}`, written as
    :math:`u(a+b)/(a+s)` so that it stays accurate when :math:`a \approx b`; ``u`` where both vanish.
    """
    s = ((1 - u) * a * a + u * b * b).sqrt()
    den = a + s
    x = torch.where(den > 0, u * (a + b) / den.clamp_min(1e-300), u)
    return x.clamp(0, 1)


def _node_coverage(H: int, s: int, sun: torch.Tensor, radius: float) -> torch.Tensor:
    r""":math:`\int\Lambda_{ij}\,1_\mathrm{sun}\,d\omega / \Omega_{ij}` for the nodes of an H x 2H map.

    Each cell between four nodes near the sun gets ``s x s`` midpoint subsamples in
    :math:`(\theta, \phi)`, weighted by their solid angle and spread on the corners with the
    bilinear weights. Returns (H, 2H) float64.
    """
    W = 2 * H
    delta = math.pi / (H - 1)
    theta_sun = math.acos(max(-1.0, min(1.0, float(sun[1]))))
    i0 = max(0, math.floor((theta_sun - radius) / delta) - 1)
    i1 = min(H - 1, math.ceil((theta_sun + radius) / delta) + 1)  # cells i0 .. i1-1
    f = (torch.arange(s, dtype=torch.float64) + 0.5) / s
    theta = (torch.arange(i0, i1, dtype=torch.float64)[:, None] + f) * delta  # (rows, s)
    phi = (torch.arange(W, dtype=torch.float64)[:, None] + 0.5 + f) * (2 * math.pi / W)  # (W, s)
    d = latlong_to_direction(theta[:, None, :, None], phi[None, :, None, :])  # (rows, W, s, s, 3)
    area = (theta.sin() * delta / s * (2 * math.pi / W) / s)[:, None, :, None]
    a = ((d @ sun) >= math.cos(radius)).double() * area  # (rows, W, s, s)
    fy, fx = f[:, None], f[None, :]
    acc = torch.zeros(H, W, dtype=torch.float64)
    rows = torch.arange(i0, i1)
    for wy, dr in ((1 - fy, 0), (fy, 1)):
        for wx, dc in ((1 - fx, 0), (fx, 1)):
            part = (a * (wy * wx)).sum((-1, -2))  # (rows, W)
            acc[rows + dr] += torch.roll(part, dc, dims=1)
    return acc / node_solid_angles(H, W)


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
        lookup: ``"bilinear"`` (Mitsuba 3's reading, the default) or ``"nearest"`` (piecewise
            constant texels); see the module docstring.

    Raises:
        ShapeError: not (H, W, 3), ``W != 2H`` or ``H < 2``.
        ValueRangeError: NaN, Inf or negative texels (the message gives the counts), or an
            unknown ``lookup``.

    Buffers: ``radiance`` (H, W, 3) float32, ``to_world`` (3, 3) float64, ``solid_angle``
    (H, W) float64 (what each entry stands for: texel or node solid angles) and the float64
    sampling tables: nearest: ``texel_pdf`` (H, W) (solid-angle pdf per texel), ``cdf``
    (H*W,) and ``cos_bounds`` (H+1,); bilinear: ``node_density`` (H, W) (:math:`g/(Z\,2\pi^2)`,
    so the pdf is its bilinear interpolant over :math:`\sin\theta`) and ``cdf`` ((H-1)*W,)
    over the cells between nodes.
    """

    is_delta = False
    is_infinite = True

    def __init__(self, radiance, rotation_y: float = 0.0, source: str = "radiance", lookup: str = "bilinear"):
        super().__init__()
        if lookup not in LOOKUPS:
            raise ValueRangeError(f"{source}: lookup must be one of {list(LOOKUPS)}; got {lookup!r}")
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
        self.lookup = lookup
        self.bilinear = lookup == "bilinear"  # a plain attribute: part of the scene's content key
        self.register_buffer("radiance", L.to(torch.float32).contiguous())
        self.register_buffer("to_world", _rotation_y(self.rotation_y).to(L.device))
        lum = luminance(self.radiance.double()).clamp_min(0)
        if not bool((lum > 0).any()):  # black map: sampled as a constant one
            lum = torch.ones_like(lum)
        if self.bilinear:
            self._init_bilinear(lum)
            return
        omega = texel_solid_angles(H, W, device=L.device)
        w = (lum * omega).reshape(-1)
        cdf = w.cumsum(0)
        self.register_buffer("solid_angle", omega)
        self.register_buffer("texel_pdf", lum / cdf[-1])
        self.register_buffer("cdf", cdf / cdf[-1])  # trailing zero-weight texels get exactly 1
        self.register_buffer("cos_bounds", row_cos_bounds(H, device=L.device))

    def _init_bilinear(self, lum: torch.Tensor) -> None:
        """Mitsuba's ``Hierarchical2D`` over :math:`g = Y\\sin\theta` as flat tables."""
        H, W = lum.shape
        sin_t = torch.sin(torch.arange(H, dtype=torch.float64, device=lum.device) * (math.pi / (H - 1)))
        sin_t[0], sin_t[-1] = 0.0, 0.0
        g = lum * sin_t[:, None]
        g1 = torch.roll(g, -1, dims=1)  # the next column, periodic
        cell = 0.25 * (g[:-1] + g1[:-1] + g[1:] + g1[1:])  # (H-1, W): the mean of the corners
        cdf = cell.reshape(-1).cumsum(0)
        z = float(cdf[-1]) / ((H - 1) * W)  # the integral of the interpolant over the unit square
        self.register_buffer("solid_angle", node_solid_angles(H, W, device=lum.device))
        self.register_buffer("node_density", g / (z * 2 * math.pi**2))
        self.register_buffer("cdf", cdf / cdf[-1])

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_exr(
        cls, path: str | os.PathLike, scale: float = 1.0, rotation_y: float = 0.0, lookup: str = "bilinear"
    ) -> EnvironmentMap:
        """Load a lat-long OpenEXR file (R, G, B channels) with :func:`torch_brdf.io.exr.read_exr`.

        Args:
            path: the ``.exr`` file.
            scale: factor applied to the radiance (finite, >= 0).
            rotation_y: see the class.
            lookup: see the class.
        Raises:
            FileFormatError: missing or unreadable file, or channels other than R, G, B (+A).
            ShapeError / ValueRangeError: as for the constructor; messages name the file.
        """
        scale = check_real(scale, "scale", minimum=0.0)
        src = os.fspath(path)
        # scaled in float64, so a scale that overflows float32 is reported, not turned into Inf
        return cls(
            read_exr(src).double() * scale, rotation_y=rotation_y, source=f"environment map file {src}", lookup=lookup
        )

    @classmethod
    def from_file(
        cls, path: str | os.PathLike, scale: float = 1.0, rotation_y: float = 0.0, lookup: str = "bilinear"
    ) -> EnvironmentMap:
        """Load a lat-long map from OpenEXR (``.exr``) or Radiance RGBE (``.hdr``, ``.pic``), by suffix.

        Raises:
            FileFormatError: unknown suffix, missing or unreadable file; as :meth:`from_exr` otherwise.
        """
        src = os.fspath(path)
        suffix = os.path.splitext(src)[1].lower()
        if suffix == ".exr":
            return cls.from_exr(src, scale, rotation_y, lookup)
        if suffix not in (".hdr", ".pic"):
            raise FileFormatError(f"environment map {src}: unknown image type {suffix!r}; known: .exr, .hdr, .pic")
        from ..io.hdr import read_hdr

        scale = check_real(scale, "scale", minimum=0.0)
        return cls(
            read_hdr(src).double() * scale, rotation_y=rotation_y, source=f"environment map file {src}", lookup=lookup
        )

    @classmethod
    def constant(cls, rgb=1.0, height: int = 64, lookup: str = "bilinear") -> EnvironmentMap:
        """A uniform map of radiance ``rgb`` (scalar or 3 values) with ``height`` rows."""
        c = torch.tensor(check_rgb(rgb, "rgb"), dtype=torch.float32)
        h = check_count(height, "height", MAX_ENVMAP_HEIGHT)
        return cls(c.expand(h, 2 * h, 3).clone(), source="constant environment map", lookup=lookup)

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
        lookup: str = "bilinear",
    ) -> EnvironmentMap:
        r"""A procedural sky: zenith-to-horizon gradient, flat ground, and a small bright sun.

        Units are relative (not calibrated). The sky above the horizon is
        :math:`L = L_h + (L_z - L_h)\sqrt{\cos\theta}`, the lower hemisphere is
        ``ground_color``, and each texel adds ``sun_radiance`` times the fraction of the
        texel (``supersample``\ :sup:`2` subsamples, uniform in solid angle) inside the sun
        disk, so the sun's power :math:`\approx L_\mathrm{sun}\,2\pi(1-\cos r)` does not
        depend on the resolution. With the defaults the sun (radius 1.5 deg, about 2 texels
        across at 128 rows) gives roughly as much irradiance as the sky. With the bilinear
        lookup the sky is sampled at the nodes and each node adds ``sun_radiance`` times the
        hat-weighted fraction of its footprint inside the disk (:math:`\int\Lambda\,1_\mathrm{sun}
        \,d\omega / \Omega`), which keeps the sun's power exact for the interpolated map too.

        Args:
            height: H (the map is H x 2H).
            sun_direction: 3 numbers, direction towards the sun (normalised here).
            sun_angular_radius_deg: angular radius of the sun disk in degrees.
            sun_radiance: RGB (scalar or 3 values).
            zenith_color: as ``sun_radiance``.
            horizon_color: as ``sun_radiance``.
            ground_color: as ``sun_radiance``.
            supersample: subsamples per texel side for the sun's coverage.
            lookup: see the class.
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
        y = (node_directions(H, W) if lookup == "bilinear" else texel_centers(H, W))[..., 1:2]
        L = torch.where(y >= 0, hor + (zen - hor) * y.clamp_min(0).sqrt(), gnd)
        radius = math.radians(sun_angular_radius_deg)
        if lookup == "bilinear":
            L += _node_coverage(H, s, sun, radius)[..., None] * sun_L
            return cls(L.float(), source="procedural sky", lookup=lookup)
        # sun coverage of the rows near the sun: s x s subsamples per texel, uniform in
        # (cos theta, phi)
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
        return cls(L.float(), source="procedural sky", lookup=lookup)

    def rotated(self, angle_rad: float) -> EnvironmentMap:
        """The map turned by a further ``angle_rad`` about +y (a new module, same radiance)."""
        angle = check_real(angle_rad, "rotated: angle_rad")
        return EnvironmentMap(self.radiance, rotation_y=self.rotation_y + angle, source=self.source, lookup=self.lookup)

    def extra_repr(self) -> str:
        H, W = self.radiance.shape[:2]
        return f"{H}x{W}, rotation_y={self.rotation_y:.4g}, lookup={self.lookup}, source={self.source!r}"

    # ------------------------------------------------------------------ lookups
    @property
    def height(self) -> int:
        return self.radiance.shape[0]

    @property
    def width(self) -> int:
        return self.radiance.shape[1]

    def _to_map(self, directions: torch.Tensor) -> torch.Tensor:
        return directions.to(torch.float64) @ self.to_world  # row vectors: R^T d

    def _texel(self, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return direction_to_texel(self._to_map(directions), self.height, self.width)

    def entry_directions(self) -> torch.Tensor:
        """World direction of every map entry: texel centres (nearest) or nodes (bilinear).

        Returns:
            (H, W, 3) float64 unit vectors; ``solid_angle`` is what each one stands for.
        """
        H, W = self.height, self.width
        d = node_directions(H, W) if self.bilinear else texel_centers(H, W)
        return d.to(self.to_world.device) @ self.to_world.T

    def eval_miss(self, directions: torch.Tensor) -> torch.Tensor:
        """Radiance along escaping rays, bilinear or nearest texel as ``lookup`` says.

        Args:
            directions: (..., 3) world directions (need not be unit length).
        Returns:
            (..., 3) radiance in ``directions``' dtype.
        """
        d = check_vectors(directions, "directions", ndim=None)
        if self.bilinear:
            return bilinear_lookup(self.radiance.double(), self._to_map(d)).to(d.dtype)
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
        return self._pdf64(d).to(d.dtype)

    def _pdf64(self, d: torch.Tensor) -> torch.Tensor:
        if not self.bilinear:
            row, col = self._texel(d)
            return self.texel_pdf[row, col]
        dm = self._to_map(d)
        g = bilinear_lookup(self.node_density, dm)
        sin_t = direction_to_latlong(dm)[0].sin()
        # g vanishes on the poles' rows as fast as sin(theta): 0 only exactly on a pole
        return torch.where(sin_t > 0, g / sin_t.clamp_min(1e-300), torch.zeros_like(g))

    # ------------------------------------------------------------------ sampling
    def _sample(self, n: int, generator: torch.Generator | None):
        """float64 world directions (n, 3) and their solid-angle pdf (n,)."""
        H, W = self.height, self.width
        u = torch.rand(n, 3, generator=generator, dtype=torch.float64, device=self.cdf.device)
        idx = torch.searchsorted(self.cdf, u[:, 0].contiguous(), right=True).clamp_max(self.cdf.numel() - 1)
        row, col = idx // W, idx % W
        if self.bilinear:
            g, col1 = self.node_density, (col + 1) % W
            g00, g01, g10, g11 = g[row, col], g[row, col1], g[row + 1, col], g[row + 1, col1]
            fy = _sample_linear(g00 + g01, g10 + g11, u[:, 1])
            fx = _sample_linear((1 - fy) * g00 + fy * g10, (1 - fy) * g01 + fy * g11, u[:, 2])
            theta = (row + fy) * (math.pi / (H - 1))
            phi = (col + 0.5 + fx) * (2 * math.pi / W)
            d = latlong_to_direction(theta, phi) @ self.to_world.T
            return d, self._pdf64(d)
        c0, c1 = self.cos_bounds[row], self.cos_bounds[row + 1]
        cos_t = c0 + u[:, 1] * (c1 - c0)
        sin_t = (1 - cos_t * cos_t).clamp_min(0).sqrt()
        phi = (col + u[:, 2]) * (2 * math.pi / W)
        d_map = torch.stack([sin_t * phi.sin(), cos_t, -sin_t * phi.cos()], dim=-1)
        return d_map @ self.to_world.T, self.texel_pdf[row, col]

    def sample_directions(
        self, n: int, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float32
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Importance-sample ``n`` directions.

        Returns:
            directions (n, 3) unit world vectors and their solid-angle pdf (n,), in ``dtype``.
        """
        d, pdf = self._sample(int(n), generator)
        return d.to(dtype), pdf.to(dtype)

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
        d, pdf = self._sample(points.shape[0], generator)
        L = self.eval_miss(d)
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
        r""":math:`\int L\,d\omega = \sum_t L_t\Omega_t` (exact for either lookup, with its ``solid_angle``).

        Returns:
            (3,) float64.
        """
        return (self.radiance.double() * self.solid_angle[..., None]).sum((0, 1))

    def power_estimate(self) -> float:
        return float(luminance(self.integral()))

    def irradiance(self, normals: torch.Tensor, chunk: int = 1 << 22) -> torch.Tensor:
        r"""Dense oracle :math:`E(n) = \sum_t L_t \max(0, n\cdot\omega_t)\,\Omega_t`.

        :math:`\omega_t` are the entries' directions (:meth:`entry_directions`), :math:`\Omega_t`
        their ``solid_angle``.

        Args:
            normals: (N, 3) unit world normals.
            chunk: at most this many normal x texel products at a time.
        Returns:
            (N, 3) irradiance, summed in float64, in ``normals``' dtype.
        """
        n = check_vectors(normals, "normals")
        dirs = self.entry_directions().to(n.device).reshape(-1, 3)
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
        dirs = (node_directions if self.bilinear else texel_centers)(H, W, device=omega.device)
        # row spacing and the polar angle of row r's entry (nodes sit on rows, texels between)
        dt, t0 = (math.pi / (H - 1), 0.0) if self.bilinear else (math.pi / H, 0.5 * math.pi / H)
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
            mid_theta = t0 + 0.5 * (r0 + r1 - 1) * dt
            wide = (c1 - c0) * (2 * math.pi / W) * math.sin(mid_theta) > (r1 - r0) * dt
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
            t0 + (r0 + r1 - 1).double()[:, None] * (0.5 * dt),
            (c0 + c1).double()[:, None] * (math.pi / W),
        )
        d = torch.where(norm > 1e-9 * sums[:, 4:5], d / norm, centre[:, 0])  # symmetric region: its centre
        d = d @ self.to_world.T
        return PointLightSet(d.to(dtype), (power / solid[:, None]).to(dtype), solid.to(dtype))
