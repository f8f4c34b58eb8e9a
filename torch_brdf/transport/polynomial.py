r"""Monte Carlo precomputation of the multibounce polynomial tensors (Ben-Artzi et al. 2008).

With interreflections the image is a polynomial in the scene's BRDF coefficients
(Sec. 3, Eq. 14-16): bounce :math:`N` is a degree-:math:`N` polynomial. With a *BRDF series*
:math:`(J_N, \dots, J_1)` (Sec. 4.1, Eq. 17-19) the eye vertex uses the object's full band
basis, an optional low-frequency second bounce uses a coarsened basis (Sec. 4.3), and all
later vertices use the diffuse equivalent :math:`d_m` of each object (Sec. 4.2, App. B). The
pixel value is then (Eq. 26, Eq. 29)

.. math::
    B(x) = E(x) + \sum_{N=1}^{\bar N}\sum_j\sum_t T^N_{jt}(x)\, c_j\, \hat c_{w_t}\,\bar d_{z_t},

where a *term* :math:`t` is a pair (second-bounce coefficient slot :math:`w_t`, or none;
multiset :math:`z_t` of the objects of the diffuse-equivalent vertices) and
:math:`\bar d_z = \prod_{m\in z} d_m` (Eq. 25). Symmetry (Sec. 4): with diffuse equivalents
the order of the later vertices does not matter, so a term holds a *multiset*, stored as a
count per object.

Estimator (Sec. 5.1). A batched (wavefront) path tracer from the eye on embree:

* directions are sampled independently of the final BRDF, from a mixture of a cosine lobe
  (70%) and a Blinn lobe of exponent 200 about the mirror direction (30%) (:class:`Mixture`);
* next-event estimation at every vertex to every light of the scene (area lights, the
  environment, directional lights; or the environment's median-cut point lights,
  ``env_point_lights=K``, as the seed does);
* each light sample at vertex :math:`N` of a path adds its weight to exactly one entry per
  basis layer: the band :math:`j` of :math:`(\omega_i, \omega_o)` at the eye vertex (Eq. 22),
  the second-bounce slot :math:`w` for a low-frequency second bounce, and the multiset of the
  objects of vertices :math:`3..N` (or :math:`2..N`). Editable objects contribute their
  quotient :math:`\rho_q` and band indicator at banded vertices and :math:`\cos/\pi` at
  diffuse-equivalent vertices (Eq. 23-24); *fixed* objects (``SceneObject.editable`` False)
  contribute their full BRDF :math:`f\cos` and no index (Sec. 5.3);
* emission seen directly from the eye is the constant term :math:`E`; emission reached by a
  continuation ray is not counted (NEE covers it), as in :func:`.pathtrace.path_trace`, so a
  scene of Lambertian objects evaluated at their albedos estimates the same image.

Bookkeeping. Per pass group, entries are reduced to per-path sums (so the per-entry Monte
Carlo variance is the variance over paths, not over light samples); sums and sums of squares
accumulate per tile; a tile's entries become one block per (eye object, bounce) that numbers
the terms and pixels occurring in that tile and stores only the entries that occur, sparse
(:class:`TensorBlock`). A pixel whose jittered samples see two objects has a record under each.

Reproducibility. Tile ``k`` with pass group ``g`` draws from its own generator seeded by
``(seed, k, g)``; each finished tile is written atomically to the checkpoint folder, so an
interrupted run resumes at the first unfinished tile and the result equals an uninterrupted
run bit for bit (at most one tile of work is lost).
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from .._checks import MAX_BANDS, check_count, check_seed
from ..brdf import BRDF
from ..brdf.bands import BandBasis, Quotient, SchlickFresnel, make_quotient
from ..errors import FileFormatError, SceneError, ShapeError, ValueRangeError
from ..io.arrays import load_arrays, save_arrays
from ..render.record import BasisImage
from ..scene.envmap import EnvironmentMap
from ..scene.lights import Light, LightSample, luminance
from ..scene.scene import Scene
from ..sphere.warps import cosine_hemisphere_pdf, square_to_cosine_hemisphere
from .pathtrace import emission_seen, material_brdfs, rows_by_object, sample_light, seeded_generator, shading_frame

TENSOR_KIND = "multibounce-tensors"
TILE_KIND = "multibounce-tile"
_SUPPORTED_VARIABLES = ("theta_h", "theta_d")


# --------------------------------------------------------------------------------------------
# series and per-object bases
# --------------------------------------------------------------------------------------------
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
        if any(b[i] < b[i + 1] for i in range(len(b) - 1)):
            raise ValueRangeError(f"a BRDF series must not increase away from the eye (Eq. 17); got {b}")
        if any(x != 1 for x in b[2:]):
            raise ValueRangeError(f"bounces beyond the second from the eye must be diffuse equivalents (1); got {b}")

    @classmethod
    def parse(cls, spec: str | Sequence[int] | Series) -> Series:
        if isinstance(spec, Series):
            return spec
        if isinstance(spec, str):
            try:
                spec = [int(s) for s in spec.replace("(", "").replace(")", "").split(",") if s.strip()]
            except ValueError as exc:
                raise ValueRangeError(f"cannot parse BRDF series {spec!r}; expected e.g. '64,1,1,1'") from exc
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
        if self.J < 1 or not 1 <= self.second <= self.J:
            raise ValueRangeError(f"need J >= 1 and 1 <= second <= J; got J={self.J}, second={self.second}")

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


def plan_bases(
    scene: Scene, series: Series, overrides: dict[str, dict[str, Any]] | None = None
) -> list[ObjectBasis | None]:
    """Choose each object's basis from its material: model only what the scene requires.

    * fixed objects (``editable=False``): None (their full BRDF is baked into path weights);
    * Lambertian materials: one band (an editable diffuse colour; its equivalent albedo is
      its albedo);
    * Blinn-Phong / Phong of exponent ``n``: ``series.eye`` bands of theta_h with spacing
      ``lobe:n`` (bands adapted to that lobe, 1.4% projection error at J = 64, n = 100);
    * anything else: ``series.eye`` bands of theta_h with MERL's ``sqrt`` spacing.

    ``overrides`` maps object names to :class:`ObjectBasis` fields (``J``, ``spacing``,
    ``quotient``, ``fresnel``, ``variable``), e.g. to make a diffuse wall glossy-editable.
    """
    overrides = dict(overrides or {})
    unknown = sorted(set(overrides) - {o.name for o in scene.objects})
    if unknown:
        raise SceneError(f"basis overrides name unknown objects: {unknown}")
    out: list[ObjectBasis | None] = []
    for obj in scene.objects:
        if not obj.editable:
            if obj.name in overrides:
                raise SceneError(f"object {obj.name!r} is fixed (editable=False); it has no basis to override")
            out.append(None)
            continue
        mat = scene.materials[obj.material]
        kind = mat.get("type")
        if kind == "lambert":
            spec: dict[str, Any] = {"J": 1, "spacing": "uniform"}
        elif kind in ("blinn_phong", "phong"):
            spec = {"J": series.eye, "spacing": f"lobe:{float(mat.get('exponent', 20.0)):g}"}
        else:
            spec = {"J": series.eye, "spacing": "sqrt"}
        spec.update(overrides.get(obj.name, {}))
        spec["J"] = int(min(spec["J"], series.eye)) if "J" not in overrides.get(obj.name, {}) else int(spec["J"])
        spec["second"] = min(series.second, spec["J"])
        out.append(ObjectBasis(**spec))
    return out


@dataclass(frozen=True)
class Mixture:
    r"""Direction sampling independent of the final BRDF (Sec. 5.1): with probability
    ``diffuse`` a cosine lobe, otherwise a Blinn lobe :math:`\cos^n\theta_h` about the
    mirror direction (the seed: 70% diffuse, 30% Blinn exponent 200)."""

    diffuse: float = 0.7
    exponent: float = 200.0

    def __post_init__(self):
        if not 0.0 <= self.diffuse <= 1.0 or not self.exponent >= 0.0:
            raise ValueRangeError(f"mixture needs diffuse in [0, 1] and exponent >= 0; got {self}")

    def sample(self, wo: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Local ``wo`` (n, 3), uniforms ``u`` (n, 3) -> ``wi`` (n, 3), solid-angle pdf (n,)."""
        cosine = square_to_cosine_hemisphere(u[:, 1:])
        n = self.exponent
        cos_h = u[:, 1].clamp_min(1e-12) ** (1.0 / (n + 1.0))
        sin_h = (1 - cos_h * cos_h).clamp_min(0).sqrt()
        phi = 2 * math.pi * u[:, 2]
        h = torch.stack((sin_h * phi.cos(), sin_h * phi.sin(), cos_h), -1)
        glossy = 2 * (wo * h).sum(-1, keepdim=True) * h - wo
        wi = torch.where((u[:, :1] < self.diffuse), cosine, glossy)
        return wi, self.pdf(wi, wo)

    def pdf(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """Solid-angle density of :meth:`sample` (0 below the horizon)."""
        n = self.exponent
        h = wi + wo
        h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        cos_h = h[:, 2].clamp_min(0)
        cos_oh = (wo * h).sum(-1).abs().clamp_min(1e-12)
        p_h = (n + 1) / (2 * math.pi) * cos_h.clamp_min(1e-30) ** n * (cos_h > 0)
        p = self.diffuse * cosine_hemisphere_pdf(wi[:, 2]) + (1 - self.diffuse) * p_h / (4 * cos_oh)
        return torch.where(wi[:, 2] > 0, p, torch.zeros_like(p))


class PointLights(Light):
    """Distant point lights (e.g. an environment map's median-cut set), one sampled per point
    in proportion to its luminance; ``weight`` = intensity / selection probability."""

    is_delta = True
    is_infinite = True

    def __init__(self, directions: torch.Tensor, intensity: torch.Tensor):
        super().__init__()
        self.register_buffer("directions", directions.float())
        self.register_buffer("intensity", intensity.float())
        p = luminance(self.intensity).clamp_min(0)
        if not float(p.sum()) > 0:
            p = torch.ones_like(p)
        self.register_buffer("prob", p / p.sum())

    def sample(self, points, generator=None):
        n = points.shape[0]
        k = torch.multinomial(self.prob, n, replacement=True, generator=generator) if n else torch.zeros(0).long()
        w = self.intensity[k] / self.prob[k, None]
        d = self.directions[k].to(points.dtype)
        inf = torch.full((n,), math.inf, dtype=points.dtype)
        return LightSample(d, inf, w.to(points.dtype), inf)

    def power_estimate(self) -> float:
        return float(luminance(self.intensity).sum())


# --------------------------------------------------------------------------------------------
# the precomputed record
# --------------------------------------------------------------------------------------------
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


@dataclass(frozen=True)
class PolynomialTensors:
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
    def save(self, path: str | Path, storage: str = "float32") -> Path:
        """Write atomically (versioned, checksummed npz; no pickle).

        Args:
            storage: ``"float32"`` or ``"float16"`` (half the bytes; relative rounding error
                <= 2^-11 = 4.9e-4 per entry; entries below ~6e-8 flush towards zero and
                above 65504 overflow, which is checked: use float32 then).
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
            arrays[f"b{i}_values"] = v.astype(dt)
            small = math.prod(b.shape[1:]) < 2**31
            arrays[f"b{i}_index"] = b.index.numpy().astype(np.int32 if small else np.int64)
            arrays[f"b{i}_pixels"] = b.pixels.numpy()
            arrays[f"b{i}_terms"] = b.terms.numpy()
            if b.variance is not None:
                arrays[f"b{i}_variance"] = b.variance.numpy().astype(dt)
            index.append([b.object_id, b.bounce, b.J])
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
        return save_arrays(path, arrays, kind=TENSOR_KIND, meta=meta)

    @classmethod
    def load(cls, path: str | Path) -> PolynomialTensors:
        """Read a file written by :meth:`save` (kind, version and checksum verified)."""
        arrays, meta = load_arrays(path, kind=TENSOR_KIND)
        try:
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
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise FileFormatError(f"{path}: not a valid multibounce tensor file ({exc})") from exc


# --------------------------------------------------------------------------------------------
# path tracing with symbolic bookkeeping
# --------------------------------------------------------------------------------------------
class _Layers:
    """Band index and quotient weight of every (object, layer) at a banded vertex."""

    def __init__(self, bases: list[ObjectBasis | None], brdfs: list[BRDF], level: int, offsets: list[int]):
        self.level = level  # 1: eye vertex, 2: low-frequency second bounce
        self.brdfs = brdfs
        self.max_layers = max([1] + [b.layers for b in bases if b is not None])
        self.per_object: list[tuple[BandBasis, list[Quotient], int, int] | None] = []
        for b, off in zip(bases, offsets, strict=True):
            if b is None:
                self.per_object.append(None)
                continue
            basis = b.band_basis() if level == 1 else b.second_basis()
            self.per_object.append((basis, b.quotients(), basis.J, off))

    def __call__(self, oid: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor):
        """-> index (n, L) long and weight (n, L, 3): slot of each layer and its factor
        (quotient for editable objects; the full BRDF f for fixed ones, index -1 at level 2
        and 0 at level 1). Pairs below either horizon get weight 0."""
        n, L = oid.numel(), self.max_layers
        idx = torch.full((n, L), -1 if self.level == 2 else 0, dtype=torch.long)
        wgt = torch.zeros(n, L, 3, dtype=wi.dtype)
        up = ((wi[:, 2] > 0) & (wo[:, 2] > 0)).to(wi.dtype)[:, None]
        for o, m in rows_by_object(oid):
            spec = self.per_object[o]
            wim, wom = wi[m], wo[m]
            if spec is None:
                wgt[m, 0] = self.brdfs[o].eval_local(wim, wom).to(wi.dtype)
                continue
            basis, quotients, J, off = spec
            band = basis.index(basis.gamma(wim, wom))
            for layer, q in enumerate(quotients):
                qv = q(wim, wom).to(wi.dtype)
                qv = qv[:, None].expand(-1, 3) if qv.ndim == 1 else qv
                idx[m, layer] = off + layer * J + band
                wgt[m, layer] = qv * up[m]
        return idx, wgt


@dataclass
class _Entries:
    """Path contributions: one row per (path, bounce, layer combination)."""

    path: list[torch.Tensor] = field(default_factory=list)
    obj: list[torch.Tensor] = field(default_factory=list)
    bounce: list[torch.Tensor] = field(default_factory=list)
    j: list[torch.Tensor] = field(default_factory=list)
    w: list[torch.Tensor] = field(default_factory=list)
    counts: list[torch.Tensor] = field(default_factory=list)
    weight: list[torch.Tensor] = field(default_factory=list)

    def add(self, path, obj, bounce, j, w, counts, weight):
        keep = weight.abs().amax(-1) > 0
        if not bool(keep.any()):
            return
        for lst, x in zip(
            (self.path, self.obj, self.bounce, self.j, self.w, self.counts, self.weight),
            (path, obj, bounce, j, w, counts, weight),
            strict=True,
        ):
            lst.append(x[keep] if x.ndim else x.expand(keep.numel())[keep])

    def cat(self) -> dict[str, torch.Tensor]:
        names = ("path", "obj", "bounce", "j", "w", "counts", "weight")
        lists = (self.path, self.obj, self.bounce, self.j, self.w, self.counts, self.weight)
        if not self.path:
            return {}
        return {k: torch.cat(v) for k, v in zip(names, lists, strict=True)}


class _Tracer:
    """The batched symbolic path tracer (one instance per precomputation)."""

    def __init__(self, scene: Scene, bases, series: Series, mixture: Mixture, lights: list[Light]):
        self.scene, self.series, self.mixture, self.lights = scene, series, mixture, lights
        self.brdfs = material_brdfs(scene)
        self.bases = bases
        self.num_objects = len(scene.objects)
        self.editable = torch.tensor([b is not None for b in bases])
        self.level1 = _Layers(bases, self.brdfs, 1, [0] * len(bases))
        offs, off = [], 0
        for b in bases:
            offs.append(off)
            if b is not None and series.two_level:
                off += b.second_size
        self.level2 = _Layers(bases, self.brdfs, 2, offs) if series.two_level else None
        self.rays = {"closest": 0, "shadow": 0}

    def _trace(self, o, d):
        self.rays["closest"] += o.shape[0]
        return self.scene.trace(o, d)

    def _fixed_f(self, oid, wi, wo):
        """(n, 3): the full BRDF of fixed objects, 1 for editable ones."""
        out = torch.ones(oid.numel(), 3, dtype=wi.dtype)
        for o, m in rows_by_object(oid):
            if not self.editable[o]:
                out[m] = self.brdfs[o].eval_local(wi[m], wo[m]).to(wi.dtype)
        return out

    @torch.no_grad()
    def run(self, origins, directions, rec, gen, paths: dict | None = None):
        """Trace one path per ray. ``rec`` (n,) is the path's pixel record id.

        Returns the emission seen directly (n, 3) and the :class:`_Entries`. With ``paths``
        (a dict), also records for every entry the raw weight without editable factors and
        the local directions and objects needed to re-evaluate it with explicit BRDFs (the
        exactness oracle of the tests).
        """
        scene, nb = self.scene, self.series.bounces
        ent = _Entries()
        hits = self._trace(origins, directions)
        emis = emission_seen(scene, directions, hits)
        idx = torch.nonzero(hits.hit).squeeze(1)
        d_in, pos = directions[idx], hits.position[idx]
        ng, ns, oid = hits.geometric_normal[idx], hits.normal[idx], hits.object_id[idx]
        m1 = oid.clone()
        k = idx.numel()
        raw = torch.ones(k, 3)  # throughput without editable factors and without 1/pi of D
        A_i = torch.zeros(k, 1, dtype=torch.long)  # eye-vertex slots (n, L1)
        A_w = torch.ones(k, 1, 3)  # eye-vertex layer weights
        B_i = torch.full((k, 1), -1, dtype=torch.long)  # second-bounce slots (n, L2)
        B_w = torch.ones(k, 1, 3)
        counts = torch.zeros(k, self.num_objects, dtype=torch.int8)
        rec_p = None
        if paths is not None:
            rec_p = {"wi1": None, "wo1": None, "wi2": None, "wo2": None, "m2": None, "objs": []}
        for v in range(1, nb + 1):
            if idx.numel() == 0:
                break
            ng, ns, frame, wo = shading_frame(d_in, ng, ns)
            banded2 = v == 2 and self.level2 is not None
            ed = self.editable[oid]
            for light in self.lights:
                ls, cos, cast, kk = sample_light(scene, light, pos, ng, ns, gen)
                self.rays["shadow"] += cast
                if kk.numel() == 0:
                    continue
                wl = frame.to_local(ls.direction)[kk]
                lw = ls.weight[kk] * cos[kk, None]
                self._emit(
                    ent,
                    v,
                    kk,
                    wl,
                    wo[kk],
                    oid[kk],
                    ed[kk],
                    lw,
                    idx,
                    m1,
                    raw,
                    A_i,
                    A_w,
                    B_i,
                    B_w,
                    counts,
                    banded2,
                    paths,
                    rec_p,
                    rec,
                )
            if v == nb:
                break
            u = torch.rand(idx.numel(), 3, generator=gen)
            wi, pdf = self.mixture.sample(wo, u)
            ok = (pdf > 0) & (wi[:, 2] > 0) & (wo[:, 2] > 0)
            cosw = torch.where(ok, wi[:, 2] / pdf.clamp_min(1e-30), torch.zeros_like(pdf))
            if v == 1:
                A_i, A_w = self.level1(oid, wi, wo)
                raw = raw * cosw[:, None]
                if rec_p is not None:
                    rec_p["wi1"], rec_p["wo1"] = wi.clone(), wo.clone()
            elif banded2:
                B_i, B_w = self.level2(oid, wi, wo)
                raw = raw * cosw[:, None]
                if rec_p is not None:
                    rec_p["wi2"], rec_p["wo2"], rec_p["m2"] = wi.clone(), wo.clone(), oid.clone()
            else:
                f = self._fixed_f(oid, wi, wo)
                raw = raw * f * cosw[:, None]
                counts = counts.clone()
                counts[ed, oid[ed]] += 1
                if rec_p is not None:
                    rec_p["objs"].append(torch.where(ed, oid, -1))
            wworld = frame.to_world(wi)
            alive = ok & ((wworld * ng).sum(-1) > 0) & (raw.amax(-1) > 0)
            alive &= (A_w.abs().amax((-1, -2)) > 0) & (B_w.abs().amax((-1, -2)) > 0)
            a = torch.nonzero(alive).squeeze(1)
            sub = self._trace(scene.spawn(pos[a], ng[a], wworld[a]), wworld[a])
            keep = a[sub.hit]
            idx, d_in, m1, raw = idx[keep], wworld[keep], m1[keep], raw[keep]
            A_i, A_w, B_i, B_w, counts = A_i[keep], A_w[keep], B_i[keep], B_w[keep], counts[keep]
            if rec_p is not None:
                for key in ("wi1", "wo1", "wi2", "wo2", "m2"):
                    if rec_p[key] is not None:
                        rec_p[key] = rec_p[key][keep]
                rec_p["objs"] = [t[keep] for t in rec_p["objs"]]
            pos, ng, ns, oid = (x[sub.hit] for x in (sub.position, sub.geometric_normal, sub.normal, sub.object_id))
        return emis, ent

    def _emit(
        self, ent, v, kk, wl, wo, ob, ed, lw, idx, m1, raw, A_i, A_w, B_i, B_w, counts, banded2, paths, rec_p, rec
    ):
        """Add the entries of light samples at vertex ``v`` for paths ``kk``."""
        n = kk.numel()
        cnt = counts[kk]
        if v == 1:
            j, q = self.level1(ob, wl, wo)  # (n, L1), (n, L1, 3)
            w = torch.full_like(j, -1)
            wts = q * lw[:, None, :]
            combos = [(j[:, a], w[:, a], wts[:, a]) for a in range(j.shape[1])]
            extra = None
        elif banded2:
            k2, q2 = self.level2(ob, wl, wo)
            base = raw[kk] * lw
            combos = [
                (A_i[kk, a], k2[:, b], base * A_w[kk, a] * q2[:, b])
                for a in range(A_i.shape[1])
                for b in range(k2.shape[1])
            ]
            extra = None
        else:
            f = torch.where(ed[:, None], torch.full((1, 3), 1.0 / math.pi), self._fixed_f(ob, wl, wo))  # D = cos/pi
            cnt = cnt.clone()
            cnt[ed, ob[ed]] += 1
            scale = math.pi ** -(cnt.sum(-1).double() - ed.double()).float()  # 1/pi of earlier D vertices
            base = raw[kk] * lw * f * scale[:, None]
            combos = [
                (A_i[kk, a], B_i[kk, b], base * A_w[kk, a] * B_w[kk, b])
                for a in range(A_i.shape[1])
                for b in range(B_i.shape[1])
            ]
            extra = torch.where(ed, ob, -1)
        bounce = torch.full((n,), v, dtype=torch.long)
        for j, w, wt in combos:
            ent.add(rec[idx[kk]], m1[kk], bounce, j, w, cnt, wt)
        if paths is not None:
            self._record(paths, v, kk, wl, wo, ob, lw, idx, m1, raw, rec_p, rec, extra, cnt)

    def _record(self, paths, v, kk, wl, wo, ob, lw, idx, m1, raw, rec_p, rec, extra, cnt):
        """Raw path data for the exactness oracle (tests)."""
        n = kk.numel()
        fixed_f = (
            torch.where(self.editable[ob][:, None], torch.ones(1, 3), self._fixed_f(ob, wl, wo))
            if v > 1 and not (v == 2 and self.level2 is not None)
            else torch.ones(n, 3)
        )
        row = {
            "rec": rec[idx[kk]],
            "m1": m1[kk],
            "bounce": torch.full((n,), v),
            "raw": raw[kk] * lw * fixed_f,
            "wl": wl,
            "wo": wo,
            "ob": ob,
        }
        for key in ("wi1", "wo1", "wi2", "wo2", "m2"):
            row[key] = None if rec_p[key] is None else rec_p[key][kk]
        objs = [t[kk] for t in rec_p["objs"]]
        if extra is not None:
            objs.append(extra)
        row["objs"] = torch.stack(objs, -1) if objs else torch.zeros(n, 0, dtype=torch.long)
        paths.setdefault("rows", []).append(row)


# --------------------------------------------------------------------------------------------
# aggregation
# --------------------------------------------------------------------------------------------
def _radix_key(cols: list[tuple[torch.Tensor, int]]) -> torch.Tensor:
    key = torch.zeros_like(cols[0][0])
    total = 1
    for x, size in cols:
        total *= max(size, 1)
        if total >= 2**62:
            raise ValueRangeError("too many distinct tensor entries per tile for 64-bit keys; use smaller tiles")
        key = key * max(size, 1) + x
    return key


def _multiset_ids(counts: torch.Tensor) -> tuple[torch.Tensor, int]:
    """Dense ids of the distinct rows of ``counts`` (n, M) int8: one exact int64 code per row
    (base = max count + 1) when it fits in 62 bits, else ``unique(dim=0)``."""
    m = counts.shape[1]
    base = int(counts.max()) + 1 if counts.numel() else 1
    if m * math.log2(max(base, 2)) < 62:
        powers = base ** torch.arange(m, dtype=torch.long)
        code = (counts.long() * powers).sum(-1)
        uniq, zid = torch.unique(code, return_inverse=True)
        return zid, uniq.numel()
    uniq, zid = torch.unique(counts, dim=0, return_inverse=True)
    return zid, uniq.shape[0]


def _reduce(d: dict[str, torch.Tensor], sizes: dict[str, int], by_path: bool) -> dict[str, torch.Tensor]:
    """Sum rows with equal (record, object, bounce, j, w, counts[, path]) keys.

    Returns unique rows with ``sum`` (U, 3) float64 (and ``sq``: the sum of per-path squares
    when ``by_path``; otherwise ``sq`` is summed from the input's ``sq``)."""
    if not d:
        return {}
    zid, nz = _multiset_ids(d["counts"])
    cols = [
        (d["rec"], sizes["rec"]),
        (d["obj"], sizes["obj"]),
        (d["bounce"], sizes["bounce"]),
        (d["j"], sizes["j"]),
        (d["w"] + 1, sizes["w"] + 1),
        (zid, nz),
    ]
    if by_path:
        cols.append((d["path"], sizes["path"]))
    key = _radix_key(cols)
    uniq, inv = torch.unique(key, return_inverse=True)
    u = uniq.numel()
    first = torch.full((u,), key.numel(), dtype=torch.long).scatter_reduce(
        0, inv, torch.arange(key.numel()), reduce="amin"
    )
    w = d["weight"].double()
    s = torch.zeros(u, 3, dtype=torch.float64).index_add_(0, inv, w)
    out = {k: d[k][first] for k in ("rec", "obj", "bounce", "j", "w", "counts")}
    if by_path:
        out["sum"], out["sq"] = s, s * s
    else:
        out["sum"] = s
        out["sq"] = torch.zeros(u, 3, dtype=torch.float64).index_add_(0, inv, d["sq"])
    return out


def _settings_digest(settings: dict) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


def _tile_entries(tracer, scene, pixels, tile, spp, group, seed, paths=None):
    """Trace a tile and reduce its entries to (sum, sum of per-path squares) per key."""
    cam = scene.camera
    p = pixels.numel()
    sizes = {
        "rec": p,
        "obj": tracer.num_objects,
        "bounce": tracer.series.bounces + 1,
        "j": max([1] + [b.size for b in tracer.bases if b is not None]),
        "w": max(1, sum(b.second_size for b in tracer.bases if b is not None) if tracer.series.two_level else 1),
    }
    emis = torch.zeros(p, 3, dtype=torch.float64)
    reduced = []
    for gi, g0 in enumerate(range(0, spp, group)):
        ng = min(group, spp - g0)
        gen = seeded_generator(seed, tile, gi)
        off = torch.rand(ng * p, 2, generator=gen, dtype=torch.float64)
        ray = torch.arange(ng * p)
        rec = ray % p
        pix = pixels[rec]
        o, d = cam.rays_through((pix % cam.width).double() + off[:, 1], (pix // cam.width).double() + off[:, 0])
        e, ent = tracer.run(o, d, ray, gen, paths)  # entries carry the ray index as "path"
        emis.index_add_(0, rec, e.double())
        dd = ent.cat()
        if not dd:
            continue
        ray_id = dd.pop("path")
        dd["rec"], dd["path"] = ray_id % p, ray_id // p
        reduced.append(_reduce(dd, {**sizes, "path": ng}, by_path=True))
    reduced = [r for r in reduced if r]
    if not reduced:
        return emis, {}
    cat = {k: torch.cat([r[k] for r in reduced]) for k in reduced[0]}
    cat["weight"] = cat.pop("sum")
    return emis, _reduce(cat, sizes, by_path=False)


def _blocks_from_entries(
    red: dict[str, torch.Tensor], pixels: torch.Tensor, bases, spp: int, term_index: dict[int, dict]
) -> list[TensorBlock]:
    """Dense blocks per (eye object, bounce) over the terms and pixels that occur."""
    if not red:
        return []
    out = []
    mean = red["sum"] / spp
    var = ((red["sq"] / spp - mean * mean) / max(spp - 1, 1)).clamp_min(0)
    group = red["obj"] * 1000 + red["bounce"]
    for gkey in group.unique().tolist():
        m = group == gkey
        obj, bounce = divmod(int(gkey), 1000)
        rec = red["rec"][m]
        upix, prow = torch.unique(rec, return_inverse=True)
        table = term_index.setdefault(bounce, {})
        tw, tc = red["w"][m], red["counts"][m]
        zid, nz = _multiset_ids(tc)
        pid = (tw + 1) * nz + zid
        upid, pinv = torch.unique(pid, return_inverse=True)
        first = torch.full((upid.numel(),), pid.numel(), dtype=torch.long).scatter_reduce(
            0, pinv, torch.arange(pid.numel()), reduce="amin"
        )
        gids = []
        for w_, row in zip(tw[first].tolist(), tc[first].tolist(), strict=True):
            t = (w_, *row)
            if t not in table:
                table[t] = len(table)
            gids.append(table[t])
        gids = torch.tensor(gids, dtype=torch.long)
        order = torch.argsort(gids)
        rank = torch.empty_like(order)
        rank[order] = torch.arange(order.numel())
        tid = rank[pinv]
        J = 1 if bases[obj] is None else bases[obj].size
        z, p = upid.numel(), upix.numel()
        flat = (red["j"][m] * z + tid) * p + prow  # unique per entry
        flat, perm = torch.sort(flat)
        vals, vv = mean[m][perm].T.float().contiguous(), var[m][perm].T.float().contiguous()
        out.append(TensorBlock(obj, bounce, pixels[upix], gids[order], J, flat, vals, vv))
    return out


def _term_tables(term_index: dict[int, dict], num_objects: int, bounces: int) -> dict[int, TermTable]:
    out = {}
    for n in range(1, bounces + 1):
        rows = sorted(term_index.get(n, {}).items(), key=lambda kv: kv[1])
        w = torch.tensor([r[0][0] for r in rows], dtype=torch.long)
        c = torch.tensor([list(r[0][1:]) for r in rows], dtype=torch.long).reshape(-1, num_objects)
        out[n] = TermTable(w, c)
    return out


# --------------------------------------------------------------------------------------------
# the public entry point
# --------------------------------------------------------------------------------------------
def _lights(scene: Scene, env_point_lights: int | None) -> list[Light]:
    if env_point_lights is None:
        return list(scene.lights)
    if env_point_lights < 1:
        raise ValueRangeError(f"env_point_lights must be >= 1; got {env_point_lights}")
    out: list[Light] = []
    for li in scene.lights:
        if isinstance(li, EnvironmentMap):
            pl = li.point_lights(env_point_lights)
            out.append(PointLights(pl.directions, pl.intensity))
        else:
            out.append(li)
    return out


def precompute_polynomial(
    scene: Scene,
    series: str | Sequence[int] | Series = "64,1,1,1",
    spp: int = 64,
    seed: int = 0,
    bases: list[ObjectBasis | None] | dict[str, dict[str, Any]] | None = None,
    mixture: Mixture | None = None,
    env_point_lights: int | None = None,
    tile_rows: int | None = None,
    group: int | None = None,
    checkpoint: str | Path | None = None,
    progress: bool = True,
    paths: dict | None = None,
) -> PolynomialTensors:
    """Precompute the multibounce tensors of ``scene``'s view (Sec. 5.1).

    Args:
        scene: the scene; objects with ``editable=False`` are fixed.
        series: the BRDF series, e.g. ``"64,1,1,1"``; its length is the number of bounces.
        spp: paths per pixel.
        seed: the result is a deterministic function of (scene, settings, seed).
        bases: per-object :class:`ObjectBasis` list, or overrides for :func:`plan_bases`.
        mixture: direction sampling (default 70% cosine, 30% Blinn 200).
        env_point_lights: replace the environment by its K median-cut point lights for NEE.
        tile_rows: image rows per tile (default: about 16k pixels per tile).
        group: passes traced together (default: enough for >= 64k rays per batch, which
            lets embree use both cores).
        checkpoint: folder for finished tiles; an interrupted run resumes from it.
        progress: tqdm bar over tiles.
        paths: tests only: a dict that receives the raw path records (exactness oracle).
    Returns:
        :class:`PolynomialTensors`.
    """
    series = Series.parse(series)
    check_count(series.eye, "series bands per bounce", MAX_BANDS)
    spp, seed = check_count(spp, "spp"), check_seed(seed)
    tile_rows, group, env_point_lights = (
        None if v is None else check_count(v, k)
        for v, k in ((tile_rows, "tile_rows"), (group, "group"), (env_point_lights, "env_point_lights"))
    )
    if isinstance(bases, list):
        if len(bases) != len(scene.objects):
            raise ShapeError(f"expected {len(scene.objects)} bases (one per object); got {len(bases)}")
        plan = bases
    else:
        plan = plan_bases(scene, series, bases)
    mixture = mixture or Mixture()
    lights = _lights(scene, env_point_lights)
    cam = scene.camera
    h, w = cam.height, cam.width
    tile_rows = tile_rows or max(1, min(h, 16384 // w))
    tiles = [torch.arange(r0 * w, min(h, r0 + tile_rows) * w) for r0 in range(0, h, tile_rows)]
    group = group or max(1, min(spp, math.ceil(65536 / max(1, tiles[0].numel()))))
    tracer = _Tracer(scene, plan, series, mixture, lights)
    settings = {
        "scene": scene.name,
        "width": w,
        "height": h,
        "series": list(series.bands),
        "spp": spp,
        "seed": seed,
        "bases": [None if b is None else b.spec() for b in plan],
        "mixture": [mixture.diffuse, mixture.exponent],
        "env_point_lights": env_point_lights,
        "tile_rows": tile_rows,
        "group": group,
    }
    digest = _settings_digest(settings)
    ckdir = None if checkpoint is None else Path(checkpoint)
    term_index: dict[int, dict] = {}
    blocks: list[TensorBlock] = []
    emission = torch.zeros(3, h * w)
    t0 = time.perf_counter()
    bar = tqdm(range(len(tiles)), desc=f"precompute {scene.name} ({series.key})", disable=not progress)
    for ti in bar:
        pix = tiles[ti]
        tile_file = None if ckdir is None else ckdir / f"tile{ti:05d}_{digest}.npz"
        red = None
        if tile_file is not None and tile_file.exists():
            try:
                arrays, meta = load_arrays(tile_file, kind=TILE_KIND)
                if meta.get("digest") == digest:
                    red = {k[2:]: torch.from_numpy(v) for k, v in arrays.items() if k.startswith("r_")}
                    emis = torch.from_numpy(arrays["emission"])
                    for k, v in meta.get("rays", {}).items():
                        tracer.rays[k] += int(v)
            except FileFormatError:
                red = None  # a corrupt tile file is recomputed
        if red is None:
            before = dict(tracer.rays)
            emis, red = _tile_entries(tracer, scene, pix, ti, spp, group, seed, paths)
            if tile_file is not None:
                rays = {k: tracer.rays[k] - before[k] for k in before}
                arrays = {"emission": emis.numpy(), **{f"r_{k}": v.numpy() for k, v in red.items()}}
                save_arrays(
                    tile_file, arrays, kind=TILE_KIND, meta={"digest": digest, "settings": settings, "rays": rays}
                )
        emission[:, pix] = (emis / spp).float().T
        blocks.extend(_blocks_from_entries(red, pix, plan, spp, term_index))
    terms = _term_tables(term_index, len(scene.objects), series.bounces)
    meta = {**settings, "rays": dict(tracer.rays), "seconds": time.perf_counter() - t0}
    return PolynomialTensors(h, w, series, [o.name for o in scene.objects], plan, emission, terms, blocks, meta)
