r"""The per-vertex steps of the GI tracer in the compiled kernel (#14): one C call per step and
wavefront instead of ~40 torch ops per vertex.

:class:`VertexKernel` wraps ``tb_frame``, ``tb_area_sample``, ``tb_light_gather``, ``tb_layers``,
``tb_mixture`` and ``tb_advance`` of :mod:`torch_brdf.transport._native` (see ``_native.c``):
the shading frame, an area light's next-event sample and its shadow ray, the light samples in
the local frame, the band slots and quotients of the editable objects, the direction mixture and
the path's advance. They compute what the torch steps of :meth:`~.tracer._Tracer.run` compute
with the same formulas, in the same precision and order, and draw the same random numbers, but
with the C library's scalar ``sqrtf``/``atan2f``/``powf``/... rather than torch's vectorised
ones, so values may differ in the last ulp (``tests/transport/test_vertex.py`` compares both
with tolerances; the exactness oracles re-evaluate the paths this code traced). What the kernel
does not know stays torch: fixed objects' BRDFs (their rows are filled in by torch), quotients
other than the built-in ones, and lights other than :class:`~torch_brdf.scene.lights.AreaLight`
(sampled by torch, then gathered by the kernel).
"""

from __future__ import annotations

import ctypes
import math
from dataclasses import fields

import torch

from ...brdf.bands import quotients as _q
from ...brdf.base import Lambert
from ...scene.lights import AreaLight
from .._native import library
from .._native import ptr as _p
from ..pathtrace import rows_by_object, sample_light

__all__ = ["VertexKernel", "quotient_code"]

_BASE_CODES = {_q._One: 0, _q._Distribution: 1, _q._Microfacet: 2, _q._CookTorrance: 3, _q._AshikhminShirley: 4}
_VARIABLES = {"theta_h": 0, "theta_d": 1}
_F32, _I64 = {"dtype": torch.float32}, {"dtype": torch.int64}


def quotient_code(q) -> int | None:
    """The kernel's code of a quotient (``Q_*`` in ``_native.c``), None when it has none."""
    if type(q) in _BASE_CODES:
        return _BASE_CODES[type(q)]
    if type(q) is _q.SchlickFresnel and q.f0 is None and type(q.base) in _BASE_CODES:
        return 8 + _BASE_CODES[type(q.base)]
    return None


def _f(t: torch.Tensor) -> torch.Tensor:
    return t if t.dtype == torch.float32 and t.is_contiguous() else t.to(torch.float32).contiguous()


def _i(t: torch.Tensor) -> torch.Tensor:
    return t if t.dtype == torch.int64 and t.is_contiguous() else t.to(torch.int64).contiguous()


def _lambert(brdfs) -> tuple[torch.Tensor, list[bool]]:
    """(O, 3) float32 reflectance of each Lambertian BRDF (zeros for others) and which are."""
    is_l = [type(b) is Lambert for b in brdfs]
    rho = [b.reflectance.detach().float().reshape(3) if k else torch.zeros(3) for b, k in zip(brdfs, is_l, strict=True)]
    return torch.stack(rho).contiguous(), is_l


class _LayerSpec:
    """One level of :class:`~.tracer._Layers` as the kernel's table: ``spec`` (O, 8) int32 rows
    (mode, variable, J, offset, layers, two quotient codes, first edge), ``edges`` float32, and
    the objects whose rows torch fills (``torch_objects``: fixed ones other than Lambertian and
    unknown quotients)."""

    def __init__(self, layers):
        rows, edges, self.torch_objects = [], [], set()
        _, is_l = _lambert(layers.brdfs)
        for o, spec in enumerate(layers.per_object):
            if spec is None:
                rows.append([2 if is_l[o] else 0] + [0] * 7)
                if not is_l[o]:
                    self.torch_objects.add(o)
                continue
            basis, quotients, J, off = spec
            codes = [quotient_code(q) for q in quotients]
            if basis.variable not in _VARIABLES or None in codes or len(codes) > 2:
                rows.append([0] * 8)
                self.torch_objects.add(o)
                continue
            codes += [0] * (2 - len(codes))
            rows.append([1, _VARIABLES[basis.variable], J, off, len(quotients), *codes, sum(map(len, edges))])
            edges.append(basis.edges[1:-1].to(torch.float32).tolist())  # torch's bucketize compares in float32
        self.spec = torch.tensor(rows, dtype=torch.int32).contiguous()
        self.edges = torch.tensor([e for es in edges for e in es] or [0.0], dtype=torch.float32)
        self.layers = layers


class VertexKernel:
    """The compiled per-vertex steps for one tracer (see the module docstring).

    Args:
        lib: :func:`~torch_brdf.transport._native.library`'s kernel.
        tracer: the :class:`~.tracer._Tracer` whose steps it runs.
    """

    def __init__(self, lib, tracer):
        self.lib, self.tracer = lib, tracer
        self.eps = float(tracer.scene.ray_epsilon)
        self.levels = {1: _LayerSpec(tracer.level1)}
        if tracer.level2 is not None:
            self.levels[2] = _LayerSpec(tracer.level2)
        self.editable = tracer.editable.to(torch.uint8).contiguous()
        self.lambert, is_l = _lambert(tracer.brdfs)
        # per object: 0 editable, 1 fixed Lambertian, 2 another fixed BRDF (torch)
        mode = [0 if e else (1 if lam else 2) for e, lam in zip(tracer.editable.tolist(), is_l, strict=True)]
        self.fixed_mode = torch.tensor(mode, dtype=torch.int32)
        self.torch_fixed = {o for o, k in enumerate(mode) if k == 2}
        m = tracer.mixture
        n = float(m.exponent)
        self.mix = [m.diffuse, 1 - m.diffuse, n, (n + 1.0) / (2 * math.pi)]

    @classmethod
    def make(cls, tracer) -> VertexKernel | None:
        """The kernel for ``tracer``, or None (no compiler, ``TORCH_BRDF_NATIVE=0``, or a mixture
        that is not the built-in :class:`~.sampler.Mixture`): the torch steps run then."""
        from .sampler import Mixture

        lib = library()
        if lib is None or type(tracer.mixture) is not Mixture:
            return None
        return cls(lib, tracer)

    def frame(self, d_in, ng, ns):
        """:func:`~torch_brdf.transport.pathtrace.shading_frame`: (ng, ns) flipped, frame (n, 9)
        rows s, t, n, and wo (n, 3)."""
        n = d_in.shape[0]
        ng, ns = _f(ng).clone(), _f(ns).clone()
        fr, wo = torch.empty(n, 9, **_F32), torch.empty(n, 3, **_F32)
        self.lib.tb_frame(n, _p(_f(d_in)), _p(ng), _p(ns), _p(fr), _p(wo))
        return ng, ns, fr, wo

    def light(self, light, pos, ng, ns, gen):
        """Next-event samples of ``light`` from every vertex and their shadow rays.

        Returns:
            (direction (n, 3), weight (n, 3), cos (n,), shadow rays cast, kk): ``kk`` the rows
            whose light sample is visible.
        """
        scene = self.tracer.scene
        if type(light) is not AreaLight:
            ls, cos, cast, kk = sample_light(scene, light, pos, ng, ns, gen)
            return _f(ls.direction), _f(ls.weight), _f(cos), cast, kk
        n = pos.shape[0]
        u = torch.rand(n, 3, generator=gen, dtype=torch.float64)  # as AreaLight.sample_points draws them
        d, w, cos = torch.empty(n, 3, **_F32), torch.empty(n, 3, **_F32), torch.empty(n, **_F32)
        k, so, sd, tmax = (
            torch.empty(n, **_I64),
            torch.empty(n, 3, **_F32),
            torch.empty(n, 3, **_F32),
            torch.empty(n, **_F32),
        )
        tri, nrm, cdf = light.triangles.contiguous(), light.normals.contiguous(), light.cdf.contiguous()
        rad = light.radiance.to(torch.float32).contiguous()
        m = self.lib.tb_area_sample(
            n, _p(u), _p(cdf), cdf.numel(), _p(_f(tri)), _p(_f(nrm)), _p(rad), ctypes.c_float(light.total_area),
            _p(pos), _p(ng), _p(ns), ctypes.c_float(self.eps), *map(_p, (d, w, cos, k, so, sd, tmax)),
        )  # fmt: skip
        if m == 0:
            return d, w, cos, 0, k[:0]
        # the kernel wrote the shadow directions (sd); the scene's rays or the compiled ones cast them
        occ = self.tracer.occluded(so[:m], sd[:m], tmax[:m]).contiguous()
        kk = torch.empty(m, **_I64)
        return d, w, cos, m, kk[: self.lib.tb_unoccluded(m, _p(k), _p(occ), _p(kk))]

    def gather(self, kk, d, w, cos, reps: int, fr, wo, oid):
        """The light samples ``kk`` in their frames: (wl, wo, object, editable, lw = weight cos / reps)."""
        m = kk.numel()
        wl, wok, lw = torch.empty(m, 3, **_F32), torch.empty(m, 3, **_F32), torch.empty(m, 3, **_F32)
        ob, ed = torch.empty(m, **_I64), torch.empty(m, dtype=torch.bool)
        self.lib.tb_light_gather(
            m, _p(_i(kk)), _p(d), _p(w), _p(cos), ctypes.c_float(reps), _p(fr), _p(wo), _p(_i(oid)), _p(self.editable),
            *map(_p, (wl, wok, ob, ed, lw)),
        )  # fmt: skip
        return wl, wok, ob, ed, lw

    def layers(self, level: int, oid, wi, wo):
        """:class:`~.tracer._Layers` of ``level``: index (n, L) and weight (n, L, 3)."""
        spec = self.levels[level]
        layers = spec.layers
        with layers.clock("brdf"):
            n, L = oid.numel(), layers.max_layers
            idx, w = torch.empty(n, L, **_I64), torch.empty(n, L, 3, **_F32)
            oid, wi, wo = _i(oid), _f(wi), _f(wo)
            fill = -1 if level == 2 else 0
            self.lib.tb_layers(
                n, L, fill, _p(spec.spec), _p(spec.edges), _p(self.lambert), _p(oid), _p(wi), _p(wo), _p(idx), _p(w)
            )
            if spec.torch_objects:
                for o, m in rows_by_object(oid):
                    if o in spec.torch_objects:
                        idx[m], w[m] = layers.rows(o, wi[m], wo[m], idx[m], w[m])
            return idx, w

    def fixed_f(self, oid, wi, wo):
        """:meth:`~.tracer._Tracer._fixed_f`: (n, 3) the full BRDF of fixed objects, 1 for
        editable ones (Lambertian ones in the kernel, others by torch)."""
        tracer = self.tracer
        with tracer.clock("brdf"):
            n = oid.numel()
            out = torch.empty(n, 3, **_F32)
            oid, wi, wo = _i(oid), _f(wi), _f(wo)
            self.lib.tb_fixed_f(n, _p(self.fixed_mode), _p(self.lambert), _p(oid), _p(wi), _p(wo), _p(out))
            if self.torch_fixed:
                for o, m in rows_by_object(oid):
                    if o in self.torch_fixed:
                        out[m] = tracer.brdfs[o].eval_local(wi[m], wo[m]).to(torch.float32)
            return out

    def take(self, rows, *xs: torch.Tensor) -> list[torch.Tensor]:
        """``[x[rows] for x in xs]`` (contiguous tensors, any dtype) in one kernel call."""
        rows = _i(rows)
        m, xs = rows.numel(), [x.contiguous() for x in xs]
        out = [torch.empty((m, *x.shape[1:]), dtype=x.dtype) for x in xs]
        ptrs = ctypes.c_void_p * len(xs)
        rb = torch.tensor([x[0].numel() * x.element_size() if x.shape[0] else 0 for x in xs], dtype=torch.int64)
        self.lib.tb_gather(
            m, _p(rows), len(xs), ptrs(*[x.data_ptr() for x in xs]), ptrs(*[o.data_ptr() for o in out]), _p(rb)
        )
        return out

    def keep(self, st, rows):
        """``st.keep(rows)`` (the oracle's records, if any, by torch)."""
        if st.oracle is not None:
            return st.keep(rows)
        names = [f.name for f in fields(st) if f.name != "oracle"]
        return type(st)(**dict(zip(names, self.take(rows, *(getattr(st, k) for k in names)), strict=True)))

    def mixture(self, u, wo):
        """:meth:`~.sampler.Mixture.sample` and the tracer's ok, cos / pdf: wi, pdf, cosw, ok."""
        n = wo.shape[0]
        wi, pdf, cosw, ok = (torch.empty(n, 3, **_F32), torch.empty(n, **_F32), torch.empty(n, **_F32),
                             torch.empty(n, dtype=torch.bool))  # fmt: skip
        self.lib.tb_mixture(n, _p(_f(u)), _p(wo), *map(ctypes.c_float, self.mix), *map(_p, (wi, pdf, cosw, ok)))
        return wi, pdf, cosw, ok

    def advance(self, st, wi, cosw, ok, f, count: bool, oid, fr, ng, pos):
        """The path state after the sample (``st.raw``, ``st.counts`` replaced) and its next rays:
        (rows a (m,), origins (m, 3), directions (m, 3))."""
        n = wi.shape[0]
        raw, counts = _f(st.raw).clone(), st.counts.contiguous().clone()
        A_w, B_w = _f(st.A_w), _f(st.B_w)
        a, so, sd = torch.empty(n, **_I64), torch.empty(n, 3, **_F32), torch.empty(n, 3, **_F32)
        m = self.lib.tb_advance(
            n, _p(wi), _p(cosw), _p(ok), _p(None if f is None else _f(f)), int(count), _p(_i(oid)), _p(self.editable),
            counts.shape[1], _p(counts), _p(raw), _p(fr), _p(ng), _p(_f(pos)), A_w.shape[1], _p(A_w), B_w.shape[1],
            _p(B_w), ctypes.c_float(self.eps), *map(_p, (a, so, sd)),
        )  # fmt: skip
        st.raw, st.counts = raw, counts
        return a[:m], so[:m], sd[:m]
