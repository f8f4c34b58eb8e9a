"""Non-linear manifold of measured BRDFs (Soler, Subr, Nowrouzezahrai 2017, INRIA RR-9069).

A GPLVM places the materials in a q-dimensional latent space; any latent point x* gives the
BRDF z* = b(x*)ᵀ Z, a linear combination of the measured rows, so images, ZH coefficients
and other linear functionals of the BRDF blend with the same weights b.

* :mod:`.kernel`: shifted SE kernel (Eq. 5), Cholesky with jitter escalation.
* :mod:`.gplvm`: Gram-matrix fit (Eq. 6), :class:`GPLVM` interpolation / variance / projection.
* :mod:`.data`: MERL grids, observation matrices (NBRDF, ``.binary``), split, PCA
  (the held-out metrics live in :mod:`torch_brdf.metrics`).
* :mod:`.evaluate`: held-out reconstruction against PCA.
* :mod:`.paths`: latent slices, best paths, limitation diagnostics.
* :mod:`.materials`: per-material image records and the sphere scene (rendered by :mod:`torch_brdf.render.manifold`).
* :mod:`.zh`: real SH / rotated ZH shading of interpolated materials.
"""

from ..metrics import cosine_weighted_rmse, log_relative_rmse  # re-exported from torch_brdf.metrics
from .data import (
    MERLGrid,
    Observations,
    analytic_observations,
    default_grid,
    fit_pca,
    nbrdf_observations,
    read_split,
    split_names,
)
from .evaluate import HeldOut, heldout_reconstruction
from .gplvm import (
    GPLVM,
    VALIDITY,
    GPLVMFit,
    default_validity,
    fit_gplvm,
    gram,
    log_likelihood,
    projection_terms,
    simplex_projection,
)
from .kernel import JitterWarning, cholesky_jitter, kernel_matrix
from .materials import material_record, merl_material, random_record, sphere_scene, with_material
from .paths import (
    Interpolation,
    LatentPath,
    LatentSlice,
    PathProfile,
    best_path,
    directional_albedo,
    highlight_width,
    interpolant_diagnostics,
    interpolation_share,
    latent_points,
    latent_slice,
    resample_path,
    straight_paths,
)
from .zh import ZHCoefficients, env_sh, rows_brdf, zh_coefficients, zh_shade

__all__ = [
    "GPLVM",
    "VALIDITY",
    "GPLVMFit",
    "HeldOut",
    "Interpolation",
    "JitterWarning",
    "LatentPath",
    "LatentSlice",
    "MERLGrid",
    "Observations",
    "PathProfile",
    "ZHCoefficients",
    "analytic_observations",
    "best_path",
    "cholesky_jitter",
    "cosine_weighted_rmse",
    "default_grid",
    "default_validity",
    "directional_albedo",
    "env_sh",
    "fit_gplvm",
    "fit_pca",
    "gram",
    "heldout_reconstruction",
    "highlight_width",
    "interpolant_diagnostics",
    "interpolation_share",
    "kernel_matrix",
    "latent_points",
    "latent_slice",
    "log_likelihood",
    "log_relative_rmse",
    "material_record",
    "merl_material",
    "nbrdf_observations",
    "projection_terms",
    "random_record",
    "read_split",
    "resample_path",
    "rows_brdf",
    "simplex_projection",
    "sphere_scene",
    "split_names",
    "straight_paths",
    "with_material",
    "zh_coefficients",
    "zh_shade",
]
