r"""One record for every image that is linear in basis coefficients ("pixels x basis x channels").

Three capabilities produce the same kind of object: the first-order term of the multibounce
tensors (Ben-Artzi et al. 2008, Eq. 9: pixel value = :math:`\sum_j c_j T_j`), the transfer
functions of inverse BRDF design (Iwasaki et al., Eq. 6: :math:`B(x) = \sum_j c_j T_j(x)`), and
the per-material images that the BRDF manifold blends (Soler et al. 2017:
:math:`I^* = \sum_i b_i I_i`). :class:`BasisImage` holds any of them:

.. math:: I(p, c) = k(p, c) + \sum_j a_{jc}\, T(c, j, p)

for the pixels ``p`` it covers (a subset of an ``H x W`` frame), channels ``c`` and basis
functions ``j``; ``k`` is an optional constant part (emission, fixed objects, a diffuse term).

Memory layout decides the speed of evaluating it (measured with torch 2.13 on 2 cores): ``values`` is stored
``(C, J, P)``, coefficient axis before the pixel axis, so one evaluation is ``C`` matrix-vector
products that stream the record once (memory-bandwidth bound), never a ``(P, J)`` gather.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np
import torch

from .._checks import as_float_tensor, check_finite, check_image_size
from ..errors import ShapeError
from .codec import Member, Record

RECORD_KIND = "basis-image"
_STORAGE = {"float32": np.float32, "float16": np.float16, "float64": np.float64}


@dataclass(frozen=True)
class BasisImage(Record):
    """An image linear in ``J`` basis coefficients, over a subset of an ``H x W`` frame.

    Attributes:
        values: ``(C, J, P)`` the basis images ``T`` (coefficient axis before pixels).
        pixels: ``(P,)`` int64 flat row-major indices into the ``height x width`` frame.
        height, width: frame size.
        constant: ``(C, P)`` part independent of the coefficients, or None (zero).
        variance: ``(C, J, P)`` Monte Carlo variance of each entry's mean, or None.
        basis: what the basis functions are (e.g. ``"bands:theta_h:64"``, ``"srbf:147"``,
            ``"materials:merl100"``); coefficients of another basis must not be applied.
        meta: JSON-serialisable provenance (scene, spp, seed, ...).
    """

    values: torch.Tensor
    pixels: torch.Tensor
    height: int
    width: int
    constant: torch.Tensor | None = None
    variance: torch.Tensor | None = None
    basis: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    kind = RECORD_KIND
    version = 1
    schema: ClassVar[dict[str, Member]] = {
        "values": Member("f", 3, finite=True),
        "pixels": Member("iu", 1),
        "constant": Member("f", 2, finite=True, required=False),
        "variance": Member("f", 3, required=False),
    }

    def __post_init__(self):
        check_image_size(self.width, self.height, "basis image")  # the same cap as any image input
        v = self.values
        if v.ndim != 3:
            raise ShapeError(f"Expected values to have shape (C, J, P); got {tuple(v.shape)}")
        c, _, p = v.shape
        if self.pixels.shape != (p,) or self.pixels.dtype != torch.int64:
            raise ShapeError(
                f"Expected pixels to be int64 of shape ({p},); got {self.pixels.dtype} {tuple(self.pixels.shape)}"
            )
        if p and (int(self.pixels.min()) < 0 or int(self.pixels.max()) >= self.height * self.width):
            raise ShapeError(f"pixel indices fall outside the {self.height}x{self.width} frame")
        if self.constant is not None and self.constant.shape != (c, p):
            raise ShapeError(f"Expected constant to have shape ({c}, {p}); got {tuple(self.constant.shape)}")
        if self.variance is not None and self.variance.shape != v.shape:
            raise ShapeError(f"Expected variance to have shape {tuple(v.shape)}; got {tuple(self.variance.shape)}")

    # -- construction -------------------------------------------------------------------
    @classmethod
    def from_dense(cls, images, constant=None, mask=None, basis: str = "", meta=None) -> BasisImage:
        """Build from full-frame basis images.

        Args:
            images: ``(J, H, W, C)`` one image per basis function.
            constant: ``(H, W, C)`` or None.
            mask: ``(H, W)`` bool, the pixels to keep (default all).
        """
        images = as_float_tensor(images, "images")
        if images.ndim != 4:
            raise ShapeError(f"Expected images to have shape (J, H, W, C); got {tuple(images.shape)}")
        j, h, w, c = images.shape
        if mask is None:
            keep = torch.ones(h * w, dtype=torch.bool)
        else:
            keep = torch.as_tensor(mask, dtype=torch.bool).reshape(-1)
        if keep.numel() != h * w:
            raise ShapeError(f"Expected mask of shape ({h}, {w}); got {tuple(torch.as_tensor(mask).shape)}")
        pix = torch.nonzero(keep).squeeze(1)
        values = images.reshape(j, h * w, c)[:, pix].permute(2, 0, 1).contiguous()
        k = None
        if constant is not None:
            constant = as_float_tensor(constant, "constant")
            if constant.shape != (h, w, c):
                raise ShapeError(f"Expected constant to have shape ({h}, {w}, {c}); got {tuple(constant.shape)}")
            k = constant.reshape(h * w, c)[pix].T.contiguous()
        return cls(values, pix, h, w, k, None, basis, dict(meta or {}))

    # -- sizes --------------------------------------------------------------------------
    @property
    def channels(self) -> int:
        return self.values.shape[0]

    @property
    def num_basis(self) -> int:
        return self.values.shape[1]

    @property
    def num_pixels(self) -> int:
        return self.values.shape[2]

    @property
    def nbytes(self) -> int:
        n = self.values.numel() * self.values.element_size()
        for t in (self.constant, self.variance):
            if t is not None:
                n += t.numel() * t.element_size()
        return n

    # -- evaluation ---------------------------------------------------------------------
    def _coefficients(self, coefficients) -> torch.Tensor:
        a = coefficients if isinstance(coefficients, torch.Tensor) else torch.as_tensor(coefficients)
        a = a.to(self.values.dtype)
        c, j, _ = self.values.shape
        if a.shape == (j,):
            a = a[:, None].expand(j, c)
        if a.shape != (j, c):
            raise ShapeError(
                f"Expected coefficients of shape ({j},) or ({j}, {c}) for basis {self.basis!r}; got {tuple(a.shape)}"
            )
        check_finite(a, "coefficients")
        return a

    def pixel_values(self, coefficients) -> torch.Tensor:
        """``(P, C)`` radiance of the covered pixels for coefficients ``(J,)`` or ``(J, C)``.

        Differentiable in ``coefficients``; one pass over ``values``.
        """
        a = self._coefficients(coefficients)
        out = torch.bmm(a.T.unsqueeze(1), self.values).squeeze(1)  # (C, P)
        if self.constant is not None:
            out = out + self.constant
        return out.T

    def image(self, coefficients, background: float = 0.0) -> torch.Tensor:
        """``(H, W, C)`` frame; pixels the record does not cover hold ``background``."""
        vals = self.pixel_values(coefficients)
        frame = torch.full(
            (self.height * self.width, self.channels), float(background), dtype=vals.dtype, device=vals.device
        )
        frame = frame.index_put((self.pixels,), vals)
        return frame.reshape(self.height, self.width, self.channels)

    def to(self, dtype: torch.dtype) -> BasisImage:
        f = lambda t: None if t is None else t.to(dtype)  # noqa: E731
        return replace(self, values=self.values.to(dtype), constant=f(self.constant), variance=f(self.variance))

    def select(self, keep: torch.Tensor) -> BasisImage:
        """The record restricted to pixels where ``keep`` (``(P,)`` bool) holds."""
        idx = torch.nonzero(torch.as_tensor(keep, dtype=torch.bool)).squeeze(1)
        return replace(
            self,
            values=self.values[:, :, idx].contiguous(),
            pixels=self.pixels[idx],
            constant=None if self.constant is None else self.constant[:, idx].contiguous(),
            variance=None if self.variance is None else self.variance[:, :, idx].contiguous(),
        )

    # -- files --------------------------------------------------------------------------
    def to_arrays(self, storage: str = "float32") -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Arrays and metadata for :meth:`save` (``save(path, storage=...)``).

        Args:
            storage: ``"float32"`` (default), ``"float16"`` (half the bytes; relative rounding
                error <= 2^-11 per entry, and values above 65504 or below ~6e-8 are not
                representable: check with :func:`float16_error` first) or ``"float64"``.
        """
        if storage not in _STORAGE:
            raise ShapeError(f"storage must be one of {sorted(_STORAGE)}; got {storage!r}")
        dt = _STORAGE[storage]
        arrays = {"values": self.values.detach().numpy().astype(dt), "pixels": self.pixels.numpy()}
        if self.constant is not None:
            arrays["constant"] = self.constant.detach().numpy().astype(dt)
        if self.variance is not None:
            arrays["variance"] = self.variance.detach().numpy().astype(dt)
        meta = {"height": self.height, "width": self.width, "basis": self.basis, "storage": storage, "meta": self.meta}
        return arrays, meta

    @classmethod
    def from_arrays(cls, arrays, meta, dtype: torch.dtype = torch.float32) -> BasisImage:
        """The record of :meth:`to_arrays` output, in ``dtype`` (``load(path, dtype=...)``)."""
        t = {k: torch.from_numpy(np.asarray(v)) for k, v in arrays.items()}
        return cls(
            t["values"].to(dtype),
            t["pixels"].to(torch.int64),
            int(meta["height"]),
            int(meta["width"]),
            None if "constant" not in t else t["constant"].to(dtype),
            None if "variance" not in t else t["variance"].to(dtype),
            str(meta.get("basis", "")),
            dict(meta.get("meta", {})),
        )


def float16_error(t: torch.Tensor) -> float:
    """Largest relative error (over entries with ``|t| > 0``) of storing ``t`` as float16; inf on overflow."""
    t64 = t.detach().double()
    h = t64.to(torch.float16).double()
    if not bool(torch.isfinite(h).all()):
        return float("inf")
    nz = t64 != 0
    if not bool(nz.any()):
        return 0.0
    return float(((h - t64).abs()[nz] / t64.abs()[nz]).max())


__all__ = ["RECORD_KIND", "BasisImage", "float16_error"]
