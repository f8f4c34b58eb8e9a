"""Light transport: the reference path tracer, the precomputations (multibounce tensors) and the
differential block visibility of all-frequency relighting."""

from ..records.visibility_codec import BlockVisibility
from .pathtrace import PathTraceSettings, path_trace, reference_path_trace
from .polynomial import (
    LobeMixture,
    Mixture,
    ObjectBasis,
    PolynomialSettings,
    PolynomialTensors,
    Series,
    TensorBlock,
    TermTable,
    plan_bases,
    precompute_polynomial,
)
from .visibility import SceneVertices, VertexVisibility, VisibilitySettings, precompute_visibility, scene_vertices

__all__ = [
    "BlockVisibility",
    "LobeMixture",
    "Mixture",
    "ObjectBasis",
    "PathTraceSettings",
    "PolynomialSettings",
    "PolynomialTensors",
    "SceneVertices",
    "Series",
    "TensorBlock",
    "TermTable",
    "VertexVisibility",
    "VisibilitySettings",
    "path_trace",
    "plan_bases",
    "precompute_polynomial",
    "precompute_visibility",
    "reference_path_trace",
    "scene_vertices",
]
