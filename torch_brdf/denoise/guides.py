"""The denoisers' guide buffers (computed in :mod:`torch_brdf.transport.guides`, where the
precomputation attaches them to its record; re-exported here)."""

from ..scene.guides import GuideBuffers, object_albedo_proxy
from ..transport.guides import guide_buffers

__all__ = ["GuideBuffers", "guide_buffers", "object_albedo_proxy"]
