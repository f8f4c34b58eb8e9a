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
* A non-negative parameter of J x 3 values (``factored_1d``'s ``coefficients``) is a curve:
  ``"curve"``, edited as text, one band per line, on the selected object's own bands.
* Models built from data (``nbrdf``: a network per material; ``merl``: a measured table)
  get one ``"choice"`` parameter, the material, from the shared data files
  (:func:`data_models`); without the file the model is left out and the page says why.
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
        options: the values of a ``"choice"``.
    """

    name: str
    kind: str
    lo: float
    hi: float
    default: Any
    options: tuple[str, ...] = ()


@dataclass(frozen=True)
class ModelChoice:
    """An entry of the model menu: a registered model and the fixed options of a variant."""

    label: str
    model: str
    fixed: tuple[tuple[str, str], ...] = ()
    data: ParamSpec | None = None

    @property
    def on_bands(self) -> bool:
        """True for the models whose values are a curve on the object's own bands."""
        return self.model.startswith("factored_1d")

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
    data = data_models()
    for name in available():
        if name in data:
            entry = data[name]
            if isinstance(entry, str):
                skipped[name] = entry
            else:
                choices.append(entry)
            continue
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


def data_models() -> dict[str, ModelChoice | str]:
    """The models built from data files: model name -> its menu entry (a ``"choice"`` of the
    file's materials), or the reason it is left out (the file is not in the shared data)."""
    from ..brdf import NBRDF
    from ..data import data_path
    from ..io.merl import load_merl_table

    out: dict[str, ModelChoice | str] = {}
    weights = data_path("merl", "nbrdf_merl100_weights.npz", required=False)
    if weights is None:
        out["nbrdf"] = "needs the NBRDF weights merl/nbrdf_merl100_weights.npz (torch-brdf fetch-data): not found"
    else:
        names = tuple(NBRDF.names(weights))
        spec = ParamSpec("material", "choice", 0.0, 0.0, names[0], names)
        out["nbrdf"] = ModelChoice("nbrdf (measured, network)", "nbrdf", (("weights", str(weights)),), spec)
    full = data_path("merl", "merl100_f16.npz", required=False)
    table = full or data_path("merl", "merl_nbrdf_sample_f16.npz", required=False)
    if table is None:
        out["merl"] = "needs a MERL table merl/merl100_f16.npz in the data folder (see getting started): not found"
    else:
        names = tuple(load_merl_table(table).names)
        spec = ParamSpec("material", "choice", 0.0, 0.0, names[0], names)
        label = "merl (measured table)" if full else "merl (sample tables from NBRDF; the measured files are missing)"
        out["merl"] = ModelChoice(label, "merl", (("table", str(table)),), spec)
    return out


def choice_specs(choice: ModelChoice) -> list[ParamSpec]:
    """The controls of a menu entry: its data choice, or the model's own parameters."""
    if choice.data is not None:
        return [choice.data]
    return param_specs(choice.model, dict(choice.fixed))


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
                curve = value.ndim == 2 and value.shape[1] == 3 and isinstance(transform, Clamped)
                if curve and name in ctor and transform.lo == 0 and not math.isfinite(transform.hi):
                    specs.append(ParamSpec(name, "curve", 0.0, math.inf, None))
                else:
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
        if s.kind in ("choice", "curve"):
            if v is not None:
                out[s.name] = v
            continue
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


def curve_to_text(c) -> str:
    """(J, 3) coefficients -> one line ``r g b`` per band (what the curve box shows)."""
    t = torch.as_tensor(c, dtype=torch.float64).reshape(-1, 3)
    return "\n".join(" ".join(f"{float(x):.6g}" for x in row) for row in t)


def text_to_curve(text: str, J: int) -> list[list[float]]:
    """The curve box's text -> (J, 3) nested lists; a line of one number is grey. Raises
    ValueRangeError naming the line at fault (count, not a number, negative)."""
    from ..errors import ValueRangeError

    rows = []
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    if len(lines) != J:
        raise ValueRangeError(f"coefficients: the object has {J} bands; got {len(lines)} lines")
    for k, line in enumerate(lines, 1):
        parts = line.replace(",", " ").split()
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise ValueRangeError(f"coefficients line {k}: {line!r} is not 1 or 3 numbers") from None
        if len(vals) not in (1, 3) or not all(math.isfinite(v) for v in vals):
            raise ValueRangeError(f"coefficients line {k}: {line!r} is not 1 or 3 finite numbers")
        if min(vals) < 0:
            raise ValueRangeError(f"coefficients line {k}: {line!r}: coefficients must be >= 0")
        rows.append(vals * 3 if len(vals) == 1 else vals)
    return rows
