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

The blend becomes a ``factored_1d`` material on the object's bands, so the lobe view, the lit
sphere and the reference path trace all see exactly what the renderer shows. Not done: the
full blended table (what the bands cannot hold, e.g. the
:math:`\theta_d` dependence of the measured materials, is lost before blending).
"""

from __future__ import annotations

import torch

from ..brdf import NBRDF
from ..data import data_path
from ..errors import ValueRangeError
from ..io.merl import load_nbrdf_weights
from ..manifold import GPLVM, GPLVMFit, latent_slice


class LatentMap:
    """A clickable latent map of a GPLVM fit of NBRDF materials.

    Args:
        fit: a :class:`~torch_brdf.manifold.GPLVMFit` (or its file) whose ``names`` are NBRDF
            materials.
        weights: the NBRDF weights file (default: the shared data's
            ``merl/nbrdf_merl100_weights.npz``).
        resolution: pixels per side of the map.
        dims: the two latent dimensions shown (horizontal, vertical).
    """

    def __init__(self, fit, weights=None, resolution: int = 96, dims: tuple[int, int] = (0, 1)):
        fit = fit if isinstance(fit, GPLVMFit) else GPLVMFit.load(fit)
        if fit.latents.shape[1] < 2:
            raise ValueRangeError(f"the latent map needs q >= 2; the fit has q = {fit.latents.shape[1]}")
        self.model = GPLVM(fit)
        self.names = list(fit.names)
        self.nbrdf = load_nbrdf_weights(weights or data_path("merl", "nbrdf_merl100_weights.npz"))
        missing = [n for n in self.names if n not in self.nbrdf.names]
        if missing:
            raise ValueRangeError(f"the fit names materials the NBRDF file lacks: {missing[:5]}")
        self.resolution = resolution
        self.set_dims(dims)
        self._coefficients: dict[str, torch.Tensor] = {}

    @property
    def q(self) -> int:
        """Latent dimensions of the fit."""
        return int(self.model.latents.shape[1])

    def set_dims(self, dims: tuple[int, int]) -> None:
        """Show the slice on latent dimensions ``dims`` (two distinct axes in 0..q-1; the
        others stay at the latents' mean). Raises ValueRangeError otherwise."""
        self.slice = latent_slice(self.model, tuple(int(d) for d in dims), resolution=self.resolution)
        self.dims = self.slice.dims

    def image(self) -> torch.Tensor:
        """(R, R, 3) uint8: variance shading (row 0 = the top = largest second latent) and dots."""
        var = self.slice.variance.flip(0)
        shade = (1 - var / var.max().clamp_min(1e-12)).clamp(0, 1) * 0.85 + 0.15
        img = shade[..., None].expand(-1, -1, 3).clone()
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
        (``latent``, ``variance``, the three ``heaviest`` materials by weight)."""
        z = self.latent(x, y)
        b = self.model.weights(z)
        c = torch.einsum("n,njc->jc", b, self.material_coefficients(session, obj)).clamp_min(0)
        top = torch.argsort(b.abs(), descending=True)[:3].tolist()
        info = {
            "latent": [round(float(v), 4) for v in z],
            "variance": float(self.model.variance(z)),
            "heaviest": [(self.names[k], round(float(b[k]), 3)) for k in top],
        }
        return c, info

    def material(self, session, obj: str, c: torch.Tensor) -> dict:
        """A ``factored_1d`` material dict holding coefficients ``c`` on ``obj``'s bands."""
        return session.band_material(obj, c)
