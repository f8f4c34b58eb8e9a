"""Scene descriptions (dict / TOML), lookups, info, resolution changes, bad descriptions,
and the built-in scenes (with and without the shared data), including the Cornell box
against the published parts in the shared data folder."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
import torch
import trimesh

from tests.conftest import shared_file
from torch_brdf.data import data_path
from torch_brdf.errors import SceneError
from torch_brdf.scene import (
    BUILTIN_SCENES,
    AreaLight,
    DirectionalLight,
    EnvironmentMap,
    Scene,
    cornell_box,
    load_mesh,
)
from torch_brdf.scene.builtin import CORNELL_RGB, cornell_box_meshes

# --------------------------------------------------------------------------------------------
# descriptions
# --------------------------------------------------------------------------------------------

BOX_EXTENTS = (1.0, 0.5, 0.25)  # asymmetric, so that the rotation is visible

SCENE_TOML = """
name = "toml_scene"

[camera]
origin = [0.0, 1.0, -5.0]
target = [0.0, 0.5, 0.0]
fov_deg = 40.0
width = 24
height = 16

[materials.white]
type = "lambert"
albedo = [0.7, 0.7, 0.7]

[materials.glow]
type = "lambert"
albedo = 0.0

[[objects]]
name = "block"
mesh = "meshes/box.obj"
material = "white"
scale = 2.0
rotate_y_deg = 90.0
translate = [1.0, 0.5, 0.0]
smooth = true

[[objects]]
name = "lamp"
vertices = [[-0.5, 3.0, -0.5], [0.5, 3.0, -0.5], [0.5, 3.0, 0.5], [-0.5, 3.0, 0.5]]
faces = [[0, 1, 2], [0, 2, 3]]
material = "glow"
editable = false

[[lights]]
type = "area"
object = "lamp"
radiance = [5.0, 4.0, 3.0]

[[lights]]
type = "envmap"
procedural = "sky"
height = 16
rotation_deg = 30.0
"""


@pytest.fixture
def toml_scene_path(tmp_path, monkeypatch):
    """scene.toml + meshes/box.obj in tmp_path; the working directory is elsewhere, so a
    relative mesh path only resolves against the TOML file's folder."""
    (tmp_path / "meshes").mkdir()
    trimesh.creation.box(extents=BOX_EXTENTS).export(tmp_path / "meshes" / "box.obj")
    path = tmp_path / "scene.toml"
    path.write_text(SCENE_TOML)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    return path


def _small_desc() -> dict:
    """A minimal valid description (a triangle in front of the camera)."""
    return {
        "camera": {"origin": [0.0, 0.0, -3.0], "target": [0.0, 0.0, 0.0], "width": 8, "height": 6},
        "materials": {"m": {"type": "lambert", "albedo": 0.5}},
        "objects": [
            {"name": "tri", "material": "m", "vertices": [[-1, -1, 0], [1, -1, 0], [0, 1, 0]], "faces": [[0, 1, 2]]}
        ],
    }


def _sorted_rows(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return a[np.lexsort(a.T[::-1])]


def test_from_toml_builds_objects_placement_and_lights(toml_scene_path):
    scene = Scene.from_toml(toml_scene_path)
    assert scene.name == "toml_scene"
    assert [o.name for o in scene.objects] == ["block", "lamp"]
    block, lamp = scene.objects
    assert (block.material, block.smooth, block.editable) == ("white", True, True)
    assert (lamp.material, lamp.smooth, lamp.editable) == ("glow", False, False)
    # scale 2, then +90 deg about +y (right-handed: +x -> -z), then translate
    half = np.array(BOX_EXTENTS) / 2
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half * 2.0
    rot = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    want = corners @ rot.T + [1.0, 0.5, 0.0]
    np.testing.assert_allclose(_sorted_rows(block.mesh.vertices), _sorted_rows(want), atol=1e-9)
    assert block.mesh.volume == pytest.approx(8 * np.prod(BOX_EXTENTS))  # orientation kept
    # lights: the area light is the lamp object, facing down; the sky is rotated
    area, env = scene.lights
    assert isinstance(area, AreaLight) and isinstance(env, EnvironmentMap)
    assert area.object_id == scene.object_id("lamp") == 1
    assert scene.area_lights == {1: area}
    assert area.total_area == pytest.approx(1.0)
    torch.testing.assert_close(area.normals, torch.tensor([[0.0, -1.0, 0.0]]).expand(2, 3))
    torch.testing.assert_close(area.radiance, torch.tensor([5.0, 4.0, 3.0]))
    assert scene.environment is env
    assert env.height == 16 and env.rotation_y == pytest.approx(math.radians(30.0))
    assert (scene.camera.width, scene.camera.height, scene.camera.fov_deg) == (24, 16, 40.0)


def test_from_toml_traces_the_placed_geometry(toml_scene_path):
    scene = Scene.from_toml(toml_scene_path)
    o = torch.tensor([[1.0, 5.0, 0.9], [0.0, 5.0, 0.0], [-3.0, 5.0, 0.0]])
    d = torch.tensor([[0.0, -1.0, 0.0]]).expand(3, 3)
    hits = scene.trace(o, d)
    assert hits.object_id.tolist() == [0, 1, -1]  # block top (y = 1), lamp (y = 3), nothing
    torch.testing.assert_close(hits.t[:2], torch.tensor([4.0, 2.0]), atol=1e-5, rtol=0)


def test_from_toml_name_defaults_to_file_stem(tmp_path):
    path = tmp_path / "my_room.toml"
    path.write_text(
        '[camera]\norigin = [0, 0, -3]\ntarget = [0, 0, 0]\n[materials.m]\ntype = "lambert"\n'
        '[[objects]]\nname = "t"\nmaterial = "m"\nvertices = [[-1, -1, 0], [1, -1, 0], [0, 1, 0]]\n'
        "faces = [[0, 1, 2]]\n"
    )
    scene = Scene.from_toml(path)
    assert scene.name == "my_room"
    assert scene.lights == []


def test_from_dict_base_dir_resolves_relative_meshes(tmp_path, monkeypatch):
    trimesh.creation.box().export(tmp_path / "b.obj")
    monkeypatch.chdir(tmp_path.parent)
    desc = _small_desc()
    desc["objects"].append({"name": "box", "material": "m", "mesh": "b.obj", "translate": [0, 0, 5]})
    scene = Scene.from_dict(desc, base_dir=tmp_path)
    assert len(scene.objects[1].mesh.faces) == 12
    np.testing.assert_allclose(scene.objects[1].mesh.bounds, [[-0.5, -0.5, 4.5], [0.5, 0.5, 5.5]], atol=1e-9)


def test_from_dict_lights_directional_and_constant_envmap():
    desc = _small_desc()
    desc["lights"] = [
        {"type": "directional", "direction": [0, 3, -4], "irradiance": [1, 2, 3]},
        {"type": "envmap", "procedural": "constant", "height": 4},
    ]
    scene = Scene.from_dict(desc)
    sun, env = scene.lights
    assert isinstance(sun, DirectionalLight) and isinstance(env, EnvironmentMap)
    torch.testing.assert_close(sun.direction, torch.tensor([0.0, 0.6, -0.8]))
    torch.testing.assert_close(sun.irradiance, torch.tensor([1.0, 2.0, 3.0]))
    assert env.radiance.shape == (4, 8, 3)
    torch.testing.assert_close(env.radiance, torch.ones(4, 8, 3))
    assert scene.area_lights == {}


def test_constant_envmap_radiance_from_description():
    desc = _small_desc()
    desc["lights"] = [{"type": "envmap", "procedural": "constant", "radiance": [0.5, 0.25, 1.0], "height": 4}]
    env = Scene.from_dict(desc).environment
    torch.testing.assert_close(env.radiance, torch.tensor([0.5, 0.25, 1.0]).expand(4, 8, 3))


def _with(mutate):
    desc = _small_desc()
    mutate(desc)
    return desc


def _del(keys):
    def go(d):
        for k in keys[:-1]:
            d = d[k]
        del d[keys[-1]]

    return go


_BAD = {
    "unknown-material": lambda d: d["objects"][0].update(material="gold"),
    "duplicate-names": lambda d: d["objects"].append(copy.deepcopy(d["objects"][0])),
    "area-light-unknown-object": lambda d: d.update(lights=[{"type": "area", "object": "ghost"}]),
    "area-light-without-object": lambda d: d.update(lights=[{"type": "area"}]),
    "unknown-light-type": lambda d: d.update(lights=[{"type": "spot", "position": [0, 1, 0]}]),
    "light-without-type": lambda d: d.update(lights=[{"object": "tri"}]),
    "envmap-without-source": lambda d: d.update(lights=[{"type": "envmap"}]),
    "sky-unknown-key": lambda d: d.update(lights=[{"type": "envmap", "procedural": "sky", "sun_size": 2.0}]),
    "constant-unknown-key": lambda d: d.update(lights=[{"type": "envmap", "procedural": "constant", "rgb": 1.0}]),
    "two-envmaps": lambda d: d.update(lights=[{"type": "envmap", "procedural": "constant", "height": 2}] * 2),
    "missing-camera": _del(["camera"]),
    "missing-materials": _del(["materials"]),
    "missing-objects": _del(["objects"]),
    "no-objects": lambda d: d.update(objects=[]),
    "object-without-name": _del(["objects", 0, "name"]),
    "object-without-material": _del(["objects", 0, "material"]),
    "object-without-geometry": lambda d: [d["objects"][0].pop(k) for k in ("vertices", "faces")],
    "camera-without-origin": _del(["camera", "origin"]),
    "camera-unknown-key": lambda d: d["camera"].update(zoom=2.0),
    "material-without-type": _del(["materials", "m", "type"]),
    "material-negative-albedo": lambda d: d["materials"]["m"].update(albedo=-0.5),
}


@pytest.mark.parametrize("case", list(_BAD))
def test_bad_descriptions_raise_scene_error(case):
    with pytest.raises(SceneError):
        Scene.from_dict(_with(_BAD[case]))


@pytest.mark.parametrize(
    "case",
    [
        pytest.param(lambda d: d.update(lights=[{"type": "directional", "irradiance": 1.0}]), id="no-direction"),
        pytest.param(lambda d: d["materials"].update(m="lambert"), id="material-not-a-table"),
        pytest.param(lambda d: d["objects"][0].update(translate=[1.0, 2.0]), id="translate-of-two-numbers"),
    ],
)
def test_bad_descriptions_found_by_review_raise_scene_error(case):
    with pytest.raises(SceneError):
        Scene.from_dict(_with(case))


def test_invalid_or_missing_toml_raises_scene_error(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera\norigin = [0, 0, -3]\n")
    with pytest.raises(SceneError, match=r"bad\.toml"):
        Scene.from_toml(bad)
    with pytest.raises(SceneError, match=r"absent\.toml"):
        Scene.from_toml(tmp_path / "absent.toml")
    (tmp_path / "partial.toml").write_text('[materials.m]\ntype = "lambert"\n')
    with pytest.raises(SceneError, match="camera"):
        Scene.from_toml(tmp_path / "partial.toml")


def test_info_fields(toml_scene_path):
    info = Scene.from_toml(toml_scene_path).info()
    assert info["name"] == "toml_scene"
    assert info["triangles"] == 14
    assert info["lights"] == ["AreaLight", "EnvironmentMap"]
    assert info["objects"] == [
        {
            "id": 0,
            "name": "block",
            "material": "white",
            "type": "lambert",
            "editable": True,
            "triangles": 12,
            "vertices": 8,
        },
        {
            "id": 1,
            "name": "lamp",
            "material": "glow",
            "type": "lambert",
            "editable": False,
            "triangles": 2,
            "vertices": 4,
        },
    ]
    # block: x in [0.75, 1.25], y in [0, 1], z in [-1, 1]; lamp: [-0.5, 0.5] x {3} x [-0.5, 0.5]
    np.testing.assert_allclose(info["bounds"], [[-0.5, 0.0, -1.0], [1.25, 3.0, 1.0]], atol=1e-6)
    assert info["camera"] == {"origin": (0.0, 1.0, -5.0), "target": (0.0, 0.5, 0.0), "fov_deg": 40.0, "size": [24, 16]}
    json.dumps(info)  # plain data, ready for the CLI


def test_with_resolution_keeps_geometry(toml_scene_path):
    scene = Scene.from_toml(toml_scene_path)
    big = scene.with_resolution(40, 30)
    square = scene.with_resolution(32)
    assert (big.camera.width, big.camera.height) == (40, 30)
    assert (square.camera.width, square.camera.height) == (32, 32)
    assert (scene.camera.width, scene.camera.height) == (24, 16), "the original scene is unchanged"
    for other in (big, square):
        assert other.objects is scene.objects and other.lights is scene.lights
        assert other.tracer is scene.tracer
        assert (other.camera.origin, other.camera.target, other.camera.fov_deg) == (
            scene.camera.origin,
            scene.camera.target,
            scene.camera.fov_deg,
        )
    # same vertical fov: the centre row of rays spans the same angles
    _, d0 = scene.camera.rays_through([12.0], [0.0], dtype=torch.float64)
    _, d1 = big.camera.rays_through([20.0], [0.0], dtype=torch.float64)
    torch.testing.assert_close(d0, d1)


def test_object_id_lookup():
    desc = _small_desc()
    desc["objects"].append(
        {"name": "other", "material": "m", "vertices": [[0, 0, 1], [1, 0, 1], [0, 1, 1]], "faces": [[0, 1, 2]]}
    )
    scene = Scene.from_dict(desc)
    assert scene.object_id("tri") == 0 and scene.object_id("other") == 1
    assert scene.material_of(1) == {"type": "lambert", "albedo": 0.5}
    with pytest.raises(SceneError, match="nobody"):
        scene.object_id("nobody")


# --------------------------------------------------------------------------------------------
# built-in scenes
# --------------------------------------------------------------------------------------------

#: objects that a 16 x 16 primary-ray image of each built-in must show
_VISIBLE = {
    "cornell_box": {"floor", "ceiling", "back", "left", "right", "short_box", "tall_box"},
    "cornell_box_glossy": {"floor", "ceiling", "back", "left", "right", "short_box", "tall_box"},
    "teatray": {"teapot", "tray"},
    "ring": {"ring", "plane"},
    "bunny_plane": {"bunny", "plane"},
    "bunny_relight": {"bunny", "plane"},
}


def _check_builtin(scene: Scene, name: str):
    assert (scene.camera.width, scene.camera.height) == (16, 16)
    o, d = scene.camera.generate_rays()
    hits = scene.trace(o, d)
    assert float(hits.hit.float().mean()) > 0.5
    seen = {scene.objects[i].name for i in hits.object_id[hits.hit].unique().tolist()}
    assert _VISIBLE[name] <= seen, f"{name}: expected to see {_VISIBLE[name]}, saw {seen}"
    for field in (hits.position, hits.geometric_normal, hits.normal, hits.t[hits.hit]):
        assert bool(torch.isfinite(field).all())
    assert set(BUILTIN_SCENES) == set(_VISIBLE)
    info = scene.info()
    assert info["name"] == name and info["triangles"] > 0


def _check_resting(scene: Scene, name: str):
    """Objects rest on their supports (the placement code of the built-ins)."""
    if name == "teatray":
        teapot = scene.objects[scene.object_id("teapot")].mesh
        tray = scene.objects[scene.object_id("tray")].mesh
        floor = scene.objects[scene.object_id("floor")].mesh
        assert teapot.bounds[0, 1] == pytest.approx(tray.bounds[1, 1])
        assert tray.bounds[0, 1] == pytest.approx(floor.bounds[0, 1])
        np.testing.assert_allclose((teapot.bounds[0] + teapot.bounds[1])[[0, 2]], 0.0, atol=1e-9)
    elif name in ("bunny_plane", "bunny_relight"):
        bunny = scene.objects[scene.object_id("bunny")].mesh
        assert bunny.bounds[0, 1] == pytest.approx(0.0, abs=1e-9)
        np.testing.assert_allclose((bunny.bounds[0] + bunny.bounds[1])[[0, 2]], 0.0, atol=1e-9)


@pytest.mark.parametrize("name", list(_VISIBLE))
def test_builtin_scene_builds_and_is_seen(name):
    scene = BUILTIN_SCENES[name](16)
    _check_builtin(scene, name)
    _check_resting(scene, name)


@pytest.mark.parametrize("name", list(_VISIBLE))
def test_builtin_scene_with_procedural_stand_ins(name, tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_BRDF_DATA", str(tmp_path / "no-such-folder"))
    assert data_path("meshes", "teapot.obj", required=False) is None
    scene = BUILTIN_SCENES[name](16)
    _check_builtin(scene, name)
    _check_resting(scene, name)


def test_builtin_rectangular_resolution():
    scene = cornell_box((24, 16))
    assert (scene.camera.width, scene.camera.height) == (24, 16)


def test_teatray_uses_the_shared_teapot_when_present():
    path = shared_file("meshes", "teapot.obj")
    scene = BUILTIN_SCENES["teatray"](16)
    assert len(scene.objects[scene.object_id("teapot")].mesh.faces) == len(load_mesh(path).faces)


# -- the Cornell box ---------------------------------------------------------------------------

CORNELL_NAMES = ["floor", "ceiling", "back", "left", "right", "short_box", "tall_box", "light"]
WALLS = ["floor", "ceiling", "back", "left", "right"]
BLOCKS = ["short_box", "tall_box"]
BOX_CENTRE = np.array([278.0, 274.4, 279.6])


@pytest.fixture(scope="module")
def cornell():
    return cornell_box(16)


def _face_normals(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit counter-clockwise normals (F, 3), centroids (F, 3) and areas (F,)."""
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    c = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(c, axis=1)
    return c / area2[:, None], tri.mean(1), area2 / 2


def test_cornell_objects_and_light(cornell):
    assert sorted(o.name for o in cornell.objects) == sorted(CORNELL_NAMES)
    assert len(cornell.objects) == 8
    areas = [li for li in cornell.lights if isinstance(li, AreaLight)]
    assert len(areas) == 1 and len(cornell.lights) == 1
    light = areas[0]
    assert light.object_id == cornell.object_id("light")
    assert cornell.area_lights == {light.object_id: light}
    torch.testing.assert_close(light.normals, torch.tensor([[0.0, -1.0, 0.0]]).expand_as(light.normals))
    lm = cornell.objects[light.object_id].mesh
    n, _, _ = _face_normals(lm)
    np.testing.assert_allclose(n, [[0.0, -1.0, 0.0]] * len(n), atol=1e-12)
    ceiling_y = cornell.objects[cornell.object_id("ceiling")].mesh.vertices[:, 1]
    np.testing.assert_allclose(lm.vertices[:, 1], ceiling_y.max() - 0.5, atol=1e-9)
    assert light.total_area == pytest.approx(130.0 * 105.0)


@pytest.mark.parametrize("part", WALLS)
def test_cornell_walls_face_into_the_box(cornell, part):
    n, c, _ = _face_normals(cornell.objects[cornell.object_id(part)].mesh)
    toward = BOX_CENTRE - c
    assert bool((np.einsum("ij,ij->i", n, toward) > 0).all())


@pytest.mark.parametrize("part", BLOCKS)
def test_cornell_block_faces_face_outward(cornell, part):
    mesh = cornell.objects[cornell.object_id(part)].mesh
    v = np.asarray(mesh.vertices)
    centre = np.array([v[:, 0].mean(), v[:, 1].max() / 2, v[:, 2].mean()])
    n, c, _ = _face_normals(mesh)
    assert bool((np.einsum("ij,ij->i", n, c - centre) > 0).all())


def test_cornell_walls_face_the_camera_rays(cornell):
    """The tracer's geometric normal at every primary hit on a wall or block faces the camera."""
    o, d = cornell.camera.generate_rays()
    hits = cornell.trace(o, d)
    assert bool(hits.hit.all())
    assert bool(((hits.geometric_normal * d).sum(-1) < 0).all())


def test_cornell_camera_matches_published(cornell):
    cam = json.loads(shared_file("meshes", "cornell", "materials.json").read_text())["camera"]
    assert cornell.camera.origin == tuple(cam["position"])
    f = np.subtract(cam["look_at"], cam["position"])
    np.testing.assert_allclose(cornell.camera.frame[2].numpy(), f / np.linalg.norm(f), atol=1e-12)
    assert cornell.camera.up == tuple(cam["up"])
    assert cornell.camera.fov_deg == pytest.approx(cam["fov_deg"], abs=0.01)


def _published_part(name: str) -> trimesh.Trimesh:
    path = shared_file("meshes", "cornell", f"{name}.obj")
    mesh = trimesh.load(path, process=False, force="mesh")
    if name == "light":  # lowered by 0.5 mm in the built-in (and in the reference scene)
        mesh.apply_translation([0.0, -0.5, 0.0])
    return mesh


def _triangle_set(mesh: trimesh.Trimesh, drop=None) -> np.ndarray:
    """Rows of 9 coordinates, corners sorted within a triangle, triangles sorted: equal for
    the same triangles whatever the vertex order and winding."""
    tri = np.round(np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)], 4)
    if drop is not None:
        tri = tri[~drop(tri)]
    rows = np.array([t[np.lexsort(t.T[::-1])].reshape(-1) for t in tri])
    return rows[np.lexsort(rows.T[::-1])]


def _unique_vertices(mesh: trimesh.Trimesh) -> np.ndarray:
    return np.unique(np.round(np.asarray(mesh.vertices, dtype=np.float64), 4), axis=0)


# The blocks are compared by test_cornell_block_sides_and_top_equal_published_obj: like the
# original Cornell data they have 5 faces (no bottom on the floor), the shared OBJ parts 6.
@pytest.mark.parametrize("part", [*WALLS, "light"])
def test_cornell_part_equals_published_obj(cornell, part):
    ours = cornell.objects[cornell.object_id(part)].mesh
    ref = _published_part(part)
    assert ours.area == pytest.approx(ref.area, rel=1e-9)
    np.testing.assert_allclose(_triangle_set(ours), _triangle_set(ref), atol=1e-9)


@pytest.mark.parametrize("part", [*WALLS, "light", *BLOCKS])
def test_cornell_part_vertices_and_orientation_match_published_obj(cornell, part):
    ours = cornell.objects[cornell.object_id(part)].mesh
    ref = _published_part(part)
    np.testing.assert_allclose(_unique_vertices(ours), _unique_vertices(ref), atol=1e-9)
    # every triangle of ours faces the same way as the published triangles in its plane
    n_ours, c_ours, _ = _face_normals(ours)
    n_ref, c_ref, _ = _face_normals(ref)
    for n, c in zip(n_ours, c_ours, strict=True):
        same_plane = (np.abs(n_ref @ n) > 1 - 1e-9) & (np.abs(np.einsum("ij,j->i", c_ref - c, n)) < 1e-6)
        assert same_plane.any(), f"{part}: no published triangle in the plane of one of ours"
        assert bool((n_ref[same_plane] @ n > 0).all()), f"{part}: orientation differs from the published part"


@pytest.mark.parametrize("part", BLOCKS)
def test_cornell_block_sides_and_top_equal_published_obj(cornell, part):
    """The visible faces (all but the bottom at y = 0) equal the published ones."""
    ours = cornell.objects[cornell.object_id(part)].mesh
    ref = _published_part(part)

    def bottom(tri):
        return np.all(tri[:, :, 1] == 0.0, axis=1)

    np.testing.assert_allclose(_triangle_set(ours, bottom), _triangle_set(ref, bottom), atol=1e-9)
    assert not bottom(np.asarray(ours.vertices)[np.asarray(ours.faces)]).any()


def test_cornell_materials_equal_published_rgb(cornell):
    pub = json.loads(shared_file("meshes", "cornell", "materials.json").read_text())
    for part, mat in pub["parts"].items():
        if part == "light":
            continue
        assert cornell.objects[cornell.object_id(part)].material == mat
        ours = cornell.materials[mat]["albedo"]
        want = pub["materials"][mat]["linear_srgb_reflectance"]
        # the built-in values are the published ones at 3 decimals
        assert np.abs(np.subtract(ours, want)).max() <= 0.5e-3 + 1e-9, (mat, ours, want)
        assert cornell.materials[mat]["type"] == "lambert"
    light = cornell.area_lights[cornell.object_id("light")]
    want = pub["light"]["linear_srgb_radiance"]
    np.testing.assert_allclose(light.radiance.double().numpy(), CORNELL_RGB["light"], rtol=1e-6)
    assert np.abs(np.subtract(CORNELL_RGB["light"], want)).max() <= 0.5e-2 + 1e-9  # at 2 decimals


def test_cornell_meshes_are_fresh_copies():
    a, b = cornell_box_meshes(), cornell_box_meshes()
    a["floor"].apply_translation([0.0, 10.0, 0.0])
    assert b["floor"].bounds[0, 1] == 0.0


def test_grid_plane_faces_up_and_tessellates():
    from torch_brdf.errors import ValueRangeError
    from torch_brdf.scene.builtin import grid_plane

    m = grid_plane(2.0, 4, y=0.5)
    assert len(m.vertices) == 25 and len(m.faces) == 32
    np.testing.assert_allclose(m.face_normals, np.tile([0.0, 1.0, 0.0], (32, 1)), atol=1e-12)
    assert m.area == pytest.approx(4.0)
    np.testing.assert_allclose(m.vertices[:, 1], 0.5)
    with pytest.raises(ValueRangeError):
        grid_plane(2.0, 0)


def test_changing_geometry_after_construction_is_refused():
    """The tracer is built with the scene: swapping an object's mesh afterwards would trace
    the old geometry, so ray queries refuse; materials may still change."""
    from torch_brdf.errors import SceneError
    from torch_brdf.scene.builtin import bunny_plane, grid_plane
    from torch_brdf.scene.scene import SceneObject

    sc = bunny_plane(8, use_data=False)
    o, d = torch.zeros(1, 3) + torch.tensor([0.0, 3.0, 0.0]), torch.tensor([[0.0, -1.0, 0.0]])
    sc.materials["plane"] = {"type": "lambert", "albedo": 0.2}
    assert bool(sc.trace(o, d).hit.all())
    sc.objects[1] = SceneObject("plane", grid_plane(4.0, 2), "plane")
    with pytest.raises(SceneError, match="changed after construction"):
        sc.trace(o, d)
    with pytest.raises(SceneError):
        sc.occluded(o, d, float("inf"))
