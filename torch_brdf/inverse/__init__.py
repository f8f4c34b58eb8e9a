"""Appearance-driven inverse BRDF design (Iwasaki et al.): paint strokes on an image, fit the
SRBF coefficients of a distribution-based BRDF by constrained least squares, re-render.

Pipeline::

    px = object_pixels(scene, "teapot", scene.camera.with_size(160, 120))   # solving frame
    ls = LightSamples.from_environment(scene.environment, 1024, generator)
    rec = transfer_functions(px, ls, cosine_visibility(scene, px, ls), f0=0.9)  # BasisImage
    before = rec.pixel_values(torch.cat((torch.zeros(147, 3), torch.full((1, 3), 0.3))))  # diffuse only
    target = paint(rec, before, [Stroke(points, Brush((1, 1, 1), 40, 0.02))], display_size=(640, 480))
    result = fit(rec, target, kd=0.3)  # c >= 0 and energy rows; result.objective, .violation
    image = rerender(scene, "teapot", result, environment=scene.environment.rotated(1.0))
"""

from .energy import EnergyRows, energy_rows, outgoing_directions
from .qp import QPResult, solve_qp
from .render import distribution_image, rerender, srbf_brdf
from .solve import FitResult, NormalEquations, fit, load_fit, normal_equations, save_fit
from .strokes import Brush, Stroke, StrokeTarget, paint, stroke_distance, target_from_image
from .transfer import (
    CutOptions,
    LightSamples,
    ObjectPixels,
    cosine_visibility,
    object_pixels,
    precompute_transfer,
    split_record,
    transfer_functions,
)

__all__ = [
    "Brush",
    "CutOptions",
    "EnergyRows",
    "FitResult",
    "LightSamples",
    "NormalEquations",
    "ObjectPixels",
    "QPResult",
    "Stroke",
    "StrokeTarget",
    "cosine_visibility",
    "distribution_image",
    "energy_rows",
    "fit",
    "load_fit",
    "normal_equations",
    "object_pixels",
    "outgoing_directions",
    "paint",
    "precompute_transfer",
    "rerender",
    "save_fit",
    "solve_qp",
    "split_record",
    "srbf_brdf",
    "stroke_distance",
    "target_from_image",
    "transfer_functions",
]
