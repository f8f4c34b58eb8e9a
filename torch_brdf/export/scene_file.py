"""Save a scene, with its current (edited) materials, as a TOML scene file that re-opens in the
CLI and the editor (:meth:`torch_brdf.scene.Scene.from_toml`).

Materials are written with Python's shortest round-trip float representation, so they come
back bit for bit; meshes are written beside the file as binary ``.ply`` (float64 vertices:
exact as well); environment maps as float32 EXR (our radiance buffers are float32: exact).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import torch

from ..errors import ExportError
from ..io.atomic import replacing

__all__ = ["save_scene_toml", "toml_dumps"]


def _value(v: Any, key: str) -> str:
    if isinstance(v, torch.Tensor):
        v = v.detach().cpu().tolist()
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ExportError(f"{key}: {v!r} cannot be written to a scene file")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x, key) for x in v) + "]"
    raise ExportError(f"{key}: a value of type {type(v).__name__} cannot be written to a scene file")


def toml_dumps(desc: dict[str, Any]) -> str:
    """A scene description (the layout of :mod:`torch_brdf.scene.scene`) as TOML text: scalars
    and arrays first, then ``[camera]``, ``[materials.NAME]``, ``[[objects]]``, ``[[lights]]``."""
    lines = []
    for k, v in desc.items():
        if not isinstance(v, dict | list) or (isinstance(v, list) and not (v and isinstance(v[0], dict))):
            lines.append(f"{k} = {_value(v, k)}")
    if "camera" in desc:
        lines += ["", "[camera]"] + [f"{k} = {_value(v, 'camera.' + k)}" for k, v in desc["camera"].items()]
    for name, mat in desc.get("materials", {}).items():
        lines += ["", f"[materials.{json.dumps(name)}]"]
        lines += [f"{json.dumps(k)} = {_value(v, f'materials.{name}.{k}')}" for k, v in mat.items()]
    for section in ("objects", "lights"):
        for i, item in enumerate(desc.get(section, [])):
            lines += ["", f"[[{section}]]"] + [f"{k} = {_value(v, f'{section}[{i}].{k}')}" for k, v in item.items()]
    return "\n".join(lines) + "\n"


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in str(name))[:60] or "object"


def save_scene_toml(scene, path: str | os.PathLike, materials: dict[str, dict] | None = None) -> Path:
    """Write ``scene`` (with ``materials`` replacing its material table when given) as a TOML
    scene file, its meshes in ``<stem>_meshes/``, environment maps as ``<stem>_env<k>.exr``.

    Args:
        scene: a :class:`~torch_brdf.scene.Scene`.
        path: the ``.toml`` file; its folder must exist.
        materials: material name -> material dict (the edited table); default the scene's.
    Returns:
        the path written.
    Raises:
        ExportError: a material value that TOML cannot hold (a tensor table, NaN), a light
            without a description, an unwritable path.
    """
    from ..io import write_exr
    from ..scene.envmap import EnvironmentMap
    from ..scene.lights import AreaLight, DirectionalLight

    path = Path(path)
    if not path.parent.is_dir():
        raise ExportError(f"cannot write {path}: folder {path.parent} does not exist")
    mats = {k: dict(v) for k, v in (materials if materials is not None else scene.materials).items()}
    cam = scene.camera
    desc: dict[str, Any] = {
        "name": scene.name,
        "camera": {
            "origin": [float(x) for x in cam.origin],
            "target": [float(x) for x in cam.target],
            "up": [float(x) for x in cam.up],
            "fov_deg": float(cam.fov_deg),
            "width": int(cam.width),
            "height": int(cam.height),
        },
        "materials": mats,
        "objects": [],
        "lights": [],
    }
    mesh_dir = path.parent / f"{path.stem}_meshes"
    try:
        mesh_dir.mkdir(exist_ok=True)
        for i, obj in enumerate(scene.objects):
            fname = mesh_dir / f"{i:03d}_{_safe(obj.name)}.ply"
            with replacing(fname) as tmp, open(tmp, "wb") as fh:
                fh.write(obj.mesh.export(file_type="ply", include_attributes=False))
            desc["objects"].append(
                {
                    "name": obj.name,
                    "mesh": f"{mesh_dir.name}/{fname.name}",
                    "material": obj.material,
                    "editable": bool(obj.editable),
                    "smooth": bool(obj.smooth),
                }
            )
        for k, light in enumerate(scene.lights):
            if isinstance(light, AreaLight) and light.object_id >= 0:
                rad = light.radiance.reshape(-1).tolist()
                desc["lights"].append({"type": "area", "object": scene.objects[light.object_id].name, "radiance": rad})
            elif isinstance(light, DirectionalLight):
                desc["lights"].append(
                    {
                        "type": "directional",
                        "direction": light.direction.tolist(),
                        "irradiance": light.irradiance.reshape(-1).tolist(),
                    }
                )
            elif isinstance(light, EnvironmentMap):
                exr = path.parent / f"{path.stem}_env{k}.exr"
                write_exr(exr, light.radiance.detach().float())
                rot = math.degrees(float(light.rotation_y))
                desc["lights"].append({"type": "envmap", "file": exr.name, "rotation_deg": rot})
            else:
                raise ExportError(f"light {k} ({type(light).__name__}) has no scene-file description")
        text = toml_dumps(desc)
        with replacing(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
    except OSError as exc:
        raise ExportError(f"cannot write {path} and its files: {exc.strerror or exc}") from exc
    return path
