r"""The compiled relighting frame: :meth:`TripleProductRenderer.shade` in C (``csrc/relight.c``).

The kernel runs Algorithm 1 of Inger et al. per vertex with the same rule, samples, block cases
and lighting as :meth:`~torch_brdf.render.triple.TripleProductRenderer.shade_torch` (the
reference), on vertex ranges spread over threads (ctypes releases the GIL, so Python threads run
the C code in parallel). It folds each BRDF projection into the lighting, once per lighting
change: with :math:`A = R_l f` the coefficients of the samples :math:`f` (:math:`R_l` the
precomputed inverse of Eq. 4),

.. math:: \sum_k A_k\,(n\cdot D_k) = \sum_s f_s\,\Big(n\cdot \sum_k R_{l,ks} D_k\Big)
          = \sum_s f_s\,(n \cdot G_{l,s}),

and on texels :math:`f_t = \sum_s f_s W_{l,st}` with :math:`W_l = R_l^T B_l`. The same sums in
another order: the frame agrees with the torch path to float32 rounding, not bit for bit.

Supported: float32 renderers, 3 channels, every object Lambert or Phong (the Appendix A rule's
models), rule :class:`~torch_brdf.render.triple.PhongRule` or
:class:`~torch_brdf.render.triple.FixedRule`. :func:`unsupported` names what is not; then the
torch path runs.
"""

from __future__ import annotations

import ctypes
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import torch
from tqdm.auto import tqdm

from ..brdf.analytic import Phong
from ..brdf.base import Lambert
from ..data import progress_default
from ..records.visibility_codec import BlockVisibility
from ..sphere.cubemap import CubemapBlocks
from ..sphere.dct import LOW, dct_basis, low_indices, sample_positions, subsampled_inverse
from ..transport import _native

__all__ = ["STAT_KEYS", "NativeLighting", "level_table", "phong_lobe", "shade", "unsupported"]

#: the kernel's counters, in order
STAT_KEYS = ("occluded", "line6", "line9", "line11", "1", "4", "16", "256", "brdf_evals", "visibility_entries")
#: vertices per kernel call: enough to amortise a call, small enough to balance the threads
CHUNK = 1024
_pools: dict[int, ThreadPoolExecutor] = {}


def phong_lobe(omc: torch.Tensor, exponent: float) -> torch.Tensor:
    r"""The kernel's Phong lobe :math:`\cos^n\alpha = \exp(n\,\mathrm{log1p}(-omc))` (0 where
    ``omc >= 1``), its own log and exp polynomials (for tests).

    Args:
        omc: (N,) :math:`1 - \cos\alpha`.
        exponent: n.
    Returns:
        (N,) float32.
    """
    lib = _native.library()
    if lib is None:
        raise RuntimeError("the compiled kernel is not available")
    x = omc.to(torch.float32).contiguous()
    out = torch.empty_like(x)
    lib.tb_phong_lobe(x.numel(), x.data_ptr(), float(exponent), out.data_ptr())
    return out


def _rule_kind(rule) -> str | None:
    """``"phong"`` or ``"fixed"`` for the rules the kernel has: the class's own ``native_kind``
    (a subclass, which may override ``project``, does not inherit it)."""
    return type(rule).__dict__.get("native_kind")


def unsupported(renderer, rule) -> str | None:
    """Why the compiled frame cannot shade with ``rule`` (None when it can)."""
    if _native.library() is None:
        return "no compiled kernel"
    if renderer.dtype != torch.float32:
        return f"dtype {renderer.dtype} (the kernel computes in float32)"
    if renderer.lighting.texels.shape[-1] != 3:
        return "not 3 colour channels"
    if renderer.geometry.block != 16:
        return "blocks other than 16 x 16"
    if _rule_kind(rule) is None:
        return f"rule {type(rule).__name__} (the kernel has PhongRule and FixedRule)"
    for b in renderer.brdfs:
        if type(b) not in (Lambert, Phong) or (isinstance(b, Phong) and b.exponent.numel() != 1):
            return f"BRDF {type(b).__name__} (the kernel has Lambert and Phong)"
    return None


def level_table(renderer, rule) -> tuple[torch.Tensor, float, float]:
    """Per object the levels (samples a side) near, mid and far, and the rule's two angles.

    The Appendix A rule (:class:`~torch_brdf.render.triple.PhongRule`) as a table: the level
    depends on the angle between the view direction and the reflected block centre only through
    the two angles, and on the object through its exponent.

    Returns:
        (O, 3) int32 levels, a0, a1 (radians).
    """
    rows = []
    if _rule_kind(rule) == "fixed":
        return torch.full((len(renderer.brdfs), 3), rule.level, dtype=torch.int32), 0.0, 0.0
    geom = renderer.geometry
    scale = rule.scale
    if scale is None:
        scale = geom.angular_radius / _reference_radius(geom.block)
    a0, a1 = (min(a * scale, math.pi) for a in rule.angles)
    for b in renderer.brdfs:
        if isinstance(b, Lambert) or float(b.ks.detach().max()) == 0.0:
            rows.append((1, 1, 1))
            continue
        s = float(b.exponent.detach().max())
        rows.append((2, 2, 1) if s < rule.cuts[0] else (4, 2, 1) if s < rule.cuts[1] else (16, 4, 1))
    return torch.tensor(rows, dtype=torch.int32), a0, a1


@lru_cache(maxsize=4)
def _reference_radius(block: int) -> float:
    """The angular radius of a block of a 64x64x6 map (the rule's reference, as PhongRule's)."""
    return CubemapBlocks(64, block).angular_radius


def _brdf_params(brdfs) -> torch.Tensor:
    """(O, 8) float32: kd (Lambert: its reflectance), ks, exponent, 1 for Phong else 0."""
    rows = []
    for b in brdfs:
        with torch.no_grad():
            if isinstance(b, Lambert):
                rows.append([*b.reflectance.float().tolist(), 0.0, 0.0, 0.0, 0.0, 0.0])
            else:
                n = float(b._n(torch.float32).reshape(-1)[0])
                rows.append([*b.kd.float().tolist(), *b.ks.float().tolist(), n, 1.0])
    return torch.tensor(rows, dtype=torch.float32)


@dataclass(frozen=True)
class NativeLighting:
    r"""The block lighting as the kernel reads it (recomputed when the lighting changes).

    Attributes:
        G: per level l in (1, 2, 4) the (NB, l^2, 3, C) lighting per sample, ``R_l^T D_l``.
        M: (NB, 3, C, 256) the moments, texels last.
        I: (NB, 256, 3, C) suffix sums (line 9).
        J: per level l in (2, 4) the (NB, 256, l^2, 3, C) suffix sums over texels of
            :math:`W_{l,st} M_t`, with :math:`W_l = R_l^T B_l` taking samples to texels (line 11:
            :math:`\sum_t V_t f_t M_t = \sum_e v_e \sum_s f_s J_{l, t_e s}` over the flips).
    """

    G: tuple[torch.Tensor, ...]
    M: torch.Tensor
    I: torch.Tensor
    J: tuple[torch.Tensor, ...]

    @classmethod
    def of(cls, lighting, block: int) -> NativeLighting:
        """From a :class:`~torch_brdf.render.triple.BlockLighting` (float64 products, then float32)."""
        dct, moments = lighting.dct.double(), lighting.moments.double()
        G, J = [], []
        for l in (1, 2, 4):
            R = subsampled_inverse(l, block)  # (k, s) float64
            G.append(torch.einsum("ks,bkjc->bsjc", R, dct[:, low_indices(l, LOW)]).float().contiguous())
            if l > 1:
                W = R.T @ dct_basis(block, l)  # (s, t)
                WM = torch.einsum("st,btjc->btsjc", W, moments)
                J.append(WM.flip(1).cumsum(1).flip(1).float().contiguous())
        M = lighting.moments.float().permute(0, 2, 3, 1).contiguous()
        return cls(tuple(G), M, lighting.integral.float().contiguous(), tuple(J))


def _points(geom: CubemapBlocks) -> tuple[torch.Tensor, ...]:
    """(NB, l^2, 3) float32 sample directions for l = 1, 2, 4, 16, as the torch sampler's."""
    return tuple(geom.block_points(sample_positions(l, geom.block), torch.float32).contiguous() for l in (1, 2, 4, 16))


def _pool(threads: int) -> ThreadPoolExecutor:
    if threads not in _pools:
        _pools[threads] = ThreadPoolExecutor(threads, thread_name_prefix="torch_brdf-relight")
    return _pools[threads]


def _array(ptrs) -> ctypes.Array:
    return (ctypes.c_void_p * len(ptrs))(*ptrs)


def shade(
    renderer, view, rule, threads: int, frames=None, progress: bool | None = None
) -> tuple[torch.Tensor, dict[str, int]]:
    """Per-vertex radiance of ``view`` by the kernel.

    Args:
        renderer: a :class:`~torch_brdf.render.triple.TripleProductRenderer` that
            :func:`unsupported` accepts with ``rule``.
        view: the vertices to shade.
        rule: :class:`PhongRule` or :class:`FixedRule`.
        threads: threads the vertex ranges are spread over.
        frames: ``renderer._frames(view)`` if already computed.
        progress: tqdm bar over the ranges of :data:`CHUNK` vertices (None: on in a terminal or
            notebook).
    Returns:
        (P, 3) float32 radiance and the counters (:data:`STAT_KEYS`).
    """
    lib = _native.library()
    geom = renderer.geometry
    cache = renderer.__dict__.setdefault("_native_cache", {})
    if cache.get("lighting") is not renderer.lighting:
        cache["lighting"], cache["arrays"] = renderer.lighting, NativeLighting.of(renderer.lighting, geom.block)
    if "points" not in cache:
        cache["points"] = _points(geom)
    lit: NativeLighting = cache["arrays"]
    if frames is not None or cache.get("view") is not view:  # a view's frames, kept until it changes
        nrm, fr, wo, oid = frames if frames is not None else renderer._frames(view)
        f32 = [x.to(torch.float32).contiguous() for x in (nrm, fr.s, fr.t, fr.n, wo)]
        cache["view"], cache["frames"] = view, (f32, oid.to(torch.int32).contiguous())
    f32, obj = cache["frames"]
    prm = _brdf_params(renderer.brdfs)
    lv, a0, a1 = level_table(renderer, rule)
    blocks: BlockVisibility = view.blocks
    states, offsets, index = blocks.states.contiguous(), blocks.offsets.contiguous(), blocks.index.contiguous()
    delta = blocks.delta.contiguous() if blocks.bits else None
    levels = float(blocks.levels) if blocks.bits else 1.0
    P, NB = states.shape
    out = torch.zeros(P, 3, dtype=torch.float32)
    pts = _array([p.data_ptr() for p in cache["points"]])
    G = _array([g.data_ptr() for g in lit.G])
    J = _array([j.data_ptr() for j in lit.J])
    keep = (f32, obj, prm, lv, states, offsets, index, delta, lit)  # alive until every call returns
    starts = list(range(0, P, CHUNK))
    stats = torch.zeros(len(starts), len(STAT_KEYS), dtype=torch.int64)

    def run(i: int) -> int:
        s = starts[i]
        n = min(P, s + CHUNK) - s
        rows = [x.data_ptr() + 12 * s for x in f32]
        return lib.tb_relight(
            n,
            NB,
            *rows,
            obj.data_ptr() + 4 * s,
            prm.data_ptr(),
            lv.data_ptr(),
            a0,
            a1,
            states.data_ptr() + s * NB,
            offsets.data_ptr() + 8 * s * NB,
            index.data_ptr(),
            None if delta is None else delta.data_ptr(),
            levels,
            pts,
            G,
            lit.M.data_ptr(),
            lit.I.data_ptr(),
            J,
            out.data_ptr() + 12 * s,
            stats[i].data_ptr(),
        )

    serial = threads <= 1 or len(starts) <= 1
    calls = map(run, range(len(starts))) if serial else _pool(threads).map(run, range(len(starts)))
    bar = tqdm(calls, total=len(starts), desc="shade compiled", unit="chunk", disable=not progress_default(progress))
    codes = list(bar)
    del keep
    if any(codes):
        raise MemoryError("the relighting kernel could not allocate its per-call buffers")
    return out, dict(zip(STAT_KEYS, stats.sum(0).tolist(), strict=True))
