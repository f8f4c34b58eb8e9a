"""The denoisers' guide buffers and light lobes (computed in :mod:`torch_brdf.transport.guides`,
where the precomputation attaches the guides to its record; re-exported here)."""

from ..scene.guides import GuideBuffers, object_albedo_proxy
from ..transport.guides import guide_buffers, light_lobe_images, pixel_coverage

__all__ = ["GuideBuffers", "guide_buffers", "light_lobe_images", "object_albedo_proxy", "pixel_coverage"]
