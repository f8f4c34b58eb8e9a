"""What the capability planners share: a table of candidate settings with their predicted error
and cost (from pilot measurements), the choice for an error and/or time budget, and its print.

Every planner of :mod:`torch_brdf.planner` except the GI one (which has its own
:class:`~torch_brdf.planner.gi.GIPlan`) returns a :class:`Plan`: ``print(plan)`` shows the
chosen settings with their predicted cost and error, and the other candidates the pilots
priced, so the user sees the trade and not only the answer.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from ..errors import ValueRangeError

__all__ = ["Option", "Plan", "choose", "pareto", "power_law"]


@dataclass(frozen=True)
class Option:
    """One candidate setting and what the pilots predict for it.

    Attributes:
        settings: ((name, value), ...) in the order they are printed.
        predicted_error: the planner's error measure (lower is better; see :attr:`Plan.metric`).
        predicted_seconds: predicted cost of carrying the settings out.
        parts: ((name, error), ...) the error's components where the planner splits it.
        costs: ((name, value), ...) the cost's components, printed with it (e.g. precompute
            and frame seconds, bytes).
        interval: (low, high) of the predicted error where the planner measures its spread
            (e.g. a bootstrap interval over materials), printed with it; None: not measured.
    """

    settings: tuple[tuple[str, Any], ...]
    predicted_error: float
    predicted_seconds: float
    parts: tuple[tuple[str, float], ...] = ()
    costs: tuple[tuple[str, float], ...] = ()
    interval: tuple[float, float] | None = None

    def as_dict(self) -> dict[str, Any]:
        """The settings as a dict."""
        return dict(self.settings)

    def describe(self) -> str:
        def show(v: Any) -> str:
            return f"{v:g}" if isinstance(v, float) else f"[{len(v)} names]" if isinstance(v, tuple) else str(v)

        return ", ".join(f"{k} {show(v)}" for k, v in self.settings)


def choose(options: Sequence[Option], error: float | None, seconds: float | None) -> Option:
    """The cheapest option whose predicted error is <= ``error`` (and cost <= ``seconds``).

    With only ``seconds``: the most accurate option within it. When no option meets both
    budgets: the most accurate option within the time (or, if none is, the cheapest overall).
    """
    if error is None and seconds is None:
        raise ValueRangeError("plan for an error, a time or both; got neither")
    if error is not None and not error > 0:
        raise ValueRangeError(f"error must be > 0; got {error}")
    if not options:
        raise ValueRangeError("no candidate settings to choose from")
    in_time = [o for o in options if seconds is None or o.predicted_seconds <= seconds]
    if error is not None:
        ok = [o for o in in_time if o.predicted_error <= error]
        if ok:
            return min(ok, key=lambda o: (o.predicted_seconds, o.predicted_error))
    if in_time:
        return min(in_time, key=lambda o: (o.predicted_error, o.predicted_seconds))
    return min(options, key=lambda o: (o.predicted_seconds, o.predicted_error))


def power_law(x: Sequence[float], y: Sequence[float]) -> tuple[float, float]:
    r"""Least-squares fit of :math:`y = a x^{-p}` in log-log (``y > 0``, at least two distinct x).

    Returns:
        (a, p).
    """
    lx = torch.log(torch.as_tensor(x, dtype=torch.float64))
    ly = torch.log(torch.as_tensor(y, dtype=torch.float64).clamp_min(1e-300))
    if len(lx) < 2 or float(lx.max() - lx.min()) == 0:
        raise ValueRangeError(f"a power law needs two distinct x; got {list(x)}")
    A = torch.stack((torch.ones_like(lx), -lx), 1)
    sol = torch.linalg.lstsq(A, ly[:, None]).solution[:, 0]
    return math.exp(float(sol[0])), float(sol[1])


def pareto(options: Sequence[Option]) -> list[Option]:
    """The options no other option beats in both cost and error, cheapest first."""
    out: list[Option] = []
    for o in sorted(options, key=lambda o: (o.predicted_seconds, o.predicted_error)):
        if not out or o.predicted_error < out[-1].predicted_error:
            out.append(o)
    return out


@dataclass(frozen=True)
class Plan:
    """A capability's plan: the chosen :class:`Option` among the candidates the pilots priced.

    Attributes:
        capability: e.g. ``"inverse design"``.
        metric: what ``error`` measures (e.g. ``"relative RMSE of the design image"``).
        error, seconds: the requested budgets (None: not given).
        chosen: the chosen option; options: every priced candidate.
        pilot_seconds: what the pilot measurements cost.
        psnr: the error is RMSE / peak, printed as PSNR (dB) as well.
    """

    capability: str
    metric: str
    error: float | None
    seconds: float | None
    chosen: Option
    options: tuple[Option, ...]
    pilot_seconds: float
    psnr: bool = False

    @property
    def settings(self) -> dict[str, Any]:
        return self.chosen.as_dict()

    @property
    def predicted_error(self) -> float:
        return self.chosen.predicted_error

    @property
    def predicted_seconds(self) -> float:
        return self.chosen.predicted_seconds

    def for_budget(self, error: float | None = None, seconds: float | None = None) -> Plan:
        """The same candidates chosen for another budget (no new pilots)."""
        return dataclasses.replace(self, error=error, seconds=seconds, chosen=choose(self.options, error, seconds))

    def _err(self, e: float) -> str:
        return f"{e:.4g}" + (f" ({-20 * math.log10(max(e, 1e-300)):.2f} dB)" if self.psnr else "")

    def __str__(self) -> str:
        want = [] if self.error is None else [f"error {self._err(self.error)}"]
        want += [] if self.seconds is None else [f"time {self.seconds:g} s"]
        c = self.chosen
        lines = [
            f"{self.capability} plan for {' and '.join(want)}: {c.describe()}",
            f"  predicted error {self._err(c.predicted_error)} ({self.metric})"
            + (" = sqrt(" + " + ".join(f"{k} {v:.4g}^2" for k, v in c.parts) + ")" if c.parts else "")
            + (f"; interval {self._err(c.interval[0])} to {self._err(c.interval[1])}" if c.interval else ""),
            f"  predicted cost {c.predicted_seconds:.3g} s"
            + "".join(f", {k} {v:.3g}" for k, v in c.costs)
            + f" (pilots {self.pilot_seconds:.3g} s)",
            "  the other candidates on the cost/error front:",
        ]
        for o in pareto(self.options):
            mark = "*" if o is c else " "
            lines.append(f"  {mark} {o.describe()}: error {self._err(o.predicted_error)}, {o.predicted_seconds:.3g} s")
        return "\n".join(lines)
