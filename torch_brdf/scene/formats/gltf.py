r"""glTF 2.0 scenes (``.gltf`` with its buffers and images, or ``.glb``), parsed by pygltflib.

* Every triangle primitive of every mesh instanced by a node of the default scene becomes
  one object, named after the node (or its mesh), ``name.k`` for the k-th primitive of a
  multi-primitive mesh; node transforms (``matrix`` or TRS) are applied.
* ``pbrMetallicRoughness`` (``baseColorFactor``, ``metallicFactor``, ``roughnessFactor``,
  ``baseColorTexture`` on ``TEXCOORD_0``) maps to the ``metallic_roughness`` BRDF (the
  specification's reference model); without that model a Lambert of the base colour stands in.
  The base-colour texture is decoded from sRGB; glTF's top-left UV origin is flipped to ours.
* ``emissiveFactor`` (times ``KHR_materials_emissive_strength``) makes the primitive an area
  light of that radiance.
* ``KHR_lights_punctual``: ``directional`` (``color * intensity`` as irradiance, shining
  along the node's -z) and ``point`` (``color * intensity`` as intensity in W/sr) are
  supported; ``spot`` is refused by name (or, with ``substitute``, read as a point light).
* The first perspective camera (``yfov``, ``aspectRatio``; looking along the node's -z) is
  used, else the scene is framed automatically. A file without lights gets the procedural sky.

Refused by name: sparse accessors, primitive modes other than triangles, textures on
``TEXCOORD_1+`` or with ``KHR_texture_transform``, Draco and other required extensions.
"""

from __future__ import annotations

import base64
import json
import math
import struct
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from ...errors import FileFormatError, MeshError, SceneError
from ..camera import Camera
from ..envmap import EnvironmentMap
from ..lights import AreaLight, DirectionalLight, PointLight
from ..mesh import validate_mesh
from ..scene import Scene, SceneObject
from ..textures import Texture, read_texture, texture_from_bytes
from ._common import MAX_BINARY_BYTES, MAX_TEXT_BYTES, MAX_TRIANGLES, SceneFile, auto_camera, checked, unique_name
from .mitsuba_xml import METALLIC_ROUGHNESS

_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_SUPPORTED_EXTENSIONS = {"KHR_lights_punctual", "KHR_materials_emissive_strength"}


class _Gltf:
    def __init__(self, file: SceneFile):
        import pygltflib

        self.file = file
        data = file.read_bytes(file.path, MAX_BINARY_BYTES if file.path.suffix.lower() == ".glb" else MAX_TEXT_BYTES)
        self.blob = None
        if data[:4] == b"glTF":
            try:
                g = pygltflib.GLTF2.load_from_bytes(data)
                self.blob = g.binary_blob()
            except Exception as exc:  # pygltflib's binary parser fails with struct, value, key ... errors
                raise file.error("", f"malformed GLB ({type(exc).__name__}: {exc})") from None
        else:
            try:
                json.loads(data.decode("utf-8"))
            except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
                raise file.error("", f"not glTF JSON: {exc}") from None
            try:
                g = pygltflib.GLTF2.from_json(data.decode("utf-8"))
            except Exception as exc:  # pygltflib's schema mapping fails with many error types
                raise file.error("", f"malformed glTF JSON ({type(exc).__name__}: {exc})") from None
        if g is None or not isinstance(getattr(g, "nodes", None), list):
            raise file.error("", "not a glTF document")
        self.g = g
        required = set(g.extensionsRequired or []) - _SUPPORTED_EXTENSIONS
        if required:
            raise file.error("extensionsRequired", f"unsupported required extensions {sorted(required)}")
        self._buffers: dict[int, bytes] = {}
        self._textures: dict[int, Texture] = {}

    # -- binary data -----------------------------------------------------------------------
    def buffer(self, i: int) -> bytes:
        if i not in self._buffers:
            b = self.g.buffers[i]
            where = f"buffers[{i}]"
            if b.uri is None:
                if self.blob is None:
                    raise self.file.error(where, "no URI and no GLB binary chunk")
                data = self.blob
            else:
                data = self._uri(b.uri, where)
            if len(data) < (b.byteLength or 0):
                raise self.file.error(where, f"holds {len(data)} bytes; byteLength says {b.byteLength}")
            self._buffers[i] = data
        return self._buffers[i]

    def _uri(self, uri: str, where: str) -> bytes:
        if uri.startswith("data:"):
            head, _, payload = uri.partition(",")
            if not head.endswith(";base64"):
                raise self.file.error(where, "data URIs must be base64")
            if len(payload) > MAX_BINARY_BYTES * 4 // 3 + 4:
                raise self.file.error(where, "data URI beyond the size cap")
            try:
                return base64.b64decode(payload, validate=True)
            except ValueError as exc:
                raise self.file.error(where, f"bad base64 data: {exc}") from None
        from urllib.parse import unquote

        path = self.file.resolve(unquote(uri), where)
        return self.file.read_bytes(path, MAX_BINARY_BYTES, where)

    def view(self, i: int, where: str) -> tuple[bytes, int, int, int | None]:
        bv = self.g.bufferViews[i]
        buf = self.buffer(bv.buffer)
        off, length = bv.byteOffset or 0, bv.byteLength
        if off < 0 or length is None or length < 0 or off + length > len(buf):
            raise self.file.error(where, f"bufferViews[{i}] lies outside its buffer")
        return buf, off, length, bv.byteStride

    def accessor(self, i: int, where: str) -> np.ndarray:
        a = self.g.accessors[i]
        where = f"{where}, accessors[{i}]"
        if a.sparse is not None:
            raise self.file.error(where, "sparse accessors are not supported")
        if a.componentType not in _COMPONENTS or a.type not in _WIDTH:
            raise self.file.error(where, f"unknown componentType {a.componentType} or type {a.type!r}")
        dt = np.dtype(_COMPONENTS[a.componentType])
        n, count = _WIDTH[a.type], int(a.count)
        if count < 1:
            raise self.file.error(where, f"count {count} < 1")
        if a.bufferView is None:
            return np.zeros((count, n), dt)
        buf, off, length, stride = self.view(a.bufferView, where)
        item = dt.itemsize * n
        stride = stride or item
        start = off + (a.byteOffset or 0)
        if stride < item or start + stride * (count - 1) + item > off + length:
            raise self.file.error(where, "accessor reaches beyond its bufferView")
        arr = np.ndarray((count, n), dt, buffer=buf, offset=start, strides=(stride, dt.itemsize)).copy()
        if a.normalized and dt.kind in "iu":
            arr = np.maximum(arr / np.iinfo(dt).max, -1.0)
        return arr

    def texture(self, info, where: str) -> Texture | None:
        if info is None:
            return None
        if (info.texCoord or 0) != 0:
            self.file.unsupported(where, f"a texture on TEXCOORD_{info.texCoord}", "no texture")
            return None
        if info.extensions and "KHR_texture_transform" in info.extensions:
            self.file.unsupported(where, "KHR_texture_transform", "the untransformed texture")
        idx = info.index
        if idx not in self._textures:
            t = self.g.textures[idx]
            src = t.source
            if src is None:
                raise self.file.error(f"textures[{idx}]", "no image source (only PNG/JPEG images are read)")
            img = self.g.images[src]
            here = f"images[{src}]"
            try:
                if img.uri is not None and not img.uri.startswith("data:"):
                    from urllib.parse import unquote

                    p = self.file.resolve(unquote(img.uri), here)
                    self._textures[idx] = read_texture(p, srgb=True, name=img.name or Path(p).name)
                else:
                    if img.uri is not None:
                        data = self._uri(img.uri, here)
                    elif img.bufferView is not None:
                        buf, off, length, _ = self.view(img.bufferView, here)
                        data = buf[off : off + length]
                    else:
                        raise self.file.error(here, "no uri and no bufferView")
                    self._textures[idx] = texture_from_bytes(data, img.name or f"image{src}")
            except FileFormatError as exc:
                raise self.file.error(here, str(exc)) from None
        return self._textures[idx]


def _node_matrix(node) -> np.ndarray:
    if node.matrix is not None and len(node.matrix) == 16:
        return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T  # column-major
    m = np.eye(4)
    if node.scale is not None:
        m = np.diag([*node.scale, 1.0]) @ m
    if node.rotation is not None:
        x, y, z, w = node.rotation
        r = np.eye(4)
        r[:3, :3] = trimesh.transformations.quaternion_matrix([w, x, y, z])[:3, :3]
        m = r @ m
    if node.translation is not None:
        t = np.eye(4)
        t[:3, 3] = node.translation
        m = t @ m
    return m


def _material(r: _Gltf, i: int | None, cache: dict, taken: set[str]):
    """(material key, material dict, base-colour texture, emitted radiance or None)."""
    from ...brdf.base import available

    if i in cache:
        return cache[i]
    mat = r.g.materials[i] if i is not None else None
    where = f"materials[{i}]" if i is not None else "default material"
    pbr = mat.pbrMetallicRoughness if mat is not None else None
    base = list((pbr.baseColorFactor if pbr and pbr.baseColorFactor else [1.0, 1.0, 1.0, 1.0])[:3])
    metallic = float(pbr.metallicFactor if pbr and pbr.metallicFactor is not None else 1.0)
    rough = float(pbr.roughnessFactor if pbr and pbr.roughnessFactor is not None else 1.0)
    vals = [*base, metallic, rough]
    if not all(math.isfinite(v) and 0 <= v <= 1 for v in vals):
        raise r.file.error(where, f"baseColor/metallic/roughness factors must lie in [0, 1]; got {vals}")
    tex = r.texture(pbr.baseColorTexture, f"{where}.baseColorTexture") if pbr else None
    if pbr and pbr.metallicRoughnessTexture is not None:
        r.file.unsupported(where, "metallicRoughnessTexture", "the metallic and roughness factors")
    if METALLIC_ROUGHNESS in available():
        desc = {"type": METALLIC_ROUGHNESS, "base_color": base, "metallic": metallic, "roughness": rough}
    else:
        desc = {"type": "lambert", "albedo": base}
    emitted = None
    if mat is not None and mat.emissiveFactor and max(mat.emissiveFactor) > 0:
        strength = 1.0
        ext = (mat.extensions or {}).get("KHR_materials_emissive_strength")
        if ext is not None:
            strength = float(ext.get("emissiveStrength", 1.0))
        emitted = [float(c) * strength for c in mat.emissiveFactor[:3]]
        if not all(math.isfinite(c) and c >= 0 for c in emitted):
            raise r.file.error(where, f"emission {emitted} must be finite and >= 0")
    key = unique_name((mat.name if mat is not None and mat.name else None) or f"material_{i}", taken)
    cache[i] = (key, desc, tex, emitted)
    return cache[i]


def _walk(r: _Gltf):
    """(node index, world matrix) for every node of the default scene, parents first."""
    g = r.g
    if g.scenes:
        s = g.scene if g.scene is not None else 0
        roots = list(g.scenes[s].nodes or [])
    else:
        children = {c for n in g.nodes for c in (n.children or [])}
        roots = [i for i in range(len(g.nodes)) if i not in children]
    stack = [(i, np.eye(4), 0) for i in reversed(roots)]
    seen = 0
    while stack:
        i, parent, depth = stack.pop()
        seen += 1
        if depth > 256 or seen > 1_000_000:
            raise r.file.error("nodes", "node hierarchy too deep or cyclic")
        node = g.nodes[i]
        m = parent @ _node_matrix(node)
        if not np.isfinite(m).all():
            raise r.file.error(f"nodes[{i}]", "non-finite transform")
        yield i, m
        for c in reversed(node.children or []):
            stack.append((c, m, depth + 1))


def _read(file: SceneFile) -> Scene:
    r = _Gltf(file)
    g = r.g
    objects, materials, lights, area = [], {}, [], []
    names, mat_names, cache = set(), set(), {}
    camera: Camera | None = None
    res = file.options.resolution
    tris = 0
    punctual = ((g.extensions or {}).get("KHR_lights_punctual") or {}).get("lights", [])
    for i, m in _walk(r):
        node = g.nodes[i]
        ext = (node.extensions or {}).get("KHR_lights_punctual")
        if ext is not None:
            lights.extend(_light(r, punctual, ext.get("light"), m, f"nodes[{i}]"))
        if node.camera is not None and camera is None:
            camera = _camera(r, node.camera, m, res, f"nodes[{i}]")
        if node.mesh is None:
            continue
        mesh = g.meshes[node.mesh]
        base = node.name or mesh.name or f"node{i}"
        for k, prim in enumerate(mesh.primitives):
            where = f"nodes[{i}] ({base!r}), meshes[{node.mesh}].primitives[{k}]"
            if (prim.mode if prim.mode is not None else 4) != 4:
                file.unsupported(where, f"primitive mode {prim.mode} (only triangles, 4, are read)", "nothing")
                continue
            attrs = prim.attributes
            if attrs.POSITION is None:
                raise file.error(where, "no POSITION attribute")
            pos = r.accessor(attrs.POSITION, where).astype(np.float64)
            if pos.shape[1] != 3:
                raise file.error(where, "POSITION must be VEC3")
            idx = (
                r.accessor(prim.indices, where).astype(np.int64).reshape(-1)
                if prim.indices is not None
                else np.arange(len(pos))
            )
            if len(idx) % 3 or len(idx) == 0:
                raise file.error(where, f"{len(idx)} indices is not a whole number of triangles")
            if idx.min() < 0 or idx.max() >= len(pos):
                raise file.error(where, "indices outside the vertex range")
            tris += len(idx) // 3
            if tris > MAX_TRIANGLES:
                raise file.error(where, f"more than {MAX_TRIANGLES} triangles")
            v = pos @ m[:3, :3].T + m[:3, 3]
            faces = idx.reshape(-1, 3)
            if np.linalg.det(m[:3, :3]) < 0:
                faces = faces[:, ::-1]
            key, desc, tex, emitted = _material(r, prim.material, cache, mat_names)
            materials[key] = desc
            uv = None
            if tex is not None:
                if attrs.TEXCOORD_0 is None:
                    raise file.error(where, f"material {key!r} has a base-colour texture but the mesh has no UVs")
                t = r.accessor(attrs.TEXCOORD_0, where).astype(np.float64)
                if t.shape != (len(pos), 2):
                    raise file.error(where, "TEXCOORD_0 must be one VEC2 per vertex")
                uv = np.stack([t[:, 0], 1.0 - t[:, 1]], -1)  # glTF's v runs down the image
            name = unique_name(base if len(mesh.primitives) == 1 else f"{base}.{k}", names)
            try:
                tm = validate_mesh(trimesh.Trimesh(vertices=v, faces=faces, process=False), name)
            except MeshError as exc:
                raise file.error(where, str(exc)) from None
            textures = {"base_color": tex} if tex is not None else {}
            smooth = attrs.NORMAL is not None
            objects.append(checked(file, where, SceneObject, name, tm, key, True, smooth, uv, textures))
            if emitted is not None:
                area.append((len(objects) - 1, emitted))
    if not objects:
        raise file.error("", "the scene has no triangle meshes")
    for oid, rad in area:
        o = objects[oid]
        lights.append(checked(file, o.name, AreaLight, o.mesh.vertices, o.mesh.faces, rad, oid))
    if not lights:
        lights.append(EnvironmentMap.sky())
    if camera is None:
        camera = auto_camera([o.mesh for o in objects], res or 256, res or 256)
    return checked(file, "scene", Scene, objects, materials, lights, camera, name=file.path.stem)


def _light(r: _Gltf, punctual: list, li: Any, m: np.ndarray, where: str) -> list:
    if not isinstance(li, int) or not 0 <= li < len(punctual) or not isinstance(punctual[li], dict):
        raise r.file.error(where, f"KHR_lights_punctual light {li!r} does not exist")
    d = punctual[li]
    kind = d.get("type")
    where = f"{where}, KHR_lights_punctual.lights[{li}] ({d.get('name') or kind!r})"
    colour = np.array(d.get("color", [1.0, 1.0, 1.0]), dtype=np.float64)[:3] * float(d.get("intensity", 1.0))
    if kind == "spot":
        r.file.unsupported(where, "spot lights are not supported", "a point light (the cone ignored)")
        kind = "point"
    if kind == "directional":
        z = m[:3, 2]
        return [checked(r.file, where, DirectionalLight, z.tolist(), colour.tolist())]
    if kind == "point":
        return [checked(r.file, where, PointLight, m[:3, 3].tolist(), colour.tolist())]
    raise r.file.error(where, f"unknown light type {kind!r}")


def _camera(r: _Gltf, ci: int, m: np.ndarray, res: int | None, where: str) -> Camera | None:
    cam = r.g.cameras[ci]
    where = f"{where}, cameras[{ci}]"
    if cam.type != "perspective" or cam.perspective is None:
        r.file.unsupported(where, f"{cam.type} camera", "automatic framing")
        return None
    p = cam.perspective
    yfov = math.degrees(float(p.yfov))
    aspect = float(p.aspectRatio) if p.aspectRatio else 1.0
    if not (0 < yfov < 180 and 0.01 < aspect < 100):
        raise r.file.error(where, f"yfov {p.yfov} or aspectRatio {p.aspectRatio} out of range")
    h = res or 256
    w = max(1, round(h * aspect))
    origin = m[:3, 3]
    fwd = -m[:3, 2] / max(np.linalg.norm(m[:3, 2]), 1e-300)
    return checked(r.file, where, Camera, tuple(origin), tuple(origin + fwd), tuple(m[:3, 1]), yfov, w, h)


def read_gltf(file: SceneFile) -> Scene:
    """Read a glTF 2.0 file (see the module docstring).

    Raises:
        SceneError: naming the file, the element (``nodes[3]``, ``materials[0]`` ...) and the problem.
    """
    try:
        return _read(file)
    except SceneError:
        raise
    except (
        KeyError,
        IndexError,
        TypeError,
        ValueError,
        AttributeError,
        OverflowError,
        RecursionError,
        struct.error,
    ) as exc:
        # a malformed document: pygltflib and numpy fail with these on missing or mistyped fields
        raise file.error("", f"malformed glTF ({type(exc).__name__}: {exc})") from None
