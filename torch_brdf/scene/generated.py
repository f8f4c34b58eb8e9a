"""Seeded generated scenes for validating defaults on scenes no planner or default was tuned on.

Each builder takes an image size and a seed: the seed draws positions, sizes, colours and
glossiness (``numpy.random.default_rng(seed)``), so a scene is a pure function of its
arguments, small enough to path-trace at 24-96 pixels, and named ``KIND-SEED``. The kinds
cover the transport that fixed defaults get wrong: glossy floors reflecting diffuse and
glossy objects, glossy objects seen in glossy objects under an area light, a textured floor,
and environment lighting with and without a sun.

:func:`validation_scenes` lists the set the planner benchmark validates on; other
benchmarks (denoising, ...) may use the same builders.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
import trimesh

from ..errors import ValueRangeError
from .camera import Camera
from .envmap import EnvironmentMap
from .lights import AreaLight
from .mesh import mesh_from_arrays
from .scene import Scene, SceneObject
from .textures import Texture

__all__ = [
    "GENERATED_SCENES",
    "env_lit",
    "glossy_floor_diffuse",
    "glossy_floor_glossy",
    "glossy_in_glossy",
    "textured_floor",
    "validation_scenes",
]


def _floor(half: float = 4.0) -> trimesh.Trimesh:
    return mesh_from_arrays(
        [(-half, 0, -half), (-half, 0, half), (half, 0, half), (half, 0, -half)], [[0, 1, 2], [0, 2, 3]]
    )


def _ball(rng: np.random.Generator, x: float, z: float, r: float) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=2, radius=r)
    m.apply_translation([x, r, z])
    return mesh_from_arrays(m.vertices, m.faces)


def _box(x: float, z: float, s: float, angle: float) -> trimesh.Trimesh:
    m = trimesh.creation.box((s, s, s))
    m.apply_transform(trimesh.transformations.rotation_matrix(angle, [0, 1, 0]))
    m.apply_translation([x, s / 2, z])
    return mesh_from_arrays(m.vertices, m.faces)


def _colour(rng: np.random.Generator, lo: float = 0.2, hi: float = 0.75) -> tuple[float, float, float]:
    return tuple(float(v) for v in rng.uniform(lo, hi, 3))


def _glossy(rng: np.random.Generator, lo: float = 40.0, hi: float = 200.0) -> dict:
    return {
        "type": "blinn_phong",
        "kd": round(float(rng.uniform(0.1, 0.3)), 3),
        "ks": round(float(rng.uniform(0.35, 0.6)), 3),
        "exponent": round(float(np.exp(rng.uniform(np.log(lo), np.log(hi)))), 1),
    }


def _sky(rng: np.random.Generator, sun: bool = True) -> EnvironmentMap:
    az, el = rng.uniform(0, 2 * np.pi), rng.uniform(0.5, 1.0)
    d = (float(np.cos(el) * np.cos(az)), float(np.sin(el)), float(np.cos(el) * np.sin(az)))
    if sun:
        return EnvironmentMap.sky(height=32, sun_direction=d, sun_angular_radius_deg=5.0, sun_radiance=60.0)
    return EnvironmentMap.sky(height=32, sun_direction=d, sun_angular_radius_deg=5.0, sun_radiance=0.0)


def _camera(size: int, rng: np.random.Generator) -> Camera:
    a = rng.uniform(-0.3, 0.3)
    eye = (3.2 * float(np.sin(a)), 1.2, -3.2 * float(np.cos(a)))
    return Camera(eye, (0.0, 0.4, 0.0), fov_deg=45.0, width=size, height=size)


def _check(size: int) -> int:
    if not isinstance(size, int) or size < 4:
        raise ValueRangeError(f"size must be an integer >= 4; got {size!r}")
    return size


def glossy_floor_diffuse(size: int = 48, seed: int = 0) -> Scene:
    """A glossy floor reflecting two diffuse objects (a ball and a box), under a sky with a sun."""
    rng = np.random.default_rng(seed)
    objects = [
        SceneObject("floor", _floor(), "floor"),
        SceneObject(
            "ball",
            _ball(rng, rng.uniform(-0.6, 0.2), rng.uniform(-0.3, 0.5), rng.uniform(0.4, 0.7)),
            "ball",
            smooth=True,
        ),
        SceneObject(
            "box", _box(rng.uniform(0.6, 1.2), rng.uniform(0.0, 0.8), rng.uniform(0.4, 0.7), rng.uniform(0, 1.5)), "box"
        ),
    ]
    materials = {
        "floor": _glossy(rng),
        "ball": {"type": "lambert", "albedo": _colour(rng)},
        "box": {"type": "lambert", "albedo": _colour(rng)},
    }
    return Scene(objects, materials, [_sky(rng)], _camera(_check(size), rng), name=f"glossy_floor_diffuse-{seed}")


def _ball_and_box(rng: np.random.Generator, box_x: tuple[float, float]) -> list[SceneObject]:
    """A smooth ball near the middle of the floor and a box whose x is drawn from ``box_x``
    (drawn in that order from ``rng``)."""
    ball = _ball(rng, rng.uniform(-0.4, 0.3), rng.uniform(-0.2, 0.4), rng.uniform(0.45, 0.7))
    box = _box(rng.uniform(*box_x), rng.uniform(0.2, 0.9), rng.uniform(0.4, 0.7), rng.uniform(0, 1.5))
    return [SceneObject("ball", ball, "ball", smooth=True), SceneObject("box", box, "box")]


def glossy_floor_glossy(size: int = 48, seed: int = 0) -> Scene:
    """A glossy floor reflecting a glossy ball and a diffuse box, under a sky with a sun
    (glossy-to-glossy transport: the ball is seen in the floor, the floor in the ball)."""
    rng = np.random.default_rng(seed)
    objects = [
        SceneObject("floor", _floor(), "floor"),
        *_ball_and_box(rng, (-1.3, -0.8)),
    ]
    materials = {
        "floor": _glossy(rng, 60.0, 200.0),
        "ball": _glossy(rng, 30.0, 120.0),
        "box": {"type": "lambert", "albedo": _colour(rng)},
    }
    return Scene(objects, materials, [_sky(rng)], _camera(_check(size), rng), name=f"glossy_floor_glossy-{seed}")


def glossy_in_glossy(size: int = 48, seed: int = 0) -> Scene:
    """Two glossy balls seen in each other on a diffuse floor, lit by a square area light
    above them (glossy objects reflected in glossy objects, a small light)."""
    rng = np.random.default_rng(seed)
    r1, r2 = rng.uniform(0.4, 0.6), rng.uniform(0.4, 0.6)
    gap = rng.uniform(0.15, 0.4)
    h, s = float(rng.uniform(2.5, 3.2)), float(rng.uniform(0.5, 0.8))
    lamp = mesh_from_arrays([(-s, h, -s), (s, h, -s), (s, h, s), (-s, h, s)], [[0, 1, 2], [0, 2, 3]])
    objects = [
        SceneObject("floor", _floor(), "floor"),
        SceneObject("left", _ball(rng, -(r1 + gap / 2), 0.0, r1), "left", smooth=True),
        SceneObject("right", _ball(rng, r2 + gap / 2, 0.0, r2), "right", smooth=True),
        SceneObject("lamp", lamp, "lamp", editable=False),
    ]
    materials = {
        "floor": {"type": "lambert", "albedo": _colour(rng, 0.3, 0.6)},
        "left": _glossy(rng, 40.0, 150.0),
        "right": _glossy(rng, 40.0, 150.0),
        "lamp": {"type": "lambert", "albedo": (0.0, 0.0, 0.0)},
    }
    light = AreaLight(lamp.vertices, lamp.faces, float(rng.uniform(8.0, 14.0)), object_id=3)
    return Scene(objects, materials, [light], _camera(_check(size), rng), name=f"glossy_in_glossy-{seed}")


def _checker(rng: np.random.Generator, n: int = 8) -> Texture:
    a, b = np.array(_colour(rng, 0.5, 1.0)), np.array(_colour(rng, 0.1, 0.4))
    ij = np.add.outer(np.arange(n), np.arange(n)) % 2
    img = np.where(ij[..., None] == 0, a, b).astype(np.float32)
    return Texture(torch.from_numpy(img), name="checker")


def textured_floor(size: int = 48, seed: int = 0) -> Scene:
    """A checker-textured diffuse floor reflected in a glossy ball, and a diffuse box, under a
    sky with a sun (the texture scales the floor's albedo)."""
    rng = np.random.default_rng(seed)
    floor = _floor()
    uv = (np.asarray(floor.vertices)[:, [0, 2]] + 4.0) / 8.0
    objects = [
        SceneObject("floor", floor, "floor", uv=uv, textures={"base_color": _checker(rng)}),
        *_ball_and_box(rng, (0.8, 1.3)),
    ]
    materials = {
        "floor": {"type": "lambert", "albedo": 1.0},
        "ball": _glossy(rng, 30.0, 150.0),
        "box": {"type": "lambert", "albedo": _colour(rng)},
    }
    return Scene(objects, materials, [_sky(rng)], _camera(_check(size), rng), name=f"textured_floor-{seed}")


def env_lit(size: int = 48, seed: int = 0) -> Scene:
    """A glossy floor and a glossy ball under a sky without a sun (smooth environment light
    only), and a diffuse box."""
    rng = np.random.default_rng(seed)
    objects = [
        SceneObject("floor", _floor(), "floor"),
        *_ball_and_box(rng, (-1.3, -0.8)),
    ]
    materials = {
        "floor": _glossy(rng, 40.0, 150.0),
        "ball": _glossy(rng, 20.0, 100.0),
        "box": {"type": "lambert", "albedo": _colour(rng)},
    }
    return Scene(objects, materials, [_sky(rng, sun=False)], _camera(_check(size), rng), name=f"env_lit-{seed}")


#: kind -> builder(size, seed)
GENERATED_SCENES: dict[str, Callable[..., Scene]] = {
    "glossy_floor_diffuse": glossy_floor_diffuse,
    "glossy_floor_glossy": glossy_floor_glossy,
    "glossy_in_glossy": glossy_in_glossy,
    "textured_floor": textured_floor,
    "env_lit": env_lit,
}

#: the planner's validation set: (kind, seed); seeds from 100 up, away from any a test uses
VALIDATION_SET: tuple[tuple[str, int], ...] = (
    ("glossy_floor_diffuse", 101),
    ("glossy_floor_glossy", 102),
    ("glossy_floor_glossy", 103),
    ("glossy_in_glossy", 104),
    ("textured_floor", 105),
    ("env_lit", 106),
)


def validation_scenes(size: int = 48, subset: tuple[tuple[str, int], ...] | None = None) -> list[Scene]:
    """The validation scenes (``VALIDATION_SET`` or ``subset`` of (kind, seed)) at ``size``\\ ²."""
    return [GENERATED_SCENES[k](size, seed) for k, seed in (VALIDATION_SET if subset is None else subset)]
