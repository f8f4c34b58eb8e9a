"""What decides a multibounce precomputation: one frozen, self-hashing settings object.

:class:`PolynomialSettings` holds every choice the record depends on besides the scene and
the seed (series, spp or spp map, bases, sampler, light samples, tiles, guides, storage).
:func:`~torch_brdf.transport.polynomial.precompute_polynomial` reads it, ``torch-brdf
precompute`` builds it from its options, the GI planner returns one, and its :meth:`key` feeds
the tile cache's resume key. Every check of these values lives here, so a bad value is refused
when the object is built, before a scene is loaded.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import torch

from ..._checks import MAX_BANDS, check_bool, check_count, check_fields
from ...errors import ShapeError, ValueRangeError
from ...records.polynomial import ObjectBasis, Series
from .bases import check_basis_overrides
from .sampler import LobeMixture, Mixture

__all__ = ["STORAGES", "PolynomialSettings"]

#: how :meth:`~torch_brdf.records.polynomial.PolynomialTensors.save` may store the values
STORAGES = ("float32", "float16")


def _run_lengths(x: torch.Tensor) -> list[list[int]]:
    """[[value, run length], ...] of ``x`` (1-D int) in order: a compact, exact copy of an spp map."""
    vals, counts = torch.unique_consecutive(x, return_counts=True)
    return [[int(v), int(c)] for v, c in zip(vals.tolist(), counts.tolist(), strict=True)]


def _check_spp(spp: Any) -> int | torch.Tensor:
    """An int >= 1, or a 2-D integer map of them (its shape is checked against the camera at run time)."""
    if not isinstance(spp, torch.Tensor) or spp.ndim == 0:
        return check_count(spp, "spp")
    if spp.ndim != 2 or spp.dtype.is_floating_point or spp.dtype.is_complex or spp.dtype == torch.bool:
        raise ShapeError(f"Expected an spp map of integers with shape (H, W); got {spp.dtype} {tuple(spp.shape)}")
    if spp.numel() and int(spp.min()) < 1:
        raise ValueRangeError(f"every pixel needs spp >= 1; the map's least is {int(spp.min())}")
    return spp.detach().to(torch.long).clone()


def _check_bases(bases: Any) -> tuple[ObjectBasis | None, ...] | dict[str, dict[str, Any]] | None:
    """None, per-object bases (a list or tuple: one :class:`ObjectBasis` or None per object), or
    overrides for :func:`~.bases.plan_bases` (checked by :func:`~.bases.check_basis_overrides`)."""
    if bases is None:
        return None
    if isinstance(bases, (list, tuple)):
        bad = [b for b in bases if b is not None and not isinstance(b, ObjectBasis)]
        if bad:
            raise ValueRangeError(f"bases per object must be ObjectBasis or None; got {bad[0]!r}")
        return tuple(bases)
    return copy.deepcopy(check_basis_overrides(bases, "bases"))


def _check_optional_count(value: Any, name: str) -> int | None:
    return None if value is None else check_count(value, name)


@dataclass(frozen=True, eq=False)
class PolynomialSettings:
    """The settings of :func:`~torch_brdf.transport.polynomial.precompute_polynomial`.

    Frozen; equal settings have equal :meth:`key` and hash (an spp map is compared by value).

    Args:
        series: the BRDF series, e.g. ``"64,1,1,1"`` (a string, a sequence of ints or a
            :class:`~torch_brdf.records.polynomial.Series`); its length is the number of bounces.
        spp: paths per pixel, or an (H, W) integer map of them (adaptive sampling: each pixel
            is the average over its own paths, so every pixel stays unbiased).
        bases: per-object :class:`ObjectBasis` (or None for a fixed object), one per object, or
            overrides ``{object name: {key: value}}`` for :func:`~.bases.plan_bases`.
        mixture: direction sampling (default :class:`~.sampler.Mixture`: 70% cosine, 30% Blinn
            200); a :class:`~.sampler.LobeMixture` samples its objects from a defensive mixture
            of lobe widths (``stratified=True``: also stratified over each pixel's paths).
        env_point_lights: replace the environment by its K median-cut point lights for NEE.
        light_samples: next-event samples per light at the eye vertex, each weighted 1/k.
        tile_rows: image rows per tile (None: about ``TILE_PIXELS`` pixels per tile); part of
            the random stream.
        group: passes traced together (None: enough for >= 64k rays per batch); part of the
            random stream.
        fixed: names of objects to fix for this run (``editable=False``: their full BRDF is
            baked into the path weights), as a plan decides.
        guides: attach the view's denoiser guides to the record.
        storage: how the record's values are saved (``"float32"`` or ``"float16"``).
    Raises:
        ValueRangeError, ShapeError, SceneError: a value out of range or of the wrong form
            (the exception's ``setting`` attribute names the field, see
            :func:`~torch_brdf._checks.check_fields`).
    """

    series: Series | str | Sequence[int] = "64,1,1,1"
    spp: int | torch.Tensor = 64
    bases: tuple[ObjectBasis | None, ...] | dict[str, dict[str, Any]] | None = None
    mixture: Mixture | LobeMixture | None = None
    env_point_lights: int | None = None
    light_samples: int = 1
    tile_rows: int | None = None
    group: int | None = None
    fixed: tuple[str, ...] = ()
    guides: bool = True
    storage: str = "float32"

    def __post_init__(self):
        check_fields(
            self,
            {
                "series": _check_series,
                "spp": _check_spp,
                "bases": _check_bases,
                "mixture": _check_mixture,
                "env_point_lights": lambda v: _check_optional_count(v, "env_point_lights"),
                "light_samples": lambda v: check_count(v, "light_samples", 1024),
                "tile_rows": lambda v: _check_optional_count(v, "tile_rows"),
                "group": lambda v: _check_optional_count(v, "group"),
                "fixed": _check_names,
                "guides": lambda v: check_bool(v, "guides"),
                "storage": _check_storage,
            },
        )

    def replace(self, **changes: Any) -> PolynomialSettings:
        """A copy with ``changes`` (checked again)."""
        return replace(self, **changes)

    @property
    def uniform(self) -> bool:
        """True when every pixel takes the same number of paths."""
        return not isinstance(self.spp, torch.Tensor) or bool((self.spp == self.spp.flatten()[0]).all())

    def spp_map(self, height: int, width: int) -> torch.Tensor:
        """(H, W) int64 paths per pixel for a camera of ``height`` x ``width`` pixels.

        Raises:
            ShapeError: an spp map of another shape.
        """
        if not isinstance(self.spp, torch.Tensor):
            return torch.full((height, width), self.spp, dtype=torch.long)
        if tuple(self.spp.shape) != (height, width):
            raise ShapeError(
                f"Expected an spp map of integers with shape ({height}, {width}); got {self.spp.dtype} "
                f"{tuple(self.spp.shape)}"
            )
        return self.spp

    def key(self) -> dict[str, Any]:
        """Every field in JSON form (an spp map as its shape and run lengths): what the resume
        key and :meth:`__hash__` cover."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "series":
                v = list(v.bands)
            elif f.name == "spp" and isinstance(v, torch.Tensor):
                v = {"shape": list(v.shape), "runs": _run_lengths(v.reshape(-1))}
            elif f.name == "bases" and isinstance(v, tuple):
                v = [None if b is None else b.spec() for b in v]
            elif f.name == "mixture":
                v = [type(v).__name__, v.spec()]
            elif f.name == "fixed":
                v = list(v)
            out[f.name] = v
        return out

    def __hash__(self) -> int:
        return hash(json.dumps(self.key(), sort_keys=True))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PolynomialSettings):
            return NotImplemented
        return self.key() == other.key()


def _check_series(value: Any) -> Series:
    series = Series.parse(value)
    check_count(series.eye, "series bands per bounce", MAX_BANDS)
    return series


def _check_mixture(value: Any) -> Mixture | LobeMixture:
    if value is None:
        return Mixture()
    if not isinstance(value, (Mixture, LobeMixture)):
        raise ValueRangeError(f"mixture must be a Mixture or a LobeMixture; got {value!r}")
    return value


def _check_names(value: Any) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, Sequence) or not all(isinstance(n, str) for n in value):
        raise ValueRangeError(f"fixed must be a sequence of object names; got {value!r}")
    return tuple(value)


def _check_storage(value: Any) -> str:
    if value not in STORAGES:
        raise ValueRangeError(f"storage must be one of {STORAGES}; got {value!r}")
    return value
