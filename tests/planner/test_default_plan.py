"""Planning by default: ``precompute_planned(scene)`` with nothing said plans for
``DEFAULT_ERROR`` within ``DEFAULT_SECONDS``, and on a glossy-to-glossy scene (a glossy floor
reflecting a glossy ball, under a sky) its object means match the path tracer's."""

from __future__ import annotations

import pytest
import torch
import trimesh
from typer.testing import CliRunner

from torch_brdf.cli import app
from torch_brdf.planner.gi import DEFAULT_ERROR, DEFAULT_SECONDS, precompute_planned
from torch_brdf.records.polynomial import PolynomialTensors
from torch_brdf.render.polynomial import PolynomialRenderer
from torch_brdf.scene import Camera, EnvironmentMap, Scene, SceneObject, mesh_from_arrays
from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace

PT_RUNS, PT_SPP, PT_BOUNCES = 2, 64, 6


def glossy_floor_scene(size: int = 12) -> Scene:
    """A glossy floor, a glossy ball seen in it and a diffuse box, lit by a sky with a sun."""
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
    ball.apply_translation([0.0, 0.6, 0.0])
    box = trimesh.creation.box((0.6, 0.6, 0.6))
    box.apply_translation([-1.0, 0.3, 0.6])
    floor = mesh_from_arrays([(-4, 0, -4), (-4, 0, 4), (4, 0, 4), (4, 0, -4)], [[0, 1, 2], [0, 2, 3]])
    objects = [
        SceneObject("floor", floor, "floor"),
        SceneObject("ball", mesh_from_arrays(ball.vertices, ball.faces), "ball", smooth=True),
        SceneObject("box", mesh_from_arrays(box.vertices, box.faces), "box"),
    ]
    materials = {
        "floor": {"type": "blinn_phong", "kd": 0.15, "ks": 0.5, "exponent": 150.0},
        "ball": {"type": "blinn_phong", "kd": 0.3, "ks": 0.5, "exponent": 80.0},
        "box": {"type": "lambert", "albedo": 0.6},
    }
    sky = EnvironmentMap.sky(height=32, sun_angular_radius_deg=5.0, sun_radiance=60.0)
    cam = Camera((0.0, 1.2, -3.2), (0.0, 0.4, 0.0), fov_deg=45.0, width=size, height=size)
    return Scene(objects, materials, [sky], cam, name="glossy_floor")


@pytest.fixture(scope="module")
def default_run():
    sc = glossy_floor_scene()
    T = precompute_planned(sc, seed=1, progress=False)
    mats = {o.name: sc.materials[o.material] for o in sc.objects}
    img = PolynomialRenderer(T, mats, dtype=torch.float64)().double()
    pt = PathTraceSettings(spp=PT_SPP, max_bounces=PT_BOUNCES)
    refs = torch.stack([path_trace(sc, pt, seed=s, progress=False) for s in range(PT_RUNS)]).double()
    o, d = sc.camera.generate_rays(dtype=torch.float64)
    ids = sc.trace(o.float(), d.float()).object_id.reshape(sc.camera.height, sc.camera.width)
    return sc, T, img, refs, ids


def test_default_plan_is_the_default_budget_and_is_saved(default_run, tmp_path):
    _, T, _, _, _ = default_run
    s = T.meta["plan_summary"]
    assert s["error"] == DEFAULT_ERROR and s["seconds"] == DEFAULT_SECONDS
    assert T.series.key == s["series"] and "predicted error" in T.meta["plan"]
    assert T.series.two_level  # the glossy floor lights the ball: a banded second bounce
    assert T.series.bounces <= s["needed_bounces"]  # never more bounces than the light needs
    T.save(tmp_path / "t.npz")
    assert PolynomialTensors.load(tmp_path / "t.npz").meta["plan_summary"] == s


def test_default_precompute_matches_the_path_tracer_on_glossy_objects(default_run):
    """Object means of the glossy floor and ball within 4 standard errors of the path tracer's
    (its runs' spread, the precompute's predicted noise over the region) plus 1%. The old
    default series (64,1,1,1: the glossy floor replaced by its diffuse equivalent at the second
    vertex) was 19-48% too bright on a glossy object of such a scene."""
    sc, T, img, refs, ids = default_run
    noise = T.meta["plan_summary"]["noise_error"]
    for name in ("floor", "ball"):
        m = ids == sc.object_id(name)
        ours, theirs = img[m].mean(), refs[:, m].mean((1, 2))
        ref = theirs.mean()
        se_pt = theirs.std() / PT_RUNS**0.5 if PT_RUNS > 1 else 0.0
        se_ours = noise * img[m].norm() / m.sum() ** 0.5 / m.sum() ** 0.5
        bound = 4 * float((se_pt**2 + se_ours**2) ** 0.5) + 0.01 * float(ref)
        assert abs(float(ours - ref)) <= bound, (name, float(ours), float(ref), bound)


def test_cli_plans_by_default_and_series_opts_out(tmp_path):
    out = tmp_path / "t.npz"
    res = CliRunner().invoke(
        app, ["precompute", "cornell_box_glossy", "--resolution", "8", "--seconds", "60", "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    T = PolynomialTensors.load(out)
    s = T.meta["plan_summary"]
    assert s["seconds"] == 60 and s["error"] == DEFAULT_ERROR and "GI plan for" in res.output
    both = CliRunner().invoke(app, ["precompute", "cornell_box_glossy", "--series", "4,1", "--error", "0.1"])
    assert both.exit_code != 0 and "one or the other" in both.output
