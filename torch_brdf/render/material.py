r"""Materials to band coefficients: what :meth:`PolynomialRenderer.set_material
<torch_brdf.render.polynomial.PolynomialRenderer.set_material>` and the editor's session give an
object whose eye vertex was precomputed on bands (Ben-Artzi et al. 2008, Sec. 4 and App. A).

A BRDF becomes the object's eye-vertex coefficients ``c`` (J·layers, 3) in three steps, the
same wherever a material is set:

1. The one-layer curve (J, 3) of :math:`\rho/\rho_q` on the object's bands: a
   :class:`~torch_brdf.brdf.bands.Factored1D` on exactly these bands and quotient is used as
   is; a Lambert BRDF on a constant quotient is exact without quadrature (a constant projects
   onto box bands as itself); anything else is projected by cosine-weighted least squares
   (:func:`~torch_brdf.brdf.bands.project`, or a :class:`~torch_brdf.brdf.bands.Projector`
   built once on a coarser rule for interactive edits).
2. For an object precomputed with the Fresnel layer (App. A, Eq. 31-32), the split of that
   curve by the user's :math:`F_0`: :math:`f_1 = F_0 f`, :math:`f_2 = (1 - F_0) f`; a
   :class:`~torch_brdf.brdf.bands.FresnelFactored1D` on these bands gives its two layers itself.
3. Nothing else: the diffuse equivalent and the second-bounce coefficients follow from ``c``
   in the renderer (:meth:`~torch_brdf.render.polynomial.PolynomialRenderer.set_coefficients`).
"""

from __future__ import annotations

import math
from typing import Any

import torch

from ..brdf import BRDF, Lambert, Projector
from ..brdf.bands import Factored1D, FresnelFactored1D, project
from ..errors import ValueRangeError
from ..records.polynomial import ObjectBasis

__all__ = ["MaterialProjector"]


class MaterialProjector:
    """A BRDF's eye-vertex band coefficients on one object's basis (module docstring).

    Args:
        basis: the object's :class:`~torch_brdf.records.polynomial.ObjectBasis`.
        quadrature: None: every projection runs :func:`~torch_brdf.brdf.bands.project` on its
            default rule; a dict of :meth:`~torch_brdf.brdf.bands.PairQuadrature.build` options:
            a :class:`~torch_brdf.brdf.bands.Projector` on that rule, built once per anisotropy
            and reused (interactive edits).
        graph: keep the autograd graph of the exact cases (Lambert albedo, a curve on these
            bands) in the BRDF's own dtype; False gives them as float64 constants, as a
            projection is.
    """

    def __init__(self, basis: ObjectBasis, quadrature: dict[str, Any] | None = None, graph: bool = True):
        self.basis = basis
        self.quadrature = None if quadrature is None else dict(quadrature)
        self.graph = bool(graph)
        self._bands = None
        self._projectors: dict[bool, Projector] = {}

    @property
    def bands(self):
        """The object's :class:`~torch_brdf.brdf.bands.BandBasis` (made once)."""
        if self._bands is None:
            self._bands = self.basis.band_basis()
        return self._bands

    def _exact(self, t: torch.Tensor) -> torch.Tensor:
        return t if self.graph else t.detach().double()

    def on_bands(self, brdf: BRDF) -> bool:
        """Whether ``brdf`` is a curve on exactly these bands and quotient (used as is)."""
        return (
            isinstance(brdf, Factored1D)
            and torch.equal(brdf.basis.edges, self.bands.edges)
            and brdf.quotient.key == self.basis.quotient
        )

    def curve(self, brdf: BRDF) -> torch.Tensor:
        """The one-layer curve (J, 3) of ``brdf`` on the object's bands (step 1)."""
        b = self.basis
        if type(brdf) is Lambert and b.quotient == "one":
            return (self._exact(brdf.reflectance) / math.pi).reshape(1, -1).expand(b.J, 3)
        if type(brdf) is Factored1D and self.on_bands(brdf):
            return self._exact(brdf.coefficients)
        if self.quadrature is None:
            return project(brdf, self.bands, b.quotient)
        key = bool(brdf.anisotropic)
        if key not in self._projectors:
            self._projectors[key] = Projector(self.bands, b.quotient, key, **self.quadrature)
        return self._projectors[key](brdf)

    def __call__(self, brdf: BRDF, f0=None, name: str = "the object") -> tuple[torch.Tensor, torch.Tensor]:
        """The coefficients of ``brdf`` and its curve.

        Args:
            brdf: any BRDF of the library.
            f0: the Fresnel layer's :math:`F_0` (scalar or RGB in [0, 1]; None: 1, the BRDF as
                given); only for an object precomputed with the Fresnel layer.
            name: the object's name, for the errors.
        Returns:
            c: (J·layers, 3) eye-vertex coefficients; curve: (J, 3), the one-layer curve.
        Raises:
            ValueRangeError: ``f0`` outside [0, 1], or given for an object without the Fresnel layer.
        """
        b = self.basis
        if b.fresnel and isinstance(brdf, FresnelFactored1D) and self.on_bands(brdf):
            layers = torch.cat([lay.coefficients for lay in brdf.layers()], 0)
            return self._exact(layers), self._exact(brdf.coefficients)
        base = self.curve(brdf)
        if not b.fresnel:
            if f0 is not None:
                raise ValueRangeError(
                    f"{name!r} was precomputed without a Fresnel layer, so f0 cannot be edited; "
                    "precompute with bases={name: {'fresnel': True}} to edit f0"
                )
            return base, base
        # Eq. 32: f1 = F f, f2 = (1 - F) f with the user's F0 (default 1: no Fresnel)
        f = torch.as_tensor(1.0 if f0 is None else f0, dtype=base.dtype).reshape(-1).expand(3)
        if bool(((f < 0) | (f > 1)).any()) or not bool(torch.isfinite(f).all()):
            raise ValueRangeError(f"f0 must lie in [0, 1]; got {f.tolist()}")
        return torch.cat([base * f, base * (1 - f)], 0), base
