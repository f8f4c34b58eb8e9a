"""BRDFs as torch modules: one base class, constrained parameters, a string registry.

Importing this package registers every model: ``create("blinn_phong", exponent=100)`` or
``create({"type": "lambert", "albedo": 0.7})`` (a scene material dict).
"""

from .analytic import (
    AshikhminShirley,
    BlinnDistribution,
    BlinnPhong,
    DistributionBased,
    HalfVectorDistribution,
    Phong,
    TabulatedDistribution,
    Ward,
    WardAniso,
)
from .bands import (
    AnisotropicLobe,
    BandBasis,
    EquivalentAlbedoCacheWarning,
    Factored1D,
    FresnelFactored1D,
    PairQuadrature,
    Projector,
    Quotient,
    SchlickFresnel,
    SmithQuotient,
    band_albedos,
    band_edges,
    equivalent_albedo,
    make_quotient,
    project,
    projection_error,
)
from .base import BRDF, Clamped, Lambert, Positive, available, create, register
from .gltf import MetallicRoughness
from .measured import NBRDF, MERLTabulated, tabulate_nbrdf
from .microfacet import GGXNDF, AnisotropicPhongNDF, BeckmannNDF, BlinnNDF, CookTorrance, MicrofacetDistribution
from .plastic import RoughPlastic
from .srbf import SRBFBasis, SRBFDistribution, hemicube_centers, lambda_from_sigma, sigma_from_lambda

__all__ = [
    "BRDF",
    "GGXNDF",
    "NBRDF",
    "AnisotropicLobe",
    "AnisotropicPhongNDF",
    "AshikhminShirley",
    "BandBasis",
    "BeckmannNDF",
    "BlinnDistribution",
    "BlinnNDF",
    "BlinnPhong",
    "Clamped",
    "CookTorrance",
    "DistributionBased",
    "EquivalentAlbedoCacheWarning",
    "Factored1D",
    "FresnelFactored1D",
    "HalfVectorDistribution",
    "Lambert",
    "MERLTabulated",
    "MetallicRoughness",
    "MicrofacetDistribution",
    "PairQuadrature",
    "Phong",
    "Positive",
    "Projector",
    "Quotient",
    "RoughPlastic",
    "SRBFBasis",
    "SRBFDistribution",
    "SchlickFresnel",
    "SmithQuotient",
    "TabulatedDistribution",
    "Ward",
    "WardAniso",
    "available",
    "band_albedos",
    "band_edges",
    "create",
    "equivalent_albedo",
    "hemicube_centers",
    "lambda_from_sigma",
    "make_quotient",
    "project",
    "projection_error",
    "register",
    "sigma_from_lambda",
    "tabulate_nbrdf",
]
