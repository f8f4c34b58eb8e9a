r"""A linear edge-aware filter: the à-trous wavelet filter with edge-stopping weights from
the guide buffers only (Dammertz et al., "Edge-avoiding à-trous wavelet transform for fast
global illumination filtering", HPG 2010; without their colour term, which would make the
filter depend on the image and so non-linear).

Level :math:`l = 0..L-1` convolves with the B3-spline kernel :math:`h = (1, 4, 6, 4, 1)/16`
(separable, 5 x 5 taps) dilated by :math:`2^l`, each tap :math:`q` of pixel :math:`p` weighted by

.. math:: w(p, q) = h_q\,[o_p = o_q]\,[m_p = m_q]\,\max(0, n_p\cdot n_q)^{\sigma_n}
          \exp\!\Big(-\frac{|n_p\cdot(x_q - x_p)|}{\sigma_x\,\delta_p\,|q - p|}\Big)
          \exp\!\Big(-\frac{\lVert a_p - a_q\rVert_1}{\sigma_a}\Big)
          \exp\!\Big(-\frac{\lVert \log(1 + L_p) - \log(1 + L_q)\rVert_1}{\sigma_m}\Big)
          \exp\!\Big(-\frac{|\cos\theta_{h,p} - \cos\theta_{h,q}|}{\sigma_h}\Big),

(object id :math:`o`, normal :math:`n`, position :math:`x`, albedo proxy :math:`a`, pixel
footprint :math:`\delta_p` = depth x pixel angle, object :math:`m` and emitted radiance
:math:`L` seen by the mirror ray, half-vector cosine :math:`\cos\theta_h` to the brightest
light: see :mod:`.guides`; the last factor only on ``glossy`` objects) and normalised to
sum to 1 over the taps. The mirror terms keep the reflection of a light or an object on a glossy surface from
being smeared over the whole surface; what they cannot keep is the soft falloff of a broad
lobe's highlight inside one mirror region (blurred at the footprint's scale), nor contact
shadows on one plane (same object, normal and plane on both sides).

Only *interior* pixels are filtered and used as taps: those whose 3 x 3 neighbourhood of pixel
centres sees one object. A silhouette pixel's jittered samples may see two objects, so the
precomputation keeps records of both there; leaving those pixels as they are (the identity)
means the filter never moves one object's records into another object's pixels, so the
denoised record covers the same pixels as the noisy one (the frame costs the same).

The weights never cross object ids and depend on the guides alone, so each level, and the
cascade, is one fixed linear operator :math:`A` on images: it commutes with any linear
combination of basis images, which is what keeps every denoised BRDF edit exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..errors import ShapeError, ValueRangeError
from ..parallel.threads import tuned
from ..records.guides import GuideBuffers

_B3 = (1 / 16, 1 / 4, 3 / 8, 1 / 4, 1 / 16)


@dataclass(frozen=True)
class GuideSigmas:
    """The tolerances of the guide weights (:class:`GuideWeights`), shared by the settings of
    the linear filters.

    Attributes:
        sigma_normal: exponent of the normal weight (larger: stops at smaller creases).
        sigma_plane: tolerance of the distance to the tangent plane, in pixel footprints per
            pixel of offset (smaller: stops at smaller depth steps, e.g. contact edges).
        sigma_albedo: tolerance of the albedo-proxy difference (L1).
        sigma_mirror: tolerance of the difference of log(1 + radiance seen by the mirror ray).
        sigma_half: tolerance of the difference of the half-vector cosine to the brightest
            light (a Blinn-Phong lobe of exponent n falls by 1/e over 1/n of it; ``inf``: off).
    """

    sigma_normal: float = 64.0
    sigma_plane: float = 1.0
    sigma_albedo: float = 0.05
    sigma_mirror: float = 0.25
    sigma_half: float = 0.002

    def __post_init__(self):
        if min(self.sigma_normal, self.sigma_plane, self.sigma_albedo, self.sigma_mirror, self.sigma_half) <= 0:
            raise ValueRangeError(f"need positive sigmas; got {self}")


@dataclass(frozen=True)
class AtrousSettings(GuideSigmas):
    """What decides the à-trous filter (hashable; benchmarks report it): the guide
    tolerances of :class:`GuideSigmas` and

    Attributes:
        levels: à-trous levels; the footprint is :math:`4 (2^L - 1) + 1` pixels wide.
    """

    levels: int = 3

    def __post_init__(self):
        super().__post_init__()
        if self.levels < 1:
            raise ValueRangeError(f"need levels >= 1; got {self}")


def _shift(x: torch.Tensor, dy: int, dx: int, fill: float = 0.0) -> torch.Tensor:
    """``out[..., y, x] = x[..., y + dy, x + dx]`` (``fill`` outside): (..., H, W) -> (..., H, W)."""
    h, w = x.shape[-2:]
    out = torch.full_like(x, fill)
    ys, yd = slice(max(dy, 0), h + min(dy, 0)), slice(max(-dy, 0), h + min(-dy, 0))
    xs, xd = slice(max(dx, 0), w + min(dx, 0)), slice(max(-dx, 0), w + min(-dx, 0))
    if ys.start < ys.stop and xs.start < xs.stop:
        out[..., yd, xd] = x[..., ys, xs]
    return out


def glossy_objects(tensors) -> list[int]:
    """Object ids of ``tensors`` with more than one band (J > 1): the filters' glossy objects."""
    return [m for m, b in enumerate(tensors.bases) if b is not None and b.J > 1]


class GuideWeights:
    """The edge-stopping weight of tap ``q = p + (dy, dx)`` for every pixel ``p`` of a view,
    from the guides only (the product in this module's docstring, without the spatial kernel):
    shared by :class:`EdgeAwareFilter` and :class:`~.regression.RegressionFilter`.

    Args:
        guides: the view's :class:`GuideBuffers`.
        glossy: object ids where the half-vector guide applies.
        keep: remember every weight computed (per offset and tolerances), so filters that share
            this object (the candidates of :class:`~.selection.SelectedRegressionFilter`) compute
            each tap once (memory: one (H, W) float64 plane per offset kept).

    Attributes:
        interior: (H, W) bool pixels whose 3 x 3 neighbourhood sees one object (the only
            pixels filtered and used as taps).
    """

    def __init__(self, guides: GuideBuffers, glossy=(), keep: bool = False):
        g = guides
        self.guides, self.glossy = guides, tuple(sorted(int(o) for o in glossy))
        self._kept: dict | None = {} if keep else None
        self.oid = g.object_id.double()
        self.n = g.normal.double().permute(2, 0, 1)  # (3, H, W)
        self.x = g.position.double().permute(2, 0, 1)
        self.a = g.albedo.double().permute(2, 0, 1)
        self.mid = g.mirror_id.double()
        self.ml = torch.log1p(g.mirror_radiance.double().clamp_min(0)).permute(2, 0, 1)
        self.ch = g.light_cos_h.double()
        self.gl = torch.isin(g.object_id, torch.tensor(sorted(glossy), dtype=torch.long))
        foot = torch.where(torch.isfinite(g.depth), g.depth.double(), 0.0) * g.pixel_angle
        self.foot = foot.clamp_min(1e-12)
        same = torch.stack([_shift(self.oid, dy, dx, fill=-2.0) == self.oid for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
        self.interior = same.all(0) & (g.object_id >= 0)

    def weight(self, dy: int, dx: int, s) -> torch.Tensor:
        """(H, W) float64 weight of the tap at offset (dy, dx); 0 across object ids, mirror
        ids, and from silhouette taps. ``s`` carries ``sigma_normal``, ``sigma_plane``,
        ``sigma_albedo``, ``sigma_mirror`` and ``sigma_half`` (:class:`AtrousSettings`)."""
        if self._kept is None:
            return self._weight(dy, dx, s)
        key = (dy, dx, s.sigma_normal, s.sigma_plane, s.sigma_albedo, s.sigma_mirror, s.sigma_half)
        if key not in self._kept:
            self._kept[key] = self._weight(dy, dx, s)
        return self._kept[key]

    def _weight(self, dy: int, dx: int, s) -> torch.Tensor:
        oid, n, x, a, ml, ch = self.oid, self.n, self.x, self.a, self.ml, self.ch
        o_q = _shift(oid, dy, dx, fill=-2.0)  # -2: outside the image
        inner_q = _shift(self.interior.double(), dy, dx) > 0
        same = (o_q == oid) & (_shift(self.mid, dy, dx, fill=-3.0) == self.mid)
        wt = torch.where(same & inner_q, 1.0, 0.0).double()
        if dy or dx:
            n_q, x_q, a_q = _shift(n, dy, dx), _shift(x, dy, dx), _shift(a, dy, dx)
            wt = wt * (n * n_q).sum(0).clamp_min(0) ** s.sigma_normal
            plane = ((x_q - x) * n).sum(0).abs() / (s.sigma_plane * self.foot * (dy * dy + dx * dx) ** 0.5)
            wt = wt * torch.exp(-plane) * torch.exp(-(a - a_q).abs().sum(0) / s.sigma_albedo)
            wt = wt * torch.exp(-(ml - _shift(ml, dy, dx)).abs().sum(0) / s.sigma_mirror)
            wt = torch.where(self.gl, wt * torch.exp(-(ch - _shift(ch, dy, dx)).abs() / s.sigma_half), wt)
        return wt


class GuideFilter:
    """What the linear guide-only filters share: building from a record that carries its
    guides, and the input check. Subclasses take ``(guides, settings, glossy=...)``."""

    shape: tuple[int, int]

    @classmethod
    def for_tensors(cls, tensors, settings=None):
        """The filter of a record that carries its guides (``tensors.guides``, e.g. the
        multibounce tensors), with the half-vector guide on its banded objects (J > 1).

        Raises:
            ValueRangeError: the record has no guides (attach :func:`~torch_brdf.transport.guides.guide_buffers`).
        """
        if getattr(tensors, "guides", None) is None:
            raise ValueRangeError("the record has no guide buffers; attach guide_buffers(scene) first")
        return cls(tensors.guides, settings, glossy=glossy_objects(tensors))

    def _setup(self, guides: GuideBuffers, settings, kind: type, glossy) -> None:
        """The fields every guide filter keeps: ``guides``, ``settings`` (``kind()`` when None;
        another type is refused), ``glossy`` (sorted object ids) and ``shape`` (H, W)."""
        self.guides = guides
        self.settings = kind() if settings is None else settings
        if not isinstance(self.settings, kind):
            raise ValueRangeError(f"expected {kind.__name__}; got {type(self.settings).__name__}")
        self.glossy = tuple(sorted(int(o) for o in glossy))
        self.shape = (guides.height, guides.width)

    def _planes(self, images: torch.Tensor) -> torch.Tensor:
        """images (..., H, W) -> planes (N, H, W), after checking the shape."""
        if images.ndim < 2 or tuple(images.shape[-2:]) != self.shape:
            raise ShapeError(
                f"expected images of shape (..., {self.shape[0]}, {self.shape[1]}); got {tuple(images.shape)}"
            )
        return images.reshape(-1, *self.shape)


class EdgeAwareFilter(GuideFilter):
    """The à-trous cascade for one view, weights precomputed from ``guides``.

    Args:
        guides: the view's :class:`GuideBuffers`.
        settings: :class:`AtrousSettings` (default: 3 levels, a 29-pixel footprint).
        glossy: object ids whose pixels also stop at half-vector changes (objects with more
            than one band; default none). Which objects are banded is part of the record
            (its bases), not of any material value, so the filter stays fixed under edits.

    Calling it on planes (N, H, W) returns the filtered planes (N, H, W) in their dtype:
    ``A(a x + b y) == a A(x) + b A(y)`` up to rounding.
    """

    def __init__(self, guides: GuideBuffers, settings: AtrousSettings | None = None, glossy=()):
        self.guides = guides
        self.settings = settings or AtrousSettings()
        self.glossy = tuple(sorted(int(o) for o in glossy))
        self.shape = (guides.height, guides.width)
        # many small elementwise ops: under load two OpenMP threads can be 15x slower than one
        with tuned("denoise.atrous_weights", guides.height * guides.width * self.settings.levels):
            self._build()

    def _build(self) -> None:
        s = self.settings
        gw = GuideWeights(self.guides, self.glossy)
        interior = self.interior = gw.interior
        self.offsets: list[list[tuple[int, int]]] = []
        self.weights: list[torch.Tensor] = []  # per level (25, H, W), normalised over taps
        for level in range(s.levels):
            step = 2**level
            offs, ws = [], []
            for iy, hy in enumerate(_B3):
                for ix, hx in enumerate(_B3):
                    dy, dx = (iy - 2) * step, (ix - 2) * step
                    offs.append((dy, dx))
                    ws.append(hy * hx * gw.weight(dy, dx, s))
            wl = torch.stack(ws)
            centre = len(offs) // 2  # the (0, 0) tap: silhouette pixels keep their value
            wl = torch.where(interior, wl, torch.zeros_like(wl))
            wl[centre] = torch.where(interior, wl[centre], 1.0)
            self.weights.append((wl / wl.sum(0).clamp_min(1e-300)).float())
            self.offsets.append(offs)

    @property
    def description(self) -> str:
        return f"linear a-trous {self.settings}, glossy objects {list(self.glossy)}"

    def __call__(self, images: torch.Tensor, groups: torch.Tensor | None = None) -> torch.Tensor:
        """Filter images (..., H, W) (any float dtype; e.g. (B, 3, H, W) basis images) ->
        the same shape. ``groups`` is ignored (a linear filter treats every image alike)."""
        lead = images.shape[:-2]
        x = self._planes(images)
        h, w = self.shape
        with tuned("denoise.atrous", x.numel() * len(self.offsets)):
            for offs, wl in zip(self.offsets, self.weights, strict=True):
                pad = abs(offs[0][0])  # the first tap is (-2 step, -2 step)
                xp = F.pad(x, (pad, pad, pad, pad))
                out = torch.zeros_like(x)
                wl = wl.to(x.dtype)
                for k, (dy, dx) in enumerate(offs):
                    out += wl[k] * xp[:, pad + dy : pad + dy + h, pad + dx : pad + dx + w]
                x = out
        return x.reshape(*lead, h, w)
