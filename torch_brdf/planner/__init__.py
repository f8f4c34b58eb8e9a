"""Error-budget planners: cheap pilot measurements in, the cheapest settings for an error out.

:mod:`.gi` plans the multibounce precomputation of BRDF editing with global illumination
(bands per object, bounces, a second bounce, spp, fixed objects). The planner decides from
records (:class:`~torch_brdf.records.polynomial.PolynomialTensors` of a pilot run) and the BRDF
layer; it does not trace: :func:`torch_brdf.transport.polynomial.plan_polynomial` runs the pilot
and calls it (so ``precompute_polynomial(scene, plan="auto", error=0.03)`` can live in transport
without an import cycle).
"""

from .gi import GIPlan, choose_bands, pilot_images, plan_from_pilots, planned_bases

__all__ = ["GIPlan", "choose_bands", "pilot_images", "plan_from_pilots", "planned_bases"]
