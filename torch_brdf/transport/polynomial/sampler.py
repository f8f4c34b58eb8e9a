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

__all__ = ["LobeMixture", "Mixture"]


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
    """

    diffuse: float = 0.5
    lobes: tuple[tuple[float, float], ...] = ((0.25, 200.0), (0.25, 2000.0))
    objects: tuple[str, ...] | None = None
    base: Mixture = Mixture()
    mis: bool = True
    ids: tuple[int, ...] | None = None

    def __post_init__(self):
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
        return [self.diffuse, [list(x) for x in self.lobes], ids, self.base.spec(), self.mis]

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
