"""The renderer of a :class:`~torch_brdf.records.BasisImage`: an ``nn.Module`` over its buffers."""

from __future__ import annotations

import torch
from torch import nn

from ..records.basis_image import BasisImage, float16_error

__all__ = ["BasisImage", "BasisImageRenderer", "float16_error"]


class BasisImageRenderer(nn.Module):
    """``nn.Module`` holding a :class:`BasisImage` as buffers; ``forward(coefficients) -> (H, W, C)``.

    ``.to(dtype)`` converts the record; gradients flow to the coefficients (and to whatever
    produced them, e.g. BRDF parameters through a projection).
    """

    def __init__(self, record: BasisImage):
        super().__init__()
        self.register_buffer("values", record.values)
        self.register_buffer("pixels", record.pixels)
        self.register_buffer("constant", record.constant)
        self.height, self.width, self.basis = record.height, record.width, record.basis

    @property
    def record(self) -> BasisImage:
        return BasisImage(self.values, self.pixels, self.height, self.width, self.constant, None, self.basis)

    def forward(self, coefficients, background: float = 0.0) -> torch.Tensor:
        return self.record.image(coefficients, background)
