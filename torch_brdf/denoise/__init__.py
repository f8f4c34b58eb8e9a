"""Denoising precomputed basis images (every BRDF edit stays exact) and final frames.

* :mod:`.guides`: per-pixel guide buffers from the camera's pixel-centre rays;
* :mod:`.atrous`: a linear edge-aware à-trous filter with weights from the guides only;
* :mod:`.oidn`: Intel Open Image Denoise per grouped basis image and per frame (optional
  extra ``denoise``);
* :mod:`.tensors`: apply a denoiser to the multibounce tensors or a frozen tensor.

HDR-FLIP, the perceptual error of the denoising benchmark, is :func:`torch_brdf.metrics.hdr_flip`.
"""

from .atrous import AtrousSettings, EdgeAwareFilter
from .guides import GuideBuffers, guide_buffers
from .oidn import OIDNBasis, oidn_available, oidn_frame, oidn_image
from .tensors import denoise_frozen, denoise_planes, denoise_tensors

__all__ = [
    "AtrousSettings",
    "EdgeAwareFilter",
    "GuideBuffers",
    "OIDNBasis",
    "denoise_frozen",
    "denoise_planes",
    "denoise_tensors",
    "guide_buffers",
    "oidn_available",
    "oidn_frame",
    "oidn_image",
]
