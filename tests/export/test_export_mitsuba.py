"""Exports checked by Mitsuba 3 (reference tests): the exact mappings evaluate as our models,
and a scene written as Mitsuba XML with stock plugins renders like our path tracer (exact
mappings within noise; a fitted material within its stated error plus noise)."""

from __future__ import annotations

import json

import pytest
import torch
import trimesh

mi = pytest.importorskip("mitsuba")

from torch_brdf.brdf import create  # noqa: E402
from torch_brdf.export import FitPairs, export_scene_mitsuba  # noqa: E402
from torch_brdf.export import _mitsuba_error as mitsuba_error  # noqa: E402
from torch_brdf.scene import Camera, DirectionalLight, Scene, SceneObject, mesh_from_arrays  # noqa: E402
from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace  # noqa: E402

pytestmark = pytest.mark.reference

GOLD = {"type": "metallic_roughness", "base_color": [1.0, 0.78, 0.34], "metallic": 1.0, "roughness": 0.35}
FLOOR = {"type": "lambert", "albedo": [0.6, 0.6, 0.5]}
PLASTIC = {"type": "metallic_roughness", "base_color": [0.2, 0.4, 0.7], "metallic": 0.0, "roughness": 0.6}
CONDUCTOR = {"type": "cook_torrance", "distribution": "ggx", "roughness": 0.3, "f0": 1.0}
ROUGH_PLASTIC = {
    "type": "rough_plastic",
    "distribution": "ggx",
    "roughness": 0.3,
    "eta": 1.5,
    "diffuse_reflectance": 0.4,
}
BECKMANN_PLASTIC = {**ROUGH_PLASTIC, "distribution": "beckmann", "roughness": 0.1, "nonlinear": True}


@pytest.mark.parametrize(
    ("material", "model", "params"),
    [
        (CONDUCTOR, "roughconductor", {"alpha": 0.3}),
        (FLOOR, "diffuse", None),
        (ROUGH_PLASTIC, "roughplastic", {"alpha": 0.3}),
        (BECKMANN_PLASTIC, "roughplastic", {"alpha": 0.1}),
    ],
)
def test_exact_mappings_evaluate_as_ours_in_mitsuba(material, model, params):
    from torch_brdf.export import _exact_mitsuba

    brdf = create(material).double()
    fit = _exact_mitsuba(brdf)
    assert fit is not None and fit.model == model
    err = mitsuba_error(fit.model, fit.params, brdf, FitPairs.build(brdf, n=1024))
    assert err is not None and err < 1e-3, err


def _scene(floor: dict, ball_material: dict = GOLD, size: int = 24) -> Scene:
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.7)
    ball.apply_translation([0.0, 0.7, 0.0])
    plane = mesh_from_arrays([(-3, 0, -3), (-3, 0, 3), (3, 0, 3), (3, 0, -3)], [[0, 1, 2], [0, 2, 3]])
    objects = [
        SceneObject("ball", mesh_from_arrays(ball.vertices, ball.faces), "gold", smooth=True),
        SceneObject("floor", plane, "floor"),
    ]
    lights = [DirectionalLight((-0.5, 0.8, -0.3), (2.0, 1.9, 1.8))]
    cam = Camera((0.5, 2.0, -3.5), (0.0, 0.5, 0.0), fov_deg=40.0, width=size, height=size)
    return Scene(objects, {"gold": dict(ball_material), "floor": dict(floor)}, lights, cam)


def _compare(tmp_path, floor: dict, ball: dict = GOLD) -> tuple[float, float, list]:
    """(|mean ratio - 1|, its 4-sigma noise, the reports) of Mitsuba rendering the exported
    file against our path tracer on the scene (2 bounces, 4 seeds each)."""
    scene = _scene(floor, ball)
    out = tmp_path / "scene.xml"
    reports = export_scene_mitsuba(scene, out, spp=8, max_bounces=2)
    assert json.loads((tmp_path / "scene.xml.export.json").read_text())
    mi.set_variant("scalar_rgb")
    loaded = mi.load_file(str(out))
    K = 4
    ours = torch.stack(
        [path_trace(scene, PathTraceSettings(spp=8, max_bounces=2), seed=s, progress=False) for s in range(K)]
    ).double()
    theirs = torch.stack(
        [torch.from_numpy(mi.TensorXf(mi.render(loaded, seed=s, spp=8)).numpy()[..., :3]) for s in range(K)]
    ).double()
    mo, mm = ours.mean(dim=(1, 2, 3)), theirs.mean(dim=(1, 2, 3))
    ratio = float(mo.mean() / mm.mean())
    noise = 4 * float((mo.var() / K + mm.var() / K).sqrt() / mm.mean())
    return abs(ratio - 1), noise, reports


def test_exported_scene_renders_like_ours_exact(tmp_path):
    dev, noise, reports = _compare(tmp_path, FLOOR, CONDUCTOR)
    assert all(r.exact for r in reports), [(r.source, r.target) for r in reports]
    assert dev <= noise + 0.01, (dev, noise)


def test_exported_scene_with_a_fitted_material(tmp_path):
    dev, noise, reports = _compare(tmp_path, PLASTIC)
    assert [r.exact for r in reports] == [False, False]  # principled is never exact for glTF
    fitted = max(reports, key=lambda r: r.error)
    assert fitted.target in ("principled", "roughconductor", "diffuse") and 0 < fitted.error < 0.5
    # the image-mean deviation stays within the stated (cosine-weighted L2) error plus noise
    assert dev <= fitted.error + noise + 0.01, (dev, fitted.error, noise)
