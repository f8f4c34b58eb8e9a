"""The editor's material form, generated from each model's own parameter list.

A model's parameters are the constrained parameters it registers (``raw_<name>`` behind a
:class:`~torch_brdf.brdf.Clamped` or :class:`~torch_brdf.brdf.Positive` transform), found by
walking the module tree of a default instance (so a distribution's ``exponent`` inside
``distribution_based`` is found too). Nothing here lists a model's parameters by hand:

* ``Clamped(lo, hi)`` gives the slider's bounds; RGB parameters (shape (3,)) become colour
  pickers.
* ``Positive`` parameters have no upper bound of their own; their range is what the model's
  constructor accepts, probed on the decades 1e-6 ... 1e6 (e.g. Blinn-Phong's exponent
  [1e-3, 1e4], Ward's alpha [1e-4, 1]), shown on a log slider.
* A constrained parameter whose name is not a constructor argument (Lambert's
  ``reflectance``, given as ``albedo``) maps to the one numeric constructor argument left.
"""

from __future__ import annotations

import inspect
import math
from dataclasses import dataclass
from typing import Any

import torch

from ..brdf import available, create
from ..brdf.base import Clamped, ConstrainedModule
from ..errors import TorchBRDFError

#: constructor options that select a variant of a model, offered as separate menu entries
VARIANTS: dict[str, tuple[str, tuple[str, ...]]] = {"cook_torrance": ("distribution", ("ggx", "beckmann"))}
#: labels of the variants (the name designers know)
VARIANT_LABELS = {("cook_torrance", "ggx"): "GGX", ("cook_torrance", "beckmann"): "Beckmann"}
_DECADES = [10.0**k for k in range(-6, 7)]


@dataclass(frozen=True)
class ParamSpec:
    """One editable parameter of a model.

    Attributes:
        name: keyword of the model's constructor (``create(model, **{name: value})``).
        kind: ``"rgb"`` (shape (3,), a colour picker), ``"linear"`` (bounded slider) or
            ``"log"`` (log slider over a positive range).
        lo, hi: the accepted range.
        default: the default value (RGB as a 3-tuple).
    """

    name: str
    kind: str
    lo: float
    hi: float
    default: Any


@dataclass(frozen=True)
class ModelChoice:
    """An entry of the model menu: a registered model and the fixed options of a variant."""

    label: str
    model: str
    fixed: tuple[tuple[str, str], ...] = ()

    def material(self, values: dict[str, Any]) -> dict[str, Any]:
        """The material dict ``{"type": model, **fixed, **values}``."""
        return {"type": self.model, **dict(self.fixed), **values}


def model_choices() -> tuple[list[ModelChoice], dict[str, str]]:
    """Every registered model that a form can edit, and why the others are left out.

    Returns:
        (choices, skipped): menu entries in :func:`~torch_brdf.brdf.available` order (variants
        expanded), and model name -> reason for the models that need data instead of values
        (``merl``: a table; ``nbrdf``: a network; ``factored_1d*``: a curve of J coefficients).
    """
    choices, skipped = [], {}
    for name in available():
        try:
            specs = param_specs(name)
        except TorchBRDFError as exc:
            skipped[name] = f"needs data, not values ({exc})"
            continue
        if any(s is None for s in specs):
            skipped[name] = "its coefficients are a curve, not a few values"
            continue
        if name in VARIANTS:
            key, options = VARIANTS[name]
            for opt in options:
                label = f"{VARIANT_LABELS.get((name, opt), opt)} ({name})"
                choices.append(ModelChoice(label, name, ((key, opt),)))
        else:
            choices.append(ModelChoice(name, name))
    return choices, skipped


def _constructor_names(model: str) -> list[str]:
    from ..brdf.base import _REGISTRY  # the registry is the one source of the constructors

    sig = inspect.signature(_REGISTRY[model].__init__)
    return [p.name for p in sig.parameters.values() if p.name != "self" and p.kind is p.POSITIONAL_OR_KEYWORD]


def _accepts(model: str, fixed: dict[str, Any], name: str, value: float) -> bool:
    try:
        create(model, **fixed, **{name: value})
    except TorchBRDFError:
        return False
    return True


def param_specs(model: str, fixed: dict[str, Any] | None = None) -> list[ParamSpec | None]:
    """The editable parameters of ``model`` (None for a parameter no form can hold).

    Args:
        model: a registered model name.
        fixed: constructor options of a variant (e.g. ``{"distribution": "ggx"}``).
    Raises:
        ValueRangeError: the model cannot be built from defaults (it needs data).
    """
    fixed = dict(fixed or {})
    brdf = create(model, **fixed)
    ctor = _constructor_names(model)
    specs: list[ParamSpec | None] = []
    for mod in brdf.modules():
        if not isinstance(mod, ConstrainedModule):
            continue
        for cname, transform in mod._constraints.items():
            value = getattr(mod, cname).detach().to(torch.float64)
            name = cname
            if name not in ctor and mod is brdf:
                left = [n for n in ctor if n not in mod._constraints and n not in fixed and _numeric_default(model, n)]
                name = left[0] if len(left) == 1 else cname
            if value.numel() not in (1, 3):
                specs.append(None)
                continue
            if isinstance(transform, Clamped):
                if not math.isfinite(transform.hi):
                    specs.append(None)
                    continue
                lo, hi, kind = transform.lo, transform.hi, ("rgb" if value.numel() == 3 else "linear")
            else:
                ok = [v for v in _DECADES if _accepts(model, fixed, name, v)]
                lo, hi, kind = (min(ok), max(ok), "log") if ok else (1e-3, 1e3, "log")
            default = tuple(_short(x) for x in value.tolist()) if value.numel() == 3 else _short(float(value))
            specs.append(ParamSpec(name, kind, float(lo), float(hi), default))
    return specs


def _short(x: float) -> float:
    """A float32 default shown as the value it was written as (0.2, not 0.20000000298)."""
    return float(f"{x:.6g}")


def _numeric_default(model: str, name: str) -> bool:
    from ..brdf.base import _REGISTRY

    p = inspect.signature(_REGISTRY[model].__init__).parameters[name]
    return isinstance(p.default, (int, float)) and not isinstance(p.default, bool)


def material_values(material: dict[str, Any], specs: list[ParamSpec]) -> dict[str, Any]:
    """Values of ``specs`` from a material dict, defaults where it says nothing; RGB as 3-tuples."""
    out = {}
    for s in specs:
        v = material.get(s.name, s.default)
        if s.kind == "rgb":
            t = torch.as_tensor(v, dtype=torch.float64).reshape(-1).expand(3)
            out[s.name] = tuple(float(x) for x in t)
        else:
            out[s.name] = float(v)
    return out


def linear_to_hex(rgb) -> str:
    """Linear RGB in [0, 1] -> ``#rrggbb`` (sRGB-encoded, what a colour picker shows)."""
    t = torch.as_tensor(rgb, dtype=torch.float64).clamp(0, 1)
    s = torch.where(t <= 0.0031308, 12.92 * t, 1.055 * t.pow(1 / 2.4) - 0.055)
    return "#" + "".join(f"{round(float(x) * 255):02x}" for x in s)


def hex_to_linear(color: str) -> tuple[float, float, float]:
    """``#rrggbb`` (sRGB) -> linear RGB in [0, 1]; raises ValueRangeError on anything else."""
    from ..errors import ValueRangeError

    c = color.strip().lstrip("#")
    if len(c) == 3:
        c = "".join(ch * 2 for ch in c)
    try:
        s = torch.tensor([int(c[k : k + 2], 16) / 255 for k in (0, 2, 4)], dtype=torch.float64)
    except ValueError:
        raise ValueRangeError(f"not a colour: {color!r} (expected #rrggbb)") from None
    if len(c) != 6:
        raise ValueRangeError(f"not a colour: {color!r} (expected #rrggbb)")
    lin = torch.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055).pow(2.4))
    return tuple(float(x) for x in lin)
