r"""BRDFs whose diffuse/base colour varies over the surface (image textures).

A textured surface point has the material's BRDF with its base colour multiplied by a texel
:math:`t(x)` (RGB). For every model whose base colour is a Lambertian term added to the
rest — ``lambert`` (``albedo``), ``blinn_phong``, ``phong``, ``ward``, ``ward_aniso``,
``cook_torrance`` (``kd``) — that is exactly

.. math:: f_t(\omega_i, \omega_o) = f(\omega_i, \omega_o) + \frac{k_d\,(t(x) - 1)}{\pi}

where both directions are above the horizon. Models that name another rule register it in
:data:`TEXTURE_RULES` (a function ``(brdf, wi, wo, scale) -> f``). Sampling keeps the
untextured model's density: it is positive wherever the textured BRDF is (the diffuse lobe
is sampled wherever the factor :math:`k_d > 0`), so estimators stay unbiased.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from ..errors import SceneError
from .base import BRDF, lambert_value

__all__ = ["TEXTURE_RULES", "base_color", "texturable", "textured_eval_local"]

#: diffuse/base colour attribute of the models whose base colour is an added Lambert term
_DIFFUSE_ATTR = {
    "lambert": "reflectance",
    "blinn_phong": "kd",
    "phong": "kd",
    "ward": "kd",
    "ward_aniso": "kd",
    "cook_torrance": "kd",
    "rough_plastic": "diffuse_reflectance",  # scaled by its own rule (TEXTURE_RULES)
}

#: models with their own rule: name -> f(brdf, wi, wo, scale (n, 3)) -> (n, 3)
TEXTURE_RULES: dict[str, Callable[[BRDF, torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]] = {}


def _affine_rule(brdf: BRDF, wi: torch.Tensor, wo: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    r"""Models whose f is affine in the base colour :math:`c` per channel (the metallic-roughness
    model: its diffuse :math:`(1-m)c` and its :math:`f_0 = (1-m)\,0.04 + m\,c` both are):
    :math:`f(c\,t) = f(0) + (f(c) - f(0))\,t`, exact."""
    zero = getattr(brdf, "_zero_base_color", None)
    if zero is None:
        import copy

        zero = copy.deepcopy(brdf)
        with torch.no_grad():
            zero.base_color = torch.zeros(3)
        object.__setattr__(brdf, "_zero_base_color", zero)
    f0 = zero.eval_local(wi, wo)
    return f0 + (brdf.eval_local(wi, wo) - f0) * scale.to(wi.dtype)


TEXTURE_RULES["metallic_roughness"] = _affine_rule


def texturable(model: str) -> bool:
    """Whether a base-colour texture can scale materials of ``model``."""
    return model in _DIFFUSE_ATTR or model in TEXTURE_RULES


def base_color(brdf: BRDF) -> torch.Tensor:
    """(3,) the base/diffuse colour factor a texture multiplies."""
    name = getattr(brdf, "model_name", type(brdf).__name__)
    if name in _DIFFUSE_ATTR:
        return getattr(brdf, _DIFFUSE_ATTR[name])
    if hasattr(brdf, "base_color"):
        return brdf.base_color
    raise SceneError(f"BRDF model {name!r} has no base colour a texture could scale; texturable: {_texturable()}")


def _texturable() -> list[str]:
    return sorted({*_DIFFUSE_ATTR, *TEXTURE_RULES})


def textured_eval_local(brdf: BRDF, wi: torch.Tensor, wo: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """The BRDF with its base colour multiplied per row by ``scale`` (local directions).

    Args:
        brdf: the untextured model (its factor).
        wi: (n, 3) local incident directions.
        wo: (n, 3) local outgoing directions.
        scale: (n, 3) texel values (1 = untextured).
    Returns:
        (n, 3) f without the cosine.
    """
    name = getattr(brdf, "model_name", type(brdf).__name__)
    if name in TEXTURE_RULES:
        return TEXTURE_RULES[name](brdf, wi, wo, scale)
    if name not in _DIFFUSE_ATTR:
        raise SceneError(f"BRDF model {name!r} cannot be textured; texturable models: {_texturable()}")
    kd = getattr(brdf, _DIFFUSE_ATTR[name]).to(wi.dtype)
    f = brdf.eval_local(wi, wo)
    return f + lambert_value(kd * (scale.to(wi.dtype) - 1.0), wi, wo)
