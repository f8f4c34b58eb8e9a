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

Light lobes (:func:`light_lobe_images`). A glossy object's sharpest basis images are the area
lights' reflections through its narrowest bands, and their edges are where the band's box
cuts the light's image: no geometric guide shows them. Without visibility they are a plain
integral over the lights, computed here by quadrature (no sampling noise): per pixel centre on
the object, :math:`U_k = \sum_{j \le k} \int_{A} L_e\,\rho_q\,b_j\,\cos\theta_i\cos\theta_l
/ r^2\,dA`, the unoccluded direct light through the prefix of bands up to :math:`k`. A denoiser
may divide a prefix-sum image by it (:class:`~torch_brdf.denoise.CumulativeOIDN`'s ``lobes``) so that
what it smooths is the smooth remainder (visibility, indirect light); like every guide it
depends on geometry, lights and the basis, never on coefficients.
"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import ShapeError, ValueRangeError
from ..frame import orthonormal_basis
from ..records.guides import GuideBuffers
from ..scene.gbuffer import trace_gbuffer
from .pathtrace import emission_seen

__all__ = ["guide_buffers", "light_lobe_images", "object_albedo_proxy", "pixel_coverage"]

#: the most subpixel rays :func:`pixel_coverage` casts per pixel (64 x 64)
MAX_COVERAGE_SAMPLES = 64


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


def object_albedo_proxy(object_id: torch.Tensor) -> torch.Tensor:
    """(..., 3) grey in [0.35, 0.95] per object id by a fixed golden-ratio sequence; 0 for -1."""
    g = 0.35 + 0.6 * torch.remainder(object_id.double() * 0.6180339887498949 + 0.5, 1.0)
    g = torch.where(object_id >= 0, g, 0.0).float()
    return g[..., None].expand(*object_id.shape, 3).contiguous()


def pixel_coverage(scene, samples: int = 8, object_id: torch.Tensor | None = None) -> torch.Tensor:
    """Per pixel, the fraction of its area whose first hit is the pixel centre's object (a
    miss counts as object -1): ``samples`` x ``samples`` rays through the centres of a grid of
    subpixel cells. Like every guide it depends on geometry and the camera only, never on a
    material: where it is below 1, the pixel's record mixes two objects in that proportion,
    which a silhouette filter can fit (:class:`~torch_brdf.denoise.SelectionSettings`'s
    ``silhouette_regression``).

    Args:
        scene: the scene (its camera's view).
        samples: cells per side, 1 to :data:`MAX_COVERAGE_SAMPLES` (1: the centre ray, all ones).
        object_id: (H, W) the centre objects (default: traced through the pixel centres, as
            :func:`guide_buffers` does; pass ``T.guides.object_id`` to skip that trace).
    Returns:
        (H, W) float32 in [0, 1] (multiples of 1 / samples²).
    Raises:
        ValueRangeError: ``samples`` not an int in [1, MAX_COVERAGE_SAMPLES].
        ShapeError: ``object_id`` not the camera's (H, W).
    """
    if isinstance(samples, bool) or not isinstance(samples, int) or not 1 <= samples <= MAX_COVERAGE_SAMPLES:
        raise ValueRangeError(f"samples must be an int in [1, {MAX_COVERAGE_SAMPLES}]; got {samples!r}")
    cam = scene.camera
    h, w = cam.height, cam.width
    if object_id is not None and tuple(object_id.shape) != (h, w):
        raise ShapeError(f"object_id must be the camera's {(h, w)}; got {tuple(object_id.shape)}")
    rows, cols = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    rows, cols = rows.reshape(-1), cols.reshape(-1)

    def first_hit(dy: float, dx: float) -> torch.Tensor:  # (H*W,) object ids at that raster offset
        hits = scene.trace(*cam.rays_through(cols + dx, rows + dy))
        return torch.where(hits.hit, hits.object_id.long(), -1)

    centre = first_hit(0.5, 0.5) if object_id is None else object_id.reshape(-1).long()  # the G-buffer's rays
    same = torch.zeros(h * w, dtype=torch.int64)
    for i in range(samples):
        for j in range(samples):
            same += (first_hit((i + 0.5) / samples, (j + 0.5) / samples) == centre).long()
    return (same.double() / samples**2).float().reshape(h, w)


def _brightest_light_directions(scene, points: torch.Tensor) -> torch.Tensor | None:
    """(P, 3) unit directions from ``points`` towards the most powerful light, or None."""
    from ..scene.envmap import EnvironmentMap
    from ..scene.lights import AreaLight, DirectionalLight, luminance

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
        k = int(torch.argmax(luminance(light.radiance.double()).reshape(-1)))  # the brightest entry
        d = light.entry_directions().reshape(-1, 3)[k]
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


def light_lobe_images(scene, basis, obj, samples: int = 16, chunk: int = 256) -> torch.Tensor | None:
    """The unoccluded direct light of ``scene``'s area lights through each prefix of the eye
    bands of object ``obj`` (module docstring), at the pixel centres whose first hit is ``obj``.

    Args:
        scene: the scene.
        basis: ``obj``'s :class:`~torch_brdf.records.polynomial.ObjectBasis` (``tensors.bases[m]``).
        obj: object name or index.
        samples: quadrature points per triangle side (``samples**2`` per emitter triangle, on
            equal-area cells).
        chunk: at most this many pixels per step, fewer for large lights: a step holds at most
            ``2**20`` (pixel, light point) pairs (a few tens of MB).
    Returns:
        (J, 3, H, W) float32, row ``k`` the sum over bands ``0..k`` (0 off the object), or None
        when the scene has no area light.
    Raises:
        ValueRangeError: ``basis`` is None, anisotropic or two-layered (Fresnel), or
            ``samples < 1``.
    """
    from ..scene.lights import AreaLight

    if basis is None or basis.layers != 1:
        raise ValueRangeError(f"light lobes need a one-layer banded basis; got {basis}")
    bands = basis.band_basis()
    if bands.anisotropic:
        raise ValueRangeError("light lobes are not defined for an anisotropic basis (no tangent frame here)")
    if samples < 1:
        raise ValueRangeError(f"samples must be >= 1; got {samples}")
    lights = [li for li in scene.lights if isinstance(li, AreaLight)]
    if not lights:
        return None
    m = scene.object_id(obj) if isinstance(obj, str) else int(obj)
    quotient = basis.quotients()[0]
    cam = scene.camera
    gb = trace_gbuffer(scene)
    on = gb.object_id == m
    pix = gb.pixels[on]
    wo = gb.wo[on].double()
    n = gb.normal[on].double()
    n = torch.where(((n * wo).sum(-1) < 0)[:, None], -n, n)
    pos = gb.position[on].double()
    t1, t2 = orthonormal_basis(n)
    frame = torch.stack([t1, t2, n], 1)  # (P, 3, 3): rows are the local axes
    wo_l = torch.einsum("pij,pj->pi", frame, wo)
    # equal-area cells of each triangle: a uniform grid through the square-to-triangle map
    g = (torch.arange(samples, dtype=torch.float64) + 0.5) / samples
    u1, u2 = torch.meshgrid(g, g, indexing="ij")
    s_ = u1.reshape(-1).sqrt()
    b1, b2 = 1 - s_, u2.reshape(-1) * s_
    J = bands.J
    out = torch.zeros(pix.numel(), J, 3, dtype=torch.float64)
    for light in lights:
        tri = light.triangles.double()
        area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)
        y = tri[:, None, 0] + b1[None, :, None] * (tri[:, None, 1] - tri[:, None, 0])
        y = (y + b2[None, :, None] * (tri[:, None, 2] - tri[:, None, 0])).reshape(-1, 3)
        ny = light.normals.double().repeat_interleave(b1.numel(), 0)
        dA = (area / b1.numel()).repeat_interleave(b1.numel(), 0)
        radiance = light.radiance.double()
        step = max(1, min(chunk, (1 << 20) // y.shape[0]))  # an emitter mesh of many triangles: fewer pixels
        for a in range(0, pix.numel(), step):
            d = y[None] - pos[a : a + step, None]  # (p, Y, 3)
            r2 = (d * d).sum(-1)
            wi = d / r2.sqrt()[..., None]
            wi_l = torch.einsum("pij,pyj->pyi", frame[a : a + step], wi)
            cos_l = -(wi * ny[None]).sum(-1)
            w_o = wo_l[a : a + step, None].expand_as(wi_l)
            ok = (wi_l[..., 2] > 0) & (cos_l > 0)
            q = quotient(wi_l, w_o)
            q = q.mean(-1) if q.ndim == wi_l.ndim else q  # an RGB quotient: its mean (a guide)
            w = torch.where(ok, q * wi_l[..., 2] * cos_l / r2 * dA[None], 0.0)
            ja, jb = bands.membership(wi_l, w_o)
            acc = torch.zeros(w.shape[0], J, dtype=torch.float64)
            acc.scatter_add_(1, ja, 0.5 * w).scatter_add_(1, jb, 0.5 * w)  # a == b: one band
            out[a : a + step] += acc[..., None] * radiance
    img = torch.zeros(J, 3, cam.height * cam.width, dtype=torch.float32)
    img[:, :, pix] = out.cumsum(1).permute(1, 2, 0).float()
    return img.reshape(J, 3, cam.height, cam.width)
