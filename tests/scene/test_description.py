"""TOML scene validation: every key type-checked with its name in the message, unknown keys
refused with the known ones, non-finite numbers and oversized images refused, and random
mutations of a valid file's keys and values either load or raise the package's error."""

from __future__ import annotations

import copy
import json
import math

import pytest
import trimesh
from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st

from torch_brdf.errors import SceneError, TorchBRDFError
from torch_brdf.scene import Scene

VALID = {
    "name": "mutant",
    "camera": {"origin": [0.0, 1.0, -5.0], "target": [0.0, 0.5, 0.0], "fov_deg": 40.0, "width": 12, "height": 8},
    "materials": {
        "white": {"type": "lambert", "albedo": [0.7, 0.7, 0.7]},
        "shiny": {"type": "blinn_phong", "kd": 0.2, "ks": 0.5, "exponent": 50.0},
        "glow": {"type": "lambert", "albedo": 0.0},
    },
    "objects": [
        {
            "name": "block",
            "mesh": "box.obj",
            "material": "shiny",
            "scale": 2.0,
            "rotate_y_deg": 90.0,
            "translate": [1.0, 0.5, 0.0],
            "smooth": True,
        },
        {
            "name": "lamp",
            "vertices": [[-0.5, 3.0, -0.5], [0.5, 3.0, -0.5], [0.5, 3.0, 0.5], [-0.5, 3.0, 0.5]],
            "faces": [[0, 1, 2], [0, 2, 3]],
            "material": "glow",
            "editable": False,
        },
    ],
    "lights": [
        {"type": "area", "object": "lamp", "radiance": [5.0, 4.0, 3.0]},
        {"type": "directional", "direction": [0.0, 1.0, 0.2], "irradiance": 2.0},
        {"type": "envmap", "procedural": "sky", "height": 8, "rotation_deg": 30.0, "sun_radiance": 100.0},
    ],
}


def toml_value(v) -> str:
    """A TOML value (inline tables and arrays), enough for the descriptions written here."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(str(k))} = {toml_value(x)}" for k, x in v.items()) + "}"


def write_scene(folder, desc) -> object:
    path = folder / "scene.toml"
    path.write_text("\n".join(f"{json.dumps(k)} = {toml_value(v)}" for k, v in desc.items()) + "\n")
    return path


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    d = tmp_path_factory.mktemp("scenes")
    trimesh.creation.box(extents=(1.0, 0.5, 0.25)).export(d / "box.obj")
    return d


def mutated(path: tuple, op: str, value=None) -> dict:
    desc = copy.deepcopy(VALID)
    node = desc
    for k in path[:-1]:
        node = node[k]
    last = path[-1]
    if op == "delete":
        del node[last]
    elif op == "set":
        node[last] = value
    else:  # "add": an unknown key next to ``last``
        (node[last] if isinstance(node[last], dict) else node)["colour"] = value
    return desc


def test_the_valid_scene_loads(folder):
    scene = Scene.from_toml(write_scene(folder, VALID))
    assert [o.name for o in scene.objects] == ["block", "lamp"] and len(scene.lights) == 3


# mutations a bad-input campaign found escaping or silently accepted
NAMED = [
    (("camera", "origin"), [1, 2], "camera.origin"),
    (("camera", "fov_deg"), "wide", "camera.fov_deg"),
    (("camera", "width"), 256.0, "camera.width"),
    (("lights",), [1], "lights"),
    (("objects", 0, "mesh"), 5, r"objects\[0\].mesh"),
    (("objects", 1, "editable"), "no", r"objects\[1\].editable"),
    (("objects", 0, "smooth"), "false", r"objects\[0\].smooth"),
    (("objects", 0, "scale"), -1.0, r"objects\[0\].scale"),
    (("lights", 2, "rotation_deg"), math.nan, r"lights\[2\].rotation_deg"),
    (("lights", 1, "direction"), [0.0, math.inf, 0.0], r"lights\[1\].direction"),
    (("lights", 0, "radiance"), [1.0, math.nan, 1.0], r"lights\[0\].radiance"),
    # beyond float32 (the lights' buffers): the render came out Inf, refused only after it
    (("lights", 1, "irradiance"), 1e300, r"lights\[1\].irradiance"),
    (("lights", 0, "radiance"), [1.0, 1e39, 1.0], r"lights\[0\].radiance"),
    (("objects", 1, "vertices", 0), [-0.5, 1e300, -0.5], r"objects\[1\].vertices\[0\]"),
    (("lights", 2, "height"), 100000, r"lights\[2\].height"),
    (("materials", "white", "albedo"), "red", "materials.white.albedo"),
    (("materials", "shiny", "exponent"), math.inf, "materials.shiny.exponent"),
    (("materials", "white", "type"), "gold", "materials.white.type"),
]


# values of the right type the BRDF refuses: refused only once rendering (or a precompute) began
MATERIAL_VALUES = [
    ("exponent", -5.0, r"BlinnPhong.exponent must lie in \[0.001, 10000\]; got -5.0"),
    ("exponent", "abc", "BlinnPhong.exponent must be a number or a list of numbers; got 'abc'"),
    ("exponent", [[0], []], "BlinnPhong.exponent must be a number or a list of numbers"),  # ragged
    ("ks", 1.5, r"must lie in \[0.0, 1.0\]"),
]


@pytest.mark.parametrize(("param", "value", "words"), MATERIAL_VALUES)
def test_material_values_the_brdf_refuses_raise_scene_error_at_load(folder, param, value, words):
    with pytest.raises(SceneError, match=rf"^materials.shiny: .*{words}"):
        Scene.from_toml(write_scene(folder, mutated(("materials", "shiny", param), "set", value)))


@pytest.mark.parametrize(("path", "value", "key"), NAMED, ids=[n[2].replace("\\", "") for n in NAMED])
def test_bad_values_raise_scene_error_naming_the_key(folder, path, value, key):
    with pytest.raises(SceneError, match=rf"^{key}: expected"):
        Scene.from_toml(write_scene(folder, mutated(path, "set", value)))


def test_huge_images_are_refused_before_anything_is_allocated(folder):
    desc = mutated(("camera", "width"), "set", 100000)
    desc["camera"]["height"] = 100000
    with pytest.raises(SceneError, match=r"camera.width: expected an integer in \[1, 16384\]"):
        Scene.from_toml(write_scene(folder, desc))
    desc["camera"].update(width=16384, height=16384)
    with pytest.raises(SceneError, match="exceeds the cap"):
        Scene.from_toml(write_scene(folder, desc))


@pytest.mark.parametrize(
    ("path", "where", "known"),
    [
        (("camera",), "camera", "fov_deg"),
        (("objects", 0), r"objects\[0\]", "rotate_y_deg"),
        (("lights", 2), r"lights\[2\]", "sun_direction"),
        (("materials", "shiny"), "materials.shiny", "exponent"),
        (("name",), "scene", "materials"),
    ],
)
def test_unknown_keys_are_refused_with_the_known_ones(folder, path, where, known):
    with pytest.raises(SceneError, match=rf"^{where}: unknown key\(s\) \['colour'\].*known keys: .*{known}"):
        Scene.from_toml(write_scene(folder, mutated(path, "add", 1.0)))


def test_unreadable_files_raise_scene_error(folder, tmp_path):
    bad = tmp_path / "latin1.toml"
    bad.write_bytes(write_scene(folder, VALID).read_bytes().replace(b'"mutant"', b'"caf\xe9"'))
    with pytest.raises(SceneError, match="not UTF-8"):
        Scene.from_toml(bad)
    (tmp_path / "dir.toml").mkdir()
    with pytest.raises(SceneError, match="is a directory"):
        Scene.from_toml(tmp_path / "dir.toml")


def _paths(node, prefix=()):
    """Every key path of a description: tables, arrays and leaves."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for k, v in items:
        yield (*prefix, k)
        yield from _paths(v, (*prefix, k))


PATHS = list(_paths(VALID))
SCALARS = st.one_of(
    st.integers(-(2**63), 2**63 - 1),
    st.integers(-3, 20),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.booleans(),
)
VALUES = st.recursive(
    SCALARS,
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=3)),
    max_leaves=8,
)


@seed(13)
@settings(
    max_examples=300, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(path=st.sampled_from(PATHS), op=st.sampled_from(["set", "set", "delete", "add"]), value=VALUES)
def test_every_mutation_loads_or_raises_the_package_error(folder, path, op, value):
    if op == "add" and not isinstance(path[-1], str):
        op = "set"
    desc = mutated(path, op, value)
    try:
        Scene.from_toml(write_scene(folder, desc))
    except TorchBRDFError:
        pass  # anything else (TypeError, KeyError, RuntimeError, ...) fails the test
