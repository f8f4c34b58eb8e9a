r"""The per-vertex steps of the GI tracer in the compiled kernel: one C call per step and
wavefront instead of ~40 torch ops per vertex.

:class:`VertexKernel` wraps ``tb_frame``, ``tb_area_sample``, ``tb_light_gather``, ``tb_layers``,
``tb_mixture`` and ``tb_advance`` of :mod:`torch_brdf.transport._native` (see ``transport/csrc/vertex.c``):
the shading frame, an area light's next-event sample and its shadow ray, the light samples in
the local frame, the band slots and quotients of the editable objects, the direction mixture and
the path's advance. They compute what the torch steps of :meth:`~.tracer._Tracer.run` compute
with the same formulas, in the same precision and order, and draw the same random numbers, but
with the C library's scalar ``sqrtf``/``atan2f``/``powf``/... and, in the mixture, the
kernel's own vectorised cos/sin (``sincos_fd``, <= 0.5 ulp) rather than torch's vectorised
ones, so values may differ in the last ulp (``tests/transport/test_vertex.py`` compares both
with tolerances; the exactness oracles re-evaluate the paths this code traced). What the kernel
does not know stays torch: fixed objects' BRDFs (their rows are filled in by torch), quotients
other than the built-in ones, and lights other than :class:`~torch_brdf.scene.lights.AreaLight`
(sampled by torch, then gathered by the kernel).
"""

from __future__ import annotations

import ctypes
import functools
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
    """The kernel's code of a quotient (``Q_*`` in ``csrc/vertex.c``), None when it has none."""
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


@functools.cache
def c_rand_matches(lib) -> bool:
    """Whether ``tb_rand`` draws what ``torch.rand`` draws (float32 and float64, bit for bit, and
    the same generator state after), checked once per process on a generator of its own; the
    wavefront keeps ``torch.rand``'s stream either way (without the match it is not used)."""
    g = torch.Generator().manual_seed(20260)
    torch.rand(1000, generator=g)  # somewhere inside the engine's 624-word block
    s0 = g.get_state()
    a = torch.rand(1500, generator=g)
    b = torch.rand(700, 3, generator=g, dtype=torch.float64)
    after = g.get_state()
    s = s0.clone()
    if s.dtype != torch.uint8 or s.numel() < 24 + 8 * 624:
        return False
    x, y = torch.empty(1500, **_F32), torch.empty(2100, dtype=torch.float64)
    lib.tb_rand(_p(s), 1500, 0, _p(x))
    lib.tb_rand(_p(s), 2100, 1, _p(y))
    used = list(range(8, 12)) + list(range(16, 24 + 8 * 624))  # left, next, the state words
    if not (torch.equal(a, x) and torch.equal(b.flatten(), y) and torch.equal(s[used], after[used])):
        return False
    h = torch.Generator()  # the state written back goes on as torch's own would
    h.set_state(s)
    return torch.equal(torch.rand(5, generator=h), torch.rand(5, generator=g))


class Wavefront:
    r"""The GI tracer's wavefront in buffers allocated once and reused: the path
    state, the vertices and every per-step output of :meth:`~.tracer._Tracer._run_wavefront`, so
    a bounce runs as a few kernel calls on them (frame, light samples with their uniforms drawn in
    the kernel, the light samples that reach their vertex with their factors, mixture, band slots,
    advance, compaction of the paths whose ray hit) with no torch op or fresh page between them.
    The arithmetic is :class:`VertexKernel`'s (the same C functions), the random numbers are
    ``torch.rand``'s stream drawn by ``tb_rand`` (:func:`c_rand_matches`), so the tensors are
    the same bit for bit as with the per-step calls.

    Args:
        vk: the tracer's :class:`VertexKernel`.
    """

    def __init__(self, vk: VertexKernel):
        self.vk, self.lib, t = vk, vk.lib, vk.tracer
        self.La = t.level1.max_layers
        self.Lb = t.level2.max_layers if t.level2 is not None else 1
        self.M = t.num_objects
        self.room = 0
        self._lights: dict[int, tuple] = {}

    @classmethod
    def make(cls, vk: VertexKernel | None) -> Wavefront | None:
        """The wavefront of ``vk``'s tracer, or None when a step would need torch (lights other
        than area lights, fixed BRDFs or quotients the kernel does not know), its rays are not
        the kernel's, or ``tb_rand`` does not match ``torch.rand`` here."""
        if vk is None:
            return None
        t = vk.tracer
        if any(type(li) is not AreaLight for li in t.lights) or vk.torch_fixed:
            return None
        if any(s.torch_objects for s in vk.levels.values()) or t._native_rays() is None:
            return None
        return cls(vk) if c_rand_matches(vk.lib) else None

    def ensure(self, n: int) -> None:
        """Buffers for wavefronts of up to ``n`` paths (grown, never shrunk)."""
        if n <= self.room:
            return
        r = self.room = max(n, int(1.25 * self.room))
        La, Lb, M = self.La, self.Lb, self.M
        e = torch.empty
        u8 = {"dtype": torch.uint8}
        self.st = {"idx": e(r, **_I64), "m1": e(r, **_I64), "A_i": e(r, La, **_I64), "B_i": e(r, Lb, **_I64),
                   "oid": e(r, **_I64), "raw": e(r, 3, **_F32), "A_w": e(r, La, 3, **_F32),
                   "B_w": e(r, Lb, 3, **_F32), "d_in": e(r, 3, **_F32), "pos": e(r, 3, **_F32),
                   "ng": e(r, 3, **_F32), "ns": e(r, 3, **_F32), "counts": e(r, M, dtype=torch.int8)}  # fmt: skip
        self.fr, self.wo = e(r, 9, **_F32), e(r, 3, **_F32)
        # the order of tb_wf in csrc/wavefront.c
        ptrs = [x.data_ptr() for x in (*self.st.values(), self.fr, self.wo)]
        self._st_ptrs = (ctypes.c_void_p * 15)(*ptrs)
        # light samples: per vertex, candidates, the ones that reach their vertex
        self.lcos = e(r, **_F32)
        self.ldir, self.lwt = e(r, 3, **_F32), e(r, 3, **_F32)
        self.k, self.so, self.sd, self.tmax = e(r, **_I64), e(r, 3, **_F32), e(r, 3, **_F32), e(r, **_F32)
        self.kk, self.ob, self.ed = e(r, **_I64), e(r, **_I64), e(r, **u8)
        self.wl, self.wok, self.lw, self.lf = (e(r, 3, **_F32) for _ in range(4))
        self.lj = {1: e(r, La, **_I64), 2: e(r, Lb, **_I64)}
        self.lq = {1: e(r, La, 3, **_F32), 2: e(r, Lb, 3, **_F32)}
        # the mixture and the advance
        self.u32, self.wi, self.ok = e(r, 3, **_F32), e(r, 3, **_F32), e(r, **u8)
        self.pdf, self.cosw = e(r, **_F32), e(r, **_F32)
        self.f, self.a, self.nso, self.nsd = e(r, 3, **_F32), e(r, **_I64), e(r, 3, **_F32), e(r, 3, **_F32)

    def state(self, n: int, cls):
        """The :class:`~.tracer.PathState` of the ``n`` live paths (views of the buffers)."""
        s = self.st
        return cls(s["idx"][:n], s["m1"][:n], s["raw"][:n], s["A_i"][:n], s["A_w"][:n], s["B_i"][:n],
                   s["B_w"][:n], s["counts"][:n])  # fmt: skip

    def start(self, directions, hits) -> int:
        """The eye vertices of the rays that hit (``PathState.start``) with their shading frames
        (``fr``, ``wo``; normals flipped); returns the paths."""
        self.ensure(directions.shape[0])
        d = _f(directions)
        return self.lib.tb_wf_start(
            d.shape[0], _p(d), _p(hits.object_id), _p(hits.position), _p(hits.geometric_normal), _p(hits.normal),
            self._st_ptrs, self.La, self.Lb, self.M,
        )  # fmt: skip

    def compact(self, m: int, hits) -> int:
        """After the trace of the ``m`` next rays: the paths whose ray hit, at their new vertex
        with its shading frame."""
        return self.lib.tb_wf_compact(
            m, _p(self.a), _p(self.nsd), _p(hits.object_id), _p(hits.position), _p(hits.geometric_normal),
            _p(hits.normal), self._st_ptrs, self.La, self.Lb, self.M,
        )  # fmt: skip

    def _light(self, light):
        if id(light) not in self._lights:
            cdf = light.cdf.to(torch.float64).contiguous()
            tri, nrm = _f(light.triangles), _f(light.normals)
            self._lights[id(light)] = (light, cdf, tri, nrm, light.radiance.to(torch.float32).contiguous())
        return self._lights[id(light)]

    def light_sample(self, light, n: int, gs) -> int:
        """``light``'s next-event samples from the ``n`` vertices (uniforms from the state bytes
        ``gs``): the candidates' rows, shadow rays and ``t_max`` in ``k``, ``so``, ``sd``, ``tmax``."""
        _, cdf, tri, nrm, rad = self._light(light)
        s = self.st
        # the uniforms torch.rand(n, 3, dtype=float64) would give (as AreaLight.sample_points draws them)
        return self.lib.tb_wf_area_sample(
            _p(gs), n, _p(cdf), cdf.numel(), _p(tri), _p(nrm), _p(rad), ctypes.c_float(light.total_area),
            _p(s["pos"]), _p(s["ng"]), _p(s["ns"]), ctypes.c_float(self.vk.eps),
            *map(_p, (self.ldir, self.lwt, self.lcos, self.k, self.so, self.sd, self.tmax)),
        )  # fmt: skip

    def light_hits(self, m: int, occ, reps: int, diffuse: bool) -> int:
        """The candidates not occluded (``occ`` (m,) bool), gathered into ``kk``, ``wl``, ``wok``,
        ``ob``, ``ed``, ``lw`` (and the diffuse factor ``lf`` when ``diffuse``)."""
        vk = self.vk
        return self.lib.tb_wf_light_hits(
            m, _p(self.k), _p(occ), _p(self.ldir), _p(self.lwt), _p(self.lcos), ctypes.c_float(reps), _p(self.fr),
            _p(self.wo), _p(self.st["oid"]), _p(vk.editable), int(diffuse), _p(vk.fixed_mode), _p(vk.lambert),
            *map(_p, (self.kk, self.wl, self.wok, self.ob, self.ed, self.lw, self.lf)),
        )  # fmt: skip

    def layers(self, level: int, n: int, oid, wi, wo, idx, w) -> None:
        """``tb_layers`` of ``level`` on rows ``oid``, ``wi``, ``wo`` into ``idx``, ``w`` (buffers)."""
        spec = self.vk.levels[level]
        L = self.La if level == 1 else self.Lb
        self.lib.tb_layers(n, L, -1 if level == 2 else 0, _p(spec.spec), _p(spec.edges), _p(self.vk.lambert),
                           _p(oid), _p(wi), _p(wo), _p(idx), _p(w))  # fmt: skip

    def mixture(self, n: int, gs) -> None:
        """Directions from the mixture at the ``n`` vertices into ``wi``, ``pdf``, ``cosw``, ``ok``."""
        self.lib.tb_rand(_p(gs), 3 * n, 0, _p(self.u32))
        self.lib.tb_mixture(n, _p(self.u32), _p(self.wo), *map(ctypes.c_float, self.vk.mix),
                            *map(_p, (self.wi, self.pdf, self.cosw, self.ok)))  # fmt: skip

    def fixed_f(self, n: int):
        vk = self.vk
        self.lib.tb_fixed_f(n, _p(vk.fixed_mode), _p(vk.lambert), _p(self.st["oid"]), _p(self.wi), _p(self.wo),
                            _p(self.f))  # fmt: skip
        return self.f

    def advance(self, n: int, f, count: bool) -> int:
        """``tb_advance`` in place on the state; the next rays in ``a``, ``nso``, ``nsd``. Returns them."""
        s = self.st
        return self.lib.tb_advance(
            n, _p(self.wi), _p(self.cosw), _p(self.ok), _p(f), int(count), _p(s["oid"]), _p(self.vk.editable),
            self.M, _p(s["counts"]), _p(s["raw"]), _p(self.fr), _p(s["ng"]), _p(s["pos"]), self.La, _p(s["A_w"]),
            self.Lb, _p(s["B_w"]), ctypes.c_float(self.vk.eps), _p(self.a), _p(self.nso), _p(self.nsd),
        )  # fmt: skip
