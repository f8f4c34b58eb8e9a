"""The glTF metallic-roughness model against Mitsuba 3: the bridge's Python BSDF (written
from the formula, independently of the torch code) pointwise, our path tracer against
Mitsuba on a scene with a gold sphere and a plastic floor, and the residual of Mitsuba's
stock ``principled`` (Disney's model) at matching parameters."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

mi = pytest.importorskip("mitsuba")

from torch_brdf.brdf import create  # noqa: E402
from torch_brdf.scene import Camera, DirectionalLight, EnvironmentMap, Scene, SceneObject, mesh_from_arrays  # noqa: E402
from torch_brdf.transport import mitsuba as tbm  # noqa: E402
from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace  # noqa: E402

pytestmark = pytest.mark.reference

GOLD = {"type": "metallic_roughness", "base_color": (1.0, 0.78, 0.34), "metallic": 1.0, "roughness": 0.35}
PLASTIC = {"type": "metallic_roughness", "base_color": (0.2, 0.4, 0.7), "metallic": 0.0, "roughness": 0.5}


def cosine_pairs(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, 3) pairs, both directions cosine-distributed (the projection's cos cos measure)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(2, n, 2, generator=g, dtype=torch.float64)
    r, p = u[..., 0].sqrt(), 2 * math.pi * u[..., 1]
    w = torch.stack([r * p.cos(), r * p.sin(), (1 - u[..., 0]).sqrt()], -1)
    return w[0], w[1]


def mitsuba_f(bsdf, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """Mitsuba's f (without the cosine) at local pairs: (n, 3)."""
    ctx, si = mi.BSDFContext(), mi.SurfaceInteraction3f()
    out = []
    for a, b in zip(wo.tolist(), wi.tolist(), strict=True):
        si.wi = mi.Vector3f(*a)
        out.append(list(bsdf.eval(ctx, si, mi.Vector3f(*b))))
    return torch.tensor(out, dtype=torch.float64) / wi[:, 2:]


@pytest.mark.parametrize("material", [GOLD, PLASTIC, {**PLASTIC, "metallic": 0.5, "roughness": 0.05}])
def test_python_bsdf_matches_ours(material):
    tbm.set_variant("scalar_rgb")
    brdf = create(material).double()
    with torch.no_grad():
        c = brdf.base_color.tolist()
        m, r = float(brdf.metallic), float(brdf.roughness)
    bsdf = mi.load_dict(
        {"type": tbm.METALLIC_ROUGHNESS_PLUGIN, "base_color": mi.ScalarColor3f(*c), "metallic": m, "roughness": r}
    )
    wi, wo = cosine_pairs(400, 1)
    torch.testing.assert_close(mitsuba_f(bsdf, wi, wo), brdf.eval(wi, wo).detach(), rtol=2e-4, atol=1e-6)


def principled_residual(material: dict) -> float:
    """Cosine-weighted relative L2 difference between our model and Mitsuba's stock
    ``principled`` at the matching parameters (``specular`` 0.5 is f0 = 0.04; sheen,
    clearcoat, anisotropy, transmission 0), on the export's importance-sampled pairs (which
    reach the grazing mirror pairs where the two differ)."""
    from torch_brdf.export import FitPairs, _mitsuba_error
    from torch_brdf.export.fit import principled_params

    brdf = create(material).double()
    return _mitsuba_error("principled", principled_params(brdf), brdf, FitPairs.build(brdf))


def test_principled_residual():
    # principled is not glTF's model: its masking is the separable Smith G1 G1 (glTF's is
    # height-correlated: they differ at grazing pairs: a few percent for the metal) and its dielectric
    # diffuse is Disney's (retro-reflection, 1 - F/2 per direction), not Lambert x (1 - F)
    metal, plastic = principled_residual(GOLD), principled_residual(PLASTIC)
    print(f"principled residual: metal r=0.35 {metal:.4f}, dielectric r=0.5 {plastic:.4f}")
    assert 0.005 < metal < 0.1
    assert 0.02 < plastic < 0.3


def _scene(size: int = 24) -> Scene:
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.7)
    ball.apply_translation([0.0, 0.7, 0.0])
    plane = mesh_from_arrays([(-3, 0, -3), (-3, 0, 3), (3, 0, 3), (3, 0, -3)], [[0, 1, 2], [0, 2, 3]])
    objects = [
        SceneObject("ball", mesh_from_arrays(ball.vertices, ball.faces), "gold", smooth=True),
        SceneObject("floor", plane, "plastic"),
    ]
    sky = EnvironmentMap.sky(height=32, sun_direction=(0.6, 0.5, -0.4), sun_angular_radius_deg=6.0)
    lights = [sky, DirectionalLight((-0.5, 0.8, -0.3), (0.5, 0.4, 0.3))]
    cam = Camera((0.5, 2.0, -3.5), (0.0, 0.5, 0.0), fov_deg=40.0, width=size, height=size)
    return Scene(objects, {"gold": dict(GOLD), "plastic": dict(PLASTIC)}, lights, cam)


def test_path_tracer_agrees_with_mitsuba():
    """Two bounces, 4 seeds per renderer: 4 x 4 block means within 4 standard errors (with a
    1% floor for the env-map lookups, as in test_mitsuba.py) in >= 95% of the block-channels
    and the image means within 2%."""
    scene = _scene()
    variant = tbm.default_variant()
    K, spp = 4, 8
    ours = torch.stack(
        [path_trace(scene, PathTraceSettings(spp=spp, max_bounces=2), seed=s, progress=False) for s in range(K)]
    ).double()
    theirs = torch.stack([tbm.render_mitsuba(scene, spp, 2, seed=s, variant=variant) for s in range(K)]).double()
    bo = torch.nn.functional.avg_pool2d(ours.permute(0, 3, 1, 2), 4)
    bm = torch.nn.functional.avg_pool2d(theirs.permute(0, 3, 1, 2), 4)
    se = (bo.var(0) / K + bm.var(0) / K + (0.01 * bm.mean(0)) ** 2).sqrt().clamp_min(1e-12)
    t = (bo.mean(0) - bm.mean(0)) / se
    assert float((t.abs() <= 4).double().mean()) >= 0.95, t.abs().max()
    assert abs(float(ours.mean() / theirs.mean()) - 1) < 0.02
