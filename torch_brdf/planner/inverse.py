r"""The error-budget planner of inverse BRDF design: light samples S, SRBF count J
(hemicube resolution n, :math:`J = 3n^2`) and the visibility-cut tolerance for a fit-error target.

The error is the relative RMSE, over the object's pixels, of the *design image* (the fitted
coefficients applied to the record the fit was made on) against the design of the converged
precomputation: the dense sum over many light samples with the richest candidate basis. It
splits into three parts that add in quadrature,

.. math:: e^2 = e_J^2 + \sigma_J^2 / S + e_t^2,

all measured by cheap pilots on a random subset of the pixels (``pilot_pixels``) at a small
sample count (``pilot_samples``):

* **basis** :math:`e_J`: the design fitted with :math:`J` lobes against the design fitted with
  the largest candidate, both on the same pilot samples;
* **noise** :math:`\sigma_J / \sqrt S`: K independent pilot sample sets give K designs;
  :math:`\sigma_J^2 = S_p \sum_k \|B_k - \bar B\|^2 / (K - 1) / \|B\|^2` (the fit included, so
  the noise is the design's, not the record's);
* **cuts** :math:`e_t`: the design fitted on the cut record (tolerance :math:`t`) against the one
  fitted on the dense record of the same samples.

Cost: visibility rays and transfer sums both scale with pixels x samples (the transfer also with
J; cuts divide it by the measured speed-up), plus the fit; the rates are the pilots'.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import replace

import torch

from ..brdf.srbf import SRBFBasis
from ..errors import ValueRangeError
from ..inverse.energy import energy_rows
from ..inverse.solve import fit
from ..inverse.strokes import StrokeTarget
from ..inverse.transfer import CutOptions, cosine_visibility, transfer_functions
from ..records.basis_image import BasisImage
from ..scene.gbuffer import GBuffer
from ..scene.lights import LightSamples
from ..scene.scene import Scene
from .table import Option, Plan, choose

__all__ = ["design_image", "plan_inverse", "subset_target"]

_BASES: dict[int, SRBFBasis] = {}


def _basis(n: int) -> SRBFBasis:
    """The hemicube SRBF basis of resolution ``n`` (J = 3 n^2), built once per process."""
    if n not in _BASES:
        _BASES[n] = SRBFBasis(n=n)
    return _BASES[n]


def subset_target(target: StrokeTarget, rows: torch.Tensor) -> StrokeTarget:
    """``target`` restricted to the pixel rows ``rows`` ((P',) long)."""
    return StrokeTarget(target.target[rows], target.weight[rows], target.painted[rows])


def design_image(record: BasisImage, target: StrokeTarget, n: int, kd) -> torch.Tensor:
    """(P, 3) the design: the constrained fit of ``target`` on ``record`` (basis of resolution
    ``n``), applied to ``record``."""
    basis = _basis(n)
    res = fit(record, target, kd=kd, basis=basis, energy=energy_rows(basis))
    return record.pixel_values(torch.cat((res.coefficients, res.kd[None]), 0))


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp_min(1e-300))


def plan_inverse(
    scene: Scene,
    px: GBuffer,
    environment,
    target: StrokeTarget,
    error: float | None = 0.05,
    seconds: float | None = None,
    kd=0.3,
    f0=0.9,
    light_samples: Sequence[int] = (128, 256, 512, 1024, 2048, 4096),
    hemicube: Sequence[int] = (5, 7),
    tolerances: Sequence[float] = (0.0, 0.1, 0.2),
    pilot_samples: int = 128,
    pilot_sets: int = 3,
    pilot_pixels: int = 1024,
    generator: torch.Generator | None = None,
) -> Plan:
    """Plan the precomputation and fit of an inverse design for a relative-RMSE ``error`` (see the module).

    Args:
        scene: the scene (its tracer casts the visibility rays).
        px: the object's pixels (:func:`~torch_brdf.inverse.object_pixels`).
        environment: the lighting the light samples come from.
        target: the painted target over ``px``'s pixels.
        error: budget on the design image's relative RMSE; seconds: budget on precompute + fit.
        kd: diffuse albedo of the design.
        f0: Schlick F0 of the design.
        light_samples: candidate S (powers of two: cuts need them).
        hemicube: candidate hemicube resolutions n (J = 3 n^2); the largest is the reference.
        tolerances: candidate cut tolerances (0: dense, no cuts).
        pilot_samples: S of each pilot sample set (a power of two).
        pilot_sets: independent pilot sample sets (>= 2; their spread gives the noise).
        pilot_pixels: pixels of the pilot subset (all when fewer).
        generator: seeds the pilots' pixel subset and light samples.
    Returns:
        :class:`~torch_brdf.planner.table.Plan` with settings ``light_samples``, ``J``,
        ``hemicube``, ``cut_tolerance``.
    """
    if pilot_sets < 2:
        raise ValueRangeError(f"the noise needs at least two pilot sample sets; got {pilot_sets}")
    if pilot_samples & (pilot_samples - 1) or any(s & (s - 1) for s in light_samples):
        raise ValueRangeError(f"light sample counts must be powers of two; got {pilot_samples}, {list(light_samples)}")
    g = generator if generator is not None else torch.Generator().manual_seed(0)
    t_start = time.perf_counter()
    P = px.count
    rows = torch.randperm(P, generator=g)[: min(P, pilot_pixels)].sort().values
    sub, tgt = px.select(rows), subset_target(target, rows)
    n_ref = max(hemicube)
    designs: dict[tuple[int, int], torch.Tensor] = {}
    records: dict[tuple[int, int], BasisImage] = {}
    t_vis = 0.0
    samples = []
    for k in range(pilot_sets):
        ls = LightSamples.from_environment(environment, pilot_samples, g)
        t0 = time.perf_counter()
        vis = cosine_visibility(scene, sub, ls)
        t_vis += time.perf_counter() - t0
        samples.append((ls, vis))
        for n in hemicube:
            records[(k, n)] = transfer_functions(sub, ls, vis, basis=_basis(n), f0=f0)
    t0 = time.perf_counter()
    for n in hemicube:
        for k in range(pilot_sets):
            designs[(k, n)] = design_image(records[(k, n)], tgt, n, kd)
    t_fit = (time.perf_counter() - t0) / (pilot_sets * len(hemicube)) * (P / sub.count)
    # the fit on the mean of the sets (K S_p samples) for the basis error; the noise from the
    # spread of the K designs: sigma^2 = S_p sum_k |B_k - mean|^2 / (K - 1) / |B|^2
    mean = {
        n: design_image(
            replace(records[(0, n)], values=sum(records[(k, n)].values for k in range(pilot_sets)) / pilot_sets),
            tgt,
            n,
            kd,
        )
        for n in hemicube
    }
    norm = mean[n_ref]
    basis_err = {n: _rel(mean[n], norm) for n in hemicube}
    sigma = {}
    for n in hemicube:
        d = torch.stack([designs[(k, n)] for k in range(pilot_sets)])
        spread = float(((d - d.mean(0)) ** 2).sum()) / (pilot_sets - 1)
        sigma[n] = math.sqrt(spread * pilot_samples) / float(norm.norm())
    # per-basis transfer rate (seconds per pixel-sample), from the first pilot's dense records
    rate_rec = {n: float(records[(0, n)].meta["seconds"]) / (sub.count * pilot_samples) for n in hemicube}
    rate_vis = t_vis / (pilot_sets * sub.count * pilot_samples)
    # cut error and speed-up at each tolerance, with the reference basis on the first sample set
    cut_err, cut_speed = {0.0: 0.0}, {0.0: 1.0}
    ls0, vis0 = samples[0]
    for tol in tolerances:
        if tol == 0:
            continue
        rec = transfer_functions(sub, ls0, vis0, basis=_basis(n_ref), f0=f0, cuts=CutOptions(tolerance=tol))
        cut_err[tol] = _rel(design_image(rec, tgt, n_ref, kd), designs[(0, n_ref)])
        cut_speed[tol] = float(records[(0, n_ref)].meta["seconds"]) / max(float(rec.meta["seconds"]), 1e-9)
    options = []
    for S in light_samples:
        for n in hemicube:
            for tol in tolerances:
                parts = (("basis", basis_err[n]), ("noise", sigma[n] / math.sqrt(S)), ("cuts", cut_err[tol]))
                e = math.sqrt(sum(v * v for _, v in parts))
                secs = P * S * (rate_vis + rate_rec[n] / cut_speed[tol]) + t_fit
                settings = (("light_samples", S), ("J", 3 * n * n), ("hemicube", n), ("cut_tolerance", tol))
                options.append(Option(settings, e, secs, parts))
    chosen = choose(options, error, seconds)
    return Plan(
        capability="inverse design",
        metric="relative RMSE of the design image",
        error=error,
        seconds=seconds,
        chosen=chosen,
        options=tuple(options),
        pilot_seconds=time.perf_counter() - t_start,
    )
