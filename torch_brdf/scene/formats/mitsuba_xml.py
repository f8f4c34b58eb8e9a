r"""Mitsuba 3 XML scenes: the subset common research scenes use.

Parsed with :mod:`defusedxml` (no DTDs, entities or external references; at most
:data:`~._common.MAX_TEXT_BYTES` bytes, :data:`~._common.MAX_ELEMENTS` elements nested at
most :data:`~._common.MAX_DEPTH` deep). ``<default name value>`` parameters and ``$name``
substitution in attribute values, ``id``/``<ref>`` for BSDFs and textures.

Supported plugins and how they map (exact = the same function; approximate = stated):

=========================  ===============================================================
``diffuse``                ``lambert`` (exact); a ``bitmap`` reflectance becomes a texture
``twosided``               its inner BSDF (our surfaces are two-sided; exact)
``roughconductor``         ``cook_torrance`` with the same distribution and :math:`\alpha`,
                           ``kd = 0``, Schlick with :math:`F_0` of the complex IOR
                           (approximate: Schlick instead of the conductor Fresnel)
``conductor``              the same at :math:`\alpha` = :data:`SMOOTH_ALPHA` (approximate)
``roughplastic``           ``rough_plastic`` (:mod:`torch_brdf.brdf.plastic`): Mitsuba's
                           function, its tables integrated by another rule (pointwise
                           within 0.2%, ``tests/brdf/test_plastic.py``)
``plastic``                ``rough_plastic`` with ``smooth``: the diffuse exact up to
                           Mitsuba's fit of the internal reflectance (within 1%); the delta
                           coat a GGX lobe of :math:`\alpha` = :data:`SMOOTH_ALPHA`
``principled``             ``metallic_roughness`` (approximate: Mitsuba's Disney diffuse
                           and specular tint; only base colour, metallic, roughness, specular)
=========================  ===============================================================

Shapes ``obj``, ``ply`` (files; ``face_normals``, ``flip_normals``), ``rectangle``, ``cube``,
``disk`` (exact), ``sphere`` (tessellated: an approximation); emitters ``area`` (on its
shape), ``envmap`` (EXR or ``.hdr``; ``scale``, a rotation about +y), ``constant``,
``directional``, ``point``; the ``perspective`` sensor (``to_world`` with ``lookat``,
``translate``, ``rotate``, ``scale``, ``matrix``; ``fov``, ``fov_axis``; the ``hdrfilm``
size); the integrator's ``max_depth`` (stored as :attr:`Scene.max_bounces`).
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from ...errors import FileFormatError, MeshError
from ..camera import Camera
from ..envmap import EnvironmentMap
from ..lights import AreaLight, DirectionalLight, PointLight
from ..mesh import validate_mesh
from ..scene import Scene, SceneObject
from ..textures import read_texture
from ._common import MAX_DEPTH, MAX_ELEMENTS, MAX_TEXT_BYTES, SceneFile, auto_camera, checked, unique_name

#: roughness standing in for Mitsuba's perfectly smooth ``conductor`` and ``plastic``
SMOOTH_ALPHA = 0.01
#: the glTF metallic-roughness model that ``principled`` maps to
METALLIC_ROUGHNESS = "metallic_roughness"

#: RGB complex IOR (eta, k) of Mitsuba's named conductors used here (approximate RGB values)
CONDUCTORS = {
    "none": None,
    "Au": ((0.143, 0.374, 1.442), (3.983, 2.385, 1.603)),
    "Ag": ((0.155, 0.117, 0.138), (4.828, 3.122, 2.147)),
    "Cu": ((0.200, 0.924, 1.102), (3.912, 2.452, 2.142)),
    "Al": ((1.657, 0.880, 0.521), (9.224, 6.270, 4.837)),
    "Cr": ((3.109, 3.186, 2.293), (3.310, 3.332, 3.226)),
}
_IORS = {"vacuum": 1.0, "air": 1.000277, "water": 1.333, "glass": 1.5, "bk7": 1.5046, "polypropylene": 1.49}
_BSDFS = ("diffuse", "twosided", "conductor", "roughconductor", "plastic", "roughplastic", "principled")
_SHAPES = ("obj", "ply", "rectangle", "cube", "sphere", "disk")
_EMITTERS = ("area", "envmap", "constant", "directional", "point")
_VAR = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")
_NUM = re.compile(r"[,\s]+")


class _Builder(ET.TreeBuilder):
    """An element tree that remembers each element's line, with caps on count and depth."""

    def __init__(self, file: SceneFile):
        super().__init__()
        self.file, self.parser, self.lines, self.depth, self.count = file, None, {}, 0, 0

    def start(self, tag, attrs):
        self.count += 1
        self.depth += 1
        line = self.parser.parser.CurrentLineNumber if self.parser is not None else 0
        if self.count > MAX_ELEMENTS:
            raise self.file.error(f"line {line}", f"more than {MAX_ELEMENTS} XML elements")
        if self.depth > MAX_DEPTH:
            raise self.file.error(f"line {line}", f"XML nested deeper than {MAX_DEPTH}")
        e = super().start(tag, attrs)
        self.lines[id(e)] = line
        return e

    def end(self, tag):
        self.depth -= 1
        return super().end(tag)


def _parse(file: SceneFile) -> tuple[ET.Element, dict[int, int]]:
    from defusedxml import DefusedXmlException
    from defusedxml.ElementTree import DefusedXMLParser

    data = file.read_bytes(file.path, MAX_TEXT_BYTES)
    builder = _Builder(file)
    parser = DefusedXMLParser(target=builder, forbid_dtd=True, forbid_entities=True, forbid_external=True)
    builder.parser = parser
    try:
        parser.feed(data)
        root = parser.close()
    except DefusedXmlException as exc:
        raise file.error(
            "", f"refused XML ({type(exc).__name__}: DTDs, entities and external references are not read)"
        ) from None
    except ET.ParseError as exc:
        raise file.error(f"line {exc.position[0]}", f"not well-formed XML: {exc}") from None
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise file.error("", f"cannot parse XML: {exc}") from None
    if root.tag != "scene":
        raise file.error(f"line {builder.lines.get(id(root), 1)}", f"the root element is <{root.tag}>, not <scene>")
    return root, builder.lines


class _Reader:
    def __init__(self, file: SceneFile, root: ET.Element, lines: dict[int, int]):
        self.file, self.root, self.lines = file, root, lines
        self.defaults: dict[str, str] = {}
        self.named: dict[str, ET.Element] = {}
        self.materials: dict[str, dict[str, Any]] = {}
        self.material_textures: dict[str, Any] = {}
        self.objects: list[SceneObject] = []
        self.lights: list = []
        self.area: list[tuple[int, Any]] = []
        self.camera: Camera | None = None
        self.max_bounces: int | None = None
        self.names: set[str] = set()

    # -- helpers -----------------------------------------------------------------------
    def where(self, e: ET.Element) -> str:
        t = e.get("type")
        label = f"<{e.tag}{' type=' + repr(t) if t else ''}{' name=' + repr(e.get('name')) if e.get('name') else ''}>"
        return f"line {self.lines.get(id(e), '?')}, {label}"

    def attr(self, e: ET.Element, key: str, default: str | None = None) -> str | None:
        v = e.get(key, default)
        if v is None:
            return None

        def sub(m):
            if m.group(1) not in self.defaults:
                name = m.group(1)
                raise self.file.error(self.where(e), f"unknown parameter ${name} (no <default name={name!r}>)")
            return self.defaults[m.group(1)]

        return _VAR.sub(sub, v)

    def numbers(self, e: ET.Element, key: str = "value", count: int | None = None) -> list[float]:
        text = self.attr(e, key)
        if text is None:
            raise self.file.error(self.where(e), f"missing attribute {key!r}")
        try:
            vals = [float(x) for x in _NUM.split(text.strip()) if x]
        except ValueError:
            raise self.file.error(self.where(e), f"{key}={text!r} is not a list of numbers") from None
        if not vals or not all(math.isfinite(x) for x in vals) or (count is not None and len(vals) != count):
            want = f"{count} finite numbers" if count else "finite numbers"
            raise self.file.error(self.where(e), f"{key}={text!r}: expected {want}")
        return vals

    def xyz(self, e: ET.Element, default: float = 0.0) -> list[float]:
        if e.get("value") is not None:
            v = self.numbers(e)
            return v * 3 if len(v) == 1 else self._three(e, v)
        out = []
        for k in "xyz":
            t = self.attr(e, k)
            try:
                out.append(float(t) if t is not None else default)
            except ValueError:
                raise self.file.error(self.where(e), f"{k}={t!r} is not a number") from None
        if not all(math.isfinite(x) for x in out):
            raise self.file.error(self.where(e), "coordinates must be finite")
        return out

    def _three(self, e, v):
        if len(v) != 3:
            raise self.file.error(self.where(e), f"expected 3 numbers; got {len(v)}")
        return v

    def props(self, e: ET.Element) -> dict[str, ET.Element]:
        """Named child properties (``<float name=...>`` ...), refs resolved."""
        out = {}
        for c in e:
            if c.tag == "ref":
                rid = self.attr(c, "id")
                if rid not in self.named:
                    raise self.file.error(self.where(c), f"reference to unknown id {rid!r}")
                target = self.named[rid]
                out[c.get("name") or target.tag] = target
                continue
            name = c.get("name") or (c.tag if c.tag in ("bsdf", "emitter", "film", "sampler", "rfilter") else None)
            if name is None:
                if c.tag in ("shape", "emitter", "bsdf", "medium"):
                    name = f"{c.tag}:{len(out)}"
                else:
                    raise self.file.error(self.where(c), "a property needs a name attribute")
            out[name] = c
        return out

    def value(self, e: ET.Element):
        """A property element's value: float, int, bool, string, RGB list, 3-vector or 4x4."""
        tag = e.tag
        if tag in ("float", "integer"):
            v = self.numbers(e, count=1)[0]
            if tag == "integer" and v != int(v):
                raise self.file.error(self.where(e), f"value {v} is not an integer")
            return int(v) if tag == "integer" else v
        if tag == "boolean":
            t = (self.attr(e, "value") or "").lower()
            if t not in ("true", "false"):
                raise self.file.error(self.where(e), f"value {t!r} is not true or false")
            return t == "true"
        if tag == "string":
            v = self.attr(e, "value")
            if v is None:
                raise self.file.error(self.where(e), "missing attribute 'value'")
            return v
        if tag in ("rgb", "spectrum"):
            v = self.numbers(e)
            if tag == "spectrum" and (len(v) != 1 or ":" in (e.get("value") or "")):
                self.file.unsupported(self.where(e), "only uniform spectra (one value) are read", "the mean value")
                v = [float(np.mean(v))]
            if len(v) not in (1, 3):
                raise self.file.error(self.where(e), f"expected 1 or 3 values; got {len(v)}")
            return v * 3 if len(v) == 1 else v
        if tag in ("point", "vector"):
            return self.xyz(e)
        if tag == "transform":
            return self.transform(e)
        raise self.file.error(self.where(e), f"<{tag}> is not a value")

    def get(self, props, name, default=None, kinds=None):
        e = props.get(name)
        if e is None:
            return default
        if kinds and e.tag not in kinds:
            raise self.file.error(self.where(e), f"property {name!r} must be one of {list(kinds)}; got <{e.tag}>")
        return self.value(e)

    def transform(self, e: ET.Element) -> np.ndarray:
        m = np.eye(4)
        for c in e:
            if c.tag == "translate":
                op = np.eye(4)
                op[:3, 3] = self.xyz(c)
            elif c.tag == "scale":
                s = self.numbers(c) if c.get("value") is not None else self.xyz(c, default=1.0)
                s = s * 3 if len(s) == 1 else self._three(c, s)
                op = np.diag([*s, 1.0])
            elif c.tag == "rotate":
                axis = np.array(self.numbers(c, count=3) if c.get("value") is not None else self.xyz(c))
                angle = math.radians(self.numbers(c, "angle", 1)[0])
                if np.linalg.norm(axis) == 0:
                    raise self.file.error(self.where(c), "rotation axis is zero")
                op = np.eye(4)
                op[:3, :3] = _rotation(axis / np.linalg.norm(axis), angle)
            elif c.tag == "matrix":
                op = np.array(self.numbers(c, count=16)).reshape(4, 4)
            elif c.tag == "lookat":
                op = _look_at(*(np.array(self.numbers(c, k, 3)) for k in ("origin", "target")), self._up(c), self, c)
            else:
                raise self.file.error(self.where(c), f"unknown transform operation <{c.tag}>")
            m = op @ m
        return m

    def _up(self, c):
        return np.array(self.numbers(c, "up", 3)) if c.get("up") is not None else np.array([0.0, 1.0, 0.0])

    # -- the scene ------------------------------------------------------------------------
    def read(self) -> Scene:
        for c in self.root:
            if c.tag == "default":
                name, val = c.get("name"), c.get("value")
                if not name or val is None:
                    raise self.file.error(self.where(c), "<default> needs name and value")
                self.defaults.setdefault(name, val)
        for c in self.root:
            tag = c.tag
            if tag == "default":
                continue
            if c.get("id") is not None and tag in ("bsdf", "texture"):
                self.named[self.attr(c, "id")] = c
            elif tag == "integrator":
                self.integrator(c)
            elif tag == "sensor":
                self.sensor(c)
            elif tag == "shape":
                self.shape(c)
            elif tag == "emitter":
                self.emitter(c)
            elif tag in ("bsdf", "texture"):
                pass  # unnamed top-level definitions are unused, as in Mitsuba
            else:
                self.file.unsupported(self.where(c), f"unsupported element <{tag}>", "nothing (it is skipped)")
        if not self.objects:
            raise self.file.error("", "the scene has no shapes")
        for oid, radiance in self.area:
            m = self.objects[oid].mesh
            light = checked(self.file, self.objects[oid].name, AreaLight, m.vertices, m.faces, radiance, oid)
            self.lights.append(light)
        res = self.file.options.resolution
        cam = self.camera or auto_camera([o.mesh for o in self.objects])
        if res:
            cam = cam.with_size(res, res)
        return checked(
            self.file,
            "scene",
            Scene,
            self.objects,
            self.materials,
            self.lights,
            cam,
            name=self.file.path.stem,
            max_bounces=self.max_bounces,
        )

    def integrator(self, e):
        kind = self.attr(e, "type")
        props = self.props(e)
        if kind in ("path", "volpath", "direct"):
            depth = self.get(props, "max_depth", -1, ("integer",))
            self.max_bounces = 1 if kind == "direct" else (None if depth < 0 else max(1, depth - 1))
        else:
            self.file.unsupported(self.where(e), f"unsupported integrator {kind!r}", "the path tracer")

    def sensor(self, e):
        kind = self.attr(e, "type")
        if kind != "perspective":
            self.file.unsupported(self.where(e), f"unsupported sensor {kind!r}", "a perspective camera")
        if self.camera is not None:
            self.file.unsupported(self.where(e), "a second sensor", "the first sensor")
            return
        props = self.props(e)
        if "focal_length" in props and "fov" not in props:
            raise self.file.error(self.where(e), "focal_length is not read; give fov (and fov_axis)")
        fov = self.get(props, "fov", 39.3077, ("float",))
        axis = self.get(props, "fov_axis", "x", ("string",))
        w, h = 768, 576
        film = props.get("film")
        if film is not None:
            fp = self.props(film)
            w, h = self.get(fp, "width", w, ("integer",)), self.get(fp, "height", h, ("integer",))
        m = self.get(props, "to_world", np.eye(4), ("transform",))
        if np.linalg.det(m[:3, :3]) <= 0:
            raise self.file.error(self.where(e), "a mirroring (or singular) sensor to_world is not supported")
        origin, fwd, up = m[:3, 3], m[:3, 2], m[:3, 1]
        if not 0 < fov < 180:
            raise self.file.error(self.where(e), f"fov {fov} outside (0, 180)")
        t = math.tan(math.radians(fov) / 2)
        if axis == "smaller":
            axis = "x" if w < h else "y"
        elif axis == "larger":
            axis = "x" if w >= h else "y"
        if axis == "x":
            t = t * h / w
        elif axis == "diagonal":
            t = t * h / math.hypot(w, h)
        elif axis != "y":
            raise self.file.error(self.where(e), f"fov_axis {axis!r}: expected x, y, diagonal, smaller or larger")
        fov_y = math.degrees(2 * math.atan(t))
        self.camera = checked(
            self.file,
            self.where(e),
            Camera,
            tuple(origin),
            tuple(origin + fwd / np.linalg.norm(fwd)),
            tuple(up),
            fov_y,
            int(w),
            int(h),
        )

    # -- BSDFs ----------------------------------------------------------------------------
    def bsdf(self, e: ET.Element) -> tuple[dict[str, Any], Any]:
        """(material dict, base-colour texture or None)."""
        kind = self.attr(e, "type")
        props = self.props(e)
        if kind == "twosided":
            inner = [c for k, c in props.items() if c.tag == "bsdf"]
            if len(inner) != 1:
                raise self.file.error(self.where(e), "twosided needs exactly one inner BSDF")
            return self.bsdf(inner[0])
        if kind not in _BSDFS:
            self.file.unsupported(
                self.where(e), f"unsupported BSDF plugin {kind!r}; supported: {list(_BSDFS)}", "a grey diffuse (0.5)"
            )
            return {"type": "lambert", "albedo": 0.5}, None
        if kind == "diffuse":
            refl, tex = self.colour(props, "reflectance", 0.5)
            return {"type": "lambert", "albedo": refl}, tex
        if kind in ("conductor", "roughconductor"):
            return self.conductor(e, kind, props), None
        if kind in ("plastic", "roughplastic"):
            return self.plastic(e, kind, props)
        return self.principled(e, props)

    def colour(self, props, name, default):
        e = props.get(name)
        if e is None:
            return [default] * 3 if not isinstance(default, list) else default, None
        if e.tag == "texture":
            return [1.0, 1.0, 1.0], self.texture(e)
        v = self.value(e)
        if isinstance(v, (int, float)):
            v = [float(v)] * 3
        if not isinstance(v, list) or len(v) != 3:
            raise self.file.error(self.where(e), f"{name} must be a colour")
        if any(x < 0 or x > 1 for x in v):
            raise self.file.error(self.where(e), f"{name} {v} outside [0, 1]")
        return v, None

    def texture(self, e):
        kind = self.attr(e, "type")
        if kind != "bitmap":
            self.file.unsupported(self.where(e), f"unsupported texture plugin {kind!r}; supported: ['bitmap']", "white")
            return None
        props = self.props(e)
        fname = self.get(props, "filename", None, ("string",))
        if fname is None:
            raise self.file.error(self.where(e), "bitmap needs a filename")
        path = self.file.resolve(fname, self.where(e))
        raw = self.get(props, "raw", False, ("boolean",))
        for k in ("filter_type", "wrap_mode"):
            v = self.get(props, k, None, ("string",))
            if v is not None and v not in ("bilinear", "repeat"):
                self.file.unsupported(self.where(e), f"{k}={v!r}", "bilinear filtering with repeating wrap")
        if "to_uv" in props:
            self.file.unsupported(self.where(e), "to_uv transforms of textures", "the identity")
        try:
            return read_texture(path, srgb=not raw, name=Path(fname).name)
        except FileFormatError as exc:
            raise self.file.error(self.where(e), str(exc)) from None

    def _eta(self, props, name, default):
        e = props.get(name)
        if e is None:
            return default
        if e.tag == "string":
            v = self.value(e)
            if v not in _IORS:
                raise self.file.error(self.where(e), f"unknown IOR name {v!r}; known: {sorted(_IORS)}")
            return _IORS[v]
        return float(self.get(props, name, default, ("float",)))

    def _alpha(self, e, kind, props):
        if not kind.startswith("rough"):  # a delta BSDF: approximated by a sharp lobe (module docstring)
            return "ggx", SMOOTH_ALPHA
        dist = self.get(props, "distribution", "beckmann", ("string",))
        if dist not in ("beckmann", "ggx"):
            raise self.file.error(self.where(e), f"distribution {dist!r}: expected beckmann or ggx")
        if "alpha_u" in props or "alpha_v" in props:
            au, av = self.get(props, "alpha_u", 0.1, ("float",)), self.get(props, "alpha_v", 0.1, ("float",))
            if au != av:
                self.file.unsupported(self.where(e), "anisotropic roughness", f"alpha = {(au * av) ** 0.5:g}")
            alpha = (au * av) ** 0.5
        else:
            alpha = self.get(props, "alpha", 0.1, ("float",))
        if not 1e-4 <= alpha <= 1:
            raise self.file.error(self.where(e), f"alpha {alpha} outside [1e-4, 1]")
        return dist, alpha

    def conductor(self, e, kind, props):
        dist, alpha = self._alpha(e, kind, props)
        spec, tex = self.colour(props, "specular_reflectance", 1.0)
        if tex is not None:
            self.file.unsupported(self.where(e), "a textured specular_reflectance", "1")
        if "eta" in props or "k" in props:
            eta = np.array(self.get(props, "eta", [0.0] * 3, ("rgb", "spectrum", "float")), dtype=np.float64)
            k = np.array(self.get(props, "k", [1.0] * 3, ("rgb", "spectrum", "float")), dtype=np.float64)
            f0 = ((eta - 1) ** 2 + k**2) / ((eta + 1) ** 2 + k**2)
        else:
            name = self.get(props, "material", "none", ("string",))
            if name not in CONDUCTORS:
                known = sorted(CONDUCTORS)
                raise self.file.error(self.where(e), f"conductor material {name!r} unknown; known: {known}")
            if CONDUCTORS[name] is None:
                f0 = np.ones(3)
            else:
                eta, k = (np.array(x) for x in CONDUCTORS[name])
                f0 = ((eta - 1) ** 2 + k**2) / ((eta + 1) ** 2 + k**2)
        f0 = np.clip(f0 * np.array(spec), 0, 1)
        return {"type": "cook_torrance", "distribution": dist, "roughness": alpha, "f0": f0.tolist(), "kd": 0.0}

    def plastic(self, e, kind, props):
        smooth = not kind.startswith("rough")
        if smooth:
            dist, alpha = "ggx", SMOOTH_ALPHA
        else:
            dist, alpha = self._alpha(e, kind, props)
        eta = self._eta(props, "int_ior", 1.49) / self._eta(props, "ext_ior", 1.000277)
        if not 1.0 < eta <= 4.0:
            raise self.file.error(self.where(e), f"int_ior / ext_ior = {eta:g}: expected in (1, 4]")
        kd, tex = self.colour(props, "diffuse_reflectance", 0.5)
        spec, stex = self.colour(props, "specular_reflectance", 1.0)
        if stex is not None:
            self.file.unsupported(self.where(e), "a textured specular_reflectance", "1")
        mat = {
            "type": "rough_plastic",
            "distribution": dist,
            "roughness": alpha,
            "eta": eta,
            "diffuse_reflectance": kd,
            "specular_reflectance": spec,
            "nonlinear": bool(self.get(props, "nonlinear", False, ("boolean",))),
        }
        if smooth:
            mat["smooth"] = True
        return mat, tex

    def principled(self, e, props):
        from ...brdf.base import available

        if METALLIC_ROUGHNESS not in available():
            self.file.unsupported(self.where(e), "the principled BSDF needs the metallic_roughness model", "lambert")
            base, tex = self.colour(props, "base_color", 0.5)
            return {"type": "lambert", "albedo": base}, tex
        base, tex = self.colour(props, "base_color", 0.5)
        metallic = self.get(props, "metallic", 0.0, ("float",))
        rough = self.get(props, "roughness", 0.5, ("float",))
        for k in ("specular_transmission", "sheen", "clearcoat", "anisotropic", "spec_tint"):
            v = self.get(props, k, 0.0, ("float",))
            if v:
                self.file.unsupported(self.where(e), f"principled {k} = {v}", f"{k} = 0")
        spec = self.get(props, "specular", 0.5, ("float",))
        if abs(spec - 0.5) > 1e-6:
            self.file.unsupported(self.where(e), f"principled specular = {spec} (glTF's dielectric F0 is 0.04)", "0.5")
        return {"type": METALLIC_ROUGHNESS, "base_color": base, "metallic": metallic, "roughness": rough}, tex

    def material_for(self, shape: ET.Element, props, name: str) -> tuple[str, Any]:
        b = [c for c in props.values() if c.tag == "bsdf"]
        if len(b) > 1:
            raise self.file.error(self.where(shape), "a shape has at most one BSDF")
        if not b:
            key = "__default"
            self.materials.setdefault(key, {"type": "lambert", "albedo": 0.5})
            return key, None
        key = b[0].get("id") or name
        if key not in self.materials:
            mat, tex = self.bsdf(b[0])
            self.materials[key] = mat
            self.material_textures[key] = tex
        return key, self.material_textures.get(key)

    # -- shapes ---------------------------------------------------------------------------
    def shape(self, e: ET.Element):
        kind = self.attr(e, "type")
        where = self.where(e)
        if kind not in _SHAPES:
            self.file.unsupported(where, f"unsupported shape plugin {kind!r}; supported: {list(_SHAPES)}", "nothing")
            return
        props = self.props(e)
        m = self.get(props, "to_world", np.eye(4), ("transform",))
        smooth, uv = False, None
        if kind in ("obj", "ply"):
            fname = self.get(props, "filename", None, ("string",))
            if fname is None:
                raise self.file.error(where, f"{kind} needs a filename")
            v, f, uv, smooth = _load_file_mesh(self.file, self.file.resolve(fname, where), where)
            if self.get(props, "face_normals", False, ("boolean",)):
                smooth = False
        elif kind == "rectangle":
            v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
            f = np.array([[0, 1, 2], [0, 2, 3]])
            uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], float)  # Mitsuba's (x+1)/2, (y+1)/2 with v flipped
        elif kind == "cube":
            box = trimesh.creation.box(extents=(2, 2, 2))
            v, f = np.asarray(box.vertices), np.asarray(box.faces)
        elif kind == "disk":
            n = 128
            a = np.linspace(0, 2 * math.pi, n, endpoint=False)
            v = np.concatenate([[[0, 0, 0]], np.stack([np.cos(a), np.sin(a), np.zeros(n)], -1)])
            f = np.stack([np.zeros(n, int), 1 + np.arange(n), 1 + (np.arange(n) + 1) % n], -1)
        else:  # sphere
            c = np.array(self.get(props, "center", [0.0, 0.0, 0.0], ("point",)))
            r = float(self.get(props, "radius", 1.0, ("float",)))
            if not r > 0:
                raise self.file.error(where, f"sphere radius {r} must be > 0")
            ico = trimesh.creation.icosphere(subdivisions=4)
            v, f, smooth = np.asarray(ico.vertices) * r + c, np.asarray(ico.faces), True
        v = v @ m[:3, :3].T + m[:3, 3]
        if np.linalg.det(m[:3, :3]) < 0:  # a mirror turns faces inside out
            f = f[:, ::-1]
        if self.get(props, "flip_normals", False, ("boolean",)):
            f = f[:, ::-1]
        name = unique_name(self.attr(e, "id") or f"{kind}_{len(self.objects)}", self.names)
        mat, tex = self.material_for(e, props, name)
        try:
            mesh = validate_mesh(trimesh.Trimesh(vertices=v, faces=f, process=False), name)
        except MeshError as exc:
            raise self.file.error(where, str(exc)) from None
        textures = {}
        if tex is not None:
            if uv is None:
                raise self.file.error(where, f"shape {name!r} has a texture but no UVs (texture coordinates)")
            textures["base_color"] = tex
        obj = checked(self.file, where, SceneObject, name, mesh, mat, True, smooth, uv if textures else None, textures)
        self.objects.append(obj)
        for c in props.values():
            if c.tag == "emitter":
                if self.attr(c, "type") != "area":
                    raise self.file.error(self.where(c), f"a shape's emitter must be 'area'; got {c.get('type')!r}")
                rad, _ = self._radiance(c, "radiance")
                self.area.append((len(self.objects) - 1, rad))

    def _radiance(self, e, name):
        props = self.props(e)
        pe = props.get(name)
        if pe is None:
            return [1.0] * 3, props
        if pe.tag == "texture":
            raise self.file.error(self.where(pe), f"a textured {name} is not supported")
        v = self.value(pe)
        v = [float(v)] * 3 if isinstance(v, (int, float)) else v
        if any(x < 0 for x in v):
            raise self.file.error(self.where(pe), f"{name} must be >= 0")
        return v, props

    # -- emitters -------------------------------------------------------------------------
    def emitter(self, e):
        kind = self.attr(e, "type")
        where = self.where(e)
        if kind not in _EMITTERS or kind == "area":
            why = "an area emitter belongs inside a <shape>" if kind == "area" else f"unsupported emitter {kind!r}"
            self.file.unsupported(where, f"{why}; supported: {list(_EMITTERS)}", "no light")
            return
        props = self.props(e)
        if kind == "envmap":
            fname = self.get(props, "filename", None, ("string",))
            if fname is None:
                raise self.file.error(where, "envmap needs a filename")
            path = self.file.resolve(fname, where)
            scale = self.get(props, "scale", 1.0, ("float",))
            m = self.get(props, "to_world", np.eye(4), ("transform",))
            r = m[:3, :3]
            angle = math.atan2(r[0, 2], r[0, 0])
            if not np.allclose(r, _rotation(np.array([0.0, 1.0, 0.0]), angle), atol=1e-6):
                raise self.file.error(where, "an envmap to_world other than a rotation about +y is not supported")
            env = checked(self.file, where, EnvironmentMap.from_file, path, scale)
            self.lights.append(env.rotated(angle) if angle else env)
        elif kind == "constant":
            rad, _ = self._radiance(e, "radiance")
            self.lights.append(checked(self.file, where, EnvironmentMap.constant, rad, 16))
        elif kind == "directional":
            irr, _ = self._radiance(e, "irradiance")
            if "direction" in props:
                d = np.array(self.get(props, "direction", None, ("vector",)))
            else:
                d = self.get(props, "to_world", np.eye(4), ("transform",))[:3, 2]
            self.lights.append(checked(self.file, where, DirectionalLight, (-d).tolist(), irr))
        else:  # point
            inten, _ = self._radiance(e, "intensity")
            if "position" in props:
                pos = self.get(props, "position", None, ("point",))
            else:
                pos = self.get(props, "to_world", np.eye(4), ("transform",))[:3, 3].tolist()
            self.lights.append(checked(self.file, where, PointLight, pos, inten))


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix about a unit axis (Rodrigues), Mitsuba's ``rotate`` (counter-clockwise)."""
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return c * np.eye(3) + s * k + (1 - c) * np.outer(axis, axis)


def _look_at(origin, target, up, reader, e) -> np.ndarray:
    d = target - origin
    if np.linalg.norm(d) == 0:
        raise reader.file.error(reader.where(e), "lookat origin and target coincide")
    d = d / np.linalg.norm(d)
    left = np.cross(up, d)
    if np.linalg.norm(left) < 1e-12:
        raise reader.file.error(reader.where(e), "lookat up is parallel to the viewing direction")
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, origin
    return m


def _load_file_mesh(file: SceneFile, path: Path, where: str):
    """(vertices, faces, uv or None, smooth) of an OBJ/PLY file, parts concatenated."""
    if path.suffix.lower() == ".obj":
        from .obj import obj_geometry

        v, f, uv = obj_geometry(file, path, where)
        return v, f, uv, True
    try:
        loaded = trimesh.load(path, process=False, force="mesh", maintain_order=True)
    except Exception as exc:  # trimesh raises many types on malformed files
        raise file.error(where, f"cannot read mesh {path.name}: {type(exc).__name__}: {exc}") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise file.error(where, f"mesh file {path.name} holds no triangles")
    uv = getattr(loaded.visual, "uv", None)
    uv = None if uv is None or len(uv) != len(loaded.vertices) else np.asarray(uv, dtype=np.float64)
    # Mitsuba shades file meshes smoothly unless face_normals is set (it computes vertex normals
    # when the file has none); our smooth objects interpolate trimesh's vertex normals
    return np.asarray(loaded.vertices), np.asarray(loaded.faces), uv, True


def read_mitsuba_xml(file: SceneFile) -> Scene:
    """Read a Mitsuba 3 XML scene (see the module docstring).

    Raises:
        SceneError: naming the file, the line and element, and the problem.
    """
    root, lines = _parse(file)
    return _Reader(file, root, lines).read()
