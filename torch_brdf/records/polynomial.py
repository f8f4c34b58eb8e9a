r"""The multibounce polynomial tensors of Ben-Artzi et al. 2008 as a saved record.

:class:`PolynomialTensors` is what :func:`~torch_brdf.transport.polynomial.precompute_polynomial`
produces and :class:`~torch_brdf.render.polynomial.PolynomialRenderer` reads: per bounce
:math:`N` a table of terms (:class:`TermTable`: second-bounce slot and multiset of
diffuse-equivalent objects, Eq. 25-26) and, per tile, eye object and bounce, the sparse
entries :math:`T^N_{jt}(x)` (:class:`TensorBlock`). :class:`Series` (the BRDF resolution per
bounce, Eq. 17) and :class:`ObjectBasis` (each editable object's band basis, App. A) describe
what the coefficients mean, so they travel with the record.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch

from .._checks import MAX_BANDS, MAX_BOUNCES
from ..brdf.bands import BandBasis, Quotient, SchlickFresnel, make_quotient
from ..errors import FileFormatError, SceneError, ValueRangeError
from ..io.arrays import Converted
from .basis_image import BasisImage
from .codec import Member, Record
from .guides import GuideBuffers

__all__ = ["TENSOR_KIND", "ObjectBasis", "PolynomialTensors", "Series", "TensorBlock", "TermTable"]

TENSOR_KIND = "multibounce-tensors"
_SUPPORTED_VARIABLES = ("theta_h", "theta_d")


@dataclass(frozen=True)
class Series:
    r"""The BRDF resolution per bounce from the eye, :math:`(J_N, \dots, J_1)` (Eq. 17).

    ``len(bands)`` is the number of bounces :math:`\bar N` (surface vertices per path).
    ``bands[0]`` caps the eye vertex's bands, ``bands[1]`` (if > 1) gives a low-frequency
    second bounce (Sec. 4.3); every later entry must be 1 (diffuse equivalents). Examples:
    ``Series.parse("64,1,1,1")``, ``"64,16"``, ``"128,8,1"``.
    """

    bands: tuple[int, ...]

    def __post_init__(self):
        b = tuple(int(x) for x in self.bands)
        object.__setattr__(self, "bands", b)
        if not b or any(x < 1 for x in b):
            raise ValueRangeError(f"a BRDF series needs >= 1 bounce and bands >= 1; got {b}")
        if len(b) > MAX_BOUNCES or max(b) > MAX_BANDS:
            raise ValueRangeError(
                f"a BRDF series has at most {MAX_BOUNCES} bounces of at most {MAX_BANDS} bands; got {len(b)} "
                f"bounces, {max(b)} bands"
            )
        if any(b[i] < b[i + 1] for i in range(len(b) - 1)):
            raise ValueRangeError(f"a BRDF series must not increase away from the eye (Eq. 17); got {b}")
        if any(x != 1 for x in b[2:]):
            raise ValueRangeError(f"bounces beyond the second from the eye must be diffuse equivalents (1); got {b}")

    @classmethod
    def parse(cls, spec: str | Sequence[int] | Series) -> Series:
        if isinstance(spec, Series):
            return spec
        if isinstance(spec, str):
            # every entry is a number: "4,,1" or "64,1," is a typo, not the series (4, 1) or (64, 1)
            parts = spec.strip().removeprefix("(").removesuffix(")").split(",")
            try:
                if any(not p.strip() for p in parts):
                    raise ValueError("an empty entry")
                spec = [int(p) for p in parts]
            except ValueError as exc:
                raise ValueRangeError(f"cannot parse BRDF series {spec!r} ({exc}); expected e.g. '64,1,1,1'") from None
        return cls(tuple(spec))

    @property
    def bounces(self) -> int:
        return len(self.bands)

    @property
    def eye(self) -> int:
        return self.bands[0]

    @property
    def second(self) -> int:
        return self.bands[1] if len(self.bands) > 1 else 1

    @property
    def two_level(self) -> bool:
        """True when the second bounce from the eye has its own bands (Sec. 4.3)."""
        return self.second > 1

    @property
    def key(self) -> str:
        return ",".join(map(str, self.bands))


@dataclass(frozen=True)
class ObjectBasis:
    r"""The editable 1-D basis of one object: ``J`` box bands of ``variable`` with ``spacing``
    times ``quotient`` (App. A, Eq. 30); with ``fresnel`` a second layer with the Schlick
    quotient :math:`(1-\cos\theta_d)^5\rho_q` (Eq. 31-32), doubling the coefficients.

    ``second`` is the number of bands at a low-frequency second bounce (coarsened from these
    bands by :meth:`BandBasis.coarsened`; 1 when the series has none).
    """

    J: int
    variable: str = "theta_h"
    spacing: str = "sqrt"
    quotient: str = "one"
    fresnel: bool = False
    second: int = 1

    def __post_init__(self):
        if self.variable not in _SUPPORTED_VARIABLES:
            raise ValueRangeError(
                f"precomputed bases must be one-hot in (wi, wo): variable in {_SUPPORTED_VARIABLES}; "
                f"got {self.variable!r}"
            )
        if not 1 <= self.J <= MAX_BANDS or not 1 <= self.second <= self.J:
            raise ValueRangeError(
                f"need 1 <= J <= {MAX_BANDS} and 1 <= second <= J; got J={self.J}, second={self.second}"
            )

    def spec(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in ("J", "variable", "spacing", "quotient", "fresnel", "second")}

    @property
    def layers(self) -> int:
        return 2 if self.fresnel else 1

    def band_basis(self) -> BandBasis:
        return BandBasis(self.variable, self.J, "uniform" if self.J == 1 else self.spacing)

    def second_basis(self) -> BandBasis:
        return self.band_basis().coarsened(self.second)

    def quotients(self) -> list[Quotient]:
        q = make_quotient(self.quotient)
        return [q, SchlickFresnel(q)] if self.fresnel else [q]

    @property
    def size(self) -> int:
        """Coefficients at the eye vertex (all layers)."""
        return self.J * self.layers

    @property
    def second_size(self) -> int:
        return self.second * self.layers


@dataclass(frozen=True)
class TermTable:
    """The terms of one bounce: ``w`` (T,) second-bounce coefficient slot (-1: none) and
    ``counts`` (T, M) how often each object occurs among the diffuse-equivalent vertices."""

    w: torch.Tensor
    counts: torch.Tensor

    @property
    def size(self) -> int:
        return self.w.numel()


@dataclass(frozen=True)
class TensorBlock:
    """The tensor entries of one tile, eye object and bounce that occur, stored sparse.

    Within a tile the terms and pixels that appear are numbered (``terms``, ``pixels``); an
    entry (j, z, p) of the block's dense ``(C, J, Z, P)`` tensor is kept only if some path
    reached it (coordinate format, flat index ``(j * Z + z) * P + p``, ascending). At 64 spp
    a pixel holds at most 64 entries per bounce and layer, where a dense block over the
    tile's terms would hold J x Z (up to 64 x 84 on the Cornell box).

    Attributes:
        object_id: the object seen at the eye vertex.
        bounce: N (1 = direct lighting).
        pixels: (P,) int64 flat row-major pixel indices.
        terms: (Z,) int64 rows of the bounce's :class:`TermTable`.
        J: coefficients of the eye object (1 for fixed objects).
        index: (E,) int64 flat entry indices into (J, Z, P).
        values: (C, E) mean contribution per unit coefficient.
        variance: (C, E) Monte Carlo variance of each mean, or None.
    """

    object_id: int
    bounce: int
    pixels: torch.Tensor
    terms: torch.Tensor
    J: int
    index: torch.Tensor
    values: torch.Tensor
    variance: torch.Tensor | None = None

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """The dense shape (C, J, Z, P)."""
        return (self.values.shape[0], self.J, self.terms.numel(), self.pixels.numel())

    def coordinates(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(j, z, p) of every stored entry, each (E,) int64."""
        z, p = self.terms.numel(), self.pixels.numel()
        jz, pp = torch.div(self.index, p, rounding_mode="floor"), self.index % p
        return torch.div(jz, z, rounding_mode="floor"), jz % z, pp

    def dense(self, variance: bool = False) -> torch.Tensor:
        """The block as a dense (C, J, Z, P) tensor (zeros where no path contributed)."""
        src = self.variance if variance else self.values
        if src is None:
            raise ValueRangeError("this block keeps no variances")
        c, j, z, p = self.shape
        out = torch.zeros(c, j * z * p, dtype=src.dtype)
        out[:, self.index] = src
        return out.view(c, j, z, p)

    @property
    def nbytes(self) -> int:
        """Bytes of values, variances and indices."""
        n = self.values.numel() * self.values.element_size() + self.index.numel() * self.index.element_size()
        return n + (0 if self.variance is None else self.variance.numel() * self.variance.element_size())


def _check_indices(
    n_pixels: int, n_objects: int, n_bases: int, series: Series, terms: dict[int, TermTable], blocks: list
) -> None:
    """Indices of a loaded record within their ranges (a checksummed file can still come from a
    faulty writer: pixel -1 wrapped around silently, 10**9 failed later as an IndexError).

    Raises:
        FileFormatError: the first index out of range, naming the block and the array.
    """

    def bad(x: torch.Tensor, hi: int) -> bool:
        return x.numel() > 0 and (int(x.min()) < 0 or int(x.max()) >= hi)

    if n_objects < 1 or n_bases != n_objects:
        raise FileFormatError(f"{n_objects} objects and {n_bases} bases: expected as many bases as objects (>= 1)")
    for n, tt in terms.items():
        if tt.counts.ndim != 2 or tt.counts.shape != (tt.w.numel(), n_objects) or bad(tt.w + 1, 1 << 62):
            raise FileFormatError(f"terms{n}: w {tuple(tt.w.shape)} / counts {tuple(tt.counts.shape)} are inconsistent")
    for i, b in enumerate(blocks):
        z, p = b.terms.numel(), b.pixels.numel()
        checks = [
            ("object id", torch.tensor([b.object_id]), n_objects),
            ("bounce", torch.tensor([b.bounce - 1]), series.bounces),
            ("J", torch.tensor([b.J - 1]), MAX_BANDS * 2),
            ("pixels", b.pixels, n_pixels),
            ("terms", b.terms, terms[b.bounce].size if b.bounce in terms else 0),
            ("index", b.index, b.J * z * p),
        ]
        for what, x, hi in checks:
            if bad(x, hi):
                raise FileFormatError(f"block {i}: {what} outside [0, {hi}) (min {int(x.min())}, max {int(x.max())})")
        e = b.index.numel()
        for what, v in (("values", b.values), ("variance", b.variance)):
            if v is not None and (v.ndim != 2 or v.shape[1] != e):
                raise FileFormatError(f"block {i}: {what} {tuple(v.shape)} do not match its {e} indices")


@dataclass(frozen=True)
class PolynomialTensors(Record):
    """The multibounce tensors of one view (the output of :func:`precompute_polynomial`).

    Attributes:
        height, width: image size.
        series: the BRDF series.
        object_names: (M,) scene object names; ``bases[m]`` is None for fixed objects.
        bases: per-object :class:`ObjectBasis` (None: fixed).
        emission: (C, H*W) the constant term E (emitters and environment seen directly).
        terms: bounce -> :class:`TermTable`.
        blocks: the entries, per tile, eye object and bounce.
        meta: settings and statistics (spp, seed, mixture, rays cast, seconds).
        guides: optional per-pixel :class:`~torch_brdf.records.guides.GuideBuffers` of the view
            (denoisers' guides; :func:`torch_brdf.denoise.guide_buffers`), saved with the file.
    """

    height: int
    width: int
    series: Series
    object_names: list[str]
    bases: list[ObjectBasis | None]
    emission: torch.Tensor
    terms: dict[int, TermTable]
    blocks: list[TensorBlock]
    meta: dict[str, Any] = field(default_factory=dict)
    guides: GuideBuffers | None = None

    kind = TENSOR_KIND
    version = 1
    schema: ClassVar[dict[str, Member]] = {
        "emission": Member("f", 2, finite=True),
        "terms*_w": Member("i", 1),
        "terms*_counts": Member("iu", 2),
        "b*_values": Member("f", 2, finite=True),
        "b*_variance": Member("f", 2),
        "b*_index": Member("iu", 1),
        "b*_pixels": Member("iu", 1),
        "b*_terms": Member("iu", 1),
        # optional denoiser guides (records.guides.GuideBuffers.to_arrays)
        "guide_meta": Member("f", 1, finite=True, required=False),
        "guide_*": Member("fiub", None, required=False),
    }

    @property
    def num_objects(self) -> int:
        return len(self.object_names)

    def object_id(self, name: str | int) -> int:
        if isinstance(name, int):
            if not 0 <= name < self.num_objects:
                raise SceneError(f"object id {name} out of range [0, {self.num_objects})")
            return name
        try:
            return self.object_names.index(name)
        except ValueError:
            raise SceneError(f"unknown object {name!r}; objects: {self.object_names}") from None

    def second_offsets(self) -> list[int]:
        """Start of each editable object's slots in the global second-bounce coefficient vector."""
        off, out = 0, []
        for b in self.bases:
            out.append(off)
            if b is not None and self.series.two_level:
                off += b.second_size
        return out

    def memory_per_bounce(self, variance: bool = False) -> dict[int, int]:
        """Bytes of tensor entries (float32 values and int64 indices, in memory) per bounce, like
        the seed's Table II; with ``variance`` also the per-entry variances kept beside them."""
        out = {n: 0 for n in range(1, self.series.bounces + 1)}
        for b in self.blocks:
            v = b.variance
            out[b.bounce] += b.nbytes - (0 if variance or v is None else v.numel() * v.element_size())
        return out

    @property
    def num_entries(self) -> int:
        """Stored tensor entries (all blocks, channels included)."""
        return sum(b.values.numel() for b in self.blocks)

    @property
    def num_dense_entries(self) -> int:
        """Entries the blocks would hold as dense (C, J, Z, P) tensors, for comparison."""
        return sum(math.prod(b.shape) for b in self.blocks)

    def first_order(self, obj: str | int) -> BasisImage:
        """The direct-lighting term of the pixels that see ``obj``: a :class:`BasisImage`
        (C, J, P) linear in that object's coefficients (the record shared with inverse design)."""
        m = self.object_id(obj)
        blocks = [b for b in self.blocks if b.object_id == m and b.bounce == 1]
        if not blocks:
            j = 1 if self.bases[m] is None else self.bases[m].size
            empty = torch.zeros(3, j, 0)
            return BasisImage(empty, torch.zeros(0, dtype=torch.int64), self.height, self.width)
        vals = torch.cat([b.dense()[:, :, 0] for b in blocks], -1)
        pix = torch.cat([b.pixels for b in blocks])
        var = None if blocks[0].variance is None else torch.cat([b.dense(True)[:, :, 0] for b in blocks], -1)
        basis = "fixed" if self.bases[m] is None else json.dumps(self.bases[m].spec(), sort_keys=True)
        return BasisImage(vals, pix, self.height, self.width, None, var, basis, {"object": self.object_names[m]})

    # -- files ------------------------------------------------------------------------------
    def arrays_to_save(self, storage: str = "float32") -> tuple[dict[str, Any], dict[str, Any]]:
        """:meth:`to_arrays` with the conversions of the entries deferred to the write."""
        return self.to_arrays(storage, deferred=True)

    def to_arrays(self, storage: str = "float32", deferred: bool = False) -> tuple[dict[str, Any], dict[str, Any]]:
        """Arrays and metadata for :meth:`save` (``save(path, storage=...)``).

        Args:
            storage: ``"float32"`` or ``"float16"`` (half the bytes; relative rounding error
                <= 2^-11 = 4.9e-4 per entry; entries below ~6e-8 flush towards zero and
                above 65504 overflow, which is checked: use float32 then).
            deferred: converted arrays as callables that make them (what :meth:`save` passes);
                arrays already of the stored dtype are views either way.
        """
        dt = {"float32": np.float32, "float16": np.float16}.get(storage)
        if dt is None:
            raise ValueRangeError(f"storage must be 'float32' or 'float16'; got {storage!r}")
        arrays: dict[str, np.ndarray] = {"emission": self.emission.numpy().astype(np.float32)}
        for n, t in self.terms.items():
            arrays[f"terms{n}_w"] = t.w.numpy()
            arrays[f"terms{n}_counts"] = t.counts.numpy()
        index = []
        for i, b in enumerate(self.blocks):
            v = b.values.numpy()
            if dt is np.float16 and np.abs(v).max(initial=0) > 65504:
                raise ValueRangeError("tensor entries exceed the float16 range; save with storage='float32'")
            # conversions are deferred (made while saving, one array at a time), views passed as they are
            arrays[f"b{i}_values"] = _stored(v, dt, deferred)
            small = math.prod(b.shape[1:]) < 2**31
            arrays[f"b{i}_index"] = _stored(b.index.numpy(), np.int32 if small else np.int64, deferred)
            arrays[f"b{i}_pixels"] = b.pixels.numpy()
            arrays[f"b{i}_terms"] = b.terms.numpy()
            if b.variance is not None:
                arrays[f"b{i}_variance"] = _stored(b.variance.numpy(), dt, deferred)
            index.append([b.object_id, b.bounce, b.J])
        if self.guides is not None:
            arrays.update(self.guides.to_arrays())
        meta = {
            "height": self.height,
            "width": self.width,
            "series": list(self.series.bands),
            "objects": self.object_names,
            "bases": [None if b is None else b.spec() for b in self.bases],
            "blocks": index,
            "storage": storage,
            "meta": self.meta,
        }
        return arrays, meta

    @classmethod
    def from_arrays(cls, arrays, meta) -> PolynomialTensors:
        """The record of :meth:`to_arrays` output (``load(path)``)."""
        t = {k: torch.from_numpy(np.asarray(v)) for k, v in arrays.items()}
        series = Series(tuple(meta["series"]))
        terms = {
            n: TermTable(t[f"terms{n}_w"].long(), t[f"terms{n}_counts"].long())
            for n in range(1, series.bounces + 1)
            if f"terms{n}_w" in t
        }
        blocks = [
            TensorBlock(
                int(o),
                int(n),
                t[f"b{i}_pixels"].long(),
                t[f"b{i}_terms"].long(),
                int(j),
                t[f"b{i}_index"].long(),
                t[f"b{i}_values"].float(),
                t[f"b{i}_variance"].float() if f"b{i}_variance" in t else None,
            )
            for i, (o, n, j) in enumerate(meta["blocks"])
        ]
        bases = [None if b is None else ObjectBasis(**b) for b in meta["bases"]]
        if t["emission"].shape != (3, int(meta["height"]) * int(meta["width"])):
            raise FileFormatError(
                f"emission {tuple(t['emission'].shape)} does not fit {meta['height']}x{meta['width']}"
            )
        _check_indices(t["emission"].shape[1], len(meta["objects"]), len(bases), series, terms, blocks)
        return cls(
            int(meta["height"]),
            int(meta["width"]),
            series,
            list(meta["objects"]),
            bases,
            t["emission"].float(),
            terms,
            blocks,
            dict(meta.get("meta", {})),
            GuideBuffers.from_arrays(arrays),
        )


def _stored(a: np.ndarray, dtype, deferred: bool):
    """``a`` itself when it has ``dtype``, else its conversion, made now or (``deferred``) by a
    callable while the file is written (see ``save_arrays``)."""
    if a.dtype == dtype:
        return a
    return Converted(a, dtype) if deferred else a.astype(dtype)
