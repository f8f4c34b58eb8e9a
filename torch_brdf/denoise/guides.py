r"""Guide buffers: what a denoiser may look at besides the noisy image.

Per pixel, from the camera's primary ray through the pixel *centre* (the precomputation's
jittered rays average around it): the first-hit shading normal (facing the camera), the
hit position and its distance from the eye, the object id (-1 on a miss) and a
material-independent albedo proxy. The proxy is a constant grey per object id (0 on a
miss), so that a denoiser sees object boundaries in it but never a material: a BRDF edit
cannot change a guide, which is what keeps every denoised edit exact (the filter is a fixed
function of the guides).

Glossy surfaces show what their mirror direction sees, and nothing above tells a filter
where that changes (a flat glossy wall has one normal and one plane), so two more guides
come from the mirror ray of each first hit (geometry and lights only, no material): the
object it hits (-1: it escapes; -2: no first hit) and the light it sees directly
(the environment where it escapes, an emitter's front where it hits one). And since a
glossy lobe's highlight is a function of the half-vector angle to the light, the cosine of
that angle for the scene's most powerful light (an area light's centroid, a directional
light, an environment map's brightest texel), :math:`n\cdot h` with
:math:`h = (v + l)/\lVert v + l\rVert`, is a guide too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import FileFormatError, ShapeError
from ..transport.pathtrace import emission_seen

GUIDE_NAMES = ("normal", "position", "depth", "object_id", "albedo", "mirror_id", "mirror_radiance", "light_cos_h")
GUIDE_VERSION = 1


@dataclass(frozen=True)
class GuideBuffers:
    """Per-pixel guides of one view (row-major, row 0 at the top).

    Attributes:
        normal: (H, W, 3) float32 unit shading normal facing the eye; 0 on a miss.
        position: (H, W, 3) float32 world position of the first hit; 0 on a miss.
        depth: (H, W) float32 distance from the eye; ``inf`` on a miss.
        object_id: (H, W) int64 scene object index; -1 on a miss.
        albedo: (H, W, 3) float32 material-independent albedo proxy in [0.35, 0.95] per
            object (a function of the object id only); 0 on a miss.
        mirror_id: (H, W) int64 object hit by the mirror ray of the first hit; -1 when it
            escapes, -2 where the pixel sees no surface.
        mirror_radiance: (H, W, 3) float32 emitted radiance the mirror ray sees directly.
        light_cos_h: (H, W) float32 cosine of the half-vector angle to the brightest light
            (0 where the pixel sees no surface).
        pixel_angle: the angle one pixel subtends at the image centre (radians), to turn
            depths into pixel footprints.
    """

    normal: torch.Tensor
    position: torch.Tensor
    depth: torch.Tensor
    object_id: torch.Tensor
    albedo: torch.Tensor
    mirror_id: torch.Tensor
    mirror_radiance: torch.Tensor
    light_cos_h: torch.Tensor
    pixel_angle: float

    def __post_init__(self):
        h, w = self.object_id.shape
        for name, shape in (
            ("normal", (h, w, 3)),
            ("position", (h, w, 3)),
            ("depth", (h, w)),
            ("albedo", (h, w, 3)),
        ) + (
            ("mirror_id", (h, w)),
            ("mirror_radiance", (h, w, 3)),
            ("light_cos_h", (h, w)),
        ):
            if tuple(getattr(self, name).shape) != shape:
                raise ShapeError(f"guide {name!r}: expected shape {shape}; got {tuple(getattr(self, name).shape)}")

    @property
    def height(self) -> int:
        return self.object_id.shape[0]

    @property
    def width(self) -> int:
        return self.object_id.shape[1]

    def to_arrays(self, prefix: str = "guide_") -> dict[str, np.ndarray]:
        """numpy arrays for the array codec (:func:`torch_brdf.io.arrays.save_arrays`)."""
        out = {prefix + k: getattr(self, k).numpy() for k in GUIDE_NAMES}
        out[prefix + "meta"] = np.array([self.pixel_angle, GUIDE_VERSION], dtype=np.float64)
        return out

    @classmethod
    def from_arrays(cls, arrays: dict, prefix: str = "guide_") -> GuideBuffers | None:
        """The guides stored by :meth:`to_arrays`, or None when ``arrays`` holds none.

        Raises:
            FileFormatError: guides of a newer version or incomplete.
        """
        if prefix + "meta" not in arrays:
            return None
        angle, version = (float(x) for x in np.asarray(arrays[prefix + "meta"]))
        if version > GUIDE_VERSION:
            raise FileFormatError(f"guide buffers of version {version:g}; this reader knows {GUIDE_VERSION}")
        try:
            t = {k: torch.from_numpy(np.array(arrays[prefix + k])) for k in GUIDE_NAMES}
        except KeyError as exc:
            raise FileFormatError(f"incomplete guide buffers: {exc} missing") from exc
        return cls(
            t["normal"],
            t["position"],
            t["depth"],
            t["object_id"].long(),
            t["albedo"],
            t["mirror_id"].long(),
            t["mirror_radiance"],
            t["light_cos_h"],
            angle,
        )


def object_albedo_proxy(object_id: torch.Tensor) -> torch.Tensor:
    """(..., 3) grey in [0.35, 0.95] per object id by a fixed golden-ratio sequence; 0 for -1."""
    g = 0.35 + 0.6 * torch.remainder(object_id.double() * 0.6180339887498949 + 0.5, 1.0)
    g = torch.where(object_id >= 0, g, 0.0).float()
    return g[..., None].expand(*object_id.shape, 3).contiguous()


def guide_buffers(scene) -> GuideBuffers:
    """Trace the camera's pixel-centre rays of ``scene`` (a :class:`~torch_brdf.scene.Scene`).

    Returns:
        :class:`GuideBuffers` at the camera's resolution.
    """
    cam = scene.camera
    h, w = cam.height, cam.width
    o, d = cam.generate_rays()
    hits = scene.trace(o, d)
    n = hits.normal
    n = torch.where(((n * d).sum(-1) > 0)[:, None], -n, n)  # face the eye
    hit = hits.hit
    depth = torch.where(hit, hits.t.float(), float("inf"))
    idx = torch.nonzero(hit).squeeze(1)
    r = d[idx] - 2 * (d[idx] * n[idx]).sum(-1, keepdim=True) * n[idx]
    mh = scene.trace(scene.spawn(hits.position[idx], n[idx], r), r)
    mirror_id = torch.full((h * w,), -2, dtype=torch.long)
    mirror_id[idx] = mh.object_id.long()
    mirror_rad = torch.zeros(h * w, 3)
    mirror_rad[idx] = emission_seen(scene, r, mh).float()
    angle = 2.0 * float(np.tan(np.radians(cam.fov_deg) / 2)) / h
    return GuideBuffers(
        normal=n.float().reshape(h, w, 3),
        position=hits.position.float().reshape(h, w, 3),
        depth=depth.reshape(h, w),
        object_id=hits.object_id.long().reshape(h, w),
        albedo=object_albedo_proxy(hits.object_id.long()).reshape(h, w, 3),
        mirror_id=mirror_id.reshape(h, w),
        mirror_radiance=mirror_rad.reshape(h, w, 3),
        light_cos_h=_light_cos_h(scene, hits, d).reshape(h, w),
        pixel_angle=angle,
    )


def _brightest_light_directions(scene, points: torch.Tensor) -> torch.Tensor | None:
    """(P, 3) unit directions from ``points`` towards the most powerful light, or None."""
    from ..scene.envmap import EnvironmentMap
    from ..scene.lights import AreaLight, DirectionalLight

    if not scene.lights:
        return None
    light = max(scene.lights, key=lambda li: li.power_estimate())
    if isinstance(light, AreaLight):
        tri = light.triangles.double()
        area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)
        centre = (tri.mean(1) * area[:, None]).sum(0) / area.sum()
        return torch.nn.functional.normalize(centre.float() - points, dim=-1)
    if isinstance(light, DirectionalLight):
        return light.direction.float().expand_as(points)
    if isinstance(light, EnvironmentMap):
        from ..sphere.latlong import texel_centers

        k = int(torch.argmax(light.texel_pdf.reshape(-1)))
        d = texel_centers(light.height, light.width).reshape(-1, 3)[k] @ light.to_world.T
        return d.float().expand_as(points)
    return None


def _light_cos_h(scene, hits, d: torch.Tensor) -> torch.Tensor:
    """(P,) n.h for the brightest light at the first hits (0 on a miss or without lights)."""
    out = torch.zeros(d.shape[0])
    idx = torch.nonzero(hits.hit).squeeze(1)
    if idx.numel() == 0:
        return out
    l = _brightest_light_directions(scene, hits.position[idx].float())
    if l is None:
        return out
    n = hits.normal[idx].float()
    n = torch.where(((n * d[idx]).sum(-1) > 0)[:, None], -n, n)
    h = torch.nn.functional.normalize(l - d[idx].float(), dim=-1)
    out[idx] = (n * h).sum(-1)
    return out
