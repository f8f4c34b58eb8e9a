"""The foundation's path tracer against analytic values: furnace, closed box, delta light."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from torch_brdf.errors import ValueRangeError
from torch_brdf.scene import AreaLight, Camera, DirectionalLight, EnvironmentMap, Scene, SceneObject, mesh_from_arrays
from torch_brdf.transport import pathtrace
from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace


def _sphere_in_env(albedo: float, size: int = 32) -> Scene:
    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    objects = [SceneObject("ball", mesh_from_arrays(s.vertices, s.faces), "m", smooth=True)]
    cam = Camera((0.0, 0.0, -4.0), (0.0, 0.0, 0.0), fov_deg=40.0, width=size, height=size)
    return Scene(objects, {"m": {"type": "lambert", "albedo": albedo}}, [EnvironmentMap.constant(1.0, height=16)], cam)


@pytest.mark.parametrize("albedo", [0.0, 0.5, 1.0])
def test_white_furnace(albedo):
    """A convex Lambert object in a constant environment L = 1 has radiance albedo * L."""
    scene = _sphere_in_env(albedo, size=64)
    img = path_trace(scene, PathTraceSettings(spp=64, max_bounces=3), seed=1, progress=False)
    o, d = scene.camera.generate_rays()
    on = scene.trace(o, d).hit.reshape(img.shape[:2]).float()[None]
    # pixels whose whole 3x3 neighbourhood is on (off) the ball: jittered rays cannot leave it
    inside = -torch.nn.functional.max_pool2d(-on, 3, 1, 1)[0] == 1
    outside = torch.nn.functional.max_pool2d(on, 3, 1, 1)[0] == 0
    assert int(inside.sum()) > 100 and int(outside.sum()) > 100
    assert bool(torch.isfinite(img).all())
    assert torch.equal(img[outside], torch.ones_like(img[outside]))  # background: the map itself
    _assert_mean(img[inside], albedo)


def _assert_mean(pixels: torch.Tensor, expected: float):
    """The mean of independent pixel estimates is within 4 standard errors of ``expected``,
    and the test resolves a 2% bias: the standard error is below 0.5% of the value."""
    x = pixels.double().reshape(-1, 3).mean(-1)  # grey scenes: one value per pixel
    se = float(x.std() / math.sqrt(x.numel()))
    assert se <= 0.005 * max(expected, 1e-12) + 1e-12
    assert abs(float(x.mean()) - expected) <= 4 * se + 1e-12


def _closed_cube(albedo: float, emission: float, size: int = 16) -> Scene:
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    mesh = mesh_from_arrays(box.vertices, box.faces[:, ::-1])  # normals point inwards
    objects = [SceneObject("cube", mesh, "wall")]
    lights = [AreaLight(mesh.vertices, mesh.faces, emission, object_id=0)]
    cam = Camera((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), fov_deg=60.0, width=size, height=size)
    return Scene(objects, {"wall": {"type": "lambert", "albedo": albedo}}, lights, cam)


@pytest.mark.parametrize("bounces", [1, 2, 4])
def test_closed_emissive_box_geometric_series(bounces):
    """Inside a closed box whose walls all emit Le and reflect rho, the radiance after B
    bounces is Le * (1 + rho + ... + rho^B), whatever the geometry."""
    rho, le = 0.6, 2.0
    img = path_trace(
        _closed_cube(rho, le, size=32), PathTraceSettings(spp=96, max_bounces=bounces), seed=3, progress=False
    )
    _assert_mean(img, le * sum(rho**k for k in range(bounces + 1)))


def test_directional_light_on_plane_is_exact():
    """A delta light makes direct lighting noise-free: L = rho / pi * E * cos(theta)."""
    plane = mesh_from_arrays([(-5, 0, -5), (-5, 0, 5), (5, 0, 5), (5, 0, -5)], [[0, 1, 2], [0, 2, 3]])
    theta = math.radians(30.0)
    sun = DirectionalLight((math.sin(theta), math.cos(theta), 0.0), (2.0, 1.0, 0.5))
    cam = Camera((0.0, 2.0, -2.0), (0.0, 0.0, 0.0), width=16, height=16)
    scene = Scene([SceneObject("plane", plane, "m")], {"m": {"type": "lambert", "albedo": 0.5}}, [sun], cam)
    img = path_trace(scene, PathTraceSettings(spp=2, max_bounces=3), seed=0, progress=False)
    expected = 0.5 / math.pi * torch.tensor([2.0, 1.0, 0.5]) * math.cos(theta)
    hit = img.sum(-1) > 0
    assert bool(hit.all())
    torch.testing.assert_close(img.reshape(-1, 3), expected.expand(256, 3), rtol=1e-5, atol=0)


def test_interrupted_render_resumes_bit_exactly(tmp_path, monkeypatch):
    scene = _closed_cube(0.5, 1.0, size=8)
    full = path_trace(scene, PathTraceSettings(spp=6, max_bounces=2), seed=5, progress=False)
    ckpt = tmp_path / "render.ckpt.npz"
    real = pathtrace._radiance
    calls = {"n": 0}

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 5:  # during the 5th pass (one chunk per pass here)
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(pathtrace, "_radiance", flaky)
    with pytest.raises(KeyboardInterrupt):
        path_trace(
            scene, PathTraceSettings(spp=6, max_bounces=2), seed=5, progress=False, checkpoint=ckpt, checkpoint_every=2
        )
    monkeypatch.setattr(pathtrace, "_radiance", real)
    assert ckpt.exists()
    resumed = path_trace(
        scene, PathTraceSettings(spp=6, max_bounces=2), seed=5, progress=False, checkpoint=ckpt, checkpoint_every=2
    )
    assert torch.equal(resumed, full)


def test_seeded_and_validated():
    scene = _closed_cube(0.5, 1.0, size=8)
    a = path_trace(scene, PathTraceSettings(spp=2, max_bounces=2), seed=9, progress=False)
    b = path_trace(scene, PathTraceSettings(spp=2, max_bounces=2), seed=9, progress=False)
    c = path_trace(scene, PathTraceSettings(spp=2, max_bounces=2), seed=10, progress=False)
    assert torch.equal(a, b) and not torch.equal(a, c)
    with pytest.raises(ValueRangeError):
        path_trace(scene, PathTraceSettings(spp=0))


@pytest.mark.parametrize(
    "material",
    [
        {"type": "blinn_phong", "kd": 0.3, "ks": 0.5, "exponent": 20.0},
        {"type": "cook_torrance", "distribution": "ggx", "roughness": 0.5, "f0": 0.9, "kd": 0.1},
    ],
)
def test_glossy_furnace_equals_directional_albedo(material):
    """A convex object in a constant environment L = 1 has radiance equal to its
    directional albedo for the view direction (no interreflection): the path tracer's
    BRDF handling against the BRDF layer's own albedo (stratified importance sampling)."""
    from torch_brdf.brdf import create
    from torch_brdf.frame import Frame

    scene = _sphere_in_env(0.5, size=48)
    scene.materials["m"] = material
    img = path_trace(scene, PathTraceSettings(spp=48, max_bounces=2), seed=2, progress=False)
    o, d = scene.camera.generate_rays()
    hits = scene.trace(o, d)
    on = hits.hit.reshape(48, 48).float()[None]
    inside = (-torch.nn.functional.max_pool2d(-on, 3, 1, 1)[0] == 1).reshape(-1)
    wo = Frame.from_normal(hits.normal[inside]).to_local(-d[inside])
    with torch.no_grad():
        expected = create(material).albedo(wo.double(), n=96).float()  # (P, 3) at pixel centres
    diff = img.reshape(-1, 3)[inside] - expected  # per-pixel errors: noise plus in-pixel variation
    x = diff.double().mean(-1)
    se = float(x.std() / math.sqrt(x.numel()))
    mean_expected = float(expected.mean())
    assert se <= 0.01 * mean_expected
    assert abs(float(x.mean())) <= 4 * se + 0.005 * mean_expected


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"chunk": -1}, "chunk"),
        ({"chunk": 0}, "chunk"),
        ({"seed": -1}, "seed"),
        ({"checkpoint_every": 0}, "checkpoint_every"),
        ({"spp": 2.5}, "spp"),
        ({"max_bounces": True}, "max_bounces"),
        ({"seed": 2**64}, "seed"),
    ],
)
def test_counts_and_seeds_are_checked_before_rendering(kwargs, name):
    # unchecked, chunk=-1 would return a black image and the others raise raw errors mid-render
    scene = _closed_cube(0.5, 1.0, size=8)
    run = {k: v for k, v in kwargs.items() if k in ("seed", "checkpoint_every")}
    with pytest.raises(ValueRangeError, match=rf"^{name} must be"):
        fields = {"spp": 1, "max_bounces": 1, **{k: v for k, v in kwargs.items() if k not in run}}
        path_trace(scene, PathTraceSettings(**fields), progress=False, **run)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [({"group": -1}, "group"), ({"tile_rows": -1}, "tile_rows"), ({"seed": -1}, "seed"), ({"spp": 0}, "spp")],
)
def test_precompute_counts_are_checked(kwargs, name):
    from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial

    scene = _closed_cube(0.5, 1.0, size=8)
    with pytest.raises(ValueRangeError, match=rf"^{name} must be"):
        fields = {"spp": 1, **{k: v for k, v in kwargs.items() if k != "seed"}}
        precompute_polynomial(scene, PolynomialSettings("2,1", **fields), seed=kwargs.get("seed", 0), progress=False)
    with pytest.raises(ValueRangeError, match="at most 4096 bands"):
        precompute_polynomial(scene, PolynomialSettings("1000000000,1", spp=1), progress=False)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [({"resolution": 16.0}, "resolution"), ({"resolution": 2**20}, "resolution"), ({"chunk": 0}, "chunk")],
)
def test_visibility_sizes_are_checked(kwargs, name):
    from torch_brdf.transport.visibility import VisibilitySettings, precompute_visibility

    with pytest.raises(ValueRangeError, match=rf"^{name} must be"):
        precompute_visibility(_closed_cube(0.5, 1.0, size=8), VisibilitySettings(**kwargs), progress=False)
