r"""All-frequency relighting with locally adaptive triple products (Inger et al.).

Direct lighting at vertex :math:`x` towards :math:`\omega_o` (the seed's Eq. 1-2),

.. math:: B = \sum_t L_t\,\Omega_t\,V_t\,f(\omega_t, \omega_o)\,(n\cdot\omega_t),

is summed over the texels :math:`t` of a world-oriented cubemap, split into ``16 x 16``
blocks, each block handled by the cheapest product that is exact enough (Algorithm 1):

- occluded block: 0;
- unoccluded block: a dot product of the first ``l x l`` DCT coefficients of lighting and
  BRDF (line 6);
- BRDF constant over the block: :math:`\bar f\,(L_{int}\cdot V_d)` over the non-zero entries
  of the differential visibility (line 9);
- otherwise: the pixel-basis product, expanding the visibility from its flips (line 11).

**The cosine is exact.** The visibility maps are 0 below each vertex's horizon (see
:mod:`torch_brdf.transport.visibility`), so :math:`\max(0, n\cdot\omega)` needs no clamp and
:math:`n\cdot\omega_t` is linear in the world direction. We keep the lighting as the
first-moment vector :math:`M_t = L_t\,\Omega_t\,\omega_t` (3 x C per texel) and every
product is :math:`n \cdot \sum_t M_t V_t f_t`: the block approximations (1, 4 or 16 DCT
coefficients) apply to the BRDF :math:`f` alone, and the cosine factor, which varies by up
to 0.4 across a block at the horizon, is never approximated. (The seed folds the cosine
into the BRDF before approximating; at 64x64x6 that puts a visible error into every block
the horizon crosses.) The standard-basis reference and the Haar baseline use the same
texel sum, so with 256 samples in every block the products agree to float rounding.

**BRDF per block, on the fly** (Sec. 4.1): ``l x l`` samples at the centres of an
``l x l`` grid of sub-blocks and a precomputed inverse (:mod:`torch_brdf.sphere.dct`) give
the coefficients; ``l = 16`` samples every texel. Samples below the horizon are evaluated
at the nearest direction just above it (the BRDF's continuation), since the visibility
masks them anyway. The number of samples comes from a rule:

- :class:`PhongRule`: the seed's Appendix A for :class:`~torch_brdf.brdf.analytic.Phong`
  (Lambert: one coefficient everywhere);
- :class:`GenericRule`: any BRDF (anisotropic, measured, microfacet ...): a cheap error
  estimate from a 2x2 grid plus the point of the block nearest the mirror direction, then a
  4x4 grid where needed;
- :class:`FixedRule`: the same level everywhere (``FixedRule(16)`` is the standard basis).

:class:`TripleProductRenderer` holds the vertices, their visibility and the current
lighting and materials; :meth:`~TripleProductRenderer.shade` returns per-vertex radiance and
per-frame statistics (the seed's Tables 1 and 2), :meth:`~TripleProductRenderer.render`
an image by interpolating vertex colours at the camera's primary hits. Baselines:
:meth:`~TripleProductRenderer.shade_standard` (dense texel sum) and
:meth:`~TripleProductRenderer.shade_haar` (Ng et al. 2004).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import ClassVar

import torch
from torch import nn
from tqdm.auto import tqdm

from ..brdf.analytic import Phong
from ..brdf.base import BRDF, Lambert, create
from ..data import progress_default
from ..errors import SceneError, ShapeError, ValueRangeError
from ..frame import Frame
from ..metrics import psnr
from ..parallel.threads import tuned_method, usable_cores
from ..records.visibility import VertexVisibility
from ..records.visibility_codec import BlockVisibility
from ..scene.camera import Camera
from ..scene.envmap import EnvironmentMap
from ..scene.gbuffer import GBuffer, trace_gbuffer
from ..scene.scene import Scene
from ..sphere.cubemap import CubemapBlocks
from ..sphere.dct import LOW, dct_basis, low_indices, sample_positions, subsampled_inverse
from ..sphere.haar import HaarTripleProduct
from ..transport.pathtrace import material_brdfs
from . import _relight

__all__ = [
    "METHODS",
    "BlockLighting",
    "FixedRule",
    "FrameStats",
    "GenericRule",
    "PhongRule",
    "TripleProductRenderer",
    "View",
    "block_lighting",
    "psnr",
]

LEVELS = (1, 2, 4, 16)
#: the shading methods of :meth:`TripleProductRenderer.render`
METHODS = ("adaptive", "standard", "haar")
_HORIZON = 1e-4  # samples below the horizon are evaluated at this height


# ---------------------------------------------------------------------------------- lighting
@dataclass(frozen=True)
class BlockLighting:
    r"""The lighting of every block in the seed's three representations (Sec. 4.3), for the
    first-moment form :math:`M_t = L_t\,\Omega_t\,\omega_t`.

    Attributes:
        texels: (NB, S^2, C) :math:`L_t\Omega_t` (solid-angle corrected radiance).
        moments: (NB, S^2, 3, C) raw texels :math:`M_t` (line 11).
        dct: (NB, 16, 3, C) the first 16 2-D DCT coefficients of :math:`M` (line 6).
        integral: (NB, S^2, 3, C) :math:`D^{-T} M`, suffix sums :math:`\sum_{s \ge t} M_s` (line 9).
    """

    texels: torch.Tensor
    moments: torch.Tensor
    dct: torch.Tensor
    integral: torch.Tensor


def block_lighting(
    envmap: EnvironmentMap, geometry: CubemapBlocks, samples: int = 4, dtype: torch.dtype = torch.float32
) -> BlockLighting:
    """Project an environment map on the cubemap blocks (recomputed on every change).

    Args:
        envmap: the lighting (its rotation included).
        geometry: cubemap layout.
        samples: k; each cube texel averages the map over a ``k x k`` grid.
        dtype: output dtype (the projection runs in float64).
    """
    L = geometry.project(lambda d: envmap.eval_miss(d).to(torch.float64), samples)  # (NB, S^2, C)
    Lw = L * geometry.solid_angles[..., None]
    M = geometry.directions[..., :, None] * Lw[..., None, :]  # (NB, S^2, 3, C)
    B16 = dct_basis(geometry.block, LOW)  # (16, S^2)
    dct = torch.einsum("kt,btjc->bkjc", B16, M)
    integral = M.flip(1).cumsum(1).flip(1)
    return BlockLighting(*(x.to(dtype).contiguous() for x in (Lw, M, dct, integral)))


# ---------------------------------------------------------------------------------- rules
@dataclass
class _Pairs:
    """The (vertex, block) pairs of one object whose BRDF is being projected."""

    frames: Frame  # (n,) frames of the pairs' vertices
    wo: torch.Tensor  # (n, 3) local outgoing directions
    blocks: torch.Tensor  # (n,) block ids
    vertex: torch.Tensor  # (n,) row of the pair's vertex among the shaded vertices


class _Sampler:
    """Evaluates a BRDF at the l x l sample grids of blocks (world directions precomputed)."""

    def __init__(self, geometry: CubemapBlocks, dtype: torch.dtype, energy: torch.Tensor):
        self.geometry, self.dtype = geometry, dtype
        self.energy = energy  # (NB,) block lighting sum L Omega, max over channels
        self.points = {l: geometry.block_points(sample_positions(l, geometry.block), dtype) for l in LEVELS}
        self.inverse = {l: subsampled_inverse(l, geometry.block, dtype) for l in LEVELS if l < 16}
        self.evals = 0

    def local(self, pairs: _Pairs, world: torch.Tensor) -> torch.Tensor:
        """World directions (n, m, 3) -> local directions lifted above the horizon."""
        f = pairs.frames
        loc = torch.stack(
            (
                (world * f.s[:, None]).sum(-1),
                (world * f.t[:, None]).sum(-1),
                (world * f.n[:, None]).sum(-1),
            ),
            -1,
        )
        z = loc[..., 2:3]
        lifted = torch.cat((loc[..., :2], z.clamp_min(_HORIZON)), -1)
        return torch.where(z > _HORIZON, loc, lifted / lifted.norm(dim=-1, keepdim=True))

    def eval(self, brdf: BRDF, pairs: _Pairs, world: torch.Tensor) -> torch.Tensor:
        """f at world directions (n, m, 3) -> (n, m, C)."""
        if world.shape[0] == 0:
            return world.new_zeros(0, world.shape[1], 3)
        return self.eval_local(brdf, self.local(pairs, world), pairs.wo)

    def eval_local(self, brdf: BRDF, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """f at lifted local directions wi (n, m, 3) for wo (n, 3) -> (n, m, C)."""
        n, m = wi.shape[:2]
        if n == 0:
            return wi.new_zeros(0, m, 3)
        self.evals += n * m
        w = wo[:, None, :].expand(-1, m, -1)
        return brdf.eval_local(wi.reshape(-1, 3), w.reshape(-1, 3)).reshape(n, m, -1).to(self.dtype)

    def samples(self, brdf: BRDF, pairs: _Pairs, l: int) -> torch.Tensor:
        """f at the l x l grid of each pair's block: (n, l^2, C)."""
        return self.eval(brdf, pairs, self.points[l][pairs.blocks])

    def coefficients(self, values: torch.Tensor, l: int) -> torch.Tensor:
        """(n, l^2, C) samples -> (n, l^2, C) DCT coefficients (p, q < l)."""
        return torch.einsum("ks,nsc->nkc", self.inverse[l], values)


class SamplingRule:
    """Decides per (vertex, block) pair how many BRDF coefficients to use, and computes them.

    ``project`` returns, for every level ``l`` in (1, 2, 4, 16), the pair indices at that
    level and their coefficients: (m, l^2, C) DCT coefficients for ``l < 16`` and the 256
    texel samples for ``l = 16``.
    """

    def project(self, brdf: BRDF, pairs: _Pairs, sampler: _Sampler) -> dict[int, tuple[torch.Tensor, torch.Tensor]]:
        raise NotImplementedError

    @staticmethod
    def _by_level(
        level: torch.Tensor, brdf: BRDF, pairs: _Pairs, sampler: _Sampler, centre: torch.Tensor | None = None
    ) -> dict:
        """Sample and project every pair at its level; ``centre`` (n, 3): the pairs' block
        centres in lifted local coordinates, if already known (the one-sample grid)."""
        out = {}
        for l in LEVELS:
            idx = (level == l).nonzero().squeeze(-1)
            if l == 1 and centre is not None:
                v = sampler.eval_local(brdf, centre[idx][:, None], pairs.wo[idx])
            else:
                v = sampler.samples(brdf, _subset(pairs, idx), l)
            out[l] = (idx, v if l == 16 else sampler.coefficients(v, l))
        return out


def _subset(pairs: _Pairs, idx: torch.Tensor) -> _Pairs:
    f = pairs.frames
    return _Pairs(Frame(f.s[idx], f.t[idx], f.n[idx]), pairs.wo[idx], pairs.blocks[idx], pairs.vertex[idx])


@dataclass
class FixedRule(SamplingRule):
    """The same number of samples per side ``l`` in every block (16 = the standard basis)."""

    level: int = 16
    #: the compiled frame's name of this rule (see ``render/_relight.py``)
    native_kind: ClassVar[str] = "fixed"

    def __post_init__(self):
        if self.level not in LEVELS:
            raise ValueRangeError(f"level must be one of {LEVELS}; got {self.level}")

    def project(self, brdf, pairs, sampler):
        return self._by_level(torch.full((len(pairs.blocks),), self.level), brdf, pairs, sampler)


@dataclass
class PhongRule(SamplingRule):
    r"""Inger et al., Appendix A, for Lambert and Phong BRDFs (any other model falls back to
    ``fallback``).

    With :math:`\alpha` the angle between the view direction and the block centre reflected
    about the normal, and :math:`s` the exponent: :math:`s <` ``cuts[0]``: 4 coefficients
    where :math:`\alpha <` ``angles[1]``; ``cuts[0]`` :math:`\le s <` ``cuts[1]``: 16 where
    :math:`\alpha <` ``angles[0]``, 4 where :math:`\alpha <` ``angles[1]``; larger :math:`s`:
    256 samples where :math:`\alpha <` ``angles[0]``, 16 where :math:`\alpha <` ``angles[1]``
    (the seed leaves that band unstated); one coefficient elsewhere. Lambert (or ``ks = 0``):
    one everywhere.

    ``scale`` multiplies the angles. The seed used 64x64x6 and 128x128x6 maps without saying
    which the angles were tuned for. The default (None) scales them by the block's angular
    radius relative to a 16-texel block of a 64x64x6 map: the printed angles at 64x64x6,
    half at 128x128x6, twice at 32x32x6. On the benchmark scene (64x64x6) the printed angles
    reach the accuracy of twice those angles at half the BRDF samples (see
    ``benchmarks/triple_product.py``'s ``curve``).
    """

    angles: tuple[float, float] = (math.pi / 8, math.pi / 4)
    cuts: tuple[float, float] = (30.0, 250.0)
    scale: float | None = None
    fallback: SamplingRule | None = None
    #: the compiled frame's name of this rule (see ``render/_relight.py``)
    native_kind: ClassVar[str] = "phong"

    def project(self, brdf, pairs, sampler):
        if not isinstance(brdf, Lambert | Phong):
            return (self.fallback or GenericRule()).project(brdf, pairs, sampler)
        geom = sampler.geometry
        scale = self.scale
        if scale is None:
            scale = geom.angular_radius / CubemapBlocks(64, geom.block).angular_radius
        a0, a1 = (min(a * scale, math.pi) for a in self.angles)
        c = sampler.local(pairs, geom.centers.to(sampler.dtype)[pairs.blocks][:, None])[:, 0]
        if isinstance(brdf, Lambert) or float(brdf.ks.detach().max()) == 0.0:
            return self._by_level(torch.ones(len(pairs.blocks), dtype=torch.long), brdf, pairs, sampler, c)
        s = float(brdf.exponent.detach().max())
        refl = torch.stack((-c[:, 0], -c[:, 1], c[:, 2]), -1)
        alpha = torch.acos((refl * pairs.wo).sum(-1).clamp(-1, 1))
        near, mid = alpha < a0, alpha < a1
        level = torch.ones(len(pairs.blocks), dtype=torch.long)
        if s < self.cuts[0]:
            level[mid] = 2
        elif s < self.cuts[1]:
            level[mid] = 2
            level[near] = 4
        else:
            level[mid] = 4
            level[near] = 16
        return self._by_level(level, brdf, pairs, sampler, c)


@dataclass
class GenericRule(SamplingRule):
    r"""A cheap error estimate for any BRDF (isotropic, anisotropic, measured).

    Per pair, ``f`` is sampled on the 2x2 grid and at the point of the block nearest the
    mirror direction of :math:`\omega_o` (where the lobes of every library model peak). The
    estimate is the share of the vertex's radiance that a constant would get wrong,

    .. math:: e_b = \frac{\max_s |f_s - \bar f_b|\; E_b}{\sum_{b'} \bar f_{b'} E_{b'}},

    with :math:`\bar f_b` the 2x2 mean, :math:`E_b = \sum_{t \in b} L_t\Omega_t` the block's
    lighting (an upper bound of its irradiance; max over channels) and the sum over the
    vertex's unoccluded blocks. :math:`e \le` ``constant`` -> 1 coefficient (the 2x2 mean),
    :math:`e \le` ``linear`` -> 4 (the 2x2 samples); otherwise a 4x4 grid is sampled: 16
    coefficients unless its highest DCT frequencies (p = 3 or q = 3), or the mirror-point
    sample standing above every grid sample (a lobe narrower than the grid spacing), weigh
    more than ``smooth`` on the same scale; then 256 samples.
    """

    constant: float = 1e-3
    linear: float = 1e-2
    smooth: float = 1e-3

    def project(self, brdf, pairs, sampler):
        n = len(pairs.blocks)
        if isinstance(brdf, Lambert):
            return self._by_level(torch.ones(n, dtype=torch.long), brdf, pairs, sampler)
        geom = sampler.geometry
        f4 = sampler.samples(brdf, pairs, 2)  # (n, 4, C)
        mirror = pairs.frames.to_world(torch.stack((-pairs.wo[:, 0], -pairs.wo[:, 1], pairs.wo[:, 2]), -1))
        peak = sampler.eval(brdf, pairs, geom.nearest_in_blocks(pairs.blocks, mirror).to(sampler.dtype)[:, None])[:, 0]
        mean = f4.mean(1)  # (n, C)
        energy = sampler.energy[pairs.blocks]  # (n,)
        total = torch.zeros(int(pairs.vertex.max()) + 1 if n else 0, dtype=mean.dtype)
        total.index_add_(0, pairs.vertex, mean.abs().amax(-1) * energy)
        weight = energy / total[pairs.vertex].clamp_min(torch.finfo(mean.dtype).tiny)  # (n,)
        spread = torch.maximum((f4 - mean[:, None]).abs().amax(1), (peak - mean).abs()).amax(-1)
        e = spread * weight
        level = torch.full((n,), 4, dtype=torch.long)
        level[e <= self.linear] = 2
        level[e <= self.constant] = 1
        out = {}
        i1 = (level == 1).nonzero().squeeze(-1)
        # one coefficient: the constant term of the 2x2 interpolant (the 2x2 mean)
        out[1] = (i1, sampler.coefficients(mean[i1][:, None], 1))
        i2 = (level == 2).nonzero().squeeze(-1)
        out[2] = (i2, sampler.coefficients(f4[i2], 2))
        i4 = (level == 4).nonzero().squeeze(-1)
        f16 = sampler.samples(brdf, _subset(pairs, i4), 4)
        A = sampler.coefficients(f16, 4).view(len(i4), 4, 4, f16.shape[-1])  # explicit C: i4 may be empty
        high = torch.cat((A[:, 3, :, :], A[:, :3, 3, :]), 1).abs().amax((1, 2)) / geom.block
        missed = (peak[i4] - f16.amax(1)).amax(-1).clamp_min(0)
        fine = torch.maximum(high, missed) * weight[i4] > self.smooth
        out[4] = (i4[~fine], A[~fine].reshape(-1, 16, A.shape[-1]))
        i16 = i4[fine]
        out[16] = (i16, sampler.samples(brdf, _subset(pairs, i16), 16))
        return out


# ---------------------------------------------------------------------------------- frames
@dataclass
class FrameStats:
    """Per-frame statistics (the seed's Tables 1 and 2).

    Attributes:
        vertices: vertices shaded.
        blocks: vertex-block pairs considered (vertices x NB).
        cases: pair counts: ``occluded``, ``line6`` (unoccluded), ``line9`` (BRDF constant,
            partial visibility), ``line11`` (pixel product).
        sampling: non-occluded pair counts by BRDF coefficients: ``1``, ``4``, ``16``, ``256``.
        brdf_evals: BRDF evaluations (including the rule's estimates).
        visibility_entries: differential-visibility entries read by line 9 and line 11.
    """

    vertices: int = 0
    blocks: int = 0
    cases: dict[str, int] = field(default_factory=lambda: {"occluded": 0, "line6": 0, "line9": 0, "line11": 0})
    sampling: dict[str, int] = field(default_factory=lambda: {"1": 0, "4": 0, "16": 0, "256": 0})
    brdf_evals: int = 0
    visibility_entries: int = 0

    def percentages(self) -> dict[str, dict[str, float]]:
        """Case shares of the non-occluded blocks (Table 1) and sampling shares (Table 2), in %."""
        lit = max(1, self.blocks - self.cases["occluded"])
        s = max(1, sum(self.sampling.values()))
        return {
            "cases": {k: 100.0 * v / lit for k, v in self.cases.items() if k != "occluded"},
            "occluded": 100.0 * self.cases["occluded"] / max(1, self.blocks),
            "sampling": {k: 100.0 * v / s for k, v in self.sampling.items()},
        }

    def as_dict(self) -> dict:
        return {
            "vertices": self.vertices,
            "blocks": self.blocks,
            "cases": dict(self.cases),
            "sampling": dict(self.sampling),
            "brdf_evals": self.brdf_evals,
            "visibility_entries": self.visibility_entries,
            "percent": self.percentages(),
        }


@dataclass(frozen=True)
class View:
    """The renderer's state for one camera, cached across frames until the camera moves.

    Attributes:
        gbuffer: what the camera sees (:func:`~torch_brdf.scene.gbuffer.trace_gbuffer`): the
            vertices to shade (``gbuffer.vertex_ids``, culled to the triangles hit), the eye,
            and per pixel the hit triangle's corners and barycentric weights.
        background: (H*W, C) float32 environment radiance of the primary rays (0 where they hit).
        blocks: the visibility of ``gbuffer.vertex_ids``.
    """

    gbuffer: GBuffer
    background: torch.Tensor
    blocks: BlockVisibility

    @property
    def vertex_ids(self) -> torch.Tensor:
        """(P,) int64 the vertices shaded (the G-buffer's)."""
        return self.gbuffer.vertex_ids

    @property
    def mask(self) -> torch.Tensor:
        """(H, W) bool: pixels that see the scene."""
        return self.gbuffer.mask


def _vertex_texels(scene, count: int) -> torch.Tensor:
    r"""(V, 3) the base-colour texel at every scene vertex (1 where untextured), in the ray
    tracer's vertex order (objects one after another).

    Relighting shades vertices and interpolates their radiance across triangles, so a texture
    enters as one texel per vertex: exact at the vertices for Lambert materials (radiance is
    linear in the albedo; for other models the whole BRDF is scaled), blurred between them (a
    texture finer than the mesh is lost; subdivide the mesh to keep it)."""
    out = torch.ones(count, 3)
    offset = 0
    for o in scene.objects:
        n = len(o.mesh.vertices)
        tex = o.textures.get("base_color")
        if tex is not None and offset + n <= count:
            out[offset : offset + n] = tex.lookup(torch.as_tensor(o.uv))
        offset += n
    if offset != count:
        raise SceneError(f"the visibility holds {count} vertices; the scene's objects {offset}")
    return out


class TripleProductRenderer(nn.Module):
    """Per-vertex relighting of a static scene with locally adaptive triple products.

    Args:
        scene: the scene whose vertices ``visibility`` was computed for.
        visibility: :func:`~torch_brdf.transport.visibility.precompute_visibility` result.
        envmap: the lighting (default: the scene's environment map).
        rule: BRDF sampling rule (default :class:`PhongRule`, falling back to
            :class:`GenericRule` for other models).
        dtype: float32 (default) or float64 for the products.
        lighting_samples: k x k lat-long lookups averaged per cube texel.

    ``threads``: threads of a frame: the compiled frame's (None, the default: the usable
    cores) and the torch path's (None: the count measured fastest for the number of vertices,
    :func:`torch_brdf.parallel.threads.tuned`). ``compiled``: None (default) shades with the
    compiled frame where it supports the scene (float32, Lambert and Phong materials, the
    Appendix A or a fixed rule; :meth:`frame_path`) and the torch path elsewhere; False always
    the torch path; True the compiled frame or an error.
    """

    threads: int | None = None
    compiled: bool | None = None

    def __init__(
        self,
        scene: Scene,
        visibility: VertexVisibility,
        envmap: EnvironmentMap | None = None,
        rule: SamplingRule | None = None,
        dtype: torch.dtype = torch.float32,
        lighting_samples: int = 4,
    ):
        super().__init__()
        visibility.check_scene(scene)
        self.scene, self.visibility, self.dtype = scene, visibility, dtype
        self.geometry = visibility.geometry
        self.rule = rule if rule is not None else PhongRule(fallback=GenericRule())
        self.lighting_samples = int(lighting_samples)
        self.brdfs = nn.ModuleList(material_brdfs(scene))
        v = visibility.vertices
        self.register_buffer("positions", v.positions.to(torch.float64))
        self.register_buffer("normals", v.normals.to(torch.float64))
        self.register_buffer("object_ids", v.object_ids)
        self.register_buffer("vertex_texels", _vertex_texels(scene, len(v.positions)))
        env = envmap if envmap is not None else scene.environment
        if env is None:
            raise SceneError(f"scene {scene.name!r} has no environment map; pass envmap=")
        self.set_lighting(env)
        self._bases = {l: dct_basis(self.geometry.block, l, dtype) for l in (2, 4)}

    @property
    def textured(self) -> bool:
        """Whether some object has a base-colour texture (sampled per vertex by :meth:`image`)."""
        return any("base_color" in o.textures for o in self.scene.objects)

    # -- state ----------------------------------------------------------------------------
    def set_lighting(self, envmap: EnvironmentMap) -> None:
        """New lighting (e.g. ``envmap.rotated(angle)``): recompute the block representations."""
        # the map is the scene's (an input, float64 rotation): not a submodule, so that
        # ``.to(dtype)`` on the renderer neither converts nor mutates it
        self.__dict__["envmap"] = envmap
        self.lighting = block_lighting(envmap, self.geometry, self.lighting_samples, self.dtype)

    def _apply(self, fn, recurse=True):
        """``.to(dtype/device)``, ``.double()``, ...: the buffers and BRDFs, and the products'
        dtype with the lighting and DCT bases recomputed in it (not rounded from the old dtype)."""
        super()._apply(fn, recurse)
        self.dtype = fn(torch.zeros((), dtype=self.dtype)).dtype
        lighting = block_lighting(self.envmap, self.geometry, self.lighting_samples, self.dtype)
        self.lighting = BlockLighting(*(fn(getattr(lighting, f.name)) for f in dataclasses.fields(lighting)))
        self._bases = {l: fn(dct_basis(self.geometry.block, l, self.dtype)) for l in (2, 4)}
        return self

    def set_material(self, obj: str | int, brdf: BRDF | dict | str) -> None:
        """Give object ``obj`` (name or id) a new BRDF (module, material dict or registry name)."""
        o = self.scene.object_id(obj) if isinstance(obj, str) else int(obj)
        if not 0 <= o < len(self.brdfs):
            raise SceneError(f"no object {obj!r} in scene {self.scene.name!r}")
        self.brdfs[o] = brdf if isinstance(brdf, BRDF) else create(brdf)

    # -- views ----------------------------------------------------------------------------
    def view(self, camera: Camera | None = None) -> View:
        """The G-buffer of ``camera`` (default: the scene's), culling the vertices to those of
        the triangles hit, with their visibility and the environment behind the misses."""
        cam = camera if camera is not None else self.scene.camera
        gb = trace_gbuffer(self.scene, cam)
        _, d = cam.generate_rays(dtype=torch.float64)
        bg = self.envmap.eval_miss(d).float()
        bg[gb.pixels] = 0
        return View(gb, bg, self.visibility.blocks.select(gb.vertex_ids))

    def all_vertices(self, eye) -> View:
        """A view of every vertex from the point ``eye`` (no image; for tests and baselines)."""
        cam = self.scene.camera
        gb = GBuffer.of_vertices(torch.arange(len(self.positions)), eye, cam.height, cam.width)
        return View(gb, torch.zeros(0, 3), self.visibility.blocks)

    def image(self, view: View, radiance: torch.Tensor, background: bool = True) -> torch.Tensor:
        """Interpolate per-vertex radiance (P, C) at the primary hits: (H, W, C) float32."""
        if radiance.shape[0] != len(view.vertex_ids):
            raise ShapeError(f"Expected radiance for {len(view.vertex_ids)} vertices; got {tuple(radiance.shape)}")
        gb = view.gbuffer
        img = view.background.clone() if background else torch.zeros_like(view.background)
        rad = radiance.to(torch.float64)
        if self.textured:  # per-vertex texture sampling: the texel at each vertex scales its radiance
            rad = rad * self.vertex_texels[view.vertex_ids].to(torch.float64)
        img[gb.pixels] = (rad[gb.corners] * gb.weights[..., None]).sum(1).float()
        return img.view(gb.height, gb.width, -1)

    def render(self, camera: Camera | None = None, method: str = "adaptive", **kwargs):
        """An image: ``(H, W, C)`` float32 and the frame statistics (adaptive only, else None).

        Args:
            camera: default the scene's.
            method: ``"adaptive"`` (ours), ``"standard"`` or ``"haar"`` (with ``fraction=``).
        """
        if method not in METHODS:
            raise ValueRangeError(f"method must be one of {METHODS}; got {method!r}")
        v = self.view(camera)
        if method == "adaptive":
            rad, stats = self.shade(v, **kwargs)
        elif method == "standard":
            rad, stats = self.shade_standard(v, **kwargs), None
        else:
            rad, stats = self.shade_haar(v, **kwargs), None
        return self.image(v, rad), stats

    # -- shading --------------------------------------------------------------------------
    def _frames(self, view: View):
        vid = view.vertex_ids
        pos = self.positions[vid].to(self.dtype)
        nrm = self.normals[vid].to(self.dtype)
        wo = view.gbuffer.eye.to(self.dtype) - pos
        wo = wo / wo.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(self.dtype).tiny)
        frames = Frame.from_normal(nrm)
        return nrm, frames, frames.to_local(wo), self.object_ids[vid]

    def frame_path(self, rule: SamplingRule | None = None) -> str:
        """The code path :meth:`shade` takes with ``rule`` (default the renderer's):
        ``"compiled"`` or ``"torch"`` (see :attr:`compiled`)."""
        rule = rule if rule is not None else self.rule
        if self.compiled is False:
            return "torch"
        why = _relight.unsupported(self, rule)
        if why is not None and self.compiled:
            raise ValueRangeError(f"the compiled relighting frame cannot shade this: {why}")
        return "torch" if why else "compiled"

    @torch.no_grad()
    def shade(
        self, view: View, rule: SamplingRule | None = None, progress: bool | None = None
    ) -> tuple[torch.Tensor, FrameStats]:
        """Outgoing radiance of the view's vertices by Algorithm 1: the compiled frame when it
        supports the scene (:meth:`frame_path`), else :meth:`shade_torch`.

        Args:
            view: the vertices to shade.
            rule: BRDF sampling rule (default the renderer's).
            progress: tqdm bar (the torch path: over the (vertex, block) pairs; the compiled
                frame: over ranges of vertices).
        Returns:
            radiance (P, C) in the renderer's dtype, and :class:`FrameStats`.
        """
        rule = rule if rule is not None else self.rule
        if self.frame_path(rule) == "torch":
            return self.shade_torch(view, rule, progress)
        return self.shade_compiled(view, rule, progress)

    @torch.no_grad()
    def shade_compiled(
        self, view: View, rule: SamplingRule | None = None, progress: bool | None = None
    ) -> tuple[torch.Tensor, FrameStats]:
        """:meth:`shade_torch` by the compiled kernel (``transport/csrc/relight.c``) over
        :attr:`threads` threads (None: the usable cores). Same rule, samples and block cases;
        the sums in another order (float32 rounding apart, see :mod:`torch_brdf.render._relight`).

        Args:
            view: the vertices to shade.
            rule: BRDF sampling rule (default the renderer's).
            progress: tqdm bar over ranges of vertices (None: on in a terminal or notebook).
        Returns:
            radiance (P, C) float32, and :class:`FrameStats`.
        Raises:
            ValueRangeError: the kernel does not support this renderer or rule.
        """
        rule = rule if rule is not None else self.rule
        why = _relight.unsupported(self, rule)
        if why is not None:
            raise ValueRangeError(f"the compiled relighting frame cannot shade this: {why}")
        threads = self.threads if self.threads is not None else usable_cores()
        out, counts = _relight.shade(self, view, rule, max(1, int(threads)), progress=progress)
        P = len(view.vertex_ids)
        stats = FrameStats(vertices=P, blocks=P * self.geometry.block_count)
        stats.cases = {k: counts[k] for k in stats.cases}
        stats.sampling = {k: counts[k] for k in stats.sampling}
        stats.brdf_evals, stats.visibility_entries = counts["brdf_evals"], counts["visibility_entries"]
        return out, stats

    @tuned_method("triple.frame", lambda r, view, *a, **k: len(view.vertex_ids))
    @torch.no_grad()
    def shade_torch(
        self, view: View, rule: SamplingRule | None = None, progress: bool | None = None
    ) -> tuple[torch.Tensor, FrameStats]:
        """Outgoing radiance of the view's vertices by Algorithm 1 in torch (the reference of
        the compiled frame; any BRDF, rule and dtype).

        Args:
            view: the vertices to shade.
            rule: BRDF sampling rule (default the renderer's).
            progress: tqdm bar over the (vertex, block) pairs, a tick per object and sampling
                level (None: on in a terminal or notebook).
        Returns:
            radiance (P, C) in the renderer's dtype, and :class:`FrameStats`.
        """
        rule = rule if rule is not None else self.rule
        blocks = view.blocks
        NB = self.geometry.block_count
        nrm, frames, wo, oid = self._frames(view)
        P = len(view.vertex_ids)
        C = self.lighting.texels.shape[-1]
        out = torch.zeros(P, C, dtype=self.dtype)
        stats = FrameStats(vertices=P, blocks=P * NB)
        states = blocks.states
        pv, pb = (states != 0).nonzero(as_tuple=True)
        pstate = states[pv, pb]
        stats.cases["occluded"] = P * NB - len(pv)
        sampler = _Sampler(self.geometry, self.dtype, self.lighting.texels.sum(1).amax(-1))
        lit = self.lighting
        values = blocks.values(self.dtype)
        integral = lit.integral.reshape(-1, 3 * C)  # (NB S^2, 3 C) rows for line 9
        bar = tqdm(total=len(pv), desc="shade adaptive", unit="pair", disable=not progress_default(progress))
        for o in torch.unique(oid[pv]).tolist():
            rows = (oid[pv] == o).nonzero().squeeze(-1)
            v, b, st = pv[rows], pb[rows], pstate[rows]
            pairs = _Pairs(Frame(frames.s[v], frames.t[v], frames.n[v]), wo[v], b, v)
            for l, (idx, coef) in rule.project(self.brdfs[o], pairs, sampler).items():
                if len(idx) == 0:
                    continue
                stats.sampling[str(l * l)] += len(idx)
                vv, bb, full = v[idx], b[idx], st[idx] == 1
                n_pair = nrm[vv]
                contrib = torch.zeros(len(idx), C, dtype=self.dtype)
                # line 6: unoccluded block
                fi = full.nonzero().squeeze(-1)
                if len(fi):
                    stats.cases["line6"] += len(fi)
                    if l == 1:  # one coefficient: a gather of the DC term, no block grouping needed
                        g = lit.dct[bb[fi], 0]  # (m, 3, C)
                        contrib[fi] = coef[fi, 0] * (n_pair[fi, :, None] * g).sum(1)
                    else:
                        table = lit.moments if l == 16 else lit.dct[:, low_indices(l)]
                        contrib[fi] = _block_contract(coef[fi], n_pair[fi], bb[fi], table)
                pi = (~full).nonzero().squeeze(-1)
                if len(pi):
                    ids = vv[pi] * NB + bb[pi]
                    row, ent = _entries(blocks.offsets, ids)
                    stats.visibility_entries += len(ent)
                    if l == 1:  # line 9: constant BRDF, L_int . V_d over the non-zero entries
                        stats.cases["line9"] += len(pi)
                        flat = bb[pi][row] * self.geometry.block_size + blocks.index[ent].long()
                        Mi = integral.index_select(0, flat) * values[ent][:, None]  # (E, 3 C)
                        acc = torch.zeros(len(pi), Mi.shape[1], dtype=self.dtype).index_add_(0, row, Mi)
                        irr = (acc.view(len(pi), 3, C) * n_pair[pi][:, :, None]).sum(1)
                        contrib[pi] = irr * coef[pi, 0] / self.geometry.block  # f = A_00 B_00, B_00 = 1/S
                    else:  # line 11: pixel product with the visibility expanded from its flips
                        stats.cases["line11"] += len(pi)
                        Vd = torch.zeros(len(pi), self.geometry.block_size, dtype=self.dtype)
                        Vd.index_put_((row, blocks.index[ent].long()), values[ent], accumulate=True)
                        V = Vd.cumsum(1)
                        f = coef[pi] if l == 16 else torch.einsum("mkc,kt->mtc", coef[pi], self._bases[l])
                        contrib[pi] = _block_contract(V[:, :, None] * f, n_pair[pi], bb[pi], lit.moments)
                out.index_add_(0, vv, contrib)
                bar.update(len(idx))
        bar.close()
        stats.brdf_evals = sampler.evals
        return out, stats

    @torch.no_grad()
    def shade_standard(
        self,
        view: View,
        chunk: int = 512,
        dense_visibility: torch.Tensor | None = None,
        progress: bool | None = None,
    ) -> torch.Tensor:
        """The standard-basis triple product: the dense sum over all texels (the baseline).

        Args:
            view: the vertices to shade.
            chunk: vertices per batch.
            dense_visibility: optional (P, NB, S^2) visibility already expanded (as a
                standard-basis system would store it); decoded here otherwise.
            progress: tqdm bar over vertex chunks (None: on in a terminal or notebook).
        Returns:
            (P, C) radiance.
        """
        _nrm, frames, wo, oid = self._frames(view)
        P = len(view.vertex_ids)
        L = self.lighting.texels.reshape(-1, self.lighting.texels.shape[-1])  # (T, C)
        out = torch.zeros(P, L.shape[-1], dtype=self.dtype)
        starts = range(0, P, chunk)
        for s in tqdm(starts, desc="shade standard", unit="chunk", disable=not progress_default(progress)):
            e = min(P, s + chunk)
            rows = torch.arange(s, e)
            if dense_visibility is None:
                V = view.blocks.decode(rows, dtype=self.dtype).reshape(e - s, -1)
            else:
                V = dense_visibility[s:e].to(self.dtype).reshape(e - s, -1)
            out[s:e] = torch.einsum("mt,mtc,tc->mc", V, self._texel_brdf(frames, wo, oid, rows), L)
        return out

    @torch.no_grad()
    def shade_haar(
        self,
        view: View,
        fraction: float = 0.01,
        chunk: int = 256,
        timings: dict | None = None,
        progress: bool | None = None,
    ) -> torch.Tensor:
        """The Haar-wavelet triple product of Ng et al. 2004 (the wavelet baseline).

        Lighting and the cosine-folded BRDF are kept to their ``fraction`` largest Haar
        coefficients per cubemap (non-linear approximation), visibility exactly; the product
        runs on the coefficients by the tripling-coefficient rules
        (:class:`~torch_brdf.sphere.haar.HaarTripleProduct`). Ng et al. precompute the
        visibility wavelets and tabulate rotated BRDF wavelets; here both are computed per
        call, and ``timings`` (if given) receives the seconds of each stage separately:
        ``visibility_s``, ``brdf_s`` (sampling every texel + transform + truncation) and
        ``product_s`` (the triple product alone, the figure comparable with a frame of theirs).
        ``progress``: tqdm bar over vertex chunks (None: on in a terminal or notebook).

        Returns:
            (P, C) radiance.
        """
        geom = self.geometry
        htp = HaarTripleProduct()
        htp.set_lighting(geom.from_blocks(self.lighting.texels.to(torch.float32)), fraction)
        P, C = len(view.vertex_ids), self.lighting.texels.shape[-1]
        out = torch.zeros(P, C, dtype=self.dtype)
        _nrm, frames, wo, oid = self._frames(view)
        t = {"visibility_s": 0.0, "brdf_s": 0.0, "product_s": 0.0}
        starts = range(0, P, chunk)
        for s in tqdm(starts, desc="shade haar", unit="chunk", disable=not progress_default(progress)):
            rows = torch.arange(s, min(P, s + chunk))
            t0 = time.perf_counter()
            V = geom.from_blocks(view.blocks.decode(rows), lead=1)
            Vc = htp.visibility_coefficients(V)
            t1 = time.perf_counter()
            rho = self._texel_brdf(frames, wo, oid, rows).view(len(rows), geom.block_count, geom.block_size, C)
            rho = geom.from_blocks(rho.to(torch.float32), lead=1)
            bc = htp.brdf_coefficients(rho, fraction)
            t2 = time.perf_counter()
            out[rows] = htp.product(Vc, bc).to(self.dtype)
            t3 = time.perf_counter()
            t["visibility_s"] += t1 - t0
            t["brdf_s"] += t2 - t1
            t["product_s"] += t3 - t2
        if timings is not None:
            timings.update(t)
        return out

    @torch.no_grad()
    def cosine_brdf_texels(self, view: View, rows: torch.Tensor) -> torch.Tensor:
        """The cosine-folded BRDF at every texel for some of the view's vertices:
        (m, NB, S^2, C), :math:`f(\\omega_t, \\omega_o)\\max(0, n\\cdot\\omega_t)`."""
        _nrm, frames, wo, oid = self._frames(view)
        C = self.lighting.texels.shape[-1]
        texels = self._texel_brdf(frames, wo, oid, rows)
        return texels.view(len(rows), self.geometry.block_count, self.geometry.block_size, C)

    def _texel_brdf(self, frames: Frame, wo: torch.Tensor, oid: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """f max(0, n.w) at every texel centre for the shaded vertices ``rows``: (m, T, C)."""
        dirs = self.geometry.directions.reshape(-1, 3).to(self.dtype)
        f = Frame(frames.s[rows], frames.t[rows], frames.n[rows])
        loc = torch.stack((f.s @ dirs.T, f.t @ dirs.T, f.n @ dirs.T), -1)  # (m, T, 3)
        C = self.lighting.texels.shape[-1]
        out = torch.zeros(len(rows), dirs.shape[0], C, dtype=self.dtype)
        for o in torch.unique(oid[rows]).tolist():
            r = (oid[rows] == o).nonzero().squeeze(-1)
            w = wo[rows][r][:, None, :].expand_as(loc[r])
            fr = self.brdfs[o].eval_local(loc[r].reshape(-1, 3), w.reshape(-1, 3)).reshape(len(r), -1, C)
            out[r] = fr.to(self.dtype) * loc[r][..., 2:3].clamp_min(0)
        return out


def _block_contract(w: torch.Tensor, n: torch.Tensor, blocks: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    r""":math:`\sum_{k,j} w_{mkc}\, n_{mj}\, T_{b_m kjc}` for pairs grouped by block.

    Gathering the (K, 3, C) table of every pair would copy K x 9 numbers per pair; grouping
    the pairs by block keeps each block's table in cache and makes the sum one small matmul
    per block present.

    Args:
        w: (m, K, C) per-pair weights (BRDF coefficients, or visibility x BRDF per texel).
        n: (m, 3) normals.
        blocks: (m,) block ids.
        table: (NB, K, 3, C) lighting representation.
    Returns:
        (m, C).
    """
    m, C = w.shape[0], w.shape[-1]
    out = torch.empty(m, C, dtype=w.dtype)
    order = torch.argsort(blocks)
    ids, counts = torch.unique_consecutive(blocks[order], return_counts=True)
    wc = w.permute(2, 0, 1)  # (C, m, K)
    for b, rows in zip(ids.tolist(), torch.split(order, counts.tolist()), strict=True):
        x = torch.bmm(wc[:, rows], table[b].permute(2, 0, 1))  # (C, r, 3)
        out[rows] = (x * n[rows].unsqueeze(0)).sum(-1).T
    return out


def _entries(offsets: torch.Tensor, ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat CSR entries of pairs ``ids``: (row of the pair in ``ids``, entry index)."""
    start, stop = offsets[ids], offsets[ids + 1]
    counts = stop - start
    row = torch.repeat_interleave(torch.arange(len(ids)), counts)
    first = torch.cumsum(counts, 0) - counts
    ent = torch.repeat_interleave(start - first, counts) + torch.arange(int(counts.sum()))
    return row, ent
