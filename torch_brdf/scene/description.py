"""Validation of scene descriptions (TOML files and dicts, the layout of :mod:`.scene`).

Every key is checked against a schema before anything is built: its type (a string where a
string is meant, an integer — not ``256.0`` and not ``true`` — where a count is meant, 3
numbers for a point or a direction, a boolean for ``editable``/``smooth``), finite numbers
(``nan``/``inf`` are refused), sizes within the caps of :mod:`torch_brdf._checks`, and no
unknown keys. Every failure raises :class:`~torch_brdf.errors.SceneError` whose message
starts with the key's path (``camera.origin``, ``objects[2].smooth``,
``lights[0].rotation_deg``, ``materials.white.albedo``) and says what was expected, what
came and, for unknown keys, which keys are known.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .._checks import MAX_ENVMAP_HEIGHT, MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE
from ..errors import SceneError

#: largest scene file read (bytes); meshes belong in mesh files, not inline arrays
MAX_SCENE_FILE_BYTES = 64 * 2**20

Check = Callable[[Any, str], Any]
#: largest finite float32: radiance, albedos and vertices live in float32 buffers
FLOAT32_MAX = 3.4028234663852886e38


def _fail(key: str, want: str, value: Any) -> SceneError:
    shown = repr(value)
    if len(shown) > 80:
        shown = shown[:77] + "..."
    return SceneError(f"{key}: expected {want}; got {shown} ({type(value).__name__})")


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _real(lo: float | None = None, hi: float | None = None, open_lo: bool = False, open_hi: bool = False) -> Check:
    lo_s = "" if lo is None else f"{'>' if open_lo else '>='} {lo:g}"
    hi_s = "" if hi is None else f"{'<' if open_hi else '<='} {hi:g}"
    want = " and ".join(["a finite number" + (f" {lo_s}" if lo_s else ""), *([hi_s] if hi_s else [])])

    def check(v, key):
        if not _is_number(v) or not math.isfinite(v):
            raise _fail(key, want, v)
        if lo is not None and (v < lo or (open_lo and v == lo)):
            raise _fail(key, want, v)
        if hi is not None and (v > hi or (open_hi and v == hi)):
            raise _fail(key, want, v)
        return float(v)

    return check


def _int(lo: int, hi: int) -> Check:
    def check(v, key):
        if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
            raise _fail(key, f"an integer in [{lo}, {hi}]", v)
        return v

    return check


def _bool(v, key):
    if not isinstance(v, bool):
        raise _fail(key, "true or false (a TOML boolean, not a string)", v)
    return v


def _str(v, key):
    if not isinstance(v, str) or not v:
        raise _fail(key, "a non-empty string", v)
    return v


def _choice(*options: str) -> Check:
    def check(v, key):
        if v not in options:
            raise _fail(key, f"one of {list(options)}", v)
        return v

    return check


def _vec3(v, key):
    if not isinstance(v, list | tuple) or len(v) != 3 or not all(_is_number(x) and math.isfinite(x) for x in v):
        raise _fail(key, "3 finite numbers [x, y, z]", v)
    return [float(x) for x in v]


def _rgb(v, key):
    ok = _is_number(v) or (isinstance(v, list | tuple) and len(v) == 3 and all(_is_number(x) for x in v))
    vals = [v] if _is_number(v) else list(v) if ok else []
    if not ok or not all(math.isfinite(x) and 0 <= x <= FLOAT32_MAX for x in vals):
        raise _fail(key, f"a finite number in [0, {FLOAT32_MAX:.4g}] (float32) or 3 of them (RGB)", v)
    return float(v) if _is_number(v) else [float(x) for x in v]


def _rows(width: int, check: Check, what: str) -> Check:
    """A non-empty list of rows, each ``width`` values passing ``check``."""

    def rows(v, key):
        if not isinstance(v, list) or not v:
            raise _fail(key, f"a non-empty list of {what}", v)
        for i, row in enumerate(v):
            if not isinstance(row, list | tuple) or len(row) != width:
                raise _fail(f"{key}[{i}]", f"{width} values", row)
            for x in row:
                check(x, f"{key}[{i}]")
        return v

    return rows


_finite = _real()
#: vertex coordinates are traced in float32: larger magnitudes would become Inf there
_coordinate = _real(-FLOAT32_MAX, FLOAT32_MAX)
_index = _int(0, 2**31 - 1)

_CAMERA: dict[str, Check] = {
    "origin": _vec3,
    "target": _vec3,
    "up": _vec3,
    "fov_deg": _real(0, 180, open_lo=True, open_hi=True),
    "width": _int(1, MAX_IMAGE_SIDE),
    "height": _int(1, MAX_IMAGE_SIDE),
}
_OBJECT: dict[str, Check] = {
    "name": _str,
    "material": _str,
    "mesh": _str,
    "vertices": _rows(3, _coordinate, "vertices [x, y, z]"),
    "faces": _rows(3, _index, "faces [i, j, k] (vertex indices >= 0)"),
    "editable": _bool,
    "smooth": _bool,
    "scale": _real(0, None, open_lo=True),
    "rotate_y_deg": _finite,
    "translate": _vec3,
}
_LIGHTS: dict[str, dict[str, Check]] = {
    "area": {"type": _str, "object": _str, "radiance": _rgb},
    "directional": {"type": _str, "direction": _vec3, "irradiance": _rgb},
    "envmap": {},  # one of _ENVMAPS
}
_ENV_COMMON: dict[str, Check] = {"type": _str, "rotation_deg": _finite, "lookup": _choice("bilinear", "nearest")}
#: envmap lights: the keys of each variant (a file, or a procedural constant or sky map)
_ENVMAPS: dict[str, dict[str, Check]] = {
    "file": {**_ENV_COMMON, "file": _str, "scale": _real(0)},
    "constant": {**_ENV_COMMON, "procedural": _str, "radiance": _rgb, "height": _int(2, MAX_ENVMAP_HEIGHT)},
    "sky": {
        **_ENV_COMMON,
        "procedural": _str,
        "height": _int(2, MAX_ENVMAP_HEIGHT),
        "sun_direction": _vec3,
        "sun_angular_radius_deg": _real(0, 90, open_lo=True, open_hi=True),
        "sun_radiance": _rgb,
        "zenith_color": _rgb,
        "horizon_color": _rgb,
        "ground_color": _rgb,
        "supersample": _int(1, 64),
    },
}
_REQUIRED = {"camera": ("origin", "target"), "object": ("name", "material")}


def _table(v, key: str, schema: dict[str, Check], required: tuple[str, ...] = ()) -> dict[str, Any]:
    if not isinstance(v, dict):
        raise _fail(key, "a table", v)
    unknown = sorted(str(k) for k in v if k not in schema)
    if unknown:
        raise SceneError(f"{key}: unknown key(s) {unknown}; known keys: {sorted(schema)}")
    missing = [k for k in required if k not in v]
    if missing:
        raise SceneError(f"{key}: missing key(s) {missing}")
    return {k: schema[k](x, f"{key}.{k}") for k, x in v.items()}


def _array_of_tables(v, key: str) -> list:
    if not isinstance(v, list) or not all(isinstance(x, dict) for x in v):
        raise _fail(key, "an array of tables ([[...]] in TOML)", v)
    return v


def _material(v, key: str) -> dict[str, Any]:
    from ..brdf.base import available, model_parameters

    if not isinstance(v, dict):
        raise _fail(key, "a table with a 'type' (a BRDF model name) and its parameters", v)
    kind = v.get("type")
    if kind not in available():
        raise _fail(f"{key}.type", f"one of the BRDF models {available()}", kind)
    params = model_parameters(kind)
    if params is not None:
        known = sorted(["type", *params])
        unknown = sorted(str(k) for k in v if k not in known)
        if unknown:
            raise SceneError(f"{key}: unknown key(s) {unknown} for a {kind!r} material; known keys: {known}")
    for k, x in v.items():
        _plain_value(x, f"{key}.{k}")
    for k in ("albedo", "kd", "ks"):
        if k in v:
            _rgb(v[k], f"{key}.{k}")
    if kind not in _DATA_MODELS:  # values in range (exponent = -5, "abc"): before any long work
        from ..brdf.base import create
        from ..errors import TorchBRDFError

        try:
            create(dict(v))
        except (TorchBRDFError, TypeError, ValueError, RuntimeError) as exc:  # e.g. a ragged list
            raise SceneError(f"{key}: {exc}") from None
    return dict(v)


#: models built from data files (read when the scene is rendered, not when it is checked)
_DATA_MODELS = ("merl", "nbrdf")


def _plain_value(v, key: str) -> None:
    """Material parameters: strings, booleans, finite numbers, or (nested) lists of them."""
    if isinstance(v, list):
        for x in v:
            _plain_value(x, key)
    elif _is_number(v):
        if not math.isfinite(v):
            raise _fail(key, "finite numbers", v)
    elif not isinstance(v, str | bool):
        raise _fail(key, "a string, a boolean, a finite number or a list of them", v)


def validate_description(desc: Any) -> dict[str, Any]:
    """Check a scene description against the schema (module docstring) and return it.

    Args:
        desc: the parsed TOML (or a dict of the same layout).
    Returns:
        The description with numbers as floats where floats are meant.
    Raises:
        SceneError: the first problem found, naming its key.
    """
    top = {"name": _str, "camera": None, "materials": None, "objects": None, "lights": None}
    if not isinstance(desc, dict):
        raise _fail("scene", "a table", desc)
    unknown = sorted(str(k) for k in desc if k not in top)
    if unknown:
        raise SceneError(f"scene: unknown key(s) {unknown}; known keys: {sorted(top)}")
    for k in ("camera", "materials", "objects"):
        if k not in desc:
            raise SceneError(f"scene description lacks {k!r}")
    out: dict[str, Any] = {}
    if "name" in desc:
        out["name"] = _str(desc["name"], "name")
    cam = _table(desc["camera"], "camera", _CAMERA, _REQUIRED["camera"])
    w, h = cam.get("width", 256), cam.get("height", 256)
    if w * h > MAX_IMAGE_PIXELS:
        raise SceneError(f"camera: image {w}x{h} = {w * h} pixels exceeds the cap of {MAX_IMAGE_PIXELS} (8192 x 8192)")
    out["camera"] = cam
    mats = desc["materials"]
    if not isinstance(mats, dict) or not mats:
        raise _fail("materials", "a table of name -> material table", mats)
    out["materials"] = {str(k): _material(m, f"materials.{k}") for k, m in mats.items()}
    objects = []
    for i, o in enumerate(_array_of_tables(desc["objects"], "objects")):
        key = f"objects[{i}]"
        o = _table(o, key, _OBJECT, _REQUIRED["object"])
        if ("vertices" in o) != ("faces" in o) or ("mesh" in o) == ("vertices" in o):
            raise SceneError(f"{key}: needs either 'mesh' (a file) or both 'vertices' and 'faces'")
        objects.append(o)
    if not objects:
        raise SceneError("objects: a scene needs at least one object")
    out["objects"] = objects
    lights = []
    for i, li in enumerate(_array_of_tables(desc.get("lights", []), "lights")):
        key = f"lights[{i}]"
        kind = li.get("type")
        if not isinstance(kind, str) or kind not in _LIGHTS:
            raise _fail(f"{key}.type", f"one of {sorted(_LIGHTS)}", kind)
        schema, required = _LIGHTS[kind], {"area": ("object",), "directional": ("direction",)}.get(kind, ())
        if kind == "envmap":
            if ("file" in li) == ("procedural" in li):
                raise SceneError(f"{key}: an envmap light needs either 'file' or procedural = 'sky' | 'constant'")
            variant = "file" if "file" in li else _choice("sky", "constant")(li["procedural"], f"{key}.procedural")
            schema = _ENVMAPS[variant]
        lights.append(_table(li, key, schema, required))
    out["lights"] = lights
    return out


def read_scene_file(path: str | os.PathLike) -> dict[str, Any]:
    """Read and parse a TOML scene file (not yet validated).

    Raises:
        SceneError: missing, a directory, unreadable, larger than
            :data:`MAX_SCENE_FILE_BYTES`, not UTF-8, or not valid TOML.
    """
    import sys

    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib

    path = Path(path)
    try:
        if path.is_dir():
            raise SceneError(f"scene file {path} is a directory")
        size = path.stat().st_size
        if size > MAX_SCENE_FILE_BYTES:
            raise SceneError(f"scene file {path} has {size} bytes; the cap is {MAX_SCENE_FILE_BYTES}")
        text = path.read_bytes().decode("utf-8")
        return tomllib.loads(text)
    except FileNotFoundError as exc:
        raise SceneError(f"scene file not found: {path}") from exc
    except OSError as exc:
        raise SceneError(f"cannot read scene file {path}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise SceneError(f"scene file {path} is not UTF-8 text (byte {exc.start}): TOML files are UTF-8") from exc
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"scene file {path} is not valid TOML: {exc}") from exc
