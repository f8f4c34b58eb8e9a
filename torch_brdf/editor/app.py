"""The material editor as an ipywidgets application (JupyterLab or a Voilà page).

``EditorApp(config).show()`` in a notebook; ``torch-brdf editor SCENE_OR_TENSORS`` serves it
through Voilà (:mod:`torch_brdf.editor.server`). Layout: the frame (click an object to
select and freeze it), the per-bounce view and bounce count, exposure; the material panel
(model menu, one control per parameter of the model's own list, a typed-value box that the
model validates, Fresnel ``f0`` where the tensors have the layer); the lobe (polar plot and
lit sphere); the reference (background path trace, progress, cancel, difference image and
relative RMSE); an "open" box to load other tensors or another scene. Every error is shown
as a message on the page; the kernel and the server stay up.
"""

from __future__ import annotations

import asyncio
import html
import time
import traceback
from typing import Any

import ipywidgets as W
import torch
from IPython.display import display

from ..brdf import Factored1D, create
from ..errors import TorchBRDFError
from .form import Bands, MaterialForm
from .lobe import lit_sphere, lobe_svg
from .params import model_choices
from .session import EditorSession, ReferenceJob, checked_create, load_source
from .widgets import FrameView, srgb8_fast

DEFAULTS: dict[str, Any] = {
    "source": "cornell_box_glossy",
    "scene": None,
    "resolution": 128,
    "series": "64,1,1,1",
    "spp": 16,
    "seed": 0,
    "cache_dir": None,
    "reference_spp": 16,
    "display_width": 512,
    # torch threads of the kernel: "auto" times three frozen frames on 1 and on 2 threads when
    # a view opens and keeps 2 only if clearly faster. On a loaded 2-core machine two OpenMP
    # threads that spin-wait made a 128² edit 20-100x slower (projection 155 ms vs 2.3 ms, frame
    # 120 vs 9 ms at load 18); on a quiet one they halve a 512² frame. An int fixes the count;
    # 0 leaves torch's setting alone.
    "threads": "auto",
    # a GPLVM fit (GPLVMFit file) of NBRDF materials: shows the measured-material latent map
    "gplvm": None,
    "nbrdf_weights": None,
    # the relighting tab: a scene and its visibility record (torch-brdf precompute-visibility)
    "relight_scene": None,
    "relight_visibility": None,
    "relight_resolution": None,
    # frame messages carry a CRC-32 of the whole frame and the page checks the frame it assembled
    # from the changed tiles (the browser tests; costs ~1 ms a 512² frame)
    "verify_frames": False,
    # memory bound of the frozen states the renderer keeps per object, so that switching back to
    # an object costs no new freeze (PolynomialRenderer.max_frozen_bytes)
    "frozen_cache_mb": 2048,
    # "messages": RGBE frames in binary messages, tone mapped on the page (FrameView); "state":
    # the earlier transport, kernel-side 8-bit sRGB in the widget's synced state and the page's
    # latency sent back per frame (the benchmark's baseline)
    "frame_transport": "messages",
}


def _rgb8(img: torch.Tensor, exposure: float = 0.0):
    return srgb8_fast(img, exposure).numpy()


def _difference_rgb(diff: torch.Tensor) -> torch.Tensor:
    """Signed luminance difference (H, W, 3) -> false colour (red: editor brighter, blue:
    reference brighter), scaled so the 99th percentile of |difference| is full intensity."""
    d = (diff * torch.tensor([0.2126, 0.7152, 0.0722])).sum(-1)
    scale = float(torch.quantile(d.abs().flatten().double(), 0.99)) or 1.0
    v = (d / scale).clamp(-1, 1)
    out = torch.stack([v.clamp_min(0), torch.zeros_like(v), (-v).clamp_min(0)], -1)
    return out.float()


class EditorApp:
    """The editor page. ``config`` keys: see :data:`DEFAULTS` (``source``: tensors file or
    scene; ``scene``: the scene of a tensors file; precomputation settings for a scene)."""

    def __init__(self, config: dict[str, Any] | None = None):
        self.config = {**DEFAULTS, **(config or {})}
        threads = self.config.get("threads")
        if threads and threads != "auto":
            torch.set_num_threads(int(threads))
        self.session: EditorSession | None = None
        self.job: ReferenceJob | None = None
        self._busy = False  # True while controls are rebuilt (their observers stay quiet)
        self._lobe_timer: asyncio.TimerHandle | None = None
        self.choices, self.skipped = model_choices()
        self._build()
        self.open(self.config["source"], self.config.get("scene"))

    # -- layout ----------------------------------------------------------------------------------
    def _build(self) -> None:
        dw = int(self.config["display_width"])
        self.title = W.HTML("<h3 style='margin:4px 0'>torch_brdf material editor</h3>")
        self.status = W.HTML("", layout=W.Layout(min_height="20px"))
        self.message = W.HTML("", layout=W.Layout(min_height="20px"))
        self.frame = FrameView(
            role="tb-main",
            measure=True,
            display_width=dw,
            verify=bool(self.config["verify_frames"]),
            transport=self.config["frame_transport"],
        )
        self.frame.on_msg(self._on_frame_msg)
        self.view = W.Dropdown(options=["image"], value="image", description="view")
        self.bounces = W.IntSlider(value=1, min=1, max=1, description="bounces", continuous_update=False)
        self.exposure = W.FloatSlider(value=0.0, min=-4, max=4, step=0.25, description="exposure")
        self.exposure.add_class("tb-exposure")
        for w in (self.view, self.bounces):
            w.observe(lambda _c: self._redraw(), "value")
        self.selected = W.HTML("<b>click an object</b> in the frame to edit its material")
        bands = Bands(
            self._band_curve,
            lambda: self.session.basis(self.session.selected).J,
            lambda c, model: self.session.band_material(self.session.selected, c, model),
        )
        self.panel = MaterialForm(self.choices, self._apply_material, self._guard, bands)
        self.f0 = W.FloatSlider(value=1.0, min=0.0, max=1.0, step=0.01, description="Fresnel f0")
        self.f0.observe(lambda _c: self._apply(), "value")
        self.f0_box = W.VBox([])
        self.lobe = W.HTML("")
        self.sphere = FrameView(role="tb-sphere", display_width=160)
        self.theta_i = W.FloatSlider(value=45.0, min=0.0, max=85.0, step=1.0, description="θi (lobe)")
        self.theta_i.observe(lambda _c: self._draw_lobe(), "value")
        self.ref_spp = W.BoundedIntText(value=int(self.config["reference_spp"]), min=1, max=65536, description="spp")
        self.ref_button = W.Button(description="Reference", button_style="info", icon="play")
        self.ref_button.on_click(lambda _b: self.start_reference())
        self.cancel_button = W.Button(description="Cancel", icon="stop", disabled=True)
        self.cancel_button.on_click(lambda _b: self.cancel_reference())
        self.ref_progress = W.IntProgress(value=0, min=0, max=1, description="reference")
        self.ref_result = W.HTML("")
        self.ref_image = FrameView(role="tb-reference", display_width=dw // 2)
        self.diff_image = FrameView(role="tb-difference", display_width=dw // 2)
        self.latent = None
        self.latent_view = FrameView(role="tb-latent", display_width=192)
        self.latent_view.on_msg(self._on_latent_msg)
        self.latent_info = W.HTML("")
        self.latent_x = W.Dropdown(options=[0], value=0, description="x dim", layout=W.Layout(width="140px"))
        self.latent_y = W.Dropdown(options=[1], value=1, description="y dim", layout=W.Layout(width="140px"))
        for w in (self.latent_x, self.latent_y):
            w.add_class("tb-latent-dim")
            w.observe(lambda _c: self._guard(self._on_latent_dims), "value")
        self.latent_dims = W.HBox([self.latent_x, self.latent_y])
        self.latent_box = W.VBox([])
        self._build_keep()
        self.open_path = W.Text(placeholder="tensors .npz, built-in scene name or scene .toml", description="open")
        self.open_button = W.Button(description="Open")
        self.open_button.on_click(lambda _b: self.open(self.open_path.value.strip()))
        note = "; ".join(f"{k}: {v}" for k, v in sorted(self.skipped.items())) or "none"
        self.menu_note = W.HTML(f"<small class='tb-menu-note'>not in the menu: {html.escape(note)}</small>")
        left = W.VBox([self.frame, W.HBox([self.view, self.bounces]), self.exposure])
        right = W.VBox(
            [self.selected, self.panel.model, self.panel.box, self.f0_box, self.menu_note],
            layout=W.Layout(min_width="380px"),
        )
        lobe = W.VBox([W.HTML("<b>lobe</b> (plane of incidence) and lit sphere"), W.HBox([self.lobe, self.sphere])])
        self.latent_box.children = [
            W.HTML(
                "<b>measured materials</b> (GPLVM latent map; white: near the measured materials, "
                "blue: uncertain, red: the model's prediction is not a valid BRDF): click to blend; "
                "a click outside the yellow edge snaps to the nearest trusted point"
            ),
            self.latent_dims,
            W.HBox([self.latent_view, self.latent_info]),
        ]
        self.latent_box.layout.display = "none"
        reference = W.VBox(
            [
                W.HTML("<b>reference</b>: path trace of the current materials, compared with the editor"),
                W.HBox([self.ref_spp, self.ref_button, self.cancel_button]),
                self.ref_progress,
                self.ref_result,
                W.HBox([self.ref_image, self.diff_image]),
            ]
        )
        main = W.VBox(
            [
                W.HBox([left, W.VBox([right, lobe, self.theta_i, self.latent_box])]),
                self.keep_box,
                reference,
                W.HBox([self.open_path, self.open_button]),
            ]
        )
        self.tabs = W.Tab([main, self._build_relight()])
        # the page tone maps the linear frames: an exposure change repaints there, in the browser
        # (jslink) and in the kernel's copy of the value
        for view in (self.frame, self.ref_image, self.rl_frame):
            W.jslink((self.exposure, "value"), (view, "exposure"))
        self.exposure.observe(self._on_exposure, "value")
        self.tabs.set_title(0, "multibounce")
        self.tabs.set_title(1, "relighting")
        self.root = W.VBox([self.title, self.status, self.message, self.tabs])

    def _on_exposure(self, change) -> None:
        for view in (self.frame, self.ref_image, self.rl_frame):
            view.exposure = float(change["new"])
        if self.frame.transport == "state":  # the baseline tone maps in the kernel
            self._redraw()

    # -- undo, A/B, save, export -------------------------------------------------------------------
    def _build_keep(self) -> None:
        def button(text: str, cls: str, icon: str, fn) -> W.Button:
            b = W.Button(description=text, icon=icon, layout=W.Layout(width="auto"))
            b.add_class(cls)
            b.on_click(lambda _b: self._guard(fn))
            return b

        self.undo_button = button("Undo", "tb-undo", "undo", self.undo)
        self.redo_button = button("Redo", "tb-redo", "repeat", self.redo)
        self.ab_button = button("A/B: showing the edit", "tb-ab", "exchange", self.toggle_ab)
        self.save_path = W.Text(placeholder="scene file (.toml) to save the edited scene to", description="save")
        self.save_path.add_class("tb-save-path")
        self.save_button = button("Save", "tb-save", "save", self.save)
        self.export_format = W.Dropdown(options=["mitsuba", "gltf", "merl"], value="mitsuba", description="format")
        self.export_format.add_class("tb-export-format")
        self.export_path = W.Text(placeholder="file for the selected material", description="export")
        self.export_path.add_class("tb-export-path")
        self.export_button = button("Export", "tb-export", "download", self.export)
        self.keep_box = W.VBox(
            [
                W.HBox([self.undo_button, self.redo_button, self.ab_button]),
                W.HBox([self.save_path, self.save_button]),
                W.HBox([self.export_path, self.export_format, self.export_button]),
            ]
        )

    def _after_material_change(self, obj: str | None) -> None:
        s = self.session
        if obj is not None and obj == s.selected:
            self._busy = True
            try:
                self.select(obj)  # the form shows the material now in force
            finally:
                self._busy = False
        self._redraw()

    def undo(self) -> None:
        """Undo the last material edit (a message when there is none)."""
        if self.session is None:
            return
        obj = self.session.undo()
        if obj is None:
            self.info("nothing to undo")
            return
        self._after_material_change(obj)
        self.info(f"undid an edit of {obj}")

    def redo(self) -> None:
        """Redo the last undone edit."""
        if self.session is None:
            return
        obj = self.session.redo()
        if obj is None:
            self.info("nothing to redo")
            return
        self._after_material_change(obj)
        self.info(f"redid an edit of {obj}")

    def toggle_ab(self) -> None:
        """Switch between the current edit and the saved (or opened) materials."""
        if self.session is None:
            return
        saved = self.session.toggle_ab()
        self.ab_button.description = "A/B: showing the saved" if saved else "A/B: showing the edit"
        self._after_material_change(self.session.selected)

    def save(self) -> None:
        """Save the edited scene to the file in the save box (a TOML scene file)."""
        path = self.save_path.value.strip()
        if not path:
            self.error("give a scene file to save to (e.g. out/edited.toml)")
            return
        out = self.session.save(path)
        self.ab_button.description = "A/B: showing the edit"
        self.info(f"saved the scene with its edits to {out}")

    def export(self) -> None:
        """Export the selected object's material to the file in the export box."""
        s, path = self.session, self.export_path.value.strip()
        if s is None or s.selected is None:
            self.error("select an object first")
            return
        if not path:
            self.error("give a file to export the material to")
            return
        rep = s.export(s.selected, path, self.export_format.value)
        how = "exact" if rep.exact else f"fitted, error {rep.error:.3g}"
        self.info(f"exported {s.selected} as {rep.target} ({how}) to {rep.path}")

    # -- the relighting tab ------------------------------------------------------------------------
    def _build_relight(self) -> W.VBox:
        """Rotate the environment, orbit the view, edit materials: triple products (Inger et
        al.) on a scene with a visibility record (``relight_scene`` + ``relight_visibility``)."""
        c = self.config
        self.relight = None
        self.rl_frame = FrameView(
            role="tb-relight", display_width=int(c["display_width"]), verify=bool(c["verify_frames"])
        )
        self.rl_frame.on_msg(lambda _w, m, _b: self._guard(self._on_relight_click, m))
        wide = {"description_width": "initial"}
        self.rl_rotation = W.FloatSlider(0.0, min=0.0, max=360.0, step=5.0, description="environment °", style=wide)
        self.rl_orbit = W.FloatSlider(0.0, min=-90.0, max=90.0, step=5.0, description="view orbit °", style=wide)
        self.rl_rotation.add_class("tb-rl-rotation")
        self.rl_orbit.add_class("tb-rl-orbit")
        self.rl_rotation.observe(lambda ch: self._guard(self._relight_set, "rotation", ch["new"]), "value")
        self.rl_orbit.observe(lambda ch: self._guard(self._relight_set, "orbit", ch["new"]), "value")
        self.rl_selected = W.HTML("")
        self.rl_panel = MaterialForm(self.choices, self._relight_material, self._guard, None, prefix="tb-rl")
        if not (c.get("relight_scene") and c.get("relight_visibility")):
            self.rl_selected.value = (
                "<i class='tb-rl-none'>no scene with a visibility record: start the editor with "
                "--relight SCENE --visibility VIS.npz (from torch-brdf precompute-visibility)</i>"
            )
        else:
            try:
                self._open_relight(c["relight_scene"], c["relight_visibility"], c.get("relight_resolution"))
            except Exception as exc:  # shown in the tab (the page's message line is the other tab's)
                self.relight = None
                text = str(exc) if isinstance(exc, TorchBRDFError) else f"{type(exc).__name__}: {exc}"
                self.rl_selected.value = f"<div class='tb-error' style='color:#b00020'>{html.escape(text)}</div>"
        controls = W.VBox(
            [self.rl_selected, self.rl_panel.model, self.rl_panel.box], layout=W.Layout(min_width="380px")
        )
        return W.VBox([W.HBox([W.VBox([self.rl_frame, self.rl_rotation, self.rl_orbit]), controls])])

    def _open_relight(self, scene: str, visibility: str, resolution: int | None = None) -> None:
        from .relight import RelightSession

        try:
            self.relight = RelightSession(scene, visibility, resolution)
        except TorchBRDFError as exc:
            raise TorchBRDFError(f"could not open the relighting scene {scene!r} with {visibility!r}: {exc}") from None
        rl = self.relight
        editable = [o for o in rl.objects if o in rl.materials]
        self._relight_select(editable[0])
        self._relight_draw()

    def _relight_select(self, obj: str) -> None:
        rl = self.relight
        rl.select(obj)
        self.rl_selected.value = (
            f"<span class='tb-rl-selected' data-object='{html.escape(obj)}'>selected: <b>{html.escape(obj)}</b></span>"
            " · click an object in the frame"
        )
        self.rl_panel.show(rl.materials[obj])

    def _on_relight_click(self, content) -> None:
        if self.relight is None or not (isinstance(content, dict) and content.get("event") == "click"):
            return
        obj = self.relight.object_at(int(content["x"]), int(content["y"]))
        if obj is None:
            self.info("nothing there (the environment)")
            return
        self._relight_select(obj)

    def _relight_set(self, what: str, value: float) -> None:
        if self.relight is None:
            return
        (self.relight.set_rotation if what == "rotation" else self.relight.set_orbit)(float(value))
        self._relight_draw()

    def _relight_material(self, material: dict[str, Any]) -> None:
        rl = self.relight
        if rl is None or rl.selected is None:
            return
        rl.set_material(rl.selected, material)
        self.message.value = ""
        self._relight_draw()

    def _relight_draw(self) -> None:
        rl = self.relight
        t0 = time.perf_counter()
        img = rl.render()
        st = rl.stats
        extra = f" · {st.vertices} vertices" if st is not None else ""
        self.rl_frame.show_linear(
            img,
            f"triple products {rl.last_frame_s * 1e3:.1f} ms · kernel {(time.perf_counter() - t0) * 1e3:.1f} ms{extra}"
            f" · environment {rl.rotation_deg:.0f}° · orbit {rl.orbit_deg:.0f}°",
        )

    def show(self) -> None:
        display(self.root)

    # -- messages --------------------------------------------------------------------------------
    def error(self, text: str) -> None:
        self.message.value = f"<div class='tb-error' style='color:#b00020'><b>error:</b> {html.escape(text)}</div>"

    def info(self, text: str) -> None:
        self.message.value = f"<div class='tb-info' style='color:#555'>{html.escape(text)}</div>"

    def _guard(self, fn, *args):
        """Run a handler; bad input becomes a message, never an exception out of the kernel."""
        try:
            return fn(*args)
        except TorchBRDFError as exc:
            self.error(str(exc))
        except Exception as exc:  # the page must survive anything a handler meets
            self.error(f"{type(exc).__name__}: {exc}")
            traceback.print_exc()
        return None

    # -- loading ---------------------------------------------------------------------------------
    def open(self, source: str, scene: str | None = None) -> None:
        """Load tensors or a scene (precomputing if needed); on failure show why and keep the
        current session (if any)."""
        if not source:
            self.error("nothing to open: give a tensors file, a built-in scene name or a scene .toml")
            return
        self.status.value = f"loading {html.escape(source)} …"
        c = self.config
        try:
            tensors, sc, note = load_source(
                source, scene, c["resolution"], c["series"], c["spp"], c["seed"], c["cache_dir"], progress=False
            )
            session = EditorSession(tensors, sc, frozen_cache_mb=float(c["frozen_cache_mb"]))
        except TorchBRDFError as exc:
            self.status.value = "" if self.session is None else self.status.value
            self.error(f"could not open {source!r}: {exc}")
            return
        except Exception as exc:
            self.error(f"could not open {source!r}: {type(exc).__name__}: {exc}")
            return
        self.session = session
        self.cancel_reference()
        self.status.value = html.escape(
            f"{note} · {tensors.width}x{tensors.height}, series {tensors.series.key}, "
            f"{tensors.series.bounces} bounces · object ids from {session.ids_source}"
            + ("" if sc is not None else " · no scene: no reference")
        )
        self.message.value = ""
        self._busy = True
        self.view.options, self.view.value = session.views(), "image"
        self.bounces.max, self.bounces.value = session.bounces, session.bounces
        self._busy = False
        self.ref_button.disabled = sc is None
        if c.get("gplvm") and self.latent is None:
            self._guard(self._load_latent)
        start = "back" if "back" in session.editable else session.editable[0]
        self._guard(self.select, start)
        if self.config.get("threads") == "auto" and session.selected is not None:
            n = self._pick_threads()
            self.status.value += f" · {n} torch thread{'s' if n > 1 else ''} (timed)"
        self._redraw()

    def _pick_threads(self) -> int:
        """1 or 2 torch threads, whichever renders the frozen frame faster (median of 3)."""
        import os

        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        best = {}
        for n in (1, 2) if cores > 1 else (1,):
            torch.set_num_threads(n)
            times = []
            for _ in range(3):
                self.session.render()
                times.append(self.session.last_frame_s)
            best[n] = sorted(times)[1]
        n = 2 if 2 in best and best[2] < 0.7 * best[1] else 1
        torch.set_num_threads(n)
        return n

    # -- measured materials ------------------------------------------------------------------------
    def _load_latent(self) -> None:
        from .latent import LatentMap

        self.latent = LatentMap(self.config["gplvm"], self.config.get("nbrdf_weights"))
        self._busy = True
        dims = list(range(self.latent.q))
        self.latent_x.options, self.latent_y.options = dims, dims
        self.latent_x.value, self.latent_y.value = self.latent.dims
        self._busy = False
        self.latent_dims.layout.display = None if self.latent.q > 2 else "none"  # q = 2: one slice
        self._show_latent()
        self.latent_box.layout.display = None

    def _show_latent(self) -> None:
        a, b = self.latent.dims
        trusted = float(self.latent.trusted.float().mean())
        self.latent_view.show(
            self.latent.image(),
            f"{len(self.latent.names)} materials, latent dims {a}-{b} of {self.latent.q} · "
            f"trusted {trusted:.0%} (edge yellow; blue: uncertain, red: invalid prediction)",
        )

    def _on_latent_dims(self) -> None:
        """Another pair of latent dimensions (the other dimensions stay at the latents' mean)."""
        if self._busy or self.latent is None:
            return
        dims = (int(self.latent_x.value), int(self.latent_y.value))
        if dims[0] == dims[1]:
            raise TorchBRDFError(f"the latent map needs two different dimensions; got {dims[0]} twice")
        self.latent.set_dims(dims)
        self._show_latent()

    def _on_latent_msg(self, _widget, content, _buffers) -> None:
        if isinstance(content, dict) and content.get("event") == "click":
            self._guard(self.pick_latent, int(content["x"]), int(content["y"]))

    def pick_latent(self, x: int, y: int) -> None:
        """Give the selected object the measured blend at latent-map pixel (x, y)."""
        s = self.session
        if self.latent is None or s is None or s.selected is None:
            return
        self.latent_info.value = "projecting the measured materials onto the bands …"
        c, info = self.latent.pick(s, s.selected, x, y)
        s.set_material(s.selected, self.latent.material(s, s.selected, c))
        heavy = ", ".join(f"{n} {w:+.2f}" for n, w in info["heaviest"])
        near = ", ".join(n for n, _ in info["nearest"])
        text = html.escape(
            f"latent {info['latent']} · variance {info['variance']:.3f} · heaviest weights: {heavy}"
            f" · nearest materials: {near}"
        )
        px, py = info["picked"]
        warn = info["warning"]
        note = (
            f"<div class='tb-latent-warning' data-x='{px}' data-y='{py}' style='color:#b36b00'>"
            f"{html.escape(warn)}</div>"
            if warn
            else ""
        )
        self.latent_info.value = f"{note}<span class='tb-latent-pick' data-x='{px}' data-y='{py}'>{text}</span>"
        self.panel.show(s.materials[s.selected], note="measured blend on the bands: edit its curve or pick a model")
        self.message.value = ""
        self._redraw()
        self._draw_lobe()

    # -- selection -------------------------------------------------------------------------------
    def _on_frame_msg(self, _widget, content, _buffers) -> None:
        if isinstance(content, dict) and content.get("event") == "click":
            self._guard(self.click, int(content["x"]), int(content["y"]))

    def click(self, x: int, y: int) -> None:
        """Select the object seen at pixel (x, y)."""
        if self.session is None:
            return
        obj = self.session.object_at(x, y)
        if obj is None:
            self.info(f"nothing at pixel ({x}, {y})")
            return
        self.select(obj, redraw=True)

    def select(self, obj: str, redraw: bool = False) -> None:
        """Select (and freeze) ``obj``; with ``redraw`` a frame answers first, then the form follows."""
        s = self.session
        secs = s.select(obj)  # SceneError for fixed objects -> message
        if redraw:
            self._redraw()
        self.message.value = ""
        mat = s.materials[obj]
        b = s.basis(obj)
        bands = f"{b.J} band{'s' if b.J > 1 else ''} over {b.variable}"
        hint = " (one band: glossy models show as their diffuse equivalent)" if b.J == 1 else ""
        how = {
            "frozen": f"frozen in {secs * 1e3:.0f} ms",
            "kept": f"its kept frozen state ({secs * 1e3:.0f} ms)",
            "refreshed": f"its kept frozen state brought up to date in {secs * 1e3:.0f} ms",
            "active": "frozen",
        }[s.last_select]
        self.selected.value = (
            f"<span class='tb-selected' data-object='{html.escape(obj)}' data-how='{s.last_select}'>"
            f"selected: <b>{html.escape(obj)}</b></span> · {bands}{hint} · {how}"
        )
        self.panel.show(mat)
        self.f0_box.children = [self.f0] if s.has_fresnel(obj) else []
        self._schedule_lobe(0.0)

    # -- the material form (see .form) ------------------------------------------------------------
    @property
    def model(self) -> W.Dropdown:
        return self.panel.model

    @property
    def controls(self) -> dict[str, W.Widget]:
        return self.panel.controls

    def _on_typed(self, name: str, text: str) -> None:
        self.panel.on_typed(name, text)

    def _band_curve(self):
        s = self.session
        c = s.projected.get(s.selected)
        return c if c is not None else s.coefficients(s.selected, checked_create(s.materials[s.selected]))

    def _apply(self) -> None:
        if self._busy or self.session is None or self.session.selected is None:
            return
        self.panel.changed()

    def _apply_material(self, material: dict[str, Any]) -> None:
        s = self.session
        if s is None or s.selected is None:
            return
        obj = s.selected
        f0 = float(self.f0.value) if s.has_fresnel(obj) else None
        s.set_material(obj, material, f0=f0)
        self.message.value = ""
        self._redraw()
        self._schedule_lobe()

    def _schedule_lobe(self, delay: float = 0.15) -> None:
        """Redraw the lobe once the edits pause for ``delay`` s (in a kernel's event loop), so
        that a drag's next input does not wait for it; immediately outside an event loop."""
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            self._draw_lobe()
            return
        if self._lobe_timer is not None:
            self._lobe_timer.cancel()
        self._lobe_timer = loop.call_later(delay, self._draw_lobe)

    # -- drawing ---------------------------------------------------------------------------------
    def _redraw(self) -> None:
        if self._busy or self.session is None:
            return
        s = self.session
        t0 = time.perf_counter()
        img = self._guard(s.render, self.view.value, self.bounces.value)
        if img is None:
            return
        head = f"frame {s.last_frame_s * 1e3:.1f} ms · projection {s.last_set_s * 1e3:.1f} ms · "
        # the caption's kernel time includes the encoding (the caption is made right before sending)
        self.frame.show_linear(img, lambda: head + f"kernel {(time.perf_counter() - t0 + s.last_set_s) * 1e3:.1f} ms")

    def _draw_lobe(self) -> None:
        s = self.session
        if s is None or s.selected is None:
            return
        try:
            brdf = create(s.materials[s.selected])
            b = s.basis(s.selected)
            c = s.projected.get(s.selected)
            c = s.coefficients(s.selected, brdf) if c is None else c
            curve = Factored1D(s.band_basis(s.selected), c.float(), b.quotient)
            self.lobe.value = lobe_svg(brdf, curve, self.theta_i.value)
            self.sphere.show(_rgb8(lit_sphere(brdf)), s.selected)
        except TorchBRDFError as exc:
            self.lobe.value = f"<i>no lobe: {html.escape(str(exc))}</i>"

    # -- reference -------------------------------------------------------------------------------
    def start_reference(self) -> None:
        """Path-trace the current materials in the background; compare when done."""
        s = self.session
        if s is None or s.scene is None:
            self.error("no scene: the reference needs the scene the tensors were precomputed from")
            return
        self.cancel_reference()
        with torch.no_grad():
            editor_image = s.renderer.evaluate()  # the materials the reference will trace
        spp = int(self.ref_spp.value)
        self.ref_progress.max, self.ref_progress.value = spp, 0
        self.ref_result.value = f"path tracing {spp} spp …"
        self.ref_button.disabled, self.cancel_button.disabled = True, False

        def progress(done: int, total: int) -> None:
            self.ref_progress.value = done

        def finished(job: ReferenceJob) -> None:
            self.ref_button.disabled, self.cancel_button.disabled = False, True
            if job.error:
                self.ref_result.value = f"<span class='tb-error' style='color:#b00020'>{html.escape(job.error)}</span>"
            elif job.image is None:
                self.ref_result.value = f"cancelled after {job.done} of {job.spp} spp"
            else:
                self._guard(self._show_reference, editor_image, job)

        self.job = ReferenceJob(s.reference_scene(), spp, s.bounces, seed=1, on_progress=progress, on_done=finished)
        self.job.start()

    def _show_reference(self, editor_image: torch.Tensor, job: ReferenceJob) -> None:
        from ..metrics import relative_rmse

        rmse = relative_rmse(editor_image, job.image, self.session.mask)
        diff = editor_image - job.image
        self.ref_image.show_linear(job.image, f"reference {job.spp} spp, {job.seconds:.1f} s")
        self.diff_image.show(_rgb8(_difference_rgb(diff)), "difference (red: editor brighter)")
        self.ref_result.value = (
            f"<span class='tb-rmse'>relative RMSE {rmse:.4f}</span> (pixels that see no emitter; "
            f"{job.spp} spp reference, {job.seconds:.1f} s; part of it is the reference's own noise)"
        )

    def cancel_reference(self) -> None:
        if self.job is not None and self.job.running:
            self.job.cancel()
