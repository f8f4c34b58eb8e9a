"""Error-budget planners: cheap pilot measurements in, the cheapest settings for an error out.

The planner sits above the producers it measures (transport, inverse, manifold, render): it
runs their pilots and hands them settings objects; no producer imports it.

* :mod:`.gi` plans the multibounce precomputation of BRDF editing with global illumination
  (bands per object, bounces, a second bounce, spp, fixed objects): :func:`plan_polynomial`
  runs pilot :func:`~torch_brdf.transport.polynomial.precompute_polynomial` runs,
  :func:`plan_from_pilots` decides from their records, and :meth:`GIPlan.settings` is the
  :class:`~torch_brdf.transport.polynomial.PolynomialSettings` that carries the plan out
  (:func:`precompute_planned` does both).
* :mod:`.inverse` plans inverse BRDF design (light samples, SRBF count, visibility-cut
  tolerance): ``from torch_brdf.planner.inverse import plan_inverse`` (not imported here: it
  pulls in the inverse package).
* :mod:`.relight` decides all-frequency relighting (cubemap resolution, visibility bits, BRDF-
  sampling rule) for a PSNR from pilot measurements that :mod:`.relight_pilots`
  (:func:`~.relight_pilots.plan_relighting`) makes with the renderer.
* :mod:`.table`: the candidate table, the choice for an error and/or time budget and the
  printed :class:`Plan` that the capability planners share.
"""

from .gi import GIPlan, choose_bands, pilot_images, plan_from_pilots, plan_polynomial, planned_bases, precompute_planned
from .table import Option, Plan, choose, pareto, power_law

__all__ = [
    "GIPlan",
    "Option",
    "Plan",
    "choose",
    "choose_bands",
    "pareto",
    "pilot_images",
    "plan_from_pilots",
    "plan_polynomial",
    "planned_bases",
    "power_law",
    "precompute_planned",
]
