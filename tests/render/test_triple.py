"""Locally adaptive triple products: exact bookkeeping against the dense standard-basis sum,
analytic values, rules, extremes and the image path."""

from __future__ import annotations

import pytest
import torch

from tests.conftest import RTOL
from tests.transport.test_visibility import ball_on_plane
from torch_brdf.brdf.analytic import Phong, WardAniso
from torch_brdf.brdf.base import Lambert
from torch_brdf.brdf.measured import MERLTabulated
from torch_brdf.errors import SceneError, ShapeError, ValueRangeError
from torch_brdf.io.merl import merl_index_to_angles
from torch_brdf.metrics import psnr
from torch_brdf.render.triple import (
    FixedRule,
    GenericRule,
    PhongRule,
    TripleProductRenderer,
    block_lighting,
)
from torch_brdf.scene.envmap import EnvironmentMap
from torch_brdf.sphere.cubemap import CubemapBlocks
from torch_brdf.transport.visibility import VisibilitySettings, precompute_visibility

EYE = (0.3, 1.4, -2.4)


def sky(height: int = 32) -> EnvironmentMap:
    return EnvironmentMap.sky(height=height, sun_radiance=(400.0, 380.0, 350.0), sun_angular_radius_deg=4.0)


@pytest.fixture(scope="module")
def scene():
    sc = ball_on_plane(quads=8)
    sc.lights[:] = [sky()]
    return sc


@pytest.fixture(scope="module")
def vis(scene):
    return precompute_visibility(scene, VisibilitySettings(resolution=32, chunk=64), progress=False)


def measured_like() -> MERLTabulated:
    """A tabulated, isotropic, glossy 'measured' BRDF (a function of theta_h only)."""
    ih = torch.arange(90)
    th, _, _ = merl_index_to_angles(ih, torch.zeros(90, dtype=torch.long), torch.zeros(90, dtype=torch.long))
    f = 0.08 + 3.0 * torch.exp(-((th / 0.15) ** 2))
    table = f.view(1, 90, 1, 1).expand(3, 90, 4, 2).clone()
    return MERLTabulated(table, theta_d_index=[0, 30, 60, 89], phi_d_index=[0, 90], name="synthetic")


MATERIALS = {
    "lambert": lambda: Lambert((0.6, 0.5, 0.4)),
    "phong": lambda: Phong(0.3, 0.5, 120.0),
    "ward_aniso": lambda: WardAniso(0.3, 0.4, 0.08, 0.3),
    "measured": measured_like,
}


def renderer(scene, vis, dtype=torch.float64, box="phong", floor="lambert"):
    r = TripleProductRenderer(scene, vis, dtype=dtype)
    r.set_material("box", MATERIALS[box]())
    r.set_material("floor", MATERIALS[floor]())
    return r


@pytest.mark.parametrize("box", sorted(MATERIALS))
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_forced_256_samples_equals_standard_basis(scene, vis, box, dtype):
    r = renderer(scene, vis, dtype, box=box, floor="phong")
    view = r.all_vertices(EYE)
    ours, stats = r.shade(view, rule=FixedRule(16))
    ref = r.shade_standard(view)
    scale = float(ref.abs().max())
    assert scale > 0
    assert float((ours - ref).abs().max()) <= 10 * RTOL[dtype] * scale
    # bookkeeping: every pair is in exactly one case; no pair used the DCT paths
    assert sum(stats.cases.values()) == stats.blocks == len(view.vertex_ids) * vis.geometry.block_count
    assert stats.sampling["256"] == stats.blocks - stats.cases["occluded"]
    assert stats.cases["line9"] == 0


def test_standard_basis_is_the_texel_sum_oracle(scene, vis):
    """The dense product equals an explicit per-texel loop over raw inputs for a few vertices."""
    r = renderer(scene, vis, box="phong", floor="lambert")
    view = r.all_vertices(EYE)
    ref = r.shade_standard(view)
    geom = vis.geometry
    lit = block_lighting(r.envmap, geom, samples=4, dtype=torch.float64)
    for vid in (0, 5, len(view.vertex_ids) - 1):
        p, n = vis.vertices.positions[vid], vis.vertices.normals[vid]
        wo = torch.tensor(EYE, dtype=torch.float64) - p
        wo = wo / wo.norm()
        V = vis.blocks.decode([vid])[0].double().reshape(-1)
        d = geom.directions.reshape(-1, 3)
        brdf = r.brdfs[int(vis.vertices.object_ids[vid])]
        from torch_brdf.frame import Frame

        fr = Frame.from_normal(n.view(1, 3))
        f = brdf.eval(d, wo.expand_as(d), Frame(fr.s.expand_as(d), fr.t.expand_as(d), fr.n.expand_as(d))).double()
        cos = (d @ n).clamp_min(0)
        B = (lit.texels.reshape(-1, 3) * (V * cos)[:, None] * f).sum(0)
        torch.testing.assert_close(ref[vid], B, rtol=1e-10, atol=1e-12)


def test_lambert_scene_is_exact_with_one_coefficient(scene, vis):
    """The cosine is handled exactly, so a constant BRDF needs one coefficient per block in
    every case (lines 6 and 9) and matches the dense sum to rounding."""
    r = renderer(scene, vis, box="lambert", floor="lambert")
    view = r.all_vertices(EYE)
    for rule in (FixedRule(1), PhongRule(), GenericRule()):
        ours, stats = r.shade(view, rule=rule)
        torch.testing.assert_close(ours, r.shade_standard(view), rtol=1e-10, atol=1e-12)
        assert stats.sampling["1"] == stats.blocks - stats.cases["occluded"]
        assert stats.cases["line11"] == 0 and stats.cases["line9"] > 0 and stats.cases["line6"] > 0


def test_white_furnace_on_open_plane():
    """Constant sky of radiance 1, white Lambert plane, nothing above: B = 1 up to the texel
    quadrature of the cosine (which the dense sum shares)."""
    sc = ball_on_plane(quads=2, box=False)
    sc.lights[:] = [EnvironmentMap.constant(1.0, 16)]
    vis = precompute_visibility(sc, VisibilitySettings(resolution=32), progress=False)
    r = TripleProductRenderer(sc, vis, dtype=torch.float64)
    r.set_material("floor", Lambert(1.0))
    B, _ = r.shade(r.all_vertices((0.0, 2.0, -1.0)))
    assert torch.allclose(B, torch.ones_like(B), rtol=2e-3)
    r.set_material("floor", Lambert(0.0))
    B, _ = r.shade(r.all_vertices((0.0, 2.0, -1.0)))
    assert float(B.abs().max()) == 0.0


@pytest.mark.parametrize("box", ["phong", "ward_aniso", "measured"])
def test_rules_are_close_to_the_standard_basis(scene, vis, box):
    r = renderer(scene, vis, box=box, floor="phong")
    view = r.all_vertices(EYE)
    ref = r.shade_standard(view)
    for rule, tol in ((GenericRule(), 0.02), (PhongRule(), 0.05)):
        ours, stats = r.shade(view, rule=rule)
        err = float((ours - ref).abs().max() / ref.abs().max())
        assert err < tol, (rule, err)
        if isinstance(rule, GenericRule):  # most blocks need one coefficient
            assert stats.sampling["1"] > 0.5 * sum(stats.sampling.values())


def test_more_coefficients_are_more_accurate(scene, vis):
    r = renderer(scene, vis, box="phong", floor="phong")
    view = r.all_vertices(EYE)
    ref = r.shade_standard(view)
    errs = [float((r.shade(view, rule=FixedRule(l))[0] - ref).norm()) for l in (1, 2, 4, 16)]
    assert errs[0] > errs[1] > errs[2] > errs[3]
    assert errs[3] < 1e-10 * float(ref.norm())


def test_near_mirror_lobe_uses_pixel_samples_at_the_peak(scene, vis):
    r = renderer(scene, vis, box="lambert", floor="lambert")
    r.set_material("floor", Phong(0.05, 0.9, 5000.0))
    view = r.all_vertices(EYE)
    ref = r.shade_standard(view)
    for rule in (PhongRule(), GenericRule()):
        ours, stats = r.shade(view, rule=rule)
        assert stats.sampling["256"] > 0
        assert float((ours - ref).abs().max() / ref.abs().max()) < 0.02


def test_grazing_view_and_backfacing_vertices(scene, vis):
    r = renderer(scene, vis, box="phong", floor="phong")
    for eye in ((3.0, 0.02, 0.0), (0.0, -1.0, 0.0)):  # grazing the floor; below it
        view = r.all_vertices(eye)
        ours, _ = r.shade(view, rule=GenericRule())
        ref = r.shade_standard(view)
        assert bool(torch.isfinite(ours).all())
        assert float((ours - ref).abs().max()) <= 0.05 * max(float(ref.abs().max()), 1e-12)


def test_lighting_rotation_is_recomputed(scene, vis):
    r = renderer(scene, vis, box="phong", floor="lambert")
    view = r.all_vertices(EYE)
    before, _ = r.shade(view)
    r.set_lighting(sky().rotated(1.0))
    after, _ = r.shade(view)
    assert float((after - before).abs().max()) > 0.05 * float(before.abs().max())
    torch.testing.assert_close(r.shade(view, rule=FixedRule(16))[0], r.shade_standard(view), rtol=1e-9, atol=1e-12)


def test_float32_matches_float64(scene, vis):
    a, _ = renderer(scene, vis, torch.float32).shade(renderer(scene, vis, torch.float32).all_vertices(EYE))
    b, _ = renderer(scene, vis, torch.float64).shade(renderer(scene, vis, torch.float64).all_vertices(EYE))
    assert float((a.double() - b).abs().max()) <= 1e-4 * float(b.abs().max())


def test_stats_tables(scene, vis):
    r = renderer(scene, vis)
    _, stats = r.shade(r.all_vertices(EYE))
    pct = stats.percentages()
    assert sum(pct["cases"].values()) == pytest.approx(100.0)
    assert sum(pct["sampling"].values()) == pytest.approx(100.0)
    assert stats.brdf_evals >= sum(stats.sampling.values())
    assert set(stats.as_dict()) >= {"cases", "sampling", "percent", "brdf_evals"}


def test_image_interpolates_vertex_colours_at_primary_hits(scene, vis):
    r = renderer(scene, vis)
    view = r.view()
    assert len(view.vertex_ids) < len(vis.vertices)  # culled: not every vertex is seen
    rad = torch.rand(len(view.vertex_ids), 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    img = r.image(view, rad, background=False)
    gb = view.gbuffer
    k = len(gb.pixels) // 2
    expect = (rad[gb.corners[k]] * gb.weights[k][:, None]).sum(0)
    flat = img.view(-1, 3)[gb.pixels[k]]
    torch.testing.assert_close(flat.double(), expect, rtol=1e-6, atol=1e-7)
    assert float(img.view(-1, 3)[~view.mask.view(-1)].abs().max()) == 0.0
    ours, stats = r.render()
    ref, _ = r.render(method="standard")
    assert ours.shape == (scene.camera.height, scene.camera.width, 3) and stats is not None
    assert psnr(ours, ref, view.mask) > 40.0
    with pytest.raises(ShapeError):
        r.image(view, rad[:-1])
    with pytest.raises(ValueRangeError):
        r.render(method="wavelets")


def test_mismatched_record_and_bad_input(scene, vis):
    other = ball_on_plane(quads=5)
    other.lights[:] = [sky()]
    with pytest.raises(SceneError):
        TripleProductRenderer(other, vis)
    r = renderer(scene, vis)
    with pytest.raises(SceneError):
        r.set_material(7, Lambert(0.5))
    with pytest.raises(ValueRangeError):
        FixedRule(3)


def test_block_lighting_representations_agree():
    geom = CubemapBlocks(32, 16)
    lit = block_lighting(sky(), geom, dtype=torch.float64)
    # the DC term of the DCT and the first prefix integral both hold the block total
    total = lit.moments.sum(1)
    torch.testing.assert_close(lit.integral[:, 0], total)
    torch.testing.assert_close(lit.dct[:, 0] * 16, total)
    # the sun's energy is where the sun is: total L Omega over the sphere matches the lat-long integral
    env = sky()
    torch.testing.assert_close(lit.texels.sum((0, 1)), env.integral().double(), rtol=0.02, atol=0)


@pytest.mark.parametrize("samples", [4, 16])
def test_block_lighting_carries_the_maps_power(samples):
    """The cube texels (solid-angle means of the map's own lookup) sum to the map's integral,
    even for a 1.5 deg sun smaller than a cube texel: within 0.05% from 4 x 4 samples."""
    env = EnvironmentMap.sky(height=64)
    lit = block_lighting(env, CubemapBlocks(32), samples, torch.float64)
    torch.testing.assert_close(lit.texels.sum((0, 1)), env.integral(), rtol=5e-4, atol=0.0)


def test_haar_baseline_is_exact_with_every_coefficient(scene, vis):
    r = renderer(scene, vis, box="phong", floor="phong")
    view = r.all_vertices(EYE)
    ref = r.shade_standard(view)
    timings: dict = {}
    full = r.shade_haar(view, fraction=1.0, timings=timings)
    torch.testing.assert_close(full, ref, rtol=1e-5, atol=1e-5 * float(ref.abs().max()))
    assert set(timings) == {"visibility_s", "brdf_s", "product_s"}
    few = r.shade_haar(view, fraction=0.01)
    assert bool(torch.isfinite(few).all())
    assert float((few - ref).abs().max()) > float((full - ref).abs().max())


def test_graded_visibility_products(scene):
    """Anti-aliased maps (2x2 rays per texel, 6 bits): the differential values are fractions,
    lines 9 and 11 walk them the same way, and the bookkeeping stays exact."""
    vis = precompute_visibility(scene, VisibilitySettings(resolution=16, supersample=2, bits=6), progress=False)
    r = renderer(scene, vis, box="phong", floor="lambert")
    view = r.all_vertices(EYE)
    ref = r.shade_standard(view)
    torch.testing.assert_close(r.shade(view, rule=FixedRule(16))[0], ref, rtol=1e-10, atol=1e-12)
    lamb = renderer(scene, vis, box="lambert", floor="lambert")
    ours, stats = lamb.shade(view, rule=FixedRule(1))
    torch.testing.assert_close(ours, lamb.shade_standard(view), rtol=1e-10, atol=1e-12)
    assert stats.cases["line9"] > 0
    v = vis.blocks.values(torch.float64)
    assert bool(((v.abs() > 0) & (v.abs() < 1)).any())  # really fractional steps
