"""The editor without a browser: parameter forms, fast projection, object ids, edits, reference."""

from __future__ import annotations

import math

import pytest
import torch

from tests.conftest import corrupted_copy
from torch_brdf.brdf import Projector, available, create, project
from torch_brdf.brdf.analytic import EXPONENT_RANGE, WARD_ALPHA_RANGE
from torch_brdf.brdf.microfacet import CookTorrance
from torch_brdf.editor import (
    EditorSession,
    ReferenceJob,
    load_source,
    model_choices,
    object_id_buffer,
    param_specs,
    scene_with_materials,
)
from torch_brdf.editor.params import hex_to_linear, linear_to_hex
from torch_brdf.editor.session import FAST_QUADRATURE
from torch_brdf.errors import FileFormatError, SceneError, ValueRangeError
from torch_brdf.transport import PathTraceSettings, path_trace


@pytest.fixture(scope="module")
def session(small_tensors_file, small_scene):
    return EditorSession(small_tensors_file[1], small_scene)


# -- the form comes from the models ----------------------------------------------------------
def test_ranges_come_from_the_models_own_checks():
    spec = {s.name: s for s in param_specs("blinn_phong")}
    assert (spec["exponent"].lo, spec["exponent"].hi, spec["exponent"].kind) == (*EXPONENT_RANGE, "log")
    assert spec["kd"].kind == spec["ks"].kind == "rgb" and (spec["kd"].lo, spec["kd"].hi) == (0.0, 1.0)
    ggx = {s.name: s for s in param_specs("cook_torrance", {"distribution": "ggx"})}
    assert (ggx["roughness"].lo, ggx["roughness"].hi) == CookTorrance.ROUGHNESS_RANGE
    assert (param_specs("ward")[2].lo, param_specs("ward")[2].hi) == WARD_ALPHA_RANGE
    assert [s.name for s in param_specs("lambert")] == ["albedo"]  # the constructor's name, not "reflectance"
    assert "exponent" in {s.name for s in param_specs("distribution_based")}  # found inside the distribution


def test_every_menu_entry_builds_at_its_bounds_and_refuses_beyond():
    choices, skipped = model_choices()
    labels = [c.label for c in choices]
    assert "GGX (cook_torrance)" in labels and "blinn_phong" in labels
    assert set(skipped) <= {"merl", "nbrdf"}  # only the data models, and only without their files
    assert {c.model for c in choices} | set(skipped) == set(available())
    for c in choices:
        if c.data is not None:  # a choice of materials: each builds
            for name in c.data.options[:2]:
                create(c.material({"material": name}))
            continue
        for s in param_specs(c.model, dict(c.fixed)):
            if s.kind == "curve":  # J x 3 non-negative values: zeros build, a negative one does not
                create(c.material({s.name: [[0.0] * 3] * 64}))
                with pytest.raises(ValueRangeError):
                    create(c.material({s.name: [[-1.0] * 3] * 64}))
                continue
            for v in (s.lo, s.hi):
                create(c.material({s.name: (v, v, v) if s.kind == "rgb" else v}))
            beyond = s.hi * 10 if s.kind == "log" else s.hi + 0.5
            with pytest.raises(ValueRangeError):
                create(c.material({s.name: (beyond,) * 3 if s.kind == "rgb" else beyond}))


def test_colour_round_trip():
    for rgb in [(0.0, 0.5, 1.0), (0.2, 0.02, 0.7)]:
        back = hex_to_linear(linear_to_hex(rgb))
        assert all(abs(a - b) < 0.01 for a, b in zip(rgb, back, strict=True))
    with pytest.raises(ValueRangeError):
        hex_to_linear("#12zz45")


# -- fast projection -------------------------------------------------------------------------
def test_coarse_rule_error(small_tensors_file):
    """Blinn-Phong depends on theta_h alone: the coarse rule loses nothing; GGX's Fresnel and
    masking vary with theta_d: a few per cent (the price of ~40x fewer BRDF evaluations)."""
    b = small_tensors_file[1].bases[small_tensors_file[1].object_id("back")]
    fast = Projector(b.band_basis(), b.quotient, **FAST_QUADRATURE)
    for brdf, tol in ((create("blinn_phong", exponent=100.0), 1e-4), (create("cook_torrance", roughness=0.2), 0.1)):
        ref = project(brdf, b.band_basis(), b.quotient)
        assert float((fast(brdf) - ref).norm() / ref.norm()) < tol


# -- object ids ------------------------------------------------------------------------------
def test_object_ids_primary_rays_and_tensor_entries_agree(small_tensors_file, small_scene):
    tensors = small_tensors_file[1]
    rays, how = object_id_buffer(tensors, small_scene)
    entries, how2 = object_id_buffer(tensors)
    assert (how, how2) == ("primary rays", "tensor entries")
    back = tensors.object_id("back")
    assert int((rays == back).sum()) > 0.15 * rays.numel()
    seen = (entries >= 0) & (rays >= 0)  # jittered paths reach past the pixel centres at the box's rim
    assert int(seen.sum()) > 0.8 * rays.numel()
    assert float((entries[seen] == rays[seen]).float().mean()) > 0.9  # object edges may differ


# -- edits -----------------------------------------------------------------------------------
def test_edit_changes_the_wall_and_frozen_equals_full(session):
    session.select("back")
    session.set_material("back", {"type": "blinn_phong", "kd": 0.25, "ks": 0.6, "exponent": 100.0})
    before = session.render()
    session.set_material("back", {"type": "blinn_phong", "kd": 0.25, "ks": 0.6, "exponent": 2000.0})
    after = session.render()
    assert session.renderer.frozen_object == "back"
    full = session.renderer.evaluate()
    assert torch.allclose(after, full, rtol=1e-4, atol=1e-5 * float(full.abs().max()))
    wall = session.ids == session.tensors.object_id("back")
    change = (after - before).abs().sum(-1)
    assert float(change[wall].mean()) > 10 * float(change[~wall].mean())
    light = session.tensors.emission.abs().sum(0).reshape(change.shape) > 0
    light &= session.ids == session.tensors.object_id("light")
    assert float(change[light].max()) < 1e-3 * float(after[light].max())  # the emitter's own pixels stay


def test_per_bounce_views_sum_to_the_image(session):
    parts = [session.render(v) for v in session.views()[1:]]
    assert torch.allclose(sum(parts[1:], parts[0]), session.render(), rtol=1e-4, atol=1e-6)
    one = session.render("image", bounces=1)
    assert torch.allclose(one, parts[0] + parts[1], rtol=1e-5, atol=1e-7)
    with pytest.raises(ValueRangeError):
        session.render("image", bounces=session.bounces + 1)


def test_bad_edits_raise_readable_errors(session):
    with pytest.raises(ValueRangeError, match="exponent"):
        session.set_material("back", {"type": "blinn_phong", "exponent": 1e6})
    with pytest.raises(ValueRangeError, match=r"blinn_phong kd: .*\[0.0, 1.0\]"):
        session.set_material("back", {"type": "blinn_phong", "kd": 1.5})
    with pytest.raises(SceneError, match="fixed"):
        session.select("light")
    with pytest.raises(ValueRangeError, match="Fresnel"):
        session.set_material("back", {"type": "lambert"}, f0=0.5)


def test_fresnel_layer_f0(small_scene):
    from torch_brdf.transport import PolynomialSettings, precompute_polynomial

    t = precompute_polynomial(
        small_scene, PolynomialSettings("8,1", spp=1, bases={"back": {"fresnel": True}}), seed=0, progress=False
    )
    s = EditorSession(t, small_scene)
    s.select("back")
    mat = {"type": "blinn_phong", "kd": 0.2, "ks": 0.6, "exponent": 50.0}
    s.set_material("back", mat, f0=1.0)
    a = s.render()
    s.set_material("back", mat, f0=0.1)
    assert not torch.equal(a, s.render())
    with pytest.raises(ValueRangeError, match="f0"):
        s.set_material("back", mat, f0=1.5)


# -- loading ---------------------------------------------------------------------------------
def test_load_source_errors_and_cache(tmp_path, small_tensors_file, monkeypatch):
    path = small_tensors_file[0]
    t, sc, _ = load_source(str(path))
    assert t.object_names == small_tensors_file[1].object_names
    assert sc is not None and sc.name == "cornell_box_glossy" and (sc.camera.width, sc.camera.height) == (32, 32)
    with pytest.raises(FileFormatError):
        load_source(str(corrupted_copy(path, tmp_path / "bad.npz")))
    with pytest.raises(FileFormatError):
        load_source(str(tmp_path / "missing.npz"))
    with pytest.raises(SceneError):
        load_source("no_such_scene")
    bad = tmp_path / "bad.toml"
    bad.write_text('[camera]\norigin = [0, 1, -4]\n[[objects]]\nname = "x"\nmesh = "missing.ply"\nmaterial = "m"\n')
    with pytest.raises(SceneError):
        load_source(str(bad))
    _, _, note = load_source("cornell_box_glossy", resolution=8, spp=1, series="4,1", cache_dir=tmp_path)
    t2, _, note2 = load_source("cornell_box_glossy", resolution=8, spp=1, series="4,1", cache_dir=tmp_path)
    assert note.startswith("precomputed") and note2.startswith("cached") and t2.height == 8
    a_file = tmp_path / "cache_is_a_file"
    a_file.write_text("")
    import torch_brdf.editor.session as session_module

    def no_precompute(*_a, **_k):
        raise AssertionError("refused before the precompute")

    monkeypatch.setattr(session_module, "precompute_polynomial", no_precompute)
    with pytest.raises(FileFormatError, match="cache_is_a_file"):
        load_source("cornell_box_glossy", resolution=8, spp=1, series="4,1", cache_dir=a_file)


# -- reference -------------------------------------------------------------------------------
def test_reference_averages_passes_and_cancels(small_scene):
    sc = scene_with_materials(small_scene.with_resolution(8), {"back": {"type": "lambert", "albedo": 0.9}})
    assert small_scene.materials[small_scene.objects[small_scene.object_id("back")].material]["type"] == "blinn_phong"
    seen = []
    job = ReferenceJob(sc, 2, 2, seed=3, on_progress=lambda d, n: seen.append((d, n))).start()
    assert job.wait(300) and job.error is None
    manual = (path_trace(sc, PathTraceSettings(spp=1, max_bounces=2), seed=3 * 1_000_003, progress=False).double()) / 2
    manual += (
        path_trace(sc, PathTraceSettings(spp=1, max_bounces=2), seed=3 * 1_000_003 + 1, progress=False).double() / 2
    )
    assert torch.allclose(job.image.double(), manual, rtol=1e-6, atol=1e-7)
    assert seen == [(1, 2), (2, 2)]
    job = ReferenceJob(sc, 1000, 2)
    job.cancel()
    job.start()
    assert job.wait(60) and job.image is None and job.done == 0 and job.cancelled


def test_compare_reports_relative_rmse(session):
    ref = session.renderer.evaluate() * 1.1
    diff, rmse = session.compare(ref)
    assert diff.shape == ref.shape and math.isclose(rmse, 0.1 / 1.1, rel_tol=1e-4)


# -- measured materials ----------------------------------------------------------------------
def test_latent_pick_blends_the_materials_projections(session, small_fit):
    if small_fit is None:
        pytest.skip("shared data not found: merl/nbrdf_merl100_weights.npz")
    from torch_brdf.brdf import NBRDF
    from torch_brdf.editor.latent import LatentMap

    lm = LatentMap(small_fit, resolution=32)
    assert lm.image().shape == (32, 32, 3)
    session.select("back")
    c, info = lm.pick(session, "back", 5, 20)
    b = lm.model.weights(lm.latent(*info["picked"]))
    own = torch.stack([session.coefficients("back", NBRDF(n, lm.nbrdf)) for n in lm.names])
    assert torch.allclose(c, torch.einsum("n,njc->jc", b, own).clamp_min(0), rtol=1e-12, atol=0)
    assert len(info["heaviest"]) == 3 and info["variance"] >= 0
    session.set_material("back", lm.material(session, "back", c))
    m = session.tensors.object_id("back")
    assert torch.allclose(session.renderer.c[m].double(), c, rtol=1e-6, atol=1e-9)  # the curve is used as is
    with pytest.raises(ValueRangeError):
        lm.latent(32, 0)
    session.set_material("back", {"type": "blinn_phong", "kd": 0.25, "ks": 0.6, "exponent": 100.0})


def test_latent_map_shows_any_pair_of_dimensions(tmp_path):
    """q = 3: the slice on dims (1, 2) keeps dim 0 at the latents' mean, moves dim 1 along x
    and dim 2 up the map, and draws the materials at their (1, 2) coordinates."""
    from torch_brdf.data import data_path
    from torch_brdf.editor.latent import LatentMap
    from torch_brdf.io.merl import load_nbrdf_weights
    from torch_brdf.manifold import fit_gplvm, gram, nbrdf_observations

    weights = data_path("merl", "nbrdf_merl100_weights.npz", required=False)
    if weights is None:
        pytest.skip("shared data not found: merl/nbrdf_merl100_weights.npz")
    obs = nbrdf_observations(weights, names=list(load_nbrdf_weights(weights).names)[:6], progress=False)
    s, d = gram(obs.z, obs.cosine_weights())
    fit = fit_gplvm(s, d, q=3, names=obs.names, max_iter=20)
    lm = LatentMap(fit, weights, resolution=24)
    assert lm.q == 3 and lm.dims == (0, 1)
    first = lm.image()
    lm.set_dims((1, 2))
    assert lm.dims == (1, 2) and not torch.equal(lm.image(), first)
    mean = lm.model.latents.mean(0)
    z00, z_right, z_up = lm.latent(0, 23), lm.latent(23, 23), lm.latent(0, 0)
    for z in (z00, z_right, z_up):
        assert math.isclose(float(z[0]), float(mean[0]), rel_tol=1e-12, abs_tol=1e-12)
    assert float(z_right[1]) > float(z00[1]) and float(z_up[2]) > float(z00[2])
    assert float(z_right[2]) == float(z00[2]) and float(z_up[1]) == float(z00[1])
    for bad in ((1, 1), (0, 3)):
        with pytest.raises(ValueRangeError):
            lm.set_dims(bad)


# -- switching the edited object ---------------------------------------------------------------
def _close(a: torch.Tensor, b: torch.Tensor) -> bool:
    return torch.allclose(a, b, rtol=1e-4, atol=1e-5 * float(b.abs().max()))


def test_switching_objects_reuses_kept_states_and_stays_exact(small_tensors_file, small_scene):
    s = EditorSession(small_tensors_file[1], small_scene, frozen_cache_mb=64)
    assert s.renderer.max_frozen_bytes == 64 * 2**20
    full = s.renderer.evaluate
    wall = {"type": "blinn_phong", "kd": 0.2, "ks": 0.6, "exponent": 300.0}
    s.select("back")
    assert s.last_select == "frozen"
    s.set_material("back", wall)
    s.select("left")  # first visit: frozen now
    assert s.last_select == "frozen" and set(s.renderer.frozen_objects) == {"back", "left"}
    s.select("back")  # nothing changed since: its kept state as it is
    assert s.last_select == "kept" and _close(s.render(), full())
    s.select("back")
    assert s.last_select == "active"
    s.set_material("back", {**wall, "exponent": 60.0})
    s.select("left")  # back changed since left's state was made: brought up to date, exact
    assert s.last_select == "refreshed" and _close(s.render(), full())
    s.set_material("left", {"type": "lambert", "albedo": [0.7, 0.1, 0.1]})
    assert _close(s.render(), full())
    s.set_material("back", wall)  # an object that is not selected
    assert _close(s.render(), full())
    assert s.undo() == "back" and _close(s.render(), full())


def test_latent_map_marks_where_the_model_is_trusted_and_snaps_outside(small_fit):
    if small_fit is None:
        pytest.skip("shared data not found: merl/nbrdf_merl100_weights.npz")
    from torch_brdf.brdf import NBRDF
    from torch_brdf.editor.latent import NEGATIVE_TOLERANCE, LatentMap, validity_pairs

    lm = LatentMap(small_fit, resolution=32)
    r, limit = 32, lm.trust * (1 + lm.model.mu)
    var = torch.stack([torch.stack([lm.model.variance(lm.latent(x, y)) for x in range(r)]) for y in range(r)])
    assert torch.equal(lm.untrusted, var > limit)  # the mask is the predictive variance, pixel by pixel
    assert bool(lm.untrusted.any()) and bool(lm.trusted.any())
    img = lm.image().int()
    assert bool((img[lm.untrusted][:, 2] > img[lm.untrusted][:, 0]).all())  # untrusted: dimmed, blue
    # a click outside snaps to the nearest trusted pixel and says why; inside it stays
    ys, xs = torch.nonzero(lm.untrusted, as_tuple=True)
    x, y = int(xs[0]), int(ys[0])
    sx, sy, why = lm.snap(x, y)
    ty, tx = torch.nonzero(lm.trusted, as_tuple=True)
    assert bool(lm.trusted[sy, sx]) and (sx - x) ** 2 + (sy - y) ** 2 == int(((tx - x) ** 2 + (ty - y) ** 2).min())
    assert "variance" in why and "snapped" in why
    assert lm.snap(int(tx[0]), int(ty[0])) == (int(tx[0]), int(ty[0]), None)
    # the seed's unconstrained weights: the validity mask against the blend evaluated directly
    raw = LatentMap(small_fit, resolution=16, valid="none")
    wi, wo, w = validity_pairs()
    wi, wo = wi.expand(-1, wo.shape[1], 3), wo.expand(wi.shape[0], -1, 3)
    mats = [NBRDF(n, raw.nbrdf) for n in raw.names]
    checked = {True: 0, False: 0}
    for y in range(0, 16, 3):
        for x in range(0, 16, 3):
            b = raw.model.weights(raw.latent(x, y))
            f = sum(float(b[i]) * m.eval(wi.float(), wo.float()).double() for i, m in enumerate(mats))  # (A, M, 3)
            albedo = (f * w[None, :, None]).sum(1)
            bad = bool(f.min() < -NEGATIVE_TOLERANCE * f.abs().max()) or bool(albedo.max() > 1)
            assert bool(raw.invalid[y, x]) == bad
            checked[bad] += 1
    assert checked[True]  # the seed's raw weights between 8 materials predict invalid BRDFs somewhere
    with pytest.raises(ValueRangeError):
        LatentMap(small_fit, resolution=16, trust=0.0)
