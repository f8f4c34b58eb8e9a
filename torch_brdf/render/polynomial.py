r"""Interactive rendering of the multibounce polynomial (Ben-Artzi et al. 2008, Sec. 5.2).

Full evaluation (Eq. 26 / Eq. 29, one gather-multiply-scatter over the stored entries of each block):

.. math:: B(x) = E(x) + \sum_N\sum_j\sum_t T^N_{jt}(x)\,c_j\,g_t, \qquad
          g_t = \hat c_{w_t}\prod_m d_m^{\,n_m(t)}.

Object freezing (Eq. 27-28): while one object :math:`i` is edited, every other object's
coefficients are constants, so each pixel reduces to a polynomial in :math:`d_i` (and, with
a low-frequency second bounce, linear in :math:`\hat c_i`; the seed's :math:`F_{jkn}` with
:math:`k` and :math:`n` merged into one axis :math:`k'`, Sec. 5.2):

.. math:: B(x) = E(x) + \sum_{k'} g'_{k'}\sum_j c_j F_{jk'}(x) \quad\text{(pixels of } i\text{)},\qquad
          B(x) = E(x) + \sum_{k'} g'_{k'} V_{k'}(x) \quad\text{(other pixels)},

with :math:`g'_{(\varnothing, n)} = d_i^n` and :math:`g'_{(k, n)} = \hat c_{i,k} d_i^n`. ``F`` is
stored ``(C, J, K'·P)`` with the coefficient axis first and ``V`` ``(C, K', H·W)`` on every
pixel; a frame is one ``baddbmm`` (emission + g'·V) and, where F is sparse, one CSR
matrix-vector product per channel over F's non-zeros (else two batched matrix products over F).

Several objects stay frozen: each object's state is kept (least recently used dropped beyond
:attr:`PolynomialRenderer.max_frozen_bytes`). A state depends on the other objects'
coefficients only; when they change it is brought up to date exactly by adding, for the
entries whose term or eye vertex involves a changed object, their new minus old contribution.

Materials: :meth:`PolynomialRenderer.set_material` accepts any BRDF of the library (or a
scene material dict): ``c`` by :class:`~torch_brdf.render.material.MaterialProjector`
(cosine-weighted projection onto the object's bands; a Lambert BRDF on a constant quotient
exactly, a :class:`~torch_brdf.brdf.bands.Factored1D` on the same bands as is, both keeping
gradients; the Fresnel layer's :math:`F_0` split), ``d = (1/pi) sum_j c_j e_j`` (App. B, Eq. 37)
and the second-bounce ``c_hat`` by the albedo-weighted coarsening of Sec. 4.1. Everything is
RGB and differentiable in ``c``, ``c_hat`` and ``d``.
"""

from __future__ import annotations

import math
import warnings
from collections import OrderedDict
from typing import Any

import torch
from torch import nn

from .._checks import as_float_tensor, check_finite
from ..brdf import BRDF, create
from ..brdf.bands import band_albedos, coarsen_coefficients
from ..errors import SceneError, ShapeError, ValueRangeError
from ..metrics import relative_rmse as relative_rmse  # re-exported; defined in torch_brdf.metrics
from ..parallel.threads import tuned_method
from ..records.polynomial import ObjectBasis, PolynomialTensors
from .material import MaterialProjector


def _term_factors(counts: torch.Tensor, d: torch.Tensor, skip: int | None = None) -> torch.Tensor:
    r""":math:`\prod_m d_m^{n_m(t)}` (T, C) by repeated products (no ``pow``: exact, and
    gradients stay finite at :math:`d = 0`). ``skip`` leaves one object out."""
    t = counts.shape[0]
    g = torch.ones(t, d.shape[1], dtype=d.dtype)
    if t == 0:
        return g
    top = int(counts.max()) if counts.numel() else 0
    for m in range(counts.shape[1]):
        if m == skip:
            continue
        cm = counts[:, m]
        for k in range(1, top + 1):
            sel = (cm >= k)[:, None]
            if bool(sel.any()):
                g = g * torch.where(sel, d[m], torch.ones_like(d[m]))
    return g


class PolynomialRenderer(nn.Module):
    """Renders :class:`~torch_brdf.records.polynomial.PolynomialTensors` for edited BRDFs.

    Args:
        tensors: the precomputed tensors.
        materials: initial materials, object name -> BRDF or material dict (e.g. the scene's
            ``{o.name: scene.materials[o.material] for o in scene.objects}``); editable
            objects not given start as Lambert of albedo 0.5.
        dtype: dtype of the tensors and coefficients (float32 default; float64 for tests).
        max_bounces: render only bounces 1..max_bounces (default all precomputed).

    ``threads``: torch threads of :meth:`freeze` and frozen frames; None (default) uses the
    count measured fastest for their size (:func:`torch_brdf.parallel.threads.tuned`).
    """

    threads: int | None = None

    def __init__(
        self,
        tensors: PolynomialTensors,
        materials: dict[str, Any] | None = None,
        dtype: torch.dtype = torch.float32,
        max_bounces: int | None = None,
    ):
        super().__init__()
        self.tensors = tensors
        self.height, self.width = tensors.height, tensors.width
        nb = tensors.series.bounces
        self.max_bounces = nb if max_bounces is None else int(max_bounces)
        if not 1 <= self.max_bounces <= nb:
            raise ValueRangeError(f"max_bounces must lie in [1, {nb}] (precomputed); got {max_bounces}")
        self.register_buffer("emission", tensors.emission.to(dtype))
        self.blocks = [b for b in tensors.blocks if b.bounce <= self.max_bounces]
        self._coords = []
        for i, b in enumerate(self.blocks):
            self.register_buffer(f"block{i}", b.values.to(dtype), persistent=False)
            j, z, p = b.coordinates()
            self._coords.append((j, b.terms[z], b.pixels[p]))  # eye slot, term row, pixel per entry
        self.offsets = tensors.second_offsets()
        self.two_level = tensors.series.two_level
        m = tensors.num_objects
        self.c: list[torch.Tensor | None] = [None] * m
        self.c_hat: list[torch.Tensor | None] = [None] * m
        self.d: list[torch.Tensor] = [torch.zeros(3, dtype=dtype) for _ in range(m)]
        self.weight_maps: dict[int, torch.Tensor] = {}
        self._map_means: dict[int, torch.Tensor] = {}
        self._albedo_weights: dict[int, list[torch.Tensor]] = {}
        self._projectors: dict[int, MaterialProjector] = {}
        # frozen states by object id, least recently used first (see :meth:`freeze`)
        self._states: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._active: int | None = None  # whose state frames read
        self._versions = [0] * m  # bumped whenever an object's coefficients or weight map change
        self._last_edited: int | None = None
        self.frame_denoiser = None
        materials = dict(materials or {})
        for k, b in enumerate(tensors.bases):
            if b is None:
                continue
            name = tensors.object_names[k]
            self.set_material(name, materials.get(name, {"type": "lambert", "albedo": 0.5}))
        unknown = sorted(set(materials) - set(tensors.object_names))
        if unknown:
            raise SceneError(f"materials for unknown objects: {unknown}")

    # -- module state -----------------------------------------------------------------------
    @property
    def dtype(self) -> torch.dtype:
        """The dtype of the tensors and coefficients (follows ``.to(dtype)``)."""
        return self.emission.dtype

    def _apply(self, fn, recurse=True):
        """``.to(dtype/device)``, ``.double()``, ...: the buffers, and also the coefficients, weight
        maps, entry coordinates and frozen tensors held outside them (autograd graphs are kept)."""
        super()._apply(fn, recurse)

        def conv(t):
            return None if t is None else fn(t)

        self.c = [conv(t) for t in self.c]
        self.c_hat = [conv(t) for t in self.c_hat]
        self.d = [fn(t) for t in self.d]
        self.weight_maps = {k: fn(v) for k, v in self.weight_maps.items()}
        self._map_means = {k: fn(v) for k, v in self._map_means.items()}
        self._coords = [tuple(fn(x) for x in c) for c in self._coords]

        def deep(v):
            if isinstance(v, torch.Tensor):
                return fn(v)
            if isinstance(v, dict):
                return {k: deep(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return type(v)(deep(x) for x in v)
            return v

        for m, st in self._states.items():
            # derived caches (non-zeros, CSR) are rebuilt from the converted F
            st = {k: deep(v) for k, v in st.items() if k not in ("nonzeros", "csr")}
            if "pattern" in st:
                st["pattern"] = (st["F"], *st["pattern"][1:])
            self._states[m] = st
        return self

    # -- materials --------------------------------------------------------------------------
    def _basis(self, obj) -> tuple[int, ObjectBasis]:
        m = self.tensors.object_id(obj)
        b = self.tensors.bases[m]
        if b is None:
            raise SceneError(
                f"object {self.tensors.object_names[m]!r} is fixed: its BRDF was baked in at precomputation"
            )
        return m, b

    def albedo_weights(self, obj) -> list[torch.Tensor]:
        """Per layer, the band albedos :math:`e_j` (J, C) float64 of the object's basis (App. B)."""
        m, b = self._basis(obj)
        if m not in self._albedo_weights:
            basis = b.band_basis()
            out = []
            for q in b.quotients():
                e = band_albedos(basis, q, progress=False)
                out.append((e[:, None].expand(-1, 3) if e.ndim == 1 else e).to(torch.float64))
            self._albedo_weights[m] = out
        return self._albedo_weights[m]

    def set_material(self, obj, brdf: BRDF | dict, f0=None) -> None:
        """Give an editable object a new BRDF (any model of the library or a material dict).

        Args:
            obj: object name or id.
            brdf: a :class:`~torch_brdf.brdf.BRDF` or ``{"type": ..., **params}``. A
                :class:`Factored1D` on exactly this object's bands and quotient keeps its coefficients
                (and their gradients); anything else is projected (float64, no gradient).
            f0: for objects precomputed with ``fresnel=True`` (App. A, Eq. 31-32): the
                normal-incidence reflectance :math:`F_0` (scalar or RGB in [0, 1]) of the Schlick
                factor :math:`F_0 + (1 - F_0)(1 - \\cos\\theta_d)^5` that multiplies the BRDF's
                projected curve; None (default) is 1, the BRDF as given.

        The coefficients keep the autograd graph of the BRDF's parameters (Lambert albedo,
        Factored1D curve); in an optimisation loop call ``set_material`` every step, as a
        graph is used by one ``backward``.
        """
        m, b = self._basis(obj)
        from_dict = isinstance(brdf, dict)
        if from_dict:
            brdf = create(brdf)
        if not isinstance(brdf, BRDF):
            raise ShapeError(f"set_material expects a BRDF module or a material dict; got {type(brdf).__name__}")
        if m not in self._projectors:
            self._projectors[m] = MaterialProjector(b)
        c, _ = self._projectors[m](brdf, f0, self.tensors.object_names[m])
        self.set_coefficients(m, c.detach() if from_dict else c)

    def set_coefficients(self, obj, c, d=None, c_hat=None) -> None:
        """Set an object's band coefficients directly (e.g. an edited 1-D curve).

        Args:
            c: (J·layers, C) eye-vertex coefficients (or (J·layers,) grey).
            d: (C,) diffuse equivalent; default :math:`\\frac1\\pi\\sum_j c_j e_j` (Eq. 37).
            c_hat: (second·layers, C) second-bounce coefficients; default the albedo-weighted
                coarsening of ``c`` (Sec. 4.1).
        Gradients flow from the image to every tensor given (and to what produced them).
        """
        m, b = self._basis(obj)
        c = as_float_tensor(c, "c")
        if c.ndim == 1:
            c = c[:, None].expand(-1, 3)
        if c.shape != (b.size, 3):
            raise ShapeError(
                f"Expected c of shape ({b.size}, 3) for object {self.tensors.object_names[m]!r}; got {tuple(c.shape)}"
            )
        check_finite(c, "c")
        c = c.to(self.dtype)
        es = self.albedo_weights(m)
        if d is None:
            d = sum((c[k * b.J : (k + 1) * b.J] * e.to(c)).sum(0) for k, e in enumerate(es)) / math.pi
        d = as_float_tensor(d, "d").to(self.dtype).reshape(-1).expand(3)
        check_finite(d, "d")
        if self.two_level:
            if c_hat is None:
                g = b.band_basis().groups(b.second)
                parts = [coarsen_coefficients(c[k * b.J : (k + 1) * b.J], e, g, b.second) for k, e in enumerate(es)]
                c_hat = torch.cat(parts, 0)
            c_hat = as_float_tensor(c_hat, "c_hat").to(self.dtype)
            if c_hat.shape != (b.second_size, 3):
                raise ShapeError(f"Expected c_hat of shape ({b.second_size}, 3); got {tuple(c_hat.shape)}")
        self.c[m], self.c_hat[m], self.d[m] = c, c_hat, d
        self._changed(m)

    def set_weight_map(self, obj, weights, mean=None) -> None:
        """Modulate the directly seen pixels of ``obj`` by a texture / weight map (H, W) or
        (H, W, C); later bounces see the object's diffuse equivalent times ``mean`` (3 values;
        default: the map's mean over the object's pixels) (Sec. 5.3)."""
        m = self.tensors.object_id(obj)
        w = as_float_tensor(weights, "weights").to(self.dtype)
        if w.ndim == 2:
            w = w[..., None].expand(-1, -1, 3)
        if w.shape != (self.height, self.width, 3):
            raise ShapeError(f"Expected a weight map of shape ({self.height}, {self.width}[, 3]); got {tuple(w.shape)}")
        check_finite(w, "weights")
        self.weight_maps[m] = w = w.reshape(-1, 3)
        pix = torch.cat([b.pixels for b in self.blocks if b.object_id == m] or [torch.zeros(0, dtype=torch.long)])
        self._map_means[m] = w[pix.unique()].mean(0) if pix.numel() else w.mean(0)
        if mean is not None:
            mean = as_float_tensor(mean, "mean").to(self.dtype).reshape(-1).expand(3)
            check_finite(mean, "mean")
            self._map_means[m] = mean.clone()
        self._changed(m)

    def _changed(self, m: int) -> None:
        """Object ``m``'s coefficients or weight map changed: every other object's frozen state
        is now stale in ``m`` (refreshed exactly when next used, :meth:`_refresh`), except a
        denoised one, whose bases cannot take an exact update: it is dropped."""
        self._versions[m] += 1
        self._last_edited = m
        for k in [k for k, st in self._states.items() if k != m and st.get("denoiser") is not None]:
            self._drop(k)

    def _map_mean(self, m: int) -> torch.Tensor:
        """The weight map's mean over the object's seen pixels (set once by :meth:`set_weight_map`)."""
        mean = self._map_means.get(m)
        return torch.ones(3, dtype=self.dtype) if mean is None else mean

    # -- coefficient vectors -------------------------------------------------------------------
    def _d_all(self) -> torch.Tensor:
        return torch.stack([self.d[m] * self._map_mean(m) for m in range(self.tensors.num_objects)])

    def _c_hat_ext(self) -> torch.Tensor:
        parts = [self.c_hat[m] for m, b in enumerate(self.tensors.bases) if b is not None and self.two_level]
        return torch.cat(parts + [torch.ones(1, 3, dtype=self.dtype)], 0)

    def _eye(self, m: int) -> torch.Tensor:
        return torch.ones(1, 3, dtype=self.dtype) if self.c[m] is None else self.c[m]

    def _pixel_weights(self, m: int, pixels: torch.Tensor) -> torch.Tensor | None:
        w = self.weight_maps.get(m)
        return None if w is None else w[pixels].T  # (C, P)

    # -- full evaluation ------------------------------------------------------------------------
    def evaluate(self, per_bounce: bool = False) -> torch.Tensor | list[torch.Tensor]:
        """Full evaluation of Eq. 26/29: (H, W, C); with ``per_bounce`` the list
        ``[E, B^1, ..., B^N]`` of (H, W, C) images (their sum is the image)."""
        d = self._d_all()
        ch = self._c_hat_ext()
        g = {}
        for n, table in self.tensors.terms.items():
            w = torch.where(table.w >= 0, table.w, ch.shape[0] - 1)
            g[n] = ch[w] * _term_factors(table.counts, d)
        hw = self.height * self.width
        out = [torch.zeros(3, hw, dtype=self.dtype) for _ in range(self.max_bounces + 1)]
        out[0] = out[0] + self.emission
        for i, b in enumerate(self.blocks):
            vals = getattr(self, f"block{i}")  # (C, E)
            j, t, pix = self._coords[i]
            contrib = vals * self._eye(b.object_id)[j].T * g[b.bounce][t].T
            pw = self._pixel_weights(b.object_id, pix)
            if pw is not None:
                contrib = contrib * pw
            out[b.bounce] = out[b.bounce].index_add(1, pix, contrib)
        imgs = [o.T.reshape(self.height, self.width, 3) for o in out]
        return imgs if per_bounce else sum(imgs[1:], imgs[0])

    # -- object freezing ------------------------------------------------------------------------
    #: bytes the frozen states of all objects may hold together (:attr:`frozen_cache_nbytes`);
    #: beyond it the least recently used states are dropped (the active one always stays)
    max_frozen_bytes: int = 1 << 30

    def freeze(self, obj, denoiser=None, cached: bool = True) -> None:
        """Make ``obj`` the frozen object: precompute :math:`F_{jk'}` (Eq. 27, §5.2) for its
        pixels and the polynomials :math:`V_{k'}` of all pixels, so that :meth:`forward` while
        ``obj``'s material changes costs one pass over them.

        Several objects stay frozen: each object's state is kept (least recently used dropped
        beyond :attr:`max_frozen_bytes`), and freezing an object again reuses its state. A state
        depends on every *other* object's coefficients and weight map; when one of those changed
        since, the state is brought up to date exactly by adding the change of the entries whose
        term or eye vertex involves the changed objects (:meth:`_refresh`), not rebuilt.

        Args:
            obj: the object whose material will change (name or index).
            denoiser: also denoise every basis image of the frozen tensor once
                (:func:`torch_brdf.denoise.denoise_frozen`): ``"linear"``, ``"regression"``, ``"oidn"``
                or ``"cumulative"`` with the guides the tensors carry (:func:`torch_brdf.denoise.make_denoiser`), or any
                denoiser callable. Every later frame of ``obj``'s edits is exact in the denoised
                bases and costs what a noisy frame costs; :attr:`frozen_denoiser` names it.
                A denoised state cannot take an exact update: changing another object's
                material drops it (freeze again).
            cached: reuse ``obj``'s kept state (False: contract it again from the tensors).
        Raises:
            ValueRangeError: a denoiser name while the tensors carry no guides.
        """
        i, _ = self._basis(obj)
        st = self._states.get(i) if cached and denoiser is None else None
        if st is not None and st.get("denoiser") is None:
            self._activate(i)
            return
        self._store(self._freeze(i))
        if denoiser is None:
            return
        from ..denoise import denoise_frozen, glossy_objects, make_denoiser

        if isinstance(denoiser, str):
            if self.tensors.guides is None:
                raise ValueRangeError(
                    "the tensors carry no guides (precomputed with guides=False); pass a denoiser callable"
                )
            denoiser = make_denoiser(self.tensors.guides, denoiser, glossy_objects(self.tensors))
        fz = denoise_frozen(self._frozen, denoiser, (self.height, self.width))
        fz["denoiser"] = getattr(denoiser, "description", type(denoiser).__name__)
        fz.pop("nonzeros", None)
        fz.pop("csr", None)
        self._store(fz)

    @property
    def _frozen(self) -> dict[str, Any] | None:
        """The active frozen state (the one frames read), or None."""
        return None if self._active is None else self._states.get(self._active)

    @property
    def frozen_denoiser(self) -> str | None:
        """What denoised the frozen tensor (:meth:`freeze`'s ``denoiser``), or None."""
        return None if self._frozen is None else self._frozen.get("denoiser")

    @property
    def frozen_object(self) -> str | None:
        """The object whose frozen state frames read (None: frames are full evaluations)."""
        return None if self._frozen is None else self.tensors.object_names[self._frozen["object"]]

    @property
    def frozen_objects(self) -> list[str]:
        """Objects with a kept frozen state, least recently used first."""
        return [self.tensors.object_names[m] for m in self._states]

    def is_fresh(self, obj) -> bool:
        """True when ``obj`` has a kept frozen state and nothing it depends on (the other
        objects' coefficients and weight maps) changed since it was made or refreshed.

        Args:
            obj: object name or id.
        """
        m = self.tensors.object_id(obj)
        st = self._states.get(m)
        return st is not None and not self._stale(st)

    def drop_frozen(self, obj=None) -> None:
        """Forget a kept frozen state.

        Args:
            obj: object name or id; None: every object's.
        """
        for m in list(self._states) if obj is None else [self.tensors.object_id(obj)]:
            self._drop(m)

    def _drop(self, m: int) -> None:
        self._states.pop(m, None)
        if self._active == m:
            self._active = None

    def _store(self, st: dict[str, Any]) -> None:
        self._states[st["object"]] = st
        self._activate(st["object"])

    def _activate(self, m: int) -> None:
        """Frames read ``m``'s state from now on: brought up to date, marked most recently used,
        and the least recently used other states dropped beyond :attr:`max_frozen_bytes`."""
        self._active = m
        self._states.move_to_end(m)
        self._refresh(self._states[m])
        while self.frozen_cache_nbytes > self.max_frozen_bytes and len(self._states) > 1:
            self._drop(next(iter(self._states)))

    @staticmethod
    def _state_nbytes(st: dict[str, Any]) -> int:
        seen, total = set(), 0

        def add(t):
            nonlocal total
            if isinstance(t, torch.Tensor) and t.layout == torch.strided and id(t) not in seen:
                seen.add(id(t))
                total += t.numel() * t.element_size()
            elif isinstance(t, (list, tuple)):
                for x in t:
                    add(x)

        for k in ("F", "V", "pix_i", "pix_r", "nonzeros", "csr"):
            add(st.get(k))
        return total

    @property
    def frozen_cache_nbytes(self) -> int:
        """Bytes held by all kept frozen states (dense F, V, pixel lists, the frame's non-zeros)."""
        return sum(self._state_nbytes(st) for st in self._states.values())

    def _snapshot(self) -> dict[str, Any]:
        """What a frozen state depends on, as it is now (constants: no gradient)."""
        return {
            "versions": list(self._versions),
            "d": self._d_all().detach().clone(),
            "ch": self._c_hat_ext().detach().clone(),
            "eyes": [None if c is None else c.detach().clone() for c in self.c],
            "weights": {k: v.detach() for k, v in self.weight_maps.items()},
        }

    def _stale(self, st: dict[str, Any]) -> list[int]:
        """Objects other than the state's own whose coefficients changed since it was made."""
        old, i = st["snap"]["versions"], st["object"]
        return [m for m, v in enumerate(self._versions) if m != i and v != old[m]]

    def _term_weights(self, i: int, d: torch.Tensor, ch: torch.Tensor):
        r"""Per bounce, the index :math:`k'` of each term (T,) and its factor over every object but
        ``i`` (C, T): :math:`\prod_{m\ne i} d_m^{n_m(t)}`, times :math:`\hat c_{w_t}` unless the
        second vertex is ``i``'s own (then :math:`\hat c_{i}` is read at frame time)."""
        nb = self.max_bounces
        b = self.tensors.bases[i]
        slots = b.second_size if self.two_level else 0
        off = self.offsets[i]
        kidx, phis = {}, {}
        for n, table in self.tensors.terms.items():
            w = table.w
            own = (w >= off) & (w < off + slots)
            kidx[n] = torch.where(own, w - off + 1, 0) * nb + table.counts[:, i]
            phi = _term_factors(table.counts, d, skip=i)
            wc = torch.where(w >= 0, w, ch.shape[0] - 1)
            phis[n] = (phi * torch.where(own[:, None], torch.ones_like(ch[wc]), ch[wc])).T  # (C, T)
        return kidx, phis

    def _involves(self, objects: list[int]) -> dict[int, torch.Tensor]:
        """Per bounce, (T,) bool: terms with one of ``objects`` at a later vertex (a power of its
        d or its second-bounce slot)."""
        out = {}
        for n, table in self.tensors.terms.items():
            hit = (table.counts[:, objects] > 0).any(1)
            for m in objects:
                b = self.tensors.bases[m]
                if self.two_level and b is not None:
                    off = self.offsets[m]
                    hit |= (table.w >= off) & (table.w < off + b.second_size)
            out[n] = hit
        return out

    @tuned_method("polynomial.freeze", lambda r, *a, **k: sum(b.values.numel() for b in r.blocks))
    def _freeze(self, i: int) -> dict[str, Any]:
        """A new frozen state of object ``i`` (Eq. 27): ``F`` (C, J, K'·P_i) on its pixels ``pix_i``
        and ``V`` (C, K', H·W) on every pixel (``pix_r``), with the snapshot it depends on."""
        b = self.tensors.bases[i]
        nb = self.max_bounces
        slots = b.second_size if self.two_level else 0
        K = (slots + 1) * nb
        snap = self._snapshot()
        kidx, phis = self._term_weights(i, snap["d"], snap["ch"])
        mine = [q for q, bl in enumerate(self.blocks) if bl.object_id == i]
        empty = [torch.zeros(0, dtype=torch.long)]
        pix_i = torch.cat([self._coords[q][2] for q in mine] or empty).unique()
        hw = self.height * self.width
        F = torch.zeros(3, b.size * K * pix_i.numel(), dtype=self.dtype)
        V = torch.zeros(3, K * hw, dtype=self.dtype)
        st = {"object": i, "K": K, "slots": slots, "pix_i": pix_i, "pix_r": torch.arange(hw), "snap": snap}
        self._scatter(st, F, V, kidx, phis, snap)
        st["F"], st["V"] = F.reshape(3, b.size, K * pix_i.numel()), V.reshape(3, K, hw)
        # where F can be non-zero whatever the other objects' coefficients: every (j, k', pixel)
        # some entry reaches (by pixel), so an update keeps the frame's non-zeros in place
        p_i, kp = pix_i.numel(), K * pix_i.numel()
        flat = [(j * K + kidx[bl.bounce][t]) * p_i + torch.searchsorted(pix_i, pix)
                for (j, t, pix), bl in zip(self._coords, self.blocks, strict=True) if bl.object_id == i]  # fmt: skip
        flat = torch.cat(flat or empty).unique()
        order = torch.argsort(flat % p_i, stable=True)
        st["pattern"] = (st["F"], flat[order] // kp, flat[order] % kp)
        self._frozen_nonzeros(st)
        return st

    def _seen_factor(self, snap, o: int, j: torch.Tensor, pix: torch.Tensor) -> torch.Tensor | None:
        """(C, E) eye coefficient times pixel weight of entries seen on object ``o`` (of ``snap``),
        None for a fixed object without weights (a factor of one)."""
        eye, w = snap["eyes"][o], snap["weights"].get(o)
        f = None if eye is None else eye[j].T
        if w is not None:
            f = w[pix].T if f is None else f * w[pix].T
        return f

    def _add(self, st, F, V, kidx, bl, j, t, pix, contrib) -> None:
        """Add ``contrib`` (C, E) of block ``bl``'s entries to the flat F (C, J·K'·P_i) or V
        (C, K'·H·W) of state ``st`` (Eq. 27: F[j, k'(t), p] at the frozen object's pixels)."""
        K, pix_i, n = st["K"], st["pix_i"], bl.bounce
        if bl.object_id == st["object"]:
            F.index_add_(1, (j * K + kidx[n][t]) * pix_i.numel() + torch.searchsorted(pix_i, pix), contrib)
        else:
            V.index_add_(1, kidx[n][t] * (self.height * self.width) + pix, contrib)

    def _scatter(self, st, F, V, kidx, phis, snap) -> None:
        """Every entry's contribution ``T · phis[n][:, t]`` (times the eye coefficient and pixel
        weight of ``snap`` away from the frozen object) into F and V of state ``st``."""
        for q, bl in enumerate(self.blocks):
            j, t, pix = self._coords[q]
            contrib = getattr(self, f"block{q}") * phis[bl.bounce][:, t]
            f = None if bl.object_id == st["object"] else self._seen_factor(snap, bl.object_id, j, pix)
            self._add(st, F, V, kidx, bl, j, t, pix, contrib if f is None else contrib * f)

    def _refresh(self, st: dict[str, Any]) -> None:
        r"""Bring a kept state up to date after other objects changed, exactly: F and V are sums
        over entries of ``T · (their factors)``, so only entries whose term involves a changed
        object (a power of its d, its second-bounce slot) or whose eye vertex is on a changed
        object (its coefficients, weight map) change; their new minus old contribution is added.
        Blocks none of whose terms involve a changed object (all first-bounce blocks, most
        blocks of the others) are skipped whole: the cost is that of the moved entries."""
        changed = self._stale(st)
        if not changed:
            return
        if st.get("denoiser") is not None:  # kept only while nothing else changes (_changed)
            raise ValueRangeError("a denoised frozen state cannot be updated; freeze again")
        i = st["object"]
        with torch.no_grad():
            old, new = st["snap"], self._snapshot()
            kidx, phi_old = self._term_weights(i, old["d"], old["ch"])
            _, phi_new = self._term_weights(i, new["d"], new["ch"])
            inv = self._involves(changed)
            F, V = st["F"].reshape(3, -1), st["V"].reshape(3, -1)
            delta = {n: phi_new[n] - phi_old[n] for n in phi_new}
            for q, bl in enumerate(self.blocks):
                n, o = bl.bounce, bl.object_id
                if o in changed:  # seen on a changed object: its eye coefficients or weights moved too
                    j, t, pix = self._coords[q]
                    vals = getattr(self, f"block{q}")
                    f_new, f_old = self._seen_factor(new, o, j, pix), self._seen_factor(old, o, j, pix)
                    g_new, g_old = phi_new[n][:, t], phi_old[n][:, t]
                    contrib = vals * (
                        (g_new if f_new is None else g_new * f_new) - (g_old if f_old is None else g_old * f_old)
                    )
                    self._add(st, F, V, kidx, bl, j, t, pix, contrib)
                    continue
                moved = inv[n][bl.terms]
                if not bool(moved.any()):
                    continue
                j, t, pix = self._coords[q]
                contrib = getattr(self, f"block{q}")
                if float(moved.float().mean()) < 0.5:  # few moved: select them
                    keep = inv[n][t].nonzero().squeeze(1)
                    j, t, pix, contrib = j[keep], t[keep], pix[keep], contrib[:, keep]
                # (else every entry: the others' delta is exactly zero, the same products of the same factors)
                contrib = contrib * delta[n][:, t]
                f = None if o == i else self._seen_factor(new, o, j, pix)
                self._add(st, F, V, kidx, bl, j, t, pix, contrib if f is None else contrib * f)
        st["snap"] = new
        cached, structural = st.get("nonzeros"), st.get("pattern")
        if cached is not None and cached[0] is st["F"] and cached[1] is not None and structural is not None:
            vals = cached[1][2]  # same positions (the freeze's pattern), new values, in place
            vals.copy_(st["F"][:, structural[1], structural[2]].T)
            mats = st.get("csr")
            if mats is not None and mats[0] is cached[1]:
                for k, m in enumerate(mats[1]):
                    m.values().copy_(vals[:, k])
        elif cached is not None and cached[1] is not None:
            st.pop("nonzeros")
            st.pop("csr", None)
        st["refreshes"] = st.get("refreshes", 0) + 1

    #: the frame reads F's non-zeros instead of F when at most this fraction is non-zero
    SPARSE_FRAME_DENSITY = 0.25

    @staticmethod
    def _frozen_nonzeros(fz: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """The non-zeros of the frozen ``F`` (C, J, K'·P_i) as ``(jk, p, values)``: (nnz,)
        index ``j·K' + k'``, (nnz,) pixel slot, (nnz, C) values (sorted by pixel), or None when
        more than :attr:`SPARSE_FRAME_DENSITY` of F is non-zero.

        A pixel's entries reach only the few bands its eye and light directions fall in (~2 %
        of F for a 64-band wall), so the frame's cost is then that of the non-zeros, not of F.
        Cached in ``fz`` with the F it came from: a dict whose F was replaced (e.g. by
        :func:`~torch_brdf.denoise.denoise_frozen`) is read densely again."""
        cached = fz.get("nonzeros")
        if cached is not None and cached[0] is fz["F"]:
            return cached[1]
        F, K, p_i = fz["F"], int(fz["K"]), fz["pix_i"].numel()
        structural = fz.get("pattern")
        if structural is not None and structural[0] is F:  # kept from the freeze
            j, col = structural[1], structural[2]
        else:  # e.g. a denoised F: its values' pattern
            with torch.no_grad():
                pattern = (F != 0).any(0)  # (J, K'·P_i)
            j, col = pattern.nonzero(as_tuple=True)
            order = torch.argsort(col % p_i, stable=True)
            j, col = j[order], col[order]
        out = None
        if F[0].numel() and j.numel() <= PolynomialRenderer.SPARSE_FRAME_DENSITY * F[0].numel():
            out = (j * K + col // p_i, col % p_i, F[:, j, col].T.contiguous())
        fz["nonzeros"] = (F, out)
        return out

    def _frozen_csr(self, fz: dict[str, Any]) -> list[torch.Tensor] | None:
        """The non-zeros as one CSR matrix per channel, (H·W, J·K'), rows the image's pixels
        (int32 indices): the frozen object's part of a frame is then one sparse matrix-vector
        product per channel, a single pass over values and column indices (the gather-multiply-
        scatter over the same non-zeros makes three, with (nnz, C) temporaries). None when F is
        read densely or the frozen object has a weight map."""
        nonzeros = self._frozen_nonzeros(fz)
        if nonzeros is None or fz["object"] in self.weight_maps:
            return None
        cached = fz.get("csr")
        if cached is not None and cached[0] is nonzeros:
            return cached[1]
        jk, slot, vals = nonzeros
        hw = self.height * self.width
        rows = torch.bincount(fz["pix_i"][slot], minlength=hw)
        crow = torch.cat([rows.new_zeros(1), rows.cumsum(0)]).to(torch.int32)
        col = jk.to(torch.int32)
        size = (hw, int(fz["F"].shape[1]) * int(fz["K"]))
        with warnings.catch_warnings():  # "sparse CSR support is in beta": used for mv only
            warnings.simplefilter("ignore", UserWarning)
            mats = [torch.sparse_csr_tensor(crow, col, vals[:, k].contiguous(), size=size) for k in range(3)]
        fz["csr"] = (nonzeros, mats)
        return mats

    def _frame_state(self) -> dict[str, Any] | None:
        """The state a frame reads: the last edited object's when it is kept (it becomes the
        active one), else the active one; brought up to date first."""
        last = self._last_edited
        if last is not None and last != self._active and last in self._states:
            self._activate(last)
        elif self._active is not None:
            self._activate(self._active)
        return self._frozen

    @tuned_method("polynomial.frame", lambda r: r.frozen_nbytes)
    def _frozen_frame(self) -> torch.Tensor:
        fz = self._frozen
        i, nb, K = fz["object"], self.max_bounces, fz["K"]
        di = self.d[i] * self._map_mean(i)
        powers = [torch.ones(3, dtype=self.dtype)]
        for _ in range(1, nb):
            powers.append(powers[-1] * di)
        pw = torch.stack(powers)  # (nb, C)
        slot = [torch.ones(1, 3, dtype=self.dtype)]
        if fz["slots"]:
            slot.append(self.c_hat[i])
        sv = torch.cat(slot, 0)  # (slots + 1, C)
        g = (sv[:, None, :] * pw[None, :, :]).reshape(K, 3).T  # (C, K)
        hw, p_i = self.height * self.width, fz["pix_i"].numel()
        if fz["pix_r"].numel() == hw:  # V on every pixel: emission + g·V in one pass
            img = torch.baddbmm(self.emission.unsqueeze(1), g.unsqueeze(1), fz["V"]).squeeze(1)
        else:  # (a denoised state may keep V on fewer pixels)
            img = self.emission.index_add(1, fz["pix_r"], torch.bmm(g.unsqueeze(1), fz["V"]).squeeze(1))
        csr = self._frozen_csr(fz)
        if csr is not None:  # own[p] = sum c[j] g[k'] F[j, k', p] over the non-zeros
            cg = (self.c[i].unsqueeze(1) * g.T.unsqueeze(0)).reshape(-1, 3).T.contiguous()  # (C, J·K')
            if torch.is_grad_enabled() and (cg.requires_grad or img.requires_grad):
                img = img + torch.stack([torch.mv(csr[k], cg[k]) for k in range(3)])
            else:  # in place: the image is written once
                for k in range(3):
                    torch.addmv(img[k], csr[k], cg[k], out=img[k])
            return img.T.reshape(self.height, self.width, 3)
        nonzeros = self._frozen_nonzeros(fz)
        if nonzeros is None:
            u = torch.bmm(self.c[i].T.unsqueeze(1), fz["F"]).reshape(3, K, p_i)
            own = torch.bmm(g.unsqueeze(1), u).squeeze(1)  # (C, P_i)
        else:  # the same sum over the non-zeros: own[p] = sum c[j] g[k'] F[j, k', p]
            jk, pix, vals = nonzeros
            cg = (self.c[i].unsqueeze(1) * g.T.unsqueeze(0)).reshape(-1, 3)  # (J·K', C)
            own = torch.zeros(p_i, 3, dtype=vals.dtype).index_add(0, pix, cg.index_select(0, jk) * vals).T
        w = self._pixel_weights(i, fz["pix_i"])
        if w is not None:
            own = own * w
        return img.index_add(1, fz["pix_i"], own).T.reshape(self.height, self.width, 3)

    def denoise_frames(self, denoiser="oidn", **options) -> None:
        """Denoise every frame :meth:`forward` returns, after any edits of any objects, keeping
        each object region's mean (:class:`torch_brdf.denoise.FrameDenoiser`).

        Args:
            denoiser: ``"oidn"``, ``"regression"``, ``"linear"`` (built on the guides the tensors
                carry), a :class:`~torch_brdf.denoise.FrameDenoiser`, or None to stop denoising.
            **options: passed to :class:`~torch_brdf.denoise.FrameDenoiser` with a method name
                (``keep_mean``, ``mean_tolerance``, ``quality``).
        Raises:
            ValueRangeError: a method name while the tensors carry no guides.
        """
        if isinstance(denoiser, str):
            from ..denoise import FrameDenoiser, glossy_objects

            if self.tensors.guides is None:
                raise ValueRangeError("the tensors carry no guides (precomputed with guides=False); pass a denoiser")
            denoiser = FrameDenoiser(self.tensors.guides, denoiser, glossy_objects(self.tensors), **options)
        self.frame_denoiser = denoiser

    def forward(self) -> torch.Tensor:
        """The current image (H, W, C): the frozen fast path when a frozen state is kept for the
        object edited last (or the one frozen last), brought up to date if other objects changed
        (Eq. 28); else the full evaluation; denoised by :attr:`frame_denoiser` when
        :meth:`denoise_frames` set one."""
        img = self._frozen_frame() if self._frame_state() is not None else self.evaluate()
        return img if self.frame_denoiser is None else self.frame_denoiser(img)

    def frame_arrays(self) -> list[torch.Tensor]:
        """The frozen arrays a frame reads (the CSR matrices' values and indices, or F; V; the
        emission): what one pass over memory must read at least."""
        fz = self._frame_state()
        if fz is None:
            raise ValueRangeError("nothing is frozen; call freeze(object) first")
        out = [fz["V"], self.emission]
        csr = self._frozen_csr(fz)
        if csr is None:
            nonzeros = self._frozen_nonzeros(fz)
            out += [fz["F"]] if nonzeros is None else list(nonzeros)
        else:
            out += [csr[0].crow_indices(), csr[0].col_indices()] + [m.values() for m in csr]
        if fz["pix_r"].numel() != self.height * self.width:
            out.append(fz["pix_r"])
        return out

    def stream(self) -> torch.Tensor:
        """One pass over what a frame reads (:meth:`frame_arrays`; their sum): the
        memory-bandwidth floor of a frame when those arrays come from memory."""
        return sum(a.sum(dtype=self.dtype) for a in self.frame_arrays())

    @property
    def frozen_nbytes(self) -> int:
        """Bytes of the active frozen state's F and V."""
        if self._frozen is None:
            return 0
        return sum(self._frozen[k].numel() * self._frozen[k].element_size() for k in ("F", "V"))


def apply_scene_textures(renderer: PolynomialRenderer, scene, samples: int = 16, seed: int = 0) -> list[str]:
    r"""Give every textured editable object of ``scene`` its texture as the renderer's weight map
    (Ben-Artzi et al. 2008, Sec. 5.3): the directly seen surface exactly (per pixel, the texel
    averaged over ``samples`` jittered camera rays, :func:`~torch_brdf.scene.textures.texture_weight_map`),
    later bounces the texture's surface mean (:func:`~torch_brdf.scene.textures.surface_mean`)
    times the material's diffuse equivalent.

    The texture multiplies the whole eye-vertex BRDF of the object, which is the base-colour
    texture exactly for Lambert materials and an approximation for models whose base colour is
    only part of the BRDF (``blinn_phong``: its specular lobe is scaled too).

    Args:
        renderer: a :class:`PolynomialRenderer` of tensors precomputed from ``scene``.
        scene: the scene (any resolution: its camera is resized to the tensors').
        samples: samples of the weight maps.
        seed: seed of the weight maps.
    Returns:
        The names of the objects given a weight map.
    """
    from ..scene.textures import surface_mean, texture_weight_map

    sc = scene.with_resolution(renderer.width, renderer.height)
    names = set(renderer.tensors.object_names)
    done = []
    for k, o in enumerate(sc.objects):
        if "base_color" not in o.textures or o.name not in names:
            continue
        m = renderer.tensors.object_id(o.name)
        if renderer.tensors.bases[m] is None:
            continue  # a fixed object: its BRDF is baked into the tensors with its factor
        w = texture_weight_map(sc, o.name, samples, seed + k)
        renderer.set_weight_map(o.name, w, mean=surface_mean(sc, o.name, seed=seed + k))
        done.append(o.name)
    return done


def emitter_mask(tensors: PolynomialTensors, dilate: int = 1) -> torch.Tensor:
    """(H, W) bool: pixels that see no emitter directly (the emission term is zero there and
    in their ``dilate``-pixel neighbourhood). Emitters seen through a pixel are the same in
    every method but their jittered edges dominate Monte Carlo noise; comparisons exclude them."""
    e = tensors.emission.abs().sum(0).reshape(1, 1, tensors.height, tensors.width) > 0
    if dilate:
        e = torch.nn.functional.max_pool2d(e.float(), 2 * dilate + 1, stride=1, padding=dilate) > 0
    return ~e[0, 0]


def series_approximations(
    scene, series="64,1,1,1", spp: int = 64, seed: int = 0, progress: bool | None = None
) -> dict[str, Any]:
    """The three approximations of the seed's Fig. 6(b)/7 for ``scene``'s materials.

    Returns a dict with images (H, W, C) ``"series"`` (the given series: full BRDF at the eye
    vertex, diffuse equivalents after), ``"diffuse_indirect"`` (full BRDF for direct lighting
    plus indirect light from a series of 1-band bases: Fig. 7a) and ``"direct"`` (direct
    lighting only: Fig. 7b), the two :class:`PolynomialTensors` and their precompute seconds.
    """
    from ..transport.polynomial import PolynomialSettings, Series, precompute_polynomial

    s = Series.parse(series)
    mats = {o.name: scene.materials[o.material] for o in scene.objects if o.editable}
    full = precompute_polynomial(scene, PolynomialSettings(s, spp=spp), seed=seed, progress=progress)
    ones = Series((1,) * s.bounces)
    flat = {o.name: {"J": 1, "spacing": "uniform"} for o in scene.objects if o.editable}
    diffuse = precompute_polynomial(
        scene, PolynomialSettings(ones, spp=spp, bases=flat), seed=seed + 1, progress=progress
    )
    parts = PolynomialRenderer(full, mats).evaluate(per_bounce=True)
    dparts = PolynomialRenderer(diffuse, mats).evaluate(per_bounce=True)
    direct = parts[0] + parts[1]
    return {
        "series": sum(parts[1:], parts[0]),
        "diffuse_indirect": sum(dparts[2:], direct),
        "direct": direct,
        "tensors": full,
        "diffuse_tensors": diffuse,
    }
