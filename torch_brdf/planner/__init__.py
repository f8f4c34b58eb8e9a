"""Error-budget planners: cheap pilot measurements in, the cheapest settings for an error out.

* :mod:`.gi` plans the multibounce precomputation of BRDF editing with global illumination
  (bands per object, bounces, a second bounce, spp, fixed objects). It decides from records
  (:class:`~torch_brdf.records.polynomial.PolynomialTensors` of a pilot run) and the BRDF layer;
  it does not trace: :func:`torch_brdf.transport.polynomial.plan_polynomial` runs the pilot and
  calls it (so ``precompute_polynomial(scene, plan="auto", error=0.03)`` can live in transport
  without an import cycle).
* :mod:`.inverse` plans inverse BRDF design (light samples, SRBF count, visibility-cut
  tolerance): ``from torch_brdf.planner.inverse import plan_inverse`` (not imported here, so
  that transport's import of :mod:`.gi` does not pull in the inverse package).
* :mod:`.relight` decides all-frequency relighting (cubemap resolution, visibility bits, BRDF-
  sampling rule) for a PSNR from pilot measurements that
  :func:`torch_brdf.render.relight_plan.plan_relighting` makes with the renderer (a layer above).
* :mod:`.table`: the candidate table, the choice for an error and/or time budget and the
  printed :class:`Plan` that the capability planners share.
"""

from .gi import GIPlan, choose_bands, pilot_images, plan_from_pilots, planned_bases
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
    "planned_bases",
    "power_law",
]
