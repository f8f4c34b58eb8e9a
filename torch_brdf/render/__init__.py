"""Modules that turn precomputed records plus coefficients into images."""

from .record import BasisImage, BasisImageRenderer, float16_error

__all__ = ["BasisImage", "BasisImageRenderer", "float16_error"]
