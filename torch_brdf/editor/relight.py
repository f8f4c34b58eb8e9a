r"""The relighting tab's state: all-frequency relighting of a scene with visibility records.

:class:`RelightSession` wraps a :class:`~torch_brdf.render.triple.TripleProductRenderer`
(Inger et al.: per-vertex direct lighting :math:`B = \sum_t L_t\Omega_t V_t f(\omega_t,
\omega_o)(n\cdot\omega_t)` by locally adaptive triple products). Nothing is frozen here: the
products are evaluated per frame from the visibility record, so every control is live —

* the environment turned about +y (:meth:`~torch_brdf.scene.EnvironmentMap.rotated`; the
  block lighting is recomputed),
* the view orbited about the camera's target (a new G-buffer: which vertices are shaded and
  towards which eye — the triple products take :math:`\omega_o` per vertex, so moving the
  camera needs no new precomputation),
* the material of any object (any BRDF: :class:`~torch_brdf.render.triple.GenericRule`
  samples it per block).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import torch

from ..errors import SceneError, ValueRangeError
from ..render.triple import TripleProductRenderer
from ..scene import Camera
from .session import checked_create, load_scene


def orbit_camera(camera: Camera, degrees: float) -> Camera:
    """``camera`` turned by ``degrees`` about the vertical (+y) axis through its target."""
    a = math.radians(degrees)
    o, t = torch.tensor(camera.origin, dtype=torch.float64), torch.tensor(camera.target, dtype=torch.float64)
    d = o - t
    x = math.cos(a) * float(d[0]) + math.sin(a) * float(d[2])
    z = -math.sin(a) * float(d[0]) + math.cos(a) * float(d[2])
    origin = (float(t[0]) + x, float(o[1]), float(t[2]) + z)
    return dataclasses.replace(camera, origin=origin)


class RelightSession:
    """A scene with its visibility record, relit interactively.

    Args:
        scene: the scene (built-in name, TOML file or :class:`~torch_brdf.scene.Scene`).
        visibility: the record (:class:`~torch_brdf.transport.visibility.VertexVisibility`
            or its file) written by ``torch-brdf precompute-visibility`` for that scene.
        resolution: image size (square) for a scene given by name.
    Raises:
        TorchBRDFError: the scene or record does not load, or they do not belong together.
    """

    def __init__(self, scene, visibility, resolution: int | None = None):
        from ..transport.visibility import VertexVisibility

        sc = load_scene(scene, resolution) if isinstance(scene, str) else scene
        vis = visibility if isinstance(visibility, VertexVisibility) else VertexVisibility.load(visibility)
        self.scene = sc
        self.renderer = TripleProductRenderer(sc, vis)
        self.base_envmap = self.renderer.envmap
        self.materials = {o.name: dict(sc.materials[o.material]) for o in sc.objects}
        self.rotation_deg = 0.0
        self.orbit_deg = 0.0
        self._view = None
        self.selected: str | None = None
        self.last_frame_s = 0.0
        self.stats = None

    @property
    def objects(self) -> list[str]:
        return [o.name for o in self.scene.objects]

    def camera(self) -> Camera:
        return orbit_camera(self.scene.camera, self.orbit_deg)

    def view(self):
        """The current camera's view (G-buffer and visibility of the vertices it sees), cached."""
        if self._view is None:
            self._view = self.renderer.view(self.camera())
        return self._view

    def set_rotation(self, degrees: float) -> None:
        """Turn the environment to ``degrees`` about +y (from the scene's own orientation)."""
        if not math.isfinite(degrees):
            raise ValueRangeError(f"rotation must be finite; got {degrees}")
        self.rotation_deg = float(degrees)
        self.renderer.set_lighting(self.base_envmap.rotated(math.radians(self.rotation_deg)))

    def set_orbit(self, degrees: float) -> None:
        """Move the camera ``degrees`` about the vertical axis through its target."""
        if not math.isfinite(degrees):
            raise ValueRangeError(f"orbit must be finite; got {degrees}")
        if float(degrees) != self.orbit_deg:
            self.orbit_deg = float(degrees)
            self._view = None

    def object_at(self, x: int, y: int) -> str | None:
        """The object seen at pixel column ``x``, row ``y`` of the current view (None: none)."""
        gb = self.view().gbuffer
        if not (0 <= x < gb.width and 0 <= y < gb.height):
            return None
        hit = (gb.pixels == y * gb.width + x).nonzero()
        return None if hit.numel() == 0 else self.objects[int(gb.object_id[int(hit[0, 0])])]

    def select(self, obj: str) -> None:
        if obj not in self.objects:
            raise SceneError(f"unknown object {obj!r}; objects: {self.objects}")
        self.selected = obj

    def set_material(self, obj: str, material: dict[str, Any]) -> None:
        """Give ``obj`` a material dict (validated by the model; ValueRangeError names the
        parameter at fault)."""
        if obj not in self.objects:
            raise SceneError(f"unknown object {obj!r}; objects: {self.objects}")
        self.renderer.set_material(obj, checked_create(material))
        self.materials[obj] = dict(material)

    def render(self) -> torch.Tensor:
        """The frame (H, W, 3) float32 (environment behind the misses); its time and the
        triple products' statistics go to ``last_frame_s`` and ``stats``."""
        t0 = time.perf_counter()
        view = self.view()
        rad, self.stats = self.renderer.shade(view)
        img = self.renderer.image(view, rad)
        self.last_frame_s = time.perf_counter() - t0
        return img
