r"""Intel Open Image Denoise (``pyoidn``, the optional extra ``denoise``) on basis images and
on final frames, with the guide buffers as its auxiliary albedo and normal inputs.

OIDN is not linear, so :class:`OIDNBasis` is exact *across edits* only in this sense: it is
applied once to fixed basis images, and every edited frame is the same linear combination
of the denoised bases (:mod:`.tensors`); it is not OIDN of the edited frame, and scaling a
basis image before denoising does not scale the result exactly.

Sparse bands. With :math:`J` bands at the eye vertex, each band's image holds only the pixels
where some path's half-vector fell in that band: at 64 spp and 64 bands most band images
are a scatter of isolated pixels, which OIDN takes for noise and removes (a bias). So bands
are grouped: consecutive images of one term (the ``groups`` of :mod:`.tensors`: bands
:math:`j, j+1, \dots` of one :math:`k'`) are merged until the group's sum covers at least
``min_occupancy`` of the pixels its term covers; OIDN denoises the group sum :math:`S`, and
each band gets the share its linear-filtered image has of the linear-filtered sum,
:math:`D(x_b) = \mathrm{OIDN}(S)\,A(x_b)/A(S)` (per pixel and channel; :math:`A` is
:class:`~.atrous.EdgeAwareFilter`), so the group's bands sum to OIDN's output. Silhouette
pixels (see :mod:`.atrous`) keep their values, as with the linear filter.

Cumulative bands (:class:`CumulativeOIDN`). A band image is a histogram bin: at 64 spp and 64
bands it holds about one path per pixel, and a sharp edited lobe (Blinn-Phong n = 1000 on
bands spaced for n = 100) weighs only the first few bands, so its frame rests on a handful of
paths per pixel that no band image shows OIDN together. :class:`CumulativeOIDN` rotates each
term's bands into their prefix sums :math:`S_k = \sum_{j \le k} x_j` (bands ordered from the
mirror direction outwards, as the bases store them): :math:`S_k` is the image of the object
under a box lobe of half-width :math:`\theta_k`, a natural image with every path inside that
cone. OIDN denoises every :math:`S_k`, and the bands are the differences again,
:math:`D(x_k) = \mathrm{OIDN}(S_k) - \mathrm{OIDN}(S_{k-1})`. The change of basis is fixed and
invertible, so every edit is exact given the denoised bases, as above; a lobe whose band
coefficients fall with the angle (:math:`c_0 \ge c_1 \ge \dots`, every Blinn-Phong or
microfacet lobe) is the non-negative combination :math:`\sum_k (c_k - c_{k+1})\,S_k` of
denoised box-lobe images, with no cancellation between them.

Local means (``keep_mean``). OIDN keeps each prefix sum's total (within 1% on the glossy Cornell
box's wall) but moves radiance locally: the narrow sums :math:`S_k` of a glossy highlight come
back with a dark ring around the light's reflection, which the sharp edited lobe (weight on
the first few :math:`S_k`) shows as a bias. Each denoised sum is therefore rescaled to the
noisy sum's local mean, :math:`\mathrm{OIDN}(S_k)\,G(S_k)/G(\mathrm{OIDN}(S_k))` per channel,
with :math:`G` a Gaussian of ``keep_mean`` pixels normalised over the pixels the sum is
denoised on: the detail is OIDN's, the mean over a few pixels is the samples' own (its noise
is that of a :math:`\sim 2\pi\sigma^2`-pixel average). It is a fixed function of each fixed
sum, so edits stay exact as above.

Light lobes (``lobes``). What is left of the dark ring is OIDN guessing where an area light's
reflection ends in a narrow sum: the box lobe cuts the light's image sharply, and the guides
(one plane, one normal) do not show that edge. Without visibility that part of :math:`S_k` is a
plain integral over the lights, :math:`U_k`
(:func:`~torch_brdf.transport.guides.light_lobe_images`, by quadrature: noise-free). So each sum
is demodulated, as renderers divide out a texture before denoising: OIDN denoises
:math:`S_k / M_k` with :math:`M_k = U_k + G(S_k)` (:math:`G` the Gaussian mean above, ``lobe_floor``
pixels, so that :math:`M_k > 0` wherever the sum has samples, e.g. in indirect light) and the
result is multiplied by :math:`M_k` again. The sharp shape comes from :math:`U_k`; OIDN sees the
smooth remainder (visibility, indirect light, the ratio of the two). :math:`M_k` is a fixed
function of the fixed sum and of geometry, so edits stay exact as above.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import ShapeError, TorchBRDFError, ValueRangeError
from ..records.guides import GuideBuffers
from .atrous import EdgeAwareFilter, GuideFilter


def _pyoidn():
    try:
        import pyoidn
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise TorchBRDFError("Open Image Denoise needs the optional extra: pip install 'torch_brdf[denoise]'") from exc
    return pyoidn


def oidn_available() -> bool:
    """True when ``pyoidn`` imports."""
    try:
        _pyoidn()
    except TorchBRDFError:
        return False
    return True


def oidn_image(
    image: torch.Tensor, guides: GuideBuffers | None = None, quality: str = "high", normal: bool = True
) -> torch.Tensor:
    """OIDN's ``RT`` filter in HDR mode on one image.

    Args:
        image: (H, W, 3) linear radiance, >= 0 (negative values are clamped).
        guides: albedo proxy and normals as clean auxiliary images (None: colour only).
        quality: ``"high"``, ``"balanced"`` or ``"fast"``.
        normal: with ``guides``, also pass the normals (False: the albedo proxy alone).
    Returns:
        (H, W, 3) float32.
    """
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ShapeError(f"expected an image (H, W, 3); got {tuple(image.shape)}")
    oidn = _pyoidn()
    color = np.ascontiguousarray(image.detach().float().clamp_min(0).numpy())
    kw = {}
    if guides is not None:
        kw = {
            "albedo": np.ascontiguousarray(guides.albedo.numpy(), dtype=np.float32),
            "clean_aux": True,
        }
        if normal:
            kw["normal"] = np.ascontiguousarray(guides.normal.numpy(), dtype=np.float32)
    out = oidn.denoise(color, hdr=True, quality=quality, **kw)
    return torch.from_numpy(np.array(out, dtype=np.float32))


def oidn_frame(image: torch.Tensor, guides: GuideBuffers, quality: str = "high") -> torch.Tensor:
    """The path-tracer user's baseline: OIDN on a final frame (H, W, 3) -> (H, W, 3)."""
    return oidn_image(image, guides, quality)


def _runs(groups: torch.Tensor) -> list[tuple[int, int]]:
    """The [start, end) ranges of the runs of equal consecutive values of ``groups`` (B,)."""
    _, counts = torch.unique_consecutive(groups, return_counts=True)
    ends = counts.cumsum(0).tolist()
    return list(zip([0, *ends][:-1], ends, strict=True))


class OIDNBasis:
    """OIDN per (grouped) basis image, a denoiser for :mod:`.tensors`.

    Args:
        guides: the view's guides.
        linear: the linear filter that splits a group's output among its bands (default
            :class:`EdgeAwareFilter` of the guides).
        min_occupancy: a group grows until its sum is non-zero on this fraction of the pixels
            where the whole term is non-zero.
        quality: OIDN quality.
    """

    def __init__(
        self,
        guides: GuideBuffers,
        linear: EdgeAwareFilter | None = None,
        min_occupancy: float = 0.5,
        quality: str = "high",
    ):
        self.guides = guides
        self.linear = linear or EdgeAwareFilter(guides)
        self.min_occupancy = float(min_occupancy)
        self.quality = quality
        self.calls = 0

    @property
    def description(self) -> str:
        return f"oidn per basis group (min_occupancy {self.min_occupancy}, quality {self.quality})"

    def _subgroups(self, images: torch.Tensor, groups: torch.Tensor) -> list[tuple[int, int]]:
        out = []
        for start, end in _runs(groups):
            n = end - start
            occ = (images[start : start + n] != 0).any(1).flatten(1)  # (n, H*W)
            total = max(int(occ.any(0).sum()), 1)
            a, have = start, torch.zeros_like(occ[0])
            for b in range(start, start + n):
                have |= occ[b - start]
                if int(have.sum()) >= self.min_occupancy * total:
                    out.append((a, b + 1))
                    a, have = b + 1, torch.zeros_like(have)
            if a < start + n:  # the remainder joins the last subgroup
                if out and out[-1][1] == a and out[-1][0] >= start:
                    out[-1] = (out[-1][0], start + n)
                else:
                    out.append((a, start + n))
        return out

    def __call__(self, images: torch.Tensor, groups: torch.Tensor) -> torch.Tensor:
        """images (B, 3, H, W) -> (B, 3, H, W); ``groups`` (B,) as :mod:`.tensors`."""
        lin = self.linear(images)
        out = torch.zeros_like(images)
        inner = self.linear.interior
        for a, b in self._subgroups(images, groups):
            s = images[a:b].sum(0)  # (3, H, W)
            if not bool((s != 0).any()):
                continue
            den = oidn_image(s.permute(1, 2, 0), self.guides, self.quality).permute(2, 0, 1).to(images.dtype)
            self.calls += 1
            ls = lin[a:b].sum(0)
            share = torch.where(ls > 0, lin[a:b] / ls.clamp_min(1e-30), 0.0)
            out[a:b] = den * share
        return torch.where(inner, out, images)


#: the default ``keep_mean`` of :class:`CumulativeOIDN` (pixels): the first guess, kept. On the
#: stratified 64-spp Cornell box, default / edited rel. RMSE was 0.0235 / 0.0297 at 1.5 px,
#: 0.0230 / 0.0294 at 2.5, 0.0229 / 0.0301 at 4, 0.0230 / 0.0309 at 8 and 0.0230 / 0.0320 off
#: (see the denoising guide); picking the edit's best would tune on the edit.
KEEP_MEAN_SIGMA = 4.0


def _gaussian_within(x: torch.Tensor, mask: torch.Tensor, sigma: float) -> torch.Tensor:
    """(C, H, W) Gaussian blur of ``x`` over the pixels of ``mask`` (H, W) only (a normalised
    convolution; 0 where no mask pixel is within reach), separable, radius ``3 sigma``."""
    r = max(int(3 * sigma + 0.5), 1)
    t = torch.arange(-r, r + 1, dtype=x.dtype)
    g = torch.exp(-0.5 * (t / sigma) ** 2)
    g = g / g.sum()
    m = mask.to(x.dtype)[None]
    stack = torch.cat([x * m, m])[:, None]  # (C + 1, 1, H, W): the channels and the weights
    out = F.conv2d(F.conv2d(stack, g.view(1, 1, 1, -1), padding=(0, r)), g.view(1, 1, -1, 1), padding=(r, 0))[:, 0]
    return out[:-1] / out[-1:].clamp_min(1e-12)


def match_local_mean(
    noisy: torch.Tensor,
    denoised: torch.Tensor,
    mask: torch.Tensor,
    sigma: float,
    noisy_mean: torch.Tensor | None = None,
) -> torch.Tensor:
    r"""``denoised`` (C, H, W) rescaled per channel to the local mean of ``noisy``:
    :math:`D\,G(N)/G(D)` with :math:`G` a Gaussian of ``sigma`` pixels over the pixels of
    ``mask`` (H, W); unchanged where :math:`G(D)` is 0. ``noisy_mean``: :math:`G(N)` when the
    caller has it already (the same ``sigma`` and ``mask``)."""
    gn = _gaussian_within(noisy, mask, sigma) if noisy_mean is None else noisy_mean
    gd = _gaussian_within(denoised, mask, sigma)
    return torch.where(gd > 0, denoised * gn / torch.where(gd > 0, gd, 1.0), denoised)


class CumulativeOIDN:
    """OIDN per prefix sum of each term's bands (see the module docstring), a denoiser for
    :mod:`.tensors`.

    Groups of more than one image (consecutive bands ``j = 0, 1, ...`` of one term) are summed
    cumulatively, each prefix sum goes through ``image_denoiser`` once on its interior pixels
    that hold a record of the group, and the bands are the differences of the denoised sums.
    Single images (terms without bands, other objects' records) and the remaining pixels
    (silhouettes, pixels where the group has no record) take the linear ``fallback`` filter.

    Args:
        guides: the view's guides (OIDN's albedo and normal).
        fallback: the linear filter of single images and non-interior pixels (default
            :class:`EdgeAwareFilter` of the guides); a :class:`~.selection.SelectedRegressionFilter`
            when the spp was spent as two halves.
        quality: OIDN quality.
        image_denoiser: ``(H, W, 3) -> (H, W, 3)`` in place of OIDN (tests; other denoisers).
        mix: weight of the fallback filter's output in the banded groups' result,
            ``(1 - mix) D + mix A`` (two denoisers of the same fixed images, so edits stay
            exact; their errors are partly independent: see ``benchmarks/denoise.py``).
        keep_mean: sigma (pixels) of the Gaussian window within which each denoised prefix
            sum is rescaled to the noisy sum's mean (module docstring); 0 turns it off.
        lobes: (J, 3, H, W) prefix images of the frozen object's light lobes
            (:func:`~torch_brdf.transport.guides.light_lobe_images`, None: none): every banded
            group must then have J images (freeze the object they were computed for), and
            each prefix sum is demodulated by its lobe (module docstring).
        lobe_floor: sigma (pixels) of the Gaussian mean of the sum added to the lobe image
            in the demodulating image.
    Raises:
        ValueRangeError: ``mix`` outside [0, 1]; ``keep_mean`` or ``lobe_floor`` negative
            or not finite (``lobe_floor`` must be > 0).
        ShapeError: ``lobes`` not (J, 3, H, W) with finite values >= 0; at call time, a banded
            group whose length or image size differs from the lobes'.
    """

    def __init__(
        self,
        guides: GuideBuffers,
        fallback: GuideFilter | None = None,
        quality: str = "high",
        image_denoiser: Callable[[torch.Tensor], torch.Tensor] | None = None,
        mix: float = 0.0,
        keep_mean: float = KEEP_MEAN_SIGMA,
        lobes: torch.Tensor | None = None,
        lobe_floor: float = KEEP_MEAN_SIGMA,
    ):
        if not 0.0 <= mix <= 1.0:
            raise ValueRangeError(f"mix must be in [0, 1]; got {mix}")
        if not (np.isfinite(keep_mean) and keep_mean >= 0):
            raise ValueRangeError(f"keep_mean must be a finite sigma >= 0 (pixels); got {keep_mean}")
        if not (np.isfinite(lobe_floor) and lobe_floor > 0):
            raise ValueRangeError(f"lobe_floor must be a finite sigma > 0 (pixels); got {lobe_floor}")
        if lobes is not None:
            if lobes.ndim != 4 or lobes.shape[1] != 3:
                raise ShapeError(f"lobes must be (J, 3, H, W); got {tuple(lobes.shape)}")
            if not bool(torch.isfinite(lobes).all()) or float(lobes.min()) < 0:
                raise ShapeError("lobes must be finite and >= 0")
        self.mix = float(mix)
        self.keep_mean = float(keep_mean)
        self.lobes = lobes
        self.lobe_floor = float(lobe_floor)
        self.guides = guides
        self.fallback = fallback or EdgeAwareFilter(guides)
        self.quality = quality
        self.image_denoiser = image_denoiser or (lambda img: oidn_image(img, guides, quality))
        self.calls = 0

    @property
    def description(self) -> str:
        fb = getattr(self.fallback, "description", type(self.fallback).__name__)
        return (
            f"oidn per cumulative band sum (quality {self.quality}, mix {self.mix}, "
            f"local mean {f'kept over {self.keep_mean} px' if self.keep_mean > 0 else 'not kept'}"
            + (f", light lobes {tuple(self.lobes.shape)} + {self.lobe_floor} px mean" if self.lobes is not None else "")
            + f"; else {fb})"
        )

    def _denoise(self, s: torch.Tensor, keep: torch.Tensor, k: int, mean: torch.Tensor | None) -> torch.Tensor:
        r"""The image denoiser on prefix sum ``s`` (3, H, W), through its light lobe ``k`` when
        there are lobes: :math:`M\,D(S/M)` with :math:`M = U_k + G(S)`; ``mean`` is
        :math:`G(S)` when the caller has it (``lobe_floor`` equal to ``keep_mean``)."""
        if self.lobes is None:
            return self.image_denoiser(s.permute(1, 2, 0)).permute(2, 0, 1).to(s.dtype)
        m = self.lobes[k].to(s.dtype) + (_gaussian_within(s, keep, self.lobe_floor) if mean is None else mean)
        ratio = torch.where(m > 0, s / torch.where(m > 0, m, 1.0), 0.0)
        return self.image_denoiser(ratio.permute(1, 2, 0)).permute(2, 0, 1).to(s.dtype) * m

    def __call__(self, images: torch.Tensor, groups: torch.Tensor) -> torch.Tensor:
        """images (B, 3, H, W) -> (B, 3, H, W); ``groups`` (B,) as :mod:`.tensors`."""
        if images.ndim != 4 or groups.shape != images.shape[:1]:
            raise ShapeError(
                f"expected images (B, 3, H, W) and groups (B,); got {tuple(images.shape)}, {tuple(groups.shape)}"
            )
        out = self.fallback(images)
        inner = self.fallback.interior
        # one blur of each sum where the demodulator and the kept mean share a sigma
        shared = self.lobes is not None and self.keep_mean == self.lobe_floor
        for a, b in _runs(groups):
            n = b - a
            if n == 1:
                continue
            sums = images[a:b].cumsum(0)
            keep = inner & (images[a:b] != 0).any(0).any(0)  # (H, W)
            den = out[a:b].cumsum(0)  # the fallback's prefix sums where OIDN does not apply
            if self.lobes is not None and (n, *images.shape[2:]) != (self.lobes.shape[0], *self.lobes.shape[2:]):
                raise ShapeError(
                    f"a banded group of {n} images {tuple(images.shape[2:])} but lobes {tuple(self.lobes.shape)}: "
                    "the lobes are of another object (freeze the object they were computed for)"
                )
            for k in range(n):
                if bool((sums[k][:, keep] != 0).any()):
                    mean = _gaussian_within(sums[k], keep, self.keep_mean) if shared else None
                    d = self._denoise(sums[k], keep, k, mean)
                    if self.keep_mean > 0:
                        d = match_local_mean(sums[k], d, keep, self.keep_mean, mean)
                    den[k] = torch.where(keep, d, den[k])
                    self.calls += 1
            bands = torch.diff(den, dim=0, prepend=torch.zeros_like(den[:1]))
            out[a:b] = (1 - self.mix) * bands + self.mix * out[a:b]
        return out
