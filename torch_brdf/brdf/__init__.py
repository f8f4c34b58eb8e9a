"""BRDFs as torch modules: one base class, constrained parameters, a string registry."""

from .base import BRDF, Clamped, Lambert, Positive, available, create, register

__all__ = ["BRDF", "Clamped", "Lambert", "Positive", "available", "create", "register"]
