"""Modules that turn precomputed records plus coefficients into images.

- :class:`BasisImageRenderer`: any :class:`~torch_brdf.records.BasisImage` (first-order
  multibounce term, inverse-design transfer functions, the manifold's per-material images);
- :class:`PolynomialRenderer`: the multibounce polynomial tensors (Ben-Artzi et al. 2008);
- :class:`TripleProductRenderer`: all-frequency relighting from per-vertex visibility (Inger et al.);
- :mod:`.manifold`: images of interpolated materials by blending per-material renders (Soler et al.).
"""

from ..records.basis_image import BasisImage, float16_error
from .fit import ImageFit, blinn_phong_family, fit_image, object_mask, paint_image
from .manifold import blend, gi_blend_error, render_rows
from .polynomial import PolynomialRenderer, apply_scene_textures
from .record import BasisImageRenderer
from .triple import TripleProductRenderer

__all__ = [
    "BasisImage",
    "BasisImageRenderer",
    "ImageFit",
    "PolynomialRenderer",
    "TripleProductRenderer",
    "apply_scene_textures",
    "blend",
    "blinn_phong_family",
    "fit_image",
    "float16_error",
    "gi_blend_error",
    "object_mask",
    "paint_image",
    "render_rows",
]
