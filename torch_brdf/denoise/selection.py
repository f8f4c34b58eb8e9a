r"""A linear denoiser that picks, per pixel, the local regression whose error is lowest,
with the error estimated from two independent half-sample buffers (NFOR's selection,
Bitterli et al., "Nonlinearly weighted first-order regression for denoising Monte Carlo
renderings", EGSR 2016, Sec. 5, with cross-validated instead of SURE errors).

The candidates are :class:`~.regression.RegressionFilter` s of several window radii and
degrees (and the identity), all with the guide-only weights of :class:`~.atrous.GuideWeights`.
Given two independent estimates :math:`a, b` of the same pilot image (e.g. the frame of two
half-spp precomputations at the freeze-time material), the mean-squared error of candidate
:math:`A_k` applied to the full buffer :math:`y = (a + b)/2` at pixel :math:`p` is, up to a
term common to all candidates,

.. math:: \hat R_k(p) = \tfrac12\big[(A_k a - b)_p^2 + (A_k b - a)_p^2\big]
          - \tfrac14 (A_k a - A_k b)_p^2,

because :math:`E(A_k a - b)^2 = \mathrm{bias}_k^2 + \mathrm{Var}(A_k a) + \mathrm{Var}\,b`,
:math:`E(A_k a - A_k b)^2 = 2\,\mathrm{Var}(A_k a)` and the full buffer has half the variance
of a half buffer (for the identity :math:`\hat R` is :math:`\tfrac34 (a - b)^2`, i.e.
:math:`\mathrm{Var}\,y + \mathrm{Var}\,b`). :math:`\hat R_k` is summed over channels and
pilot pairs, smoothed by a box of radius ``smooth`` inside each object, and every pixel takes
the candidate of lowest :math:`\hat R_k`: small windows at soft shadows, contact and
reflections the guides do not see, large ones on flat shading.

The pick is computed **once from fixed data** (the halves) and then frozen: the filter is
one fixed set of hat weights, applied alike to every basis image, so it is linear and
every BRDF edit stays exact, as with the other linear filters. It never crosses object ids
(each candidate's weights do not).

Silhouette pixels (whose 3 x 3 neighbourhood sees two objects, or the image border) hold
records of both objects and are no regression's taps. They get candidates of their own:
the mean over pixels along the same edge (the same objects on the same side of it, the same
mirror object, similar normals; :func:`silhouette_signature`), chosen by the same error
estimate (smoothed along the edge) against the unfiltered pixel, so a pixel whose coverage
differs from its neighbours' keeps its value. Their taps stay inside pixels that see the same
pair of objects, so the denoised record covers the same pixels (the frame costs the same).

What it cannot do: choose for a material it never saw (the pick follows the pilots; an edit
that makes a reflection sharper than the pilot's keeps the pilot's windows; pilots at several
probe materials, ``relative=True``, spread the pick over them) and remove structure no
candidate keeps.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..errors import ShapeError, ValueRangeError
from ..parallel.threads import tuned
from ..records.guides import GuideBuffers
from .atrous import GuideFilter, GuideSigmas, GuideWeights, _shift
from .regression import RegressionFilter, RegressionSettings, apply_hat


@dataclass(frozen=True)
class SelectionSettings(GuideSigmas):
    """What decides the selecting filter (hashable; benchmarks report it).

    Attributes:
        candidates: (radius, degree) of each candidate regression (radius >= 1, degree 0-2).
        identity: also offer the unfiltered pixel.
        smooth: radius of the box that smooths the error estimates (0: per pixel).
        ridge: the candidates' ridge (:class:`~.regression.RegressionSettings`).
        silhouette: radii of the silhouette candidates: for a pixel whose 3 x 3 neighbourhood
            sees two objects (or the image border), the mean over its window of the pixels of
            the same *signature* (:func:`silhouette_signature`: the same objects, on the same
            side of the edge) and the same mirror object, weighted by normal agreement
            (``sigma_normal``); () leaves silhouette pixels as they are.
        silhouette_smooth: radius of the box that smooths the silhouette pixels' error
            estimates (over pixels of the same signature).
        silhouette_regression: radii of the coverage regressions offered to silhouette pixels
            when the filter is given the pixels' coverage (:func:`~torch_brdf.transport.guides.pixel_coverage`):
            over the same taps as the silhouette means, a weighted least-squares fit of degree 1
            in the tap's coverage and its offset along x and y, evaluated at the pixel (an edge's
            pixels mix their objects in proportions that change along it; a mean blends them).
        relative: divide each pilot pair's error map by the image mean of its full buffer's
            square (summed over channels) before the pairs are summed, so that every pilot
            (e.g. each probe material of an edited object) counts as its relative squared
            error rather than by its brightness.
    """

    sigma_half: float = 0.02
    candidates: tuple[tuple[int, int], ...] = ((1, 1), (2, 2), (3, 2), (5, 2), (8, 1), (8, 2))
    identity: bool = True
    smooth: int = 12
    ridge: float = 1e-3
    silhouette: tuple[int, ...] = (1, 2, 4)
    silhouette_smooth: int = 6
    relative: bool = False
    silhouette_regression: tuple[int, ...] = (1, 2, 3, 5)

    def __post_init__(self):
        super().__post_init__()
        if not self.candidates or self.smooth < 0:
            raise ValueRangeError(f"need at least one candidate and smooth >= 0; got {self}")
        if any(r < 1 for r in self.silhouette + self.silhouette_regression) or self.silhouette_smooth < 0:
            raise ValueRangeError(f"need silhouette radii >= 1 and silhouette_smooth >= 0; got {self}")
        if self.silhouette and not self.identity:
            raise ValueRangeError("silhouette candidates need the identity (interior pixels' fallback)")

    def regression(self, radius: int, order: int) -> RegressionSettings:
        """The :class:`RegressionSettings` of one candidate (same guide tolerances)."""
        return RegressionSettings(
            sigma_normal=self.sigma_normal,
            sigma_plane=self.sigma_plane,
            sigma_albedo=self.sigma_albedo,
            sigma_mirror=self.sigma_mirror,
            sigma_half=self.sigma_half,
            radius=radius,
            order=order,
            ridge=self.ridge,
        )


def silhouette_signature(object_id: torch.Tensor) -> torch.Tensor:
    """(H, W) int64 id of each pixel's (centre object, least id, greatest id) over its 3 x 3
    neighbourhood (-2 beyond the image border): pixels of one signature lie on the same side
    of an edge between the same objects."""
    oid = object_id.double()[None, None]
    pad = F.pad(oid, (1, 1, 1, 1), value=-2.0)
    hi = F.max_pool2d(pad, 3, 1)[0, 0]
    lo = -F.max_pool2d(-pad, 3, 1)[0, 0]
    trip = torch.stack([object_id.double(), lo, hi], -1).reshape(-1, 3)
    return torch.unique(trip, dim=0, return_inverse=True)[1].reshape(object_id.shape)


def _box_within(x: torch.Tensor, label: torch.Tensor, r: int) -> torch.Tensor:
    """Mean of ``x`` (K, H, W) over the (2r + 1)² box of each pixel, over pixels of the same ``label``."""
    if r == 0:
        return x
    out = torch.zeros_like(x)
    count = torch.zeros_like(x[0])
    h, w = label.shape
    lp = F.pad(label[None, None].double(), (r, r, r, r), value=float("nan"))[0, 0]  # nan: equals no label
    xp = F.pad(x, (r, r, r, r))
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            same = (lp[r + dy : r + dy + h, r + dx : r + dx + w] == label).to(x.dtype)
            out += same * xp[:, r + dy : r + dy + h, r + dx : r + dx + w]
            count += same
    return out / count.clamp_min(1)


class SelectedRegressionFilter(GuideFilter):
    """Per-pixel choice among guide-weighted local regressions, picked once from half buffers.

    Args:
        guides: the view's :class:`GuideBuffers`.
        halves: pairs ``(a, b)`` of independent estimates of pilot images, each (..., H, W)
            (e.g. the frames of two half-spp precomputations, permuted to (C, H, W)).
        settings: :class:`SelectionSettings`.
        glossy: object ids where the half-vector guide applies.
        coverage: (H, W) fractions in [0, 1] of each pixel covered by its centre's object
            (:func:`~torch_brdf.transport.guides.pixel_coverage`); given, silhouette pixels also
            get the fits of ``settings.silhouette_regression``.

    Calling it on images (..., H, W) returns the filtered images; it is linear.

    Attributes:
        pick: (H, W) int64 index of each pixel's candidate in :attr:`names`.
        names: the candidates, ``"identity"``, ``"r{radius}o{degree}"``, ``"silhouette_r{radius}"`` or
            ``"silhouette_fit_r{radius}"``.
        coverage: the ``coverage`` given (None: none).
        interior: (H, W) bool pixels the regressions filter (the others: silhouette candidates).
        weights: ((2R + 1)², H, W) float32 hat weights (R the largest candidate radius).
    """

    def __init__(
        self,
        guides: GuideBuffers,
        halves: Sequence[tuple[torch.Tensor, torch.Tensor]],
        settings: SelectionSettings | None = None,
        glossy=(),
        coverage: torch.Tensor | None = None,
    ):
        self._setup(guides, settings, SelectionSettings, glossy)
        if coverage is not None:
            coverage = torch.as_tensor(coverage)
            if tuple(coverage.shape) != self.shape or not bool(((coverage >= 0) & (coverage <= 1)).all()):
                raise ShapeError(f"coverage must be {self.shape} fractions in [0, 1]; got {tuple(coverage.shape)}")
        self.coverage = coverage
        pairs = []
        for a, b in halves:
            a, b = torch.as_tensor(a), torch.as_tensor(b)
            if a.shape != b.shape:
                raise ShapeError(f"the halves of a pair differ in shape: {tuple(a.shape)} vs {tuple(b.shape)}")
            a, b = self._planes(a).double(), self._planes(b).double()
            scale = 1.0
            if self.settings.relative:
                scale = 1.0 / float((0.25 * (a + b) ** 2).sum(0).mean()) if bool((a + b).any()) else 0.0
            pairs.append((a, b, scale))
        if not pairs:
            raise ValueRangeError("need at least one pair of half buffers")
        # many small elementwise ops (the box over the error maps): pick the thread count
        with tuned("denoise.selection", guides.height * guides.width * (2 * self.settings.smooth + 1) ** 2):
            self._build(pairs)

    def _build(self, pairs) -> None:
        s = self.settings
        gw = GuideWeights(self.guides, self.glossy, keep=True)  # each tap's weight once for all candidates
        cands = [RegressionFilter(self.guides, s.regression(r, o), self.glossy, gw) for r, o in s.candidates]
        del gw
        self.names = (["identity"] if s.identity else []) + [f"r{r}o{o}" for r, o in s.candidates]
        interior = self.interior = cands[0].interior
        sil_radii = s.silhouette
        if sil_radii:
            self.signature = silhouette_signature(self.guides.object_id)
        sil = [_SilhouetteMean(self.guides, interior, self.signature, r, s.sigma_normal) for r in sil_radii]
        self.names += [f"silhouette_r{r}" for r in sil_radii]
        if sil_radii and self.coverage is not None:
            reg = s.silhouette_regression
            sil += [_SilhouetteFit(self.guides, interior, self.signature, self.coverage, r, s) for r in reg]
            self.names += [f"silhouette_fit_r{r}" for r in reg]
            sil_radii = tuple(sil_radii) + tuple(reg)
        risks = []
        for A in [None] * s.identity + cands + sil:
            risk = torch.zeros(self.shape, dtype=torch.float64)
            for a, b, scale in pairs:
                fa, fb = (a, b) if A is None else (A(a), A(b))
                risk += scale * (0.5 * ((fa - b) ** 2 + (fb - a) ** 2) - 0.25 * (fa - fb) ** 2).sum(0)
            risks.append(risk)
        risks = torch.stack(risks)
        first_sil = len(risks) - len(sil)
        inner = _box_within(risks, torch.where(interior, self.guides.object_id, -1), s.smooth)
        inner[first_sil:] = torch.inf  # silhouette candidates leave interior pixels as they are
        self.pick = inner.argmin(0)
        if sil:
            outer = _box_within(risks, torch.where(interior, -1, self.signature), s.silhouette_smooth)
            outer[s.identity : first_sil] = torch.inf  # the regressions leave silhouettes as they are
            self.pick = torch.where(interior, self.pick, outer.argmin(0))
        self.radius = max([r for r, _ in s.candidates] + list(sil_radii))
        big = self.radius
        self.offsets = [(dy, dx) for dy in range(-big, big + 1) for dx in range(-big, big + 1)]
        where = {o: k for k, o in enumerate(self.offsets)}
        hat = torch.zeros(len(self.offsets), *self.shape)
        hat[where[(0, 0)]] = 1.0  # the identity (pixels that pick it keep their value)
        first = 1 if s.identity else 0
        for k, A in enumerate(cands + sil):
            mine = self.pick == k + first
            rows = torch.tensor([where[o] for o in A.offsets])
            hat[:, mine] = 0.0
            hat[rows] = torch.where(mine, A.weights, hat[rows])
        self.weights = hat

    @property
    def description(self) -> str:
        counts = torch.bincount(self.pick.flatten(), minlength=len(self.names)).tolist()
        picks = dict(zip(self.names, counts, strict=True))
        return f"selected regression {self.settings}, glossy objects {list(self.glossy)}, picks {picks}"

    def __call__(self, images: torch.Tensor, groups: torch.Tensor | None = None) -> torch.Tensor:
        """Filter images (..., H, W) -> the same shape. ``groups`` is ignored (linear)."""
        return apply_hat(self, images)


class _SilhouetteMean:
    """The silhouette candidate of radius ``r`` (see :class:`SelectionSettings`): hat
    weights (offsets of radius r) that average, at every non-interior pixel, the non-interior
    pixels of the same signature and mirror object in its window, weighted by
    ``max(0, n_p . n_q) ** sigma_normal``; interior pixels keep their value (this candidate is
    never picked there)."""

    def __init__(
        self, guides: GuideBuffers, interior: torch.Tensor, signature: torch.Tensor, r: int, sigma_normal: float
    ):
        self.shape, self.radius = (guides.height, guides.width), r
        self.offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
        w = _silhouette_taps(guides, interior, signature, self.offsets, sigma_normal)
        w = w / w.sum(0)
        centre = self.offsets.index((0, 0))
        w = torch.where(interior, 0.0, w)
        w[centre] = torch.where(interior, 1.0, w[centre])
        self.weights = w.float()

    def _planes(self, images: torch.Tensor) -> torch.Tensor:
        return images.reshape(-1, *self.shape)

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        return apply_hat(self, images)


def _silhouette_taps(guides: GuideBuffers, interior, signature, offsets, sigma_normal: float) -> torch.Tensor:
    """(len(offsets), H, W) float64 weights of a silhouette pixel's taps: the non-interior
    pixels of the same signature and mirror object, ``max(0, n_p . n_q) ** sigma_normal``, or 1
    where the pixel's centre misses the scene (no normal: its taps, of the same signature, miss
    too, and what it records is the part of it that an object covers); the pixel itself 1."""
    shape = (guides.height, guides.width)
    sig = signature.double()  # silhouette_signature of the guides' object ids
    outer = (~interior).double()
    mid = guides.mirror_id.double()
    n = guides.normal.double().permute(2, 0, 1)
    miss = guides.object_id < 0
    w = []
    for dy, dx in offsets:
        if not (dy or dx):  # the pixel itself, weight 1
            w.append(torch.ones(shape, dtype=torch.float64))
            continue
        same = (_shift(sig, dy, dx, fill=-1.0) == sig) & (_shift(outer, dy, dx) > 0)
        same &= _shift(mid, dy, dx, fill=-9.0) == mid
        cos = torch.where(miss, 1.0, (n * _shift(n, dy, dx)).sum(0).clamp_min(0) ** sigma_normal)
        w.append(torch.where(same, cos, 0.0).double())
    return torch.stack(w)


class _SilhouetteFit(_SilhouetteMean):
    r"""The silhouette candidate of radius ``r`` that fits, over :class:`_SilhouetteMean`'s
    taps :math:`q` (weights :math:`w_q`), a plane in the tap's coverage and offset,
    :math:`f_q = (1,\ c_q - c_p,\ \Delta x_q / r,\ \Delta y_q / r)`, by weighted least
    squares with ``settings.ridge`` on the slopes (times :math:`\sum w_q`), and returns its
    value at the pixel: hat weights :math:`w_q\, e_0^\top M^{-1} f_q`,
    :math:`M = \sum_q w_q f_q f_q^\top + \text{ridge}`. It reproduces every image that is
    such a plane over the taps exactly (the coverage regression's oracle). Interior pixels
    keep their value."""

    def __init__(self, guides, interior, signature, coverage, r: int, settings: SelectionSettings):
        self.shape, self.radius = (guides.height, guides.width), r
        self.offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
        w = _silhouette_taps(guides, interior, signature, self.offsets, settings.sigma_normal)
        outer = ~interior
        cov = coverage.double()[outer]  # only silhouette pixels are fitted
        k = cov.numel()
        wt = w[:, outer]  # (T, K)
        ridge = max(settings.ridge, 1e-9) * wt.sum(0)  # on the slopes (keeps a lone pixel's M regular)
        m = torch.diag_embed(ridge[:, None] * torch.tensor([0.0, 1.0, 1.0, 1.0], dtype=torch.float64))

        def features(dy, dx):  # (K, 4) of the tap at (dy, dx), rebuilt rather than kept (T x K x 4)
            ct = _shift(coverage.double(), dy, dx)[outer] - cov
            return torch.stack([torch.ones_like(ct), ct, torch.full_like(ct, dx / r), torch.full_like(ct, dy / r)], -1)

        for t, (dy, dx) in enumerate(self.offsets):
            f = features(dy, dx)
            m += wt[t, :, None, None] * f[:, :, None] * f[:, None, :]
        e0 = torch.zeros(k, 4, 1, dtype=torch.float64)
        e0[:, 0] = 1.0
        sol = torch.linalg.solve(m, e0)[..., 0]  # (K, 4): row 0 of M^-1 (M symmetric)
        hat = torch.zeros(w.shape, dtype=torch.float32)
        for t, (dy, dx) in enumerate(self.offsets):
            hat[t, outer] = (wt[t] * (features(dy, dx) * sol).sum(-1)).float()
        del w, wt
        centre = self.offsets.index((0, 0))
        hat[centre] = torch.where(interior, 1.0, hat[centre])
        self.weights = hat
