r"""The editor's state without any user interface: tensors, renderer, selection, materials.

:class:`EditorSession` owns a :class:`~torch_brdf.render.polynomial.PolynomialRenderer` and
keeps it frozen on the selected object (Ben-Artzi et al. 2008, Eq. 27-28), so that a
material edit costs a projection onto the object's bands and one frozen frame. The widget
application (:mod:`torch_brdf.editor.app`) and the tests drive the same session.

Projection at interactive rates. :func:`torch_brdf.brdf.project` is the float64
cosine-weighted least squares on a ~410k-pair quadrature (about a second per call on two
shared cores). The session gives each object the renderer's
:class:`~torch_brdf.render.material.MaterialProjector` (the same exact cases and Fresnel split)
with a :class:`~torch_brdf.brdf.Projector` (the quadrature, memberships and factorised normal
matrix made once) on a coarser rule
(:data:`FAST_QUADRATURE`, ~10k pairs; the :math:`\theta_h` cells keep the band edges, so band
boxes are still integrated cell-exactly), so an edit evaluates the BRDF on the stored pairs and
solves a factorised J x J system per channel. The coarse rule's difference from
:func:`~torch_brdf.brdf.project` is tested (Blinn-Phong, a function of :math:`\theta_h` alone, agrees to
~1e-6; GGX to a few per cent, its Fresnel and masking depend on :math:`\theta_d`).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from ..brdf import BRDF, create
from ..errors import FileFormatError, SceneError, TorchBRDFError, ValueRangeError
from ..metrics import relative_rmse
from ..records import PolynomialTensors
from ..render import PolynomialRenderer
from ..render.material import MaterialProjector
from ..render.polynomial import apply_scene_textures, emitter_mask
from ..scene import trace_gbuffer
from ..transport import PathTraceSettings, PolynomialSettings, path_trace, precompute_polynomial

#: memory bound of the frozen states the renderer keeps for switching (its ``max_frozen_bytes``)
FROZEN_CACHE_MB = 2048

#: the coarse pair quadrature of interactive projection (see the module docstring)
FAST_QUADRATURE = {"n_theta_d": 2, "n_phi_d": 4, "n_phi_h": 4, "order": 2}


def object_id_buffer(tensors: PolynomialTensors, scene=None) -> tuple[torch.Tensor, str]:
    """Which object each pixel shows: (H, W) int64 object ids (-1: nothing), and how it was found.

    The tensors do not store a primary-hit buffer. With ``scene`` (the scene the tensors were
    precomputed from, same camera size and object names) the buffer comes from the scene's
    G-buffer, primary rays through the pixel centres (``"primary rays"``). Without it, from
    the tensors: every
    entry names its eye object (the block's object), and each pixel takes the object most of
    its entries name (``"tensor entries"``; pixels that see only an emitter or nothing get -1).
    """
    h, w = tensors.height, tensors.width
    if scene is not None and (scene.camera.width, scene.camera.height) == (w, h):
        if [o.name for o in scene.objects] == list(tensors.object_names):
            g = trace_gbuffer(scene)
            ids = torch.full((h * w,), -1, dtype=torch.int64)
            ids[g.pixels] = g.object_id
            return ids.reshape(h, w), "primary rays"
    counts = torch.zeros(tensors.num_objects, h * w)
    for b in tensors.blocks:  # every block's entries belong to its eye object, whatever the bounce
        pix = b.pixels[b.coordinates()[2]]
        counts[b.object_id].index_add_(0, pix, torch.ones(pix.shape[0]))
    ids = torch.where(counts.sum(0) > 0, counts.argmax(0), -1)
    return ids.reshape(h, w), "tensor entries"


def scene_with_materials(scene, materials: dict[str, dict[str, Any]]):
    """A copy of ``scene`` whose named objects use the given material dicts (the geometry and
    its ray tracer are shared; other objects keep their materials)."""
    out = copy.copy(scene)
    out.materials = dict(scene.materials)
    objects = []
    for o in scene.objects:
        if o.name in materials:
            key = f"editor:{o.name}"
            out.materials[key] = dict(materials[o.name])
            o = dataclasses.replace(o, material=key)
        objects.append(o)
    out.objects = objects
    return out


class ReferenceJob:
    """A cancellable background path trace of the current materials (the unbiased reference).

    Passes of one sample per pixel (:func:`~torch_brdf.transport.path_trace` with seed
    ``seed * 1_000_003 + s`` for pass ``s``) are averaged, so progress is reported and a
    cancel takes effect between passes.

    Args:
        scene: the scene with the materials to render (see :func:`scene_with_materials`).
        spp: passes (samples per pixel).
        max_bounces: surface vertices per path (the tensors' bounce count).
        on_progress: called with (passes done, spp) after each pass (from the worker thread).
        on_done: called with the job when it ends (finished, cancelled or failed).
    """

    def __init__(
        self,
        scene,
        spp: int,
        max_bounces: int,
        seed: int = 0,
        on_progress: Callable[[int, int], None] | None = None,
        on_done: Callable[[ReferenceJob], None] | None = None,
    ):
        if spp < 1:
            raise ValueRangeError(f"reference spp must be >= 1; got {spp}")
        self.scene, self.spp, self.max_bounces, self.seed = scene, int(spp), int(max_bounces), int(seed)
        self.on_progress, self.on_done = on_progress, on_done
        self.done = 0
        self.image: torch.Tensor | None = None
        self.error: str | None = None
        self.seconds = 0.0
        self._cancel = threading.Event()
        self._thread = threading.Thread(target=self._run, name="torch_brdf-reference", daemon=True)

    def start(self) -> ReferenceJob:
        self._thread.start()
        return self

    def cancel(self) -> None:
        self._cancel.set()

    @property
    def cancelled(self) -> bool:
        return self._cancel.is_set()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the job; True if it has ended."""
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def _run(self) -> None:
        t0 = time.perf_counter()
        total = None
        try:
            for s in range(self.spp):
                if self._cancel.is_set():
                    break
                img = path_trace(
                    self.scene,
                    PathTraceSettings(spp=1, max_bounces=self.max_bounces),
                    seed=self.seed * 1_000_003 + s,
                    progress=False,
                )
                total = img.double() if total is None else total + img.double()
                self.done = s + 1
                if self.on_progress is not None:
                    self.on_progress(self.done, self.spp)
            if not self._cancel.is_set() and total is not None:
                self.image = (total / self.done).float()
        except TorchBRDFError as exc:
            self.error = str(exc)
        except Exception as exc:  # a failed reference must not take the editor down: report it
            self.error = f"{type(exc).__name__}: {exc}"
        self.seconds = time.perf_counter() - t0
        if self.on_done is not None:
            self.on_done(self)


def load_scene(spec: str, resolution: int | None = None):
    """:func:`torch_brdf.scene.load_scene` with the editor's default size (128)."""
    from ..scene import load_scene as load

    return load(spec, resolution, default_resolution=128)


def _cache_name(scene, spec: str, series: str, spp: int, seed: int) -> str:
    key = f"{spec}|{scene.name}|{scene.camera.width}x{scene.camera.height}|{series}|{spp}|{seed}"
    if Path(spec).is_file():
        key += "|" + hashlib.sha256(Path(spec).read_bytes()).hexdigest()
    digest = hashlib.sha256(key.encode()).hexdigest()[:16]
    return f"{scene.name}_{scene.camera.width}x{scene.camera.height}_{spp}spp_{digest}.npz"


def load_source(
    source: str,
    scene: str | None = None,
    resolution: int | None = None,
    series: str = "64,1,1,1",
    spp: int = 16,
    seed: int = 0,
    cache_dir: str | Path | None = None,
    progress: bool = True,
):
    """Tensors and (if known) the scene for ``source``: a tensors file (``.npz``) or a scene.

    Args:
        source: a multibounce tensor file written by ``torch-brdf precompute``, or a built-in
            scene name / TOML scene file (then the tensors are precomputed, or read from
            ``cache_dir`` where an earlier run with the same settings left them).
        scene: the scene of a tensors file (default: the built-in scene named in the file's
            settings, if there is one; else no scene: no reference, ids from the tensors).
        resolution: precomputation settings for a scene.
        series: as ``resolution``.
        spp: as ``resolution``.
        seed: as ``resolution``.
        progress: tqdm bar of the precomputation.
    Returns:
        (tensors, scene or None, note): ``note`` says where the tensors came from.
    Raises:
        TorchBRDFError: the source does not load (missing, corrupt, unknown scene).
    """
    path = Path(source)
    if path.suffix == ".npz" or (path.is_file() and not source.endswith(".toml")):
        if not path.is_file():
            raise FileFormatError(f"no tensors file at {source!r}")
        tensors = PolynomialTensors.load(path)
        name = scene or tensors.meta.get("scene")
        sc = None
        if name:
            try:
                sc = load_scene(str(name)).with_resolution(tensors.width, tensors.height)
            except TorchBRDFError:
                if scene is not None:
                    raise
        return tensors, sc, f"tensors {path.name}"
    sc = load_scene(source, resolution)
    if cache_dir is not None:
        cached = Path(cache_dir) / _cache_name(sc, source, series, spp, seed)
        if cached.is_file():
            return PolynomialTensors.load(cached), sc, f"cached precomputation {cached.name}"
        if Path(cache_dir).exists() and not Path(cache_dir).is_dir():  # before the precompute
            raise FileFormatError(f"the cache folder {str(cache_dir)!r} is a file (set TORCH_BRDF_CACHE to a folder)")
    tensors = precompute_polynomial(sc, PolynomialSettings(series, spp=spp), seed=seed, progress=progress)
    if cache_dir is not None:
        Path(cache_dir).mkdir(parents=True, exist_ok=True)
        tensors.save(cached)
    return tensors, sc, f"precomputed {sc.name} ({series}, {spp} spp)"


def checked_create(material: dict[str, Any]) -> BRDF:
    """``create(material)``, with a refusal naming the parameter at fault (the transforms'
    own message says only "value must lie in [0.0, 1.0]")."""
    try:
        return create(material)
    except ValueRangeError as exc:
        model = material.get("type")
        for key, value in material.items():
            if key == "type":
                continue
            try:
                create({"type": model, key: value})
            except ValueRangeError:
                raise ValueRangeError(f"{model} {key}: {exc}") from None
        raise


class EditorSession:
    """Materials of a precomputed view, edited one object at a time.

    Args:
        tensors: the multibounce tensors.
        scene: the scene they were precomputed from (for the object ids by primary rays,
            the starting materials and the reference); None: tensors only.
    """

    def __init__(self, tensors: PolynomialTensors, scene=None, frozen_cache_mb: float = FROZEN_CACHE_MB):
        self.tensors, self.scene = tensors, scene
        names = list(tensors.object_names)
        self.editable = [n for n, b in zip(names, tensors.bases, strict=True) if b is not None]
        mats: dict[str, dict[str, Any]] = {}
        if scene is not None and [o.name for o in scene.objects] == names:
            mats = {o.name: dict(scene.materials[o.material]) for o in scene.objects if o.name in self.editable}
        self.materials = {n: mats.get(n, {"type": "lambert", "albedo": 0.5}) for n in self.editable}
        self.f0: dict[str, Any] = {n: None for n in self.editable}
        self.renderer = PolynomialRenderer(tensors, self.materials)
        #: objects whose base-colour texture modulates the frame (Sec. 5.3 weight maps)
        self.textured = apply_scene_textures(self.renderer, scene) if scene is not None else []
        self.ids, self.ids_source = object_id_buffer(tensors, scene)
        self.mask = emitter_mask(tensors)
        self.selected: str | None = None
        self._projectors: dict[str, MaterialProjector] = {}
        self.projected: dict[str, torch.Tensor] = {}  # obj -> (J, 3) last projected curve
        self._base_textures: dict[str, Any] = {}  # obj -> the texture before its tint
        self.last_frame_s = 0.0
        self.last_set_s = 0.0
        # undo/redo of material edits: (object, snapshot before the edit); snapshots keep the
        # coefficients too, so that undo and A/B give back the very same image
        self._undo: list[tuple[str, tuple]] = []
        self._redo: list[tuple[str, tuple]] = []
        # the A/B toggle compares the current edit with the last saved (or opened) materials
        self.saved = {n: self._snapshot(n) for n in self.editable}
        self._ab_stash: dict[str, tuple] | None = None
        # switching objects: the renderer keeps every object's frozen state (least recently used
        # out past the bound) and brings a state made before another object changed up to date
        # exactly when the object is selected again
        self.renderer.max_frozen_bytes = int(frozen_cache_mb * 2**20)
        #: how the last select got its frozen state: "frozen" (first visit), "kept" (its state
        #: was current), "refreshed" (its state was brought up to date), "active" (already on)
        self.last_select = ""

    # -- selection ----------------------------------------------------------------------------
    @property
    def bounces(self) -> int:
        return self.renderer.max_bounces

    def object_at(self, x: int, y: int) -> str | None:
        """The object seen at pixel column ``x``, row ``y`` (None: nothing or out of the image)."""
        if not (0 <= x < self.tensors.width and 0 <= y < self.tensors.height):
            return None
        m = int(self.ids[y, x])
        return None if m < 0 else self.tensors.object_names[m]

    def select(self, obj: str) -> float:
        """Select and freeze an editable object; returns the freeze time in seconds.

        Raises:
            SceneError: unknown or fixed object (fixed objects' BRDFs are baked in).
        """
        if obj not in self.tensors.object_names:
            raise SceneError(f"unknown object {obj!r}; objects: {self.tensors.object_names}")
        if obj not in self.editable:
            raise SceneError(f"{obj!r} is fixed: its BRDF was baked into the precomputation, it cannot be edited")
        t0 = time.perf_counter()
        with torch.no_grad():
            self.last_select = self._switch(self.tensors.object_id(obj))
        self.selected = obj
        return time.perf_counter() - t0

    def _switch(self, m: int) -> str:
        r = self.renderer
        fz = r._frozen
        if fz is not None and fz["object"] == m and r.is_fresh(m):
            return "active"
        kept, fresh = m in r._states, r.is_fresh(m)
        r.freeze(m)  # a kept state is reused (and refreshed exactly when stale)
        return "kept" if fresh else ("refreshed" if kept else "frozen")

    def basis(self, obj: str):
        return self.tensors.bases[self.tensors.object_id(obj)]

    def band_basis(self, obj: str):
        """The object's :class:`~torch_brdf.brdf.BandBasis` (made once: its lobe-spaced edges
        take ~7 ms to compute, a tenth of an edit's budget)."""
        return self.projector(obj).bands

    def band_material(self, obj: str, coefficients=None, model: str = "factored_1d") -> dict[str, Any]:
        """A ``factored_1d`` (or ``factored_1d_fresnel``) material dict on ``obj``'s own bands
        holding ``coefficients`` (J, 3) (default: the object's current curve), which
        :meth:`coefficients` then uses as is."""
        spec = self.basis(obj).spec()
        c = self.projected.get(obj) if coefficients is None else coefficients
        J = int(spec["J"])
        out = {
            "type": model,
            "quotient": spec.get("quotient", "one"),
            "variable": spec.get("variable", "theta_h"),
            "J": J,
            "spacing": "uniform" if J == 1 else spec.get("spacing"),
        }
        if c is not None:
            out["coefficients"] = torch.as_tensor(c, dtype=torch.float64).reshape(J, 3).tolist()
        return out

    def has_fresnel(self, obj: str) -> bool:
        return bool(self.basis(obj).fresnel)

    # -- materials ----------------------------------------------------------------------------
    def projector(self, obj: str) -> MaterialProjector:
        """The object's :class:`~torch_brdf.render.material.MaterialProjector` on the coarse rule
        :data:`FAST_QUADRATURE` (float64 constants; made once per object)."""
        if obj not in self._projectors:
            self._projectors[obj] = MaterialProjector(self.basis(obj), FAST_QUADRATURE, graph=False)
        return self._projectors[obj]

    def coefficients(self, obj: str, brdf: BRDF) -> torch.Tensor:
        """The object's eye-vertex curve (J, 3) for ``brdf`` (fast projection; Lambert
        on a one-band constant quotient exactly, as the renderer does)."""
        return self.projector(obj).curve(brdf)

    def set_material(self, obj: str, material: dict[str, Any], f0=None) -> float:
        """Give ``obj`` a material dict (validated by the model itself); returns the seconds spent.

        Raises:
            ValueRangeError: a value out of the model's range, an unknown model, or ``f0``
                outside [0, 1] / on an object precomputed without the Fresnel layer.
            SceneError: unknown or fixed object.
        """
        if obj not in self.editable:
            self.select(obj)  # raises the readable error
        before = self._snapshot(obj)
        self._set(obj, material, f0)
        if self._ab_stash is not None:  # an edit while B is shown continues from B
            self._ab_stash = None
        self._undo.append((obj, before))
        self._redo.clear()
        return self.last_set_s

    def _snapshot(self, obj: str) -> tuple:
        """(material, f0, c, c_hat, d, projected curve) of ``obj`` as they are now."""
        m = self.tensors.object_id(obj)
        r = self.renderer
        return (dict(self.materials[obj]), self.f0[obj], r.c[m], r.c_hat[m], r.d[m], self.projected.get(obj))

    def _restore(self, obj: str, snap: tuple) -> None:
        material, f0, c, c_hat, d, projected = snap
        self.renderer.set_coefficients(obj, c, d, c_hat)
        self.materials[obj], self.f0[obj] = dict(material), f0
        if projected is None:
            self.projected.pop(obj, None)
        else:
            self.projected[obj] = projected
        if self.selected is not None and self.renderer.frozen_object is None:
            self.select(self.selected)

    def _set(self, obj: str, material: dict[str, Any], f0=None) -> None:
        t0 = time.perf_counter()
        c, base = self.projector(obj)(checked_create(material), f0, obj)
        self.renderer.set_coefficients(obj, c)
        self.materials[obj], self.f0[obj] = dict(material), f0
        self.projected[obj] = base
        if self.selected is not None and self.renderer.frozen_object is None:
            self.select(self.selected)  # another object's constants changed: freeze again
        self.last_set_s = time.perf_counter() - t0

    # -- undo, redo, A/B, save, export ---------------------------------------------------------
    def undo(self) -> str | None:
        """Undo the last material edit; returns the object it changed (None: nothing to undo)."""
        return self._step(self._undo, self._redo)

    def redo(self) -> str | None:
        """Redo the last undone edit; returns the object it changed (None: nothing to redo)."""
        return self._step(self._redo, self._undo)

    def _step(self, src: list, dst: list) -> str | None:
        if not src:
            return None
        self._ab_stash = None
        obj, snap = src.pop()
        dst.append((obj, self._snapshot(obj)))
        self._restore(obj, snap)
        return obj

    @property
    def showing_saved(self) -> bool:
        """True while the A/B toggle shows the saved materials (B)."""
        return self._ab_stash is not None

    def toggle_ab(self) -> bool:
        """Switch between the current edit (A) and the saved materials (B); returns
        :attr:`showing_saved`. Coefficients are restored as they were (the same images)."""
        if self._ab_stash is None:
            stash = {n: self._snapshot(n) for n in self.editable}
            target = self.saved
        else:
            stash, target = None, self._ab_stash
        for n, snap in target.items():
            if snap[:2] != (self.materials[n], self.f0[n]):
                self._restore(n, snap)
        self._ab_stash = stash
        return self.showing_saved

    def edited_scene(self):
        """The scene with each object's current material (edited objects get a material key of
        their own; objects that shared it keep the old one), at the tensors' image size.

        Raises:
            SceneError: a session opened from tensors alone (no scene to save).
        """

        from ..scene import Scene

        if self.scene is None:
            raise SceneError("this session has no scene (tensors alone): nothing to save")
        table = {k: dict(v) for k, v in self.scene.materials.items()}
        objects = []
        for o in self.scene.objects:
            if o.name in self.materials and self.materials[o.name] != table.get(o.material):
                key = o.name if o.name not in table else f"{o.name}_edited"
                table[key] = dict(self.materials[o.name])
                o = dataclasses.replace(o, material=key)
            objects.append(o)
        sc = Scene(objects, table, self.scene.lights, self.scene.camera, name=self.scene.name)
        return sc.with_resolution(self.tensors.width, self.tensors.height)

    def save(self, path) -> Any:
        """Save the scene with the current materials as a TOML scene file (see
        :func:`torch_brdf.export.scene_file.save_scene_toml`); they become the saved (B)
        materials. Returns the path written."""
        from ..export.scene_file import save_scene_toml

        if self._ab_stash is not None:
            self.toggle_ab()  # save the edit, not the saved materials on show
        out = save_scene_toml(self.edited_scene(), path)
        self.saved = {n: self._snapshot(n) for n in self.editable}
        return out

    def export(self, obj: str, path, fmt: str | None = None, tolerance: float | None = None):
        """Export ``obj``'s current material (:func:`torch_brdf.export.export_material`)."""
        from ..export import export_material

        if obj not in self.materials:
            raise SceneError(f"unknown or fixed object {obj!r}; editable: {self.editable}")
        return export_material(self.materials[obj], path, fmt, tolerance, name=obj)

    def set_texture(self, obj: str, image=None, tint=None) -> float:
        """Swap ``obj``'s base-colour texture for ``image`` and/or multiply it by ``tint`` at run
        time (Ben-Artzi et al. 2008, Fig. 1: retexturing the floor); returns the seconds spent.

        Args:
            obj: an editable, textured object of the session's scene.
            image: a :class:`~torch_brdf.scene.textures.Texture`, an (H, W, 3) linear image or an
                image file (PNG/JPEG decoded from sRGB, EXR, .hdr); None keeps the current one.
            tint: RGB (3 values or one) multiplying the texture; None: no tint.
        Raises:
            SceneError: no scene, an unknown, fixed or untextured object, or a bad image.
        """
        from ..scene.textures import Texture, read_texture

        if self.scene is None:
            raise SceneError("set_texture needs the session's scene (EditorSession(tensors, scene))")
        if obj not in self.editable:
            self.select(obj)  # raises the readable error
        i = self.scene.object_id(obj)
        o = self.scene.objects[i]
        if "base_color" not in o.textures:
            raise SceneError(f"object {obj!r} has no texture to change; textured: {self.textured}")
        t0 = time.perf_counter()
        if image is None:
            tex = self._base_textures.get(obj, o.textures["base_color"])
        elif isinstance(image, Texture):
            tex = image
        elif isinstance(image, (str, Path)):
            tex = read_texture(image)
        else:
            tex = Texture(torch.as_tensor(image), "image")
        self._base_textures[obj] = tex
        if tint is not None:
            tex = tex.tinted(tint)
        scene = copy.copy(self.scene)
        scene.objects = list(self.scene.objects)
        scene.objects[i] = dataclasses.replace(o, textures={**o.textures, "base_color": tex})
        self.scene = scene
        self.renderer.weight_maps.pop(self.tensors.object_id(obj), None)
        self.textured = apply_scene_textures(self.renderer, scene)
        if self.selected is not None:
            self.select(self.selected)
        self.last_set_s = time.perf_counter() - t0
        return self.last_set_s

    # -- images -------------------------------------------------------------------------------
    def views(self) -> list[str]:
        """Names of the per-bounce views: ``image``, ``emission``, ``bounce 1`` ... ``bounce N``."""
        return ["image", "emission"] + [f"bounce {n}" for n in range(1, self.bounces + 1)]

    def render(self, view: str = "image", bounces: int | None = None) -> torch.Tensor:
        """The current frame (H, W, 3) linear radiance; ``view`` one of :meth:`views`,
        ``bounces`` the number of bounces summed in the ``image`` view (default all). The
        full image with all bounces uses the frozen fast path."""
        nb = self.bounces if bounces is None else int(bounces)
        if not 1 <= nb <= self.bounces:
            raise ValueRangeError(f"bounces must lie in [1, {self.bounces}]; got {bounces}")
        if view not in self.views():
            raise ValueRangeError(f"unknown view {view!r}; views: {self.views()}")
        t0 = time.perf_counter()
        with torch.no_grad():
            if view == "image" and nb == self.bounces:
                img = self.renderer()
            else:
                parts = self.renderer.evaluate(per_bounce=True)
                img = sum(parts[1 : nb + 1], parts[0]) if view == "image" else parts[self.views().index(view) - 1]
        self.last_frame_s = time.perf_counter() - t0
        return img

    def reference_scene(self):
        """The scene with the editor's current materials (None without a scene)."""
        if self.scene is None:
            return None
        return scene_with_materials(self.scene, self.materials)

    def compare(self, reference: torch.Tensor) -> tuple[torch.Tensor, float]:
        """Full evaluation against ``reference`` (H, W, 3): the difference image (H, W, 3) and
        the relative RMSE over the pixels that see no emitter (:func:`emitter_mask`)."""
        with torch.no_grad():
            img = self.renderer.evaluate()
        return img - reference, relative_rmse(img, reference, self.mask)
