r"""The error-budget planner of BRDF editing with global illumination.

Given a relative-RMSE budget :math:`e` (and optionally seconds), choose the settings of
:func:`~torch_brdf.transport.polynomial.precompute_polynomial` that model only what the scene
requires, from cheap measurements:

* **bands** per edited object: the fewest box bands (powers of two) whose cosine-weighted
  projection error (:func:`~torch_brdf.brdf.bands.projection_error`) is below the bands' share
  :math:`0.3e` (a Lambertian material: 1 band, exactly; a glossy lobe: as many as it needs);
* **bounces and spp together**: for each number of bounces :math:`N` the pilots give the tail
  :math:`\|\sum_{k>N} B^k\| / \|B\|` (less what the pilots' own noise adds to it), the
  band error and the noise of the first :math:`N` bounces; the spp that reach the budget with
  :math:`N` bounces follow, and the plan takes the :math:`N` of least cost in ray units
  (:func:`_path_cost` x spp: a shorter series is cheaper per path but leaves the noise less of
  the budget), among those whose tail is at most :math:`0.6e` and never more than the light
  needs: the last bounce whose own light (measured in the pilots, less their noise) exceeds
  :math:`0.1e` (:data:`LAST_BOUNCE_SHARE`);
* **second bounce**: low-frequency bands at the second vertex only where the pilot shows
  glossy-to-glossy transport (bounce-2 energy whose eye and second vertex are both glossy),
  weighted by the diffuse equivalent's projection error, above :math:`0.3e`; its noise is
  then measured with two pilots that have the banded second bounce (the 1-band pilots'
  diffuse equivalent varies far less than the glossy lobe's bands: they under-predicted the
  noise of glossy-to-glossy scenes) and the plan is made again with it
  (:func:`banded_noise_scale`);
* **spp**: from :math:`K \ge 2` independent pilot runs of :math:`s_k` spp (four by default:
  more paths make the estimate steadier where the variance is heavy-tailed, as under a sun),
  the per-pixel variance of one path is the pooled
  :math:`\sigma_i^2 = \sum_k s_k (I_{k,i} - \bar I_i)^2 / (K - 1)` (unbiased; for two pilots
  :math:`(I_a - I_b)^2 / (1/s_a + 1/s_b)`), and the relative noise at a map :math:`n_i` is
  :math:`\sqrt{\sum_i \sigma_i^2 / n_i} / \|\bar I\|`; the noise gets what the biases leave,
  :math:`e_n^2 = (0.95e)^2 - e_b^2 - e_t^2` (the plan aims 5% under the budget: one run's
  error scatters by a few percent around the prediction; adaptive plans aim 10% under, see
  :data:`AIM_ADAPTIVE`);
* **adaptive sampling** (default): the spp map :math:`n_i \propto \sigma_i / \sqrt{c_i}`
  (:func:`allocate_spp`; :math:`c_i` the rays of a path from pixel :math:`i`) is the least-cost
  map for that noise, since relative RMSE weighs every counted pixel alike; pixels the budget
  does not count get ``MIN_SPP``. :math:`\sigma_i` for the allocation is smoothed over a
  window (with a defensive floor), the prediction uses the unsmoothed estimate. Each pixel is
  the average over its own paths, so the record stays unbiased and exactly polynomial;
* **light samples per eye vertex** :math:`k` (splitting, :data:`LIGHT_SAMPLES`): two more pilots
  with :math:`K = 4` samples give the share :math:`B` of a path's variance that the eye vertex's
  next-event estimate makes, :math:`V(k) = A + B/k`; each extra sample costs a path
  :data:`EXTRA_SAMPLE_COST` ray units per light; the plan takes the :math:`k` of least cost (a
  sun-lit scene's noise is almost all direct light: 98% on teatray);
* objects not in ``edit`` are fixed (their full BRDF is baked into the path weights).

The predicted error is :math:`\sqrt{e_b^2 + e_t^2 + e_n^2}` with the band error
:math:`e_b = \sqrt{\sum_m \epsilon_m^2 \|B_m\|^2} / \|B\|` (:math:`B_m`: the image of the paths
whose eye vertex is on object :math:`m`), measured against the converged image of the same
polynomial model (many bounces, many bands, high spp); the approximation of the diffuse
equivalents themselves (Sec. 4.2) is the model, not an error the planner budgets.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from .._checks import check_count
from ..brdf import create
from ..brdf.bands import BandBasis, Factored1D, equivalent_albedo, project, projection_error
from ..brdf.bands.projection import PairQuadrature
from ..errors import SceneError, ValueRangeError
from ..records.polynomial import ObjectBasis, PolynomialTensors, Series
from ..scene.scene import Scene
from ..transport.polynomial import PolynomialSettings, precompute_polynomial, with_fixed

__all__ = [
    "DEFAULT_ERROR",
    "DEFAULT_SECONDS",
    "GIPlan",
    "allocate_spp",
    "check_variance",
    "choose_bands",
    "pilot_images",
    "plan_from_pilots",
    "plan_polynomial",
    "planned_bases",
    "precompute_planned",
    "unlit_mask",
    "with_fixed",
]

#: the shares of the budget given to each deterministic error (the noise gets the rest); the
#: bounce tail may take up to BOUNCE_SHARE, the bounces are then chosen for the least cost
BAND_SHARE = 0.3
BOUNCE_SHARE = 0.6
#: the plan aims its predicted error at this fraction of the budget: one run's achieved error
#: scatters by a few percent around the prediction (pilot noise in sigma, the run's own noise)
AIM = 0.95
#: adaptive plans aim lower: allocating paths from the same noisy pilot variance the noise is
#: predicted with puts too few paths where the estimate came out low (heavy-tailed pixels, e.g.
#: a glossy tray under a sun), and the achieved noise came out 2-8% above the prediction
#: on the benchmark scenes (glossy Cornell box, teatray at 32^2)
AIM_ADAPTIVE = 0.9
SECOND_SHARE = 0.3
#: a bounce whose own light is at most this share of the budget is not one the light needs
LAST_BOUNCE_SHARE = 0.1
MAX_BANDS = 128
#: adaptive sampling: a pixel's noise estimate is averaged over the SMOOTH x SMOOTH window's
#: counted pixels and DEFENSIVE x the image's mean is added (a pilot pixel has few paths and a
#: heavy-tailed variance: allocating from the raw estimate gives too few paths where it came out
#: low, and the achieved noise then exceeds the prediction); spp levels are MIN_SPP * 2^(k/2)
#: (few levels: a steadier allocation; rounding up to the next level costs ~1% against exact spp)
SMOOTH = 7
DEFENSIVE = 0.1
MIN_SPP = 4
LEVELS_PER_OCTAVE = 2
#: the light samples per eye vertex a plan may choose, and what one more costs a path in ray
#: units (a shadow ray is 1; measured on teatray at 32^2: seconds per path grew by ~0.36 of a
#: 2.8-ray path per extra sample, ~1 ray; 1.5 leaves room for the bookkeeping of 32-band entries)
LIGHT_SAMPLES = (1, 2, 4, 8, 16)
EXTRA_SAMPLE_COST = 1.5
#: what :func:`precompute_planned` and ``torch-brdf precompute`` plan for when told nothing: a
#: relative RMSE of 3% against the converged model (edits inherit it) within 10 minutes of
#: precompute (the time budget wins when both cannot be met: the plan then says its error)
DEFAULT_ERROR = 0.03
DEFAULT_SECONDS = 600.0
#: the most paths per pixel (on average) a time budget alone may buy: a generous budget on a small
#: view would otherwise ask for more memory than any machine has
MAX_PLANNED_SPP = 1 << 14


def _quadrature(basis: BandBasis) -> PairQuadrature:
    # coarser than project's default (3 s instead of 17 s per basis on a shared 2-core machine);
    # it reproduces the default's errors to 4 digits for Blinn-Phong n = 100 at J = 1, 16, 64
    return PairQuadrature.build(basis, n_theta_h=48, n_theta_d=4, n_phi_d=8, order=2)


def _basis(material: dict[str, Any], J: int) -> ObjectBasis:
    kind = material.get("type")
    spacing = f"lobe:{float(material.get('exponent', 20.0)):g}" if kind in ("blinn_phong", "phong") else "sqrt"
    return ObjectBasis(J=J, spacing=spacing)


def _error_at(material: dict[str, Any], J: int) -> float:
    basis = _basis(material, J).band_basis()
    brdf = create(material)
    q = _quadrature(basis)
    curve = Factored1D(basis, coefficients=project(brdf, basis, quadrature=q))
    return float(projection_error(brdf, curve, quadrature=q))


def choose_bands(material: dict[str, Any], target: float, max_bands: int = MAX_BANDS) -> tuple[int, float]:
    """The fewest bands (a power of two, at most ``max_bands``) whose projection error is <= ``target``.

    Lambertian materials take 1 band with error 0 without a measurement. Otherwise J = 1 is
    measured, then J is doubled until the error is below ``target`` (box bands converge about
    as 1/J, so the search starts near the J that a 1/J law predicts from J = 1).

    Returns:
        (J, projection error at J).
    """
    if material.get("type") == "lambert":
        return 1, 0.0
    e1 = _error_at(material, 1)
    if e1 <= target:
        return 1, e1
    J = min(max_bands, 2 ** max(0, math.floor(math.log2(e1 / target))))
    e = _error_at(material, J) if J > 1 else e1
    while e > target and J < max_bands:
        J *= 2
        e = _error_at(material, J)
    return J, e


def planned_bases(
    scene: Scene, error: float, edit: list[str] | None = None
) -> tuple[list[ObjectBasis | None], dict[str, float], tuple[str, ...]]:
    """Bands per object for the budget ``error`` (the first step of the plan; no pilot needed).

    Returns:
        (bases per object, None for fixed ones; projection error per edited object; names of
        the objects the plan fixes).
    """
    names = [o.name for o in scene.objects]
    edit_set = {o.name for o in scene.objects if o.editable} if edit is None else set(edit)
    unknown = sorted(edit_set - set(names))
    if unknown:
        raise SceneError(f"edit names unknown objects: {unknown}; objects: {names}")
    bases: list[ObjectBasis | None] = []
    errors: dict[str, float] = {}
    fixed = []
    for o in scene.objects:
        if o.name not in edit_set or not o.editable:
            if o.editable:
                fixed.append(o.name)
            bases.append(None)
            continue
        mat = scene.materials[o.material]
        J, e = choose_bands(mat, BAND_SHARE * error)
        bases.append(_basis(mat, J))
        errors[o.name] = e
    return bases, errors, tuple(fixed)


def _coefficients(material: dict[str, Any], basis: ObjectBasis) -> tuple[torch.Tensor, torch.Tensor]:
    """(c (J, 3), d (3,)) of ``material`` on ``basis``: projected bands (Lambert exactly:
    albedo / pi) and the diffuse equivalent as the renderer computes it. Memoised."""
    key = (json.dumps(material, sort_keys=True, default=str), basis)
    if key not in _COEFFICIENTS:
        b = basis.band_basis()
        with torch.no_grad():
            if material.get("type") == "lambert":
                a = torch.as_tensor(material.get("albedo", 0.5), dtype=torch.float64).reshape(-1).expand(3)
                c = (a / math.pi)[None].expand(basis.J, 3).clone()
            else:
                c = project(create(material), b, quadrature=_quadrature(b))
            # the renderer's d (Eq. 37 with the cached Monte Carlo band albedos), also for Lambert
            d = equivalent_albedo(Factored1D(b, coefficients=c), progress=False).to(torch.float64)
        _COEFFICIENTS[key] = (c.detach(), d.detach())
    return _COEFFICIENTS[key]


_COEFFICIENTS: dict[tuple[str, ObjectBasis], tuple[torch.Tensor, torch.Tensor]] = {}


def unlit_mask(tensors: PolynomialTensors) -> torch.Tensor:
    """(H*W,) bool: pixels that see no emitter directly, nor next to one (the error budget's
    pixels; jittered emitter edges would dominate every error, as in the benchmarks)."""
    e = tensors.emission.abs().sum(0).reshape(1, 1, tensors.height, tensors.width) > 0
    e = torch.nn.functional.max_pool2d(e.float(), 3, stride=1, padding=1) > 0
    return ~e.reshape(-1)


def pilot_images(
    tensors: PolynomialTensors,
    materials: dict[str, dict[str, Any]],
    eye: set[int] | None = None,
    through: set[int] | None = None,
) -> torch.Tensor:
    r"""The per-bounce images of a pilot record at the scene's materials, from the record alone.

    The same sum as ``PolynomialRenderer.evaluate(per_bounce=True)`` (Eq. 26) for a series
    without a second-bounce level: entry value x eye coefficient :math:`c_j` x
    :math:`\prod_m d_m^{n_m}` (the planner sits below the render layer).

    Args:
        tensors: a record without a low-frequency second bounce.
        materials: object name -> material dict of every editable object.
        eye: only paths whose eye vertex is on one of these objects (default all).
        through: only terms with a diffuse-equivalent vertex on one of these objects.
    Returns:
        (N + 1, H, W, C) float64: emission, then bounces 1..N.
    """
    if tensors.series.two_level:
        raise ValueRangeError("pilot records have no second-bounce level")
    m_all = tensors.num_objects
    cs: list[torch.Tensor] = []
    d = torch.ones(m_all, 3, dtype=torch.float64)
    for m, b in enumerate(tensors.bases):
        if b is None:
            cs.append(torch.ones(1, 3, dtype=torch.float64))
            continue
        c, dm = _coefficients(materials[tensors.object_names[m]], b)
        cs.append(c)
        d[m] = dm
    g = {}
    for n, table in tensors.terms.items():
        counts = table.counts.to(torch.float64)
        g[n] = torch.exp(counts @ torch.log(d.clamp_min(1e-300))) * (counts @ (d == 0).double() == 0).double()
    hw = tensors.height * tensors.width
    out = torch.zeros(tensors.series.bounces + 1, 3, hw, dtype=torch.float64)
    out[0] = tensors.emission.double()
    for blk in tensors.blocks:
        if eye is not None and blk.object_id not in eye:
            continue
        j, t, p = blk.coordinates()
        if through is not None:
            keep = tensors.terms[blk.bounce].counts[blk.terms[t]][:, sorted(through)].sum(1) > 0
            j, t, p = j[keep], t[keep], p[keep]
            vals = blk.values.double()[:, keep]
        else:
            vals = blk.values.double()
        contrib = vals * cs[blk.object_id][j].T * g[blk.bounce][blk.terms[t]].T
        out[blk.bounce].index_add_(1, blk.pixels[p], contrib)
    return out.transpose(1, 2).reshape(-1, tensors.height, tensors.width, 3)


def spp_levels(x: torch.Tensor) -> torch.Tensor:
    """``x`` (any shape, >= 0) rounded up to the adaptive spp grid ``MIN_SPP * 2^(k / LEVELS_PER_OCTAVE)`` (made
    integers), as int64: few distinct levels (the precompute traces them in one pass sequence
    per tile, whatever the levels)."""
    k = torch.ceil(LEVELS_PER_OCTAVE * torch.log2(x.double().clamp_min(MIN_SPP) / MIN_SPP) - 1e-9)
    return torch.ceil(MIN_SPP * 2 ** (k / LEVELS_PER_OCTAVE) - 1e-9).long()


def _smoothed(var: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """(H, W): ``var`` averaged over the SMOOTH x SMOOTH window's counted pixels (0 elsewhere)."""
    pool = torch.nn.functional.avg_pool2d
    kw = {"kernel_size": SMOOTH, "stride": 1, "padding": SMOOTH // 2, "count_include_pad": False}
    num = pool((var * keep)[None, None], **kw)[0, 0]
    den = pool(keep.double()[None, None], **kw)[0, 0]
    return torch.where(keep, num / den.clamp_min(1e-12), torch.zeros_like(num))


def allocate_spp(
    var: torch.Tensor,
    shape: torch.Tensor,
    cost: torch.Tensor,
    noise: float | None = None,
    mean_cost: float | None = None,
) -> torch.Tensor:
    r"""Per-pixel spp :math:`n_i \propto s_i / \sqrt{c_i}` on the :func:`spp_levels` grid (at
    least ``MIN_SPP``): the allocation that minimises :math:`\sum_i \sigma_i^2 / n_i` at a fixed
    cost :math:`\sum_i c_i n_i` (Lagrange: :math:`n_i = \lambda \sigma_i / \sqrt{c_i}`), with
    the shape :math:`s_i` a smoothed estimate of :math:`\sigma_i`.

    Args:
        var: (H, W) per-path variance estimate :math:`\sigma_i^2` (0 where not counted).
        shape: (H, W) :math:`s_i \ge 0` (0: the pixel gets ``MIN_SPP``).
        cost: (H, W) relative cost of one path from pixel :math:`i` (> 0).
        noise: the least :math:`\lambda` whose :math:`\sum_i \sigma_i^2 / n_i \le` ``noise``, or
        mean_cost: the largest whose :math:`\sum_i c_i n_i / \sum_i c_i \le` ``mean_cost``
            (both given: the cheaper of the two).
    Returns:
        (H, W) int64 spp map.
    """
    w = shape / cost.sqrt()

    def at(t: float) -> torch.Tensor:  # the map at lambda = 2^t
        return spp_levels(2.0**t * w)

    def search(good, least: bool) -> torch.Tensor:
        # bisection on log2 lambda: the least lambda where ``good`` holds (it holds above), or
        # the largest (it holds below)
        lo, hi = -40.0, 40.0
        for _ in range(60):
            mid = (lo + hi) / 2
            if good(at(mid)) == least:
                hi = mid
            else:
                lo = mid
        return at(hi if least else lo)

    def mean_cost_of(n: torch.Tensor) -> float:
        return float((cost * n).sum() / cost.sum())

    if noise is not None:
        n = search(lambda m: float((var / m).sum()) <= noise, least=True)
        if mean_cost is None or mean_cost_of(n) <= mean_cost:
            return n
    return search(lambda m: mean_cost_of(m) <= mean_cost, least=False)


@dataclass(frozen=True)
class GIPlan:
    """The planned settings of a multibounce precomputation and their predictions.

    Attributes:
        series: the BRDF series (its length is the number of bounces).
        bases: per object (scene order) the :class:`ObjectBasis`, None for fixed objects.
        object_names: the scene's object names.
        spp: paths per pixel (uniform plans), or the mean of ``spp_map``.
        spp_map: (H, W) int64 paths per pixel of an adaptive plan, None for a uniform one.
        fixed: editable objects of the scene that the plan fixes (not in ``edit``).
        error: the requested relative RMSE (None when only ``seconds`` was given).
        seconds: the requested precompute seconds (None: no time budget).
        band_error, bounce_error, noise_error: the predicted parts (relative RMSE each).
        projection_errors: ((object, J, projection error), ...) of the edited objects.
        glossy_to_glossy: relative RMS of the pilot's glossy-to-glossy bounce-2 light.
        predicted_seconds: the predicted precompute time, fixed + rate x spp fitted through
            the pilots (the rate scaled by bounces / pilot bounces; for a map, spp is the
            mean weighted by each pixel's path cost).
        pilot_seconds: what the pilot runs cost.
        light_samples: next-event samples per light at the eye vertex.
        eye_light_share: the share of a path's variance that the eye vertex's next-event
            estimate makes (what light samples divide), at the planned bounces.
        needed_bounces: the bounces the light needs: the last whose own light (measured in the
            pilots, less their noise) is above :data:`LAST_BOUNCE_SHARE` of the budget.
        last_bounce_light: the planned last bounce's light (relative to the image).
        banded_noise: the factor a banded second bounce put on the predicted noise variance
            (measured with banded pilots, :func:`banded_noise_scale`; 1 without one).
        noise_map: (H, W) each pixel's predicted noise variance over the image's squared norm
            (its sum is ``noise_error`` squared); how far one run's noise may fall from the
            prediction follows from it (a sum of P independent squares whose effective count
            is ``noise_map.sum()**2 / (noise_map**2).sum()``).
        checked: the noise was measured with check pilots of the planned settings
            (:func:`check_variance`), not modelled from the 1-band pilots.
    """

    series: Series
    bases: tuple[ObjectBasis | None, ...]
    object_names: tuple[str, ...]
    spp: float
    fixed: tuple[str, ...]
    error: float | None
    seconds: float | None
    band_error: float
    bounce_error: float
    noise_error: float
    projection_errors: tuple[tuple[str, int, float], ...]
    glossy_to_glossy: float
    predicted_seconds: float
    pilot_seconds: float
    spp_map: torch.Tensor | None = None
    light_samples: int = 1
    eye_light_share: float = 0.0
    needed_bounces: int = 0
    last_bounce_light: float = 0.0
    banded_noise: float = 1.0
    noise_map: torch.Tensor | None = None
    checked: bool = False

    @property
    def predicted_error(self) -> float:
        """:math:`\\sqrt{e_b^2 + e_t^2 + e_n^2}` (relative RMSE against the converged model)."""
        return math.sqrt(self.band_error**2 + self.bounce_error**2 + self.noise_error**2)

    def __str__(self) -> str:
        want = [] if self.error is None else [f"error {self.error:g}"]
        want += [] if self.seconds is None else [f"time {self.seconds:g} s"]
        if self.spp_map is None:
            spp = f"spp {self.spp}"
        else:
            m = self.spp_map
            spp = (
                f"adaptive spp {self.spp:.1f} per pixel on average ({int(m.min())} to {int(m.max())},"
                f" {torch.unique(m).numel()} levels)"
            )
        lines = [
            f"GI plan for {' and '.join(want)}: series {self.series.key}, {spp}",
            f"  predicted error {self.predicted_error:.4f} = sqrt(bands {self.band_error:.4f}^2"
            f" + bounces {self.bounce_error:.4f}^2 + noise {self.noise_error:.4f}^2)",
            f"  predicted cost {self.predicted_seconds:.2f} s (pilot {self.pilot_seconds:.2f} s)",
        ]
        for name, J, e in self.projection_errors:
            lines.append(f"  {name}: {J} band{'s' if J > 1 else ''} (projection error {e:.4f})")
        lines.append(f"  glossy-to-glossy bounce-2 light {self.glossy_to_glossy:.4f} of the image")
        if self.series.two_level:
            lines.append(f"  the banded second bounce multiplies the noise variance by {self.banded_noise:.2f}")
        if self.checked:
            lines.append("  noise measured with check runs of the planned settings")
        lines.append(
            f"  the light needs {self.needed_bounces} bounce{'s' if self.needed_bounces > 1 else ''}"
            f" (the planned last bounce carries {self.last_bounce_light:.4f} of the image)"
        )
        lines.append(
            f"  {self.light_samples} light sample{'s' if self.light_samples > 1 else ''} per eye vertex"
            f" (its next-event estimate makes {self.eye_light_share:.0%} of a path's variance)"
        )
        if self.fixed:
            lines.append(f"  fixed (not edited): {', '.join(self.fixed)}")
        return "\n".join(lines)

    def summary(self) -> dict[str, Any]:
        """The plan as JSON-ready values (what a planned record saves in ``meta["plan_summary"]``)."""
        return {
            "error": self.error,
            "seconds": self.seconds,
            "series": self.series.key,
            "spp": self.spp,
            "adaptive": self.spp_map is not None,
            "light_samples": self.light_samples,
            "fixed": list(self.fixed),
            "predicted_error": self.predicted_error,
            "band_error": self.band_error,
            "bounce_error": self.bounce_error,
            "noise_error": self.noise_error,
            "predicted_seconds": self.predicted_seconds,
            "pilot_seconds": self.pilot_seconds,
            "glossy_to_glossy": self.glossy_to_glossy,
            "needed_bounces": self.needed_bounces,
            "last_bounce_light": self.last_bounce_light,
            "banded_noise": self.banded_noise,
            "checked": self.checked,
        }

    def settings(self, base: PolynomialSettings | None = None) -> PolynomialSettings:
        """The :class:`~torch_brdf.transport.polynomial.PolynomialSettings` that carry out the
        plan: ``base`` (sampler, tiles, guides, storage; None: the defaults) with the plan's
        series, spp (or spp map), bases, light samples and fixed objects."""
        spp = self.spp_map if self.spp_map is not None else self.spp
        base = PolynomialSettings() if base is None else base
        return base.replace(
            series=self.series, spp=spp, bases=self.bases, light_samples=self.light_samples, fixed=self.fixed
        )


def _pooled_variance(x: torch.Tensor, spp: torch.Tensor) -> torch.Tensor:
    r"""Per-pixel per-path variance from K independent pilot images of ``spp`` paths each:
    :math:`\sum_k s_k (I_k - \bar I)^2 / (K - 1)` with :math:`\bar I` the path-weighted mean
    (unbiased; for two pilots :math:`(I_a - I_b)^2 / (1/s_a + 1/s_b)`), summed over channels.

    Args:
        x: (K, H, W, C). spp: (K,) float64.
    Returns:
        (H, W).
    """
    sk = spp[:, None, None, None]
    m = (sk * x).sum(0) / spp.sum()
    return (sk * (x - m) ** 2).sum((0, -1)) / (x.shape[0] - 1)


def _slope(s: torch.Tensor, t: torch.Tensor) -> float:
    """Seconds per spp, least squares through pilots (``s`` spp, ``t`` seconds; >= 0)."""
    if float(s.var()) > 0:
        return max(0.0, float(((s - s.mean()) * (t - t.mean())).sum() / ((s - s.mean()) ** 2).sum()))
    return float(t.mean() / s.mean())


def _path_cost(pilots: list[PolynomialTensors], n_max: int) -> torch.Tensor:
    """(n_max + 1, H, W): relative rays of one path from each pixel with n bounces: 1 eye ray,
    then 2 (a shadow and a continuation ray) per bounce that some pilot path of the pixel reached."""
    h, w = pilots[0].height, pilots[0].width
    reached = torch.zeros(n_max + 1, h * w, dtype=torch.bool)
    for p in pilots:
        for blk in p.blocks:
            reached[blk.bounce, blk.pixels] = True
    return (1 + 2 * reached.double().cumsum(0)).reshape(n_max + 1, h, w)


def _check_pilots(error: float | None, seconds: float | None, pilots: list[PolynomialTensors]) -> None:
    if error is None and seconds is None:
        raise ValueRangeError("plan for an error, a time or both; got neither")
    if error is not None and not error > 0:
        raise ValueRangeError(f"error must be > 0; got {error}")
    if len(pilots) < 2:
        raise ValueRangeError(f"the planner needs at least two independent pilot runs; got {len(pilots)}")
    if any(p.meta.get("spp_map") is not None for p in pilots):
        raise ValueRangeError("pilot runs take one spp for every pixel")


def _pilot_stats(bases, projection_errors: dict[str, float], pilots: list[PolynomialTensors], mats: dict):
    """What the pilots measure (see the module): the counted pixels, the image's norm, the
    bounces, the bounce tails, the per-object light by eye vertex, the
    glossy-to-glossy light, the per-pixel noise and its relative sigma per bounce count, the
    path cost per pixel, and the cost fit (seconds per spp, fixed seconds)."""
    keep = unlit_mask(pilots[0]).reshape(pilots[0].height, pilots[0].width)
    imgs = torch.stack([pilot_images(p, mats) for p in pilots])  # (K, N + 1, H, W, C)
    s = torch.tensor([float(p.meta["spp"]) for p in pilots], dtype=torch.float64)
    mean = (s[:, None, None, None, None] * imgs).sum(0) / s.sum()
    norm = float((mean.sum(0)[keep] ** 2).sum()) ** 0.5
    if norm == 0:
        raise ValueRangeError("the pilot image is black: nothing to plan for")
    n_max = pilots[0].series.bounces
    # the tail's squared norm less what the pilots' own noise adds to it (E|mean|^2 = |B|^2 +
    # sum_i sigma_i^2 / sum_k s_k, with sigma_i^2 the pooled per-pixel variance)
    tails, lasts = [], [0.0]
    for n in range(n_max + 1):
        noise2 = float(_pooled_variance(imgs[:, n + 1 :].sum(1), s)[keep].sum()) / float(s.sum())
        tails.append(max(0.0, float((mean[n + 1 :].sum(0)[keep] ** 2).sum()) - noise2) ** 0.5 / norm)
        if n >= 1:  # bounce n's own light, measured the same way
            noise2 = float(_pooled_variance(imgs[:, n], s)[keep].sum()) / float(s.sum())
            lasts.append(max(0.0, float((mean[n][keep] ** 2).sum()) - noise2) ** 0.5 / norm)
    names = list(pilots[0].object_names)
    # per-object light whose eye vertex is on the object, per bounce (for the band error at N)
    # (cumulated over bounces 1..n: index n - 1)
    eye_parts = {
        name: pilot_images(pilots[0], mats, eye={names.index(name)})[1:, keep].cumsum(0) for name in projection_errors
    }
    # glossy-to-glossy bounce-2 transport: eye vertex and second vertex both on glossy objects
    glossy = {m for m, bb in enumerate(bases) if bb is not None and bb.J > 1}
    g2g = 0.0
    if glossy and n_max >= 2:
        part = pilot_images(pilots[0], mats, eye=glossy, through=glossy)[2, keep]
        g2g = float((part**2).sum()) ** 0.5 / norm
    # per-pixel noise of one path with the first n bounces (pooled over the pilots), 0 where
    # the budget does not count; sigmas: the relative noise of the image at one spp
    cum = imgs.cumsum(1)
    pixvar = [_pooled_variance(cum[:, n], s) * keep for n in range(n_max + 1)]
    sigmas = [float(v.sum()) ** 0.5 / norm for v in pixvar]
    cost = _path_cost(pilots, n_max)
    # cost: t = fixed + rate * spp, least squares through the pilots; the rate scales with
    # bounces (each bounce casts a closest-hit and a shadow ray per live path: linear in them)
    t = torch.tensor([float(p.meta["seconds"]) for p in pilots], dtype=torch.float64)
    rate_max = _slope(s, t)
    fixed_s = max(0.0, float(t.mean()) - rate_max * float(s.mean()))

    return keep, norm, n_max, (tails, lasts), eye_parts, g2g, pixvar, sigmas, cost, rate_max, fixed_s


def _light_sample_ratios(split_pilots, mats: dict, pixvar: list, keep, n_max: int, max_light_samples: int):
    """Per bounce count n: {k: V(k) / V(1)} for the light samples k a plan may take, and the
    share B / V(1) of a path's variance the eye vertex's next-event estimate makes (from
    ``split_pilots`` at K light samples; without them only k = 1, share 0)."""
    ratios = {n: {1: 1.0} for n in range(n_max + 1)}
    shares = [0.0] * (n_max + 1)
    if split_pilots:
        k_p = int(split_pilots[0].meta.get("light_samples", 1))
        if k_p < 2 or any(int(p.meta.get("light_samples", 1)) != k_p for p in split_pilots) or len(split_pilots) < 2:
            raise ValueRangeError("split_pilots: at least two runs, all with the same light_samples >= 2")
        s_k = torch.tensor([float(p.meta["spp"]) for p in split_pilots], dtype=torch.float64)
        cum_k = torch.stack([pilot_images(p, mats) for p in split_pilots]).cumsum(1)
        for n in range(1, n_max + 1):
            v1, vk = float(pixvar[n].sum()), float((_pooled_variance(cum_k[:, n], s_k) * keep).sum())
            b = min(v1, max(0.0, (v1 - vk) * k_p / (k_p - 1))) if v1 > 0 else 0.0
            shares[n] = b / v1 if v1 > 0 else 0.0
            ratios[n] = {k: (v1 - b + b / k) / v1 if v1 > 0 else 1.0 for k in LIGHT_SAMPLES if k <= max_light_samples}
    return ratios, shares


def _needed_bounces(lasts: list[float], budget: float) -> int:
    """The bounces the light needs: up to the last one whose own light (``lasts[n]``) is above
    LAST_BOUNCE_SHARE of the budget. Beyond it more bounces only add cost: a longer series may
    still look cheaper (it leaves the noise more of the budget), but it models light that is not
    there."""
    return max([1] + [n for n in range(1, len(lasts)) if lasts[n] > LAST_BOUNCE_SHARE * budget])


def _choose(options: dict, tails: list[float], needed: int, budget: float, for_error: bool) -> tuple[int, int]:
    """(bounces, light samples) among ``options`` ((n, k) -> spp_for's tuple), never more bounces
    than ``needed``: for an error the cheapest whose tail is at most BOUNCE_SHARE of the budget
    (else the fewest bounces whose tail fits), for a time alone the most accurate."""
    if not for_error:
        capped = [nk for nk in options if nk[0] <= needed] or list(options)
        return min(capped, key=lambda nk: (options[nk][3], nk))
    allowed = [nk for nk in options if tails[nk[0]] <= BOUNCE_SHARE * budget and nk[0] <= needed]
    if not allowed:  # the tail at the needed bounces is still too large: the fewest whose tail fits
        fits = [nk[0] for nk in options if tails[nk[0]] <= BOUNCE_SHARE * budget] or [max(n for n, _ in options)]
        allowed = [nk for nk in options if nk[0] == min(fits)]
    return min(allowed, key=lambda nk: (options[nk][4], nk))


def _two_level(bases, bounces: int, g2g: float, budget: float) -> bool:
    """Whether :func:`_planned_series` gives ``bounces`` a banded second bounce."""
    return _planned_series(bases, bounces, g2g, budget)[0].two_level


def banded_noise_scale(
    banded: list[PolynomialTensors], pilots: list[PolynomialTensors], mats: dict[str, dict[str, Any]]
) -> dict[int, float]:
    r"""How much a banded second bounce multiplies the noise, per number of bounces n >= 2:
    :math:`\sum_i \sigma_{i,n}^2` of the banded pilots (rendered at the scene's materials) over
    the same of the 1-band pilots, both pooled per pixel (:func:`_pooled_variance`) over the
    counted pixels; at least 1 (a banded vertex cannot make the estimate steadier than its
    diffuse equivalent beyond the pilots' own noise)."""
    from ..render.polynomial import PolynomialRenderer

    keep = unlit_mask(pilots[0]).reshape(pilots[0].height, pilots[0].width)

    def cumulative(records):
        imgs = []
        for t in records:
            parts = PolynomialRenderer(t, mats, dtype=torch.float64).evaluate(per_bounce=True)
            imgs.append(torch.stack([p.double() for p in parts]).cumsum(0))
        return torch.stack(imgs), torch.tensor([float(t.meta["spp"]) for t in records], dtype=torch.float64)

    a, sa = cumulative(banded)
    b, sb = (
        torch.stack([pilot_images(p, mats).cumsum(0) for p in pilots]),
        torch.tensor([float(p.meta["spp"]) for p in pilots], dtype=torch.float64),
    )
    out = {}
    for n in range(2, min(a.shape[1], b.shape[1])):
        den = float(_pooled_variance(b[:, n], sb)[keep].sum())
        if den > 0:
            out[n] = max(1.0, float(_pooled_variance(a[:, n], sa)[keep].sum()) / den)
    return out


def _planned_series(bases, bounces: int, g2g: float, budget: float) -> tuple[Series, list]:
    """The series of ``bounces`` (a low-frequency second bounce where the glossy-to-glossy light
    ``g2g`` exceeds its share of the budget) and the bases with its second-bounce bands."""
    series_bands = [max([1] + [bb.J for bb in bases if bb is not None])] + [1] * (bounces - 1)
    if bounces >= 2 and g2g * 0.88 > SECOND_SHARE * budget:
        series_bands[1] = min(16, series_bands[0])
    series = Series(tuple(series_bands))
    if series.two_level:
        bases = [None if bb is None else dataclasses.replace(bb, second=min(series.second, bb.J)) for bb in bases]
    return series, bases


def plan_from_pilots(
    scene: Scene,
    bases: list[ObjectBasis | None],
    projection_errors: dict[str, float],
    fixed: tuple[str, ...],
    pilots: list[PolynomialTensors],
    error: float | None = None,
    seconds: float | None = None,
    adaptive: bool = True,
    split_pilots: list[PolynomialTensors] | None = None,
    max_light_samples: int = max(LIGHT_SAMPLES),
    banded_noise: dict[int, float] | None = None,
    check: tuple[int, int, torch.Tensor] | None = None,
) -> GIPlan:
    """Decide bounces, second bounce and spp from independent pilot records (see the module).

    Args:
        scene: the scene (with the plan's fixed objects already fixed).
        bases: from :func:`planned_bases`.
        projection_errors: as ``bases``.
        fixed: as ``bases``.
        pilots: at least two records of the same series and bases, different seeds and (for
            the cost fit) at least two different spp; bounces >= the most the plan may
            choose; no second-bounce level; uniform spp.
        error: relative RMSE budget; seconds: precompute time budget (at least one).
        adaptive: a per-pixel spp map (:func:`allocate_spp`); False: one spp for all pixels.
        split_pilots: optional, at least two more records like ``pilots`` but with
            ``light_samples`` K >= 2: the plan then also chooses the light samples per eye vertex
            (one of :data:`LIGHT_SAMPLES`, at most ``max_light_samples``) from how much of the
            noise they take away.
        banded_noise: bounces -> the factor a banded second bounce puts on the noise variance
            of the first n bounces (:func:`banded_noise_scale`; absent: 1).
        check: (bounces, light samples, (H, W) per-path variance) measured by check pilots run
            with the planned settings themselves (:func:`check_variance`): the plan keeps
            those bounces and light samples and takes its spp and predicted noise from this
            variance (the allocation's shape still from ``pilots``, so the two are independent).
    Returns:
        :class:`GIPlan`.
    """
    _check_pilots(error, seconds, pilots)
    banded_noise = banded_noise or {}
    mats = {o.name: scene.materials[o.material] for o in scene.objects if o.editable}
    keep, norm, n_max, (tails, lasts), eye_parts, g2g, pixvar, sigmas, cost, rate_max, fixed_s = _pilot_stats(
        bases, projection_errors, pilots, mats
    )
    budget = error if error is not None else 1.0
    needed = _needed_bounces(lasts, budget)
    names = list(pilots[0].object_names)

    def band_error_at(n: int) -> float:
        # the projection error weighted by the light whose eye vertex is on the object
        return (
            sum(eps**2 * float((eye_parts[name][n - 1] ** 2).sum()) for name, eps in projection_errors.items()) ** 0.5
            / norm
        )

    # light splitting at the eye vertex: a path's variance is V(k) = A + B / k with k light
    # samples (B: the variance of the eye vertex's next-event estimate), from the variance at
    # k = 1 (the pilots) and at k = K (``split_pilots``); each extra sample costs a path
    # EXTRA_SAMPLE_COST ray units per light where the eye ray hits something (the pilots'
    # seconds are too short to measure it on a loaded machine)
    ratios, shares = _light_sample_ratios(split_pilots, mats, pixvar, keep, n_max, max_light_samples)
    hit = (cost[1] > 1).double()  # the eye ray found a surface (a pilot path got light there)
    extra = EXTRA_SAMPLE_COST * len(scene.lights)

    def spp_for(
        n: int, k: int = 1, checked: torch.Tensor | None = None
    ) -> tuple[float, torch.Tensor | None, float, float, float]:
        # the cheapest spp (map) with n bounces and k eye light samples for the error within the
        # time budget: its mean spp, map, seconds, error and ray units per pixel (the cost the
        # plan minimises: the pilots' seconds are too short to rank options on a loaded machine)
        c = cost[n] + (k - 1) * extra * hit
        rate = rate_max * n / n_max * float(c.mean() / cost[n].mean())
        scale = banded_noise.get(n, 1.0) if _two_level(bases, n, g2g, budget) else 1.0
        var = pixvar[n] * ratios[n][k] * scale
        sigma = sigmas[n] * (ratios[n][k] * scale) ** 0.5
        nvar = var if checked is None else checked * keep
        if checked is not None:
            sigma = float(nvar.sum()) ** 0.5 / norm
        bias2 = band_error_at(n) ** 2 + tails[n] ** 2
        share2 = None
        if error is not None:
            share2 = ((AIM_ADAPTIVE if adaptive else AIM) * error) ** 2 - bias2
            if share2 <= 0:
                share2 = (0.1 * error) ** 2  # the biases already exceed the budget: keep noise small
        spp_time = None if seconds is None else min(MAX_PLANNED_SPP, max(1e-9, (seconds - fixed_s) / max(rate, 1e-12)))
        if adaptive:
            noise = None if share2 is None else share2 * norm**2
            shape = (_smoothed(var, keep) + DEFENSIVE * float(var[keep].mean())).sqrt() * keep
            m = allocate_spp(nvar, shape, c, noise=noise, mean_cost=spp_time)
            eff = float((c * m).sum() / c.sum())
            return (
                float(m.double().mean()),
                m,
                fixed_s + rate * eff,
                math.sqrt(bias2 + float((nvar / m).sum()) / norm**2),
                float((c * m).mean()),
                nvar / m / norm**2,
            )
        spp_err = None if share2 is None else max(1, math.ceil(sigma**2 / share2))
        spp = min(x for x in (spp_err, None if spp_time is None else max(1, int(spp_time))) if x is not None)
        return (
            spp,
            None,
            fixed_s + rate * spp,
            math.sqrt(bias2 + sigma**2 / spp),
            float(c.mean()) * spp,
            nvar / spp / norm**2,
        )

    options = {(n, k): spp_for(n, k) for n in range(1, n_max + 1) for k in ratios[n]}
    bounces, light_samples = _choose(options, tails, needed, budget, error is not None)
    if check is not None:
        bounces, light_samples = check[0], check[1]
        options[bounces, light_samples] = spp_for(bounces, light_samples, check[2].to(torch.float64))
    spp, spp_map, predicted_seconds, predicted, _, noise_map = options[bounces, light_samples]
    band_error = band_error_at(bounces)
    series, bases = _planned_series(bases, bounces, g2g, budget)
    return _assemble_plan(locals())


def _assemble_plan(v: dict[str, Any]) -> GIPlan:
    """The :class:`GIPlan` of :func:`plan_from_pilots`'s decisions (its local values ``v``)."""
    n, names, bases, series = v["bounces"], v["names"], v["bases"], v["series"]
    bias2 = v["band_error"] ** 2 + v["tails"][n] ** 2
    return GIPlan(
        series=series,
        bases=tuple(bases),
        object_names=tuple(names),
        spp=v["spp"],
        fixed=tuple(v["fixed"]),
        error=v["error"],
        seconds=v["seconds"],
        band_error=v["band_error"],
        bounce_error=v["tails"][n],
        noise_error=math.sqrt(max(0.0, v["predicted"] ** 2 - bias2)),
        projection_errors=tuple((o, bases[names.index(o)].J, e) for o, e in v["projection_errors"].items()),
        glossy_to_glossy=v["g2g"],
        predicted_seconds=v["predicted_seconds"],
        pilot_seconds=sum(float(p.meta["seconds"]) for p in v["pilots"]),
        spp_map=v["spp_map"],
        light_samples=v["light_samples"],
        eye_light_share=v["shares"][n],
        needed_bounces=v["needed"],
        last_bounce_light=v["lasts"][n],
        banded_noise=v["banded_noise"].get(n, 1.0) if series.two_level else 1.0,
        noise_map=v["noise_map"],
        checked=v["check"] is not None,
    )


def plan_polynomial(
    scene: Scene,
    error: float | None = 0.03,
    seconds: float | None = None,
    edit: list[str] | None = None,
    pilot_spp: int = 4,
    pilot_bounces: int = 8,
    seed: int = 0,
    env_point_lights: int | None = None,
    progress: bool | None = None,
    pilot_runs: int = 4,
    adaptive: bool = True,
    max_light_samples: int = 16,
    check_runs: int = 4,
) -> GIPlan:
    """Plan the precomputation for a relative-RMSE ``error`` and/or ``seconds``.

    Bands per object come from projection errors (no tracing); ``pilot_runs`` independent pilot
    runs of ``pilot_spp`` x 1, 2, 2, 4, 1, 2, 2, 4, ... spp and ``pilot_bounces`` bounces (seeds
    independent of ``seed``'s final run) measure the bounce tail, glossy-to-glossy transport,
    the per-pixel Monte Carlo noise and the cost; the decisions are :func:`plan_from_pilots`'s.
    The pilots are :func:`~torch_brdf.transport.polynomial.precompute_polynomial` runs; the
    plan's :meth:`GIPlan.settings` carry it out.

    Args:
        scene: the scene.
        error: relative RMSE budget (against the converged polynomial model).
        seconds: precompute time budget.
        edit: the objects to keep editable (default every editable object); the others are fixed.
        pilot_spp: the pilots' samples per pixel.
        pilot_bounces: the pilots' bounces (all 1-band after the eye).
        seed: the pilots use seeds derived from it, independent of the final run's ``seed``.
        env_point_lights: as :class:`~torch_brdf.transport.polynomial.PolynomialSettings` (the
            pilots light the scene the same way).
        progress: a tqdm bar per pilot run (None: on when attached to a terminal or notebook).
        pilot_runs: independent pilot runs (>= 2; more give a steadier per-pixel noise estimate).
        adaptive: plan a per-pixel spp map (adaptive sampling); False: one spp for all pixels.
        max_light_samples: the most light samples per eye vertex the plan may choose; above 1,
            two more pilots (``pilot_spp`` x 1 and 2 spp) with 4 samples measure what they buy.
        check_runs: independent runs of the planned settings (``pilot_spp`` x 1, 2, 2, 4, ...
            spp) whose variance gives the final spp and predicted noise (:func:`check_variance`);
            0 keeps the noise modelled from the pilots alone.
    Returns:
        :class:`GIPlan` (``print(plan)`` shows choices, cost and error).
    """
    if check_count(pilot_runs, "pilot_runs") < 2:
        raise ValueRangeError(f"the planner needs at least two pilot runs; got {pilot_runs}")
    bases, errors, fixed = planned_bases(scene, error if error is not None else 0.03, edit)
    scene = with_fixed(scene, fixed)
    eye = max([1] + [b.J for b in bases if b is not None])
    pilot = PolynomialSettings(
        series=Series((eye,) + (1,) * (pilot_bounces - 1)), bases=bases, env_point_lights=env_point_lights
    )
    pilots = [
        precompute_polynomial(
            scene, pilot.replace(spp=pilot_spp * (1, 2, 2, 4)[k % 4]), seed=seed + 7919 * (k + 1), progress=progress
        )
        for k in range(pilot_runs)
    ]
    split = []
    if check_count(max_light_samples, "max_light_samples") > 1:
        split = [
            precompute_polynomial(
                scene,
                pilot.replace(spp=pilot_spp * (k + 1), light_samples=4),
                seed=seed + 7919 * (pilot_runs + k + 1),
                progress=progress,
            )
            for k in range(2)
        ]
    args = (scene, bases, errors, fixed, pilots)
    kw = {"error": error, "seconds": seconds, "adaptive": adaptive, "split_pilots": split}
    plan = plan_from_pilots(*args, **kw, max_light_samples=max_light_samples)
    mats = {o.name: scene.materials[o.material] for o in scene.objects if o.editable}
    scale = None
    if plan.series.two_level:
        # a banded second bounce: its noise is measured with two pilots that have it (the
        # 1-band pilots under-predict it), and the choice of bounces is made again with it
        banded_series = Series((eye, plan.series.second) + (1,) * (pilot_bounces - 2))
        second = [None if b is None else dataclasses.replace(b, second=min(plan.series.second, b.J)) for b in bases]
        banded = [
            precompute_polynomial(
                scene,
                pilot.replace(series=banded_series, bases=tuple(second), spp=pilot_spp * (k + 1)),
                seed=seed + 7919 * (pilot_runs + 3 + k),
                progress=progress,
            )
            for k in range(2)
        ]
        scale = banded_noise_scale(banded, pilots, mats)
        plan = plan_from_pilots(*args, **kw, max_light_samples=max_light_samples, banded_noise=scale)
    if check_runs < 2:
        return plan
    # check pilots: the planned settings themselves (series, second-bounce bands, light samples)
    # at uniform pilot spp; the noise the plan predicts comes from their variance, not from the
    # 1-band pilots scaled by modelled factors (see check_variance)
    checks = [
        precompute_polynomial(
            scene,
            plan.settings(pilot).replace(spp=pilot_spp * (1, 2, 2, 4)[k % 4], fixed=()),
            seed=seed + 7919 * (pilot_runs + 5 + k),
            progress=progress,
        )
        for k in range(check_runs)
    ]
    var = check_variance(checks, mats)
    return plan_from_pilots(
        *args,
        **kw,
        max_light_samples=max_light_samples,
        banded_noise=scale,
        check=(plan.series.bounces, plan.light_samples, var),
    )


def check_variance(records: list[PolynomialTensors], mats: dict[str, dict[str, Any]]) -> torch.Tensor:
    r"""(H, W) per-path variance of the image at the scene's materials, pooled per pixel
    (:func:`_pooled_variance`) over independent runs of the *planned* settings at uniform spp.

    Why: the pilots run a 1-band series with one light sample, and the noise of a plan with a
    banded second bounce and several light samples was predicted from them by factors each
    measured on other pilots (the banded noise scale, the light-sample ratio). On glossy
    floors reflecting glossy objects those factors came out low (the banded bounce's glossy
    quotients are heavy-tailed, and a ratio of two noisy sums is biased), and the achieved
    noise exceeded the prediction. Measuring the planned estimator itself removes the model;
    and since these runs are independent of the pilots that shape the spp map, the predicted
    noise :math:`\sum_i \sigma_i^2 / n_i` is unbiased for that map (the same pilots for both
    favour pixels whose variance came out high and under-predict).

    Args:
        records: at least two runs of the same settings (different seeds, uniform spp).
        mats: object name -> material of every editable object.
    Returns:
        (H, W) float64.
    """
    from ..render.polynomial import PolynomialRenderer

    if len(records) < 2:
        raise ValueRangeError(f"check_variance needs at least two runs; got {len(records)}")
    imgs = torch.stack([PolynomialRenderer(t, mats, dtype=torch.float64)().double() for t in records])
    s = torch.tensor([float(t.meta["spp"]) for t in records], dtype=torch.float64)
    return _pooled_variance(imgs, s)


def precompute_planned(
    scene: Scene,
    settings: PolynomialSettings | None = None,
    *,
    plan: GIPlan | None = None,
    error: float | None = None,
    seconds: float | None = None,
    seed: int = 0,
    progress: bool | None = None,
    checkpoint: str | Path | None = None,
    **run: Any,
) -> PolynomialTensors:
    """Plan the multibounce precomputation for ``error`` and/or ``seconds`` and carry it out.

    Args:
        scene: the scene.
        settings: :class:`~torch_brdf.transport.polynomial.PolynomialSettings` whose sampler,
            environment point lights, tiles, guides and storage the run keeps (the plan
            decides series, spp, bases, light samples and fixed objects; the pilots use the
            same environment point lights); None: the defaults.
        plan: a :class:`GIPlan` to carry out instead of planning (``error`` and ``seconds``
            are then not used).
        error: relative RMSE budget; seconds: precompute time budget (see :func:`plan_polynomial`);
            when neither is given, :data:`DEFAULT_ERROR` within :data:`DEFAULT_SECONDS`.
        seed: the final run's seed (the pilots take seeds derived from it).
        progress: tqdm bars (None: on when attached to a terminal or notebook).
        checkpoint: the final run's tile folder (see
            :func:`~torch_brdf.transport.polynomial.precompute_polynomial`).
        run: the rest of ``precompute_polynomial``'s keywords (``executor``, ``processes``...).
    Returns:
        :class:`~torch_brdf.records.polynomial.PolynomialTensors` whose ``meta["plan"]`` prints the
        plan and ``meta["plan_summary"]`` holds it as values (:meth:`GIPlan.summary`).
    """
    base = PolynomialSettings() if settings is None else settings
    if not isinstance(base, PolynomialSettings):
        raise ValueRangeError(f"settings must be a PolynomialSettings; got {settings!r}")
    if plan is None and error is None and seconds is None:
        error, seconds = DEFAULT_ERROR, DEFAULT_SECONDS
    if plan is None:
        plan = plan_polynomial(
            scene, error=error, seconds=seconds, seed=seed, env_point_lights=base.env_point_lights, progress=progress
        )
    elif not isinstance(plan, GIPlan):
        raise ValueRangeError(f"plan must be a GIPlan; got {plan!r}")
    out = precompute_polynomial(scene, plan.settings(base), seed=seed, progress=progress, checkpoint=checkpoint, **run)
    out.meta["plan"] = str(plan)
    out.meta["plan_summary"] = plan.summary()
    return out
