r"""Lights: the common interface, a directional light, emissive-triangle area lights, and the
one home of distant light sets (:class:`PointLights` for next-event estimation,
:class:`PointLightSet` from an environment map's median cut, :class:`LightSamples`
importance-sampled from it).

Every light answers two questions for a batch of shading points:

* ``sample(points, generator)`` -> :class:`LightSample`: a direction towards the light
  (unit, world space), the distance to the sampled point (``inf`` for distant lights),
  the solid-angle pdf of that direction (``inf`` for delta lights) and ``weight`` =
  incident radiance / pdf (for delta lights: the irradiance carried along the direction),
  so that a one-sample estimate of :math:`\int L_i f \cos\theta\,d\omega` is
  ``weight * f * cos`` times the shadow test.
* ``eval_miss(directions)``: the radiance seen along rays that leave the scene (non-zero
  only for environment maps; see :mod:`torch_brdf.scene.envmap`).

Environment maps live in :mod:`torch_brdf.scene.envmap`; they implement the same
interface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from .._checks import check_finite, check_rgb, check_vectors
from ..errors import MeshError, SceneError, ShapeError, ValueRangeError


@dataclass(frozen=True)
class LightSample:
    """One light sample per shading point.

    Attributes:
        direction: (P, 3) unit vector from the point towards the light.
        distance: (P,) distance to the sampled light point; ``inf`` for distant lights.
        weight: (P, 3) incident radiance divided by ``pdf`` (irradiance for delta lights).
        pdf: (P,) solid-angle density of ``direction``; ``inf`` for delta lights and 0
            where the sample is invalid (then ``weight`` is 0).
    """

    direction: torch.Tensor
    distance: torch.Tensor
    weight: torch.Tensor
    pdf: torch.Tensor


class Light(nn.Module):
    """Base class of all lights. Subclasses set ``is_delta`` and ``is_infinite``."""

    is_delta: bool = False
    is_infinite: bool = False

    def sample(self, points: torch.Tensor, generator: torch.Generator | None = None) -> LightSample:
        """Sample one direction towards the light per point.

        Args:
            points: (P, 3) shading positions.
            generator: random source (tests pass a seeded one).
        Returns:
            :class:`LightSample` with (P, ...) fields in ``points.dtype``.
        """
        raise NotImplementedError

    def eval_miss(self, directions: torch.Tensor) -> torch.Tensor:
        """Radiance (P, 3) along rays (P, 3) that leave the scene; zero by default."""
        return directions.new_zeros(directions.shape)

    def power_estimate(self) -> float:
        """A rough scalar power used to choose between lights (luminance-weighted)."""
        raise NotImplementedError


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    """Rec. 709 / sRGB luminance of linear RGB ``(..., 3)`` -> ``(...)``."""
    w = torch.tensor([0.2126, 0.7152, 0.0722], dtype=rgb.dtype, device=rgb.device)
    return rgb @ w


class DirectionalLight(Light):
    """A distant light from one direction (a delta light, e.g. a sun without a disk).

    Args:
        direction: 3 numbers, the direction *towards* the light (normalised here).
        irradiance: RGB irradiance on a surface facing the light (scalar or 3 values).
    """

    is_delta = True
    is_infinite = True

    def __init__(self, direction, irradiance):
        super().__init__()
        d = check_vectors(torch.as_tensor(direction, dtype=torch.float64).reshape(1, 3), "direction")
        n = float(d.norm())
        if n == 0.0:
            raise ValueRangeError("DirectionalLight direction must be non-zero")
        self.register_buffer("direction", (d[0] / n).to(torch.float32))
        self.register_buffer("irradiance", torch.tensor(check_rgb(irradiance, "irradiance"), dtype=torch.float32))

    def sample(self, points, generator=None):
        p = points.shape[0]
        d = self.direction.to(points.dtype).expand(p, 3)
        return LightSample(
            direction=d,
            distance=points.new_full((p,), float("inf")),
            weight=self.irradiance.to(points.dtype).expand(p, 3),
            pdf=points.new_full((p,), float("inf")),
        )

    def power_estimate(self) -> float:
        return float(luminance(self.irradiance.double()))


class PointLight(Light):
    r"""An isotropic point light at a position (a delta light): irradiance
    :math:`I\cos\theta / r^2` on a surface at distance :math:`r`.

    Args:
        position: 3 numbers.
        intensity: RGB radiant intensity in W/sr (scalar or 3 values), Mitsuba's ``point``
            ``intensity``.
    """

    is_delta = True
    is_infinite = False

    def __init__(self, position, intensity):
        super().__init__()
        p = check_vectors(torch.as_tensor(position, dtype=torch.float64).reshape(1, 3), "position")
        self.register_buffer("position", p[0].to(torch.float32))
        self.register_buffer("intensity", torch.tensor(check_rgb(intensity, "intensity"), dtype=torch.float32))

    def sample(self, points, generator=None):
        d = self.position.to(points.dtype) - points
        dist = d.norm(dim=-1)
        ok = dist > 0
        w = d / dist.clamp_min(torch.finfo(points.dtype).tiny)[:, None]
        irr = self.intensity.to(points.dtype) / (dist * dist).clamp_min(1e-30)[:, None]
        weight = torch.where(ok[:, None], irr, 0.0)
        return LightSample(
            direction=w,
            distance=dist,
            weight=weight,
            pdf=torch.where(ok, float("inf"), 0.0).to(points.dtype),
        )

    def power_estimate(self) -> float:
        return float(luminance(self.intensity.double())) * 4.0 * float(np.pi)


class PointLights(Light):
    """K distant point lights, e.g. an environment map's median-cut set
    (:meth:`~torch_brdf.scene.envmap.EnvironmentMap.point_lights`); next-event estimation picks
    one per point in proportion to its luminance (``weight`` = intensity / selection probability).

    Args:
        directions: (K, 3) unit directions towards the lights.
        intensity: (K, 3) RGB irradiance each light gives a surface facing it.
    """

    is_delta = True
    is_infinite = True

    def __init__(self, directions: torch.Tensor, intensity: torch.Tensor):
        super().__init__()
        self.register_buffer("directions", directions.float())
        self.register_buffer("intensity", intensity.float())
        p = luminance(self.intensity).clamp_min(0)
        if not float(p.sum()) > 0:
            p = torch.ones_like(p)
        self.register_buffer("prob", p / p.sum())

    def sample(self, points, generator=None):
        n = points.shape[0]
        k = torch.multinomial(self.prob, n, replacement=True, generator=generator) if n else torch.zeros(0).long()
        w = self.intensity[k] / self.prob[k, None]
        d = self.directions[k].to(points.dtype)
        inf = torch.full((n,), math.inf, dtype=points.dtype)
        return LightSample(d, inf, w.to(points.dtype), inf)

    def power_estimate(self) -> float:
        return float(luminance(self.intensity).sum())


@dataclass(frozen=True)
class PointLightSet:
    r"""K distant point lights standing in for a map (see :meth:`EnvironmentMap.point_lights`).

    Attributes:
        directions: (K, 3) unit directions towards the lights (world space).
        radiance: (K, 3) mean RGB radiance of each light's region of the map.
        solid_angle: (K,) solid angle of each region (sums to :math:`4\pi`).
    """

    directions: torch.Tensor
    radiance: torch.Tensor
    solid_angle: torch.Tensor

    @property
    def intensity(self) -> torch.Tensor:
        """(K, 3) radiance x solid angle: the region's power (irradiance at normal incidence)."""
        return self.radiance * self.solid_angle[:, None]

    def irradiance(self, normals: torch.Tensor) -> torch.Tensor:
        r"""Irradiance :math:`\sum_k I_k \max(0, n\cdot\omega_k)`: unit normals (N, 3) -> (N, 3)."""
        n = check_vectors(normals, "normals")
        cos = (n @ self.directions.to(n).T).clamp_min(0)
        return cos @ self.intensity.to(n)

    def as_light(self) -> PointLights:
        """The set as a :class:`Light` for next-event estimation."""
        return PointLights(self.directions, self.intensity)

    def to(self, *args, **kwargs) -> PointLightSet:
        """A copy with every tensor moved/cast by ``Tensor.to(*args, **kwargs)``."""
        return PointLightSet(*(t.to(*args, **kwargs) for t in (self.directions, self.radiance, self.solid_angle)))


@dataclass(frozen=True)
class LightSamples:
    """S distant light directions shared by every pixel.

    Attributes:
        directions: (S, 3) unit world directions towards the light, float64.
        weight: (S, 3) :math:`L(\\omega_s) / (S\\,\\mathrm{pdf}(\\omega_s))`, float64 (RGB).
    """

    directions: torch.Tensor
    weight: torch.Tensor

    def __post_init__(self):
        d, w = self.directions, self.weight
        if d.ndim != 2 or d.shape[-1] != 3 or w.shape != (d.shape[0], 3) or d.shape[0] < 1:
            raise ShapeError(f"Expected directions (S, 3) and weight (S, 3); got {tuple(d.shape)}, {tuple(w.shape)}")
        check_finite(d, "light directions")
        check_finite(w, "light weights")

    @property
    def count(self) -> int:
        return self.directions.shape[0]

    def as_light(self) -> PointLights:
        """The samples as a :class:`Light` for next-event estimation (``weight`` as intensities)."""
        return PointLights(self.directions, self.weight)

    @classmethod
    def from_environment(
        cls,
        env: Light,
        count: int = 1024,
        generator: torch.Generator | None = None,
    ) -> LightSamples:
        """Importance-sample ``count`` directions from ``env`` (luminance x solid angle).

        Args:
            env: the :class:`~torch_brdf.scene.envmap.EnvironmentMap` (rotated maps sample their
                rotated radiance).
            count: S >= 1 (a power of two if visibility cuts will be used).
            generator: random source (seed it for reproducible records).
        """
        if not callable(getattr(env, "sample_directions", None)):  # an EnvironmentMap (it imports this module)
            raise SceneError(f"expected an EnvironmentMap; got {type(env).__name__}")
        if int(count) < 1:
            raise ValueRangeError(f"light sample count must be >= 1; got {count}")
        d, pdf = env.sample_directions(int(count), generator=generator, dtype=torch.float64)
        L = env.eval_miss(d)
        w = torch.where(pdf[:, None] > 0, L / (pdf[:, None].clamp_min(1e-300) * int(count)), torch.zeros_like(L))
        return cls(d, w)


class AreaLight(Light):
    r"""Emissive triangles with constant radiance, emitting from their front side.

    The front side is the one the counter-clockwise normal :math:`(v_1-v_0)\times(v_2-v_0)`
    points to. Sampling picks a triangle with probability proportional to its area and a
    uniform point on it, so the area pdf is ``1 / total_area``; the solid-angle pdf is
    :math:`p_A\,r^2/|\cos\theta_l|`.

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) vertex indices.
        radiance: RGB emitted radiance (scalar or 3 values).
        object_id: the scene object these triangles belong to (-1 if none), so that a
            renderer can recognise hits on the emitter.
    """

    def __init__(self, vertices, faces, radiance, object_id: int = -1):
        super().__init__()
        v = check_vectors(torch.as_tensor(np.asarray(vertices), dtype=torch.float64), "vertices")
        f = torch.as_tensor(np.asarray(faces), dtype=torch.int64)
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
            raise MeshError(f"AreaLight faces must have shape (F, 3) with F > 0; got {tuple(f.shape)}")
        tri = v[f]  # (F, 3, 3)
        cross = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area = 0.5 * cross.norm(dim=-1)
        if not bool((area > 0).any()):
            raise MeshError("AreaLight has no triangle with non-zero area")
        keep = area > 0
        tri, cross, area = tri[keep], cross[keep], area[keep]
        self.register_buffer("triangles", tri.to(torch.float32))
        self.register_buffer("normals", (cross / (2 * area[:, None])).to(torch.float32))
        self.register_buffer("cdf", torch.cumsum(area / area.sum(), 0).to(torch.float64))
        self.total_area = float(area.sum())
        self.register_buffer("radiance", torch.tensor(check_rgb(radiance, "radiance"), dtype=torch.float32))
        self.object_id = int(object_id)

    def sample_points(self, n: int, generator=None, dtype=torch.float32, u: torch.Tensor | None = None):
        """Uniform points on the emitter: (n, 3) positions and (n, 3) normals. ``u`` (n, 3)
        float64: the uniforms to use (column 0 picks the triangle by area, 1 and 2 the point on
        it) instead of drawing them from ``generator``."""
        if u is None:
            u = torch.rand(n, 3, generator=generator, dtype=torch.float64)
        idx = self.triangle_of(u[:, 0])
        s = u[:, 1].sqrt()
        b1, b2 = 1 - s, u[:, 2] * s  # uniform barycentrics
        tri = self.triangles[idx].to(torch.float64)
        p = tri[:, 0] + b1[:, None] * (tri[:, 1] - tri[:, 0]) + b2[:, None] * (tri[:, 2] - tri[:, 0])
        return p.to(dtype), self.normals[idx].to(dtype)

    def triangle_of(self, u0: torch.Tensor) -> torch.Tensor:
        """The triangle (n,) int64 that uniforms ``u0`` (n,) float64 pick by area (the last one
        also takes any rounding gap of the cdf below 1)."""
        return torch.searchsorted(self.cdf, u0.contiguous(), right=True).clamp_max(len(self.cdf) - 1)

    def sample(self, points, generator=None, u: torch.Tensor | None = None):
        """:meth:`Light.sample`; ``u`` as for :meth:`sample_points`."""
        y, n_l = self.sample_points(points.shape[0], generator, dtype=points.dtype, u=u)
        d = y - points
        dist2 = (d * d).sum(-1)
        dist = dist2.sqrt()
        w = d / dist.clamp_min(torch.finfo(points.dtype).tiny)[:, None]
        cos_l = -(w * n_l).sum(-1)  # > 0 when the point sees the front side
        valid = (cos_l > 0) & (dist > 0)
        pdf = torch.where(valid, dist2 / (cos_l.clamp_min(1e-12) * self.total_area), torch.zeros_like(dist))
        weight = torch.where(
            valid[:, None], self.radiance.to(points.dtype) / pdf.clamp_min(1e-30)[:, None], torch.zeros_like(d)
        )
        return LightSample(direction=w, distance=dist, weight=weight, pdf=pdf)

    def emitted(self, directions, normals):
        """Radiance (P, 3) leaving the emitter towards ``-directions`` at points with ``normals``.

        Args:
            directions: (P, 3) directions of the rays that hit the emitter.
            normals: (P, 3) geometric normals at the hits.
        """
        front = (directions * normals).sum(-1) < 0
        return torch.where(front[:, None], self.radiance.to(directions.dtype), directions.new_zeros(()))

    def power_estimate(self) -> float:
        return float(luminance(self.radiance.double())) * self.total_area * float(np.pi)
