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

import numpy as np
import torch

from ..scene.guides import GuideBuffers, object_albedo_proxy
from ..transport.pathtrace import emission_seen

__all__ = ["GuideBuffers", "guide_buffers", "object_albedo_proxy"]


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
