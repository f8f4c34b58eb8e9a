r"""The batched symbolic path tracer of the multibounce precomputation (Ben-Artzi et al. 2008, Sec. 5.1).

A wavefront path tracer from the eye on embree. Directions come from the BRDF-independent
:class:`~.sampler.Mixture`; at every vertex each light of the scene gets one next-event sample,
and each light sample adds its weight to one entry per basis layer (Eq. 22-24): the band of
:math:`(\omega_i, \omega_o)` at the eye vertex, the second-bounce slot for a low-frequency
second bounce, and the multiset of the objects of the diffuse-equivalent vertices. The live
paths of a batch are one :class:`PathState`; each light sample is one :class:`LightHit`.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace

import torch

from ...brdf import BRDF
from ...brdf.bands import BandBasis, Quotient
from ...records.polynomial import ObjectBasis, Series
from ...scene.lights import AreaLight, Light
from ...scene.scene import Scene
from .._native import library
from ..pathtrace import (
    _mis_lights,
    emission_and_light_pdf,
    emission_seen,
    material_brdfs,
    power_heuristic,
    rows_by_object,
    sample_light,
    shading_frame,
)
from ..rays import NativeRays
from .sampler import Mixture
from .vertex import VertexKernel, Wavefront

__all__ = ["Clock", "LightHit", "PathState"]


class Clock:
    """Exclusive wall seconds per section of the precomputation (the profile split).

    ``with clock("brdf"): ...`` adds the block's time less that of sections nested in it; the
    time the scene's :class:`~torch_brdf.scene.raytrace.RayTracer` spends casting rays inside
    a section (its ``seconds``) goes to ``"rays"`` instead.

    Args:
        ray_tracer: the scene's ray tracer (``scene.tracer``).
    """

    def __init__(self, ray_tracer):
        self.seconds: dict[str, float] = defaultdict(float)
        self._rt = ray_tracer
        self._stack: list[list[float]] = []

    @contextmanager
    def __call__(self, name: str):
        t0, r0 = time.perf_counter(), self._rt.seconds
        self._stack.append([0.0, 0.0])  # time and ray time of nested sections
        try:
            yield
        finally:
            child_t, child_r = self._stack.pop()
            total, rays = time.perf_counter() - t0, self._rt.seconds - r0
            self.seconds[name] += total - child_t - (rays - child_r)
            self.seconds["rays"] += rays - child_r
            if self._stack:
                self._stack[-1][0] += total
                self._stack[-1][1] += rays


@dataclass
class PathState:
    """The live paths of one batch after some vertices (one row per path still alive).

    Attributes:
        idx: (n,) ray id of each path (its pixel record is ``rec[idx]``).
        m1: (n,) object seen at the eye vertex.
        raw: (n, 3) throughput without editable factors and without the 1/pi of diffuse equivalents.
        A_i, A_w: (n, L1) eye-vertex slots and (n, L1, 3) their layer weights.
        B_i, B_w: (n, L2) second-bounce slots (-1: none) and (n, L2, 3) their weights.
        counts: (n, M) int8 occurrences of each object among the diffuse-equivalent vertices.
        oracle: tests only: local directions and objects to re-evaluate each entry, or None.
    """

    idx: torch.Tensor
    m1: torch.Tensor
    raw: torch.Tensor
    A_i: torch.Tensor
    A_w: torch.Tensor
    B_i: torch.Tensor
    B_w: torch.Tensor
    counts: torch.Tensor
    oracle: dict | None = None

    @classmethod
    def start(cls, idx: torch.Tensor, m1: torch.Tensor, num_objects: int, oracle: bool) -> PathState:
        """Paths that just hit their eye vertex (no factors yet)."""
        k = idx.numel()
        rec_p = {"wi1": None, "wo1": None, "wi2": None, "wo2": None, "m2": None, "objs": []} if oracle else None
        return cls(
            idx,
            m1,
            torch.ones(k, 3),
            torch.zeros(k, 1, dtype=torch.long),
            torch.ones(k, 1, 3),
            torch.full((k, 1), -1, dtype=torch.long),
            torch.ones(k, 1, 3),
            torch.zeros(k, num_objects, dtype=torch.int8),
            rec_p,
        )

    def keep(self, rows: torch.Tensor) -> PathState:
        """The paths ``rows`` (index tensor) only."""
        out = {f.name: getattr(self, f.name)[rows] for f in fields(self) if f.name != "oracle"}
        rec_p = self.oracle
        if rec_p is not None:
            rec_p = {k: (None if v is None else v[rows]) for k, v in rec_p.items() if k != "objs"}
            rec_p["objs"] = [t[rows] for t in self.oracle["objs"]]
        return PathState(**out, oracle=rec_p)


@dataclass
class LightHit:
    """The light samples that reach paths ``kk`` of a :class:`PathState` at one vertex.

    Attributes:
        kk: (n,) rows of the path state. wl: (n, 3) local direction to the light.
        wo: (n, 3) local outgoing direction. ob: (n,) object at the vertex.
        ed: (n,) bool, the object is editable. lw: (n, 3) light weight times cosine.
    """

    kk: torch.Tensor
    wl: torch.Tensor
    wo: torch.Tensor
    ob: torch.Tensor
    ed: torch.Tensor
    lw: torch.Tensor


class _Layers:
    """Band index and quotient weight of every (object, layer) at a banded vertex."""

    def __init__(self, bases: list[ObjectBasis | None], brdfs: list[BRDF], level: int, offsets: list[int], clock):
        self.clock = clock  # its "brdf" section times the calls
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
        with self.clock("brdf"):
            return self._call(oid, wi, wo)

    def _call(self, oid: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor):
        n, L = oid.numel(), self.max_layers
        idx = torch.full((n, L), -1 if self.level == 2 else 0, dtype=torch.long)
        wgt = torch.zeros(n, L, 3, dtype=wi.dtype)
        for o, m in rows_by_object(oid):
            idx[m], wgt[m] = self.rows(o, wi[m], wo[m], idx[m], wgt[m])
        return idx, wgt

    def rows(self, o: int, wi: torch.Tensor, wo: torch.Tensor, idx: torch.Tensor, wgt: torch.Tensor):
        """The slots (m, L) and weights (m, L, 3) of object ``o``'s pairs ``wi``, ``wo`` (m, 3),
        written into ``idx`` and ``wgt`` (which hold the defaults) and returned."""
        spec = self.per_object[o]
        if spec is None:
            wgt[:, 0] = self.brdfs[o].eval_local(wi, wo).to(wi.dtype)
            return idx, wgt
        up = ((wi[:, 2] > 0) & (wo[:, 2] > 0)).to(wi.dtype)[:, None]
        basis, quotients, J, off = spec
        band = basis.index(basis.gamma(wi, wo))
        for layer, q in enumerate(quotients):
            qv = q(wi, wo).to(wi.dtype)
            qv = qv[:, None].expand(-1, 3) if qv.ndim == 1 else qv
            idx[:, layer] = off + layer * J + band
            wgt[:, layer] = qv * up
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
    """The batched symbolic path tracer (one instance per precomputation).

    ``eye_light_samples``: next-event samples per light at the eye vertex, each weighted
    1/k (splitting: the same estimator of the same polynomial, less noise where direct
    light dominates it, e.g. under a sun); later vertices take one.
    """

    def __init__(
        self, scene: Scene, bases, series: Series, mixture: Mixture, lights: list[Light], eye_light_samples: int = 1
    ):
        self.scene, self.series, self.mixture, self.lights = scene, series, mixture, lights
        self.eye_light_samples = eye_light_samples
        self.brdfs = material_brdfs(scene)
        self.bases = bases
        self.num_objects = len(scene.objects)
        self.editable = torch.tensor([b is not None for b in bases])
        self.all_editable = bool(self.editable.all())
        self.clock = Clock(scene.tracer)
        self.level1 = _Layers(bases, self.brdfs, 1, [0] * len(bases), self.clock)
        offs, off = [], 0
        for b in bases:
            offs.append(off)
            if b is not None and series.two_level:
                off += b.second_size
        self.level2 = _Layers(bases, self.brdfs, 2, offs, self.clock) if series.two_level else None
        self.rays = {"closest": 0, "shadow": 0}
        self._vk = None  # the compiled per-vertex steps, made on first use
        self._wf = None  # their reused wavefront buffers (vertex.py Wavefront), made on first use
        self._rays = None  # the compiled ray casting, made on first use
        # pi^-k by the number k of earlier diffuse-equivalent vertices (one table for both the
        # torch and the compiled entries, so they agree bit for bit)
        self.pi_powers = math.pi ** -(torch.arange(series.bounces + 2).double()).float()
        # a LobeMixture with mis: its objects' eye vertices combine next-event estimation and
        # the mixture's own samples by MIS (the power heuristic; weights from the two pdfs only,
        # so every edit stays exact), for the lights a sampled ray can find
        ids = getattr(mixture, "ids", None) if getattr(mixture, "mis", False) else None
        self.mis_ids = None if not ids else torch.tensor(ids, dtype=torch.long)
        self.mis_lights = _mis_lights(scene) & {id(li) for li in lights} if self.mis_ids is not None else set()

    def _trace(self, o, d):
        """Closest hits of the rays (:meth:`Scene.trace <torch_brdf.scene.scene.Scene.trace>`; by the
        compiled kernel where it can, :class:`~torch_brdf.transport.rays.NativeRays`: its hits hold
        until the next call)."""
        self.rays["closest"] += o.shape[0]
        with self.clock("rays"):
            rays = self._native_rays()
            return self.scene.trace(o, d) if rays is None else rays.trace(o, d)

    def occluded(self, o, d, t_max):
        """(n,) bool: shadow rays from ``o`` (n, 3) along ``d`` (n, 3) within ``t_max`` (n,), by the
        compiled kernel where it can (else the scene's tracer)."""
        rays = self._native_rays()
        return self.scene.tracer.occluded(o, d, t_max) if rays is None else rays.occluded(o, d, t_max)

    def _native_rays(self):
        """:class:`~torch_brdf.transport.rays.NativeRays` of the scene's tracer, or None."""
        if self._rays is None:
            self._rays = NativeRays.make(self.scene.tracer) or False
        return self._rays or None

    def _fixed_f(self, oid, wi, wo):
        """(n, 3): the full BRDF of fixed objects, 1 for editable ones."""
        with self.clock("brdf"):
            out = torch.ones(oid.numel(), 3, dtype=wi.dtype)
            if self.all_editable:
                return out
            for o, m in rows_by_object(oid):
                if not self.editable[o]:
                    out[m] = self.brdfs[o].eval_local(wi[m], wo[m]).to(wi.dtype)
            return out

    @torch.no_grad()
    def run(self, origins, directions, rec, gen, paths: dict | None = None, ent=None, strata=None):
        """Trace one path per ray. ``rec`` (n,) is the path's pixel record id; ``strata``
        (:class:`~.sampler.EyeStrata` of the rays) stratifies the eye vertex's samples when the
        mixture asks for it (a :class:`~.sampler.LobeMixture` with ``stratified``).

        Returns the emission seen directly (n, 3) and the entries: ``ent`` (anything with
        :meth:`_Entries.add`, e.g. the compiled :class:`~.reduce.NativeEntries`) or a new
        :class:`_Entries`. With ``paths``
        (a dict), also records for every entry the raw weight without editable factors and
        the local directions and objects needed to re-evaluate it with explicit BRDFs (the
        exactness oracle of the tests).
        """
        scene, nb, clock = self.scene, self.series.bounces, self.clock
        ent = _Entries() if ent is None else ent
        vk = self._vertex_kernel() if directions.dtype == torch.float32 else None
        if vk is not None and paths is None and getattr(ent, "native", False) and isinstance(gen, torch.Generator):
            wf = self._wavefront(vk)
            if wf is not None and gen.device.type == "cpu":
                return self._run_wavefront(wf, origins, directions, rec, gen, ent)
        if vk is not None:
            return self._run_fused(vk, origins, directions, rec, gen, paths, ent)
        emis, st, d_in, pos, ng, ns, oid = self._start(origins, directions, paths)
        if strata is not None and not getattr(self.mixture, "stratified", False):
            strata = None
        eye = strata.take(st.idx) if strata is not None else None  # the eye vertices' strata
        for v in range(1, nb + 1):
            if st.idx.numel() == 0:
                break
            with clock("sampling"):
                ng, ns, frame, wo = shading_frame(d_in, ng, ns)
                ed = self.editable[oid]
            reps = self.eye_light_samples if v == 1 else 1
            for i, light in enumerate([li for li in self.lights for _ in range(reps)]):
                with clock("sampling"):
                    u = None
                    if v == 1 and eye is not None and isinstance(light, AreaLight):
                        u = torch.rand(st.idx.numel(), 3, generator=gen, dtype=torch.float64)  # as drawn inside
                        u = eye.light_uniforms(light, u, salt=2 + i)
                    ls, cos, cast, kk = sample_light(scene, light, pos, ng, ns, gen, u)
                    self.rays["shadow"] += cast
                    if kk.numel() == 0:
                        continue
                    wl = frame.to_local(ls.direction)[kk]
                    lw = ls.weight[kk] * cos[kk, None] / reps
                    if v == 1 and id(light) in self.mis_lights:  # the mixture's sample may find it too
                        mine = torch.isin(oid[kk], self.mis_ids)
                        p_m = self.mixture.pdf(wl, wo[kk], oid[kk])
                        w_l = power_heuristic(reps * ls.pdf[kk], p_m)
                        lw = lw * torch.where(mine, w_l, torch.ones_like(w_l))[:, None]
                    hit = LightHit(kk, wl, wo[kk], oid[kk], ed[kk], lw)
                with clock("bookkeeping"):
                    self._emit(ent, st, v, hit, paths, rec)
            if v == nb:
                break
            with clock("sampling"):
                u = torch.rand(st.idx.numel(), 3, generator=gen)
                if v == 1 and eye is not None:
                    u = self.mixture.stratify(u, eye, oid)
                wi, pdf = self.mixture.sample(wo, u, oid)
                ok = (pdf > 0) & (wi[:, 2] > 0) & (wo[:, 2] > 0)
                cosw = torch.where(ok, wi[:, 2] / pdf.clamp_min(1e-30), torch.zeros_like(pdf))
            rec_p = st.oracle
            with clock("bookkeeping"):
                if v == 1:
                    st.A_i, st.A_w = self.level1(oid, wi, wo)
                    st.raw = st.raw * cosw[:, None]
                    if rec_p is not None:
                        rec_p["wi1"], rec_p["wo1"] = wi.clone(), wo.clone()
                elif v == 2 and self.level2 is not None:
                    st.B_i, st.B_w = self.level2(oid, wi, wo)
                    st.raw = st.raw * cosw[:, None]
                    if rec_p is not None:
                        rec_p["wi2"], rec_p["wo2"], rec_p["m2"] = wi.clone(), wo.clone(), oid.clone()
                else:
                    f = self._fixed_f(oid, wi, wo)
                    st.raw = st.raw * f * cosw[:, None]
                    st.counts = st.counts.clone()
                    st.counts[ed, oid[ed]] += 1
                    if rec_p is not None:
                        rec_p["objs"].append(torch.where(ed, oid, -1))
            with clock("sampling"):
                wworld = frame.to_world(wi)
                alive = ok & ((wworld * ng).sum(-1) > 0) & (st.raw.amax(-1) > 0)
                alive &= (st.A_w.abs().amax((-1, -2)) > 0) & (st.B_w.abs().amax((-1, -2)) > 0)
                a = torch.nonzero(alive).squeeze(1)
                origins = scene.spawn(pos[a], ng[a], wworld[a])
            sub = self._trace(origins, wworld[a])
            if v == 1 and self.mis_lights:
                self._emit_found(ent, st, sub, a, pos, wworld, wi, wo, oid, ed, pdf, cosw, paths, rec)
            with clock("bookkeeping"):
                keep = a[sub.hit]
                st, d_in = st.keep(keep), wworld[keep]
                pos, ng, ns, oid = (x[sub.hit] for x in (sub.position, sub.geometric_normal, sub.normal, sub.object_id))
        return emis, ent

    def _start(self, origins, directions, paths, vk=None):
        """The eye rays traced: (emission seen (n, 3), the :class:`PathState` of the rays that hit,
        their arriving directions, positions, both normals and objects; ``vk``: gathered by the
        compiled kernel)."""
        hits = self._trace(origins, directions)
        with self.clock("bookkeeping"):
            emis = emission_seen(self.scene, directions, hits)
            idx = torch.nonzero(hits.hit).squeeze(1)
            if vk is None:
                d_in, pos = directions[idx], hits.position[idx]
                ng, ns, oid = hits.geometric_normal[idx], hits.normal[idx], hits.object_id[idx]
            else:
                d_in, pos, ng, ns, oid = vk.take(
                    idx, directions, hits.position, hits.geometric_normal, hits.normal, hits.object_id
                )
            st = PathState.start(idx, oid.clone(), self.num_objects, paths is not None)
        return emis, st, d_in, pos, ng, ns, oid

    def _vertex_kernel(self):
        """The compiled per-vertex steps (:class:`~.vertex.VertexKernel`), or None: the torch steps
        (no compiler, ``TORCH_BRDF_NATIVE=0``; :meth:`run` also keeps them for float64 rays)."""
        if library() is None:
            return None
        if self._vk is None:
            self._vk = VertexKernel.make(self) or False
        return self._vk or None

    def _wavefront(self, vk):
        """The reused wavefront buffers (:class:`~.vertex.Wavefront`), or None (see its ``make``)."""
        if self._wf is None:
            self._wf = Wavefront.make(vk) or False
        return self._wf or None

    def _run_wavefront(self, wf, origins, directions, rec, gen, ent):
        """:meth:`run` on the reused buffers of ``wf`` (:class:`~.vertex.Wavefront`), the entries
        going to the compiled ``ent``: the steps of :meth:`_run_fused` in the same order on the
        same random numbers (drawn by the kernel from ``gen``'s state, written back at the end),
        so the same tensors bit for bit, with no torch op between the kernel calls of a bounce."""
        nb, clock = self.series.bounces, self.clock
        hits = self._trace(origins, directions)
        with clock("bookkeeping"):
            emis = emission_seen(self.scene, directions, hits)
        with clock("sampling"):
            gs = gen.get_state()  # the kernel draws torch.rand's numbers from these bytes
            n = wf.start(directions, hits)
        try:
            for v in range(1, nb + 1):
                if n == 0:
                    break
                banded = self._banded(v)
                st = wf.state(n, PathState)  # its vertices' frames came with them (start, compact)
                reps = self.eye_light_samples if v == 1 else 1
                for light in [li for li in self.lights for _ in range(reps)]:
                    with clock("sampling"):
                        m = wf.light_sample(light, n, gs)
                    self.rays["shadow"] += m
                    if m == 0:
                        continue
                    with clock("rays"):  # (the clock counts ray time only inside a section)
                        occ = self.occluded(wf.so[:m], wf.sd[:m], wf.tmax[:m])
                    with clock("sampling"):
                        h = wf.light_hits(m, occ, reps, v > 1 and not banded)
                    if h == 0:
                        continue
                    ob, lq = wf.ob[:h], None
                    if v == 1 or banded:
                        level = 1 if v == 1 else 2
                        with clock("brdf"):
                            wf.layers(level, h, ob, wf.wl, wf.wok, wf.lj[level], wf.lq[level])
                        lq = (wf.lj[level][:h], wf.lq[level][:h])
                    with clock("bookkeeping"):
                        self._emit_entries(ent, v, wf.kk[:h], st, wf.lw[:h], rec, ob, lq, wf.ed[:h], wf.lf[:h])
                if v == nb:
                    break
                with clock("sampling"):
                    wf.mixture(n, gs)
                with clock("brdf"):
                    f = None
                    if v == 1 or banded:
                        level, i, w = (1, st.A_i, st.A_w) if v == 1 else (2, st.B_i, st.B_w)
                        wf.layers(level, n, wf.st["oid"], wf.wi, wf.wo, i, w)
                    elif not self.all_editable:
                        f = wf.fixed_f(n)
                with clock("sampling"):
                    m = wf.advance(n, f, v > 1 and not banded)
                sub = self._trace(wf.nso[:m], wf.nsd[:m])
                with clock("sampling"):
                    n = wf.compact(m, sub)
        finally:
            gen.set_state(gs)
        return emis, ent

    def _run_fused(self, vk, origins, directions, rec, gen, paths, ent):
        """:meth:`run` with the per-vertex steps in the compiled kernel: the same steps in the
        same order, drawing the same random numbers (see :mod:`.vertex`)."""
        nb, clock = self.series.bounces, self.clock
        emis, st, d_in, pos, ng, ns, oid = self._start(origins, directions, paths, vk)
        for v in range(1, nb + 1):
            if st.idx.numel() == 0:
                break
            with clock("sampling"):
                ng, ns, fr, wo = vk.frame(d_in, ng, ns)
            reps = self.eye_light_samples if v == 1 else 1
            for light in [li for li in self.lights for _ in range(reps)]:
                with clock("sampling"):
                    d, w, cos, cast, kk = vk.light(light, pos, ng, ns, gen)
                    self.rays["shadow"] += cast
                    if kk.numel() == 0:
                        continue
                    hit = LightHit(kk, *vk.gather(kk, d, w, cos, reps, fr, wo, oid))
                with clock("bookkeeping"):
                    self._emit(ent, st, v, hit, paths, rec, vk)
            if v == nb:
                break
            with clock("sampling"):
                u = torch.rand(st.idx.numel(), 3, generator=gen)
                wi, _, cosw, ok = vk.mixture(u, wo)
            rec_p = st.oracle
            with clock("bookkeeping"):
                f = None
                if v == 1:
                    st.A_i, st.A_w = vk.layers(1, oid, wi, wo)
                    if rec_p is not None:
                        rec_p["wi1"], rec_p["wo1"] = wi.clone(), wo.clone()
                elif self._banded(v):
                    st.B_i, st.B_w = vk.layers(2, oid, wi, wo)
                    if rec_p is not None:
                        rec_p["wi2"], rec_p["wo2"], rec_p["m2"] = wi.clone(), wo.clone(), oid.clone()
                else:
                    f = None if self.all_editable else vk.fixed_f(oid, wi, wo)
                    if rec_p is not None:
                        rec_p["objs"].append(torch.where(self.editable[oid], oid, -1))
            with clock("sampling"):
                counted = v > 1 and not self._banded(v)
                a, so, sd = vk.advance(st, wi, cosw, ok, f, counted, oid, fr, ng, pos)
            sub = self._trace(so, sd)
            with clock("bookkeeping"):
                h = torch.nonzero(sub.hit).squeeze(1)
                st = vk.keep(st, a[h])
                d_in, pos, ng, ns, oid = vk.take(h, sd, sub.position, sub.geometric_normal, sub.normal, sub.object_id)
        return emis, ent

    def _emit(
        self, ent: _Entries, st: PathState, v: int, hit: LightHit, paths: dict | None, rec: torch.Tensor, vk=None
    ):
        """Add the entries of the light samples ``hit`` at vertex ``v`` of the paths ``st``
        (with ``vk``, a :class:`~.vertex.VertexKernel`, its band slots and quotients)."""
        lv1 = self.level1 if vk is None else lambda *a: vk.layers(1, *a)
        lv2 = self.level2 if vk is None else lambda *a: vk.layers(2, *a)
        fixed = self._fixed_f if vk is None else vk.fixed_f
        if getattr(ent, "native", False):
            self._emit_native(ent, st, v, hit, rec, lv1, lv2, fixed)
            if paths is not None:
                extra = None if v == 1 or self._banded(v) else torch.where(hit.ed, hit.ob, -1)
                self._record(paths, st, v, hit, rec, extra)
            return
        kk, wl, wo, ob, ed, lw = hit.kk, hit.wl, hit.wo, hit.ob, hit.ed, hit.lw
        n = kk.numel()
        cnt = st.counts[kk]
        if v == 1:
            j, q = lv1(ob, wl, wo)  # (n, L1), (n, L1, 3)
            w = torch.full_like(j, -1)
            wts = q * lw[:, None, :]
            combos = [(j[:, a], w[:, a], wts[:, a]) for a in range(j.shape[1])]
            extra = None
        elif v == 2 and self.level2 is not None:
            k2, q2 = lv2(ob, wl, wo)
            base = st.raw[kk] * lw
            combos = [
                (st.A_i[kk, a], k2[:, b], base * st.A_w[kk, a] * q2[:, b])
                for a in range(st.A_i.shape[1])
                for b in range(k2.shape[1])
            ]
            extra = None
        else:
            f = self._diffuse_f(ob, ed, wl, wo, fixed)
            scale = self.pi_powers[cnt.sum(-1)]  # 1/pi of earlier D vertices
            cnt = cnt.clone()
            cnt[ed, ob[ed]] += 1
            base = st.raw[kk] * lw * f * scale[:, None]
            combos = [
                (st.A_i[kk, a], st.B_i[kk, b], base * st.A_w[kk, a] * st.B_w[kk, b])
                for a in range(st.A_i.shape[1])
                for b in range(st.B_i.shape[1])
            ]
            extra = torch.where(ed, ob, -1)
        bounce = torch.full((n,), v, dtype=torch.long)
        for j, w, wt in combos:
            ent.add(rec[st.idx[kk]], st.m1[kk], bounce, j, w, cnt, wt)
        if paths is not None:
            self._record(paths, st, v, hit, rec, extra)

    def _emit_found(self, ent, st, sub, a, pos, wworld, wi, wo, oid, ed, pdf, cosw, paths, rec):
        """Eye-vertex entries of what the mixture's samples ``wi`` of the paths ``a`` find on
        the lights (``sub``: their hits), on the objects of a :class:`LobeMixture` with
        ``mis``, weighted by the power heuristic against next-event estimation (which the
        light loop weights the other way): light radiance times cos / pdf, the band of
        (``wi``, ``wo``) as for a light sample."""
        with self.clock("sampling"):
            le, pdf_l = emission_and_light_pdf(self.scene, pos[a], wworld[a], sub)
            # only the lights next-event estimation samples as they are (not an environment
            # replaced by its median-cut point lights, which NEE alone reaches)
            env = self.scene.environment
            if env is not None and id(env) not in self.mis_lights:
                le[~sub.hit] = 0.0
            for o, light in self.scene.area_lights.items():
                if id(light) not in self.mis_lights:
                    le[sub.object_id == o] = 0.0
            reps = self.eye_light_samples
            w_m = power_heuristic(pdf[a], reps * pdf_l)
            rows = torch.nonzero(torch.isin(oid[a], self.mis_ids) & (le.amax(-1) > 0) & (w_m > 0)).squeeze(1)
            if rows.numel() == 0:
                return
            kk = a[rows]
            lw = le[rows] * (w_m[rows] * cosw[kk])[:, None]
            hit = LightHit(kk, wi[kk], wo[kk], oid[kk], ed[kk], lw)
        with self.clock("bookkeeping"):
            # the eye vertex's entries take no path throughput (raw is 1 before the vertex)
            self._emit(ent, replace(st, raw=torch.ones_like(st.raw)), 1, hit, paths, rec)

    def _banded(self, v: int) -> bool:
        """Vertex ``v`` > 1 uses the second-bounce band basis (else a diffuse equivalent)."""
        return v == 2 and self.level2 is not None

    def _diffuse_f(self, ob, ed, wl, wo, fixed=None) -> torch.Tensor:
        """(n, 3) factor of a diffuse-equivalent vertex: D = cos/pi for editable objects (the
        cosine is in the light weight), the full BRDF of fixed ones (``fixed``: its function,
        default :meth:`_fixed_f`)."""
        return torch.where(ed[:, None], torch.full((1, 3), 1.0 / math.pi), (fixed or self._fixed_f)(ob, wl, wo))

    def _emit_native(
        self, ent, st: PathState, v: int, hit: LightHit, rec: torch.Tensor, lv1=None, lv2=None, fixed=None
    ):
        """:meth:`_emit` in the compiled kernel (:class:`~.reduce.NativeEntries`): the same
        entries in the same order, made without torch ops per layer combination."""
        wl, wo, ob, ed = hit.wl, hit.wo, hit.ob, hit.ed
        lq = f = None
        if v == 1:
            lq = (lv1 or self.level1)(ob, wl, wo)
        elif self._banded(v):
            lq = (lv2 or self.level2)(ob, wl, wo)
        else:
            f = self._diffuse_f(ob, ed, wl, wo, fixed)
        self._emit_entries(ent, v, hit.kk, st, hit.lw, rec, ob, lq, ed, f)

    def _emit_entries(self, ent, v: int, kk, st: PathState, lw, rec, ob, lq=None, ed=None, f=None):
        """The compiled entries (``ent.emit``) of the light samples ``kk`` reaching vertex ``v``:
        ``lq`` the band slots and quotients of their directions at the first vertex or a banded
        one, else ``ed`` (editable flags) and ``f`` (the diffuse-equivalent factor)."""
        common = (v, kk, st, lw, rec, ob)
        if v == 1:
            ent.emit(*common, None, None, None, lq, False, None, False)
        elif self._banded(v):
            ent.emit(*common, None, None, None, (st.A_i, st.A_w), True, lq, False)
        else:
            ent.emit(*common, ed, f, self.pi_powers, (st.A_i, st.A_w), True, (st.B_i, st.B_w), True)

    def _record(self, paths: dict, st: PathState, v: int, hit: LightHit, rec: torch.Tensor, extra):
        """Raw path data for the exactness oracle (tests)."""
        kk, wl, wo, ob = hit.kk, hit.wl, hit.wo, hit.ob
        n = kk.numel()
        fixed_f = (
            torch.where(self.editable[ob][:, None], torch.ones(1, 3), self._fixed_f(ob, wl, wo))
            if v > 1 and not (v == 2 and self.level2 is not None)
            else torch.ones(n, 3)
        )
        row = {
            "rec": rec[st.idx[kk]],
            "m1": st.m1[kk],
            "bounce": torch.full((n,), v),
            "raw": st.raw[kk] * hit.lw * fixed_f,
            "wl": wl,
            "wo": wo,
            "ob": ob,
        }
        rec_p = st.oracle
        for key in ("wi1", "wo1", "wi2", "wo2", "m2"):
            row[key] = None if rec_p[key] is None else rec_p[key][kk]
        objs = [t[kk] for t in rec_p["objs"]]
        if extra is not None:
            objs.append(extra)
        row["objs"] = torch.stack(objs, -1) if objs else torch.zeros(n, 0, dtype=torch.long)
        paths.setdefault("rows", []).append(row)
