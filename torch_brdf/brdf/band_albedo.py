"""Old home of the equivalent albedo, now :mod:`torch_brdf.brdf.bands.albedo`.

Kept only so that ``from torch_brdf.brdf.band_albedo import band_albedos`` in modules owned
by concurrent branches (``render/polynomial.py``) keeps working until they are merged; new
code imports from :mod:`torch_brdf.brdf.bands`. Delete this module once no import is left.
"""

from .bands.albedo import EquivalentAlbedoCacheWarning, band_albedos, cache_dir, equivalent_albedo

__all__ = ["EquivalentAlbedoCacheWarning", "band_albedos", "cache_dir", "equivalent_albedo"]
