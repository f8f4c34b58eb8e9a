"""The guide-buffer record: per-pixel first-hit data of one view that denoisers use as guides
(traced by :func:`torch_brdf.transport.guides.guide_buffers`, saved with the multibounce tensors
and read by :mod:`torch_brdf.denoise`). See :mod:`torch_brdf.transport.guides` for what each
guide means and why none depends on a material."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import FileFormatError, ShapeError

GUIDE_NAMES = ("normal", "position", "depth", "object_id", "albedo", "mirror_id", "mirror_radiance", "light_cos_h")
GUIDE_VERSION = 1


@dataclass(frozen=True)
class GuideBuffers:
    """Per-pixel guides of one view (row-major, row 0 at the top).

    Attributes:
        normal: (H, W, 3) float32 unit shading normal facing the eye; 0 on a miss.
        position: (H, W, 3) float32 world position of the first hit; 0 on a miss.
        depth: (H, W) float32 distance from the eye; ``inf`` on a miss.
        object_id: (H, W) int64 scene object index; -1 on a miss.
        albedo: (H, W, 3) float32 material-independent albedo proxy in [0.35, 0.95] per
            object (a function of the object id only); 0 on a miss.
        mirror_id: (H, W) int64 object hit by the mirror ray of the first hit; -1 when it
            escapes, -2 where the pixel sees no surface.
        mirror_radiance: (H, W, 3) float32 emitted radiance the mirror ray sees directly.
        light_cos_h: (H, W) float32 cosine of the half-vector angle to the brightest light
            (0 where the pixel sees no surface).
        pixel_angle: the angle one pixel subtends at the image centre (radians), to turn
            depths into pixel footprints.
    """

    normal: torch.Tensor
    position: torch.Tensor
    depth: torch.Tensor
    object_id: torch.Tensor
    albedo: torch.Tensor
    mirror_id: torch.Tensor
    mirror_radiance: torch.Tensor
    light_cos_h: torch.Tensor
    pixel_angle: float

    def __post_init__(self):
        h, w = self.object_id.shape
        for name, shape in (
            ("normal", (h, w, 3)),
            ("position", (h, w, 3)),
            ("depth", (h, w)),
            ("albedo", (h, w, 3)),
        ) + (
            ("mirror_id", (h, w)),
            ("mirror_radiance", (h, w, 3)),
            ("light_cos_h", (h, w)),
        ):
            if tuple(getattr(self, name).shape) != shape:
                raise ShapeError(f"guide {name!r}: expected shape {shape}; got {tuple(getattr(self, name).shape)}")

    @property
    def height(self) -> int:
        return self.object_id.shape[0]

    @property
    def width(self) -> int:
        return self.object_id.shape[1]

    def to_arrays(self, prefix: str = "guide_") -> dict[str, np.ndarray]:
        """numpy arrays for the array codec (:func:`torch_brdf.io.arrays.save_arrays`)."""
        out = {prefix + k: getattr(self, k).numpy() for k in GUIDE_NAMES}
        out[prefix + "meta"] = np.array([self.pixel_angle, GUIDE_VERSION], dtype=np.float64)
        return out

    @classmethod
    def from_arrays(cls, arrays: dict, prefix: str = "guide_") -> GuideBuffers | None:
        """The guides stored by :meth:`to_arrays`, or None when ``arrays`` holds none.

        Raises:
            FileFormatError: guides of a newer version or incomplete.
        """
        if prefix + "meta" not in arrays:
            return None
        angle, version = (float(x) for x in np.asarray(arrays[prefix + "meta"]))
        if version > GUIDE_VERSION:
            raise FileFormatError(f"guide buffers of version {version:g}; this reader knows {GUIDE_VERSION}")
        try:
            t = {k: torch.from_numpy(np.array(arrays[prefix + k])) for k in GUIDE_NAMES}
        except KeyError as exc:
            raise FileFormatError(f"incomplete guide buffers: {exc} missing") from exc
        return cls(
            t["normal"],
            t["position"],
            t["depth"],
            t["object_id"].long(),
            t["albedo"],
            t["mirror_id"].long(),
            t["mirror_radiance"],
            t["light_cos_h"],
            angle,
        )
