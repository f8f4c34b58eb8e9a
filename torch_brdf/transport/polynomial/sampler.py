r"""The direction sampler of the multibounce precomputation (Ben-Artzi et al. 2008, Sec. 5.1)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from ...errors import SceneError, ValueRangeError
from ...frame import half_vector
from ...sphere.warps import (
    cosine_hemisphere_pdf,
    cosine_power_hemisphere_pdf,
    square_to_cosine_hemisphere,
    square_to_cosine_power_hemisphere,
)

__all__ = ["EyeStrata", "LobeMixture", "Mixture"]


_BELOW_ONE = {torch.float32: 1.0 - 2.0**-24, torch.float64: 1.0 - 2.0**-53}


def _hash31(x: torch.Tensor) -> torch.Tensor:
    """A 31-bit integer hash of int64 ``x`` (two LCG + xorshift rounds on 31 bits: no overflow)."""
    x = x & 0x7FFFFFFF
    for _ in range(2):
        x = (x * 1103515245 + 12345) & 0x7FFFFFFF
        x = x ^ (x >> 13)
    return x


def _rescale(x: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, dtype) -> torch.Tensor:
    """``x`` in [lo, hi) mapped to [0, 1) (float64 arithmetic, then ``dtype``, kept below 1)."""
    r = (x.double() - lo) / (hi - lo).clamp_min(1e-300)
    return r.to(dtype).clamp(0.0, _BELOW_ONE[dtype])


@dataclass(frozen=True)
class EyeStrata:
    r"""Where each path's eye-vertex samples fall among its pixel's paths: path ``sample``
    (0-based) of the ``count`` paths of pixel ``key`` (a flat pixel index).

    :meth:`square` places the paths of a pixel one per cell of an m x n grid of the unit
    square, m = floor(sqrt(count)), n = floor(count / m) (jittered sampling, e.g. 8 x 8 at
    64 spp), each pixel visiting the cells in its own order (a rotation by a hash of the pixel
    and ``salt``, so the light's and the mixture's cells are not paired alike everywhere); the
    paths beyond m x n keep their uniforms. Every path's point is still uniform on the square,
    so every estimate stays unbiased, and the tensors stay exact polynomials (the sample
    positions never depend on a BRDF); what changes is that a pixel's paths cover the square
    evenly, which removes most of the noise of a smooth integrand, e.g. an area light's
    sharp highlight on a glossy wall.
    """

    sample: torch.Tensor
    count: torch.Tensor
    key: torch.Tensor

    def take(self, rows: torch.Tensor) -> EyeStrata:
        """The strata of ``rows``."""
        return EyeStrata(self.sample[rows], self.count[rows], self.key[rows])

    def square(self, ux: torch.Tensor, uy: torch.Tensor, salt: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Uniforms ``ux``, ``uy`` (n,) -> the jittered points (x, y) (n,) float64 in [0, 1)."""
        c = self.count.clamp_min(1)
        m = torch.sqrt(c.double()).floor().long().clamp_min(1)  # exact for counts < 2**52
        n = c // m
        cells = m * n
        t = (self.sample + _hash31(self.key * 64 + salt)) % cells
        inside = self.sample < cells
        x = torch.where(inside, ((t % m).double() + ux.double()) / m.double(), ux.double())
        y = torch.where(inside, ((t // m).double() + uy.double()) / n.double(), uy.double())
        below = _BELOW_ONE[torch.float64]
        return x.clamp(0.0, below), y.clamp(0.0, below)

    def light_uniforms(self, light, u: torch.Tensor, salt: int) -> torch.Tensor:
        """An :class:`~torch_brdf.scene.lights.AreaLight`'s uniforms ``u`` (n, 3) float64 (column 0
        picks the triangle by area, 1 and 2 the point on it) stratified: the jittered point (x,
        y) of columns 1 and 2 picks the triangle by x, and x's place inside that triangle's share
        of [0, 1) and y place the point, so the cells cover the whole light evenly."""
        x, y = self.square(u[:, 1], u[:, 2], salt)
        cdf = light.cdf.to(torch.float64)
        last = cdf.numel() - 1
        k = light.triangle_of(x)
        lo = torch.where(k > 0, cdf[(k - 1).clamp_min(0)], torch.zeros_like(x))
        hi = torch.where(k == last, torch.clamp_min(cdf[last], 1.0), cdf[k])
        return torch.stack([x, _rescale(x, lo, hi, torch.float64), y], 1)


@dataclass(frozen=True)
class Mixture:
    r"""Direction sampling independent of the final BRDF (Sec. 5.1): with probability
    ``diffuse`` a cosine lobe, otherwise a Blinn lobe :math:`\cos^n\theta_h` about the
    mirror direction (the seed: 70% diffuse, 30% Blinn exponent 200)."""

    diffuse: float = 0.7
    exponent: float = 200.0

    def __post_init__(self):
        if not 0.0 <= self.diffuse <= 1.0 or not self.exponent >= 0.0:
            raise ValueRangeError(f"mixture needs diffuse in [0, 1] and exponent >= 0; got {self}")

    def spec(self) -> list:
        """The settings-key form (the precompute's resume key and ``meta``)."""
        return [self.diffuse, self.exponent]

    def sample(
        self, wo: torch.Tensor, u: torch.Tensor, oid: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Local ``wo`` (n, 3), uniforms ``u`` (n, 3) -> ``wi`` (n, 3), solid-angle pdf (n,).
        ``oid`` (n,), the vertex's object, is not used (the same mixture everywhere)."""
        cosine = square_to_cosine_hemisphere(u[:, 1:])
        h = square_to_cosine_power_hemisphere(u[:, 1:], self.exponent)
        glossy = 2 * (wo * h).sum(-1, keepdim=True) * h - wo
        wi = torch.where((u[:, :1] < self.diffuse), cosine, glossy)
        return wi, self.pdf(wi, wo)

    def pdf(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """Solid-angle density of :meth:`sample` (0 below the horizon)."""
        n = self.exponent
        h = half_vector(wi, wo)
        cos_oh = (wo * h).sum(-1).abs().clamp_min(1e-12)
        p_h = cosine_power_hemisphere_pdf(h[:, 2], n)
        p = self.diffuse * cosine_hemisphere_pdf(wi[:, 2]) + (1 - self.diffuse) * p_h / (4 * cos_oh)
        return torch.where(wi[:, 2] > 0, p, torch.zeros_like(p))


@dataclass(frozen=True)
class LobeMixture:
    r"""An edit-robust (defensive) direction mixture on glossy objects: with probability
    ``diffuse`` a cosine lobe, with probability :math:`w_k` a Blinn lobe
    :math:`\cos^{n_k}\theta_h` about the mirror direction, for ``lobes`` = ((w_k, n_k), ...);
    the vertices on other objects sample ``base``.

    The tensors do not depend on the sampling pdf in expectation (every path weight divides by
    the density it was drawn from, :meth:`pdf`, the whole mixture's: the balance heuristic of
    the one-sample model, Veach 1997, Sec. 9.2.4), so every edit stays unbiased; what the
    mixture decides is which edits are sampled well. The default mixture's Blinn 200 lobe
    suits an exponent ~100 material, and an edit to n = 1000 rests on ~12% of the paths'
    worth of samples (importance-sampling efficiency, ``(E w)^2 / E w^2``); a sharper
    lobe beside it keeps a share for sharp edits at some cost for the broad ones.

    ``objects``: the object names that use the mixture (None: every object with a banded
    basis); :meth:`resolve` turns them into ids before tracing (:func:`precompute_polynomial`
    calls it).

    ``mis``: at the eye vertex of these objects, the light a mixture sample finds (an area
    light's object, or the environment where NEE samples it) is counted too, and both it and
    next-event estimation are weighted by the power heuristic (Veach 1997, Eq. 9.13), as
    :func:`~torch_brdf.transport.pathtrace.path_trace` does. Without it a sharp edit's
    highlight of an area light rests on next-event samples alone, which the lobe mixture
    cannot help (the reflected light's noise on the Cornell box's edited wall). The weights
    depend on the two pdfs only, never on the BRDF, so the tensors stay exact polynomials.

    ``stratified``: the eye vertex's next-event sample of each area light and its mixture
    sample are stratified over the pixel's paths (:class:`EyeStrata`, e.g. 8 x 8 cells of the
    light and of the mixture's square at 64 spp; the component is picked by the cell's x, so
    each lobe gets its share of the cells in order). Unbiased, the same random numbers drawn.

    ``share = (k, of)`` (stratified only): this precomputation is share ``k`` of ``of``
    complementary shares of one stratification. With ``spp`` paths a pixel, its paths take the
    strata of paths ``k * spp ... (k + 1) * spp - 1`` of ``of * spp`` (e.g. two 32-spp shares
    take the two halves of an 8 x 8 grid), so the mean record of the ``of`` shares (any seeds)
    samples exactly as one stratified ``of * spp`` precomputation does. A share alone covers
    only its part of each pixel's cells (which part is set by the pixel's rotation), so only
    that mean is unbiased pixel by pixel: for half-sample denoisers (two halves whose mean is
    the image, their difference the noise estimate).
    """

    diffuse: float = 0.5
    lobes: tuple[tuple[float, float], ...] = ((0.25, 200.0), (0.25, 2000.0))
    objects: tuple[str, ...] | None = None
    base: Mixture = Mixture()
    mis: bool = True
    ids: tuple[int, ...] | None = None
    stratified: bool = False
    share: tuple[int, int] = (0, 1)

    def __post_init__(self):
        k, of = (int(x) for x in self.share)
        object.__setattr__(self, "share", (k, of))
        if not (of >= 1 and 0 <= k < of) or (of > 1 and not self.stratified):
            raise ValueRangeError(
                f"share must be (k, of) with 0 <= k < of, and of > 1 only when stratified; "
                f"got {self.share} (stratified {self.stratified})"
            )
        lobes = tuple((float(w), float(n)) for w, n in self.lobes)
        object.__setattr__(self, "lobes", lobes)
        if self.objects is not None:
            object.__setattr__(self, "objects", tuple(self.objects))
        total = self.diffuse + sum(w for w, _ in lobes)
        if (
            not 0.0 <= self.diffuse <= 1.0
            or any(not (w >= 0.0 and n >= 0.0) for w, n in lobes)
            or abs(total - 1.0) > 1e-9
        ):
            raise ValueRangeError(
                f"a lobe mixture needs diffuse in [0, 1], lobe weights and exponents >= 0 and "
                f"diffuse + the lobe weights = 1; got diffuse {self.diffuse}, lobes {lobes} (sum {total})"
            )

    def resolve(self, scene, bases) -> LobeMixture:
        """This mixture with ``ids`` set: the ids of ``objects`` in ``scene`` (None: every
        object whose basis has more than one band, ``bases`` one entry per object).

        Raises:
            SceneError: an object name that is not in the scene.
        """
        if self.objects is None:
            ids = tuple(k for k, b in enumerate(bases) if b is not None and b.J > 1)
        else:
            names = [o.name for o in scene.objects]
            unknown = sorted(set(self.objects) - set(names))
            if unknown:
                raise SceneError(f"lobe mixture names unknown objects {unknown}; the scene has {names}")
            ids = tuple(sorted(names.index(n) for n in self.objects))
        return replace(self, ids=ids)

    def spec(self) -> list:
        """The settings-key form (the precompute's resume key and ``meta``)."""
        ids = None if self.ids is None else list(self.ids)
        out = [self.diffuse, [list(x) for x in self.lobes], ids, self.base.spec(), self.mis]
        if self.stratified:  # (unstratified keys as before)
            out = out + ["stratified"]
        return out + [["share", *self.share]] if self.share[1] > 1 else out

    def _intervals(self, x: torch.Tensor, oid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(lo, hi) (n,) float64: the share of [0, 1) of the component :meth:`sample` picks
        for ``u[:, 0] = x`` (its float value) at each vertex's object."""
        mine = self._mask(oid, x.device)
        xd = x.double()
        ends = [self.diffuse + sum(w for w, _ in self.lobes[: k + 1]) for k in range(len(self.lobes))]  # as sample()
        edges = torch.tensor([0.0, self.diffuse, *ends[:-1], 1.0], dtype=torch.float64)
        inner = torch.tensor(ends[:-1], dtype=x.dtype)
        # sample(): cosine when x < diffuse, else lobe k = #(lobe ends <= x), clamped to the last
        k = torch.where(
            x < self.diffuse,
            torch.zeros_like(oid),
            1 + torch.searchsorted(inner, x.contiguous(), right=True),
        )
        lo, hi = edges[k], edges[k + 1]
        b = self.base.diffuse
        base_glossy = x >= b
        lo_b = torch.where(base_glossy, torch.full_like(xd, b), torch.zeros_like(xd))
        hi_b = torch.where(base_glossy, torch.ones_like(xd), torch.full_like(xd, b))
        return torch.where(mine, lo, lo_b), torch.where(mine, hi, hi_b)

    def stratify(self, u: torch.Tensor, strata: EyeStrata, oid: torch.Tensor, salt: int = 1) -> torch.Tensor:
        """The eye vertex's uniforms ``u`` (n, 3) stratified (:class:`EyeStrata`): the jittered
        point (x, y) of columns 1 and 2 picks the component by x, and x's place inside that
        component's share of [0, 1) and y warp its lobe, so each component's samples cover
        its lobe evenly."""
        x, y = strata.square(u[:, 1], u[:, 2], salt)
        below = _BELOW_ONE[u.dtype]
        x = x.to(u.dtype).clamp_max(below)  # the value sample() compares
        lo, hi = self._intervals(x, oid)
        return torch.stack([x, _rescale(x, lo, hi, u.dtype), y.to(u.dtype).clamp_max(below)], 1)

    def _mask(self, oid: torch.Tensor | None, device) -> torch.Tensor:
        if self.ids is None:
            raise ValueRangeError("LobeMixture.resolve(scene, bases) must run before sampling (it names the objects)")
        if oid is None:
            raise ValueRangeError("LobeMixture needs the vertices' object ids (oid)")
        return torch.isin(oid, torch.tensor(self.ids, dtype=oid.dtype, device=device))

    def sample(
        self, wo: torch.Tensor, u: torch.Tensor, oid: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Local ``wo`` (n, 3), uniforms ``u`` (n, 3), the vertices' objects ``oid`` (n,) ->
        ``wi`` (n, 3), solid-angle pdf (n,) of the mixture of each vertex's object.
        ``u[:, 0]`` picks the component, ``u[:, 1:]`` warps."""
        mine = self._mask(oid, wo.device)
        wi, _ = self.base.sample(wo, u)
        if bool(mine.any()):
            exps = torch.tensor([n for _, n in self.lobes], dtype=u.dtype, device=u.device)
            edges = torch.tensor(
                [self.diffuse + sum(w for w, _ in self.lobes[: k + 1]) for k in range(len(self.lobes))],
                dtype=u.dtype,
                device=u.device,
            )
            k = torch.searchsorted(edges, u[:, 0].contiguous(), right=True).clamp_max(len(self.lobes) - 1)
            cosine = square_to_cosine_hemisphere(u[:, 1:])
            h = square_to_cosine_power_hemisphere(u[:, 1:], exps[k])
            glossy = 2 * (wo * h).sum(-1, keepdim=True) * h - wo
            own = torch.where(u[:, :1] < self.diffuse, cosine, glossy)
            wi = torch.where(mine[:, None], own.to(wi.dtype), wi)
        return wi, self.pdf(wi, wo, oid)

    def pdf(self, wi: torch.Tensor, wo: torch.Tensor, oid: torch.Tensor | None = None) -> torch.Tensor:
        """Solid-angle density of :meth:`sample` at each vertex's object (0 below the horizon)."""
        mine = self._mask(oid, wo.device)
        h = half_vector(wi, wo)
        cos_oh = (wo * h).sum(-1).abs().clamp_min(1e-12)
        p = self.diffuse * cosine_hemisphere_pdf(wi[:, 2])
        for w, n in self.lobes:
            p = p + w * cosine_power_hemisphere_pdf(h[:, 2], n) / (4 * cos_oh)
        p = torch.where(wi[:, 2] > 0, p, torch.zeros_like(p))
        return torch.where(mine, p, self.base.pdf(wi, wo))
