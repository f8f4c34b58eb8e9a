"""The material panel: a model menu and one control per parameter of the model's own list.

Shared by the multibounce view and the relighting tab of :class:`~torch_brdf.editor.app.EditorApp`
(the same controls edit either renderer). The parameters come from :mod:`.params`: RGB
parameters are colour pickers, bounded scalars sliders, positive ones log sliders, each
slider with a typed-value box that the model validates; measured models offer their
materials; a ``factored_1d`` curve is a text box on the object's own bands (only where
the view has bands).
"""

from __future__ import annotations

import html
import math
from collections.abc import Callable
from typing import Any

import ipywidgets as W

from ..errors import TorchBRDFError
from .params import (
    ModelChoice,
    choice_specs,
    curve_to_text,
    hex_to_linear,
    linear_to_hex,
    material_values,
    text_to_curve,
)
from .session import checked_create


class Bands:
    """What a curve control needs from the view: the current curve (J, 3), J, and a
    material dict on the object's bands (``material(coefficients, model)``)."""

    def __init__(self, curve: Callable[[], Any], count: Callable[[], int], material: Callable[[Any, str], dict]):
        self.curve, self.count, self.material = curve, count, material


class MaterialForm:
    """Model menu + controls; ``on_apply(material_dict)`` is called on every edit.

    Args:
        choices: the menu entries (:func:`~.params.model_choices`).
        on_apply: called with the new material dict (inside ``guard``).
        guard: runs a handler and turns errors into a message on the page.
        bands: the view's bands; None leaves out the curve models (no bands to hold them).
        prefix: CSS class prefix of the controls (``tb-param-NAME``, ``tb-typed-NAME``).
    """

    def __init__(
        self,
        choices: list[ModelChoice],
        on_apply: Callable[[dict], None],
        guard: Callable[..., Any],
        bands: Bands | None = None,
        prefix: str = "tb",
    ):
        self.choices = [c for c in choices if bands is not None or not c.on_bands]
        self.on_apply, self.guard, self.bands, self.prefix = on_apply, guard, bands, prefix
        self.model = W.Dropdown(options=[c.label for c in self.choices], description="model")
        self.model.observe(self._on_model, "value")
        self.model.add_class(f"{prefix}-model")
        self.box = W.VBox([])
        self.controls: dict[str, W.Widget] = {}
        self.shown: dict[str, Any] | None = None  # the material last shown or applied
        self.busy = False  # True while controls are rebuilt (their observers stay quiet)
        self.setting = False  # True while the kernel moves a slider to a typed value
        self.exact: dict[str, float] = {}  # slider values kept exact under the browser's grid snap

    # -- showing ---------------------------------------------------------------------------------
    def choice_for(self, material: dict[str, Any]) -> ModelChoice:
        for c in self.choices:
            if c.model == material.get("type") and all(material.get(k, v) == v for k, v in c.fixed):
                return c
        raise TorchBRDFError(f"the material {material!r} has no editable model in the menu")

    def current_choice(self) -> ModelChoice:
        return next(c for c in self.choices if c.label == self.model.value)

    def show(self, material: dict[str, Any], note: str | None = None) -> None:
        """The menu entry of ``material`` and its controls holding the material's values."""
        choice = self.choice_for(material)
        self.busy = True
        self.model.value = choice.label
        self.busy = False
        self.shown = dict(material)
        self.build(choice, material_values(material, choice_specs(choice)))
        if note:
            self.box.children = [W.HTML(f"<i class='tb-blend'>{html.escape(note)}</i>"), *self.box.children]

    def build(self, choice: ModelChoice, values: dict[str, Any]) -> None:
        """One control per parameter of ``choice``'s own list (see :mod:`.params`)."""
        self.busy = True
        self.controls = {}
        self.exact = {}
        rows = []
        p = self.prefix
        for spec in choice_specs(choice):
            v = values.get(spec.name, spec.default)
            if spec.kind == "choice":
                ctl = W.Dropdown(options=list(spec.options), value=v if v in spec.options else spec.default)
                ctl.description = spec.name
                rows.append(ctl)
            elif spec.kind == "curve":
                ctl = W.Textarea(value=curve_to_text(v if v is not None else self.bands.curve()), rows=6)
                ctl.layout.width = "360px"
                ctl.continuous_update = False
                ctl.description = f"{spec.name} (r g b per band)"
                rows.append(ctl)
            elif spec.kind == "rgb":
                ctl = W.ColorPicker(value=linear_to_hex(v), description=spec.name, concise=False)
                rows.append(ctl)
            else:
                if spec.kind == "log":
                    ctl = W.FloatLogSlider(
                        value=v, base=10, min=math.log10(spec.lo), max=math.log10(spec.hi), step=0.02
                    )
                else:
                    ctl = W.FloatSlider(value=v, min=spec.lo, max=spec.hi, step=(spec.hi - spec.lo) / 200)
                ctl.description, ctl.readout = spec.name, False
                ctl.continuous_update = True
                typed = W.Text(value=f"{v:.4g}", continuous_update=False, layout=W.Layout(width="90px"))
                typed.add_class(f"{p}-typed-{spec.name}")
                typed.observe(lambda ch, n=spec.name: self.guard(self.on_typed, n, ch["new"]), "value")
                ctl.observe(lambda ch, s=spec, t=typed: self._slider_moved(s, t, ch), "value")
                rows.append(W.HBox([ctl, typed]))
            if spec.kind not in ("log", "linear"):
                ctl.observe(lambda _c: self.changed(), "value")
            ctl.add_class(f"{p}-param-{spec.name}")
            self.controls[spec.name] = ctl
        self.box.children = rows
        self.busy = False

    # -- reading ---------------------------------------------------------------------------------
    def values(self) -> dict[str, Any]:
        out = {}
        for name, ctl in self.controls.items():
            if isinstance(ctl, W.ColorPicker):
                out[name] = hex_to_linear(ctl.value)
            elif isinstance(ctl, W.Dropdown):
                out[name] = ctl.value
            elif isinstance(ctl, W.Textarea):
                out[name] = text_to_curve(ctl.value, self.bands.count())
            else:
                out[name] = self.exact.get(name, float(ctl.value))
        return out

    def material(self) -> dict[str, Any]:
        """The material dict of the controls' values (a curve on the object's bands)."""
        choice = self.current_choice()
        values = self.values()
        if choice.on_bands:
            return {**self.bands.material(values.pop("coefficients", None), choice.model), **values}
        return choice.material(values)

    # -- events ----------------------------------------------------------------------------------
    def on_typed(self, name: str, text: str) -> None:
        """A typed value: the model checks it; in range it moves the slider, else a message."""
        if self.busy:
            return
        ctl = self.controls[name]
        try:
            value = float(text)
        except ValueError:
            raise TorchBRDFError(f"{name}: {text!r} is not a number") from None
        if math.isclose(value, self.values()[name], rel_tol=1e-3):
            return
        checked_create({**self.material(), name: value})  # out of range: raises
        self.setting = True
        try:
            ctl.value = value
        finally:
            self.setting = False

    def _slider_moved(self, spec, typed: W.Text, change: dict) -> None:
        """A slider's new value. The browser's slider moves every value it is sent to its own
        grid and sends that back (ipywidgets' ``FloatLogSlider`` does so for each value the kernel
        sets, including a new form's first one); such an echo, within half a step of the value
        the kernel holds, is not an edit: it neither re-renders nor clears a message shown for a
        value typed meanwhile, and the material keeps the exact value."""
        if self.busy:
            return
        held = self.exact.get(spec.name, change["old"])
        if not self.setting and _within_half_step(spec, self.controls[spec.name].step, held, change["new"]):
            self.exact[spec.name] = held
            return
        self.exact.pop(spec.name, None)
        typed.value = f"{change['new']:.4g}"
        self.changed()

    def _on_model(self, _change) -> None:
        if self.busy or self.shown is None:
            return
        choice = self.current_choice()
        self.build(choice, material_values(self.shown, choice_specs(choice)))
        self.changed()

    def changed(self) -> None:
        """Apply the controls' material (errors become the page's message)."""
        if self.busy or self.shown is None:
            return
        self.guard(self._apply)

    def _apply(self) -> None:
        material = self.material()
        self.on_apply(material)
        self.shown = material


def _within_half_step(spec, step: float, held: float, new: float) -> bool:
    """True if ``new`` is ``held`` moved to a slider grid of ``step`` (log10 units for log
    sliders), i.e. no farther than half a step."""
    if spec.kind == "log":
        if held <= 0 or new <= 0:
            return False
        return abs(math.log10(new) - math.log10(held)) <= 0.5 * step * (1 + 1e-9)
    return abs(new - held) <= 0.5 * step * (1 + 1e-9)
