"""Built-in scenes, each a function of the image resolution.

They need no data files: the Cornell box uses the published coordinates, the other
scenes use procedural stand-ins where the shared meshes (``TORCH_BRDF_DATA``) are absent.
Materials are dicts ``{"type": model, **parameters}`` of the BRDF layer
(:func:`torch_brdf.brdf.create`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh

from .._checks import check_image_size
from ..data import data_path
from ..errors import SceneError, ValueRangeError
from .camera import Camera
from .envmap import EnvironmentMap
from .lights import AreaLight, DirectionalLight
from .mesh import load_mesh, mesh_from_arrays
from .scene import Scene, SceneObject

Resolution = int | tuple[int, int]

# The Cornell box as published by the Cornell Program of Computer Graphics
# (millimetres, y up): each part is a list of quads, vertices in published order.
_CORNELL_QUADS: dict[str, list[list[tuple[float, float, float]]]] = {
    "floor": [[(552.8, 0, 0), (0, 0, 0), (0, 0, 559.2), (549.6, 0, 559.2)]],
    "ceiling": [[(556.0, 548.8, 0), (556.0, 548.8, 559.2), (0, 548.8, 559.2), (0, 548.8, 0)]],
    "back": [[(549.6, 0, 559.2), (0, 0, 559.2), (0, 548.8, 559.2), (556.0, 548.8, 559.2)]],
    "left": [[(552.8, 0, 0), (549.6, 0, 559.2), (556.0, 548.8, 559.2), (556.0, 548.8, 0)]],
    "right": [[(0, 0, 559.2), (0, 0, 0), (0, 548.8, 0), (0, 548.8, 559.2)]],
    "short_box": [
        [(130.0, 165.0, 65.0), (82.0, 165.0, 225.0), (240.0, 165.0, 272.0), (290.0, 165.0, 114.0)],
        [(290.0, 0.0, 114.0), (290.0, 165.0, 114.0), (240.0, 165.0, 272.0), (240.0, 0.0, 272.0)],
        [(130.0, 0.0, 65.0), (130.0, 165.0, 65.0), (290.0, 165.0, 114.0), (290.0, 0.0, 114.0)],
        [(82.0, 0.0, 225.0), (82.0, 165.0, 225.0), (130.0, 165.0, 65.0), (130.0, 0.0, 65.0)],
        [(240.0, 0.0, 272.0), (240.0, 165.0, 272.0), (82.0, 165.0, 225.0), (82.0, 0.0, 225.0)],
    ],
    "tall_box": [
        [(423.0, 330.0, 247.0), (265.0, 330.0, 296.0), (314.0, 330.0, 456.0), (472.0, 330.0, 406.0)],
        [(423.0, 0.0, 247.0), (423.0, 330.0, 247.0), (472.0, 330.0, 406.0), (472.0, 0.0, 406.0)],
        [(472.0, 0.0, 406.0), (472.0, 330.0, 406.0), (314.0, 330.0, 456.0), (314.0, 0.0, 456.0)],
        [(314.0, 0.0, 456.0), (314.0, 330.0, 456.0), (265.0, 330.0, 296.0), (265.0, 0.0, 296.0)],
        [(265.0, 0.0, 296.0), (265.0, 330.0, 296.0), (423.0, 330.0, 247.0), (423.0, 0.0, 247.0)],
    ],
    # The light is coplanar with the ceiling in the published data; like Mitsuba's
    # reference scene we lower it by 0.5 mm so it is not hidden by the ceiling.
    "light": [[(343.0, 548.3, 227.0), (343.0, 548.3, 332.0), (213.0, 548.3, 332.0), (213.0, 548.3, 227.0)]],
}

#: Linear-sRGB reflectances and light radiance derived from the published Cornell box
#: spectra (CIE 1931 2 deg, equal-energy illuminant, Bradford to D65), as in
#: shared/data/meshes/cornell/materials.json.
CORNELL_RGB = {
    "white": (0.738, 0.737, 0.735),
    "red": (0.529, 0.048, 0.051),
    "green": (0.051, 0.397, 0.086),
    "light": (17.98, 11.50, 3.15),
}


def _size(resolution: Resolution) -> tuple[int, int]:
    if isinstance(resolution, int):
        return resolution, resolution
    w, h = resolution
    return int(w), int(h)


def _oriented_quads(quads, facing: Callable[[np.ndarray, np.ndarray], bool], name: str) -> trimesh.Trimesh:
    """Triangulate quads (each split along v0-v2) and flip each so ``facing`` holds."""
    verts, faces = [], []
    for q in quads:
        q = np.asarray(q, dtype=np.float64)
        n = np.cross(q[1] - q[0], q[2] - q[0])
        order = [0, 1, 2, 3] if facing(q.mean(0), n) else [0, 3, 2, 1]
        base = len(verts)
        verts.extend(q[order])
        faces.extend([[base, base + 1, base + 2], [base, base + 2, base + 3]])
    return mesh_from_arrays(verts, faces, name)


def cornell_box_meshes() -> dict[str, trimesh.Trimesh]:
    """The eight Cornell box parts as meshes: walls face into the box, blocks outwards,
    the light downwards. Block faces do not share vertices (flat shading)."""
    inside = np.array([278.0, 274.4, 279.6])
    out = {}
    for name, quads in _CORNELL_QUADS.items():
        if name == "light":
            facing = lambda c, n: n[1] < 0  # noqa: E731
        elif name.endswith("_box"):
            centre = np.asarray(quads, dtype=np.float64).reshape(-1, 3).mean(0)
            centre[1] = np.asarray(quads, dtype=np.float64)[..., 1].max() / 2
            facing = lambda c, n, centre=centre: np.dot(n, c - centre) > 0  # noqa: E731
        else:
            facing = lambda c, n: np.dot(n, inside - c) > 0  # noqa: E731
        out[name] = _oriented_quads(quads, facing, name)
    return out


def cornell_box(resolution: Resolution = 256) -> Scene:
    """The Cornell box: 8 objects (walls, two blocks, light), Lambert materials from the
    published spectra, an area light, and the published camera (35 mm lens, 25 mm film:
    39.31 deg vertical fov). Like the published data the blocks have no bottom face.

    Args:
        resolution: image width = height, or (width, height).
    """
    w, h = _size(resolution)
    meshes = cornell_box_meshes()
    mat = {
        "floor": "white",
        "ceiling": "white",
        "back": "white",
        "left": "red",
        "right": "green",
        "short_box": "white",
        "tall_box": "white",
        "light": "light",
    }
    objects = [SceneObject(n, m, mat[n]) for n, m in meshes.items()]
    objects[-1].editable = False
    materials = {k: {"type": "lambert", "albedo": CORNELL_RGB[k]} for k in ("white", "red", "green")}
    materials["light"] = {"type": "lambert", "albedo": (0.0, 0.0, 0.0)}
    light_id = len(objects) - 1
    lights = [AreaLight(meshes["light"].vertices, meshes["light"].faces, CORNELL_RGB["light"], object_id=light_id)]
    # the published camera: focal length 35 mm, film 25 mm x 25 mm
    fov = math.degrees(2 * math.atan(12.5 / 35.0))
    cam = Camera((278.0, 273.0, -800.0), (278.0, 273.0, 0.0), (0.0, 1.0, 0.0), fov, w, h)
    return Scene(objects, materials, lights, cam, name="cornell_box")


def _ground(size: float, y: float = 0.0, name: str = "plane") -> trimesh.Trimesh:
    s = size / 2
    v = [(-s, y, -s), (-s, y, s), (s, y, s), (s, y, -s)]
    return mesh_from_arrays(v, [[0, 1, 2], [0, 2, 3]], name)


def grid_plane(size: float, quads: int, y: float = 0.0, name: str = "plane") -> trimesh.Trimesh:
    """A square ``size`` x ``size`` plane at height ``y`` facing +y, tessellated into
    ``quads`` x ``quads`` quads (two triangles each): receivers of per-vertex shadows need
    vertices where the shadows fall."""
    n = int(quads)
    if n < 1 or not size > 0:
        raise ValueRangeError(f"grid_plane: need size > 0 and quads >= 1; got {size}, {quads}")
    c = np.linspace(-size / 2, size / 2, n + 1)
    x, z = np.meshgrid(c, c, indexing="ij")
    v = np.stack((x.ravel(), np.full(x.size, y), z.ravel()), -1)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    i = i.ravel()
    f = np.concatenate((np.stack((i, i + 1, i + n + 2), -1), np.stack((i, i + n + 2, i + n + 1), -1)))
    return mesh_from_arrays(v, f, name)


def _default_sky() -> EnvironmentMap:
    """The procedural sky of the built-in scenes: sun irradiance about 1.3 (relative
    units), so a white Lambert surface in the sun has radiance of order 0.5."""
    return EnvironmentMap.sky(sun_radiance=(600.0, 570.0, 520.0))


def _teapot_stand_in() -> trimesh.Trimesh:
    """A procedural teapot-like body of revolution with a spout (when no data is present):
    base at y = 0, about 2 units wide and 1 tall like the Utah teapot of the shared data."""
    t = np.linspace(0, np.pi, 33)
    profile = np.stack((0.7 * np.sin(t) + 0.01, 0.45 * (1 - np.cos(t))), -1)
    profile[0, 0] = profile[-1, 0] = 0.0
    body = trimesh.creation.revolve(profile, sections=48)
    # revolve spins about z; make y the axis
    body.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    spout = trimesh.creation.cylinder(radius=0.09, height=0.6, sections=16)
    spout.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 4, [0, 0, 1]))
    spout.apply_translation([-0.8, 0.55, 0.0])
    m = trimesh.util.concatenate([body, spout])
    return mesh_from_arrays(m.vertices, m.faces, "teapot")


def teatray(resolution: Resolution = 256, envmap: EnvironmentMap | None = None) -> Scene:
    """A teapot on a glossy tray under an environment map (the seed's teatray).

    The teapot comes from the shared data (``meshes/teapot.obj``) when present, else a
    procedural stand-in. The environment defaults to the procedural sky with a sun.
    """
    w, h = _size(resolution)
    p = data_path("meshes", "teapot.obj", required=False)
    teapot = load_mesh(p, "teapot") if p is not None else _teapot_stand_in()
    lo, hi = teapot.bounds
    teapot.apply_translation([-(lo[0] + hi[0]) / 2, 0.02 - lo[1], -(lo[2] + hi[2]) / 2])
    tray = trimesh.creation.box(extents=(3.2, 0.04, 2.4))
    tray.apply_translation([0, 0.0, 0])
    objects = [
        SceneObject("teapot", teapot, "teapot", smooth=True),
        SceneObject("tray", mesh_from_arrays(tray.vertices, tray.faces, "tray"), "tray"),
        SceneObject("floor", _ground(40.0, -0.02, "floor"), "floor", editable=False),
    ]
    materials = {
        "teapot": {"type": "lambert", "albedo": (0.6, 0.45, 0.3)},
        "tray": {"type": "blinn_phong", "kd": (0.15, 0.15, 0.17), "ks": (0.6, 0.6, 0.6), "exponent": 200.0},
        "floor": {"type": "lambert", "albedo": (0.4, 0.4, 0.4)},
    }
    env = envmap if envmap is not None else _default_sky()
    cam = Camera((0.0, 2.0, -4.0), (0.0, 0.35, 0.0), (0.0, 1.0, 0.0), 35.0, w, h)
    return Scene(objects, materials, [env], cam, name="teatray")


def ring(resolution: Resolution = 256) -> Scene:
    """A metal torus ring lying on a diffuse plane under a low sun: the caustic case."""
    w, h = _size(resolution)
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.12, major_sections=96, minor_sections=24)
    torus.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    torus.apply_translation([0, 0.12, 0])
    objects = [
        SceneObject("ring", mesh_from_arrays(torus.vertices, torus.faces, "ring"), "metal", smooth=True),
        SceneObject("plane", _ground(20.0, 0.0), "plane"),
    ]
    materials = {
        "metal": {
            "type": "blinn_phong",
            "kd": (0.02, 0.02, 0.02),
            "ks": (0.95, 0.8, 0.45),
            "exponent": 2000.0,
        },
        "plane": {"type": "lambert", "albedo": (0.7, 0.7, 0.7)},
    }
    sun = (-math.cos(math.radians(25)), math.sin(math.radians(25)), 0.3)
    lights = [DirectionalLight(sun, 3.0), EnvironmentMap.constant(0.05)]
    cam = Camera((0.0, 3.2, -3.2), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 40.0, w, h)
    return Scene(objects, materials, lights, cam, name="ring")


def bunny_plane(resolution: Resolution = 256, envmap: EnvironmentMap | None = None, use_data: bool = True) -> Scene:
    """The Stanford bunny (shared data; an icosphere stand-in otherwise or with
    ``use_data=False``) on a plane under an environment map (procedural sky by default)."""
    w, h = _size(resolution)
    p = data_path("meshes", "bunny.ply", required=False) if use_data else None
    if p is not None:
        bunny = load_mesh(p, "bunny")
        bunny.apply_scale(10.0)
    else:
        bunny = trimesh.creation.icosphere(subdivisions=4, radius=0.8)
        bunny.apply_scale([1.0, 0.9, 1.2])
        bunny = mesh_from_arrays(bunny.vertices, bunny.faces, "bunny")
    lo, hi = bunny.bounds
    bunny.apply_translation([-(lo[0] + hi[0]) / 2, -lo[1], -(lo[2] + hi[2]) / 2])
    objects = [
        SceneObject("bunny", bunny, "bunny", smooth=True),
        SceneObject("plane", _ground(30.0, 0.0), "plane"),
    ]
    materials = {
        "bunny": {"type": "lambert", "albedo": (0.7, 0.7, 0.7)},
        "plane": {"type": "lambert", "albedo": (0.5, 0.5, 0.5)},
    }
    env = envmap if envmap is not None else _default_sky()
    cam = Camera((0.0, 2.2, -4.5), (0.0, 0.7, 0.0), (0.0, 1.0, 0.0), 40.0, w, h)
    return Scene(objects, materials, [env], cam, name="bunny_plane")


def mesh_scene(path, resolution: Resolution = 256, envmap: EnvironmentMap | None = None) -> Scene:
    """Any mesh file (OBJ, PLY, ...) on a grey plane under an environment map (default: the
    procedural sky), framed by the camera: ``torch-brdf render --mesh FILE [--envmap FILE]``.

    The mesh is scaled to 1.6 units of height (its aspect kept), stood on the plane (y = 0) and
    centred; the camera looks at it from the front (-z), a little from the side and above, its
    bounding sphere filling ~90% of the vertical field of view.
    """
    w, h = _size(resolution)
    mesh = load_mesh(path, Path(path).stem)
    lo, hi = mesh.bounds
    mesh.apply_scale(1.6 / max(float(hi[1] - lo[1]), 1e-12))
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -lo[1], -(lo[2] + hi[2]) / 2])
    lo, hi = mesh.bounds
    centre = (lo + hi) / 2
    radius = float(np.linalg.norm(hi - lo)) / 2
    fov = 35.0
    dist = 1.1 * radius / math.tan(math.radians(fov / 2))
    eye = centre + dist * np.array([0.3, 0.25, -1.0]) / np.linalg.norm([0.3, 0.25, -1.0])
    objects = [
        SceneObject("mesh", mesh, "mesh", smooth=True),
        SceneObject("plane", _ground(30.0 * max(radius, 1.0), 0.0), "plane"),
    ]
    materials = {
        "mesh": {"type": "lambert", "albedo": (0.7, 0.7, 0.7)},
        "plane": {"type": "lambert", "albedo": (0.5, 0.5, 0.5)},
    }
    env = envmap if envmap is not None else _default_sky()
    cam = Camera(tuple(float(v) for v in eye), tuple(float(v) for v in centre), (0.0, 1.0, 0.0), fov, w, h)
    return Scene(objects, materials, [env], cam, name=f"mesh:{Path(path).name}")


def bunny_relight(
    resolution: Resolution = 256,
    plane_quads: int = 96,
    exponent: float = 200.0,
    envmap: EnvironmentMap | None = None,
    use_data: bool = True,
) -> Scene:
    """The relighting test of Inger et al.: a glossy Phong bunny (exponent ``exponent``) on
    a tessellated, mildly glossy plane (Phong exponent 20) under a sun-like sky.

    Per-vertex shading needs vertices where shadows fall, so the plane is a 6 x 6 grid of
    ``plane_quads`` x ``plane_quads`` quads. The bunny comes from the shared data when
    present (35,947 vertices) and ``use_data``, else a procedural stand-in (2,562 vertices).
    """
    base = bunny_plane(resolution, envmap, use_data)  # the bunny, sky and camera
    objects = [base.objects[0], SceneObject("plane", grid_plane(6.0, plane_quads), "plane")]
    materials = {
        "bunny": {"type": "phong", "kd": (0.35, 0.3, 0.25), "ks": 0.5, "exponent": float(exponent)},
        "plane": {"type": "phong", "kd": 0.45, "ks": 0.15, "exponent": 20.0},
    }
    return Scene(objects, materials, base.lights, base.camera, name="bunny_relight")


#: name -> builder, for the CLI and tests.
def cornell_box_glossy(resolution: Resolution = 128, exponent: float = 100.0) -> Scene:
    """The Cornell box of Ben-Artzi et al. 2008, Fig. 6(b): a glossy Blinn-Phong back wall
    (``kd`` 0.25, ``ks`` 0.6, exponent ``exponent``) and coloured blocks (a yellow short
    block, a blue tall block); everything else as :func:`cornell_box`."""
    sc = cornell_box(resolution)
    sc.materials["glossy_back"] = {"type": "blinn_phong", "kd": 0.25, "ks": 0.6, "exponent": float(exponent)}
    sc.materials["yellow"] = {"type": "lambert", "albedo": (0.75, 0.62, 0.08)}
    sc.materials["blue"] = {"type": "lambert", "albedo": (0.10, 0.22, 0.65)}
    for name, mat in (("back", "glossy_back"), ("short_box", "yellow"), ("tall_box", "blue")):
        sc.objects[sc.object_id(name)].material = mat
    sc.name = "cornell_box_glossy"
    return sc


BUILTIN_SCENES: dict[str, Callable[..., Scene]] = {
    "cornell_box": cornell_box,
    "cornell_box_glossy": cornell_box_glossy,
    "teatray": teatray,
    "ring": ring,
    "bunny_plane": bunny_plane,
    "bunny_relight": bunny_relight,
}


def load_scene(
    spec: str | Path,
    resolution: int | None = None,
    default_resolution: int = 256,
    *,
    allow_outside: bool = False,
    substitute: bool = False,
) -> Scene:
    """A built-in scene by name (:data:`BUILTIN_SCENES`) or a scene file: ``.toml``,
    ``.gltf``/``.glb`` (glTF 2.0), ``.xml`` (Mitsuba 3) or ``.obj`` (with its ``.mtl``); see
    :mod:`torch_brdf.scene.formats`.

    Args:
        spec: scene name or path of a scene file.
        resolution: square image size overriding the scene's (None: a built-in scene gets
            ``default_resolution``, a file keeps its own camera).
        allow_outside: follow file references (meshes, textures, maps) that leave the scene
            file's folder; refused by default.
        substitute: replace unsupported plugins and features by stated substitutes, with a
            :class:`~torch_brdf.scene.formats.SubstitutionWarning`, instead of raising.
    Raises:
        SceneError: neither a built-in name nor a scene file of an accepted type, or a problem in
            the file (naming the file, the element and the problem); ValueRangeError: bad size.
    """
    from .formats import SCENE_SUFFIXES, ImportOptions, accepted_formats, read_scene_file

    if resolution is not None:
        check_image_size(resolution, resolution, "resolution")
    if isinstance(spec, str) and spec in BUILTIN_SCENES:
        return BUILTIN_SCENES[spec](resolution or default_resolution)
    path = Path(spec)
    if path.suffix.lower() in SCENE_SUFFIXES or path.is_file():
        return read_scene_file(path, ImportOptions(allow_outside, substitute, resolution))
    raise SceneError(
        f"unknown scene {str(spec)!r}: give a scene file ({accepted_formats()}) or one of {sorted(BUILTIN_SCENES)}"
    )
