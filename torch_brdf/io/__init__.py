"""Files: OpenEXR for linear radiance, 8-bit sRGB PNG for display, versioned array files."""

from .arrays import load_arrays, save_arrays
from .exr import read_exr, write_exr
from .png import TONEMAPS, read_png, to_srgb8, write_png

__all__ = ["TONEMAPS", "load_arrays", "read_exr", "read_png", "save_arrays", "to_srgb8", "write_exr", "write_png"]
