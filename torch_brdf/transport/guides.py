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

from ..scene.gbuffer import trace_gbuffer
from ..scene.guides import GuideBuffers, object_albedo_proxy
from .pathtrace import emission_seen

__all__ = ["GuideBuffers", "guide_buffers", "object_albedo_proxy"]


def guide_buffers(scene) -> GuideBuffers:
    """The guides of ``scene``'s view (a :class:`~torch_brdf.scene.Scene`), from the camera's
    G-buffer (:func:`~torch_brdf.scene.gbuffer.trace_gbuffer`, pixel-centre rays) plus one
    mirror ray per hit.

    Returns:
        :class:`GuideBuffers` at the camera's resolution.
    """
    cam = scene.camera
    h, w = cam.height, cam.width
    gb = trace_gbuffer(scene)
    pix = gb.pixels
    wo = gb.wo.float()
    n = gb.normal.float()
    n = torch.where(((n * wo).sum(-1) < 0)[:, None], -n, n)  # face the eye
    pos = gb.position.float()
    r = 2 * (wo * n).sum(-1, keepdim=True) * n - wo  # the mirror direction of the view
    mh = scene.trace(scene.spawn(pos, n, r), r)

    def image(values, fill, width=None):
        shape = (h * w,) if width is None else (h * w, width)
        out = torch.full(shape, fill, dtype=values.dtype)
        out[pix] = values
        return out.reshape(h, w, *(() if width is None else (width,)))

    oid = image(gb.object_id.long(), -1)
    return GuideBuffers(
        normal=image(n, 0.0, 3),
        position=image(pos, 0.0, 3),
        depth=image(gb.depth.float(), float("inf")),
        object_id=oid,
        albedo=object_albedo_proxy(oid),
        mirror_id=image(mh.object_id.long(), -2),
        mirror_radiance=image(emission_seen(scene, r, mh).float(), 0.0, 3),
        light_cos_h=image(_light_cos_h(scene, pos, n, wo), 0.0),
        pixel_angle=2.0 * float(np.tan(np.radians(cam.fov_deg) / 2)) / h,
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


def _light_cos_h(scene, pos: torch.Tensor, n: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """(P,) n.h for the brightest light at hits ``pos`` with eye-facing normals ``n`` and
    directions to the eye ``wo`` (0 without lights)."""
    l = _brightest_light_directions(scene, pos)
    if l is None or pos.shape[0] == 0:
        return torch.zeros(pos.shape[0])
    h = torch.nn.functional.normalize(l + wo, dim=-1)
    return (n * h).sum(-1)
