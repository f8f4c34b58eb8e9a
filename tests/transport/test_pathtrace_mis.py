"""Multiple importance sampling in the reference path tracer: the weights, unbiasedness
against plain next-event estimation (block t-tests over seeds), less noise where MIS
should help, and agreement with Mitsuba 3 on a glossy object under sun and sky."""

from __future__ import annotations

import pytest
import torch
import trimesh

from torch_brdf.scene import Camera, EnvironmentMap, Scene, SceneObject, mesh_from_arrays
from torch_brdf.scene.builtin import cornell_box
from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace, power_heuristic, reference_path_trace

GLOSSY_BALL = {"type": "blinn_phong", "kd": 0.1, "ks": 0.6, "exponent": 3000.0}
GLOSSY_PLANE = {"type": "blinn_phong", "kd": (0.3, 0.25, 0.2), "ks": 0.3, "exponent": 30.0}


def _sky_scene(size: int = 24, ball=GLOSSY_BALL) -> Scene:
    """A sharp glossy sphere on a glossy plane under a sky with a 3-degree sun."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.7)
    sphere.apply_translation([0.3, 0.7, 0.0])
    plane = mesh_from_arrays([(-3, 0, -3), (-3, 0, 3), (3, 0, 3), (3, 0, -3)], [[0, 1, 2], [0, 2, 3]])
    objects = [
        SceneObject("ball", mesh_from_arrays(sphere.vertices, sphere.faces), "ball", smooth=True),
        SceneObject("plane", plane, "plane"),
    ]
    sky = EnvironmentMap.sky(height=32, sun_direction=(0.6, 0.5, -0.4), sun_angular_radius_deg=3.0)
    cam = Camera((0.5, 2.0, -3.5), (0.0, 0.5, 0.0), fov_deg=45.0, width=size, height=size)
    return Scene(objects, {"ball": dict(ball), "plane": dict(GLOSSY_PLANE)}, [sky], cam)


def _glossy_cornell(size: int = 24) -> Scene:
    scene = cornell_box(size)
    scene.materials["glossy"] = {
        "type": "blinn_phong",
        "kd": (0.3, 0.25, 0.2),
        "ks": (0.4, 0.45, 0.5),
        "exponent": 100.0,
    }
    scene.objects[scene.object_id("back")].material = "glossy"
    return scene


def _block_t(a: torch.Tensor, b: torch.Tensor, block: int, floor: float = 0.0):
    """Block t statistics of two stacks of independent renders (K, H, W, 3): per block and
    channel, the difference of the K-seed means over its standard error (sample variances
    over the seeds, plus ``floor`` times the block mean as a systematic allowance).

    Returns:
        (t (H/B, W/B, 3), median relative standard error): the second says which bias the
        test could see.
    """

    def blocks(x):
        return torch.nn.functional.avg_pool2d(x.double().permute(0, 3, 1, 2), block)

    ba, bb = blocks(a), blocks(b)
    k = a.shape[0]
    se = (ba.var(0) / k + bb.var(0) / k + (floor * bb.mean(0)) ** 2).sqrt()
    t = (ba.mean(0) - bb.mean(0)) / se.clamp_min(1e-12)
    return t, float((se / bb.mean(0).abs().clamp_min(1e-12)).median())


def test_power_heuristic_weights():
    pa = torch.tensor([1.0, 0.0, 2.0, 3.0, float("inf"), 5.0])
    pb = torch.tensor([0.0, 1.0, 2.0, 1.0, 1.0, 1e-30])
    w = power_heuristic(pa, pb)
    torch.testing.assert_close(w, torch.tensor([1.0, 0.0, 0.5, 0.9, 1.0, 1.0]))
    finite = torch.isfinite(pa) & (pa + pb > 0)
    torch.testing.assert_close((w + power_heuristic(pb, pa))[finite], torch.ones(int(finite.sum())))


def _sky_moderate() -> Scene:
    """:func:`_sky_scene` with an n = 200 sphere: sharp enough for MIS to matter, broad enough
    that next-event estimation alone has a variance that 8 seeds estimate (at n = 3000 its
    rare huge samples make the seed variance, and so any t-test against it, unreliable)."""
    return _sky_scene(24, ball={**GLOSSY_BALL, "exponent": 200.0})


@pytest.mark.parametrize(
    ("scene_fn", "bounces"),
    [(_sky_moderate, 1), (_sky_moderate, 2), (_glossy_cornell, 3)],
    ids=["sky-direct", "sky-2", "cornell-3"],
)
def test_mis_equals_nee_in_expectation(scene_fn, bounces):
    r"""Same scene, K = 8 seeds each (disjoint), 8 spp: per 4 x 4 block and channel
    :math:`|t| \le 4` for >= 95% of the block-channels (Student t with ~14 degrees of freedom:
    P(|t| > 4) ~ 0.1% per block under "same expectation"; heavy-tailed fireflies of the NEE
    side make it larger, hence the 5% allowance), and the image means agree within 4
    standard errors. The test can see a bias: the median block standard error is below 6%
    of the block mean, so a 25% bias in a block fails it."""
    scene = scene_fn()
    K, spp = 8, 8
    mis = torch.stack(
        [
            path_trace(scene, PathTraceSettings(spp=spp, max_bounces=bounces, mis=True), seed=s, progress=False)
            for s in range(K)
        ]
    )
    nee = torch.stack(
        [
            path_trace(scene, PathTraceSettings(spp=spp, max_bounces=bounces, mis=False), seed=100 + s, progress=False)
            for s in range(K)
        ]
    )
    t, rel_se = _block_t(mis, nee, 4)
    assert rel_se < 0.06, rel_se
    assert float((t.abs() <= 4).double().mean()) >= 0.95, t.abs().max()
    m, n = mis.double().mean((1, 2, 3)), nee.double().mean((1, 2, 3))
    se = float((m.var() / K + n.var() / K).sqrt())
    assert abs(float(m.mean() - n.mean())) <= 4 * se, (float(m.mean()), float(n.mean()), se)


def test_mis_changes_the_estimator_and_is_seeded():
    """MIS is a different estimator (not a no-op) and still a function of the seed."""
    scene = _sky_scene(12)
    a = reference_path_trace(scene, spp=2, max_bounces=2, seed=3, progress=False)
    b = reference_path_trace(scene, spp=2, max_bounces=2, seed=3, progress=False)
    c = reference_path_trace(scene, spp=2, max_bounces=2, seed=3, progress=False, mis=False)
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_mis_removes_fireflies_of_a_sharp_lobe_under_the_sky():
    """A Blinn-Phong sphere with n = 3000 under sun and sky, direct lighting: NEE alone
    samples the sky by its luminance, so the narrow lobe's reflection of the sky is found
    by rare samples with huge weights. MIS (BRDF sampling takes over there) must cut the
    per-pixel variance over seeds on the sphere by at least 2x (measured ~4x)."""
    scene = _sky_scene(24)
    K = 8
    o, d = scene.camera.generate_rays()
    ball = (scene.trace(o, d).object_id == scene.object_id("ball")).reshape(24, 24)
    var = {}
    for mis in (True, False):
        imgs = torch.stack(
            [
                path_trace(scene, PathTraceSettings(spp=2, max_bounces=1, mis=mis), seed=s, progress=False)
                for s in range(K)
            ]
        ).double()
        var[mis] = float(imgs.var(0)[ball].mean())
    assert var[True] < 0.5 * var[False], var


@pytest.mark.reference
def test_mis_agrees_with_mitsuba_glossy_sky():
    """The glossy sphere (n = 200) on the glossy plane under sun and sky, 2 bounces, against
    Mitsuba 3's path tracer (which uses MIS too): block means within 4 standard errors in >=
    95% of the block-channels, with a 1% floor for Mitsuba's bilinear envmap lookup against
    our nearest texel (see tests/transport/test_mitsuba.py), and image means within 2%."""
    pytest.importorskip("mitsuba")
    from torch_brdf.transport import mitsuba as tbm

    scene = _sky_scene(24, ball={**GLOSSY_BALL, "exponent": 200.0})
    K, spp = 4, 8
    ours = torch.stack([reference_path_trace(scene, spp, 2, seed=s, progress=False) for s in range(K)])
    theirs = torch.stack([tbm.render_mitsuba(scene, spp, 2, seed=s) for s in range(K)])
    t, rel_se = _block_t(ours, theirs, 4, floor=0.01)
    assert rel_se < 0.06, rel_se
    assert float((t.abs() <= 4).double().mean()) >= 0.95, t.abs().max()
    assert abs(float(ours.double().mean() / theirs.double().mean()) - 1) < 0.02
