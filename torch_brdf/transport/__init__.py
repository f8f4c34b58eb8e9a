"""Light transport: the reference path tracer and the precomputations (multibounce tensors)."""

from .pathtrace import path_trace, reference_path_trace
from .polynomial import (
    Mixture,
    ObjectBasis,
    PolynomialTensors,
    Series,
    TensorBlock,
    TermTable,
    plan_bases,
    precompute_polynomial,
)

__all__ = [
    "Mixture",
    "ObjectBasis",
    "PolynomialTensors",
    "Series",
    "TensorBlock",
    "TermTable",
    "path_trace",
    "plan_bases",
    "precompute_polynomial",
    "reference_path_trace",
]
