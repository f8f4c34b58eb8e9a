"""Functions on the sphere: sampling warps with pdfs, lat-long map geometry, cubemaps in blocks,
the block DCT and Haar wavelets on cubemaps."""

from .cubemap import CubemapBlocks, cube_directions, direction_to_cube, texel_solid_angles_cube
from .dct import dct_basis, sample_positions, subsampled_inverse
from .haar import (
    HaarTripleProduct,
    SparseHaar,
    haar2d,
    haar_tripling_coefficients,
    ihaar2d,
    keep_largest,
)
from .latlong import (
    direction_to_latlong,
    direction_to_texel,
    latlong_to_direction,
    row_cos_bounds,
    texel_centers,
    texel_solid_angles,
)
from .warps import (
    cosine_hemisphere_pdf,
    square_to_cosine_hemisphere,
    square_to_uniform_disk_concentric,
    square_to_uniform_hemisphere,
    square_to_uniform_sphere,
    square_to_uniform_triangle,
    uniform_hemisphere_pdf,
    uniform_sphere_pdf,
)

__all__ = [
    "CubemapBlocks",
    "HaarTripleProduct",
    "SparseHaar",
    "cosine_hemisphere_pdf",
    "cube_directions",
    "dct_basis",
    "direction_to_cube",
    "direction_to_latlong",
    "direction_to_texel",
    "haar2d",
    "haar_tripling_coefficients",
    "ihaar2d",
    "keep_largest",
    "latlong_to_direction",
    "row_cos_bounds",
    "sample_positions",
    "square_to_cosine_hemisphere",
    "square_to_uniform_disk_concentric",
    "square_to_uniform_hemisphere",
    "square_to_uniform_sphere",
    "square_to_uniform_triangle",
    "subsampled_inverse",
    "texel_centers",
    "texel_solid_angles",
    "texel_solid_angles_cube",
    "uniform_hemisphere_pdf",
    "uniform_sphere_pdf",
]
