r"""Wavefront OBJ with its MTL materials.

One object per part: an ``o``/``g`` name and the material in use (``usemtl``); a part with
several materials becomes ``name.material`` objects. Polygons are fanned into triangles;
``v``/``vt`` pairs become the vertices (so UV seams split vertices); ``vn`` is not read
(flat shading). Materials (MTL):

* ``Kd`` (and ``map_Kd``, a texture multiplied by ``Kd``) with ``Ks`` absent or 0: ``lambert``;
* ``Ks > 0``: ``blinn_phong`` with ``kd = Kd``, ``ks = Ks``, ``exponent = Ns`` (our
  energy-normalised lobe, :class:`~torch_brdf.brdf.analytic.BlinnPhong`; MTL does not define a
  normalisation);
* ``Ke > 0``: the part is also an area light of that radiance.

Other statements (``illum``, ``d``, ``Ni``, maps other than ``map_Kd``) are ignored.
A file without lights gets the procedural sky of :meth:`EnvironmentMap.sky`; the camera
frames the scene (:func:`~._common.auto_camera`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from ...errors import FileFormatError, MeshError, SceneError
from ..envmap import EnvironmentMap
from ..lights import AreaLight
from ..mesh import validate_mesh
from ..scene import Scene, SceneObject
from ..textures import read_texture
from ._common import MAX_BINARY_BYTES, MAX_TEXT_BYTES, MAX_TRIANGLES, SceneFile, auto_camera, checked, unique_name


def _floats(file: SceneFile, where: str, tokens: list[str], n: int) -> list[float]:
    try:
        v = [float(t) for t in tokens[:n]]
    except ValueError:
        raise file.error(where, f"expected numbers; got {' '.join(tokens[:n])!r}") from None
    if len(v) < n or not all(math.isfinite(x) for x in v):
        raise file.error(where, f"expected {n} finite numbers; got {' '.join(tokens)!r}")
    return v


def read_mtl(file: SceneFile, path: Path, where: str) -> dict[str, dict[str, Any]]:
    """The materials of an MTL file: name -> {Kd, Ks, Ns, Ke, map_Kd (a Texture)}."""
    mtl = SceneFile(path, file.options)
    mtl.root = file.root  # references stay inside the OBJ's folder
    try:
        text = mtl.read_bytes(path, MAX_TEXT_BYTES, where).decode("utf-8", errors="replace")
    except UnicodeDecodeError as exc:  # pragma: no cover - errors="replace"
        raise file.error(where, f"{path.name} is not text: {exc}") from None
    out: dict[str, dict[str, Any]] = {}
    cur: dict[str, Any] | None = None
    for no, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        key, *rest = line.split()
        here = f"{path.name} line {no}"
        if key == "newmtl":
            if not rest:
                raise file.error(here, "newmtl needs a name")
            cur = out.setdefault(" ".join(rest), {})
            continue
        if cur is None:
            if key in ("Kd", "Ks", "Ns", "Ke", "map_Kd"):
                raise file.error(here, f"{key} before any newmtl")
            continue
        if key in ("Kd", "Ks", "Ke"):
            v = _floats(file, here, rest, 1) if len(rest) < 3 else _floats(file, here, rest, 3)
            v = v * 3 if len(v) == 1 else v
            if any(x < 0 for x in v) or (key != "Ke" and any(x > 1 for x in v)):
                raise file.error(here, f"{key} {v} outside {'[0, inf)' if key == 'Ke' else '[0, 1]'}")
            cur[key] = v
        elif key == "Ns":
            ns = _floats(file, here, rest, 1)[0]
            if not 0 <= ns <= 1e4:
                raise file.error(here, f"Ns {ns} outside [0, 10000]")
            cur["Ns"] = ns
        elif key == "map_Kd":
            if not rest:
                raise file.error(here, "map_Kd needs a file name")
            if len(rest) > 1:
                file.unsupported(here, f"map_Kd options {' '.join(rest[:-1])!r}", "none (the last word is the file)")
            tex_path = file.resolve(rest[-1], here)
            try:
                cur["map_Kd"] = read_texture(tex_path, srgb=True, name=Path(rest[-1]).name)
            except FileFormatError as exc:
                raise file.error(here, str(exc)) from None
    return out


def _material(name: str, m: dict[str, Any]) -> dict[str, Any]:
    kd = m.get("Kd", [0.8, 0.8, 0.8])
    ks = m.get("Ks", [0.0, 0.0, 0.0])
    if max(ks) > 0:
        return {"type": "blinn_phong", "kd": kd, "ks": ks, "exponent": max(1e-3, float(m.get("Ns", 10.0)))}
    return {"type": "lambert", "albedo": kd}


def _parse_obj(file: SceneFile, text: str):
    """(positions (V, 3), uvs (T, 2), parts: {(name, material): [(v idx, vt idx or -1) triangles]}, mtllibs)."""
    pos, uvs, parts, libs = [], [], {}, []
    name, mat = file.path.stem, None
    tri_count = 0
    for no, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        key, *rest = line.split()
        here = f"line {no}"
        if key == "v":
            pos.append(_floats(file, here, rest, 3))
        elif key == "vt":
            uv = _floats(file, here, rest, 2) if len(rest) >= 2 else [*_floats(file, here, rest, 1), 0.0]
            uvs.append(uv)
        elif key == "f":
            if len(rest) < 3:
                raise file.error(here, f"a face needs at least 3 vertices; got {len(rest)}")
            corners = []
            for t in rest:
                bits = t.split("/")
                try:
                    vi = int(bits[0])
                    ti = int(bits[1]) if len(bits) > 1 and bits[1] else 0
                except ValueError:
                    raise file.error(here, f"bad face vertex {t!r}") from None
                vi = vi - 1 if vi > 0 else len(pos) + vi
                ti = (ti - 1 if ti > 0 else len(uvs) + ti) if ti else -1
                if not 0 <= vi < len(pos) or (ti != -1 and not 0 <= ti < len(uvs)):
                    raise file.error(here, f"face vertex {t!r} refers to a vertex or UV that does not exist (yet)")
                corners.append((vi, ti))
            tris = parts.setdefault((name, mat), [])
            for k in range(1, len(corners) - 1):
                tris.append((corners[0], corners[k], corners[k + 1]))
            tri_count += len(corners) - 2
            if tri_count > MAX_TRIANGLES:
                raise file.error(here, f"more than {MAX_TRIANGLES} triangles")
        elif key in ("o", "g"):
            name = " ".join(rest) or file.path.stem
        elif key == "usemtl":
            mat = " ".join(rest) or None
        elif key == "mtllib":
            libs.extend(rest)
    return np.array(pos, dtype=np.float64).reshape(-1, 3), np.array(uvs, dtype=np.float64).reshape(-1, 2), parts, libs


def obj_geometry(file: SceneFile, path: Path, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """All faces of an OBJ file as one mesh (a Mitsuba ``obj`` shape): vertices (V, 3), faces
    (F, 3) and per-vertex UVs (V, 2), or None when some face has no ``vt``."""
    sub = SceneFile(path, file.options)
    text = sub.read_bytes(path, MAX_BINARY_BYTES, where).decode("utf-8", errors="replace")
    try:
        pos, uvs, parts, _ = _parse_obj(sub, text)
    except SceneError as exc:
        raise file.error(where, str(exc)) from None
    if not parts:
        raise file.error(where, f"{path.name} has no faces")
    corners = np.concatenate([np.array(t, dtype=np.int64).reshape(-1, 2) for t in parts.values()])
    uniq, inverse = np.unique(corners, axis=0, return_inverse=True)
    uv = None if (uniq[:, 1] < 0).any() else uvs[uniq[:, 1]]
    return pos[uniq[:, 0]], inverse.reshape(-1, 3), uv


def read_obj(file: SceneFile) -> Scene:
    """Read an OBJ file and its MTL libraries (see the module docstring).

    Raises:
        SceneError: naming the file, the line and the problem.
    """
    text = file.read_bytes(file.path, MAX_BINARY_BYTES).decode("utf-8", errors="replace")
    pos, uvs, parts, libs = _parse_obj(file, text)
    mtl: dict[str, dict[str, Any]] = {}
    for lib in libs:
        mtl.update(read_mtl(file, file.resolve(lib, f"mtllib {lib}"), f"mtllib {lib}"))
    if not parts:
        raise file.error("", "the file has no faces")
    materials: dict[str, dict[str, Any]] = {}
    objects, lights, names = [], [], set()
    by_name: dict[str, int] = {}
    for name, _ in parts:
        by_name[name] = by_name.get(name, 0) + 1
    for (name, mat_name), tris in parts.items():
        where = f"object {name!r}" + (f", material {mat_name!r}" if mat_name else "")
        m = mtl.get(mat_name, {}) if mat_name else {}
        if mat_name and mat_name not in mtl:
            file.unsupported(where, f"material {mat_name!r} is not in the MTL files {libs}", "a grey Lambert (0.8)")
        key = mat_name or "default"
        materials.setdefault(key, _material(key, m))
        corners = np.array(tris, dtype=np.int64).reshape(-1, 2)
        uniq, inverse = np.unique(corners, axis=0, return_inverse=True)
        faces = inverse.reshape(-1, 3)
        verts = pos[uniq[:, 0]]
        tex = m.get("map_Kd")
        uv = None
        if tex is not None:
            if (uniq[:, 1] < 0).any():
                raise file.error(where, f"uses texture {tex.name!r} but its faces have no UVs (vt)")
            uv = uvs[uniq[:, 1]]
        obj_name = unique_name(name if by_name[name] == 1 else f"{name}.{key}", names)
        try:
            mesh = validate_mesh(trimesh.Trimesh(vertices=verts, faces=faces, process=False), obj_name)
        except MeshError as exc:
            raise file.error(where, str(exc)) from None
        textures = {"base_color": tex} if tex is not None else {}
        objects.append(checked(file, where, SceneObject, obj_name, mesh, key, True, False, uv, textures))
        ke = m.get("Ke")
        if ke is not None and max(ke) > 0:
            lights.append(checked(file, where, AreaLight, mesh.vertices, mesh.faces, ke, len(objects) - 1))
    if not lights:
        lights.append(EnvironmentMap.sky())
    res = file.options.resolution or 256
    cam = auto_camera([o.mesh for o in objects], res, res)
    return checked(file, "scene", Scene, objects, materials, lights, cam, name=file.path.stem)
