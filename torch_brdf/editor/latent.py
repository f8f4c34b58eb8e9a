r"""The measured-material picker: a 2-D slice of a GPLVM latent space (Soler et al. 2017).

The map is :func:`~torch_brdf.manifold.latent_slice` of a fit through the latents' mean, on
any pair of latent dimensions (:meth:`LatentMap.set_dims`; (0, 1) first), shaded by the
predictive variance (white: near the
measured materials, dark: the model is unsure), with the training materials as dots. A click
at latent :math:`x_*` gives the weights :math:`b(x_*) = K^{-1}k(x_*)`; since the band
projection is linear in the BRDF, the object's coefficients are the same blend of the
materials' own projections, :math:`c_* = \sum_i b_i c_i` (seed Eq. 8 applied to the
coefficients), clamped at 0 like the renderer's reading of a blended table. Each material's
:math:`c_i` is its NBRDF network (an approximation of MERL) projected onto the object's bands
once (:class:`~torch_brdf.brdf.Projector`).

Where the map can be trusted. Two tests, shown on the map and applied to a click:

- **Variance**: the predictive variance :math:`\sigma^2(x_*)` (seed Eq. 2) at most ``trust``
  times the prior variance :math:`1 + \mu` (default :data:`TRUST_VARIANCE`); farther from
  the measured materials the model only returns to its prior mean.
- **Validity of the predicted BRDF**: the weights of the model's ``valid`` setting (``GPLVM(...,
  valid=...)``; the map's ``valid`` argument) blend the materials' BRDF values on
  :data:`VALIDITY_PAIRS` direction pairs and their directional albedos at
  :data:`VALIDITY_ANGLES` incidence angles; a point is invalid where the blend goes negative
  (below -1e-3 of its largest value) or an albedo exceeds 1. With ``"simplex"`` (the default:
  :func:`~torch_brdf.manifold.simplex_projection`, a convex blend) only materials whose own
  albedo exceeds 1 can make a point invalid (``"energy"`` rescales those); with ``"none"`` (the
  seed's unconstrained :math:`K^{-1}k(x_*)`) most of a slice between few materials is invalid:
  in a test fit of 8 NBRDF materials the raw weights reached -47 and 90 % of the slice predicted
  negative values or albedos above 1.

Untrusted pixels are dimmed and blue, invalid ones red, the trusted region's edge is drawn in
yellow. A click outside it snaps to the nearest trusted pixel and says so (no trusted pixel in
the slice: the click is kept, with a warning). Every pick names the nearest measured materials
(latent distance).

The blend becomes a ``factored_1d`` material on the object's bands, so the lobe view, the lit
sphere and the reference path trace all see exactly what the renderer shows. Not done: the
full blended table (what the bands cannot hold, e.g. the
:math:`\theta_d` dependence of the measured materials, is lost before blending).
"""

from __future__ import annotations

import math

import torch

from ..brdf import NBRDF
from ..data import data_path
from ..errors import ValueRangeError
from ..io.merl import load_nbrdf_weights
from ..manifold import GPLVM, GPLVMFit, latent_slice

#: trusted: predictive variance at most this fraction of the prior variance 1 + mu
TRUST_VARIANCE = 0.25
#: incidence angles (degrees, in [0, 80]) and outgoing cells (cos theta_o x phi_o) of the
#: validity check: 6 x (8 x 16) = 768 direction pairs
VALIDITY_ANGLES = 6
VALIDITY_CELLS = (8, 16)
VALIDITY_PAIRS = VALIDITY_ANGLES * VALIDITY_CELLS[0] * VALIDITY_CELLS[1]
#: a blend is negative where a value is below this fraction of its largest value
NEGATIVE_TOLERANCE = 1e-3


def validity_pairs(dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Direction pairs of the validity check: wi (A, 1, 3), wo (1, M, 3) and each outgoing
    cell's :math:`\\cos\theta_o\\,d\\omega_o` (M,) (midpoint rule in :math:`(\\cos\theta_o, \\phi_o)`)."""
    a, (nt, nph) = VALIDITY_ANGLES, VALIDITY_CELLS
    th = torch.linspace(0, math.radians(80), a, dtype=dtype)
    wi = torch.stack((th.sin(), torch.zeros_like(th), th.cos()), -1)[:, None]
    ct = (torch.arange(nt, dtype=dtype) + 0.5) / nt
    ph = (torch.arange(nph, dtype=dtype) + 0.5) / nph * 2 * math.pi
    c, p = torch.meshgrid(ct, ph, indexing="ij")
    st = (1 - c**2).sqrt()
    wo = torch.stack((st * p.cos(), st * p.sin(), c), -1).reshape(1, -1, 3)
    weight = c.reshape(-1) * (1.0 / nt) * (2 * math.pi / nph)
    return wi, wo, weight


class LatentMap:
    """A clickable latent map of a GPLVM fit of NBRDF materials.

    Args:
        fit: a :class:`~torch_brdf.manifold.GPLVMFit` (or its file) whose ``names`` are NBRDF
            materials.
        weights: the NBRDF weights file (default: the shared data's
            ``merl/nbrdf_merl100_weights.npz``).
        resolution: pixels per side of the map.
        dims: the two latent dimensions shown (horizontal, vertical).
        trust: the trusted variance as a fraction of the prior variance (module docstring).
        valid: the blend weights (``GPLVM``'s ``valid``: ``"simplex"``, ``"energy"``, ``"none"``);
            ``"energy"`` needs the materials' albedos, taken from the validity check's angles.
    """

    def __init__(
        self,
        fit,
        weights=None,
        resolution: int = 96,
        dims: tuple[int, int] = (0, 1),
        trust: float = TRUST_VARIANCE,
        valid: str = "simplex",
    ):
        fit = fit if isinstance(fit, GPLVMFit) else GPLVMFit.load(fit)
        if fit.latents.shape[1] < 2:
            raise ValueRangeError(f"the latent map needs q >= 2; the fit has q = {fit.latents.shape[1]}")
        self.names = list(fit.names)
        self.nbrdf = load_nbrdf_weights(weights or data_path("merl", "nbrdf_merl100_weights.npz"))
        missing = [n for n in self.names if n not in self.nbrdf.names]
        if missing:
            raise ValueRangeError(f"the fit names materials the NBRDF file lacks: {missing[:5]}")
        self._values, self._albedo = self._material_samples()
        albedo = self._albedo.reshape(len(self.names), VALIDITY_ANGLES, 3)
        self.model = GPLVM(fit, valid=valid, albedo=albedo if valid == "energy" else None)
        if not 0 < trust <= 1:
            raise ValueRangeError(f"trust must lie in (0, 1] (a fraction of the prior variance); got {trust}")
        self.resolution = resolution
        self.trust = float(trust)
        self.set_dims(dims)
        self._coefficients: dict[str, torch.Tensor] = {}

    def _material_samples(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Each material's BRDF on the validity pairs (N, A·M·3) and directional albedos (N, A·3)."""
        wi, wo, weight = validity_pairs(torch.float32)
        wi, wo = wi.expand(-1, wo.shape[1], 3), wo.expand(wi.shape[0], -1, 3)
        vals = []
        with torch.no_grad():
            for name in self.names:
                vals.append(NBRDF(name, self.nbrdf).eval(wi, wo).double())  # (A, M, 3)
        v = torch.stack(vals)
        albedo = (v * weight.double()[None, None, :, None]).sum(2)
        return v.reshape(len(self.names), -1), albedo.reshape(len(self.names), -1)

    @property
    def q(self) -> int:
        """Latent dimensions of the fit."""
        return int(self.model.latents.shape[1])

    def set_dims(self, dims: tuple[int, int]) -> None:
        """Show the slice on latent dimensions ``dims`` (two distinct axes in 0..q-1; the
        others stay at the latents' mean). Raises ValueRangeError otherwise."""
        self.slice = latent_slice(self.model, tuple(int(d) for d in dims), resolution=self.resolution)
        self.dims = self.slice.dims
        self._classify()

    def _classify(self) -> None:
        """(R, R) bool maps in the image's orientation (row 0 at the top): ``untrusted``
        (variance), ``invalid`` (the seed's prediction), ``trusted`` (neither)."""
        r, q = self.resolution, self.q
        pts = self.slice.points.flip(0).reshape(-1, q)
        neg, high = [], []
        for a in range(0, pts.shape[0], 1024):
            b = self.model.weights(pts[a : a + 1024])  # the weights a pick blends with
            v = b @ self._values
            top = v.abs().amax(-1).clamp_min(1e-30)
            neg.append(v.amin(-1) < -NEGATIVE_TOLERANCE * top)
            high.append((b @ self._albedo).amax(-1) > 1.0)
        self.invalid = (torch.cat(neg) | torch.cat(high)).reshape(r, r)
        limit = self.trust * (1.0 + self.model.mu)
        self.untrusted = self.slice.variance.flip(0) > limit
        self.trusted = ~self.invalid & ~self.untrusted

    def nearest_materials(self, z: torch.Tensor, k: int = 3) -> list[tuple[str, float]]:
        """The ``k`` measured materials nearest latent point ``z`` (Q,): (name, latent distance)."""
        d = (self.model.latents - z.to(self.model.latents)).norm(dim=-1)
        order = torch.argsort(d)[:k].tolist()
        return [(self.names[i], round(float(d[i]), 4)) for i in order]

    def snap(self, x: int, y: int) -> tuple[int, int, str | None]:
        """Map pixel (x, y), or the nearest trusted pixel when (x, y) is not trusted, and why it
        moved (None: it did not; a warning when the slice has no trusted pixel)."""
        self.latent(x, y)  # range check
        if bool(self.trusted[y, x]):
            return x, y, None
        why = []
        if bool(self.untrusted[y, x]):
            var = float(self.slice.variance.flip(0)[y, x])
            why.append(f"variance {var:.3f} > {self.trust * (1 + self.model.mu):.3f}")
        if bool(self.invalid[y, x]):
            why.append("the model's prediction there is not a valid BRDF (negative values or albedo > 1)")
        ys, xs = torch.nonzero(self.trusted, as_tuple=True)
        if ys.numel() == 0:
            return x, y, f"no trusted point on this slice ({'; '.join(why)}): kept as clicked"
        k = int(((ys - y) ** 2 + (xs - x) ** 2).argmin())
        return (
            int(xs[k]),
            int(ys[k]),
            f"outside the trusted region ({'; '.join(why)}): snapped to the nearest trusted point",
        )

    def image(self) -> torch.Tensor:
        """(R, R, 3) uint8: variance shading (row 0 = the top = largest second latent) and dots."""
        var = self.slice.variance.flip(0)
        shade = (1 - var / var.max().clamp_min(1e-12)).clamp(0, 1) * 0.85 + 0.15
        img = shade[..., None].expand(-1, -1, 3).clone()
        dim = torch.tensor([0.35, 0.45, 0.75], dtype=img.dtype)  # untrusted: dimmed, blue
        img[self.untrusted] = img[self.untrusted] * dim * 0.6
        red = torch.tensor([0.85, 0.15, 0.15], dtype=img.dtype)  # invalid prediction: red
        img[self.invalid] = 0.5 * img[self.invalid] + 0.5 * red
        t = self.trusted
        edge = torch.zeros_like(t)  # the trusted region's edge, in yellow
        edge[1:] |= t[1:] != t[:-1]
        edge[:, 1:] |= t[:, 1:] != t[:, :-1]
        img[edge & t] = torch.tensor([0.95, 0.8, 0.1], dtype=img.dtype)
        u0, u1, v0, v1 = self.slice.extent
        r = self.resolution
        a, b = self.dims
        for x in self.model.latents:
            px = round((float(x[a]) - u0) / (u1 - u0) * (r - 1))
            py = round((v1 - float(x[b])) / (v1 - v0) * (r - 1))
            img[max(py - 1, 0) : py + 2, max(px - 1, 0) : px + 2] = torch.tensor([0.85, 0.25, 0.05], dtype=img.dtype)
        return (img * 255).round().to(torch.uint8)

    def latent(self, x: int, y: int) -> torch.Tensor:
        """The latent point (Q,) under map pixel (x, y) (row 0 at the top)."""
        r = self.resolution
        if not (0 <= x < r and 0 <= y < r):
            raise ValueRangeError(f"({x}, {y}) is outside the {r}x{r} latent map")
        return self.slice.points.flip(0)[y, x].clone()

    def material_coefficients(self, session, obj: str) -> torch.Tensor:
        """(N, J, 3) each fitted material projected onto ``obj``'s bands (computed once)."""
        if obj not in self._coefficients:
            cs = [session.coefficients(obj, NBRDF(name, self.nbrdf)) for name in self.names]
            self._coefficients[obj] = torch.stack(cs)
        return self._coefficients[obj]

    def pick(self, session, obj: str, x: int, y: int) -> tuple[torch.Tensor, dict]:
        """Blend for map pixel (x, y): the object's coefficients (J, 3) and what they came from
        (``latent``, ``variance``, the three ``heaviest`` materials by weight, the three
        ``nearest`` by latent distance, ``picked`` (x, y) after :meth:`snap` and ``warning``:
        why it moved, or None)."""
        x, y, warning = self.snap(x, y)
        z = self.latent(x, y)
        b = self.model.weights(z)
        c = torch.einsum("n,njc->jc", b, self.material_coefficients(session, obj)).clamp_min(0)
        top = torch.argsort(b.abs(), descending=True)[:3].tolist()
        info = {
            "latent": [round(float(v), 4) for v in z],
            "variance": float(self.model.variance(z)),
            "heaviest": [(self.names[k], round(float(b[k]), 3)) for k in top],
            "nearest": self.nearest_materials(z),
            "picked": (x, y),
            "warning": warning,
        }
        return c, info

    def material(self, session, obj: str, c: torch.Tensor) -> dict:
        """A ``factored_1d`` material dict holding coefficients ``c`` on ``obj``'s bands."""
        return session.band_material(obj, c)
