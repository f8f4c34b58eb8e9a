"""GI inverse design through the polynomial tensors (issue #16): recovery, extremes, GI vs direct."""

from __future__ import annotations

import pytest
import torch

from torch_brdf.metrics import relative_rmse
from torch_brdf.render import PolynomialRenderer, fit_image, object_mask
from torch_brdf.render.fit import energy_row
from torch_brdf.render.polynomial import emitter_mask
from torch_brdf.scene import cornell_box_glossy
from torch_brdf.transport import precompute_polynomial, reference_path_trace


@pytest.fixture(scope="module")
def box():
    sc = cornell_box_glossy(24)
    T = precompute_polynomial(sc, "8,1,1,1", spp=4, seed=0, progress=False)
    mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
    return sc, T, mats


def _renderer(box, **kw):
    _, T, mats = box
    return PolynomialRenderer(T, mats, dtype=torch.float64, **kw)


def _feasible(R, res, tol=1e-8):
    for name, c in res.coefficients.items():
        assert bool((c >= 0).all())
        d = (energy_row(R, name) * c).sum(0)
        assert bool((d <= 1 + tol).all()), d
    assert res.violation <= tol
    assert all(v == v for v in res.loss_curve)  # no NaN
    assert bool(torch.isfinite(res.image).all())


def test_recovers_known_curve_and_colour_of_two_objects(box):
    R = _renderer(box)
    R.set_material("back", {"type": "blinn_phong", "kd": (0.3, 0.2, 0.1), "ks": 0.5, "exponent": 50.0})
    R.set_material("floor", {"type": "lambert", "albedo": (0.6, 0.3, 0.2)})
    truth = {o: R.c[R.tensors.object_id(o)].clone() for o in ("back", "floor")}
    target = R().detach()
    R.set_material("back", {"type": "lambert", "albedo": 0.5})
    R.set_material("floor", {"type": "lambert", "albedo": 0.5})
    res = fit_image(R, ["back", "floor"], target)
    for o, c in truth.items():
        assert float((res.coefficients[o] - c).abs().max() / c.abs().max()) < 1e-4
    _feasible(R, res)
    assert res.converged and res.loss_curve[-1] < 1e-12 * res.loss_curve[0]
    assert res.kkt_residual < 1e-6
    assert all(b <= a * (1 + 1e-12) for a, b in zip(res.loss_curve, res.loss_curve[1:], strict=False))  # monotone


def test_near_mirror_target(box):
    R = _renderer(box)
    R.set_material("back", {"type": "blinn_phong", "kd": 0.0, "ks": 0.9, "exponent": 1e4})
    truth = R.c[R.tensors.object_id("back")].clone()
    target = R().detach()
    R.set_material("back", {"type": "lambert", "albedo": 0.5})
    res = fit_image(R, "back", target, weights=object_mask(R.tensors, "back"))
    _feasible(R, res)
    assert float((res.coefficients["back"] - truth).abs().max() / truth.abs().max()) < 1e-4


def test_black_and_saturated_strokes(box):
    R = _renderer(box)
    mask = object_mask(R.tensors, "back")
    res = fit_image(R, "back", torch.zeros(24, 24, 3, dtype=torch.float64), weights=mask)
    _feasible(R, res)
    assert float(res.coefficients["back"].abs().max()) < 1e-10  # black wall: the zero curve
    # saturated / unreachable: the brightest feasible wall, albedo bound active, finite
    res = fit_image(R, "back", torch.full((24, 24, 3), 1e3, dtype=torch.float64), weights=mask)
    _feasible(R, res)
    assert bool(((res.albedo["back"] - 1).abs() < 1e-8).all())
    assert res.kkt_residual < 1e-6


def test_unreachable_colour_is_best_feasible(box):
    """A target no material reaches (pixels of one object asked to be both bright and black):
    the fit stops at a KKT point of the constrained problem, no NaN."""
    R = _renderer(box)
    mask = object_mask(R.tensors, "back")
    target = torch.zeros(24, 24, 3, dtype=torch.float64)
    target[:, :12] = 5.0
    res = fit_image(R, "back", target, weights=mask)
    _feasible(R, res)
    assert res.kkt_residual < 1e-6
    assert res.loss < res.loss_curve[0]


def test_few_painted_pixels_singular_system(box):
    R = _renderer(box)
    R.set_material("back", {"type": "blinn_phong", "kd": 0.2, "ks": 0.4, "exponent": 80.0})
    target = R().detach()
    R.set_material("back", {"type": "lambert", "albedo": 0.5})
    mask = torch.zeros(24, 24, dtype=torch.bool)
    ys, xs = object_mask(R.tensors, "back").nonzero(as_tuple=True)
    mask[ys[:2], xs[:2]] = True  # 2 pixels, 8 unknowns per channel
    res = fit_image(R, "back", target, weights=mask)
    _feasible(R, res)
    assert res.loss < 1e-12 * res.loss_curve[0]


def test_gi_fit_beats_direct_only_fit_on_ggx_target(box):
    _, T, _ = box
    ggx = cornell_box_glossy(24)
    ggx.materials["glossy_back"] = {
        "type": "cook_torrance",
        "distribution": "ggx",
        "roughness": 0.2,
        "f0": 0.5,
        "kd": 0.25,
    }
    target = reference_path_trace(ggx, spp=16, max_bounces=4, seed=1, progress=False).double()
    mask = object_mask(T, "back")
    gi = _renderer(box)
    res_gi = fit_image(gi, "back", target, weights=mask)
    direct = _renderer(box, max_bounces=1)
    res_d = fit_image(direct, "back", target, weights=mask)
    _feasible(gi, res_gi)
    gi.set_coefficients("back", res_d.coefficients["back"])
    keep = emitter_mask(T)
    err_direct = relative_rmse(gi(), target, keep)
    gi.set_coefficients("back", res_gi.coefficients["back"])
    err_gi = relative_rmse(gi(), target, keep)
    assert err_gi < err_direct


def test_cli_fit_image(tmp_path):
    import json

    from typer.testing import CliRunner

    from torch_brdf.cli import app
    from torch_brdf.io import load_arrays, write_exr

    sc = cornell_box_glossy(16)
    T = precompute_polynomial(sc, "4,1", spp=2, seed=0, progress=False)
    mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
    R = PolynomialRenderer(T, mats, dtype=torch.float64)
    R.set_material("back", {"type": "blinn_phong", "kd": 0.1, "ks": 0.3, "exponent": 60.0})
    truth = R.c[T.object_id("back")].clone()
    write_exr(tmp_path / "target.exr", R().detach().float())
    T.save(tmp_path / "cb.npz")
    args = ["fit-image", str(tmp_path / "cb.npz"), "--target", str(tmp_path / "target.exr"), "--object", "back"]
    r = CliRunner().invoke(app, args + ["--out", str(tmp_path / "fit")])
    assert r.exit_code == 0, r.output
    report = json.loads(r.output.strip().splitlines()[-1])
    assert report["violation"] <= 1e-8
    arrays, _ = load_arrays(tmp_path / "fit" / "fit.npz", "gi-image-fit")
    c = torch.as_tensor(arrays["c_back"])
    # the target went through float32 EXR: recovered to that precision
    assert float((c - truth).abs().max() / truth.abs().max()) < 1e-3
    assert (tmp_path / "fit" / "render.exr").is_file()


def test_library_brdf_parameters_recovered(box):
    """Blinn-Phong kd, ks (linear in the curve) fitted directly: in-family target recovered."""
    from torch_brdf.render import blinn_phong_family

    R = _renderer(box)
    fam = blinn_phong_family(R, "back", 50.0)
    R.set_material("back", {"type": "blinn_phong", "kd": (0.3, 0.2, 0.1), "ks": 0.5, "exponent": 50.0})
    target = R().detach()
    R.set_material("back", {"type": "lambert", "albedo": 0.5})
    res = fit_image(R, "back", target, weights=object_mask(R.tensors, "back"), families={"back": fam})
    _feasible(R, res)
    truth = torch.tensor([[0.3, 0.2, 0.1], [0.5, 0.5, 0.5]], dtype=torch.float64)
    assert float((res.parameters["back"] - truth).abs().max() / truth.abs().max()) < 1e-4
