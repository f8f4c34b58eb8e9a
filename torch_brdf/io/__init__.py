"""Files: OpenEXR for linear radiance, 8-bit sRGB PNG for display, versioned array files,
MERL BRDF files (real ``.binary`` format and the downsampled npz table)."""

from .arrays import load_arrays, max_array_bytes, read_npz, save_arrays
from .exr import read_exr, write_exr
from .merl import (
    MERL_FILE_BYTES,
    MERL_RES,
    MERL_SCALE,
    MERLTableData,
    NBRDFWeights,
    load_merl_table,
    load_nbrdf_weights,
    merl_index_to_angles,
    merl_indices,
    read_merl_binary,
    write_merl_binary,
    write_merl_table,
)
from .png import TONEMAPS, auto_exposure, read_png, to_srgb8, write_png

__all__ = [
    "MERL_FILE_BYTES",
    "MERL_RES",
    "MERL_SCALE",
    "TONEMAPS",
    "MERLTableData",
    "NBRDFWeights",
    "auto_exposure",
    "load_arrays",
    "load_merl_table",
    "load_nbrdf_weights",
    "max_array_bytes",
    "merl_index_to_angles",
    "merl_indices",
    "read_exr",
    "read_merl_binary",
    "read_npz",
    "read_png",
    "save_arrays",
    "to_srgb8",
    "write_exr",
    "write_merl_binary",
    "write_merl_table",
    "write_png",
]
