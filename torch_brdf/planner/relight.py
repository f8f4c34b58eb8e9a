r"""The error-budget planner of all-frequency relighting: cubemap resolution,
graded-visibility bits (and supersampling) and the BRDF-sampling rule for a PSNR target.

The error is :math:`e = \mathrm{RMSE} / \mathrm{peak}` of the per-vertex radiance of the
vertices the camera sees, against the *converged* relighting: the dense (standard-basis)
triple product at the reference resolution with finely supersampled, 8-bit graded visibility;
peak is the reference's maximum. PSNR is :math:`-20 \log_{10} e`. It is measured, not
modelled: the pilots (:func:`torch_brdf.planner.relight_pilots.plan_relighting`, which runs
them with the renderer) shade a random sample of the seen vertices with
every candidate (resolution, visibility, rule) and the reference, and give here, per
candidate, the RMSE over the sample; the peak comes from the reference on the sample plus
the brightest vertices of a cheap full-view pass (a highlight on few vertices sets it).

Cost: the precomputation (visibility rays of every scene vertex, from the pilots' seconds per
vertex) plus ``frames`` frames (from the pilots' shading seconds, scaled to the seen vertices):
relighting is interactive, so a plan is priced for a session of ``frames`` frames.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from ..errors import ValueRangeError
from .table import Option, Plan, choose

__all__ = ["RelightPilot", "error_from_psnr", "plan_from_relight_pilots"]


def error_from_psnr(psnr: float) -> float:
    """RMSE / peak for a PSNR in dB."""
    return 10.0 ** (-float(psnr) / 20.0)


@dataclass(frozen=True)
class RelightPilot:
    """What the pilots measured for one candidate.

    Attributes:
        resolution: cubemap texels per face side.
        supersample: k (1: binary maps).
        bits: graded-visibility bits (0: binary).
        rule: name of the BRDF-sampling rule (see :data:`torch_brdf.planner.relight_pilots.RULES`).
        sq_error: the mean over the sampled vertices and channels of the squared error
            against the reference (RMSE^2, not yet divided by the peak).
        precompute_seconds: predicted seconds of the visibility of every scene vertex.
        frame_seconds: predicted seconds of one frame of the seen vertices.
        bytes_per_vertex: visibility bytes per vertex (the pilots' mean).
    """

    resolution: int
    supersample: int
    bits: int
    rule: str
    sq_error: float
    precompute_seconds: float
    frame_seconds: float
    bytes_per_vertex: float


def plan_from_relight_pilots(
    pilots: Sequence[RelightPilot],
    peak: float,
    error: float | None = None,
    seconds: float | None = None,
    frames: int = 100,
    pilot_seconds: float = 0.0,
) -> Plan:
    """The cheapest candidate whose measured RMSE / ``peak`` is within ``error`` (see the module).

    Args:
        pilots: one entry per candidate.
        peak: the reference's maximum radiance over the seen vertices (the PSNR's peak).
        error: budget on RMSE / peak (``error_from_psnr(psnr)`` for a PSNR); seconds: budget on
            precompute + ``frames`` frames.
        frames: frames the session is priced for.
        pilot_seconds: what the pilots took (printed).
    Returns:
        :class:`~torch_brdf.planner.table.Plan` (printed in PSNR as well) with settings
        ``cubemap``, ``supersample``, ``bits``, ``rule``.
    """
    if not peak > 0 or not math.isfinite(peak):
        raise ValueRangeError(f"peak must be a positive finite radiance; got {peak}")
    if frames < 1:
        raise ValueRangeError(f"frames must be >= 1; got {frames}")
    options = []
    for p in pilots:
        settings = (("cubemap", p.resolution), ("supersample", p.supersample), ("bits", p.bits), ("rule", p.rule))
        costs = (
            ("precompute", p.precompute_seconds),
            ("frame", p.frame_seconds),
            ("bytes_per_vertex", p.bytes_per_vertex),
        )
        secs = p.precompute_seconds + frames * p.frame_seconds
        options.append(Option(settings, math.sqrt(max(p.sq_error, 0.0)) / peak, secs, costs=costs))
    return Plan(
        capability="relighting",
        metric=f"RMSE / peak of the seen vertices' radiance; cost = precompute + {frames} frames",
        error=error,
        seconds=seconds,
        chosen=choose(options, error, seconds),
        options=tuple(options),
        pilot_seconds=pilot_seconds,
        psnr=True,
    )
