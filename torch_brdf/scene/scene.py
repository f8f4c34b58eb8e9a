"""The scene: named objects with materials, lights and a camera, traced with embree.

A scene is built in Python (:class:`Scene` from :class:`SceneObject` s) or from a small
description, a dict or TOML file (:meth:`Scene.from_dict`, :meth:`Scene.from_toml`)::

    [camera]
    origin = [278, 273, -800]
    target = [278, 273, 0]
    fov_deg = 39.3
    width = 256
    height = 256

    [materials.white]
    type = "lambert"
    albedo = [0.74, 0.74, 0.74]

    [[objects]]
    name = "floor"
    mesh = "floor.obj"          # relative to the TOML file; or vertices = [...], faces = [...]
    material = "white"
    editable = true             # false: a fixed object (its BRDF is never edited)
    smooth = false              # shading normals: interpolated (true) or per face (false)
    # optional placement: scale = 1.0, rotate_y_deg = 0.0, translate = [0, 0, 0]

    [[lights]]
    type = "area"               # or "envmap" (file = ... | procedural = "sky" | "constant")
    object = "light"            #    or "directional" (direction, irradiance)
    radiance = [17.98, 11.5, 3.15]

Materials are dicts with a ``type`` — a model name of the BRDF layer — and that model's
parameters (``{"type": "lambert", "albedo": ...}``, ``{"type": "blinn_phong", "kd": ...,
"ks": ..., "exponent": ...}``); renderers turn them into modules with
:func:`torch_brdf.brdf.create`.

Descriptions are validated key by key before anything is built (:mod:`.description`): wrong
types, NaN/Inf, sizes beyond the caps and unknown keys raise :class:`SceneError` naming the key.
"""

from __future__ import annotations

import copy
import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh

from .._checks import check_rgb
from ..errors import SceneError, TorchBRDFError
from .camera import Camera
from .description import read_scene_file, validate_description
from .envmap import EnvironmentMap
from .lights import AreaLight, DirectionalLight, Light
from .mesh import load_mesh, mesh_from_arrays, validate_mesh
from .raytrace import Hits, RayTracer
from .textures import Texture

#: texture slots of an object (what a texture scales)
TEXTURE_KEYS = ("base_color",)

#: what :meth:`Scene.content_digest` covers, in the order it is hashed
CONTENT_PARTS = ("geometry", "materials", "lights", "camera")


@dataclass
class SceneObject:
    """One named object of a scene.

    Attributes:
        name: unique within the scene.
        mesh: validated triangle mesh (see :mod:`torch_brdf.scene.mesh`).
        material: key into :attr:`Scene.materials`.
        editable: False marks a fixed object whose BRDF is never edited (its full BRDF
            can be baked into precomputed path weights).
        smooth: interpolate vertex normals for shading (True) or use face normals.
        uv: (V, 2) per-vertex texture coordinates (v up, see :mod:`.textures`), or None.
        textures: image textures by what they scale; the one key is ``"base_color"``: the
            diffuse/base colour of the object's material model (Lambert ``albedo``, ``kd``,
            the metallic-roughness ``base_color``) is its factor times the texel. Needs ``uv``.
    """

    name: str
    mesh: trimesh.Trimesh
    material: str
    editable: bool = True
    smooth: bool = False
    uv: np.ndarray | None = None
    textures: dict[str, Texture] = field(default_factory=dict)

    def __post_init__(self):
        unknown = sorted(set(self.textures) - set(TEXTURE_KEYS))
        if unknown:
            raise SceneError(f"object {self.name!r}: unknown texture slot(s) {unknown}; known: {list(TEXTURE_KEYS)}")
        for k, t in self.textures.items():
            if not isinstance(t, Texture):
                raise SceneError(f"object {self.name!r}: texture {k!r} must be a Texture; got {type(t).__name__}")
        if self.uv is not None:
            uv = np.asarray(self.uv, dtype=np.float64)
            if uv.shape != (len(self.mesh.vertices), 2) or not np.isfinite(uv).all():
                raise SceneError(
                    f"object {self.name!r}: uv must be {len(self.mesh.vertices)} finite (u, v) pairs, one per "
                    f"vertex; got shape {uv.shape}"
                )
            self.uv = uv
        elif self.textures:
            raise SceneError(
                f"object {self.name!r} has a texture ({', '.join(self.textures)}) but its mesh has no UVs "
                "(texture coordinates); add UVs to the mesh or drop the texture"
            )


@dataclass
class Scene:
    """Objects, materials, lights and a camera, with embree ray tracing.

    The object id of ``objects[i]`` is ``i``; :class:`Hits` report it. ``workers`` is the
    number of processes that trace large batches (see :class:`RayTracer`): ``None`` picks
    the usable cores (``TORCH_BRDF_WORKERS`` overrides), 1 never forks; results are the same either way.
    """

    objects: list[SceneObject]
    materials: dict[str, dict[str, Any]]
    lights: list[Light]
    camera: Camera
    name: str = "scene"
    workers: int | None = None
    #: path length the file suggests (Mitsuba's integrator ``max_depth - 1``), or None
    max_bounces: int | None = None
    _tracer: RayTracer | None = field(default=None, repr=False)

    def __post_init__(self):
        if not self.objects:
            raise SceneError("a scene needs at least one object")
        names = [o.name for o in self.objects]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise SceneError(f"duplicate object names: {dup}")
        for o in self.objects:
            if o.material not in self.materials:
                raise SceneError(
                    f"object {o.name!r} uses unknown material {o.material!r}; known: {sorted(self.materials)}"
                )
        for key, mat in self.materials.items():
            _check_material(key, mat)
        for light in self.lights:
            if not isinstance(light, Light):
                raise SceneError(f"lights must be torch_brdf Light modules; got {type(light).__name__}")
        if sum(isinstance(li, EnvironmentMap) for li in self.lights) > 1:
            raise SceneError("a scene holds at most one environment map")
        self._place_area_lights()
        self._tracer = RayTracer([o.mesh for o in self.objects], [o.smooth for o in self.objects], self.workers)
        self._traced = [(o.mesh, o.smooth) for o in self.objects]

    def _place_area_lights(self) -> None:
        """Give every :class:`AreaLight` without an object (``object_id < 0``) one, so that camera
        and path rays see its emission, as in Mitsuba: the object whose triangles it is, or else a
        new fixed (non-editable), black object ``area_light_<k>`` appended after the others (it
        also casts shadows, as Mitsuba's emitter mesh does). The light is replaced by a copy that
        names its object; the caller's light, object list and materials are left as they were."""
        lights, objects, materials = [], list(self.objects), dict(self.materials)
        for k, light in enumerate(self.lights):
            if isinstance(light, AreaLight) and light.object_id < 0:
                oid = next((i for i, o in enumerate(objects) if _same_triangles(o.mesh, light.triangles)), None)
                if oid is None:
                    name = f"area_light_{k}"
                    if name in materials or any(o.name == name for o in objects):
                        raise SceneError(f"area light {k} has no object and the name {name!r} is taken")
                    tri = light.triangles.double().reshape(-1, 3).numpy()
                    faces = np.arange(len(tri)).reshape(-1, 3)
                    materials[name] = {"type": "lambert", "albedo": 0.0}
                    objects.append(SceneObject(name, mesh_from_arrays(tri, faces), name, editable=False))
                    oid = len(objects) - 1
                light = copy.copy(light)
                light.object_id = oid
            lights.append(light)
        self.lights, self.objects, self.materials = lights, objects, materials

    # -- pickling (tile executors ship a scene to other processes) ----------------------------
    def __getstate__(self) -> dict[str, Any]:
        """Everything but the embree scene, which cannot be pickled (rebuilt on load)."""
        return {k: v for k, v in self.__dict__.items() if k not in ("_tracer", "_traced")}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._tracer = RayTracer([o.mesh for o in self.objects], [o.smooth for o in self.objects], self.workers)
        self._traced = [(o.mesh, o.smooth) for o in self.objects]

    def __copy__(self) -> Scene:
        """A shallow copy that shares the ray tracer (``copy.copy`` would otherwise rebuild it)."""
        out = object.__new__(type(self))
        out.__dict__.update(self.__dict__)
        return out

    # -- lookups ---------------------------------------------------------------------------
    def object_id(self, name: str) -> int:
        """Index of the object called ``name``."""
        for i, o in enumerate(self.objects):
            if o.name == name:
                return i
        raise SceneError(f"no object called {name!r}; objects: {[o.name for o in self.objects]}")

    def material_of(self, object_id: int) -> dict[str, Any]:
        """The material dict of object ``object_id``."""
        return self.materials[self.objects[object_id].material]

    @property
    def environment(self) -> EnvironmentMap | None:
        """The scene's environment map light, if any."""
        return next((li for li in self.lights if isinstance(li, EnvironmentMap)), None)

    @property
    def area_lights(self) -> dict[int, AreaLight]:
        """Emissive objects: object id -> its :class:`AreaLight`."""
        return {li.object_id: li for li in self.lights if isinstance(li, AreaLight) and li.object_id >= 0}

    @property
    def ray_epsilon(self) -> float:
        """Offset used by :meth:`spawn` against self-intersection (scene-scale dependent)."""
        return self.tracer.ray_epsilon

    @property
    def tracer(self) -> RayTracer:
        """The underlying :class:`RayTracer` (vertex/face tables for gathers).

        Raises:
            SceneError: objects were added, removed or given other meshes after the scene was
                built (the tracer holds the meshes of construction time; build a new Scene).
        """
        now = [(o.mesh, o.smooth) for o in self.objects]
        if len(now) != len(self._traced) or any(
            a[0] is not b[0] or a[1] != b[1] for a, b in zip(now, self._traced, strict=False)
        ):
            raise SceneError(
                f"scene {self.name!r}: objects or their meshes changed after construction; the ray tracer "
                "still holds the old geometry. Build a new Scene(objects, materials, lights, camera) instead"
            )
        return self._tracer

    # -- ray queries -----------------------------------------------------------------------
    def trace(self, origins, directions) -> Hits:
        """Closest hits, see :meth:`RayTracer.trace`. origins, directions: (P, 3)."""
        return self.tracer.trace(origins, directions)

    def occluded(self, origins, directions, t_max) -> torch.Tensor:
        """(P,) bool: anything within ``(0, t_max)`` along each ray (:meth:`RayTracer.occluded`)."""
        return self.tracer.occluded(origins, directions, t_max)

    def occluded_fans(self, origins, fans, directions):
        """(P,) bool numpy: occlusion of fans of rays from shared origins (:meth:`RayTracer.occluded_fans`)."""
        return self.tracer.occluded_fans(origins, fans, directions)

    def spawn(self, position, geometric_normal, directions) -> torch.Tensor:
        """Origins offset off the surface for rays leaving along ``directions``."""
        return self._tracer.spawn(position, geometric_normal, directions)

    def visible(self, position, geometric_normal, directions, distance) -> torch.Tensor:
        """(P,) bool: the segment from a surface point along ``directions`` is free for
        ``distance`` (less twice the ray epsilon, so the target surface does not count)."""
        o = self.spawn(position, geometric_normal, directions)
        t_max = torch.as_tensor(distance, dtype=torch.float32) - 2 * self.ray_epsilon
        return ~self.occluded(o, directions, t_max)

    # -- derived scenes and statistics -----------------------------------------------------
    def with_resolution(self, width: int, height: int | None = None) -> Scene:
        """The same scene rendered at another image size (geometry is shared)."""
        out = copy.copy(self)
        out.camera = self.camera.with_size(width, height if height is not None else width)
        return out

    def content_digest(self, parts: tuple[str, ...] = CONTENT_PARTS) -> str:
        """SHA-256 (64 hex digits) of everything a render or precomputation of this scene reads.

        The resume key of every cache (:func:`torch_brdf.records.cache.settings_key`) holds it,
        so that a checkpoint written for another scene is never resumed.

        Args:
            parts: which content to cover, any of ``"geometry"`` (per object: name, vertex and
                face bytes, ``editable``, ``smooth``), ``"materials"`` (each object's material
                name and every material dict, tensors by their bytes), ``"lights"`` (each light's
                type, buffers, e.g. env-map texels, area triangles and radiance, and numeric
                attributes) and ``"camera"`` (origin, target, up, field of view, size). A
                visibility precompute, which reads geometry only, passes ``("geometry",)``.
        Not content: the scene's name, ``workers`` and message-only strings (an env map's
        ``source``); a material that names a file is covered by that name, not the file's bytes.
        """
        unknown = sorted(set(parts) - set(CONTENT_PARTS))
        if unknown:
            raise SceneError(f"unknown content parts {unknown}; known: {list(CONTENT_PARTS)}")
        h = hashlib.sha256(b"torch_brdf-scene-content-1")
        for part in CONTENT_PARTS:
            if part not in parts:
                continue
            h.update(f"|{part}|".encode())
            if part == "geometry":
                for o in self.objects:
                    _digest(h, [o.name, o.editable, o.smooth, np.asarray(o.mesh.vertices), np.asarray(o.mesh.faces)])
                    if o.uv is not None or o.textures:  # untextured scenes keep their digests
                        _digest(h, ["uv", o.uv, [[k, *o.textures[k].digest_parts()] for k in sorted(o.textures)]])
            elif part == "materials":
                _digest(h, [[o.name, o.material] for o in self.objects])
                _digest(h, self.materials)
            elif part == "lights":
                for li in self.lights:
                    plain = {k: v for k, v in vars(li).items() if not k.startswith("_") and k != "training"}
                    plain = {k: v for k, v in plain.items() if isinstance(v, (bool, int, float))}
                    _digest(h, [type(li).__name__, plain, dict(li.state_dict())])
            else:
                c = self.camera
                _digest(h, [c.origin, c.target, c.up, float(c.fov_deg), c.width, c.height])
        return h.hexdigest()

    def info(self) -> dict[str, Any]:
        """Statistics for ``torch-brdf info``: objects, triangles, bounds, lights, camera."""
        lo, hi = self._tracer.bbox
        return {
            "name": self.name,
            "objects": [
                {
                    "id": i,
                    "name": o.name,
                    "material": o.material,
                    "type": self.materials[o.material].get("type"),
                    "editable": o.editable,
                    "triangles": len(o.mesh.faces),
                    "vertices": len(o.mesh.vertices),
                    **({"textures": {k: t.name for k, t in o.textures.items()}} if o.textures else {}),
                }
                for i, o in enumerate(self.objects)
            ],
            "triangles": int(sum(len(o.mesh.faces) for o in self.objects)),
            "bounds": [lo.tolist(), hi.tolist()],
            "lights": [type(li).__name__ for li in self.lights],
            "camera": {
                "origin": self.camera.origin,
                "target": self.camera.target,
                "fov_deg": self.camera.fov_deg,
                "size": [self.camera.width, self.camera.height],
            },
        }

    # -- descriptions ----------------------------------------------------------------------
    @classmethod
    def from_toml(cls, path: str | Path) -> Scene:
        """Build a scene from a TOML description (see the module docstring)."""
        path = Path(path)
        desc = read_scene_file(path)
        desc.setdefault("name", path.stem)
        return cls.from_dict(desc, base_dir=path.parent)

    @classmethod
    def from_dict(cls, desc: dict[str, Any], base_dir: str | Path = ".") -> Scene:
        """Build a scene from a description dict (the TOML layout of the module docstring).

        Args:
            desc: with keys ``camera``, ``materials``, ``objects``, ``lights``, ``name``.
            base_dir: folder that relative mesh and EXR paths are resolved against.
        """
        base_dir = Path(base_dir)
        desc = validate_description(desc)
        try:
            camera = Camera(**desc["camera"])
        except TypeError as exc:
            raise SceneError(f"bad camera description {desc['camera']!r}: {exc}") from exc
        objects = [_object_from_dict(o, base_dir) for o in desc["objects"]]
        if not isinstance(desc["materials"], dict):
            raise SceneError(f"'materials' must be a table of name -> material; got {desc['materials']!r}")
        # copies of the tables; Scene.__post_init__ validates each one
        materials = {str(k): dict(v) if isinstance(v, dict) else v for k, v in desc["materials"].items()}
        names = [o.name for o in objects]
        lights = [_light_from_dict(li, base_dir, names, objects) for li in desc.get("lights", [])]
        return cls(objects, materials, lights, camera, name=str(desc.get("name", "scene")))


def _check_material(key: str, mat: dict[str, Any]) -> None:
    if not isinstance(mat, dict) or not isinstance(mat.get("type"), str):
        raise SceneError(f"material {key!r} must be a dict with a string 'type'; got {mat!r}")
    for k in ("albedo", "kd", "ks"):
        if k in mat:
            try:
                check_rgb(mat[k], f"material {key!r} {k}")
            except TorchBRDFError as exc:
                raise SceneError(str(exc)) from exc


def _placed(mesh: trimesh.Trimesh, d: dict[str, Any], name: str) -> trimesh.Trimesh:
    m = mesh.copy()
    if "scale" in d:
        m.apply_scale(float(d["scale"]))
    if "rotate_y_deg" in d:
        m.apply_transform(trimesh.transformations.rotation_matrix(math.radians(float(d["rotate_y_deg"])), [0, 1, 0]))
    if "translate" in d:
        t = np.asarray(d["translate"], dtype=np.float64)
        if t.shape != (3,):
            raise SceneError(f"object {name!r}: translate must be 3 numbers; got {d['translate']!r}")
        m.apply_translation(t)
    return validate_mesh(m, name)


def _object_from_dict(d: dict[str, Any], base_dir: Path) -> SceneObject:
    if "name" not in d or "material" not in d:
        raise SceneError(f"object description needs 'name' and 'material'; got keys {sorted(d)}")
    name = str(d["name"])
    if "mesh" in d:
        mesh = load_mesh(base_dir / d["mesh"], name)
    elif "vertices" in d and "faces" in d:
        mesh = mesh_from_arrays(d["vertices"], d["faces"], name)
    else:
        raise SceneError(f"object {name!r} needs 'mesh' (a file) or 'vertices' and 'faces'")
    mesh = _placed(mesh, d, name)
    return SceneObject(name, mesh, str(d["material"]), bool(d.get("editable", True)), bool(d.get("smooth", False)))


def _light_from_dict(d: dict[str, Any], base_dir: Path, names: list[str], objects: list[SceneObject]) -> Light:
    kind = d.get("type")
    if kind == "directional" and "direction" not in d:
        raise SceneError("directional light needs 'direction' (towards the light)")
    if kind == "area":
        obj = d.get("object")
        if obj not in names:
            raise SceneError(f"area light refers to unknown object {obj!r}; objects: {names}")
        i = names.index(obj)
        m = objects[i].mesh
        return AreaLight(m.vertices, m.faces, d.get("radiance", 1.0), object_id=i)
    if kind == "directional":
        return DirectionalLight(d["direction"], d.get("irradiance", 1.0))
    if kind == "envmap":
        return _envmap_from_dict(d, base_dir)
    raise SceneError(f"unknown light type {kind!r}; expected 'area', 'directional' or 'envmap'")


def _envmap_from_dict(d: dict[str, Any], base_dir: Path) -> EnvironmentMap:
    extra = {k: v for k, v in d.items() if k not in ("type", "file", "procedural", "scale", "rotation_deg", "radiance")}
    try:
        if "file" in d:
            env = EnvironmentMap.from_file(base_dir / d["file"], scale=float(d.get("scale", 1.0)), **extra)
        elif d.get("procedural") == "constant":
            env = EnvironmentMap.constant(d.get("radiance", 1.0), **extra)
        elif d.get("procedural") == "sky":
            env = EnvironmentMap.sky(**extra)
        else:
            raise SceneError("envmap light needs 'file' or procedural = 'sky' | 'constant'")
    except TypeError as exc:  # unknown keyword in the description
        raise SceneError(f"bad envmap light description {sorted(d)}: {exc}") from exc
    if d.get("rotation_deg"):
        env = env.rotated(math.radians(float(d["rotation_deg"])))
    return env


def _same_triangles(mesh: trimesh.Trimesh, triangles: torch.Tensor) -> bool:
    """Whether ``mesh``'s non-degenerate triangles are ``triangles`` (F, 3, 3), in order, to float32."""
    tri = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)]
    tri = tri[np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1) > 0]
    want = triangles.detach().cpu().numpy()
    return tri.shape == want.shape and bool(np.allclose(tri.astype(np.float32), want, rtol=0, atol=1e-6))


def _digest(h, value) -> None:
    """Feed ``value`` to the hash ``h`` unambiguously: every item is tagged with its type, arrays
    and tensors with dtype and shape, floats exactly (``float.hex``), dicts in sorted key order."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        h.update(f"a{a.dtype.str}{a.shape}:".encode())
        h.update(a.data if a.size else b"")
    elif isinstance(value, dict):
        h.update(f"d{len(value)}:".encode())
        for k in sorted(value, key=str):
            _digest(h, str(k))
            _digest(h, value[k])
    elif isinstance(value, (list, tuple)):
        h.update(f"l{len(value)}:".encode())
        for v in value:
            _digest(h, v)
    elif isinstance(value, (bool, np.bool_)):
        h.update(b"b1" if value else b"b0")
    elif isinstance(value, (int, np.integer)):
        h.update(f"i{int(value)};".encode())
    elif isinstance(value, (float, np.floating)):
        h.update(f"f{float(value).hex()};".encode())
    elif value is None:
        h.update(b"n")
    else:
        s = str(value).encode()
        h.update(f"s{len(s)}:".encode() + s)
