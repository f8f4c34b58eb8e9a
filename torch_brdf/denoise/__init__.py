"""Denoising precomputed basis images (every BRDF edit stays exact) and final frames.

* guides (traced in :mod:`torch_brdf.transport.guides`, kept as the record
  :class:`~torch_brdf.records.guides.GuideBuffers`, both exported here): per-pixel guide
  buffers from the camera's pixel-centre rays, and the area lights' noise-free light lobes
  through a glossy object's bands;
* :mod:`.atrous`: a linear edge-aware à-trous filter with weights from the guides only;
* :mod:`.regression`: a linear local polynomial regression (NFOR-style) with the same weights;
* :mod:`.selection`: per pixel the regression window of lowest error, picked once from two
  half-sample buffers (NFOR's selection; linear once picked);
* :mod:`.oidn`: Intel Open Image Denoise per grouped basis image, per cumulative band sum and
  per frame (optional extra ``denoise``);
* :mod:`.tensors`: apply a denoiser to the multibounce tensors or a frozen tensor;
* :mod:`.frame`: denoise the final edited frame and keep each object's mean (any edits).

HDR-FLIP, the perceptual error of the denoising benchmark, is :func:`torch_brdf.metrics.hdr_flip`.
"""

from ..records.guides import GuideBuffers
from ..transport.guides import guide_buffers, light_lobe_images, pixel_coverage
from .atrous import AtrousSettings, EdgeAwareFilter, GuideSigmas, GuideWeights, glossy_objects
from .frame import FrameDenoiser, keep_region_means, region_mean_error
from .oidn import KEEP_MEAN_SIGMA, CumulativeOIDN, OIDNBasis, oidn_available, oidn_frame, oidn_image
from .regression import RegressionFilter, RegressionSettings
from .selection import SelectedRegressionFilter, SelectionSettings, silhouette_signature
from .tensors import denoise, denoise_frozen, denoise_planes, denoise_tensors, make_denoiser, mean_tensors

__all__ = [
    "KEEP_MEAN_SIGMA",
    "AtrousSettings",
    "CumulativeOIDN",
    "EdgeAwareFilter",
    "FrameDenoiser",
    "GuideBuffers",
    "GuideSigmas",
    "GuideWeights",
    "OIDNBasis",
    "RegressionFilter",
    "RegressionSettings",
    "SelectedRegressionFilter",
    "SelectionSettings",
    "denoise",
    "denoise_frozen",
    "denoise_planes",
    "denoise_tensors",
    "glossy_objects",
    "guide_buffers",
    "keep_region_means",
    "light_lobe_images",
    "make_denoiser",
    "mean_tensors",
    "oidn_available",
    "oidn_frame",
    "oidn_image",
    "pixel_coverage",
    "region_mean_error",
    "silhouette_signature",
]
